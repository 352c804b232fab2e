"""The training pixel pool: every foreground pixel of every training view with its primary hits.

Geometry is fixed during the material fit, so the primary rays are traced once (by any object
with a `trace(origins, directions)` method, e.g. `vq_mitsuba.render.shading.ShadingScene`) and
their hits are kept with the pixel's target colour.
"""

from __future__ import annotations

import math
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

    def views_of(self, idx: torch.Tensor) -> torch.Tensor:
        """The view index of the hits `idx` (on the hits' device; `view` itself stays on the CPU)."""
        return self.view[idx.to(self.view.device)].to(self.position.device)


def trace_training_pixels(scene, capture: Capture, alpha_threshold: float, jitter: int = 0,
                          seed: int = 0, max_hits: int = 0) -> tuple[PixelPool, dict]:
    """Primary hits of all views' opaque pixels: the pixel centre, or `jitter` random positions
    inside each pixel (a pixel's value is an area average; centres alias thin highlights).

    `max_hits` > 0 caps the pool (72 bytes a hit): where the opaque pixels times `jitter` exceed
    it, fewer jittered hits per pixel are traced (16, 9, 4, then 1), and where the pixels alone do,
    a random share of each view's pixels is kept."""
    rng = np.random.default_rng(seed)
    opaque_of = [np.flatnonzero(capture.alpha[v].reshape(-1) >= alpha_threshold) for v in range(len(capture.cameras))]
    n_alpha = sum(len(o) for o in opaque_of)
    copies, share = max(jitter, 1), 1.0
    if max_hits > 0 and n_alpha * copies > max_hits:
        while copies > 1 and n_alpha * copies > max_hits:
            copies = (math.isqrt(copies) - 1) ** 2
        copies = max(copies, 1)
        share = min(1.0, max_hits / max(n_alpha, 1))
    jitter = copies if jitter > 0 else 0
    fields = [[] for _ in range(7)]
    n_hit = n_traced = 0
    for v, cam in enumerate(capture.cameras):
        opaque = opaque_of[v]  # only these are traced
        if share < 1.0:
            opaque = opaque[rng.random(len(opaque)) < share]
        n_traced += len(opaque)
        rgb = torch.as_tensor(capture.images[v].reshape(-1, 3)[opaque])
        for k in range(copies):
            # the jitter is drawn for every pixel, so a pixel's offsets do not depend on the mask
            offsets = pixel_jitter(cam.width * cam.height, k, jitter, rng) if jitter > 0 else None
            o, d = camera_rays(cam, None if offsets is None else offsets[opaque], pixels=opaque)
            hits = scene.trace(o, d)
            keep = hits.valid
            n_keep = int(keep.sum())
            if k == 0:
                n_hit += n_keep
            keep_cpu = keep.cpu()
            for field, part in zip(fields, (hits.position[keep], hits.normal[keep], hits.wi[keep],
                                            rgb.to(keep.device)[keep], torch.full((n_keep,), v, dtype=torch.int64),
                                            torch.as_tensor(opaque)[keep_cpu],
                                            torch.full((n_keep,), k, dtype=torch.int64))):
                field.append(part)
    cat = []
    for field in fields:  # one field at a time: the parts of the others are not copied alongside
        cat.append(torch.cat(field))
        field.clear()
    pool = PixelPool(*cat)
    stats = {"opaque_pixels": n_alpha, "used_pixels": n_hit, "geometry_coverage": n_hit / max(n_traced, 1),
             "hits_per_pixel": copies, "pixel_share": share}
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


def pixel_keys(pool: PixelPool, width: int, height: int) -> torch.Tensor:
    """(P,) each hit's pixel key view * W * H + pixel, on the CPU."""
    return pool.view.cpu() * (width * height) + pool.pixel.cpu()


