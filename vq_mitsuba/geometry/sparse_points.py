"""Sparse surface points of a posed capture, triangulated with its own cameras.

Photo folders and videos get their points from posing (COLMAP's points3D), and so do COLMAP
captures; posed captures without points (NeuS/IDR, LLFF, nerfstudio, NeRF json) get them here:
SIFT features in every view (inside its mask, where it has one), matched between each view and its
nearest views (mutual nearest neighbours, Lowe's ratio test, and the epipolar line the known cameras
give), chained into tracks across views, and each track seen by at least MIN_VIEWS views triangulated
linearly and kept when it reprojects within REPROJECTION_PX pixels into every view of it and lies in
front of each camera. The result is what `points3D` gives: positions (N, 3) in the capture's world
and each one's track length.
"""

from __future__ import annotations

import time
import warnings

import numpy as np

from vq_mitsuba.backend import import_pycolmap
from vq_mitsuba.data.cameras import Camera
from vq_mitsuba.data.imageio import LUMINANCE, linear_to_srgb

MIN_VIEWS = 3  # a point seen by fewer views is not kept (SfM's usual floor for a trusted point)
NEIGHBOURS = 6  # views each view is matched with: its nearest by viewing direction
MAX_ANGLE_DEG = 60.0  # views further apart than this are not matched (too few shared features)
MAX_FEATURES = 4096  # SIFT features per view
RATIO = 0.8  # Lowe's ratio test on descriptor distances
EPIPOLAR_PX = 2.0  # a match further from the epipolar line of the known cameras is dropped
REPROJECTION_PX = 2.0  # a track whose point lands further from one of its features is dropped


def _gray(image: np.ndarray) -> np.ndarray:
    """A linear RGB image (H, W, 3) as 8-bit sRGB luminance."""
    lum = image[..., :3] @ np.array(LUMINANCE, dtype=np.float32)
    return np.ascontiguousarray(np.round(linear_to_srgb(lum) * 255.0).astype(np.uint8))


def features(images: np.ndarray, alpha: np.ndarray | None) -> list[tuple[np.ndarray, np.ndarray]]:
    """Each view's SIFT keypoints (K, 2) in pixels (centres at +0.5) and descriptors (K, 128), only
    those inside the view's mask when `alpha` is given."""
    pycolmap = import_pycolmap()

    options = pycolmap.FeatureExtractionOptions()
    options.sift.max_num_features = MAX_FEATURES
    options.sift.max_num_orientations = 1  # one feature per place: two would make twin tracks
    options.use_gpu = False
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        sift = pycolmap.Sift(options, pycolmap.Device.cpu)
    out = []
    for i, image in enumerate(images):
        kp, desc = sift.extract(_gray(image))
        xy = np.asarray(kp[:, :2], np.float64)  # COLMAP's pixel centres are at +0.5, as ours
        if alpha is not None:
            h, w = alpha.shape[1:3]
            col = np.clip(xy[:, 0].astype(int), 0, w - 1)
            row = np.clip(xy[:, 1].astype(int), 0, h - 1)
            keep = alpha[i, row, col] > 0.5
            xy, desc = xy[keep], desc[keep]
        out.append((xy, np.asarray(desc, np.float32)))
    return out


def view_pairs(cameras: list[Camera], neighbours: int = NEIGHBOURS, max_angle_deg: float = MAX_ANGLE_DEG) \
        -> list[tuple[int, int]]:
    """Pairs (i, j), i < j, of views among each view's `neighbours` nearest by viewing direction,
    within `max_angle_deg` of each other."""
    fwd = np.stack([c.to_world[:3, 2] for c in cameras])
    fwd /= np.linalg.norm(fwd, axis=1, keepdims=True)
    cos = fwd @ fwd.T
    np.fill_diagonal(cos, -2.0)
    pairs = set()
    for i in range(len(cameras)):
        for j in np.argsort(-cos[i])[:neighbours]:
            if cos[i, j] >= np.cos(np.radians(max_angle_deg)):
                pairs.add((min(i, int(j)), max(i, int(j))))
    return sorted(pairs)


def fundamental(a: Camera, b: Camera) -> np.ndarray:
    """F with x_b^T F x_a = 0 for pixels x_a, x_b of one world point (homogeneous)."""
    pa, pb = a.projection(), b.projection()
    centre = np.append(a.origin, 1.0)
    e = pb @ centre
    ex = np.array([[0.0, -e[2], e[1]], [e[2], 0.0, -e[0]], [-e[1], e[0], 0.0]])
    return ex @ pb @ np.linalg.pinv(pa)


