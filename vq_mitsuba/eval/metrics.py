"""Image metrics for evaluating a decomposition: PSNR, SSIM and per-channel scale alignment.

Pure numpy (scikit-image for SSIM). Conventions, used by `vq_mitsuba.eval.evaluate`:
- colour images (views, relit views, basecolor) are compared in sRGB: `linear_to_srgb` of the
  linear values clipped to [0, 1], as NeRF / NeRFactor / TensoIR report them;
- scalar maps (metallic, roughness) are compared linearly in [0, 1];
- a mask (H, W) selects the pixels that count (the ground-truth foreground).

Scale alignment: the albedo (and lighting intensity) of an inverse-rendering solution is only
known up to a per-channel factor, so benchmarks align the prediction to the ground truth first.
Two conventions are in use and the method is named wherever a figure depends on it:
- "lstsq" (NeRFactor): s_c = sum(p_c g_c) / sum(p_c^2) over the mask, the least-squares scale;
- "median" (TensoIR): s_c = median(g_c / p_c) over the mask (pixels with p_c > 0).
"""

from __future__ import annotations

import math

import numpy as np

from vq_mitsuba.data.imageio import linear_to_srgb

SCALE_METHODS = ("lstsq", "median")
_EPS = 1e-8


def _as_float(x) -> np.ndarray:
    return np.asarray(x, dtype=np.float64)


def _check_pair(pred: np.ndarray, gt: np.ndarray) -> None:
    if pred.shape != gt.shape:
        raise ValueError(f"prediction and ground truth differ in shape: {pred.shape} vs {gt.shape}")


def _pixel_mask(mask, image: np.ndarray) -> np.ndarray | None:
    """Boolean mask broadcast to the image's pixel dimensions (drops a trailing channel axis)."""
    if mask is None:
        return None
    m = np.asarray(mask).astype(bool)
    if m.shape == image.shape:
        return m
    if image.ndim == m.ndim + 1:  # (..., H, W) mask for (..., H, W, C) image
        return np.broadcast_to(m[..., None], image.shape)
    raise ValueError(f"mask of shape {m.shape} does not match an image of shape {image.shape}")


def mean_of(values) -> float:
    """The mean of per-view scores, NaN ones left out (NaN when none is left)."""
    vals = [v for v in values if not (isinstance(v, float) and math.isnan(v))]
    return float(np.mean(vals)) if vals else math.nan


def mse(pred, gt, mask=None) -> float:
    """Mean squared error over the masked pixels (all channels); nan for an empty mask."""
    pred, gt = _as_float(pred), _as_float(gt)
    _check_pair(pred, gt)
    d2 = (pred - gt) ** 2
    m = _pixel_mask(mask, d2)
    if m is not None:
        d2 = d2[m]
    return float(np.mean(d2)) if d2.size else math.nan


def psnr(pred, gt, mask=None, peak: float = 1.0) -> float:
    """PSNR in dB, 10 log10(peak^2 / MSE) over the masked pixels; inf for identical images."""
    err = mse(pred, gt, mask)
    if math.isnan(err):
        return math.nan
    if err == 0.0:
        return math.inf
    return 10.0 * math.log10(peak * peak / err)


def ssim(pred, gt, mask=None) -> float:
    """SSIM (scikit-image `structural_similarity`, data_range 1, 7x7 uniform window).

    pred, gt: (H, W) or (H, W, C). With a mask (H, W) the result is the mean of the SSIM map over
    the masked pixels (and channels); windows near the mask border still see outside pixels.
    """
    from skimage.metrics import structural_similarity

    pred, gt = _as_float(pred), _as_float(gt)
    _check_pair(pred, gt)
    if pred.ndim not in (2, 3):
        raise ValueError(f"ssim expects (H, W) or (H, W, C) images, got {pred.shape}")
    side = min(pred.shape[:2])
    win = min(7, side if side % 2 == 1 else side - 1)
    if win < 3:
        raise ValueError(f"image too small for SSIM: {pred.shape}")
    channel_axis = -1 if pred.ndim == 3 else None
    mean, smap = structural_similarity(pred, gt, data_range=1.0, channel_axis=channel_axis, win_size=win,
                                       full=True)
    if mask is None:
        return float(mean)
    m = _pixel_mask(mask, smap)
    return float(np.mean(smap[m])) if m.any() else math.nan


