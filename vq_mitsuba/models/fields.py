"""Continuous material branch (paper Sec. III-B): encoder to latent z, decoders to BRDF factors."""

from __future__ import annotations

import math

import torch
from torch import nn

from vq_mitsuba import brdf
from vq_mitsuba.config import FieldConfig


class PositionalEncoding(nn.Module):
    """gamma(p) = (p, sin(2^k pi p), cos(2^k pi p)) for k < n_freqs, p in [-1, 1]^3."""

    def __init__(self, n_freqs: int):
        super().__init__()
        self.register_buffer("freqs", (2.0 ** torch.arange(n_freqs)) * math.pi, persistent=False)
        # Coarse-to-fine: frequency k is weighted by a cosine ramp of `progress` (in frequencies);
        # without it the field fits shading and highlights into basecolor before the light is found.
        self.register_buffer("progress", torch.tensor(float(n_freqs)))
        self.out_dim = 3 + 6 * n_freqs

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        xb = x[..., None, :] * self.freqs[:, None]  # (N, F, 3)
        k = torch.arange(self.freqs.shape[0], device=x.device, dtype=x.dtype)
        w = 0.5 * (1 - torch.cos(math.pi * torch.clamp(self.progress - k, 0.0, 1.0)))[:, None]
        return torch.cat([x, (torch.sin(xb) * w).flatten(-2), (torch.cos(xb) * w).flatten(-2)], -1)


class SkipMLP(nn.Module):
    """`n_layers` FC layers with ReLU; the input is concatenated again before layer `skip_at`."""

    def __init__(self, in_dim: int, hidden: int, out_dim: int, n_layers: int, skip_at: int):
        super().__init__()
        self.skip_at = skip_at
        layers = []
        for i in range(n_layers):
            d_in = in_dim if i == 0 else hidden
            if i == skip_at:
                d_in += in_dim
            d_out = out_dim if i == n_layers - 1 else hidden
            layers.append(nn.Linear(d_in, d_out))
        self.layers = nn.ModuleList(layers)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h = x
        for i, layer in enumerate(self.layers):
            if i == self.skip_at:
                h = torch.cat([h, x], -1)
            h = layer(h)
            if i < len(self.layers) - 1:
                h = torch.relu(h)
        return h


class Encoder(nn.Module):
    """f_e: positional encoding + 7 FC layers with a skip into the 4th -> latent z."""

    def __init__(self, cfg: FieldConfig):
        super().__init__()
        self.pe = PositionalEncoding(cfg.pe_freqs)
        self.mlp = SkipMLP(self.pe.out_dim, cfg.hidden, cfg.latent, n_layers=7, skip_at=3)

    def forward(self, x_unit: torch.Tensor) -> torch.Tensor:
        return self.mlp(self.pe(x_unit))


class BRDFDecoder(nn.Module):
    """f_d: three MLPs (basecolor, metallic, roughness), each 3 FC layers with a skip."""

    def __init__(self, cfg: FieldConfig):
        super().__init__()
        self.roughness_min = cfg.roughness_min
        mk = lambda out: SkipMLP(cfg.latent, cfg.decoder_hidden, out, n_layers=3, skip_at=2)
        self.basecolor = mk(3)
        self.metallic = mk(1)
        self.roughness = mk(1)
        if cfg.metallic_init > 0.0:
            # Metallic starts near the Lambertian prior's side and the images must raise it: with
            # PyTorch's initialisation every object starts at about 0.5.
            with torch.no_grad():
                self.metallic.layers[-1].bias.fill_(math.log(cfg.metallic_init / (1.0 - cfg.metallic_init)))

    def forward(self, z: torch.Tensor) -> dict[str, torch.Tensor]:
        r0 = self.roughness_min
        logit = self.metallic(z)[..., 0]
        return {
            brdf.BASECOLOR: torch.sigmoid(self.basecolor(z)),
            brdf.ROUGHNESS: r0 + (1.0 - r0) * torch.sigmoid(self.roughness(z))[..., 0],
            "metallic_logit": logit,
            brdf.METALLIC: torch.sigmoid(logit),
        }


