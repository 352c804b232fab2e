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

from vq_mitsuba.engine import skips

FLOOR_BAND = 0.02  # roughness within this of field.roughness_min counts as at the floor
METAL = 0.5  # metallic above this: a surface whose look is its specular lobe alone
MIN_SHARE = 0.01  # share of the fixed hits flagged that starts a trial
TRIAL_SHARE = 0.1  # the copy's steps, as a share of train.iterations
PULL_WEIGHT = 1.0  # weight of the pull (squared shortfall of the roughness below the glossy value)
CHUNK = 1 << 16  # hits a flag pass evaluates at once


def glossy_roughness(rows: int) -> float:
    """The roughness whose lobe an envmap of `rows` rows just resolves (inverse of
    `skips.rows_for_roughness`)."""
    return math.sqrt(math.pi / (skips.ROW_PER_ALPHA * rows))


def flag(out: dict, floor: float) -> torch.Tensor:
    """(N,) bool of the field's outputs `out`: a metal at the roughness floor."""
    return (out["roughness"].detach() < floor + FLOOR_BAND) & (out["metallic"].detach() > METAL)


@torch.no_grad()
def flag_hits(model, positions: torch.Tensor, floor: float) -> torch.Tensor:
    """`flag` of the material field at every position, in chunks."""
    return torch.cat([flag(model(positions[i:i + CHUNK]), floor) for i in range(0, len(positions), CHUNK)])


def pull_term(roughness: torch.Tensor, flags: torch.Tensor, glossy: float) -> torch.Tensor:
    """Mean squared shortfall below `glossy` of the flagged hits' roughness (0 without any)."""
    if not bool(flags.any()):
        return roughness.sum() * 0.0
    return torch.relu(glossy - roughness[flags]).square().mean()


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