def scale_align(pred, gt, mask=None, method: str = "lstsq") -> tuple[np.ndarray, np.ndarray]:
    """Per-channel scale s (C,) that best maps pred onto gt over the mask; returns (pred * s, s).

    pred, gt: (..., H, W, C) linear values, e.g. a stack of views (N, H, W, 3) to share one scale;
    mask: (..., H, W) or None. method "lstsq" (NeRFactor) or "median" (TensoIR), see the module doc.
    A channel with no usable pixel keeps scale 1.
    """
    if method not in SCALE_METHODS:
        raise ValueError(f"unknown scale method '{method}' (use {' or '.join(SCALE_METHODS)})")
    pred, gt = _as_float(pred), _as_float(gt)
    _check_pair(pred, gt)
    if pred.ndim < 3:
        raise ValueError(f"scale_align expects (..., H, W, C) images, got {pred.shape}")
    c = pred.shape[-1]
    if mask is None:
        p, g = pred.reshape(-1, c), gt.reshape(-1, c)
    else:
        m = np.asarray(mask).astype(bool)
        if m.shape != pred.shape[:-1]:
            raise ValueError(f"mask of shape {m.shape} does not match images of shape {pred.shape}")
        p, g = pred[m], gt[m]
    scales = np.ones(c)
    for k in range(c):
        if method == "lstsq":
            den = float(np.sum(p[:, k] * p[:, k]))
            if den > _EPS:
                scales[k] = float(np.sum(p[:, k] * g[:, k])) / den
        else:
            ok = p[:, k] > _EPS
            if ok.any():
                scales[k] = float(np.median(g[ok, k] / p[ok, k]))
    return pred * scales, scales


def srgb(linear) -> np.ndarray:
    """sRGB encoding of linear values clipped to [0, 1] (the space colour images are compared in)."""
    return linear_to_srgb(np.asarray(linear))


def image_metrics(pred_linear, gt_linear, mask=None, encode: bool = True) -> dict[str, float]:
    """PSNR and SSIM of one colour image; sRGB-encoded first unless encode=False."""
    if encode:
        p, g = srgb(pred_linear), srgb(gt_linear)
    else:
        p, g = np.clip(_as_float(pred_linear), 0.0, 1.0), np.clip(_as_float(gt_linear), 0.0, 1.0)
    return {"psnr": psnr(p, g, mask), "ssim": ssim(p, g, mask)}


def segmentation_scores(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray | None = None) -> dict:
    """Material segmentation against ground-truth ids (0 = background, ignored).

    Each predicted id is mapped to the ground-truth id it overlaps most (majority mapping, so
    several predicted ids may map to one material: over-segmentation is not punished by the
    mapping itself but shows in the number of materials). Returns micro-F1 (= accuracy over
    pixels, single label), and macro F1 / precision / recall over the ground-truth materials.
    """
    pred = np.asarray(pred).reshape(-1)
    gt = np.asarray(gt).reshape(-1)
    keep = gt > 0 if mask is None else (np.asarray(mask).reshape(-1) & (gt > 0))
    pred, gt = pred[keep], gt[keep]
    if gt.size == 0:
        return {"micro_f1": float("nan"), "macro_f1": float("nan"), "macro_precision": float("nan"),
                "macro_recall": float("nan"), "mapping": {}}
    mapping = {}
    for p in np.unique(pred):
        ids, counts = np.unique(gt[pred == p], return_counts=True)
        mapping[int(p)] = int(ids[np.argmax(counts)])
    mapped = np.array([mapping[int(p)] for p in pred])
    classes = np.unique(gt)
    f1s, precs, recs = [], [], []
    for c in classes:
        tp = np.sum((mapped == c) & (gt == c))
        fp = np.sum((mapped == c) & (gt != c))
        fn = np.sum((mapped != c) & (gt == c))
        prec = tp / (tp + fp) if tp + fp > 0 else 0.0
        rec = tp / (tp + fn) if tp + fn > 0 else 0.0
        precs.append(prec)
        recs.append(rec)
        f1s.append(2 * prec * rec / (prec + rec) if prec + rec > 0 else 0.0)
    return {"micro_f1": float(np.mean(mapped == gt)), "macro_f1": float(np.mean(f1s)),
            "macro_precision": float(np.mean(precs)), "macro_recall": float(np.mean(recs)),
            "mapping": mapping}
