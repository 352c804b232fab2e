"""Image metrics against hand-computed values (vq_mitsuba.eval.metrics)."""

import math

import numpy as np
import pytest

from vq_mitsuba.eval import metrics as M
from vq_mitsuba.eval.evaluate import format_table, json_safe


def _image(h=24, w=20, c=3, seed=0):
    return np.random.default_rng(seed).uniform(0.05, 0.95, size=(h, w, c))


def test_psnr_identical_is_inf():
    img = _image()
    assert M.psnr(img, img) == math.inf
    assert M.psnr(img, img, mask=np.ones(img.shape[:2], bool)) == math.inf


def test_psnr_known_mse():
    gt = np.zeros((8, 8, 3))
    pred = gt + 0.1  # MSE = 0.01 -> 10 log10(1 / 0.01) = 20 dB
    assert M.psnr(pred, gt) == pytest.approx(20.0, abs=1e-9)
    pred = gt.copy()
    pred[0, 0, 0] = 1.0  # one squared error of 1 among 192 values: MSE = 1/192
    assert M.psnr(pred, gt) == pytest.approx(10 * math.log10(192), abs=1e-9)
    # The peak enters as peak^2: at peak 2 the same MSE of 0.01 gives 20 + 20 log10(2) dB.
    assert M.psnr(gt + 0.1, gt, peak=2.0) == pytest.approx(20.0 + 20 * math.log10(2.0), abs=1e-9)


def test_masked_psnr_ignores_outside_pixels():
    gt = np.full((10, 10, 3), 0.5)
    pred = gt.copy()
    mask = np.zeros((10, 10), bool)
    mask[:5] = True
    pred[~mask] = 0.0  # large error outside the mask only
    pred[mask] += 0.01  # MSE 1e-4 inside -> 40 dB
    assert M.psnr(pred, gt, mask) == pytest.approx(40.0, abs=1e-9)
    assert M.psnr(pred, gt) < 20.0
    # Scalar maps (H, W) take the same (H, W) mask.
    assert M.psnr(pred[..., 0], gt[..., 0], mask) == pytest.approx(40.0, abs=1e-9)


def test_empty_mask_is_nan_and_shape_mismatch_raises():
    img = _image()
    assert math.isnan(M.psnr(img, img * 0.5, np.zeros(img.shape[:2], bool)))
    with pytest.raises(ValueError):
        M.psnr(img, img[:-1])
    with pytest.raises(ValueError):
        M.psnr(img, img, np.ones((3, 3), bool))


def test_ssim_identical_is_one_and_noisy_below():
    img = _image(32, 32)
    assert M.ssim(img, img) == pytest.approx(1.0, abs=1e-12)
    noisy = np.clip(img + np.random.default_rng(1).normal(0, 0.05, img.shape), 0, 1)
    s = M.ssim(noisy, img)
    assert 0.0 < s < 0.99
    mask = np.zeros((32, 32), bool)
    mask[8:24, 8:24] = True
    assert M.ssim(img, img, mask) == pytest.approx(1.0, abs=1e-12)
    assert M.ssim(noisy, img, mask) < 0.99
    assert M.ssim(img[..., 0], img[..., 0]) == pytest.approx(1.0, abs=1e-12)


def test_ssim_mask_averages_the_map():
    from skimage.metrics import structural_similarity

    img = _image(32, 32)
    noisy = np.clip(img + np.random.default_rng(2).normal(0, 0.1, img.shape), 0, 1)
    mask = np.zeros((32, 32), bool)
    mask[4:20, 10:30] = True
    _, smap = structural_similarity(noisy, img, data_range=1.0, channel_axis=-1, full=True)
    assert M.ssim(noisy, img, mask) == pytest.approx(float(smap[mask].mean()), rel=1e-12)


@pytest.mark.parametrize("method", M.SCALE_METHODS)
def test_scale_align_removes_per_channel_factor(method):
    gt = _image(16, 16)
    factors = np.array([2.0, 3.0, 0.5])
    pred = gt / factors  # gt = pred * factors
    aligned, scales = M.scale_align(pred, gt, np.ones((16, 16), bool), method=method)
    np.testing.assert_allclose(scales, factors, rtol=1e-12)
    np.testing.assert_allclose(aligned, gt, rtol=1e-12)
    assert M.psnr(aligned, gt) > 200.0  # exact up to rounding


@pytest.mark.parametrize("method", M.SCALE_METHODS)
def test_scale_align_uses_only_masked_pixels_and_stacks(method):
    gt = np.stack([_image(8, 8, seed=s) for s in range(3)])  # (N, H, W, 3): one scale for all views
    pred = gt / np.array([2.0, 3.0, 0.5])
    mask = np.zeros((3, 8, 8), bool)
    mask[:, 2:6, 2:6] = True
    pred[~mask] = 100.0  # garbage outside the mask must not influence the scales
    _, scales = M.scale_align(pred, gt, mask, method=method)
    np.testing.assert_allclose(scales, [2.0, 3.0, 0.5], rtol=1e-12)


