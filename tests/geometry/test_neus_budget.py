"""How long NeuS trains: its time budget, and the held-aside rays' plateau that ends training after a
final decay."""

from __future__ import annotations

import numpy as np
import torch

from vq_mitsuba.geometry.neus import neus_for, train
from vq_mitsuba.geometry.neus.sampling import RaySampler
from vq_mitsuba.geometry.neus.training import NeuSTraining, lr_factor

from test_geometry import sphere_capture, small_cfg


def test_held_aside_rays_are_never_drawn_and_without_them_the_draws_are_plain():
    sampler = RaySampler(2000, 100, torch.Generator().manual_seed(0), "cpu")
    assert len(sampler.held) == 100 and sampler.n == 1900
    drawn = torch.cat([sampler.draw(512) for _ in range(50)])
    assert not np.isin(drawn.numpy(), sampler.held.numpy()).any()
    assert len(torch.unique(drawn)) > 1800  # the others all come up
    assert len(RaySampler(50, 100, torch.Generator(), "cpu").held) == 5  # at most a tenth
    plain = RaySampler(2000, 0, torch.Generator().manual_seed(3), "cpu").draw(64)
    assert torch.equal(plain, torch.randint(0, 2000, (64,), generator=torch.Generator().manual_seed(3)))


def test_a_flat_held_aside_score_ends_training_after_a_final_decay(monkeypatch):
    capture = sphere_capture(n_views=6, size=16)
    # a plateau window long enough that the final decay spans many steps on a slow machine
    cfg = small_cfg(iterations=0, time_limit_s=60, plateau_s=2.0, coarse_to_fine=0.0)
    neus = neus_for(capture, cfg)
    monkeypatch.setattr(NeuSTraining, "held_aside_psnr", lambda self, lw: 20.0)
    rates = []
    step = NeuSTraining.loop_step

    def spy(self, p):
        out = step(self, p)
        rates.append(self.optim.param_groups[0]["lr"] / self.optim.param_groups[0]["base_lr"])
        return out

    monkeypatch.setattr(NeuSTraining, "loop_step", spy)
    summary = train(neus, None)
    assert summary["stopped_by_plateau"] and not summary["stopped_by_time"]
    assert summary["train_seconds"] < 20
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
    summary = train(neus, None)
    assert summary["stopped_by_time"] and not summary["stopped_by_plateau"]
