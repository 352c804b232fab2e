"""Discrete branch pieces (paper Sec. III-C/D): VQ-EMA codebook on the unit sphere, codeword
dropout for ranking, and the rule that picks the number of materials."""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from vq_mitsuba.brdf import INPUTS
from torch import nn


class VectorQuantizerEMA(nn.Module):
    """Eq. (7)-(8): z and codewords on the unit sphere, nearest codeword, straight-through.

    The codebook is not trained by gradients but by exponential moving averages of the latents
    assigned to each codeword (VQ-VAE-2 style); the loss is the commitment term only,
    `commitment * ||z - sg(e)||^2`. Codewords unused for `dead_after` updates are re-seeded from
    random latents of the current batch.
    """

    def __init__(self, num_codes: int, dim: int, decay: float = 0.99, commitment: float = 0.1,
                 eps: float = 1e-5, dead_after: int = 50):
        super().__init__()
        self.num_codes, self.dim = num_codes, dim
        self.decay, self.commitment, self.eps, self.dead_after = decay, commitment, eps, dead_after
        init = F.normalize(torch.randn(num_codes, dim), dim=-1)
        self.register_buffer("codebook", init)
        self.register_buffer("ema_count", torch.ones(num_codes))
        self.register_buffer("ema_sum", init.clone())
        self.register_buffer("unused_steps", torch.zeros(num_codes, dtype=torch.long))

    @torch.no_grad()
    def init_codebook(self, codewords: torch.Tensor) -> None:
        """Set the codebook, e.g. from k-means centres of warm-up latents (normalised here)."""
        c = F.normalize(codewords.to(self.codebook), dim=-1)
        self.codebook.copy_(c)
        self.ema_sum.copy_(c)
        self.ema_count.fill_(1.0)
        self.unused_steps.zero_()

    @torch.no_grad()
    def reorder(self, order: torch.Tensor) -> None:
        """Permute the codewords (and their EMA statistics): new codeword i = old codeword order[i]."""
        for name in ("codebook", "ema_count", "ema_sum", "unused_steps"):
            buf = getattr(self, name)
            buf.copy_(buf[order])

    def nearest(self, z_unit: torch.Tensor, drop_mask: torch.Tensor | None = None,
                n_codes: int | None = None) -> torch.Tensor:
        """Index of the nearest codeword (cosine). drop_mask (N, K) True = codeword unavailable to
        that latent; n_codes keeps only the first n codewords (the ranked prefix)."""
        sim = z_unit @ self.codebook.t()
        if n_codes is not None:
            sim[:, n_codes:] = -float("inf")
        if drop_mask is not None:
            sim = sim.masked_fill(drop_mask, -float("inf"))
        return sim.argmax(-1)

    def forward(self, z: torch.Tensor, drop_mask: torch.Tensor | None = None,
                n_codes: int | None = None, weight: torch.Tensor | None = None
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Returns (z_q with straight-through gradient, codeword indices, VQ loss).

        Latents that dropout forced onto another codeword than their nearest get no
        straight-through gradient (the identity z_q ~ z that the estimator
        assumes does not hold for them); they still train the decoder and the codebook.
        `weight` (N,): importance weights of the latents (in the EMA statistics and the loss)."""
        z_unit = F.normalize(z, dim=-1)
        idx = self.nearest(z_unit.detach(), drop_mask, n_codes)
        e = self.codebook[idx]
        if self.training:
            self.ema_update(z_unit.detach(), idx, weight)
        z_q = z_unit + (e - z_unit).detach()
        own = None
        if drop_mask is not None:
            own = idx == self.nearest(z_unit.detach(), None, n_codes)
            z_q = torch.where(own[:, None], z_q, e.detach())
        sq = torch.sum((z_unit - e.detach()) ** 2, -1)
        if own is not None:  # commitment towards the latent's own codeword only
            sq = sq * own
        loss = self.commitment * torch.mean(sq if weight is None else weight * sq)
        return z_q, idx, loss

    @torch.no_grad()
    def ema_update(self, z_unit: torch.Tensor, idx: torch.Tensor, weight: torch.Tensor | None = None) -> None:
        onehot = F.one_hot(idx, self.num_codes).to(z_unit.dtype)  # (N, K)
        if weight is not None:
            onehot = onehot * weight[:, None].to(z_unit.dtype)
        count = onehot.sum(0)
        total = onehot.t() @ z_unit  # (K, D)
        self.ema_count.mul_(self.decay).add_(count, alpha=1 - self.decay)
        self.ema_sum.mul_(self.decay).add_(total, alpha=1 - self.decay)
        n = self.ema_count.sum()
        smoothed = (self.ema_count + self.eps) / (n + self.num_codes * self.eps) * n  # Laplace smoothing
        self.codebook.copy_(F.normalize(self.ema_sum / smoothed[:, None], dim=-1))
        # Dead codes: re-seed from random latents of this batch.
        self.unused_steps.add_(1).masked_fill_(count > 0, 0)
        dead = torch.nonzero(self.unused_steps >= self.dead_after)[:, 0]
        if len(dead) > 0 and z_unit.shape[0] > 0:
            pick = torch.randint(0, z_unit.shape[0], (len(dead),), device=z_unit.device)
            self.codebook[dead] = z_unit[pick]
            self.ema_sum[dead] = z_unit[pick]
            self.ema_count[dead] = 1.0
            self.unused_steps[dead] = 0


def scale_gradient(x: torch.Tensor, scale: float) -> torch.Tensor:
    """x unchanged in the forward pass; the gradient flowing back through it is multiplied by scale."""
    if scale == 1.0:
        return x
    return x * scale + x.detach() * (1.0 - scale)


def dropout_rates(num_codes: int, max_rate: float = 0.7, protected: int = 1) -> torch.Tensor:
    """Codeword k is dropped with a rate rising linearly from 0 to `max_rate` over the codebook;
    the first `protected` codewords are never dropped. Dropping later codewords more often makes
    the network put the most important materials first (the ranking of Sec. III-D)."""
    rates = torch.zeros(num_codes)
    n = num_codes - protected
    if n > 0:
        rates[protected:] = torch.linspace(0.0, max_rate, n + 1)[1:]
    return rates


def sample_drop_mask(n: int, rates: torch.Tensor, generator: torch.Generator | None = None) -> torch.Tensor:
    """(n, K) boolean mask, True where a codeword is dropped for that latent."""
    u = torch.rand(n, rates.shape[0], generator=generator, device=rates.device)
    return u < rates[None]


def duplicates_last(brdf: dict[str, torch.Tensor], order: list[int], n_used: int,
                    tol: float) -> tuple[list[int], int]:
    """(new order, number of distinct used codewords): `order` (codeword indices, the first `n_used`
    of them picked by pixels) with every used codeword whose BRDF is within `tol` of an earlier kept
    one moved behind the kept ones (before the unused). Distance: the largest absolute difference of
    gamma-2.2 basecolor, metallic and roughness, so two codewords that decode to the same material
    count once in err_k."""
    if tol <= 0:
        return list(order), n_used
    feats = torch.cat([brdf[i.name].clamp(min=0) ** (1 / 2.2) if i.colour else brdf[i.name].reshape(-1, 1)
                       for i in INPUTS], -1)
    kept, dup = [], []
    for i in order[:n_used]:
        if any(float((feats[i] - feats[j]).abs().max()) < tol for j in kept):
            dup.append(i)
        else:
            kept.append(i)
    return kept + dup + list(order[n_used:]), len(kept)


def choose_num_materials(err: list[float] | torch.Tensor, eps: float = 0.002) -> int:
    """The smallest k whose error err_k (prefix of k codewords, k = 1..K) is within `eps` of
    every longer prefix: err_k - err_j <= eps for all j > k."""
    err = [float(e) for e in err]
    if not err:
        raise ValueError("empty error curve")
    for k in range(len(err)):
        if all(err[k] - e <= eps + 1e-12 for e in err[k + 1:]):  # inclusive despite rounding
            return k + 1
    return len(err)


def redundant_last(measure, order: list[int], eps: float,
                   n_keep: int | None = None) -> tuple[list[int], list[float], list[int]]:
    """Rank again until every codeword inside the chosen prefix pays for itself.

    `measure(order)` gives err_k for the prefixes of `order`. While some codeword at position
    j >= 1 inside the prefix that `choose_num_materials` picks lowers the error by less than `eps`
    when added (err_{j-1} - err_j < eps), it moves to the end of the first `n_keep` positions (all
    of them when None) and err_k is measured again: a near-copy of an earlier material that dropout
    happened to rank early no longer counts as one. The codewords behind `n_keep` (duplicates and
    unused ones, see `duplicates_last`) stay behind every moved one, so a distinct material that
    was moved is still ranked before them; a weak codeword from behind `n_keep` goes to the very
    end. Each codeword moves at most once. Returns (order, err_k of that order, the codewords
    moved, in the order they moved)."""
    order, moved = list(order), []
    n_keep = len(order) if n_keep is None else max(1, min(int(n_keep), len(order)))
    errs = list(measure(order))
    for _ in range(len(order)):
        m = choose_num_materials(errs, eps)
        # A codeword moves once: one that pays for itself only next to another (two codewords
        # sharing a material) would otherwise go round the end of the order for ever.
        weak = [j for j in range(1, m) if errs[j - 1] - errs[j] < eps and order[j] not in moved]
        if not weak:
            break
        j = weak[0]
        moved.append(order[j])
        end = n_keep if j < n_keep else len(order)  # a weak duplicate itself goes to the very end
        order = order[:j] + order[j + 1:end] + [order[j]] + order[end:]
        errs = list(measure(order))
    return order, errs, moved


class DiscreteBranch(nn.Module):
    """z -> nearest codeword (VQ) -> f_d^d: per-material basecolor, metallic, roughness."""

    def __init__(self, field_cfg, num_codes: int, decay: float, commitment: float):
        super().__init__()
        from vq_mitsuba.models.fields import BRDFDecoder

        self.vq = VectorQuantizerEMA(num_codes, field_cfg.latent, decay=decay, commitment=commitment)
        self.decoder = BRDFDecoder(field_cfg)
        self.register_buffer("initialised", torch.tensor(False))
        self.register_buffer("num_materials", torch.tensor(num_codes))
        # Codewords live on the unit sphere; the decoder sees them at the latents' typical length,
        # so a copy of the continuous decoder decodes a codeword like the latents around it.
        self.register_buffer("latent_scale", torch.tensor(1.0))

    @torch.no_grad()
    def warm_start(self, continuous_decoder: nn.Module, latents: torch.Tensor) -> None:
        """Start f_d^d as a copy of the continuous decoder, at the latents' mean length: right after
        the codebook's initialisation each material then decodes to the continuous branch's BRDF
        near its codeword, instead of a random decoder's output whose straight-through gradients
        would disturb the shared encoder."""
        self.decoder.load_state_dict(continuous_decoder.state_dict())
        self.latent_scale.fill_(float(latents.norm(dim=-1).mean().clamp_min(1e-6)))

    def forward(self, z: torch.Tensor, drop_mask: torch.Tensor | None = None,
                n_codes: int | None = None, weight: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        z_q, idx, loss = self.vq(z, drop_mask, n_codes, weight)
        out = self.decoder(z_q * self.latent_scale)
        out["index"] = idx
        out["vq_loss"] = loss
        return out

    def decode_codewords(self) -> dict[str, torch.Tensor]:
        """The BRDF each codeword decodes to (one material per codeword), differentiable in the
        decoder alone."""
        return self.decoder(self.vq.codebook.detach() * self.latent_scale)

    @torch.no_grad()
    def codeword_brdfs(self) -> dict[str, torch.Tensor]:
        """The BRDF each codeword decodes to (one material per codeword)."""
        return self.decode_codewords()


def kmeans_codebook(latents: torch.Tensor, num_codes: int, seed: int = 0) -> torch.Tensor:
    """k-means centres of unit-normalised latents (the codebook's initialisation after warm-up)."""
    from sklearn.cluster import KMeans

    x = F.normalize(latents, dim=-1).cpu().numpy()
    k = min(num_codes, len(x))
    km = KMeans(n_clusters=k, n_init=4, random_state=seed).fit(x)
    centres = torch.as_tensor(km.cluster_centers_, dtype=latents.dtype)
    if k < num_codes:  # fewer distinct latents than codewords: repeat with a little noise
        extra = centres[torch.randint(0, k, (num_codes - k,))] + 1e-3 * torch.randn(num_codes - k, x.shape[1])
        centres = torch.cat([centres, extra])
    # Most populated clusters first, so the protected (never dropped) codewords start on them.
    counts = np.bincount(km.labels_, minlength=num_codes)[:num_codes]
    order = np.argsort(-counts, kind="stable")
    return centres[torch.as_tensor(order)]
