"""Dropout ranking (Sec. III-D): order the codewords, measure err_k, choose M."""

from __future__ import annotations

import torch

from vq_mitsuba.brdf import INPUTS
from vq_mitsuba.config import Config
from vq_mitsuba.data.pixels import PixelPool
from vq_mitsuba.models import losses
from vq_mitsuba.models.vq import DiscreteBranch, choose_num_materials, duplicates_last, redundant_last

ERR_K_SPP = 16  # light samples per pixel when measuring err_k (the same samples for every k)


@torch.no_grad()
def rank_materials(scene, model, discrete: DiscreteBranch, pool: PixelPool, env: torch.Tensor,
                   cfg: Config) -> dict:
    """err_k of the discrete branch restricted to its first k codewords, k = 1..M0, on a fixed set of
    training pixels; M = the first k within epsilon of every longer prefix. Reorders the codebook
    into the ranked order, sets `discrete.num_materials` and returns the content of materials.json."""
    device = pool.position.device
    gen = torch.Generator(device=device).manual_seed(cfg.train.seed + 1)
    n = min(cfg.vq.rank_pixels, len(pool))
    sel = torch.randperm(len(pool), generator=gen, device=device)[:n]
    z = model(pool.position[sel])["z"]
    was_training = discrete.training
    discrete.eval()
    K = cfg.vq.num_codes
    ranking = not cfg.ablation.no_ranking
    # Codewords that (almost) no pixel picks are not materials: they go behind the used ones,
    # keeping the dropout order otherwise.
    share = torch.bincount(discrete(z)["index"], minlength=K).float() / max(n, 1)
    used = share >= cfg.vq.min_share
    order = torch.cat([torch.nonzero(used)[:, 0], torch.nonzero(~used)[:, 0]])
    # Codewords that decode to the same material as a higher-ranked one go behind the distinct ones.
    ranked, n_distinct = duplicates_last(discrete.codeword_brdfs(), order.tolist(), int(used.sum()), cfg.vq.merge_tol)
    current = list(range(K))  # training index of the codeword now at each position
    usage = torch.zeros(K)

    def measure(rank: list[int]) -> list[float]:  # err_k of the prefixes of `rank` (training indices)
        nonlocal usage, current
        discrete.vq.reorder(torch.as_tensor([current.index(i) for i in rank], device=z.device))
        current = list(rank)
        errs_k = []
        for k in range(1, K + 1):
            od = discrete(z, n_codes=k)
            g = torch.Generator(device=device).manual_seed(cfg.train.seed + 2)
            rgb = scene.shade(pool.position[sel], pool.normal[sel], pool.wi[sel], od, env, ERR_K_SPP, generator=g,
                              groups=1, views=scene.lamp_views(pool, sel))
            errs_k.append(float(losses.reconstruction_l2(rgb, pool.rgb[sel], cfg.loss.gamma)))
            if k == K:
                usage = torch.bincount(od["index"], minlength=K).float().cpu() / n
        return errs_k

    redundant = []
    if ranking and not cfg.ablation.single_pass_ranking:
        ranked, errs, redundant = redundant_last(measure, ranked, cfg.vq.rank_eps, n_keep=n_distinct)
    else:
        errs = measure(ranked)
    M = max(1, min(choose_num_materials(errs, cfg.vq.rank_eps), n_distinct)) if ranking else K
    discrete.num_materials.fill_(M)
    discrete.train(was_training)
    brdf = discrete.codeword_brdfs()
    usage_m = torch.bincount(discrete(z, n_codes=M)["index"], minlength=K).float().cpu() / n
    materials = [{"id": k + 1, **{i.name: brdf[i.name][k].tolist() for i in INPUTS},
                  "pixel_fraction": float(usage_m[k]),
                  "pixel_fraction_all_codewords": float(usage[k])} for k in range(K)]
    return {"num_materials": M, "num_codewords": K, "epsilon": cfg.vq.rank_eps, "ranking": ranking,
            "min_share": cfg.vq.min_share, "codewords_used": int(used.sum()),
            "merge_tol": cfg.vq.merge_tol, "codewords_distinct": n_distinct,
            "training_order": list(ranked), "redundant_codewords": redundant,
            "err_k": errs, "materials": materials[:M], "dropped_codewords": materials[M:]}
