"""The view-dependent residual for novel views (VQ-NeRF, Sec. 4: "residual baking").

After the decomposition, what the physically based render of the capture cannot explain (effects
beyond one bounce, the BSDF model's mismatch, a light the envmap does not hold) is fitted by a
small field r(x, wi) added to the render's linear radiance:

    L(x, wi) = clamp(L_pbr(x, wi) + r(x, wi), 0)

It is tied to the capture's own light and materials: relighting, edited parts and exports leave
it out and stay physically based (`vq_mitsuba.render.views.Renderer`).

Inputs: the positional encoding of the point mapped to [-1, 1]^3 by the mesh's bounding box,
real spherical harmonics up to degree 2 of the view direction wi and of its mirror direction
about the shading normal (where glossy reflections move as the view changes), and n . wi. The
output layer starts at zero, so an untrained field adds nothing.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from vq_mitsuba.models.fields import PositionalEncoding

PE_FREQS = 6  # positional-encoding frequencies of the point
HIDDEN = 64  # width of the hidden layers
HIDDEN_LAYERS = 2


def sh_degree2(d: torch.Tensor) -> torch.Tensor:
    """Real spherical harmonics Y_l^m, l <= 2, of unit directions (N, 3): (N, 9)."""
    x, y, z = d.unbind(-1)
    return torch.stack([torch.full_like(x, 0.28209479), 0.48860251 * y, 0.48860251 * z, 0.48860251 * x,
                        1.09254843 * x * y, 1.09254843 * y * z, 0.31539157 * (3 * z * z - 1),
                        1.09254843 * x * z, 0.54627421 * (x * x - y * y)], -1)


class ResidualField(nn.Module):
    """r(x, n, wi): linear RGB radiance (N, 3) added to the physically based render of the
    capture's own light; may be negative (the render can also be too bright)."""

    def __init__(self, bbox_min, bbox_max, scale: float = 1.0):
        super().__init__()
        bbox_min = torch.tensor(np.array(bbox_min, dtype=np.float32))
        bbox_max = torch.tensor(np.array(bbox_max, dtype=np.float32))
        self.register_buffer("center", 0.5 * (bbox_min + bbox_max))
        self.register_buffer("half_extent", (0.5 * (bbox_max - bbox_min).max() * 1.05).reshape(()))
        # The radiance scale of the capture (mean target): the network works at order one.
        self.register_buffer("scale", torch.tensor(float(scale)))
        self.pe = PositionalEncoding(PE_FREQS)
        dims = [self.pe.out_dim + 9 + 9 + 1] + [HIDDEN] * HIDDEN_LAYERS
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
        x = (points - self.center) / self.half_extent
        features = torch.cat([self.pe(x), sh_degree2(wi), sh_degree2(mirror), cos], -1)
        return self.scale * self.mlp(features)


def add_residual(rgb_linear: torch.Tensor, residual: torch.Tensor) -> torch.Tensor:
    """The radiance with the residual: their sum, never negative."""
    return (rgb_linear + residual).clamp_min(0.0)
