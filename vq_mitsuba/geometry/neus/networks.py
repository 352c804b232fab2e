"""What NeuS is: the multi-resolution feature grid, the SDF network (with its gradient in closed form),
the colour and background networks, and the grid sizes a capture chooses from (`rays.choose_grid`)."""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from vq_mitsuba.config import NeuSConfig
from vq_mitsuba.geometry.neus import grid_kernel


INIT_RADIUS, INIT_RADIUS_WITHOUT_MASKS = 0.6, 0.3  # the sphere initialisation when neus.init_radius is 0


# The feature grid, when neus.levels / neus.max_res are 0 (auto). With masks: 5 levels to 128 points
# a side while the working box spans at most FINE_GRID_FROM_PX pixels in the median view (the 200 px
# synthetic captures: on tabletop better normals and materials than 4 levels to 64, in less time than
# that grid took before the closed-form gradient; benchmarks/results/tabletop_stages/), else finer
# levels up to 512 (photographed captures; benchmarks/results/neus_dtu/); levels beyond
# 2^neus.hash_log2 points are hashed. Without masks the coarse grid stays: the background model
# shares the steps, and the fine grid fitted DTU scan37's photos worse in the same time
# (benchmarks/results/dtu_photos/).
COARSE_GRID = (4, 64)  # (levels, max_res)
MASKED_GRID = (5, 128)
FINE_GRID = (8, 512)
FINE_GRID_FROM_PX = 256
# Hidden layers of the SDF MLP when neus.sdf_layers is 0 (auto): one with the fine grid, whose
# photographs see each training ray about once (on DTU scan24 and scan37 it renders them as well or
# better at 1.23x the steps a second), two otherwise (the synthetic captures, seen several times
# over: on tabletop one layer gave worse normals at equal steps and equal ones at equal time;
# benchmarks/results/neus_step/).
SDF_LAYERS_FINE, SDF_LAYERS = 1, 2
# Share of training over which the finer grid levels fade in when neus.coarse_to_fine is -1 (auto):
# none with the fine grid, whose photographs NeuS sees about once (every level from the first step
# rendered DTU scan24's and scan37's held-out photos better in the same 480 s), 0.3 otherwise (the
# synthetic captures' grid, where it was chosen; benchmarks/results/neus_converges/).
COARSE_TO_FINE_FINE, COARSE_TO_FINE = 0.0, 0.3


def corner_weights(f: torch.Tensor, du_dp: torch.Tensor | None = None) -> torch.Tensor:
    """Trilinear weights of a cell's 8 corners (ordered dx, dy, dz, dz fastest) from the fractions
    f (..., 3) within the cell: (..., 8, 1); given du/dp (..., 3), the cell units per box unit (0 on
    an axis where the lookup is clamped to the grid), also their gradients in the point:
    (..., 8, 4), [..., 0] the weight and [..., 1:] its gradient."""
    w = torch.stack([1.0 - f, f], -1)  # (..., 3, 2): per axis, the weight of the lower / upper corner

    def outer(a, b, c):
        return (a[..., :, None, None] * b[..., None, :, None] * c[..., None, None, :]).flatten(-3)

    wx, wy, wz = w.unbind(-2)
    if du_dp is None:
        return outer(wx, wy, wz)[..., None]
    dw = torch.stack([-du_dp, du_dp], -1)
    return torch.stack([outer(wx, wy, wz), outer(dw[..., 0, :], wy, wz), outer(wx, dw[..., 1, :], wz),
                        outer(wx, wy, dw[..., 2, :])], -1)


