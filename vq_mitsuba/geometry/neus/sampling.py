"""Which training rays a NeuS step may draw: every ray but a few held aside, drawn uniformly; the
plateau check renders the held-aside rays (`NeuSTraining.check_plateau`)."""

from __future__ import annotations

import torch


class RaySampler:
    """`count` training rays; `held_aside` of them (a random, fixed set, at most a tenth) are never
    drawn."""

    def __init__(self, count: int, held_aside: int, generator: torch.Generator, device):
        self.gen = generator
        held = min(int(held_aside), count // 10)
        self.held, self.train = torch.zeros(0, dtype=torch.long, device=device), None  # None: every ray
        if held:  # (without, the draws are those of a generator that did nothing else)
            perm = torch.randperm(count, generator=generator, device=device)
            self.held, self.train = perm[:held].sort().values, perm[held:].sort().values
        self.n = count - held

    def draw(self, batch: int) -> torch.Tensor:
        """Ray indices (batch,), uniform over the rays not held aside."""
        pos = torch.randint(0, self.n, (batch,), generator=self.gen, device=self.gen.device)
        return pos if self.train is None else self.train[pos]
