"""What a fit skips for its scene: the rules that decide the bounce, the envmap's last rung, the
pace of the schedule (and so the step count) and which pixels the steps draw.

Each rule has one config key whose default, `auto`, lets the scene decide; the decision and its
reason go into fit.json (`decisions`) and the progress line.

- **Bounce** (`train.bounce`), at start-up: rays leave `BOUNCE_HITS` random training hits in
  cosine-distributed directions (`BOUNCE_RAYS` each) from their geometric normals; where under
  `BOUNCE_MIN_SHARE` of them meet the object, (almost) no surface sees another and the bounce is
  off (its light would be under about that share of the direct light).
- **Envmap** (`envmap.final_height`), where the learned envmap's ladder would grow: the sharpest
  lobe the fit needs, from the `ROUGHNESS_QUANTILE` quantile of the fitted roughness on fixed
  training hits; a GGX lobe of alpha = roughness^2 is about 2.6 alpha wide (its reflected
  directions' half-maximum width), and an envmap row of pi / H radians finer than
  `ROW_PER_ALPHA` alpha resolves what such a lobe reflects (less than 10 % of its detail lost at
  the map's Nyquist frequency). The ladder grows no higher than the first rung that fine. The
  roughness is read where the ladder reaches a rung, and again every `ENVMAP_RECHECK_EVERY` steps
  while the ladder is above the rung kept: a rung decided early is no ceiling for a roughness
  that falls later.
- **Pace** (`train.stop`): the schedule (learning-rate decay, prior decay, barrier, encoding
  frequencies, envmap ladder, discrete start) runs on schedule steps; each training step advances
  them by the pace (1 at first). Every `Pace.every` steps the loss of held-aside training pixels
  (never drawn for a step; shaded with the same samples each time) is measured. Once every stage
  of the schedule has begun (`Pace.start_share`: the encoding fully open, the envmap at its last
  rung, the barrier over, the discrete branch training; the bounce on), when the mean of the last
  `STOP_WINDOW` measurements is not `STOP_TOLERANCE` (relative) below the mean of the
  `STOP_WINDOW` before, the pace doubles (up to `MAX_PACE`): the rest of the schedule (the
  learning-rate and prior decay) runs faster instead of spending steps on a plateau. The fit ends
  when the schedule is done (the learning rate at its end), or at train.iterations steps.
- **Sampling** (`train.sampling`): `vq_mitsuba.data.pixels.ErrorSampler`, tiles of
  `sampler_tile` pixels, `SAMPLER_FLOOR` uniform share.
"""

from __future__ import annotations

import math

import numpy as np
import torch

BOUNCE_HITS = 4096  # training hits the bounce rule traces from
BOUNCE_RAYS = 8  # cosine-distributed rays from each
BOUNCE_MIN_SHARE = 0.01  # below this share of rays meeting the object, the bounce is off

ROUGHNESS_QUANTILE = 0.02  # the sharpest lobes: this quantile of the fitted roughness
ROUGHNESS_HITS = 4096  # fixed training hits it is read on
ROW_PER_ALPHA = 1.6  # an envmap row (pi / H radians) at most this many alpha resolves a lobe of alpha
ALPHA_MIN = 0.001  # Mitsuba's (and Cycles') smallest GGX alpha
ENVMAP_RECHECK_EVERY = 50  # steps between readings of the roughness while the ladder is above the rung kept

STOP_PIXELS = 2048  # held-aside pixels (at most STOP_PIXELS_SHARE of the pixels)
STOP_PIXELS_SHARE = 0.05
STOP_EVALS = 60  # measurements over train.iterations (every iterations / STOP_EVALS steps) ...
STOP_MIN_EVERY = 10  # ... but no more often than every this many steps
STOP_WINDOW = 3  # measurements averaged on each side of the comparison
STOP_TOLERANCE = 0.01
MAX_PACE = 8

SAMPLER_FLOOR = 0.3  # uniform share of the error-driven draws
SAMPLER_VISITS = 16  # draws per tile over a fit that the tile size aims at
SAMPLER_REFRESH = 10  # steps between recomputations of the draw distribution


def decision(setting: str, choice, reason: str) -> dict:
    return {"setting": setting, "choice": choice, "reason": reason}


# --- bounce --------------------------------------------------------------------------------------
def bounce_share(scene, position: torch.Tensor, wi: torch.Tensor, seed: int) -> tuple[float, int]:
    """(share of the secondary rays that meet the object, rays traced) from up to BOUNCE_HITS of
    the hits `position` / `wi`, BOUNCE_RAYS each."""
    gen = torch.Generator().manual_seed(seed)
    n = len(position)
    pick = torch.randperm(n, generator=gen)[:BOUNCE_HITS] if n > BOUNCE_HITS else torch.arange(n)
    pick = pick.repeat_interleave(BOUNCE_RAYS)
    u = torch.rand(2, len(pick), generator=gen, dtype=torch.float64).numpy()
    pos, w = position.cpu()[pick].numpy(), wi.cpu()[pick].numpy()
    valid, hit = scene.secondary_hits(pos, w, u)
    rays = int(valid.sum())
    return (float(hit.sum()) / rays if rays else 0.0), rays


