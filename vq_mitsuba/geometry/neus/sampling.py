"""Where a NeuS step draws its rays: a share in proportion to a running error map over tiles of
pixels, the rest uniformly, each ray weighted by 1 / (N q) so that the weighted loss is an
unbiased estimate of the mean over every training ray (q: the ray's probability under the
mixture; the uniform share bounds the weight by 1 / (1 - share)). A few rays are held aside from
training: the plateau check renders them (`NeuSTraining`)."""

from __future__ import annotations

import torch

# The error map's decay: a visited tile's value moves this far towards the batch's error there.
ERROR_RATE = 0.3
# An unvisited tile's error: above any L1 error of sRGB colours in [0, 1] plus a mask term, so that
# the error draws visit every tile once before they follow the map.
UNSEEN_ERROR = 2.0


class RaySampler:
    """Training rays drawn from `tiles` (N,) int64 (each ray's tile of pixels, `rays.pixel_tiles`),
    `share` of each batch by the error map; `held_aside` rays (a random, fixed set) are never drawn."""

    def __init__(self, tiles: torch.Tensor, share: float, held_aside: int, generator: torch.Generator):
        n, device = len(tiles), tiles.device
        self.share = float(share)
        self.gen = generator
        held = min(int(held_aside), n // 10)
        perm = torch.randperm(n, generator=generator, device=device)
        self.held = perm[:held].sort().values
        self.train = perm[held:].sort().values  # the rays a step draws
        self.n = len(self.train)
        cells, inverse = torch.unique(tiles[self.train], return_inverse=True)
        self.tile_of = inverse  # each training ray's compact tile (index into the map)
        order = torch.argsort(inverse, stable=True)
        self.by_tile = self.train[order]  # training rays grouped by tile
        self.count = torch.bincount(inverse, minlength=len(cells))
        self.start = torch.cumsum(self.count, 0) - self.count
        self.error = torch.full((len(cells),), UNSEEN_ERROR, device=device)
        self.seen = torch.zeros(len(cells), dtype=torch.bool, device=device)
        self._pos = torch.empty(0, dtype=torch.long, device=device)  # index into self.train of the last draw

    @property
    def tiles(self) -> int:
        return len(self.error)

    def draw(self, batch: int) -> tuple[torch.Tensor, torch.Tensor | None]:
        """(ray indices (batch,), importance weights (batch,) or None when every ray is uniform)."""
        device = self.train.device
        n_err = int(round(batch * self.share))
        if n_err <= 0:
            pos = torch.randint(0, self.n, (batch,), generator=self.gen, device=device)
            self._pos = pos
            return self.train[pos], None
        tile = torch.multinomial(self.error, n_err, replacement=True, generator=self.gen)
        u = torch.rand(n_err, generator=self.gen, device=device)
        within = (u * self.count[tile]).long().clamp(max=self.count[tile] - 1)
        rays_err = self.by_tile[self.start[tile] + within]
        pos_uni = torch.randint(0, self.n, (batch - n_err,), generator=self.gen, device=device)
        idx = torch.cat([rays_err, self.train[pos_uni]])
        tiles = torch.cat([tile, self.tile_of[pos_uni]])
        self._tiles = tiles
        p_err = self.error[tiles] / self.error.sum() / self.count[tiles]
        q = (1.0 - self.share) / self.n + self.share * p_err
        return idx, 1.0 / (self.n * q)

    def tiles_of_last(self) -> torch.Tensor:
        return self._tiles if self.share > 0 else self.tile_of[self._pos]

    @torch.no_grad()
    def update(self, ray_error: torch.Tensor) -> None:
        """Move the error of the tiles the last batch visited towards its rays' mean error there."""
        if self.share <= 0:
            return
        tiles = self._tiles
        total = torch.zeros_like(self.error).index_add_(0, tiles, ray_error.float())
        hits = torch.zeros_like(self.error).index_add_(0, tiles, torch.ones_like(ray_error, dtype=torch.float32))
        visited = hits > 0
        mean = total / hits.clamp(min=1.0)
        rate = torch.where(self.seen, ERROR_RATE, 1.0)  # a first visit sets the tile's error
        self.error = torch.where(visited, self.error + rate * (mean - self.error), self.error).clamp_(min=1e-4)
        self.seen |= visited

    def state_dict(self) -> dict:
        return {"error": self.error.cpu(), "seen": self.seen.cpu()}

    def load_state_dict(self, state: dict | None) -> None:
        if state is not None and state["error"].shape == self.error.shape:
            self.error.copy_(state["error"].to(self.error.device))
            self.seen.copy_(state["seen"].to(self.seen.device))
