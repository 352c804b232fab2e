"""Where NeuS spends its steps: rays drawn by a running error map (unbiased by their weights), and the
held-aside rays' plateau that ends training after a final decay."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from vq_mitsuba.geometry.neus import neus_for, train
from vq_mitsuba.geometry.neus.rays import pixel_tiles
from vq_mitsuba.geometry.neus.sampling import UNSEEN_ERROR, RaySampler
from vq_mitsuba.geometry.neus.training import NeuSTraining, lr_factor

from test_geometry import sphere_capture, small_cfg


def test_pixel_tiles_number_each_views_tiles_row_by_row():
    class Cam:
        def __init__(self, h, w):
            self.height, self.width = h, w

    tiles = pixel_tiles([Cam(3, 5), Cam(2, 2)], tile=2)
    first = torch.tensor([[0, 0, 1, 1, 2], [0, 0, 1, 1, 2], [3, 3, 4, 4, 5]]).reshape(-1)
    assert torch.equal(tiles, torch.cat([first, torch.tensor([6, 6, 6, 6])]))


def test_error_draws_are_unbiased_by_their_weights_and_follow_the_error():
    gen = torch.Generator().manual_seed(0)
    tiles = torch.arange(2000) // 20  # 100 tiles of 20 rays
    sampler = RaySampler(tiles, 0.5, 100, gen)
    assert len(sampler.held) == 100 and sampler.n == 1900
    assert not np.isin(sampler.held.numpy(), sampler.train.numpy()).any()
    # A map that has seen every tile: one hot tile, the rest cold.
    sampler.error[:] = 0.01
    sampler.error[7] = 5.0
    sampler.seen[:] = True
    value = torch.sin(torch.arange(2000, dtype=torch.float64))  # a per-ray quantity
    truth = float(value[sampler.train].mean())
    estimates, hot = [], 0
    held = set(sampler.held.tolist())
    for _ in range(400):
        idx, weight = sampler.draw(256)
        assert not held & set(idx.tolist())
        estimates.append(float((weight.double() * value[idx]).mean()))
        hot += int((tiles[idx] == 7).sum())
        assert float(weight.max()) <= 1.0 / (1.0 - sampler.share) + 1e-4
    spread = np.std(estimates) / math.sqrt(len(estimates))
    assert abs(np.mean(estimates) - truth) < 4 * spread
    # Tile 7 (1 % of the rays) gets about half of the error share's draws.
    assert hot / (400 * 256) > 0.15


def test_the_error_map_moves_towards_the_batch_errors_and_visits_every_tile_first():
    gen = torch.Generator().manual_seed(1)
    sampler = RaySampler(torch.arange(400) // 4, 1.0 - 1e-6, 0, gen)
    assert torch.all(sampler.error == UNSEEN_ERROR)
    idx, _ = sampler.draw(64)
    sampler.update(torch.full((64,), 0.2))
    visited = torch.unique(sampler.tiles_of_last())
    assert torch.allclose(sampler.error[visited], torch.tensor(0.2))  # a first visit sets the value
    assert torch.all(sampler.error[~sampler.seen] == UNSEEN_ERROR)
    for _ in range(30):  # unseen tiles outweigh the seen: every tile is visited soon
        sampler.draw(64)
        sampler.update(torch.full((64,), 0.2))
    assert bool(sampler.seen.all())


def test_uniform_draws_have_no_weights():
    sampler = RaySampler(torch.arange(100), 0.0, 0, torch.Generator().manual_seed(0))
    idx, weight = sampler.draw(32)
    assert weight is None and len(idx) == 32


def test_a_flat_held_aside_score_ends_training_after_a_final_decay(monkeypatch):
    capture = sphere_capture(n_views=6, size=16)
    cfg = small_cfg(iterations=0, time_limit_s=60, plateau_s=0.4, coarse_to_fine=0.0)
    neus = neus_for(capture, cfg)
    monkeypatch.setattr(NeuSTraining, "held_aside_psnr", lambda self, lw: 20.0)
    rates = []
    step = NeuSTraining.loop_step

    def spy(self, p):
        out = step(self, p)
        rates.append(self.optim.param_groups[0]["lr"] / self.optim.param_groups[0]["base_lr"])
        return out

    monkeypatch.setattr(NeuSTraining, "loop_step", spy)
    summary = train(neus, None, progress=False)
    assert summary["stopped_by_plateau"] and not summary["stopped_by_time"]
    assert summary["train_seconds"] < 10
    plateau = summary["plateau"]
    assert plateau["anneal_from_s"] is not None and len(plateau["checks"]) >= 2
    # The rate, still near its start at the plateau (a 60 s budget), ends its decay near where a run
    # of the whole budget would end it.
    end = lr_factor(cfg, 10 ** 6, 1.0)
    assert max(rates) > 0.95 and end <= rates[-1] < end + 0.05


def test_a_rising_held_aside_score_trains_to_the_time_limit(monkeypatch):
    capture = sphere_capture(n_views=6, size=16)
    neus = neus_for(capture, small_cfg(iterations=0, time_limit_s=1.5, plateau_s=0.3, coarse_to_fine=0.0))
    score = iter(range(10 ** 6))
    monkeypatch.setattr(NeuSTraining, "held_aside_psnr", lambda self, lw: float(next(score)))
    summary = train(neus, None, progress=False)
    assert summary["stopped_by_time"] and not summary["stopped_by_plateau"]
