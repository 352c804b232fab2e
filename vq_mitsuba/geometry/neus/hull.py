"""The visual hull: voxels that every view holding them sees as foreground, the cube around it, and
its smoothed signed distance (the SDF's starting point)."""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F

from vq_mitsuba.config import NeuSConfig
from vq_mitsuba.errors import InputError
from vq_mitsuba.geometry.neus.framing import _look_center


def carve(cameras, masks: torch.Tensor, lo, hi, res: int, min_views: float,
          candidates: torch.Tensor | None = None) -> torch.Tensor:
    """Visual hull on a res^3 grid of cell centres in the box [lo, hi]: (res, res, res) bool.

    A cell is kept when no view whose frustum holds it sees it as background, and at least
    `min_views` of the views hold it (so space seen by no camera does not count as object).
    """
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    device = masks.device  # the masks' device carves
    axes = [torch.tensor(lo[i] + (np.arange(res) + 0.5) / res * (hi[i] - lo[i]), dtype=torch.float32, device=device)
            for i in range(3)]
    pts = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    # cells no view has carved so far (optionally only the given candidate cells)
    alive = torch.arange(len(pts), device=device) if candidates is None else candidates.reshape(-1).nonzero()[:, 0]
    seen = torch.zeros(len(pts), dtype=torch.int32, device=device)
    for cam, mask in zip(cameras, masks):
        inv = torch.tensor(np.linalg.inv(cam.to_world), dtype=torch.float32, device=device)
        local = pts[alive] @ inv[:3, :3].T + inv[:3, 3]
        z = local[:, 2]
        fx, fy, cx, cy = cam.intrinsics()
        zc = z.clamp(min=1e-9)
        x = cx - fx * local[:, 0] / zc  # as Camera.project
        y = cy - fy * local[:, 1] / zc
        inside = (z > 1e-6) & (x >= 0) & (x < cam.width) & (y >= 0) & (y < cam.height)
        fg = mask[y.clamp(0, cam.height - 1).long(), x.clamp(0, cam.width - 1).long()]
        seen[alive] += inside.int()
        alive = alive[~inside | fg]
    keep = torch.zeros(len(pts), dtype=torch.bool, device=device)
    keep[alive] = True
    keep &= seen >= max(1, int(math.ceil(min_views * len(cameras))))
    return keep.reshape(res, res, res)


def hull_box(cameras, masks: torch.Tensor, cfg: NeuSConfig, source) -> tuple[np.ndarray, float, torch.Tensor]:
    """(centre, half-size, hull grid) of the cube around the visual hull, found in two passes."""
    center = _look_center(cameras)
    dist = min(float(np.linalg.norm(c.origin - center)) for c in cameras)
    half = 0.95 * dist
    coarse = 64
    occ = carve(cameras, masks, center - half, center + half, coarse, cfg.hull_min_views)
    if not occ.any():
        raise InputError(source, "the alpha masks have no common foreground: the visual hull is empty "
                                 "(check the masks and the camera poses)")
    idx = occ.nonzero().cpu().numpy()
    cell = 2 * half / coarse
    lo = center - half + (idx.min(0) - 1) * cell
    hi = center - half + (idx.max(0) + 2) * cell
    c = 0.5 * (lo + hi)
    h = 0.5 * float(np.max(hi - lo)) * 1.1
    # Coarse hull in the final box, dilated, bounds the candidates of the full-resolution pass.
    res = cfg.hull_resolution
    occ = carve(cameras, masks, c - h, c + h, max(res // 2, 2), cfg.hull_min_views)
    occ = F.max_pool3d(occ.float()[None, None], 3, stride=1, padding=1)[0, 0] > 0.5
    cand = F.interpolate(occ.float()[None, None], size=(res, res, res), mode="nearest")[0, 0] > 0.5
    occ = carve(cameras, masks, c - h, c + h, res, cfg.hull_min_views, candidates=cand)
    if not occ.any():
        raise InputError(source, "the visual hull vanished at full resolution (masks too thin?)")
    return c, h, occ


def hull_sdf(occ: torch.Tensor) -> torch.Tensor:
    """Smoothed signed distance (negative inside) to a boolean grid's surface, in [-1, 1]^3 box units
    (a CPU tensor)."""
    from scipy import ndimage

    o = occ.cpu().numpy()
    res = o.shape[0]
    inside = ndimage.distance_transform_edt(o)
    outside = ndimage.distance_transform_edt(~o)
    sdf = np.where(o, -(inside - 0.5), outside - 0.5) * (2.0 / res)
    sdf = ndimage.gaussian_filter(sdf, 1.0)
    return torch.tensor(sdf, dtype=torch.float32, device="cpu")  # scipy's, on the CPU
