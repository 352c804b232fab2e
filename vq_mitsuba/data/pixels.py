"""The training pixel pool: every foreground pixel of every training view with its primary hits.

Geometry is fixed during the material fit, so the primary rays are traced once (by any object
with a `trace(origins, directions)` method, e.g. `vq_mitsuba.render.shading.ShadingScene`) and
their hits are kept with the pixel's target colour.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from vq_mitsuba.data.captures import Capture
from vq_mitsuba.data.cameras import camera_rays, pixel_jitter


@dataclass
class PixelPool:
    """Foreground training pixels with their primary hits."""

    position: torch.Tensor  # (P, 3)
    normal: torch.Tensor  # (P, 3)
    wi: torch.Tensor  # (P, 3)
    rgb: torch.Tensor  # (P, 3) linear target
    view: torch.Tensor  # (P,) view index
    pixel: torch.Tensor  # (P,) pixel index in its view (row-major)
    copy: torch.Tensor  # (P,) which of the jittered hits of that pixel

    def __len__(self) -> int:
        return self.position.shape[0]


def trace_training_pixels(scene, capture: Capture, alpha_threshold: float, jitter: int = 0,
                          seed: int = 0) -> tuple[PixelPool, dict]:
    """Primary hits of all views' opaque pixels: the pixel centre, or `jitter` random positions
    inside each pixel (a pixel's value is an area average; centres alias thin highlights)."""
    rng = np.random.default_rng(seed)
    parts, n_alpha, n_hit = [], 0, 0
    for v, cam in enumerate(capture.cameras):
        opaque = np.flatnonzero(capture.alpha[v].reshape(-1) >= alpha_threshold)  # only these are traced
        rgb = torch.as_tensor(capture.images[v].reshape(-1, 3)[opaque])
        n_alpha += len(opaque)
        for k in range(max(jitter, 1)):
            # the jitter is drawn for every pixel, so a pixel's offsets do not depend on the mask
            offsets = pixel_jitter(cam.width * cam.height, k, jitter, rng) if jitter > 0 else None
            o, d = camera_rays(cam, None if offsets is None else offsets[opaque], pixels=opaque)
            hits = scene.trace(o, d)
            keep = hits.valid
            if k == 0:
                n_hit += int(keep.sum())
            n_keep = int(keep.sum())
            keep_cpu = keep.cpu()
            parts.append((hits.position[keep], hits.normal[keep], hits.wi[keep], rgb.to(keep.device)[keep],
                          torch.full((n_keep,), v, dtype=torch.int64),
                          torch.as_tensor(opaque)[keep_cpu], torch.full((n_keep,), k, dtype=torch.int64)))
    cat = [torch.cat(x) for x in zip(*parts)]
    pool = PixelPool(*cat)
    stats = {"opaque_pixels": n_alpha, "used_pixels": n_hit,
             "geometry_coverage": n_hit / max(n_alpha, 1)}
    return pool, stats


def _first_hits(pool: PixelPool, width: int, height: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(pool indices of the pixels' first hits, their pixel keys view * W * H + pixel, and a lookup
    from any pixel key to its first hit's pool index, -1 where the pixel has none)."""
    first = torch.nonzero(pool.copy == 0)[:, 0]
    key = pool.view[first] * (width * height) + pool.pixel[first]
    n_keys = int(pool.view.max()) + 1 if len(pool) else 0
    lookup = torch.full((n_keys * width * height,), -1, dtype=torch.int64)
    lookup[key] = first
    return first, key, lookup


def neighbour_pairs(pool: PixelPool, width: int, height: int) -> torch.Tensor:
    """(Q, 2) pool indices of horizontally or vertically adjacent training pixels (first hits)."""
    first, key, lookup = _first_hits(pool, width, height)
    x = pool.pixel[first] % width
    y = pool.pixel[first] // width
    pairs = []
    for ok, step in ((x < width - 1, 1), (y < height - 1, width)):
        a = first[ok]
        b = lookup[key[ok] + step]
        pairs.append(torch.stack([a[b >= 0], b[b >= 0]], -1))
    return torch.cat(pairs)
