"""What NeuS sees of a capture: the box it works in (around the visual hull of the masks, or without
masks around the bounding sphere, above a known support), the training rays in that box, the
feature grid sized by the views' footprint, and renders of the capture's cameras. `neus_for` builds
the model (`renderer.NeuS`, which takes rays, not a capture) on them."""

from __future__ import annotations

import math
import time
from dataclasses import replace

import numpy as np
import torch
import torch.nn.functional as F

from vq_mitsuba.config import NeuSConfig
from vq_mitsuba.config import check as validate
from vq_mitsuba.data.cameras import camera_rays
from vq_mitsuba.errors import InputError
from vq_mitsuba.geometry.neus.framing import bounding_sphere, box_footprint_px, uses_background_model
from vq_mitsuba.geometry.neus.hull import hull_box, hull_sdf
from vq_mitsuba.geometry.neus.networks import (COARSE_GRID, COARSE_TO_FINE, COARSE_TO_FINE_FINE, FINE_GRID,
                                             FINE_GRID_FROM_PX, MASKED_GRID, SDF_LAYERS, SDF_LAYERS_FINE)
from vq_mitsuba.geometry.neus.renderer import Box, NeuS, TrainingRays, _threads, encode_srgb
from vq_mitsuba.backend import torch_device


def neus_for(capture, cfg: NeuSConfig, sphere: tuple | None = None, support: tuple | None = None,
             points: np.ndarray | None = None) -> NeuS:
    """A NeuS model for a loaded capture's views: in the box around the visual hull of its masks, or
    without masks (`uses_background_model`) around the bounding sphere (`sphere`: (centre, radius,
    what framed it); default `bounding_sphere` of the cameras). `support`: a known supporting plane
    without masks ((unit normal towards the cameras, offset) in the world, e.g. `support_from_points`):
    the foreground is what lies inside the sphere above it, and the background model takes the plane
    and what lies below. `points`: the capture's sparse points (N, 3) in the world."""
    validate(cfg)
    mask_free = uses_background_model(capture, cfg)
    if len(capture.cameras) == 0:
        raise InputError(capture.source, "the capture has no images")
    if not capture.has_alpha and not mask_free:
        raise InputError(capture.source, "neus.background is masks, but the images have no alpha channel and "
                                         "there is no mask folder (give RGBA PNG/EXR images, masks/ for COLMAP or "
                                         "mask/ for NeuS/IDR, --background-color R,G,B for a plain backdrop, or "
                                         "leave neus.background at auto to reconstruct without masks)")
    alpha = torch.from_numpy(np.ascontiguousarray(capture.alpha))
    if not mask_free and float(alpha.max()) <= cfg.hull_threshold:
        raise InputError(capture.source, "the alpha masks are empty: no foreground pixel in any image")
    with _threads(cfg.threads):
        if mask_free:
            box, rays = _sphere_box(capture, cfg, sphere or bounding_sphere(capture.cameras), support)
        else:
            box, rays = _hull_box_rays(capture, cfg, alpha)
        chosen, grid = choose_grid(cfg, capture.cameras, box.center, box.half, masks=not mask_free)
        views = np.array([c.origin for c in capture.cameras], np.float64)
        return NeuS(chosen, box, rays, grid, views, points, capture.source)


def choose_grid(cfg: NeuSConfig, cameras, center: np.ndarray, half: float,
                masks: bool = True) -> tuple[NeuSConfig, dict]:
    """The config with neus.levels, neus.max_res, neus.sdf_layers (when 0) and neus.coarse_to_fine
    (when -1) decided, and what decided them; `masks` False: NeuS trains without masks (the coarse
    grid whatever the size)."""
    footprint = box_footprint_px(cameras, center, half)
    fine = masks and footprint > FINE_GRID_FROM_PX
    levels, max_res = FINE_GRID if fine else MASKED_GRID if masks else COARSE_GRID
    fade = cfg.coarse_to_fine if cfg.coarse_to_fine >= 0 else COARSE_TO_FINE_FINE if fine else COARSE_TO_FINE
    chosen = replace(cfg, levels=cfg.levels or levels, max_res=cfg.max_res or max_res,
                     sdf_layers=cfg.sdf_layers or (SDF_LAYERS_FINE if fine else SDF_LAYERS), coarse_to_fine=fade)
    if cfg.levels and cfg.max_res:
        reason = "neus.levels and neus.max_res given"
    elif not masks:
        reason = f"without masks (the box spans {footprint:.0f} px in the median view)"
    else:
        reason = (f"the box spans {footprint:.0f} px in the median view ({'over' if fine else 'at most'} "
                  f"{FINE_GRID_FROM_PX})")
    return chosen, {"levels": chosen.levels, "max_res": chosen.max_res, "hash_log2": chosen.hash_log2,
                    "sdf_layers": chosen.sdf_layers, "coarse_to_fine": chosen.coarse_to_fine,
                    "box_footprint_px": footprint, "reason": reason}


