"""NeuS on a CPU: geometry (an SDF) and appearance from posed images with alpha masks.

Model (NeuS, Wang et al. 2021; VQ-NeRF supplement Eq. 1-2): an SDF network f and a colour network
c; along a ray, section i between samples has opacity
    alpha_i = max((Phi_s(f_i - cos * d_i / 2) - Phi_s(f_i + cos * d_i / 2)) / Phi_s(f_i - cos * d_i / 2), 0)
with Phi_s the logistic sigmoid of learned sharpness s, and the pixel colour is the
alpha-composited c. Losses: L1 colour, eikonal (|grad f| = 1), BCE between accumulated opacity
and the alpha mask.

What makes it fast enough for two CPU cores:
- the SDF network is a tiny MLP fed by a multi-resolution *dense* feature grid (plain torch
  trilinear interpolation), with finer levels faded in coarse-to-fine; its SDF gradient is
  computed in closed form, so the eikonal loss back-propagates without a second derivative;
- the masks give a visual hull; the object lives in the hull's bounding box (normalised to
  [-1, 1]^3), the SDF starts as the hull's smoothed signed distance (or a sphere), and samples are
  only placed where the ray crosses the occupancy grid: from its entry into the (dilated) hull to
  just past the first cell the current SDF marks as deep inside (refreshed during training);
- every ray batch is drawn from the foreground-dilated pixels of all views.

Without masks (`neus.background`: model, or auto on a capture without alpha or masks), as NeuS
trains DTU "w/o mask": the object lives in a bounding sphere framed from the cameras (and the
sparse points of a COLMAP model, or an IDR capture's scale_mat_0), which is the normalised box's
unit sphere and takes the hull's place (occupancy, SDF crop); the SDF starts as a sphere; rays come
from every pixel; behind the foreground each ray composites a NeRF++ background (density and colour
of points outside the sphere from their inverted-sphere coordinates (x/r, 1/r) and the view
direction); the colour loss is on every pixel and there is no mask loss. The exported mesh keeps
the largest piece inside the sphere, without a supporting plane (`support_plane`).
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from vq_mitsuba.data.cameras import camera_rays
from vq_mitsuba.errors import InputError
from vq_mitsuba.geometry import grid_kernel
from vq_mitsuba.config import NeuSConfig
from vq_mitsuba.run.loop import Budget, Loop, Progress
from vq_mitsuba.run.run_dir import RunDir, save_torch
from vq_mitsuba.config import check as validate


BACKGROUND_SAMPLES = 16  # samples per ray of the background model (without masks)
INIT_RADIUS, INIT_RADIUS_WITHOUT_MASKS = 0.6, 0.3  # the sphere initialisation when neus.init_radius is 0



class _threads:
    """Use n torch CPU threads inside the block (n <= 0: unchanged), then restore the previous count.
    On cores shared with other work one thread can be faster than several (`neus.threads` 1)."""

    def __init__(self, n: int):
        self.n = n

    def __enter__(self):
        self.old = torch.get_num_threads()
        if self.n > 0:
            torch.set_num_threads(self.n)

    def __exit__(self, *exc):
        torch.set_num_threads(self.old)
        return False


# --------------------------------------------------------------------------------------------
# Cameras, rays and the visual hull


def _look_center(cameras) -> np.ndarray:
    """Least-squares point closest to all optical axes (where the cameras look)."""
    a, b = np.zeros((3, 3)), np.zeros(3)
    for cam in cameras:
        d = cam.to_world[:3, 2] / np.linalg.norm(cam.to_world[:3, 2])
        p = np.eye(3) - np.outer(d, d)
        a += p
        b += p @ cam.origin
    if np.linalg.cond(a) > 1e8:
        return np.mean([c.origin for c in cameras], 0)
    return np.linalg.solve(a, b)


def _frame_margins(cam, points: np.ndarray) -> np.ndarray:
    """Distance (world units) of each point (N, 3) from the nearest side plane of the camera's
    frustum: positive inside the frustum, negative outside (or behind the camera)."""
    inv = np.linalg.inv(cam.to_world)
    local = points @ inv[:3, :3].T + inv[:3, 3]
    fx, fy, cx, cy = cam.intrinsics()
    # Inward normals of the four side planes (camera space: +X left, +Y up, +Z forward; as camera_rays).
    normals = np.array([[-1.0, 0.0, cx / fx], [1.0, 0.0, (cam.width - cx) / fx],
                        [0.0, -1.0, cy / fy], [0.0, 1.0, (cam.height - cy) / fy]])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    margin = (local @ normals.T).min(1)
    return np.where(local[:, 2] > 0, margin, -np.abs(margin) - 1e-9)


def uses_background_model(capture, cfg: NeuSConfig) -> bool:
    """Whether NeuS trains without masks (a bounding sphere and a background model): with
    `neus.background` model, or auto on a capture without alpha or masks (a `capture.background_color`
    key makes masks, so a keyed capture has them)."""
    return cfg.background == "model" or (cfg.background == "auto" and not capture.has_alpha)


def well_seen(points: np.ndarray, track: np.ndarray | None = None) -> np.ndarray:
    """Sparse points (N, 3) as float64, without those seen by fewer than 3 images when their track
    lengths are known (a track per point, not all 0)."""
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    if track is not None and len(track) == len(pts) and np.max(track, initial=0) > 0:
        pts = pts[np.asarray(track) >= 3]
    return pts


def support_from_points(points: np.ndarray, cameras, sphere: tuple, track: np.ndarray | None = None,
                        min_share: float = 0.2, max_below: float = 0.05,
                        seed: int = 0) -> tuple[np.ndarray, float] | None:
    """A supporting plane (a table) among sparse points: (unit normal towards the cameras, offset c;
    the plane is n.x = c) in the world, or None.

    RANSAC (400 planes through three points) over the points within 1.5 radii of the sphere's centre
    (those seen by 3 or more images, when tracks are known); a plane's inliers lie within 2% of the
    radius of it. The plane with the most inliers among those that nine in ten cameras look down on
    and that have at most max_below of the points beneath them (the cameras cannot see under a
    table; they do see the sides of a wide object under its flat top) counts as a support when it
    holds at least min_share of the points, crosses the sphere, and its inliers run out to the
    sphere (95th-percentile distance from the centre at least 0.9 radii: a table goes on beyond the
    object, a flat top of a small object stops short)."""
    from vq_mitsuba.geometry.mesh import share_beneath

    center, radius = np.asarray(sphere[0], np.float64), float(sphere[1])
    pts = well_seen(points, track)
    pts = pts[np.linalg.norm(pts - center, axis=1) < 1.5 * radius]
    if len(pts) < 20:
        return None
    rng = np.random.default_rng(seed)
    if len(pts) > 20000:
        pts = pts[rng.choice(len(pts), 20000, replace=False)]
    views = np.array([c.origin for c in cameras])
    tol = 0.02 * radius
    best, best_count = None, 0
    for _ in range(400):
        a, b, c = pts[rng.choice(len(pts), 3, replace=False)]
        n = np.cross(b - a, c - a)
        if np.linalg.norm(n) < 1e-12:
            continue
        n /= np.linalg.norm(n)
        off = float(n @ a)
        side = np.sign(views @ n - off)
        if max(np.mean(side > 0), np.mean(side < 0)) < 0.9:
            continue
        if share_beneath(pts, n, off, views, tol) > max_below:
            continue
        count = int(np.sum(np.abs(pts @ n - off) < tol))
        if count > best_count:
            best, best_count = (n, off), count
    if best is None or best_count < min_share * len(pts):
        return None
    n, off = best
    inliers = pts[np.abs(pts @ n - off) < tol]
    mean = inliers.mean(0)
    n_fit = np.linalg.eigh(np.cov((inliers - mean).T))[1][:, 0]  # least-squares refit
    n = n_fit if n_fit @ n >= 0 else -n_fit
    off = float(n @ mean)
    if np.mean(views @ n - off > 0) < 0.5:
        n, off = -n, -off
    reach = float(np.percentile(np.linalg.norm(inliers - center, axis=1), 95))
    if (abs(float(n @ center) - off) >= 0.9 * radius or reach < 0.9 * radius
            or share_beneath(pts, n, off, views, tol) > max_below):
        return None
    return n, off


def bounding_sphere(cameras, points: np.ndarray | None = None, track: np.ndarray | None = None,
                    min_views: float = 0.75, point_views: float = 0.3) -> tuple[np.ndarray, float, str]:
    """(centre, radius, what framed it) of the sphere the object is taken to live in, without masks.

    From the cameras: centred on the point closest to all optical axes, the largest sphere there
    that at least `min_views` of the views frame whole (the region the cameras all look at).
    With sparse points (N, 3) (and their track lengths: points seen by fewer than 3 images are
    left out when tracks are known): the points inside the frusta of at least `point_views` of the
    views, when there are 20 or more, give the sphere instead: centred between their 2nd and 98th
    percentiles per axis, radius 1.1 x their 95th-percentile distance from it, at most twice the
    cameras' sphere (stray points far off are background). `point_views` is lower than
    `min_views` because close-ups crop the object: asking 3 in 4 views to frame a point leaves out
    the ends of an object wider than most frames (as the visual hull's `neus.hull_min_views`)."""
    center = _look_center(cameras)
    need = max(1, int(math.ceil(min_views * len(cameras))))
    margins = np.array([_frame_margins(cam, center[None])[0] for cam in cameras])
    # the need-th largest margin: the sphere that `need` views frame whole
    r_cam = float(np.sort(margins)[::-1][need - 1])
    if r_cam <= 0:  # the look centre is outside too many views: frame what most views hold
        r_cam = 0.5 * min(float(np.linalg.norm(c.origin - center)) for c in cameras)
    source = "cameras"
    if points is not None and len(points):
        pts = well_seen(points, track)
        if len(pts):
            seen = np.sum([_frame_margins(cam, pts) > 0 for cam in cameras], 0)
            pts = pts[seen >= max(1, int(math.ceil(point_views * len(cameras))))]
        if len(pts) >= 20:
            lo, hi = np.percentile(pts, 2, axis=0), np.percentile(pts, 98, axis=0)
            c = 0.5 * (lo + hi)
            r = 1.1 * float(np.percentile(np.linalg.norm(pts - c, axis=1), 95))
            if r > 0:
                return c, min(r, 2.0 * r_cam), "sparse points"
    return center, r_cam, source


# The feature grid, when neus.levels / neus.max_res are 0 (auto). With masks: 5 levels to 128 points
# a side while the working box spans at most FINE_GRID_FROM_PX pixels in the median view (the 200 px
# synthetic captures: on tabletop better normals and materials than 4 levels to 64, in less time than
# that grid took before the closed-form gradient; benchmarks/results/tabletop_stages/), else finer
# levels up to 512 (photographed captures; benchmarks/results/neus_dtu/); levels beyond
# 2^neus.hash_log2 points are hashed. Without masks the coarse grid stays: the background model
# shares the steps, and the fine grid fitted DTU scan37's photos worse in the same time
# (benchmarks/results/dtu_photos/).
COARSE_GRID = (4, 64)  # (levels, max_res)
MASKED_GRID = (5, 128)
FINE_GRID = (8, 512)
FINE_GRID_FROM_PX = 256


def box_footprint_px(cameras, center: np.ndarray, half: float) -> float:
    """The working box's width in pixels in the median view (its size over the distance to its centre)."""
    return float(np.median([2.0 * half * cam.focal_px() / max(float(np.linalg.norm(cam.origin - center)), 1e-12)
                            for cam in cameras]))


def choose_grid(cfg: NeuSConfig, cameras, center: np.ndarray, half: float,
                masks: bool = True) -> tuple[NeuSConfig, dict]:
    """The config with neus.levels and neus.max_res decided (when 0), and what decided them;
    `masks` False: NeuS trains without masks (the coarse grid whatever the size)."""
    footprint = box_footprint_px(cameras, center, half)
    fine = masks and footprint > FINE_GRID_FROM_PX
    levels, max_res = FINE_GRID if fine else MASKED_GRID if masks else COARSE_GRID
    chosen = replace(cfg, levels=cfg.levels or levels, max_res=cfg.max_res or max_res)
    if cfg.levels and cfg.max_res:
        reason = "neus.levels and neus.max_res given"
    elif not masks:
        reason = f"without masks (the box spans {footprint:.0f} px in the median view)"
    else:
        reason = (f"the box spans {footprint:.0f} px in the median view ({'over' if fine else 'at most'} "
                  f"{FINE_GRID_FROM_PX})")
    return chosen, {"levels": chosen.levels, "max_res": chosen.max_res, "hash_log2": chosen.hash_log2,
                    "box_footprint_px": footprint, "reason": reason}


def carve(cameras, masks: torch.Tensor, lo, hi, res: int, min_views: float,
          candidates: torch.Tensor | None = None) -> torch.Tensor:
    """Visual hull on a res^3 grid of cell centres in the box [lo, hi]: (res, res, res) bool.

    A cell is kept when no view whose frustum holds it sees it as background, and at least
    `min_views` of the views hold it (so space seen by no camera does not count as object).
    """
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    axes = [torch.tensor(lo[i] + (np.arange(res) + 0.5) / res * (hi[i] - lo[i]), dtype=torch.float32)
            for i in range(3)]
    pts = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    # cells no view has carved so far (optionally only the given candidate cells)
    alive = torch.arange(len(pts)) if candidates is None else candidates.reshape(-1).nonzero()[:, 0]
    seen = torch.zeros(len(pts), dtype=torch.int32)
    for cam, mask in zip(cameras, masks):
        inv = torch.tensor(np.linalg.inv(cam.to_world), dtype=torch.float32)
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
    keep = torch.zeros(len(pts), dtype=torch.bool)
    keep[alive] = True
    keep &= seen >= max(1, int(math.ceil(min_views * len(cameras))))
    return keep.reshape(res, res, res)


def _hull_box(cameras, masks: torch.Tensor, cfg: NeuSConfig, source) -> tuple[np.ndarray, float, torch.Tensor]:
    """(centre, half-size, hull grid) of the cube around the visual hull, found in two passes."""
    center = _look_center(cameras)
    dist = min(float(np.linalg.norm(c.origin - center)) for c in cameras)
    half = 0.95 * dist
    coarse = 64
    occ = carve(cameras, masks, center - half, center + half, coarse, cfg.hull_min_views)
    if not occ.any():
        raise InputError(source, "the alpha masks have no common foreground: the visual hull is empty "
                                 "(check the masks and the camera poses)")
    idx = occ.nonzero().numpy()
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
    """Smoothed signed distance (negative inside) to a boolean grid's surface, in [-1, 1]^3 box units."""
    from scipy import ndimage

    o = occ.numpy()
    res = o.shape[0]
    inside = ndimage.distance_transform_edt(o)
    outside = ndimage.distance_transform_edt(~o)
    sdf = np.where(o, -(inside - 0.5), outside - 0.5) * (2.0 / res)
    sdf = ndimage.gaussian_filter(sdf, 1.0)
    return torch.tensor(sdf, dtype=torch.float32)


# --------------------------------------------------------------------------------------------
# Networks


def corner_weights(f: torch.Tensor, du_dp: torch.Tensor | None = None) -> torch.Tensor:
    """Trilinear weights of a cell's 8 corners (ordered dx, dy, dz, dz fastest) from the fractions
    f (..., 3) within the cell: (..., 8, 1); given du/dp (..., 3), the cell units per box unit (0 on
    an axis where the lookup is clamped to the grid), also their gradients in the point:
    (..., 8, 4), [..., 0] the weight and [..., 1:] its gradient."""
    w = torch.stack([1.0 - f, f], -1)  # (..., 3, 2): per axis, the weight of the lower / upper corner

    def outer(a, b, c):
        return (a[..., :, None, None] * b[..., None, :, None] * c[..., None, None, :]).flatten(-3)

    wx, wy, wz = w.unbind(-2)
    if du_dp is None:
        return outer(wx, wy, wz)[..., None]
    dw = torch.stack([-du_dp, du_dp], -1)
    return torch.stack([outer(wx, wy, wz), outer(dw[..., 0, :], wy, wz), outer(wx, dw[..., 1, :], wz),
                        outer(wx, wy, dw[..., 2, :])], -1)


def _cell(p: torch.Tensor, res: torch.Tensor | float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """For a grid of `res` points per axis at the cell centres of [-1, 1]^3: each point's lower
    corner (long), its fractions in the cell (differentiable in p) and du/dp (0 where it is clamped
    to the grid)."""
    x = (p + 1.0) * (0.5 * res) - 0.5
    if not torch.is_tensor(res):
        res = torch.tensor(res, dtype=p.dtype)
    u = torch.minimum(x.clamp(min=0.0), res - 1.0)
    i0 = torch.minimum(u.floor(), res - 2.0)
    du_dp = ((x > 0.0) & (x < res - 1.0)).to(p.dtype) * (0.5 * res)
    return i0.long(), u - i0, du_dp


def trilinear(grid: torch.Tensor, res: int, p: torch.Tensor, gradient: bool = False):
    """Trilinear lookup of a (res^3, C) grid of values at cell centres of [-1, 1]^3, at points (N, 3),
    and with `gradient` also its gradient in the points (N, C, 3)."""
    i0, f, du_dp = _cell(p, float(res))
    base = (i0[:, 0] * res + i0[:, 1]) * res + i0[:, 2]
    offs = torch.tensor([dx * res * res + dy * res + dz for dx in (0, 1) for dy in (0, 1) for dz in (0, 1)],
                        device=p.device)
    vals = grid.index_select(0, (base[:, None] + offs).reshape(-1)).view(len(p), 8, -1)
    w = corner_weights(f, du_dp if gradient else None)
    out = (vals[..., None] * w[:, :, None, :]).sum(1)  # (N, C, 1 or 4)
    return (out[..., 0], out[..., 1:]) if gradient else out[..., 0]


# Instant-NGP's spatial hash: each integer coordinate times its own large prime, XOR-ed.
HASH_PRIMES = (1, 2654435761, 805459861)


class DenseGrid(nn.Module):
    """Multi-resolution feature grids (resolutions geometric from base_res to max_res), all levels
    stored in one table and looked up with one gather (few, large tensor ops: fast on a CPU). A
    level with more than 2^hash_log2 points keeps 2^hash_log2 entries, indexed by a spatial hash of
    the point (Instant-NGP); coarser levels are dense."""

    def __init__(self, levels: int, base_res: int, max_res: int, features: int, hash_log2: int = 0):
        super().__init__()
        growth = (max_res / base_res) ** (1.0 / max(levels - 1, 1))
        self.res = [int(round(base_res * growth ** level)) for level in range(levels)]
        self.features = features
        cap = 2 ** hash_log2 if hash_log2 > 0 else None
        hashed = [cap is not None and r ** 3 > cap for r in self.res]
        sizes = [cap if h else r ** 3 for r, h in zip(self.res, hashed)]
        offsets = np.cumsum([0] + sizes)
        self.table = nn.Parameter(torch.empty(int(offsets[-1]), features).uniform_(-1e-4, 1e-4))
        r = torch.tensor(self.res, dtype=torch.long)
        self.register_buffer("res_l", r, persistent=False)
        self.register_buffer("offsets", torch.tensor(offsets[:-1], dtype=torch.long), persistent=False)
        corners = torch.tensor([[dx, dy, dz] for dx in (0, 1) for dy in (0, 1) for dz in (0, 1)])
        self.register_buffer("corners", corners, persistent=False)
        self.register_buffer("corner_offs", (corners[None, :, 0] * r[:, None] ** 2 + corners[None, :, 1] * r[:, None]
                                             + corners[None, :, 2]), persistent=False)  # (L, 8)
        self.hashed = hashed
        self.register_buffer("hashed_l", torch.tensor(hashed), persistent=False)
        self.hash_mask = (cap or 1) - 1
        self.layout = grid_kernel.Layout(self.res, [int(o) for o in offsets[:-1]], hashed, self.hash_mask)

    def _indices(self, i0: torch.Tensor) -> torch.Tensor:
        """Table rows (N, L, 8) of the 8 corners of each point's cell at each level."""
        r = self.res_l[None, :]
        dense = ((i0[..., 0] * r + i0[..., 1]) * r + i0[..., 2])[..., None] + self.corner_offs[None]
        if any(self.hashed):
            c = i0[:, :, None, :] + self.corners[None, None]  # (N, L, 8, 3)
            h = (c[..., 0] * HASH_PRIMES[0]) ^ (c[..., 1] * HASH_PRIMES[1]) ^ (c[..., 2] * HASH_PRIMES[2])
            dense = torch.where(self.hashed_l[None, :, None], h & self.hash_mask, dense)
        return self.offsets[None, :, None] + dense

    def forward(self, p: torch.Tensor, level_weights: list[float], jacobian: bool = False):
        """Features (N, L * F) at points (N, 3), each level scaled by its weight; with `jacobian`
        also their derivatives in the points (N, L * F, 3), computed in closed form: the points
        are data, so the features and the Jacobian are both linear in the table and the eikonal
        loss needs no second derivative through the lookup. On the CPU the compiled kernel does it
        (`grid_kernel`), elsewhere `forward_torch`."""
        if grid_kernel.usable(self.table, p, self.features):
            return grid_kernel.lookup(self.table, p, self.layout, torch.tensor(level_weights), jacobian)
        return self.forward_torch(p, level_weights, jacobian)

    def forward_torch(self, p: torch.Tensor, level_weights: list[float], jacobian: bool = False):
        """`forward` in torch operations (any device and dtype, differentiable in the points)."""
        n, levels = len(p), len(self.res)
        res = self.res_l.to(p.dtype)[None, :, None]  # (1, L, 1)
        i0, f, du_dp = _cell(p[:, None, :], res)  # (N, L, 3)
        vals = self.table.index_select(0, self._indices(i0).reshape(-1)).view(n, levels, 8, self.features)
        w = corner_weights(f, du_dp if jacobian else None)  # (N, L, 8, 4 or 1)
        lw = torch.tensor(level_weights, dtype=p.dtype, device=p.device).view(1, levels, 1, 1)
        k = w.shape[-1]
        out = torch.bmm(vals.view(n * levels, 8, self.features).transpose(1, 2),
                        (w * lw).view(n * levels, 8, k)).view(n, levels, self.features, k)
        feats = out[..., 0].reshape(n, levels * self.features)
        return (feats, out[..., 1:].reshape(n, levels * self.features, 3)) if jacobian else feats


class SDFNetwork(nn.Module):
    """SDF = base(x) + MLP(x, grid(x))[0]; the other outputs are features for the colour network."""

    def __init__(self, cfg: NeuSConfig, base_grid: torch.Tensor | None, init_radius: float = 0.6):
        super().__init__()
        self.encoding = DenseGrid(cfg.levels, cfg.base_res, cfg.max_res, cfg.features, cfg.hash_log2)
        d_in = 3 + cfg.levels * cfg.features
        self.l1 = nn.Linear(d_in, cfg.hidden)
        self.l2 = nn.Linear(cfg.hidden, cfg.hidden)
        self.out = nn.Linear(cfg.hidden, 1 + cfg.geo_features)
        nn.init.normal_(self.out.weight, 0.0, 1e-4)
        nn.init.zeros_(self.out.bias)
        self.act = nn.Softplus(beta=100)
        self.init_radius = init_radius
        if base_grid is not None:
            self.register_buffer("base_grid", base_grid.reshape(-1, 1).contiguous())
            self.base_res = int(round(base_grid.numel() ** (1 / 3)))
            self.base_layout = grid_kernel.Layout([self.base_res], [0], [False], 0)
        else:
            self.base_grid = None

    def base(self, p: torch.Tensor, gradient: bool = False):
        """The initial SDF (the hull's smoothed distance or a sphere), with `gradient` also its
        gradient in the points."""
        if self.base_grid is None:
            r = p.norm(dim=-1)
            return (r - self.init_radius, p / r.clamp(min=1e-12)[:, None]) if gradient else r - self.init_radius
        if grid_kernel.usable(self.base_grid, p, 1):
            out = grid_kernel.lookup(self.base_grid, p, self.base_layout, torch.ones(1), gradient)
            return (out[0][:, 0], out[1][:, 0]) if gradient else out[:, 0]
        if not gradient:
            return trilinear(self.base_grid, self.base_res, p)[:, 0]
        value, grad = trilinear(self.base_grid, self.base_res, p, gradient=True)
        return value[:, 0], grad[:, 0]

    def forward(self, p: torch.Tensor, level_weights: list[float]) -> tuple[torch.Tensor, torch.Tensor]:
        h = torch.cat([p, self.encoding(p, level_weights)], -1)
        h = self.act(self.l1(h))
        h = self.act(self.l2(h))
        o = self.out(h)
        return self.base(p) + o[:, 0], o[:, 1:]

    def forward_with_gradient(self, p: torch.Tensor, level_weights: list[float]):
        """(SDF, features, SDF gradient in p) at data points p, the gradient in closed form (the
        MLP's chain rule and the grid's Jacobian) as a graph in the parameters: its eikonal loss
        back-propagates with first derivatives only, faster than autograd's double backward and the
        same to rounding (tests/test_geometry.py)."""
        enc, jac = self.encoding(p, level_weights, jacobian=True)
        a1 = self.l1(torch.cat([p, enc], -1))
        a2 = self.l2(self.act(a1))
        o = self.out(self.act(a2))
        beta = self.act.beta  # softplus(beta x)' = sigmoid(beta x), 1 to rounding past its threshold
        g = (self.out.weight[0] * torch.sigmoid(beta * a2)) @ self.l2.weight
        g = (g * torch.sigmoid(beta * a1)) @ self.l1.weight  # d sdf / d (p, features)
        base, base_grad = self.base(p, gradient=True)
        grad = g[:, :3] + torch.bmm(g[:, None, 3:], jac)[:, 0] + base_grad
        return base + o[:, 0], o[:, 1:], grad


class ColorNetwork(nn.Module):
    """Radiance from SDF features, normal and view direction (with a small frequency encoding).
    With cfg.reflect the direction encoded is the view direction reflected about the normal, and
    the cosine between the two is one more input."""

    def __init__(self, cfg: NeuSConfig, view_freqs: int = 3):
        super().__init__()
        self.view_freqs = view_freqs
        self.reflect = cfg.reflect
        d_in = cfg.geo_features + 3 + 3 + 6 * view_freqs + (1 if cfg.reflect else 0)
        self.net = nn.Sequential(nn.Linear(d_in, cfg.hidden), nn.ReLU(), nn.Linear(cfg.hidden, cfg.hidden),
                                 nn.ReLU(), nn.Linear(cfg.hidden, 3))

    def forward(self, feat, normal, view):
        extra = []
        if self.reflect:
            cos = (view * normal).sum(-1, keepdim=True)
            view = view - 2.0 * cos * normal
            extra = [cos]
        enc = extra + [view]
        for k in range(self.view_freqs):
            enc += [torch.sin((2.0 ** k) * math.pi * view), torch.cos((2.0 ** k) * math.pi * view)]
        return torch.sigmoid(self.net(torch.cat([feat, normal] + enc, -1)))


def frequency_encoding(x: torch.Tensor, freqs: int) -> torch.Tensor:
    """x and sin / cos of 2^k pi x for k < freqs."""
    enc = [x]
    for k in range(freqs):
        enc += [torch.sin((2.0 ** k) * math.pi * x), torch.cos((2.0 ** k) * math.pi * x)]
    return torch.cat(enc, -1)


class BackgroundNetwork(nn.Module):
    """NeRF++'s model of what lies outside the unit sphere: density and colour of a point from its
    inverted-sphere coordinates (x / r, 1 / r) and the view direction, each frequency-encoded."""

    POINT_FREQS, VIEW_FREQS = 6, 3

    def __init__(self, hidden: int):
        super().__init__()
        self.trunk = nn.Sequential(nn.Linear(4 * (1 + 2 * self.POINT_FREQS), hidden), nn.ReLU(),
                                   nn.Linear(hidden, hidden), nn.ReLU())
        self.sigma = nn.Linear(hidden, 1)
        self.rgb = nn.Sequential(nn.Linear(hidden + 3 * (1 + 2 * self.VIEW_FREQS), hidden // 2), nn.ReLU(),
                                 nn.Linear(hidden // 2, 3))

    def forward(self, x4: torch.Tensor, view: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        h = self.trunk(frequency_encoding(x4, self.POINT_FREQS))
        rgb = torch.sigmoid(self.rgb(torch.cat([h, frequency_encoding(view, self.VIEW_FREQS)], -1)))
        return F.softplus(self.sigma(h)[:, 0] - 1.0), rgb


class NeuSModel(nn.Module):
    def __init__(self, cfg: NeuSConfig, base_grid: torch.Tensor | None, background: bool = False):
        super().__init__()
        # Without masks the sphere is the bounding sphere, larger than the object: a small start
        # leaves less surface to recede, on which the colour network would paint the backdrop.
        radius = cfg.init_radius or (INIT_RADIUS_WITHOUT_MASKS if background else INIT_RADIUS)
        self.sdf = SDFNetwork(cfg, base_grid, radius)
        self.color = ColorNetwork(cfg)
        self.variance = nn.Parameter(torch.tensor(float(cfg.init_variance)))
        self.background = BackgroundNetwork(cfg.hidden) if background else None

    def inv_s(self) -> torch.Tensor:
        return torch.exp(10.0 * self.variance).clamp(1e-6, 1e6)

    def sdf_grad(self, p: torch.Tensor, level_weights, create_graph: bool):
        """(SDF, features, gradient) at points p; the gradient is part of the graph with
        create_graph (the eikonal loss and the normals' colour), detached without."""
        sdf, feat, grad = self.sdf.forward_with_gradient(p.detach(), level_weights)
        return sdf, feat, grad if create_graph else grad.detach()


# --------------------------------------------------------------------------------------------
# The reconstruction: data, occupancy, rendering


def encode_srgb(x: torch.Tensor) -> torch.Tensor:
    x = x.clamp(0.0, 1.0)
    return torch.where(x <= 0.0031308, 12.92 * x, 1.055 * x.clamp(min=1e-8) ** (1 / 2.4) - 0.055)


class NeuS:
    """A NeuS model bound to a capture's cameras, in the normalised box around the visual hull, or
    without masks (`uses_background_model`) in the box around the bounding sphere (`sphere`:
    (centre, radius, what framed it); default `bounding_sphere` of the cameras). `support`: a
    known supporting plane without masks ((unit normal towards the cameras, offset) in the world,
    e.g. `support_from_points`): the foreground is what lies inside the sphere above it, and the
    background model takes the plane and what lies below. `points`: the capture's sparse points
    (N, 3) in the world, which the mesh export's search for a support checks its planes against."""

    def __init__(self, capture, cfg: NeuSConfig, sphere: tuple | None = None, support: tuple | None = None,
                 points: np.ndarray | None = None):
        validate(cfg)
        self.cfg = cfg
        self.points = None if points is None else np.asarray(points, np.float64).reshape(-1, 3)
        self.capture = capture
        self.source = capture.source
        self.mask_free = uses_background_model(capture, cfg)
        self.support = None  # the supporting plane the mesh export cut away (without masks)
        self.plane = None  # a known supporting plane in box units: (normal, offset)
        if len(capture.cameras) == 0:
            raise InputError(capture.source, "the capture has no images")
        if not capture.has_alpha and not self.mask_free:
            raise InputError(capture.source, "neus.background is masks, but the images have no alpha channel and "
                                             "there is no mask folder (give RGBA PNG/EXR images, masks/ for COLMAP or "
                                             "mask/ for NeuS/IDR, --background-color R,G,B for a plain backdrop, or "
                                             "leave neus.background at auto to reconstruct without masks)")
        alpha = torch.from_numpy(np.ascontiguousarray(capture.alpha))
        if not self.mask_free and float(alpha.max()) <= cfg.hull_threshold:
            raise InputError(capture.source, "the alpha masks are empty: no foreground pixel in any image")
        torch.manual_seed(cfg.seed)
        with _threads(cfg.threads):
            if self.mask_free:
                self._setup_sphere(capture, cfg, sphere or bounding_sphere(capture.cameras), support)
            else:
                self.sphere_source = None
                self._setup(capture, cfg, alpha)

    def _setup_sphere(self, capture, cfg: NeuSConfig, sphere: tuple, support: tuple | None) -> None:
        """Without masks: the bounding sphere (above a known support) is the unit sphere of the box
        and stands in for the visual hull; the SDF starts as a sphere; every pixel of every view is
        a training ray."""
        t0 = time.perf_counter()
        center, radius, self.sphere_source = sphere
        if not (np.all(np.isfinite(center)) and math.isfinite(radius) and radius > 0):
            raise InputError(capture.source, f"the bounding sphere (centre {center}, radius {radius}, from "
                                             f"{self.sphere_source}) is degenerate: check the camera poses")
        self.center, self.half = np.asarray(center, dtype=np.float64), float(radius)
        res = cfg.hull_resolution
        axis = (torch.arange(res, dtype=torch.float32) + 0.5) / res * 2.0 - 1.0
        grid = torch.stack(torch.meshgrid(axis, axis, axis, indexing="ij"), -1)
        self.hull_sdf = grid.norm(dim=-1) - 1.0
        if support is not None:
            length = float(np.linalg.norm(support[0]))
            n = np.asarray(support[0], np.float64) / length
            c = (float(support[1]) / length - float(n @ self.center)) / self.half
            if c > 0.9:
                raise InputError(capture.source, "the supporting plane passes above the bounding sphere")
            self.plane = (torch.tensor(n, dtype=torch.float32), c)
            self.hull_sdf = torch.maximum(self.hull_sdf, c - grid @ self.plane[0])
        self.hull = self.hull_sdf < 0
        from scipy import ndimage

        self.hull_dilated = torch.from_numpy(ndimage.binary_dilation(self.hull.numpy(), iterations=2))
        self.hull_seconds = time.perf_counter() - t0
        self.cfg, self.grid = choose_grid(cfg, capture.cameras, self.center, self.half, masks=False)
        self.model = NeuSModel(self.cfg, None, background=True)
        self.deep = torch.zeros_like(self.hull)
        origins, dirs = zip(*(camera_rays(c) for c in capture.cameras))
        self.rays_o = self.to_box(torch.from_numpy(np.concatenate(origins)))
        self.rays_d = torch.from_numpy(np.concatenate(dirs))
        self.rays_rgb = encode_srgb(torch.from_numpy(np.ascontiguousarray(capture.images)).reshape(-1, 3))
        self.rays_alpha = None

    def _setup(self, capture, cfg: NeuSConfig, alpha: torch.Tensor) -> None:
        masks = alpha > cfg.hull_threshold
        # Carve with masks dilated by one pixel, so the hull stays conservative at silhouettes.
        dil = F.max_pool2d(masks.float()[:, None], 3, stride=1, padding=1)[:, 0] > 0.5
        t0 = time.perf_counter()
        center, half, occ = _hull_box(capture.cameras, dil, cfg, capture.source)
        self.center, self.half = np.asarray(center, dtype=np.float64), float(half)
        self.hull = occ
        self.hull_sdf = hull_sdf(occ)
        from scipy import ndimage

        self.hull_dilated = torch.from_numpy(ndimage.binary_dilation(occ.numpy(), iterations=2))
        self.hull_seconds = time.perf_counter() - t0
        self.cfg, self.grid = choose_grid(cfg, capture.cameras, self.center, self.half)
        self.model = NeuSModel(self.cfg, self.hull_sdf if cfg.init == "hull" else None)
        self.deep = torch.zeros_like(occ)  # cells the current SDF marks as well inside the object

        # Training rays: pixels within a few pixels of the foreground, from every view.
        near_fg = F.max_pool2d(masks.float()[:, None], 7, stride=1, padding=3)[:, 0] > 0.5
        origins, dirs = zip(*(camera_rays(c) for c in capture.cameras))
        origins = torch.from_numpy(np.concatenate(origins))
        dirs = torch.from_numpy(np.concatenate(dirs))
        sel = near_fg.reshape(-1)
        self.rays_o = self.to_box(origins[sel])
        self.rays_d = dirs[sel]
        rgb = torch.from_numpy(np.ascontiguousarray(capture.images)).reshape(-1, 3)
        self.rays_rgb = encode_srgb(rgb[sel])
        self.rays_alpha = alpha.reshape(-1)[sel].clamp(0, 1)

    # ---- coordinates
    def to_box(self, x_world: torch.Tensor) -> torch.Tensor:
        return ((x_world.double() - torch.from_numpy(self.center)) / self.half).float()

    def to_world(self, p_box: np.ndarray) -> np.ndarray:
        return np.asarray(p_box, dtype=np.float64) * self.half + self.center

    # ---- schedule
    def level_weights(self, frac: float) -> list[float]:
        """Grid level weights at training progress frac in [0, 1] (coarse-to-fine fade-in)."""
        levels = self.cfg.levels
        span = self.cfg.coarse_to_fine
        if span <= 0 or levels == 1:
            return [1.0] * levels
        progress = frac / span * (levels - 1)  # level l fully on once progress >= l
        return [float(np.clip(progress - (l - 1), 0.0, 1.0)) if l > 0 else 1.0 for l in range(levels)]

    # ---- occupancy
    @torch.no_grad()
    def refresh_occupancy(self, level_weights, chunk: int = 65536) -> None:
        """Mark hull cells whose SDF is below -margin as deep inside (ray intervals end there)."""
        res = self.cfg.hull_resolution
        cells = self.hull.nonzero()
        p = (cells.float() + 0.5) / res * 2.0 - 1.0
        sdf = torch.cat([self.model.sdf(p[i:i + chunk], level_weights)[0] for i in range(0, len(p), chunk)])
        margin = 3.0 * 2.0 / res
        deep = torch.zeros(res ** 3, dtype=torch.bool)
        flat = (cells[:, 0] * res + cells[:, 1]) * res + cells[:, 2]
        deep[flat] = sdf < -margin
        self.deep = deep.reshape(res, res, res)
        self.codes = self.hull_dilated.to(torch.uint8) + (self.deep & self.hull_dilated).to(torch.uint8)
        # Each batch's ray intervals are marched when drawn: caching them for every training ray
        # costs minutes and gigabytes per refresh on a capture of many large photos.

    def _lookup(self, grid: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
        res = grid.shape[0]
        i = ((p + 1.0) * 0.5 * res).floor().long()
        ok = ((i >= 0) & (i < res)).all(-1)
        i = i.clamp(0, res - 1)
        return grid[i[..., 0], i[..., 1], i[..., 2]] & ok

    def _codes(self, p: torch.Tensor) -> torch.Tensor:
        """Occupancy code of the cell holding each point (inside the box): 0 empty, 1 hull, 2 deep inside."""
        res = self.codes.shape[0]
        i = ((p + 1.0) * (0.5 * res)).to(torch.int32).clamp_(0, res - 1)
        flat = (i[..., 0] * res + i[..., 1]) * res + i[..., 2]
        return self.codes.view(-1)[flat.long()]

    def intervals(self, o: torch.Tensor, d: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Per ray (t_near, t_far) in box units: entry into the dilated hull to just past the first
        deep-inside cell (or the hull exit); t_near == t_far for rays that miss the hull."""
        inv = 1.0 / torch.where(d.abs() < 1e-9, torch.full_like(d, 1e-9), d)
        t1, t2 = (-1.0 - o) * inv, (1.0 - o) * inv
        t_in = torch.minimum(t1, t2).amax(-1).clamp(min=0.0)
        t_out = torch.maximum(t1, t2).amin(-1)
        hit = t_out > t_in
        if not bool(hit.all()):  # march only the rays that cross the box (without masks: often half)
            near, far = t_in.clone(), t_in.clone()
            if bool(hit.any()):
                near[hit], far[hit] = self.intervals(o[hit], d[hit])
            return near, far
        k = self.cfg.march_steps
        steps = (torch.arange(k, dtype=torch.float32) + 0.5) / k
        t = t_in[:, None] + (t_out - t_in).clamp(min=0)[:, None] * steps
        pts = o[:, None] + d[:, None] * t[..., None]
        code = self._codes(pts) * hit[:, None]
        occ = code > 0
        deep = code > 1
        any_occ = occ.any(-1)
        idx = torch.arange(k).expand_as(occ)
        first = torch.where(occ, idx, k).amin(-1).clamp(max=k - 1)
        last = torch.where(occ, idx, -1).amax(-1).clamp(min=0)
        first_deep = torch.where(deep, idx, k).amin(-1)
        end = torch.where(first_deep < k, first_deep, last)
        dt = (t_out - t_in).clamp(min=0) / k
        near = t_in + first * dt - dt
        far = t_in + (end + 1) * dt + dt
        near = torch.where(any_occ, near.clamp(min=0), t_in)
        far = torch.where(any_occ, far, near)
        if self.plane is not None:  # the foreground ends where the ray meets the support
            far = torch.maximum(torch.minimum(far, self._foreground_end(o, d)), near)
        return near, far

    def _foreground_end(self, o: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
        """Where each ray leaves the foreground region (box units): the unit sphere's exit (the
        closest approach for a ray that misses it), or, sooner, a known support's plane."""
        b = (o * d).sum(-1)
        disc = b * b - ((o * o).sum(-1) - 1.0)
        t = torch.where(disc > 0, -b + disc.clamp(min=0.0).sqrt(), (-b).clamp(min=0.0))
        if self.plane is not None:
            n, c = self.plane
            nd = d @ n
            t_plane = (c - o @ n) / torch.where(nd.abs() < 1e-9, torch.full_like(nd, -1e-9), nd)
            t = torch.where((nd < 0) & (t_plane > 0) & (t_plane < t), t_plane, t)
        return t.clamp(min=1e-3)

    # ---- rendering
    def render(self, o, d, level_weights, n_samples: int, perturb: bool, create_graph: bool,
               cos_anneal: float = 1.0, near=None, far=None) -> dict:
        """Rays (box units) through the SDF: colour `rgb`, foreground opacity `acc`, the eikonal
        term and (without create_graph) depth and normal. With a background model, `rgb` is the
        foreground composited over the background and `rgb_fg` the foreground alone."""
        out = self._foreground(o, d, level_weights, n_samples, perturb, create_graph, cos_anneal, near, far)
        if self.model.background is not None:
            out["rgb_fg"] = out["rgb"]
            out["rgb"] = out["rgb"] + (1.0 - out["acc"])[:, None] * self._background(o, d, perturb)
        return out

    def _background(self, o: torch.Tensor, d: torch.Tensor, perturb: bool) -> torch.Tensor:
        """Colour behind the unit sphere along each ray (NeRF++): samples from the sphere's exit (the
        closest approach for a ray that misses it, or a known support's plane) to far away, uniform
        in inverse distance. A point inside the sphere (on the support) is encoded as (x, 1)."""
        n = BACKGROUND_SAMPLES
        t0 = self._foreground_end(o, d)
        u = torch.rand(len(o), n) if perturb else torch.full((len(o), n), 0.5)
        inv = 1.0 - (torch.arange(n, dtype=torch.float32) + u) / n * (1.0 - 1e-3)  # 1 (the exit) .. 1e-3
        t = t0[:, None] / inv  # increasing
        pts = o[:, None] + d[:, None] * t[..., None]
        r = pts.norm(dim=-1, keepdim=True).clamp(min=1.0)
        x4 = torch.cat([pts / r, 1.0 / r], -1).reshape(-1, 4)
        sigma, color = self.model.background(x4, d[:, None].expand(-1, n, 3).reshape(-1, 3))
        dists = torch.cat([t[:, 1:] - t[:, :-1], t.new_full((len(o), 1), 1e10)], 1)
        alpha = 1.0 - torch.exp(-sigma.view(-1, n) * dists)
        trans = torch.cumprod(torch.cat([alpha.new_ones(len(o), 1), 1.0 - alpha + 1e-7], 1), 1)[:, :-1]
        return ((alpha * trans)[..., None] * color.view(-1, n, 3)).sum(1)

    def _foreground(self, o, d, level_weights, n_samples: int, perturb: bool, create_graph: bool,
                    cos_anneal: float = 1.0, near=None, far=None) -> dict:
        if near is None or far is None:
            near, far = self.intervals(o, d)
        valid = far > near + 1e-6
        b = len(o)
        out = {"rgb": o.new_zeros(b, 3), "acc": o.new_zeros(b), "eikonal": o.new_zeros(()),
               "n_points": 0, "depth": o.new_zeros(b), "normal": o.new_zeros(b, 3)}
        if not bool(valid.any()):
            return out
        ov, dv, nv, fv = o[valid], d[valid], near[valid], far[valid]
        m = len(ov)
        jitter = torch.rand(m, n_samples) if perturb else torch.full((m, n_samples), 0.5)
        steps = (torch.arange(n_samples, dtype=torch.float32) + jitter) / n_samples
        z = nv[:, None] + (fv - nv)[:, None] * steps
        dists = ((fv - nv) / n_samples)[:, None].expand(m, n_samples)
        pts = (ov[:, None] + dv[:, None] * z[..., None]).reshape(-1, 3)
        sdf, feat, grad = self.model.sdf_grad(pts, level_weights, create_graph)
        sdf = sdf.view(m, n_samples)
        g = grad.view(m, n_samples, 3)
        true_cos = (dv[:, None] * g).sum(-1)
        iter_cos = -(F.relu(-true_cos * 0.5 + 0.5) * (1.0 - cos_anneal) + F.relu(-true_cos) * cos_anneal)
        inv_s = self.model.inv_s()
        prev_cdf = torch.sigmoid((sdf - iter_cos * dists * 0.5) * inv_s)
        next_cdf = torch.sigmoid((sdf + iter_cos * dists * 0.5) * inv_s)
        alpha = ((prev_cdf - next_cdf + 1e-5) / (prev_cdf + 1e-5)).clamp(0.0, 1.0)
        trans = torch.cumprod(torch.cat([alpha.new_ones(m, 1), 1.0 - alpha + 1e-7], 1), 1)[:, :-1]
        w = alpha * trans
        normal = F.normalize(g, dim=-1)
        color = self.model.color(feat, normal.reshape(-1, 3), dv[:, None].expand(m, n_samples, 3).reshape(-1, 3))
        color = color.view(m, n_samples, 3)
        rgb = torch.zeros_like(out["rgb"])
        acc = torch.zeros_like(out["acc"])
        rgb[valid] = (w[..., None] * color).sum(1)
        acc[valid] = w.sum(1)
        out["rgb"], out["acc"] = rgb, acc
        out["eikonal"] = ((grad.norm(dim=-1) - 1.0) ** 2).mean()
        out["n_points"] = m * n_samples
        if not create_graph:
            depth = torch.zeros_like(out["depth"])
            depth[valid] = (w * z).sum(1)
            nrm = torch.zeros_like(out["normal"])
            nrm[valid] = (w[..., None] * normal).sum(1)
            out["depth"], out["normal"] = depth, nrm
        return out

    @torch.no_grad()
    def render_camera(self, cam, chunk: int = 4096) -> tuple[np.ndarray, np.ndarray]:
        """(sRGB colour (H, W, 3) on black, opacity (H, W)) of a camera, for novel-view PSNR."""
        o, d = camera_rays(cam)
        o = self.to_box(torch.from_numpy(o))
        d = torch.from_numpy(d)
        lw = [1.0] * self.cfg.levels
        rgb, acc = [], []
        for i in range(0, len(o), chunk):
            r = self.render(o[i:i + chunk], d[i:i + chunk], lw, self.cfg.n_samples, False, False)
            rgb.append(r.get("rgb_fg", r["rgb"]).detach())
            acc.append(r["acc"].detach())
        return (torch.cat(rgb).reshape(cam.height, cam.width, 3).numpy(),
                torch.cat(acc).reshape(cam.height, cam.width).numpy())

    # ---- mesh
    @torch.no_grad()
    def sdf_volume(self, res: int, chunk: int = 131072) -> np.ndarray:
        """SDF on a res^3 grid spanning [-1, 1]^3 (box units), limited to the visual hull."""
        axis = torch.linspace(-1.0, 1.0, res)
        hull_res = self.cfg.hull_resolution
        lw = [1.0] * self.cfg.levels
        vol = torch.empty(res, res, res)
        # Outside the (dilated) hull the SDF is the hull's own distance; inside, the network's,
        # never below the hull distance minus a tolerance (the visual-hull constraint).
        tol = 2.0 * 2.0 / hull_res
        for i in range(res):
            p = torch.stack(torch.meshgrid(axis[i:i + 1], axis, axis, indexing="ij"), -1).reshape(-1, 3)
            hs = trilinear(self.hull_sdf.reshape(-1, 1), hull_res, p)[:, 0]
            inside = self._lookup(self.hull_dilated, p)
            s = hs.clone()
            if bool(inside.any()):
                q = p[inside]
                s[inside] = torch.cat([self.model.sdf(q[j:j + chunk], lw)[0] for j in range(0, len(q), chunk)])
                s = torch.maximum(s, hs - tol)
            vol[i] = s.view(res, res)
        return vol.numpy()

    def _without_support(self, vol: np.ndarray, mesh):
        """The mesh (box units) cut above a supporting plane, the known one or the one the mesh
        shows (`support_plane`): the volume below the plane plus two grid cells is made empty and
        the surface extracted again. Sets self.support to the plane in world units ({normal,
        point, from}) or None."""
        from vq_mitsuba.geometry.mesh import marching_cubes, support_plane

        res = vol.shape[0]
        cell = 2.0 / (res - 1)
        if self.plane is not None:
            plane = (self.plane[0].numpy().astype(np.float64), self.plane[1])
        else:
            views = self.to_box(torch.tensor(np.array([c.origin for c in self.capture.cameras]))).numpy()
            points = None if self.points is None else self.to_box(torch.from_numpy(self.points)).numpy()
            plane = support_plane(mesh, views, radius=1.0, tol=1.5 * cell, seed=self.cfg.seed, points=points)
        if plane is None:
            return mesh
        n, c = plane
        axis = np.linspace(-1.0, 1.0, res)
        x, y, z = np.meshgrid(axis, axis, axis, indexing="ij")
        above = (c + 2.0 * cell) - (n[0] * x + n[1] * y + n[2] * z)  # positive (empty) below the cut
        try:
            cut = marching_cubes(np.maximum(vol, above.astype(np.float32)), (-1.0, -1.0, -1.0), (1.0, 1.0, 1.0))
        except ValueError:  # nothing stands on the plane: keep the surface as it is
            return mesh
        self.support = {"normal": [float(v) for v in n], "point": self.to_world(n * c).tolist(),
                        "from": "sparse points" if self.plane is not None else "mesh"}
        return cut

    def extract_mesh(self, res: int | None = None, clean: bool = True):
        from vq_mitsuba.geometry.mesh import clean_mesh, marching_cubes, smooth_vertex_normals

        res = res or self.cfg.mesh_resolution
        vol = self.sdf_volume(res)
        try:
            mesh = marching_cubes(vol, (-1.0, -1.0, -1.0), (1.0, 1.0, 1.0))
            self.support = None
            if self.mask_free and clean:
                mesh = self._without_support(vol, mesh)
        except ValueError as exc:
            raise InputError(self.source, f"NeuS produced no surface ({exc}); check the masks and cameras") from exc
        mesh.vertices = self.to_world(mesh.vertices)
        if clean:
            c = self.cfg
            # without masks only the largest piece is the object (the rest: background the SDF took)
            mesh = clean_mesh(mesh, c.min_component, c.keep_largest or self.mask_free, c.smooth_iterations,
                              c.max_faces)
            if c.normal_smoothing > 0:
                mesh = smooth_vertex_normals(mesh, c.normal_smoothing, c.normal_smoothing_angle)
        return mesh


# --------------------------------------------------------------------------------------------
# Training


def _lr_factor(cfg: NeuSConfig, step: int, prog: float) -> float:
    warm = min(1.0, (step + 1) / max(cfg.warmup, 1))
    cos = 0.5 * (1.0 + math.cos(math.pi * prog))
    return warm * (cfg.lr_end_cosine + (1.0 - cfg.lr_end_cosine) * cos)


# Keys that shape the networks: a checkpoint resumes only under the same values. A checkpoint
# written before a key existed was made with the value given here.
_ARCHITECTURE = {"levels": None, "base_res": None, "max_res": None, "features": None, "hidden": None,
                 "geo_features": None, "reflect": False, "hash_log2": None}


def _check_architecture(path: Path, saved: dict, cfg: NeuSConfig) -> None:
    diff = []
    for key, before in _ARCHITECTURE.items():
        now = getattr(cfg, key)
        then = saved.get(key, now if before is None else before)
        if then != now:
            diff.append(f"neus.{key}={then} (now {now})")
    if diff:
        raise InputError(path, "this NeuS checkpoint was made with " + ", ".join(diff) + "; resume with "
                         "the same values (--set neus.KEY=VALUE), or start over without --resume")


def train(neus: NeuS, run: RunDir | None = None, resume: bool = False, progress: bool = True,
          callback=None, callback_every_s: float = 0.0) -> dict:
    """Optimise the NeuS model; returns a summary. `callback(neus, step, train_seconds)` is called
    every `callback_every_s` seconds of training (its own time is not counted)."""

    with _threads(neus.cfg.threads):
        return _NeuSFit(neus, run).run(resume, progress, callback, callback_every_s)


class _NeuSFit:
    """NeuS's step, optimiser and checkpoint for the loop skeleton (`vq_mitsuba.run.loop`). The
    finer grid levels fade in with the share of whichever budget runs out first, so a clock-stopped
    run has opened them all; the learning rate follows the step share alone, so a run that the
    clock stops early keeps a large rate (benchmarks/results/neus_step_decay/)."""

    def __init__(self, neus: NeuS, run: RunDir | None):
        cfg = self.cfg = neus.cfg
        self.neus, self.model = neus, neus.model
        model = neus.model
        mlp = [p for name, p in model.sdf.named_parameters() if not name.startswith("encoding")]
        background = list(model.background.parameters()) if model.background is not None else []
        groups = [{"params": list(model.sdf.encoding.parameters()) + list(model.color.parameters()) + background,
                   "base_lr": cfg.lr},
                  {"params": mlp, "base_lr": cfg.lr_sdf_mlp},
                  {"params": [model.variance], "base_lr": cfg.lr_variance}]
        self.optim = torch.optim.Adam([dict(g, lr=g["base_lr"]) for g in groups], betas=(0.9, 0.99), eps=1e-15,
                                      fused=True)
        self.gen = torch.Generator().manual_seed(cfg.seed)
        torch.manual_seed(cfg.seed)
        self.step, self.elapsed, self.history = 0, 0.0, []
        self.ckpt = run.neus_checkpoint_path if run is not None else None

    def resume(self) -> None:
        if self.ckpt is None or not self.ckpt.is_file():
            return
        state = torch.load(self.ckpt, map_location="cpu", weights_only=False)
        _check_architecture(self.ckpt, state.get("config") or {}, self.cfg)
        if state.get("background_model", False) != self.neus.mask_free:
            made = "without masks (neus.background model)" if state.get("background_model") else "with masks"
            raise InputError(self.ckpt, f"this NeuS checkpoint was made {made}, this capture and neus.background "
                                        "ask for the other; resume with the same setting, or start over without "
                                        "--resume")
        self.model.load_state_dict(state["model"])
        self.optim.load_state_dict(state["optim"])
        self.gen.set_state(state["generator"].cpu())  # CPU bytes on any device
        torch.set_rng_state(state["torch_rng"].cpu())
        self.step, self.elapsed, self.history = state["step"], state["elapsed"], state["history"]

    def save(self, p: Progress) -> None:
        if self.ckpt is not None:
            save_torch({"model": self.model.state_dict(), "optim": self.optim.state_dict(),
                        "generator": self.gen.get_state(), "torch_rng": torch.get_rng_state(), "step": p.step,
                        "elapsed": p.seconds, "history": self.history, "config": asdict(self.cfg),
                        "background_model": self.neus.mask_free}, self.ckpt)

    def loop_step(self, p: Progress) -> dict | None:
        cfg, neus = self.cfg, self.neus
        lw = neus.level_weights(p.share)
        for group in self.optim.param_groups:
            group["lr"] = group["base_lr"] * _lr_factor(cfg, p.step, p.step_share)
        idx = torch.randint(0, len(neus.rays_o), (cfg.batch_rays,), generator=self.gen)
        o, d = neus.rays_o[idx], neus.rays_d[idx]
        near, far = neus.intervals(o, d)
        out = neus.render(o, d, lw, cfg.n_samples, True, True, near=near, far=far)
        target = neus.rays_rgb[idx]
        color_loss = (out["rgb"] - target).abs().mean()
        if neus.rays_alpha is None:  # no masks: the colour of every pixel, fore- and background
            mask_loss = out["acc"].new_zeros(())
        else:
            acc = out["acc"].clamp(1e-3, 1.0 - 1e-3)
            mask_loss = F.binary_cross_entropy(acc, neus.rays_alpha[idx])
        loss = color_loss + cfg.w_eikonal * out["eikonal"] + cfg.w_mask * mask_loss
        self.optim.zero_grad(set_to_none=True)
        loss.backward()
        self.optim.step()
        step = p.step + 1
        mse = float(((out["rgb"].detach() - target) ** 2).mean())
        self.history.append({"step": step, "seconds": round(self.loop.clock(), 3), "loss": float(loss.detach()),
                             "color": float(color_loss.detach()), "eikonal": float(out["eikonal"].detach()),
                             "mask": float(mask_loss.detach()), "psnr": -10.0 * math.log10(max(mse, 1e-10)),
                             "s": float(self.model.inv_s().detach())})
        if cfg.occupancy_every > 0 and step % cfg.occupancy_every == 0:
            neus.refresh_occupancy(lw)
        if step % 10 == 0:
            h = self.history[-1]
            return {"loss": f"{h['loss']:.4f}", "psnr": f"{h['psnr']:.1f}", "s": f"{h['s']:.0f}"}
        return None

    def run(self, resume: bool, progress: bool, callback, callback_every_s: float) -> dict:
        cfg = self.cfg
        if resume:
            self.resume()
        budget = Budget(cfg.iterations, cfg.time_limit_s)
        periodic = callback is not None and callback_every_s > 0
        self.loop = Loop("neus", budget, self.loop_step, start_step=self.step, start_seconds=self.elapsed,
                         checkpoint=self.save, checkpoint_every=cfg.checkpoint_every,
                         snapshot=(lambda p, label: callback(self.neus, p.step, p.seconds)) if periodic else None,
                         snapshot_every_s=callback_every_s if periodic else 0.0, progress_bar=progress)
        with self.loop.clock.paused():  # set-up work is not training time
            self.neus.refresh_occupancy(self.neus.level_weights(self.loop.progress().share))
            if periodic and self.step == 0:
                callback(self.neus, 0, 0.0)  # the starting point (visual-hull or sphere initialisation)
        result = self.loop.run()
        return {"iterations": result.steps, "train_seconds": result.seconds, "history": self.history,
                "stopped_by_time": result.stopped_by_time}


def rate_spread(history: list[dict], window_s: float = 30.0) -> dict | None:
    """Training steps per second over consecutive windows of about window_s training seconds:
    min, median and max. A wide spread on a fixed-size step means that something else shared the
    CPU (the step's cost hardly depends on the training's progress: a fixed number of rays and
    samples per ray)."""
    rates, start = [], None
    for h in history:
        if start is None:
            start = h
            continue
        if h["seconds"] - start["seconds"] >= window_s:
            rates.append((h["step"] - start["step"]) / (h["seconds"] - start["seconds"]))
            start = h
    last = history[-1] if history else None
    if start is not None and last is not start and last["seconds"] - start["seconds"] >= 0.5 * window_s:
        rates.append((last["step"] - start["step"]) / (last["seconds"] - start["seconds"]))  # the tail
    if not rates:
        return None
    return {"window_s": window_s, "min": float(np.min(rates)), "median": float(np.median(rates)),
            "max": float(np.max(rates))}


def _plot_history(history: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if not history:
        return
    steps = [h["step"] for h in history]
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.5))
    for key in ("loss", "color", "mask", "eikonal"):
        axes[0].semilogy(steps, [max(h[key], 1e-8) for h in history], label=key, lw=0.8)
    axes[0].legend()
    axes[0].set_xlabel("step")
    axes[0].set_title("NeuS losses")
    k = max(1, len(history) // 200)
    psnr = np.convolve([h["psnr"] for h in history], np.ones(k) / k, mode="valid")
    axes[1].plot(steps[k - 1:], psnr)
    axes[1].set_xlabel("step")
    axes[1].set_title("training-batch PSNR (dB, sRGB)")
    axes[2].semilogy(steps, [h["s"] for h in history])
    axes[2].set_xlabel("step")
    axes[2].set_title("sharpness s")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


@dataclass
class Reconstruction:
    """What the geometry stage made: the exported mesh, the trained NeuS model and its summary
    (the content of geometry.json)."""

    mesh: object  # trimesh.Trimesh, in the capture's world
    neus: NeuS
    summary: dict


def reconstruct(capture, run: RunDir | str | Path, cfg: NeuSConfig | None = None, resume: bool = False,
                progress: bool = True, callback=None, callback_every_s: float = 0.0,
                sphere: tuple | None = None, support: tuple | None = None,
                points: np.ndarray | None = None) -> Reconstruction:
    """NeuS on a loaded capture, then mesh export: writes the run's mesh.ply, geometry.json,
    geometry_loss.png (and the NeuS checkpoint neus.pt). `sphere`, `support`, `points`: the
    bounding sphere, a known supporting plane and the sparse points when NeuS runs without masks
    (`NeuS`)."""
    cfg = cfg or NeuSConfig()
    run = run if isinstance(run, RunDir) else RunDir(run)
    with _threads(cfg.threads):
        return _reconstruct(capture, run, cfg, resume, progress, callback, callback_every_s, sphere, support, points)


def _reconstruct(capture, run: RunDir, cfg: NeuSConfig, resume, progress, callback, callback_every_s,
                 sphere=None, support=None, points=None) -> Reconstruction:
    t0 = time.perf_counter()
    neus = NeuS(capture, cfg, sphere, support, points)
    run.create()
    setup_s = time.perf_counter() - t0
    summary = train(neus, run, resume=resume, progress=progress, callback=callback,
                    callback_every_s=callback_every_s)
    t1 = time.perf_counter()
    mesh = neus.extract_mesh()
    export_s = time.perf_counter() - t1
    run.write_mesh(mesh)
    if summary["history"]:
        run.write_file(run.GEOMETRY_PLOT, lambda path: _plot_history(summary["history"], path))
    last = summary["history"][-1] if summary["history"] else {}
    info = {
        "capture": str(Path(capture.source).resolve()),
        "world": capture.world,
        "iterations": summary["iterations"],
        "stopped_by_time_limit": summary["stopped_by_time"],
        "seconds": {"setup_and_hull": round(setup_s, 2), "hull": round(neus.hull_seconds, 2),
                    "train": round(summary["train_seconds"], 2), "mesh_export": round(export_s, 2),
                    "total": round(time.perf_counter() - t0, 2)},
        "iterations_per_s": summary["iterations"] / max(summary["train_seconds"], 1e-9),
        "iterations_per_s_spread": rate_spread(summary["history"]),
        "final_train_psnr": last.get("psnr"),
        "final_sharpness_s": last.get("s"),
        "box_center": neus.center.tolist(),
        "box_half_size": neus.half,
        "background": "model" if neus.mask_free else "masks",
        "bounding_sphere": {"center": neus.center.tolist(), "radius": neus.half, "from": neus.sphere_source}
        if neus.mask_free else None,
        "support_plane": neus.support,
        "training_rays": len(neus.rays_o),
        "mesh": {"vertices": int(len(mesh.vertices)), "faces": int(len(mesh.faces)),
                 "watertight": bool(mesh.is_watertight)},
        "grid": neus.grid,
        "config": asdict(neus.cfg),
        "torch_threads": torch.get_num_threads(),
        "grid_lookup": grid_kernel.status(),
    }
    run.write_geometry_summary(info)
    return Reconstruction(mesh, neus, info)
