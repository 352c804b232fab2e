"""Losses: pure functions of tensors (weights come from LossConfig)."""

from __future__ import annotations

import torch

from vq_mitsuba.brdf import INPUTS


def encode_gamma(rgb_linear: torch.Tensor, gamma: float) -> torch.Tensor:
    """x^(1/gamma) with a small offset so the gradient stays finite at black pixels."""
    eps = 1e-3
    return (rgb_linear.clamp_min(0.0) + eps) ** (1.0 / gamma) - eps ** (1.0 / gamma)


def reconstruction_l2(rgb_pred: torch.Tensor, rgb_target: torch.Tensor, gamma: float) -> torch.Tensor:
    """L_rec: mean squared error between gamma-encoded radiance values."""
    return torch.mean((encode_gamma(rgb_pred, gamma) - encode_gamma(rgb_target, gamma)) ** 2)


def reconstruction_l2_decorrelated(samples: torch.Tensor, rgb_target: torch.Tensor, gamma: float,
                                   weight: torch.Tensor | None = None) -> torch.Tensor:
    """L_rec from Monte Carlo samples (N, S, 3) without the variance bias of a plain L2.

    E[(X - t)^2] = (E[X] - t)^2 + Var[X]: a plain L2 on a noisy estimate X also rewards
    materials that are cheap to sample (rough, dull). Two independent half-estimates A and B
    give E[(A - t)(B - t)] = (E[X] - t)^2 (up to the gamma encoding's curvature).
    `weight` (N,): importance weights of the pixels (the mean of weight x per-pixel term).
    """
    if weight is not None:
        return torch.mean(weight * decorrelated_error(samples, rgb_target, gamma))
    half = samples.shape[1] // 2
    t = encode_gamma(rgb_target, gamma)
    a = encode_gamma(samples[:, :half].mean(1), gamma) - t
    b = encode_gamma(samples[:, half:].mean(1), gamma) - t
    return torch.mean(a * b)


def decorrelated_error(samples: torch.Tensor, rgb_target: torch.Tensor, gamma: float) -> torch.Tensor:
    """(N,) each pixel's term of `reconstruction_l2_decorrelated` (mean over the channels): an
    unbiased estimate of its squared error, negative at times from the noise."""
    half = samples.shape[1] // 2
    t = encode_gamma(rgb_target, gamma)
    a = encode_gamma(samples[:, :half].mean(1), gamma) - t
    b = encode_gamma(samples[:, half:].mean(1), gamma) - t
    return (a * b).mean(1)


def lambertian_prior(metallic: torch.Tensor, roughness: torch.Tensor, metallic_weight: float = 1.0,
                     metallic_logit: torch.Tensor | None = None, weight: torch.Tensor | None = None,
                     metallic_scale: torch.Tensor | None = None) -> torch.Tensor:
    """L_lam: pulls materials towards Lambertian (metallic 0, roughness 1) unless the images object.

    `metallic_weight` scales the metallic term against the roughness one (the paper weighs them
    equally). With `metallic_logit` (metallic = sigmoid(logit)) the metallic term is
    softplus(logit) = -log(1 - metallic): its pull on the logit tends to
    the full weight where metallic saturates at 1, where the paper's linear term's pull vanishes
    with the sigmoid's slope (a saturated wrong metal then never comes back). `weight` (N,):
    importance weights of the points (the mean of weight x per-point term). `metallic_scale` (N,):
    each point's weight of the metallic term alone (`vq_mitsuba.engine.evidence`)."""
    if weight is not None or metallic_scale is not None:
        m = torch.nn.functional.softplus(metallic_logit) if metallic_logit is not None else metallic
        if metallic_scale is not None:
            m = metallic_scale * m
        term = metallic_weight * m + 1.0 - roughness
        return torch.mean(term if weight is None else weight * term)
    if metallic_logit is not None:
        m_term = torch.mean(torch.nn.functional.softplus(metallic_logit))
    else:
        m_term = torch.mean(metallic)
    return metallic_weight * m_term + torch.mean(1.0 - roughness)


def srgb_mse(rgb_pred: torch.Tensor, rgb_target: torch.Tensor, weight: torch.Tensor | None = None) -> torch.Tensor:
    """Mean squared error of sRGB-encoded (IEC 61966-2-1, clipped to [0, 1]) colours, in torch:
    the figure behind the progress bar's PSNR, comparable with `vq-mitsuba eval`. `weight` (N,):
    importance weights of the pixels (a batch drawn by error then estimates the uniform mean)."""
    def enc(x):
        x = x.clamp(0.0, 1.0)
        return torch.where(x <= 0.0031308, x * 12.92, 1.055 * x.clamp_min(1e-12) ** (1.0 / 2.4) - 0.055)
    if weight is not None:
        return torch.mean(weight * ((enc(rgb_pred) - enc(rgb_target)) ** 2).mean(-1))
    return torch.mean((enc(rgb_pred) - enc(rgb_target)) ** 2)


def psnr(mse: torch.Tensor | float, peak: float = 1.0) -> float:
    mse = float(mse)
    return float("inf") if mse <= 0 else 10.0 * torch.log10(torch.tensor(peak**2 / mse)).item()


def chromaticity(rgb: torch.Tensor) -> torch.Tensor:
    """rgb / (r + g + b): colour without intensity."""
    return rgb / (rgb.sum(-1, keepdim=True) + 1e-4)


def chromaticity_loss(basecolor_d: torch.Tensor, basecolor_c: torch.Tensor,
                      weight: torch.Tensor | None = None) -> torch.Tensor:
    """L_chr: the discrete basecolor keeps the continuous one's chromaticity (shading and
    intensity ambiguities do not change chromaticity, so it anchors the material's colour).
    `weight` (N,): importance weights of the points."""
    sq = (chromaticity(basecolor_d) - chromaticity(basecolor_c.detach())) ** 2
    return torch.mean(sq) if weight is None else torch.mean(weight[:, None] * sq)


def colour_aware_smoothness(brdf_a: dict, brdf_b: dict, rgb_a: torch.Tensor, rgb_b: torch.Tensor,
                            alpha: float, beta: float) -> torch.Tensor:
    """L_sm on pairs of neighbouring pixels: BRDF differences weighted by exp(-alpha |I_a - I_b|),
    so the field is smooth where the image is, and free to change across colour edges; metallic
    and roughness differences count `beta` times."""
    w = torch.exp(-alpha * (rgb_a - rgb_b).abs().mean(-1))
    diff = {i.name: (brdf_a[i.name] - brdf_b[i.name]).abs() for i in INPUTS}
    d = sum(diff[i.name].mean(-1) for i in INPUTS if i.colour)
    d = d + beta * sum(diff[i.name] for i in INPUTS if not i.colour)
    return torch.mean(w * d)
