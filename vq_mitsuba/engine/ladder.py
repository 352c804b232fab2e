"""The learned envmap's rows over a fit: a ladder of rungs climbed as the encoding's frequencies
open, capped (envmap.final_height = auto) at the rung the fitted roughness resolves."""

from __future__ import annotations

from typing import Callable

import torch

from vq_mitsuba import messages
from vq_mitsuba.config import Config
from vq_mitsuba.engine import skips

ENVMAP_START_HEIGHT = 32  # rows of the learned envmap at the start of a fit


def envmap_ladder(cfg: Config) -> list[int]:
    """The learned envmap's rungs: envmap.height halved while it stays at least 32 rows."""
    ladder = [cfg.envmap.height]
    while ladder[0] % 2 == 0 and ladder[0] // 2 >= ENVMAP_START_HEIGHT:
        ladder.insert(0, ladder[0] // 2)
    return ladder


def envmap_height_at(cfg: Config, progress: float) -> int:
    """Rows of the learned envmap at this training progress: the ladder (`envmap_ladder`) climbed
    at even steps over the first field.pe_anneal share of training (the sharp light is fitted
    after the coarse light and materials, as the encoding's frequencies open)."""
    ladder = envmap_ladder(cfg)
    anneal = cfg.field.pe_anneal
    if anneal <= 0:
        return ladder[-1]
    return ladder[min(len(ladder) - 1, int(progress / anneal * len(ladder)))]


class EnvmapLadder:
    """The rung the learned envmap is at, with envmap.final_height = auto: no higher than the one
    the fitted roughness asks for, decided each time the ladder reaches a rung it has not reached
    before, and read again every `skips.ENVMAP_RECHECK_EVERY` steps while the ladder is above it,
    so a roughness that falls later still grows the light (the rung kept never goes down). A
    decision is recorded when the ladder reaches a rung or the rung grows."""

    def __init__(self, cfg: Config, auto: bool):
        self.cfg, self.auto = cfg, auto
        self.rungs = envmap_ladder(cfg)
        self.cap, self.decided, self.choices = self.rungs[0], 0, []

    def height(self, progress: float, step: int, roughness: Callable[[], torch.Tensor]) -> int:
        """Rows at `progress` and `step`; `roughness()`: the fitted roughness of fixed hits."""
        want = envmap_height_at(self.cfg, progress)
        if not self.auto:
            return want
        k = self.rungs.index(want)
        reached = k > self.decided
        if reached or (want > self.cap and step % skips.ENVMAP_RECHECK_EVERY == 0):
            self.decided = max(self.decided, k)
            rows, why = skips.envmap_rung(self.rungs, roughness())
            grows = rows > self.cap
            if rows < self.cap:
                why += f"; kept at {self.cap} rows (a rung reached is kept)"
            self.cap = max(self.cap, rows)
            if reached or grows:
                self.choices.append({"step": step, "ladder_rows": want, "rows": min(want, self.cap), "reason": why})
                messages.note(f"envmap: {min(want, self.cap)} rows at step {step} (the ladder's {want}): {why}")
        return min(want, self.cap)

    def decision(self, rows: int) -> dict:
        """fit.json's `decisions.envmap` for a learned envmap now at `rows`."""
        setting = self.cfg.envmap.final_height
        if not self.auto:
            reason = f"envmap.final_height = {setting}: the ladder's {self.rungs[-1]} rows"
        elif self.choices:
            reason = f"decided at step {self.choices[-1]['step']}: {self.choices[-1]['reason']}"
        else:
            reason = "the fit ended before the ladder grew"
        return {**skips.decision(setting, rows, reason), "ladder": list(self.rungs), "checks": list(self.choices)}

    def state_dict(self) -> dict:
        return {"cap": self.cap, "decided": self.decided, "choices": self.choices}

    def load_state_dict(self, state: dict) -> None:
        self.cap, self.decided, self.choices = int(state["cap"]), int(state["decided"]), list(state["choices"])
