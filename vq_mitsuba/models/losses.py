"""Losses: pure functions of tensors, and the declaration of the fit's named loss terms with the
config key of each one's weight (`TERMS`, `weighted`).

A material model returns its terms unweighted, by name (`MaterialModel.loss_dict`); `weighted`
reads each one's weight from the config by the name's declaration. A new loss is its function, its
entry in `TERMS` and its config key.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from vq_mitsuba.brdf import INPUTS


@dataclass(frozen=True)
class Term:
    """A named loss term: the config key of its weight ("section.key") and, for a weight that
    decays over training, the key of its factor at the end (the weight times factor ** progress)."""

    name: str
    weight: str
    decay: str | None = None
    fixed: float | None = None  # a weight that no config key sets (an internal term)


TRIAL_PULL_WEIGHT = 1.0  # the trials' pull (`vq_mitsuba.engine.trials`): a squared roughness shortfall

TERMS = {t.name: t for t in (
    Term("rec_c", "loss.w_rec_c"),  # w1: L2 reconstruction of the continuous branch
    Term("lam_c", "loss.w_lam", decay="loss.lam_decay"),  # w5: Lambertian prior, continuous branch
    Term("rec_d", "loss.w_rec_d"),  # w2: L2 reconstruction of the discrete branch
    Term("chr", "loss.w_chr"),  # w3: chromaticity
    Term("met", "loss.w_met"),  # the discrete metallic against the continuous one
    Term("vq", "loss.w_vq"),  # w4: VQ (commitment) loss
    Term("lam_d", "loss.w_lam", decay="vq.lam_decay"),  # w5: Lambertian prior, discrete branch
    Term("sm", "loss.w_sm"),  # w6: colour-aware smoothness
    Term("env_tv", "envmap.tv_weight"),  # smoothness of the learned envmap
    Term("trial", "", fixed=TRIAL_PULL_WEIGHT),
)}


def config_value(cfg, key: str) -> float:
    """The config's value at "section.key"."""
    section, name = key.split(".")
    return float(getattr(getattr(cfg, section), name))


def weight_of(cfg, name: str, progress: float) -> float:
    """The weight of the term `name` at training progress `progress` (0..1)."""
    term = TERMS.get(name)
    if term is None:
        raise KeyError(f"loss term '{name}' has no declaration in vq_mitsuba.models.losses.TERMS")
    if term.fixed is not None:
        return term.fixed
    w = config_value(cfg, term.weight)
    return w if term.decay is None else w * config_value(cfg, term.decay) ** progress


def weighted(terms: dict, cfg, progress: float) -> dict:
    """Each term of `terms` (name: unweighted tensor) times its weight (Eq. 10: their sum is the
    loss)."""
    return {name: weight_of(cfg, name, progress) * value for name, value in terms.items()}


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


def metallic_agreement(metallic_d: torch.Tensor, metallic_c: torch.Tensor,
                       weight: torch.Tensor | None = None) -> torch.Tensor:
    """The discrete metallic keeps the continuous one's: the mean absolute difference, whose
    minimum puts each codeword at the median continuous metallic of its points (so a few mixed
    points at a material's edge do not move it). Where a rough surface renders alike as a
    dielectric or as a dim metal, the continuous field's prior decides, and a codeword follows it
    instead of drifting along the ambiguity. `weight` (N,): importance weights of the points."""
    diff = (metallic_d - metallic_c.detach()).abs()
    return torch.mean(diff) if weight is None else torch.mean(weight * diff)


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