def _cell(p: torch.Tensor, res: torch.Tensor | float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """For a grid of `res` points per axis at the cell centres of [-1, 1]^3: each point's lower
    corner (long), its fractions in the cell (differentiable in p) and du/dp (0 where it is clamped
    to the grid)."""
    x = (p + 1.0) * (0.5 * res) - 0.5
    if not torch.is_tensor(res):
        res = torch.tensor(res, dtype=p.dtype, device=p.device)
    u = torch.minimum(x.clamp(min=0.0), res - 1.0)
    i0 = torch.minimum(u.floor(), res - 2.0)
    du_dp = ((x > 0.0) & (x < res - 1.0)).to(p.dtype) * (0.5 * res)
    return i0.long(), u - i0, du_dp


def trilinear(grid: torch.Tensor, res: int, p: torch.Tensor, gradient: bool = False):
    """Trilinear lookup of a (res^3, C) grid of values at cell centres of [-1, 1]^3, at points (N, 3),
    and with `gradient` also its gradient in the points (N, C, 3)."""
    i0, f, du_dp = _cell(p, float(res))
    base = (i0[:, 0] * res + i0[:, 1]) * res + i0[:, 2]
    offs = torch.tensor([dx * res * res + dy * res + dz for dx in (0, 1) for dy in (0, 1) for dz in (0, 1)],
                        device=p.device)
    vals = grid.index_select(0, (base[:, None] + offs).reshape(-1)).view(len(p), 8, -1)
    w = corner_weights(f, du_dp if gradient else None)
    out = (vals[..., None] * w[:, :, None, :]).sum(1)  # (N, C, 1 or 4)
    return (out[..., 0], out[..., 1:]) if gradient else out[..., 0]


# Instant-NGP's spatial hash: each integer coordinate times its own large prime, XOR-ed.
HASH_PRIMES = (1, 2654435761, 805459861)


class DenseGrid(nn.Module):
    """Multi-resolution feature grids (resolutions geometric from base_res to max_res), all levels
    stored in one table and looked up with one gather (few, large tensor ops: fast on a CPU). A
    level with more than 2^hash_log2 points keeps 2^hash_log2 entries, indexed by a spatial hash of
    the point (Instant-NGP); coarser levels are dense."""

    def __init__(self, levels: int, base_res: int, max_res: int, features: int, hash_log2: int = 0):
        super().__init__()
        growth = (max_res / base_res) ** (1.0 / max(levels - 1, 1))
        self.res = [int(round(base_res * growth ** level)) for level in range(levels)]
        self.features = features
        cap = 2 ** hash_log2 if hash_log2 > 0 else None
        hashed = [cap is not None and r ** 3 > cap for r in self.res]
        sizes = [cap if h else r ** 3 for r, h in zip(self.res, hashed)]
        offsets = np.cumsum([0] + sizes)
        # Built on the CPU (the same initial table on every device); `.to(device)` moves the module.
        self.table = nn.Parameter(torch.empty(int(offsets[-1]), features, device="cpu").uniform_(-1e-4, 1e-4))
        r = torch.tensor(self.res, dtype=torch.long, device="cpu")
        self.register_buffer("res_l", r, persistent=False)
        self.register_buffer("offsets", torch.tensor(offsets[:-1], dtype=torch.long, device="cpu"), persistent=False)
        corners = torch.tensor([[dx, dy, dz] for dx in (0, 1) for dy in (0, 1) for dz in (0, 1)], device="cpu")
        self.register_buffer("corners", corners, persistent=False)
        self.register_buffer("corner_offs", (corners[None, :, 0] * r[:, None] ** 2 + corners[None, :, 1] * r[:, None]
                                             + corners[None, :, 2]), persistent=False)  # (L, 8)
        self.hashed = hashed
        self.register_buffer("hashed_l", torch.tensor(hashed, device="cpu"), persistent=False)
        self.hash_mask = (cap or 1) - 1
        self.layout = grid_kernel.Layout(self.res, [int(o) for o in offsets[:-1]], hashed, self.hash_mask)

    def _indices(self, i0: torch.Tensor) -> torch.Tensor:
        """Table rows (N, L, 8) of the 8 corners of each point's cell at each level."""
        r = self.res_l[None, :]
        dense = ((i0[..., 0] * r + i0[..., 1]) * r + i0[..., 2])[..., None] + self.corner_offs[None]
        if any(self.hashed):
            c = i0[:, :, None, :] + self.corners[None, None]  # (N, L, 8, 3)
            h = (c[..., 0] * HASH_PRIMES[0]) ^ (c[..., 1] * HASH_PRIMES[1]) ^ (c[..., 2] * HASH_PRIMES[2])
            dense = torch.where(self.hashed_l[None, :, None], h & self.hash_mask, dense)
        return self.offsets[None, :, None] + dense

    def forward(self, p: torch.Tensor, level_weights, jacobian: bool = False):
        """Features (N, L * F) at points (N, 3), each level scaled by its weight (a list or a
        tensor); with `jacobian` also their derivatives in the points (N, 3, L * F), computed in closed form: the points
        are data, so the features and the Jacobian are both linear in the table and the eikonal
        loss needs no second derivative through the lookup. On the CPU the compiled kernel does it
        (`grid_kernel`), elsewhere `forward_torch`."""
        if grid_kernel.usable(self.table, p, self.features):
            weights = torch.as_tensor(level_weights, dtype=torch.float32, device=p.device)
            return grid_kernel.lookup(self.table, p, self.layout, weights, jacobian)
        return self.forward_torch(p, level_weights, jacobian)

    def forward_torch(self, p: torch.Tensor, level_weights, jacobian: bool = False):
        """`forward` in torch operations (any device and dtype, differentiable in the points)."""
        n, levels = len(p), len(self.res)
        res = self.res_l.to(p.dtype)[None, :, None]  # (1, L, 1)
        i0, f, du_dp = _cell(p[:, None, :], res)  # (N, L, 3)
        vals = self.table.index_select(0, self._indices(i0).reshape(-1)).view(n, levels, 8, self.features)
        w = corner_weights(f, du_dp if jacobian else None)  # (N, L, 8, 4 or 1)
        lw = torch.as_tensor(level_weights, dtype=p.dtype, device=p.device).view(1, levels, 1, 1)
        k = w.shape[-1]
        out = torch.bmm(vals.view(n * levels, 8, self.features).transpose(1, 2),
                        (w * lw).view(n * levels, 8, k)).view(n, levels, self.features, k)
        feats = out[..., 0].reshape(n, levels * self.features)
        if not jacobian:
            return feats
        return feats, out[..., 1:].reshape(n, levels * self.features, 3).transpose(1, 2)


class SDFNetwork(nn.Module):
    """SDF = base(x) + MLP(x, grid(x))[0]; the other outputs are features for the colour network."""

    def __init__(self, cfg: NeuSConfig, base_grid: torch.Tensor | None, init_radius: float = 0.6):
        super().__init__()
        self.encoding = DenseGrid(cfg.levels, cfg.base_res, cfg.max_res, cfg.features, cfg.hash_log2)
        d_in = 3 + cfg.levels * cfg.features
        self.l1 = nn.Linear(d_in, cfg.hidden)
        self.l2 = nn.Linear(cfg.hidden, cfg.hidden) if (cfg.sdf_layers or SDF_LAYERS) > 1 else None
        self.out = nn.Linear(cfg.hidden, 1 + cfg.geo_features)
        nn.init.normal_(self.out.weight, 0.0, 1e-4)
        nn.init.zeros_(self.out.bias)
        self.act = nn.Softplus(beta=100)
        self.init_radius = init_radius
        if base_grid is not None:
            self.register_buffer("base_grid", base_grid.reshape(-1, 1).contiguous())
            self.base_res = int(round(base_grid.numel() ** (1 / 3)))
            self.base_layout = grid_kernel.Layout([self.base_res], [0], [False], 0)
        else:
            self.base_grid = None

    def base(self, p: torch.Tensor, gradient: bool = False):
        """The initial SDF (the hull's smoothed distance or a sphere), with `gradient` also its
        gradient in the points."""
        if self.base_grid is None:
            r = p.norm(dim=-1)
            return (r - self.init_radius, p / r.clamp(min=1e-12)[:, None]) if gradient else r - self.init_radius
        if grid_kernel.usable(self.base_grid, p, 1):
            out = grid_kernel.lookup(self.base_grid, p, self.base_layout, torch.ones(1, device=p.device), gradient)
            return (out[0][:, 0], out[1][:, :, 0]) if gradient else out[:, 0]
        if not gradient:
            return trilinear(self.base_grid, self.base_res, p)[:, 0]
        value, grad = trilinear(self.base_grid, self.base_res, p, gradient=True)
        return value[:, 0], grad[:, 0]

    def forward(self, p: torch.Tensor, level_weights) -> tuple[torch.Tensor, torch.Tensor]:
        h = torch.cat([p, self.encoding(p, level_weights)], -1)
        h = self.act(self.l1(h))
        if self.l2 is not None:
            h = self.act(self.l2(h))
        o = self.out(h)
        return self.base(p) + o[:, 0], o[:, 1:]

    def forward_with_gradient(self, p: torch.Tensor, level_weights):
        """(SDF, features, SDF gradient in p) at data points p, the gradient in closed form (the
        MLP's chain rule and the grid's Jacobian) as a graph in the parameters: its eikonal loss
        back-propagates with first derivatives only, faster than autograd's double backward and the
        same to rounding (tests/geometry/test_geometry.py)."""
        enc, jac = self.encoding(p, level_weights, jacobian=True)
        a1 = self.l1(torch.cat([p, enc], -1))
        beta = self.act.beta  # softplus(beta x)' = sigmoid(beta x), 1 to rounding past its threshold
        if self.l2 is None:
            o = self.out(self.act(a1))
            g = self.out.weight[0] * torch.sigmoid(beta * a1)
        else:
            a2 = self.l2(self.act(a1))
            o = self.out(self.act(a2))
            g = (self.out.weight[0] * torch.sigmoid(beta * a2)) @ self.l2.weight
            g = g * torch.sigmoid(beta * a1)
        g = g @ self.l1.weight  # d sdf / d (p, features)
        base, base_grad = self.base(p, gradient=True)
        grad = g[:, :3] + (jac * g[:, None, 3:]).sum(-1) + base_grad
        return base + o[:, 0], o[:, 1:], grad


class ColorNetwork(nn.Module):
    """Radiance from SDF features, normal and view direction (with a small frequency encoding).
    With cfg.reflect the direction encoded is the view direction reflected about the normal, and
    the cosine between the two is one more input."""

    def __init__(self, cfg: NeuSConfig, view_freqs: int = 3):
        super().__init__()
        self.view_freqs = view_freqs
        self.reflect = cfg.reflect
        d_in = cfg.geo_features + 3 + 3 + 6 * view_freqs + (1 if cfg.reflect else 0)
        self.net = nn.Sequential(nn.Linear(d_in, cfg.hidden), nn.ReLU(), nn.Linear(cfg.hidden, cfg.hidden),
                                 nn.ReLU(), nn.Linear(cfg.hidden, 3))

    def forward(self, feat, normal, view):
        extra = []
        if self.reflect:
            cos = (view * normal).sum(-1, keepdim=True)
            view = view - 2.0 * cos * normal
            extra = [cos]
        enc = extra + [view]
        for k in range(self.view_freqs):
            enc += [torch.sin((2.0 ** k) * math.pi * view), torch.cos((2.0 ** k) * math.pi * view)]
        return torch.sigmoid(self.net(torch.cat([feat, normal] + enc, -1)))


def frequency_encoding(x: torch.Tensor, freqs: int) -> torch.Tensor:
    """x and sin / cos of 2^k pi x for k < freqs."""
    enc = [x]
    for k in range(freqs):
        enc += [torch.sin((2.0 ** k) * math.pi * x), torch.cos((2.0 ** k) * math.pi * x)]
    return torch.cat(enc, -1)


class BackgroundNetwork(nn.Module):
    """NeRF++'s model of what lies outside the unit sphere: density and colour of a point from its
    inverted-sphere coordinates (x / r, 1 / r) and the view direction, each frequency-encoded."""

    POINT_FREQS, VIEW_FREQS = 6, 3

    def __init__(self, hidden: int):
        super().__init__()
        self.trunk = nn.Sequential(nn.Linear(4 * (1 + 2 * self.POINT_FREQS), hidden), nn.ReLU(),
                                   nn.Linear(hidden, hidden), nn.ReLU())
        self.sigma = nn.Linear(hidden, 1)
        self.rgb = nn.Sequential(nn.Linear(hidden + 3 * (1 + 2 * self.VIEW_FREQS), hidden // 2), nn.ReLU(),
                                 nn.Linear(hidden // 2, 3))

    def forward(self, x4: torch.Tensor, view: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        h = self.trunk(frequency_encoding(x4, self.POINT_FREQS))
        rgb = torch.sigmoid(self.rgb(torch.cat([h, frequency_encoding(view, self.VIEW_FREQS)], -1)))
        return F.softplus(self.sigma(h)[:, 0] - 1.0), rgb


class NeuSModel(nn.Module):
    def __init__(self, cfg: NeuSConfig, base_grid: torch.Tensor | None, background: bool = False):
        super().__init__()
        # Without masks the sphere is the bounding sphere, larger than the object: a small start
        # leaves less surface to recede, on which the colour network would paint the backdrop.
        radius = cfg.init_radius or (INIT_RADIUS_WITHOUT_MASKS if background else INIT_RADIUS)
        self.sdf = SDFNetwork(cfg, base_grid, radius)
        self.color = ColorNetwork(cfg)
        self.variance = nn.Parameter(torch.tensor(float(cfg.init_variance), device="cpu"))  # moved with the module
        self.background = BackgroundNetwork(cfg.hidden) if background else None

    def inv_s(self) -> torch.Tensor:
        return torch.exp(10.0 * self.variance).clamp(1e-6, 1e6)

    def sdf_grad(self, p: torch.Tensor, level_weights, create_graph: bool):
        """(SDF, features, gradient) at points p; the gradient is part of the graph with
        create_graph (the eikonal loss and the normals' colour), detached without."""
        sdf, feat, grad = self.sdf.forward_with_gradient(p.detach(), level_weights)
        return sdf, feat, grad if create_graph else grad.detach()