def _dilated(occ: torch.Tensor, device) -> torch.Tensor:
    """The occupancy grid dilated by two cells (scipy's, on the CPU), on `device`."""
    from scipy import ndimage

    return torch.from_numpy(ndimage.binary_dilation(occ.cpu().numpy(), iterations=2)).to(device)


def _sphere_box(capture, cfg: NeuSConfig, sphere: tuple, support: tuple | None) -> tuple[Box, TrainingRays]:
    """Without masks: the bounding sphere (above a known support) is the unit sphere of the box and
    stands in for the visual hull; the SDF starts as a sphere; every pixel of every view is a
    training ray."""
    device = torch_device()
    t0 = time.perf_counter()
    center, radius, sphere_source = sphere
    if not (np.all(np.isfinite(center)) and math.isfinite(radius) and radius > 0):
        raise InputError(capture.source, f"the bounding sphere (centre {center}, radius {radius}, from "
                                         f"{sphere_source}) is degenerate: check the camera poses")
    center, half = np.asarray(center, dtype=np.float64), float(radius)
    res = cfg.hull_resolution
    axis = (torch.arange(res, dtype=torch.float32, device=device) + 0.5) / res * 2.0 - 1.0
    grid = torch.stack(torch.meshgrid(axis, axis, axis, indexing="ij"), -1)
    sdf = grid.norm(dim=-1) - 1.0
    plane = None
    if support is not None:
        length = float(np.linalg.norm(support[0]))
        n = np.asarray(support[0], np.float64) / length
        c = (float(support[1]) / length - float(n @ center)) / half
        if c > 0.9:
            raise InputError(capture.source, "the supporting plane passes above the bounding sphere")
        plane = (torch.tensor(n, dtype=torch.float32, device=device), c)
        sdf = torch.maximum(sdf, c - grid @ plane[0])
    hull = sdf < 0
    box = Box(center, half, hull, sdf, _dilated(hull, device), True, plane, sphere_source,
              time.perf_counter() - t0)
    origins, dirs = zip(*(camera_rays(c) for c in capture.cameras))
    images = torch.from_numpy(np.ascontiguousarray(capture.images)).to(device)
    rays = TrainingRays(box.to_box(torch.from_numpy(np.concatenate(origins)).to(device)),
                        torch.from_numpy(np.concatenate(dirs)).to(device), encode_srgb(images.reshape(-1, 3)), None)
    return box, rays


def _hull_box_rays(capture, cfg: NeuSConfig, alpha: torch.Tensor) -> tuple[Box, TrainingRays]:
    """With masks: the box around the visual hull, and the training rays: the pixels within a few
    pixels of the foreground, from every view."""
    device = torch_device()
    alpha = alpha.to(device)
    masks = alpha > cfg.hull_threshold
    # Carve with masks dilated by one pixel, so the hull stays conservative at silhouettes.
    dil = F.max_pool2d(masks.float()[:, None], 3, stride=1, padding=1)[:, 0] > 0.5
    t0 = time.perf_counter()
    center, half, occ = hull_box(capture.cameras, dil, cfg, capture.source)
    sdf, dilated = hull_sdf(occ).to(device), _dilated(occ, device)
    box = Box(np.asarray(center, dtype=np.float64), float(half), occ, sdf, dilated, False,
              seconds=time.perf_counter() - t0)
    near_fg = F.max_pool2d(masks.float()[:, None], 7, stride=1, padding=3)[:, 0] > 0.5
    origins, dirs = zip(*(camera_rays(c) for c in capture.cameras))
    origins = torch.from_numpy(np.concatenate(origins)).to(device)
    dirs = torch.from_numpy(np.concatenate(dirs)).to(device)
    sel = near_fg.reshape(-1)
    rgb = torch.from_numpy(np.ascontiguousarray(capture.images)).to(device).reshape(-1, 3)
    rays = TrainingRays(box.to_box(origins[sel]), dirs[sel], encode_srgb(rgb[sel]),
                        alpha.reshape(-1)[sel].clamp(0, 1))
    return box, rays


@torch.no_grad()
def render_view(neus: NeuS, cam, chunk: int = 4096, composite: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """(sRGB colour (H, W, 3) on black, or with `composite` over the background model where there is
    one; opacity (H, W)) of a camera, for novel-view PSNR."""
    o, d = camera_rays(cam)
    o = neus.to_box(torch.from_numpy(o).to(neus.device))
    d = torch.from_numpy(d).to(neus.device)
    lw = [1.0] * neus.cfg.levels
    rgb, acc = [], []
    for i in range(0, len(o), chunk):
        r = neus.render(o[i:i + chunk], d[i:i + chunk], lw, neus.cfg.n_samples, False, False)
        rgb.append(r["rgb"] if composite else r.get("rgb_fg", r["rgb"]))
        acc.append(r["acc"].detach())
    return (torch.cat(rgb).reshape(cam.height, cam.width, 3).cpu().numpy(),
            torch.cat(acc).reshape(cam.height, cam.width).cpu().numpy())
