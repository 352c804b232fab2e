"""Baselines the discrete branch is compared with.

MeanShift segmentation (the VQ-NeRF paper's baseline): cluster the continuous branch's BRDF
outputs per pixel, in the space [sRGB basecolor, metallic, roughness] (every axis in [0, 1]),
with a fixed bandwidth; the number of materials is the number of clusters found.
"""

from __future__ import annotations

import numpy as np

MEANSHIFT_BANDWIDTHS = (0.2, 0.3, 0.5)


def brdf_features(basecolor_linear: np.ndarray, metallic: np.ndarray, roughness: np.ndarray) -> np.ndarray:
    """(N, 5) features: sRGB basecolor, metallic, roughness."""
    from vq_mitsuba.eval.metrics import srgb

    bc = srgb(np.asarray(basecolor_linear, dtype=np.float64).reshape(-1, 3))
    return np.concatenate([bc, np.asarray(metallic, dtype=np.float64).reshape(-1, 1),
                           np.asarray(roughness, dtype=np.float64).reshape(-1, 1)], axis=1)


def meanshift_labels(features: np.ndarray, bandwidth: float, max_fit: int = 4000, seed: int = 0) -> np.ndarray:
    """Cluster ids 1..C (ordered by cluster size, largest first) for every row of `features`.

    MeanShift is quadratic in the number of points, so the modes are found on a random subset of
    at most `max_fit` rows; every row then takes its nearest mode."""
    from sklearn.cluster import MeanShift

    x = np.asarray(features, dtype=np.float64)
    if x.ndim != 2 or len(x) == 0:
        raise ValueError("meanshift_labels needs a non-empty (N, D) feature array")
    rng = np.random.default_rng(seed)
    sub = x[rng.choice(len(x), size=min(max_fit, len(x)), replace=False)]
    ms = MeanShift(bandwidth=bandwidth, bin_seeding=True, cluster_all=True).fit(sub)
    centres = ms.cluster_centers_
    d = ((x[:, None, :] - centres[None, :, :]) ** 2).sum(-1)
    nearest = np.argmin(d, axis=1)
    order = np.argsort(-np.bincount(nearest, minlength=len(centres)))  # largest cluster -> id 1
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    return rank[nearest] + 1
