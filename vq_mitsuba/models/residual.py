"""The view-dependent residual for novel views (VQ-NeRF, Sec. 4: "residual baking").

After the decomposition, what the physically based render of the capture cannot explain (effects
beyond one bounce, the BSDF model's mismatch, a light the envmap does not hold, texture finer than
the material network draws) is fitted by a surface light field r(x, wi) added to the render's
linear radiance:

    L(x, wi) = clamp(L_pbr(x, wi) + r(x, wi), 0)

It is tied to the capture's own light and materials: relighting, edited parts and exports leave
it out and stay physically based (`vq_mitsuba.render.views.Renderer`).

Inputs: a multiresolution hash encoding of the point (Mueller et al. 2022, "Instant neural
graphics primitives"), mapped to [0, 1]^3 by the mesh's bounding box, so that texture down to the
pixels' footprint can be held; real spherical harmonics of the view direction wi (degree 2) and
of its mirror direction about the shading normal up to degree 4 (where glossy reflections move as
the view changes: Verbin et al. 2022, "Ref-NeRF"); and n . wi. The output layer starts at zero,
so an untrained field adds nothing.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import nn

LEVELS = 12  # resolutions of the hash encoding, geometric from COARSEST to the finest cells a box side
FEATURES = 2  # features a level
LOG2_TABLE = 16  # entries a level: 2^16 (a level with fewer cells is indexed densely)
COARSEST, FINEST = 16, 512  # FINEST: the finest level's cells at most (`finest_for_hits` sets it)
HITS_PER_CELL = 8  # training hits the finest level's cells of the surface are meant to hold, at least
HIDDEN = 64  # width of the hidden layers
HIDDEN_LAYERS = 2
MIRROR_DEGREE = 4  # spherical-harmonic degree of the mirror direction
PRIMES = (1, 2654435761, 805459861)


def sh_basis(d: torch.Tensor, degree: int) -> torch.Tensor:
    """Real spherical harmonics Y_l^m, l <= degree (<= 4), of unit directions (N, 3):
    (N, (degree + 1)^2), orthonormal over the sphere."""
    x, y, z = d.unbind(-1)
    out = [torch.full_like(x, 0.28209479177387814)]
    if degree >= 1:
        out += [0.4886025119029199 * y, 0.4886025119029199 * z, 0.4886025119029199 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        out += [1.0925484305920792 * x * y, 1.0925484305920792 * y * z, 0.31539156525252005 * (3 * zz - 1),
                1.0925484305920792 * x * z, 0.5462742152960396 * (xx - yy)]
    if degree >= 3:
        out += [0.5900435899266435 * y * (3 * xx - yy), 2.890611442640554 * x * y * z,
                0.4570457994644658 * y * (5 * zz - 1), 0.3731763325901154 * z * (5 * zz - 3),
                0.4570457994644658 * x * (5 * zz - 1), 1.445305721320277 * z * (xx - yy),
                0.5900435899266435 * x * (xx - 3 * yy)]
    if degree >= 4:
        out += [2.5033429417967046 * x * y * (xx - yy), 1.7701307697799304 * y * z * (3 * xx - yy),
                0.9461746957575601 * x * y * (7 * zz - 1), 0.6690465435572892 * y * z * (7 * zz - 3),
                0.10578554691520431 * (35 * zz * zz - 30 * zz + 3), 0.6690465435572892 * x * z * (7 * zz - 3),
                0.47308734787878004 * (xx - yy) * (7 * zz - 1), 1.7701307697799304 * x * z * (xx - 3 * yy),
                0.6258357354491761 * (xx * (xx - 3 * yy) - yy * (3 * xx - yy))]
    if degree > 4:
        raise ValueError(f"spherical harmonics up to degree 4, not {degree}")
    return torch.stack(out, -1)


def finest_for_hits(hits: int) -> int:
    """The finest level's cells a box side for a field fitted on `hits` surface hits: about
    HITS_PER_CELL hits a cell on a surface as large as the box's cross-section, so that a cell
    averages the pixels (and the Monte Carlo noise of their targets) it holds instead of
    memorising one; between 2 COARSEST and FINEST."""
    return int(min(FINEST, max(2 * COARSEST, math.sqrt(max(hits, 0) / HITS_PER_CELL))))


class HashEncoding(nn.Module):
    """Multiresolution hash encoding of points in [0, 1]^3: (N, 3) -> (N, LEVELS * FEATURES),
    each level's features trilinearly interpolated from the 8 corners of the point's cell."""

    def __init__(self, levels: int = LEVELS, features: int = FEATURES, log2_table: int = LOG2_TABLE,
                 coarsest: int = COARSEST, finest: int = FINEST):
        super().__init__()
        growth = math.exp(math.log(finest / coarsest) / max(levels - 1, 1))
        res = [int(math.floor(coarsest * growth ** level + 1e-6)) for level in range(levels)]
        table = 1 << log2_table
        sizes = [min(table, (r + 1) ** 3) for r in res]
        offsets = np.concatenate([[0], np.cumsum(sizes)[:-1]])
        self.register_buffer("res", torch.tensor(res, dtype=torch.int64), persistent=False)
        self.register_buffer("sizes", torch.tensor(sizes, dtype=torch.int64), persistent=False)
        self.register_buffer("offsets", torch.tensor(offsets, dtype=torch.int64), persistent=False)
        self.register_buffer("dense", torch.tensor([(r + 1) ** 3 <= table for r in res]), persistent=False)
        corners = torch.tensor([[i >> 2 & 1, i >> 1 & 1, i & 1] for i in range(8)], dtype=torch.int64)
        self.register_buffer("corners", corners, persistent=False)
        self.register_buffer("primes", torch.tensor(PRIMES, dtype=torch.int64), persistent=False)
        self.table = nn.Parameter(torch.empty(int(sum(sizes)), features).uniform_(-1e-4, 1e-4))
        self.out_dim = levels * features

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = x.clamp(0.0, 1.0)
        scaled = x[:, None, :] * self.res[None, :, None].to(x.dtype)  # (N, L, 3)
        cell = torch.floor(scaled).to(torch.int64).minimum(self.res[None, :, None] - 1)
        frac = scaled - cell.to(x.dtype)
        c = cell[:, :, None, :] + self.corners[None, None]  # (N, L, 8, 3)
        side = (self.res + 1)[None, :, None]
        dense = c[..., 0] * side * side + c[..., 1] * side + c[..., 2]
        hashed = (c[..., 0] * self.primes[0]) ^ (c[..., 1] * self.primes[1]) ^ (c[..., 2] * self.primes[2])
        idx = torch.where(self.dense[None, :, None], dense, hashed) % self.sizes[None, :, None]
        idx = idx + self.offsets[None, :, None]
        # (N, L, 8, F); index_select, whose gradient adds in index order on a CPU (indexing's does not)
        feats = torch.index_select(self.table, 0, idx.reshape(-1)).view(*idx.shape, -1)
        w = torch.where(self.corners[None, None].bool(), frac[:, :, None, :], 1 - frac[:, :, None, :]).prod(-1)
        return (feats * w[..., None]).sum(2).flatten(1)


class ResidualField(nn.Module):
    """r(x, n, wi): linear RGB radiance (N, 3) added to the physically based render of the
    capture's own light; may be negative (the render can also be too bright)."""

    def __init__(self, bbox_min, bbox_max, scale: float = 1.0, finest: int = FINEST):
        super().__init__()
        bbox_min = torch.tensor(np.array(bbox_min, dtype=np.float32))
        bbox_max = torch.tensor(np.array(bbox_max, dtype=np.float32))
        self.register_buffer("center", 0.5 * (bbox_min + bbox_max))
        self.register_buffer("finest", torch.tensor(int(finest)))
        self.register_buffer("half_extent", (0.5 * (bbox_max - bbox_min).max() * 1.05).reshape(()))
        # The radiance scale of the capture (mean target): the network works at order one.
        self.register_buffer("scale", torch.tensor(float(scale)))
        self.encoding = HashEncoding(finest=int(finest))
        dims = [self.encoding.out_dim + 9 + (MIRROR_DEGREE + 1) ** 2 + 1] + [HIDDEN] * HIDDEN_LAYERS
        layers = []
        for a, b in zip(dims[:-1], dims[1:]):
            layers += [nn.Linear(a, b), nn.ReLU()]
        out = nn.Linear(dims[-1], 3)
        nn.init.zeros_(out.weight)
        nn.init.zeros_(out.bias)
        self.mlp = nn.Sequential(*layers, out)

    def forward(self, points: torch.Tensor, normals: torch.Tensor, wi: torch.Tensor) -> torch.Tensor:
        """points, normals (shading, facing the viewer), wi (unit, towards the viewer): (N, 3) world."""
        cos = torch.sum(normals * wi, -1, keepdim=True)
        mirror = 2 * cos * normals - wi
        x = 0.5 + 0.5 * (points - self.center) / self.half_extent
        features = torch.cat([self.encoding(x), sh_basis(wi, 2), sh_basis(mirror, MIRROR_DEGREE), cos], -1)
        return self.scale * self.mlp(features)


def add_residual(rgb_linear: torch.Tensor, residual: torch.Tensor) -> torch.Tensor:
    """The radiance with the residual: their sum, never negative."""
    return (rgb_linear + residual).clamp_min(0.0)