def match(da: np.ndarray, db: np.ndarray, xa: np.ndarray, xb: np.ndarray, f: np.ndarray,
          ratio: float = RATIO, epipolar_px: float = EPIPOLAR_PX) -> np.ndarray:
    """Matches (M, 2) of feature indices between two views: mutual nearest neighbours passing the
    ratio test, within `epipolar_px` (symmetric epipolar distance) of the known geometry."""
    if len(da) < 2 or len(db) < 2:
        return np.zeros((0, 2), np.int64)
    sim = da @ db.T
    dist = np.sqrt(np.maximum(2.0 - 2.0 * sim, 0.0))  # unit descriptors
    best_b = np.argmin(dist, axis=1)
    best_a = np.argmin(dist, axis=0)
    two = np.partition(dist, 1, axis=1)[:, :2]
    ia = np.arange(len(da))
    keep = (best_a[best_b] == ia) & (two[:, 0] < ratio * two[:, 1])
    ia, ib = ia[keep], best_b[keep]
    ha = np.column_stack([xa[ia], np.ones(len(ia))])
    hb = np.column_stack([xb[ib], np.ones(len(ib))])
    lb = ha @ f.T  # epipolar lines in b
    la = hb @ f  # in a
    d_b = np.abs(np.sum(hb * lb, 1)) / np.maximum(np.hypot(lb[:, 0], lb[:, 1]), 1e-12)
    d_a = np.abs(np.sum(ha * la, 1)) / np.maximum(np.hypot(la[:, 0], la[:, 1]), 1e-12)
    ok = np.maximum(d_a, d_b) < epipolar_px
    return np.column_stack([ia[ok], ib[ok]])


def tracks(matches: dict[tuple[int, int], np.ndarray], counts: list[int]) -> list[list[tuple[int, int]]]:
    """Features chained across views by their matches (union-find): each track a list of (view,
    feature); tracks holding two features of one view are dropped (an inconsistent chain)."""
    offsets = np.concatenate([[0], np.cumsum(counts)])
    parent = np.arange(int(offsets[-1]))

    def root(x: int) -> int:
        while parent[x] != x:
            parent[x] = parent[parent[x]]
            x = parent[x]
        return x

    for (a, b), m in matches.items():
        for fa, fb in m:
            ra, rb = root(int(offsets[a] + fa)), root(int(offsets[b] + fb))
            if ra != rb:
                parent[max(ra, rb)] = min(ra, rb)
    groups: dict[int, list[int]] = {}
    for node in {int(offsets[a] + f) for (a, b), m in matches.items() for f in m[:, 0]} | \
            {int(offsets[b] + f) for (a, b), m in matches.items() for f in m[:, 1]}:
        groups.setdefault(root(node), []).append(node)
    out = []
    for nodes in groups.values():
        views = np.searchsorted(offsets, nodes, side="right") - 1
        if len(set(views.tolist())) != len(nodes):
            continue
        out.append([(int(v), int(n - offsets[v])) for v, n in zip(views, nodes)])
    return out


def triangulate_track(projections: list[np.ndarray], pixels: np.ndarray) -> np.ndarray:
    """The world point (3,) whose projections best meet `pixels` (K, 2) in the linear (DLT) sense."""
    rows = []
    for p, (x, y) in zip(projections, pixels):
        rows.append(x * p[2] - p[0])
        rows.append(y * p[2] - p[1])
    a = np.asarray(rows)
    a /= np.maximum(np.linalg.norm(a, axis=1, keepdims=True), 1e-12)
    v = np.linalg.svd(a)[2][-1]
    return v[:3] / v[3] if abs(v[3]) > 1e-12 else np.full(3, np.nan)


def triangulate(cameras: list[Camera], images: np.ndarray, alpha: np.ndarray | None = None,
                min_views: int = MIN_VIEWS) -> dict:
    """Sparse points of posed views: {"points": (N, 3) world, "track": (N,) views seeing each,
    "views": len(cameras), "pairs": pairs matched, "seconds": wall time}."""
    t0 = time.perf_counter()
    feats = features(images, alpha)
    projections = [c.projection() for c in cameras]
    pairs = view_pairs(cameras)
    matches = {(a, b): match(feats[a][1], feats[b][1], feats[a][0], feats[b][0], fundamental(cameras[a], cameras[b]))
               for a, b in pairs}
    points, track = [], []
    for t in tracks(matches, [len(f[0]) for f in feats]):
        if len(t) < min_views:
            continue
        views = [v for v, _ in t]
        pix = np.array([feats[v][0][f] for v, f in t])
        x = triangulate_track([projections[v] for v in views], pix)
        if not np.all(np.isfinite(x)):
            continue
        hom = np.append(x, 1.0)
        proj = np.array([projections[v] @ hom for v in views])
        depth = proj[:, 2]
        err = np.linalg.norm(proj[:, :2] / np.where(np.abs(depth) > 1e-12, depth, 1e-12)[:, None] - pix, axis=1)
        if np.all(depth > 0) and np.all(err < REPROJECTION_PX):
            points.append(x)
            track.append(len(t))
    return {"points": np.asarray(points, np.float64).reshape(-1, 3), "track": np.asarray(track, np.int64),
            "views": len(cameras), "pairs": len(pairs), "seconds": time.perf_counter() - t0}