class ContinuousMaterial(nn.Module):
    """Surface point (world) -> z -> basecolor (linear RGB), metallic, roughness.

    Points are mapped to [-1, 1]^3 by the scene's bounding box (stored as buffers).
    """

    def __init__(self, cfg: FieldConfig, bbox_min: torch.Tensor, bbox_max: torch.Tensor):
        super().__init__()
        center = 0.5 * (bbox_min + bbox_max)
        half = 0.5 * (bbox_max - bbox_min).max() * 1.05
        self.register_buffer("center", center.float())
        self.register_buffer("half_extent", half.float().reshape(()))
        self.encoder = Encoder(cfg)
        self.decoder = BRDFDecoder(cfg)

    def set_progress(self, fraction: float, anneal: float) -> None:
        """Open the positional-encoding frequencies over the first `anneal` share of training."""
        pe = self.encoder.pe
        n = pe.freqs.shape[0]
        pe.progress.fill_(n if anneal <= 0 else min(n, n * fraction / anneal))

    def forward(self, x_world: torch.Tensor) -> dict[str, torch.Tensor]:
        z = self.encoder((x_world - self.center) / self.half_extent)
        out = self.decoder(z)
        out["z"] = z
        return out


class EnvironmentMap(nn.Module):
    """Learnable lat-long radiance, positive through exp(log-radiance)."""

    def __init__(self, height: int, init_radiance: float):
        super().__init__()
        self.log_radiance = nn.Parameter(torch.full((height, 2 * height, 3), math.log(max(init_radiance, 1e-4))))

    def forward(self) -> torch.Tensor:
        return torch.exp(self.log_radiance)

    @torch.no_grad()
    def resize(self, height: int) -> None:
        """Resample the log-radiance to `height` rows (bilinear, longitude wrapping around) as a
        new parameter: the coarse-to-fine schedule refines a light found at a coarse size."""
        x = self.log_radiance.permute(2, 0, 1)[None]  # (1, 3, H, W)
        h, w = x.shape[-2:]
        if height % h:
            raise ValueError(f"the envmap grows by whole factors: {h} rows cannot become {height}")
        pad = torch.cat([x[..., -1:], x, x[..., :1]], -1)  # one wrapped column each side
        scale = height / h
        y = torch.nn.functional.interpolate(pad, size=(height, round((w + 2) * scale)), mode="bilinear",
                                            align_corners=False)
        cut = height // h
        y = y[..., cut:cut + 2 * height]
        self.log_radiance = nn.Parameter(y[0].permute(1, 2, 0).contiguous())

    def smoothness(self) -> torch.Tensor:
        """Mean squared difference of neighbouring log-radiance texels (longitude wraps around)."""
        x = self.log_radiance
        dv = x[1:] - x[:-1]
        du = x - torch.roll(x, 1, dims=1)
        return torch.mean(dv**2) + torch.mean(du**2)


class PointLamps(nn.Module):
    """Learnable point lamps beside the envmap, each with an RGB radiant intensity (K, 3), positive
    through exp(log-intensity), and a position kept as an offset in units of the object's radius
    (one learning rate fits any scale): about the object's centre for lamps fixed in the world, or
    in the frame of the camera that sees a point (Mitsuba camera space) for lamps that ride with
    the camera (a flash); those need `camera_to_world` (V, 4, 4), the capture's cameras, and stay
    in the camera's plane (a flash's depth from the lens trades against its intensity almost
    exactly, so it is not fitted)."""

    def __init__(self, center, radius: float, offsets, intensity: float, camera_to_world=None):
        super().__init__()
        self.register_buffer("center", torch.as_tensor(center, dtype=torch.float32).reshape(1, 3))
        self.register_buffer("radius", torch.tensor(float(radius)))
        self.register_buffer("in_camera", torch.tensor(camera_to_world is not None))
        self.register_buffer("camera_to_world", torch.zeros(0, 4, 4) if camera_to_world is None else
                             torch.as_tensor(camera_to_world, dtype=torch.float32).reshape(-1, 4, 4))
        self.offset = nn.Parameter(torch.as_tensor(offsets, dtype=torch.float32).reshape(-1, 3).clone())
        self.log_intensity = nn.Parameter(torch.full((self.offset.shape[0], 3), math.log(max(intensity, 1e-8))))

    def placement(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(positions (K, 3): in the world, or in the camera's frame for lamps that ride with it;
        intensities (K, 3))."""
        offset = self.radius * self.offset
        if bool(self.in_camera):
            return offset * offset.new_tensor([1.0, 1.0, 0.0]), torch.exp(self.log_intensity)
        return self.center + offset, torch.exp(self.log_intensity)

    def forward(self, views: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """(positions, intensities (K, 3)) in the world: positions (K, 3) for lamps fixed in the
        world, (K, N, 3) at the cameras of the points' `views` (N,) for lamps that ride with them."""
        position, intensity = self.placement()
        if not bool(self.in_camera):
            return position, intensity
        if views is None:
            raise ValueError("lamps that ride with the camera need the views of the points they light")
        cam = self.camera_to_world[views]
        return cam[None, :, :3, 3] + torch.einsum("nij,kj->kni", cam[:, :3, :3], position), intensity