def decide_bounce(setting: str, bounces: int, scene, position, wi, seed: int) -> tuple[bool, dict]:
    """(bounce on, its decision) for train.bounce = `setting`."""
    if bounces <= 0:
        return False, decision(setting, "off", "train.bounces = 0")
    if setting != "auto":
        return setting == "on", decision(setting, setting, f"train.bounce = {setting}")
    share, rays = bounce_share(scene, position, wi, seed)
    on = share >= BOUNCE_MIN_SHARE
    return on, decision(setting, "on" if on else "off",
                        f"{100 * share:.1f} % of {rays} secondary rays (cosine-distributed from the training hits) "
                        f"hit the object ({'at least' if on else 'under'} {100 * BOUNCE_MIN_SHARE:g} %)")


# --- envmap --------------------------------------------------------------------------------------
def rows_for_roughness(roughness: float) -> float:
    """Envmap rows that resolve a GGX lobe of this roughness (pi / (ROW_PER_ALPHA alpha))."""
    alpha = max(ALPHA_MIN, roughness * roughness)
    return math.pi / (ROW_PER_ALPHA * alpha)


def envmap_rung(ladder: list[int], roughness: torch.Tensor) -> tuple[int, str]:
    """(rows of the first rung of `ladder` that resolves the sharpest fitted lobes, the reason)."""
    r = float(torch.quantile(roughness.detach().float().cpu(), ROUGHNESS_QUANTILE))
    need = rows_for_roughness(r)
    rows = next((h for h in ladder if h >= need), ladder[-1])
    lobe = math.degrees(2.6 * max(ALPHA_MIN, r * r))
    return rows, (f"{100 * ROUGHNESS_QUANTILE:g} % roughness quantile {r:.3f}: lobes about {lobe:.1f} deg wide "
                  f"need {need:.0f} rows: the {rows}-row rung ({180 / rows:.1f} deg a row)")


# --- pace ----------------------------------------------------------------------------------------
class Pace:
    """Schedule steps against training steps: the pace doubles each time the held-aside loss
    stops improving (see the module's docstring). Without measurements (train.stop =
    iterations) schedule steps are training steps."""

    def __init__(self, iterations: int, active: bool, start_share: float = 0.0):
        self.iterations, self.active = int(iterations), bool(active)
        self.start_share = float(start_share)
        self.every = max(STOP_MIN_EVERY, round(iterations / STOP_EVALS))
        self.position = 0.0  # schedule steps done
        self.rate = 1
        self.window: list[float] = []  # losses measured since the stages began (or the last speed-up)
        self.evals: list[list[float]] = []  # [step, loss]
        self.speedups: list[list[int]] = []  # [step, new pace]

    def share(self) -> float:
        return min(self.position / self.iterations, 1.0)

    @property
    def finished(self) -> bool:
        return self.position >= self.iterations

    def advance(self) -> None:
        self.position += self.rate

    def due(self, step: int) -> bool:
        return self.active and step % self.every == 0

    def new_phase(self) -> None:
        """A stage that changes the loss began (the discrete branch, the bounce): its plateau is
        measured from here."""
        self.window = []

    def observe(self, step: int, loss: float) -> bool:
        """Take the held-aside loss at `step`; True when the pace doubled."""
        self.evals.append([step, loss])
        if not math.isfinite(loss) or self.share() < self.start_share:
            return False
        self.window.append(loss)
        w = STOP_WINDOW
        if len(self.window) < 2 * w or self.rate >= MAX_PACE:
            return False
        recent, before = sum(self.window[-w:]) / w, sum(self.window[-2 * w:-w]) / w
        if recent < before * (1 - STOP_TOLERANCE):
            return False
        self.rate *= 2
        self.window = []
        self.speedups.append([step, self.rate])
        return True

    def state_dict(self) -> dict:
        """The pace's state (JSON-safe)."""
        return {"position": self.position, "rate": self.rate, "every": self.every, "start_share": self.start_share,
                "window": list(self.window),
                "evals": [[s, v if math.isfinite(v) else None] for s, v in self.evals], "speedups": self.speedups}

    def load_state_dict(self, state: dict) -> None:
        self.position, self.rate = float(state["position"]), int(state["rate"])
        self.window = [float(v) for v in state.get("window", [])]
        self.evals, self.speedups = [list(e) for e in state["evals"]], [list(s) for s in state["speedups"]]

    def decision(self, setting: str, step: int, held_pixels: int) -> dict:
        if not self.active:
            return decision(setting, "iterations", f"train.stop = {setting}: {step} of {self.iterations} steps")
        measured = (f"the loss of {held_pixels} held-aside pixels, measured every {self.every} steps, its mean over "
                    f"{STOP_WINDOW} measurements under {100 * STOP_TOLERANCE:g} % below the {STOP_WINDOW} before "
                    f"(from {100 * self.start_share:.0f} % of the schedule)")
        if not self.speedups:
            return decision(setting, "iterations", f"all {step} steps: {measured} never happened")
        sped = ", ".join(f"{r}x from step {s}" for s, r in self.speedups)
        end = (f"schedule done at step {step} of {self.iterations}" if self.finished and step < self.iterations
               else f"{step} of {self.iterations} steps")
        return decision(setting, "early" if step < self.iterations else "iterations",
                        f"{end}: {measured} sped the schedule up ({sped})")


def stop_pixels(n_pixels: int) -> int:
    return max(1, min(STOP_PIXELS, int(STOP_PIXELS_SHARE * n_pixels)))


def np_seed(seed: int, salt: int) -> int:
    """A seed of its own for one rule (the fit's seed and a fixed salt)."""
    return int(np.random.SeedSequence([seed, salt]).generate_state(1)[0])
