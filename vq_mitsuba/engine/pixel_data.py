"""The pixels a material fit trains on: the traced pool, the pixels held aside, the sampler that
draws each step's batch, the jittered hits of each pixel and the neighbour pairs of the smoothness
term.

A pixel's colour is the mean over its footprint: its jittered hits are shaded together and their
mean is scored (`pixel_means`), so the loss does not also ask each hit for the pixel's mean colour.
"""

from __future__ import annotations

import torch

from vq_mitsuba.config import Config
from vq_mitsuba.data.captures import Capture
from vq_mitsuba.data.pixels import (ErrorSampler, PixelPool, hold_aside, neighbour_pairs, pixel_hit_table,
                                    sampler_tile, trace_training_pixels)
from vq_mitsuba.engine import skips
from vq_mitsuba.errors import InputError


class PixelData:
    """The training pixels of one fit and how each step draws from them."""

    def __init__(self, scene, capture: Capture, cfg: Config, device, hold: bool):
        """Trace the capture's opaque pixels in `scene`; `hold`: keep pixels aside from the steps
        (for the pace's and the trials' measurements)."""
        t = cfg.train
        self.pool, self.stats = trace_training_pixels(scene, capture, t.alpha_threshold, t.pixel_jitter, t.seed,
                                                      t.max_hits)
        if len(self.pool) == 0:
            raise InputError(capture.source, "no training pixel hits the geometry: check the cameras, the mesh "
                                             "and the alpha masks")
        w, h = capture.width, capture.height
        self.pairs = neighbour_pairs(self.pool, w, h).to(device) if cfg.loss.w_sm > 0 else None
        self.batch = min(t.batch_rays, len(self.pool))
        self.copies = int(self.stats["hits_per_pixel"])  # 1 without jitter
        self.hit_row = self.pixel_hits = None
        if self.copies > 1:
            self.hit_row, self.pixel_hits = pixel_hit_table(self.pool, w, h, self.copies)
        n_pixels = int((self.pool.copy == 0).sum())
        self.held = self.train_idx = None
        if hold:
            self.held, self.train_idx = hold_aside(self.pool, w, h, skips.stop_pixels(n_pixels),
                                                   skips.np_seed(t.seed, 2))
        self.sampler = None
        if t.sampling == "auto":
            candidates = self.train_idx if self.train_idx is not None else torch.arange(len(self.pool))
            drawable = n_pixels - (0 if self.held is None else len(self.held))
            tile = sampler_tile(drawable, self.pixels_per_step * t.iterations, skips.SAMPLER_VISITS)
            self.sampler = ErrorSampler(self.pool, candidates, w, h, tile, skips.SAMPLER_FLOOR)
        self.device = device

    def __len__(self) -> int:
        return len(self.pool)

    @property
    def pixels_per_step(self) -> int:
        """Pixels a step draws: train.batch_rays hits, all the jittered hits of each pixel."""
        return max(1, self.batch // self.copies)

    def draw(self, step: int, gen: torch.Generator) -> tuple[torch.Tensor, torch.Tensor | None]:
        """The pixels of step `step` (pool indices) and their importance weights (None: drawn
        uniformly)."""
        n = self.pixels_per_step
        if self.sampler is not None:
            if step % skips.SAMPLER_REFRESH == 0:
                self.sampler.refresh()
            return self.sampler.draw(n, gen)
        if self.train_idx is not None:  # all but the held-aside pixels
            return self.train_idx[torch.randint(0, len(self.train_idx), (n,), generator=gen, device=self.device)], None
        return torch.randint(0, len(self.pool), (n,), generator=gen, device=self.device), None

    def observe(self, idx: torch.Tensor, per_pixel: torch.Tensor | None) -> None:
        """The squared errors of a step's pixels, for the sampler's running map."""
        if self.sampler is not None and per_pixel is not None:
            self.sampler.update(idx, per_pixel)

    def footprint(self, idx: torch.Tensor) -> torch.Tensor:
        """(len(idx) * copies,) the jittered hits of the pixels of the hits `idx`, pixel by pixel."""
        if self.pixel_hits is None:
            return idx
        return self.pixel_hits[self.hit_row[idx]].reshape(-1)

    @staticmethod
    def pixel_means(samples: torch.Tensor, n_pixels: int) -> torch.Tensor:
        """(n_pixels, ...): the mean of each pixel's hits' values (hits in pixel order)."""
        return samples.reshape(n_pixels, -1, *samples.shape[1:]).mean(1)

    def neighbours(self, gen: torch.Generator) -> torch.Tensor | None:
        """(batch / 4, 2) pool indices of neighbouring pixels for the smoothness term (None: off)."""
        if self.pairs is None or len(self.pairs) == 0:
            return None
        return self.pairs[torch.randint(0, len(self.pairs), (max(self.batch // 4, 1),), generator=gen,
                                        device=self.device)]

    def sampling_decision(self, setting: str) -> dict:
        """fit.json's `decisions.sampling`."""
        if self.sampler is None:
            return skips.decision(setting, "uniform", f"train.sampling = {setting}")
        info = self.sampler.summary()
        share = info["top10_tiles_draw_share"]
        out = skips.decision(
            setting, "error",
            f"by the running error of {info['tiles']} tiles of {info['tile_px']} x {info['tile_px']} px, "
            f"{100 * skips.SAMPLER_FLOOR:g} % uniform, importance-weighted"
            + ("" if share is None else f"; the 10 % of tiles with the largest error drew {100 * share:.0f} % "
                                        "of the rays"))
        out.update(info)
        return out

    def state_dict(self) -> dict | None:
        return self.sampler.state_dict() if self.sampler is not None else None

    def load_state_dict(self, state: dict | None) -> None:
        if self.sampler is not None and state is not None:
            self.sampler.load_state_dict(state)


__all__ = ["PixelData", "PixelPool"]