def test_scale_align_lstsq_formula_and_bad_method():
    pred = np.array([[[1.0], [2.0]]])  # (1, 2, 1)
    gt = np.array([[[1.0], [3.0]]])
    _, s = M.scale_align(pred, gt, method="lstsq")
    assert s[0] == pytest.approx((1 * 1 + 2 * 3) / (1 + 4))  # sum(p g) / sum(p p)
    _, s = M.scale_align(pred, gt, method="median")
    assert s[0] == pytest.approx(np.median([1.0, 1.5]))
    with pytest.raises(ValueError):
        M.scale_align(pred, gt, method="mean")


def test_image_metrics_compare_in_srgb():
    gt = np.full((16, 16, 3), 0.2)
    pred = np.full((16, 16, 3), 0.25)
    out = M.image_metrics(pred, gt)
    err = float(M.srgb(0.25) - M.srgb(0.2))
    assert out["psnr"] == pytest.approx(-10 * math.log10(err * err), rel=1e-5)
    # Values above 1 are clipped before encoding: an overexposed prediction of a white GT is exact.
    assert M.image_metrics(np.full((16, 16, 3), 3.0), np.ones((16, 16, 3)))["psnr"] == math.inf


def test_format_table_and_json_safe():
    metrics = {
        "scene": "demo", "n_views": 2, "render": {"spp": 8, "aa": 4}, "mask": "gt alpha > 0.5",
        "novel_view": {"psnr": 25.0, "ssim": 0.9}, "basecolor": {"psnr": 20.0, "ssim": 0.8},
        "alignment": {"method": "lstsq", "scales": [1.0, 0.9, 1.1]},
        "metallic": {"psnr": math.inf}, "roughness": {"psnr": 12.0}, "normal": {"mae_deg": 1.5},
        "relighting": {v: {"envs": {"sunset": {"psnr": 21.0, "ssim": 0.85}}, "mean": {"psnr": 21.0, "ssim": 0.85}}
                       for v in ("albedo_scale", "image_scale")},
    }
    table = format_table(metrics)
    assert "basecolor (lstsq-aligned)" in table and "relit sunset (image_scale)" in table and "inf" in table
    assert json_safe({"a": [math.inf, math.nan, np.float32(1.5)]}) == {"a": ["inf", "nan", 1.5]}


def test_segmentation_scores_permuted_labels_give_one():
    from vq_mitsuba.eval.metrics import segmentation_scores

    gt = np.array([[0, 1, 1, 2], [2, 3, 3, 0]])
    perm = {0: 0, 1: 7, 2: 4, 3: 1}
    pred = np.vectorize(perm.get)(gt)
    s = segmentation_scores(pred, gt)
    assert s["micro_f1"] == 1.0 and s["macro_f1"] == 1.0
    assert s["mapping"] == {7: 1, 4: 2, 1: 3}


def test_segmentation_scores_hand_computed():
    from vq_mitsuba.eval.metrics import segmentation_scores

    gt = np.array([1, 1, 1, 1, 2, 2, 0])
    pred = np.array([5, 5, 5, 6, 6, 6, 5])  # 6 -> 2 (2 of 3), one pixel of material 1 is wrong
    s = segmentation_scores(pred, gt)
    assert s["micro_f1"] == pytest.approx(5 / 6)
    # material 1: P = 3/3, R = 3/4; material 2: P = 2/3, R = 2/2
    f1_1, f1_2 = 2 * 1 * 0.75 / 1.75, 2 * (2 / 3) / (5 / 3)
    assert s["macro_f1"] == pytest.approx((f1_1 + f1_2) / 2)
    assert s["macro_precision"] == pytest.approx((1 + 2 / 3) / 2)
    assert s["macro_recall"] == pytest.approx((0.75 + 1) / 2)


def test_training_srgb_mse_matches_numpy_encoding():
    import torch

    from vq_mitsuba.models import losses
    from vq_mitsuba.data.imageio import linear_to_srgb

    rng = np.random.default_rng(3)
    a = rng.uniform(-0.1, 1.5, (500, 3)).astype(np.float32)  # out-of-range values are clipped by both
    b = rng.uniform(0.0, 1.0, (500, 3)).astype(np.float32)
    a[:10] = 0.001  # the linear segment of the sRGB curve
    expected = np.mean((linear_to_srgb(a) - linear_to_srgb(b)) ** 2)
    got = float(losses.srgb_mse(torch.as_tensor(a), torch.as_tensor(b)))
    assert abs(got - expected) < 1e-6 * max(expected, 1.0)


def test_meanshift_baseline_separates_distinct_materials():
    from vq_mitsuba.eval.baselines import brdf_features, meanshift_labels

    rng = np.random.default_rng(0)
    # Three materials: red diffuse, grey metal, green plastic; small per-pixel noise.
    truth = rng.integers(1, 4, 3000)
    bc = np.array([[0.6, 0.05, 0.05], [0.8, 0.8, 0.8], [0.05, 0.4, 0.1]])[truth - 1]
    met = np.array([0.0, 1.0, 0.0])[truth - 1]
    rough = np.array([0.8, 0.2, 0.3])[truth - 1]
    feats = brdf_features(bc, met, rough) + rng.normal(0, 0.02, (3000, 5))
    labels = meanshift_labels(feats, 0.3, max_fit=1500)
    assert labels.min() == 1 and len(np.unique(labels)) == 3
    assert M.segmentation_scores(labels, truth)["micro_f1"] > 0.99
    # A bandwidth wider than the distances between materials merges them.
    assert len(np.unique(meanshift_labels(feats, 5.0))) == 1
