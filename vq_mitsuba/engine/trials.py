"""Choosing between two explanations on held-aside evidence (`train.trials`).

Under a learned light a sharp metal's highlights have two explanations: a glossy lobe under a
sharp light, or a mirror under a blurrier one. A fit keeps whichever it falls into first, and
which it falls into depends on the seed: the same metal fits at its roughness floor on one seed
and glossy on another. Once every stage of the schedule has begun (`Pace.start_share`: the
encoding open, the envmap's ladder at its top, the barrier over, the discrete branch training),
the fitted roughness and metallic are read on fixed training hits; metals (metallic above
`METAL`: a surface whose look is its specular lobe alone) at the roughness floor (within
`FLOOR_BAND` of field.roughness_min) are flagged. When at least `MIN_SHARE` of the hits are, the
fit is copied and the copy trains `TRIAL_SHARE` of train.iterations steps with the flagged
surfaces pulled up to a glossy lobe (`glossy_roughness`: the one the envmap's first rung resolves,
the blur put in the surface instead of the light) for the first half of its steps, then free;
the fit itself trains as many steps, from the same state and the same random draws. Whichever
has the lower loss on the held-aside pixels (never drawn for a step, shaded with the same samples
each time) goes on; the other is dropped. The copy's steps are the trial's whole cost; a fit
without such surfaces pays for one reading of the fields. Each trial, its evidence and its
choice go into fit.json (`decisions.trials`).

Only the floor is tried. Glossy metals tried at the floor as well chose the mirror on balls'
silver (true roughness 0.15) and cost its relighting; dielectrics are left alone (polished's
glossy plastic, pulled rougher, settled as a matte one); `benchmarks/results/trials/`.
"""

from __future__ import annotations

import copy
import math

import torch

from vq_mitsuba import brdf, messages
from vq_mitsuba.engine import skips
from vq_mitsuba.engine.ladder import ENVMAP_START_HEIGHT
from vq_mitsuba.engine.schedule import schedule_at
from vq_mitsuba.run.loop import Progress

FLOOR_BAND = 0.02  # roughness within this of field.roughness_min counts as at the floor
METAL = 0.5  # metallic above this: a surface whose look is its specular lobe alone
MIN_SHARE = 0.01  # share of the fixed hits flagged that starts a trial
TRIAL_SHARE = 0.1  # the copy's steps, as a share of train.iterations
CHUNK = 1 << 16  # hits a flag pass evaluates at once


def glossy_roughness(rows: int) -> float:
    """The roughness whose lobe an envmap of `rows` rows just resolves (inverse of
    `skips.rows_for_roughness`)."""
    return math.sqrt(math.pi / (skips.ROW_PER_ALPHA * rows))


def flag(out: dict, floor: float) -> torch.Tensor:
    """(N,) bool of the field's outputs `out`: a metal at the roughness floor."""
    return (out[brdf.ROUGHNESS].detach() < floor + FLOOR_BAND) & (out[brdf.METALLIC].detach() > METAL)


@torch.no_grad()
def flag_hits(model, positions: torch.Tensor, floor: float) -> torch.Tensor:
    """`flag` of the material field at every position, in chunks."""
    return torch.cat([flag(model(positions[i:i + CHUNK]), floor) for i in range(0, len(positions), CHUNK)])


def pull_term(roughness: torch.Tensor, flags: torch.Tensor, glossy: float) -> torch.Tensor:
    """Mean squared shortfall below `glossy` of the flagged hits' roughness (0 without any)."""
    if not bool(flags.any()):
        return roughness.sum() * 0.0
    return torch.relu(glossy - roughness[flags]).square().mean()


