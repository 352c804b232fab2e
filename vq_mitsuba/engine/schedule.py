"""Per-step schedules of a fit: training progress, learning rate, metallic barrier, discrete start
(the loss weights that decay follow `progress`: `vq_mitsuba.models.losses.weight_of`)."""

from __future__ import annotations

from dataclasses import dataclass

from vq_mitsuba.config import Config
from vq_mitsuba.run.loop import Progress


@dataclass(frozen=True)
class StepSchedule:
    done: float  # share of train.iterations done
    progress: float  # training progress in [0, 1]: `done`, or under a time limit the share of time used if larger
    lr_factor: float  # learning-rate multiplier (exponential decay with `done`)
    metallic_barrier: bool  # the metallic prior is -log(1 - metallic) (else the paper's linear term)
    discrete: bool  # the discrete branch trains (after its warm-up)


def schedule_at(cfg: Config, p: Progress) -> StepSchedule:
    """The schedule of the step at `p` (the loop's step and time shares).

    The encoding frequencies, the loss weights' decay and the discrete warm-up follow the larger share,
    so a fit stopped by train.time_limit_s has run its whole schedule; the learning rate follows the
    step share alone, so a short budget's few steps keep a large rate.
    """
    done, progress = p.step_share, p.share
    return StepSchedule(
        done=done,
        progress=progress,
        lr_factor=cfg.train.lr_end_exponential ** done,
        metallic_barrier=progress < cfg.loss.metallic_barrier_until,
        discrete=cfg.vq.enabled and progress >= cfg.vq.warmup_frac,
    )
