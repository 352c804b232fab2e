"""Each BRDF input's scores against its ground-truth map, for every input of `brdf.INPUTS`.

A colour is compared in sRGB (PSNR, SSIM) after a per-channel scale that all views share (the
albedo's scale is ambiguous under unknown light: NeRFactor's and TensoIR's protocol, see
`metrics.scale_align`); a scalar linearly (PSNR, mean absolute error), inside the ground-truth
mask. `evaluate`'s image-space scores, its discrete branch's and the true surface's (`surface`)
are these, and `report` prints them: one place decides how an input is scored.
"""

from __future__ import annotations

import math

import numpy as np

from vq_mitsuba import brdf
from vq_mitsuba.eval import metrics as M


def alignment_scales(maps: list[dict], gts: list[dict], masks: np.ndarray, method: str) -> dict[str, np.ndarray]:
    """{colour input: its (3,) per-channel scales}, fitted over all views' masked pixels jointly."""
    return {i.name: M.scale_align(np.stack([m[i.name] for m in maps]), np.stack([g[i.name] for g in gts]),
                                  masks, method=method)[1] for i in brdf.INPUTS if i.colour}


def view_scores(pred: dict, gt: dict, mask: np.ndarray, scales: dict[str, np.ndarray], unaligned: bool = False,
                mae: bool = True) -> dict[str, float]:
    """One view's {input_stat: value}: a colour's aligned `_psnr`, `_ssim` (and `_psnr_unaligned`
    with `unaligned`), a scalar's `_psnr` (and `_mae` with `mae`)."""
    row = {}
    for i in brdf.INPUTS:
        p, g = pred[i.name], gt[i.name]
        if i.colour:
            s = M.image_metrics(p * scales[i.name], g, mask)
            row[f"{i.name}_psnr"], row[f"{i.name}_ssim"] = s["psnr"], s["ssim"]
            if unaligned:
                row[f"{i.name}_psnr_unaligned"] = M.psnr(M.srgb(p), M.srgb(g), mask)
        else:
            row[f"{i.name}_psnr"] = M.psnr(p, g, mask)
            if mae:
                row[f"{i.name}_mae"] = float(np.abs(p - g)[mask].mean()) if mask.any() else math.nan
    return row


def mean_scores(rows: list[dict], unaligned: bool = False, mae: bool = True) -> dict[str, dict]:
    """{input: {stat: mean over the views}} of `view_scores` rows (NaN views left out)."""
    out = {}
    for i in brdf.INPUTS:
        if i.colour:
            stats = ("psnr", "ssim") + (("psnr_unaligned",) if unaligned else ())
        else:
            stats = ("psnr",) + (("mae",) if mae else ())
        out[i.name] = {s: M.mean_of(r[f"{i.name}_{s}"] for r in rows if f"{i.name}_{s}" in r) for s in stats}
    return out


def table_rows(scores: dict, method: str, prefix: str = "") -> list[tuple[str, object, object]]:
    """(label, PSNR, SSIM or None) of each input in `scores` ({input: {psnr, ssim?}}), as the
    readable table shows them."""
    return [(f"{prefix}{i.name} ({method}-aligned)", scores[i.name]["psnr"], scores[i.name]["ssim"]) if i.colour
            else (f"{prefix}{i.name} (linear)", scores[i.name]["psnr"], None)
            for i in brdf.INPUTS if i.name in scores]