class Trials:
    """The trial of one fit: its check once every stage of the schedule has begun, the copy's
    steps, and the choice when the fit has trained as many; it drives the trainer through its
    steps, its held-aside loss and its checkpoint state."""

    def __init__(self, trainer, setting: str, decision: dict):
        """`decision`: fit.json's `decisions.trials` until the trial decides."""
        self.trainer, self.setting, self.decision = trainer, setting, decision
        self.checked, self.pending = False, None  # pending: the copy kept aside until the choice

    def after_step(self, p: Progress) -> None:
        """After a step: the choice when the trial's steps are done, or its check once every stage
        of the schedule has begun."""
        trainer = self.trainer
        if self.pending is not None:
            if trainer.step >= self.pending["until"]:
                self.finish()
        elif not self.checked and trainer.pace.share() >= trainer.pace.start_share:
            self.checked = True
            self.start(p)

    def start(self, p: Progress) -> None:
        """Flag the metals at the roughness floor on the fixed hits; where enough are flagged, train
        a copy of the fit with them pulled glossier, measure it on the held-aside pixels and keep it
        aside while the fit itself trains as many steps."""
        trainer = self.trainer
        cfg, model, pool = trainer.cfg, trainer.model, trainer.data.pool
        floor, glossy = cfg.field.roughness_min, glossy_roughness(ENVMAP_START_HEIGHT)
        probe_idx = trainer.fixed_hits
        with torch.no_grad():
            fixed = flag(model.field(pool.position[probe_idx]), floor)
        share = float(fixed.float().mean())
        seen = (f"{100 * share:.1f} % of {len(probe_idx)} fixed training hits at step {trainer.step} metal (metallic "
                f"> {METAL:g}) within {FLOOR_BAND:g} of the roughness floor {floor:g}")
        if share < MIN_SHARE:
            self.decision = skips.decision(self.setting, "none", f"{seen} (a trial from {100 * MIN_SHARE:g} %)")
            return
        flags = flag_hits(model.field, pool.position, floor)
        probe = probe_idx[fixed]  # the fixed hits flagged, read again at the choice
        steps = max(2, round(TRIAL_SHARE * cfg.train.iterations))
        messages.note(f"trial: {seen}; a copy of the fit tries them at roughness >= {glossy:.2f} for {steps} steps")
        start = copy_fit(trainer)
        model.pull = (flags.to(trainer.device), glossy)
        for i in range(steps):
            if i == steps // 2:
                model.pull = None  # the second half free: the copy settles where the images want it
            trainer.train_step(schedule_at(cfg, Progress(trainer.step, p.seconds, trainer.pace.share(),
                                                         p.time_share)))
            trainer.pace.advance()
        model.pull = None
        record = {"step": int(start["step"]), "steps": steps, "share_at_floor": share, "glossy": glossy,
                  "hits_flagged": int(flags.sum()), "held_loss_copy": trainer.held_loss(),
                  "roughness_copy": median_roughness(model, pool, probe)}
        until, copied = trainer.step, copy_fit(trainer)
        restore_fit(trainer, start)
        self.pending = {"until": until, "copy": copied, "record": record, "probe": probe}

    def finish(self) -> None:
        """Keep whichever of the fit and its copy has the lower held-aside loss."""
        trainer, pending = self.trainer, self.pending
        record = pending["record"]
        record["held_loss_fit"] = trainer.held_loss()
        record["roughness_fit"] = median_roughness(trainer.model, trainer.data.pool, pending["probe"])
        keep_copy = record["held_loss_copy"] < record["held_loss_fit"]
        if keep_copy:
            restore_fit(trainer, pending["copy"])
        fmt = lambda r: "none" if r is None else f"{r:.3f}"  # noqa: E731
        reason = (f"at step {record['step']}, {100 * record['share_at_floor']:.1f} % of the fixed hits metal at the "
                  f"roughness floor; after {record['steps']} steps the held-aside loss is "
                  f"{record['held_loss_copy']:.5g} for the copy pulled to >= {record['glossy']:.2f} (median roughness "
                  f"{fmt(record['roughness_copy'])}) against {record['held_loss_fit']:.5g} for the fit "
                  f"({fmt(record['roughness_fit'])}): " + ("the copy goes on" if keep_copy else "the fit goes on"))
        self.decision = {**skips.decision(self.setting, "swapped" if keep_copy else "kept", reason),
                         "trials": [record]}
        messages.note(f"trial: {reason}")
        self.pending = None

    def state_dict(self) -> dict:
        return {"checked": self.checked, "pending": self.pending}

    def load_state_dict(self, state: dict | None, decision: dict | None) -> None:
        state = state or {"checked": False, "pending": None}
        self.checked, self.pending = bool(state["checked"]), state["pending"]
        if decision is not None:
            self.decision = decision


def median_roughness(model, pool, idx: torch.Tensor) -> float | None:
    """Median fitted roughness of the training hits `idx` (None without any)."""
    if len(idx) == 0:
        return None
    return float(model.roughness(pool.position[idx.to(pool.position.device)]).median())


def copy_fit(trainer) -> dict:
    """Everything a step changes, copied: the trainer's checkpoint (`Trainer.training_state`:
    networks, light, optimiser, batch generator, the rules' state, the step) and torch's global
    generator (the codebook's dead codes are re-seeded from it)."""
    return {**copy.deepcopy(trainer.training_state(trainer.elapsed_before)), "torch_rng": torch.get_rng_state()}


def restore_fit(trainer, parts: dict) -> None:
    """Put the trainer back to `parts` (`copy_fit`) as a resume from it would, but for the loss
    curve and the clock, which go on."""
    history, elapsed = trainer.history, trainer.elapsed_before
    trainer.resume(parts)
    trainer.history, trainer.elapsed_before = history, elapsed
    torch.set_rng_state(parts["torch_rng"].cpu())