def pixel_hit_table(pool: PixelPool, width: int, height: int, copies: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(each hit's row (P,), (R, copies) pool indices of the jittered hits of each of the R pixels
    that have any): a pixel with fewer hits (its other rays missed) repeats one of them."""
    keys = pixel_keys(pool, width, height)
    _, row = torch.unique(keys, return_inverse=True)
    table = torch.full((int(row.max()) + 1 if len(row) else 0, copies), -1, dtype=torch.int64)
    table[row, pool.copy.cpu()] = torch.arange(len(keys))
    any_hit = table.max(dim=1).values
    table = torch.where(table < 0, any_hit[:, None], table)
    device = pool.position.device
    return row.to(device), table.to(device)


def hold_aside(pool: PixelPool, width: int, height: int, n_pixels: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(pool indices of `n_pixels` random pixels' first hits, pool indices of every hit of the
    other pixels): a fixed set of pixels kept out of the gradient steps, all jittered hits of a
    pixel on the same side, chosen from `seed` alone."""
    first, key, _ = _first_hits(pool, width, height)
    gen = torch.Generator().manual_seed(seed)
    n = max(0, min(n_pixels, len(first) - 1))
    held_keys = key[torch.randperm(len(first), generator=gen)[:n]]
    out = torch.isin(pixel_keys(pool, width, height), held_keys)
    device = pool.position.device
    held = first[torch.isin(key, held_keys)]
    return held.to(device), torch.nonzero(~out)[:, 0].to(device)


class ErrorSampler:
    """Draws pool entries by their running error, with a uniform share so that none is starved.

    The pool's pixels are grouped into square tiles of `tile` x `tile` pixels of a view (all
    jittered hits of a pixel in its pixel's tile). Each tile keeps a running estimate e_t of the
    squared error of its hits (an exponential average of the errors of the hits the steps drew
    there); a draw picks tile t with probability

        p_t = floor * n_t / N + (1 - floor) * sqrt(e_t) / sum_s sqrt(e_s)

    (n_t hits of the N drawable ones in t), then one of its hits uniformly, so every hit has at
    least `floor` / N. sqrt(e_t), the RMS error, follows the size of a hit's gradient: drawing in
    proportion to it is the importance distribution that most reduces the variance of the
    weighted gradient. `draw` returns the weight (n_t / N) / p_t of each draw: the weighted mean
    of the per-hit losses has the expectation of the uniform mean (the objective is unchanged;
    the weights are at most 1 / floor).
    """

    def __init__(self, pool: PixelPool, candidates: torch.Tensor, width: int, height: int, tile: int,
                 floor: float = 0.3, decay: float = 0.5):
        self.floor, self.decay, self.tile = float(floor), float(decay), int(tile)
        device = pool.position.device
        cand = candidates.cpu()
        pixel, view = pool.pixel.cpu()[cand], pool.view.cpu()[cand]
        tx, ty = -(-width // tile), -(-height // tile)
        key = (view * ty + pixel // width // tile) * tx + pixel % width // tile
        _, tile_of = torch.unique(key, return_inverse=True)
        order = torch.argsort(tile_of, stable=True)
        counts = torch.bincount(tile_of)
        self.entries = cand[order].to(device)  # drawable pool indices, grouped by tile
        self.counts = counts.to(device)
        self.starts = (torch.cumsum(counts, 0) - counts).to(device)
        tile_of_entry = torch.full((len(pool),), -1, dtype=torch.int64)
        tile_of_entry[cand] = tile_of
        self.tile_of_entry = tile_of_entry.to(device)
        self.error = torch.full((len(self.counts),), math.nan, dtype=torch.float64, device=device)
        self.draws = torch.zeros(len(self.counts), dtype=torch.float64, device=device)
        self._cdf: torch.Tensor | None = None
        self._p: torch.Tensor | None = None

    def __len__(self) -> int:
        return len(self.entries)

    @property
    def num_tiles(self) -> int:
        return len(self.counts)

    def probabilities(self) -> torch.Tensor:
        """p_t of every tile (the uniform share alone until the first errors come in)."""
        n = self.counts.to(torch.float64)
        uniform = n / n.sum()
        e = self.error
        if bool(torch.isnan(e).all()):
            return uniform
        rms = torch.sqrt(torch.nan_to_num(e, nan=float(torch.nanmean(e))).clamp_min(0.0))
        total = float(rms.sum())
        if not math.isfinite(total) or total <= 0:
            return uniform
        return self.floor * uniform + (1.0 - self.floor) * rms / total

    def refresh(self) -> None:
        """Recompute the draw distribution from the current error estimates (cheap: one pass
        over the tiles); `draw` uses the last one."""
        self._p = self.probabilities()
        self._cdf = torch.cumsum(self._p, 0)

    def draw(self, n: int, generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
        """(n pool indices, their importance weights (float32))."""
        if self._cdf is None:
            self.refresh()
        device = self.entries.device
        u = torch.rand(2, n, generator=generator, device=device, dtype=torch.float64)
        t = torch.searchsorted(self._cdf, u[0] * self._cdf[-1]).clamp_max(self.num_tiles - 1)
        offset = (u[1] * self.counts[t]).long().clamp_max(self.counts[t] - 1)
        idx = self.entries[self.starts[t] + offset]
        weight = (self.counts[t].to(torch.float64) / len(self.entries)) / self._p[t]
        self.draws += torch.bincount(t, minlength=self.num_tiles).to(torch.float64)
        return idx, weight.float()

    @torch.no_grad()
    def update(self, idx: torch.Tensor, err: torch.Tensor) -> None:
        """Fold the squared errors `err` (per drawn hit) of the hits `idx` into their tiles'
        running estimates; tiles not seen yet start at the mean of this batch."""
        t = self.tile_of_entry[idx]
        keep = t >= 0
        t, err = t[keep], err[keep].to(torch.float64)
        if len(t) == 0:
            return
        if bool(torch.isnan(self.error).all()):
            self.error.fill_(float(err.mean()))
        sums = torch.bincount(t, weights=err, minlength=self.num_tiles)
        seen = torch.bincount(t, minlength=self.num_tiles)
        hit = seen > 0
        self.error[hit] = (1 - self.decay) * self.error[hit] + self.decay * sums[hit] / seen[hit]

    def summary(self) -> dict:
        """Where the draws went: the share of draws and of the error held by the 10 % of tiles with
        the largest error, and the smallest probability of a hit relative to uniform."""
        p = self.probabilities()
        n = self.counts.to(torch.float64)
        k = max(1, self.num_tiles // 10)
        e = torch.nan_to_num(self.error, nan=0.0).clamp_min(0.0)
        top = torch.argsort(e, descending=True)[:k]
        draws = float(self.draws.sum())
        return {"tiles": self.num_tiles, "tile_px": self.tile, "uniform_share": self.floor,
                "top10_tiles_draw_share": float(self.draws[top].sum() / draws) if draws > 0 else None,
                "top10_tiles_pixel_share": float(n[top].sum() / n.sum()),
                "min_probability_vs_uniform": float((p / (n / n.sum())).min())}

    def state_dict(self) -> dict:
        return {"error": self.error.cpu(), "draws": self.draws.cpu()}

    def load_state_dict(self, state: dict) -> None:
        if state["error"].shape == self.error.shape:
            self.error.copy_(state["error"].to(self.error.device))
            self.draws.copy_(state["draws"].to(self.draws.device))
        self._cdf = None


def sampler_tile(pixels: int, draws: int, visits: int = 16) -> int:
    """The tile side (1, 2, 4, ... pixels) at which the fit's `draws` visit each tile of `pixels`
    pixels about `visits` times or more: a running error per tile needs repeated visits."""
    tile = 1
    while tile < 64 and pixels / (tile * tile) * visits > draws:
        tile *= 2
    return tile
