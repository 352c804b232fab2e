"""Where the object is when there are no masks: the point the cameras look at, the bounding sphere
they (or the sparse points) frame, and a supporting plane among the sparse points."""

from __future__ import annotations

import math

import numpy as np

from vq_mitsuba.config import NeuSConfig


def _look_center(cameras) -> np.ndarray:
    """Least-squares point closest to all optical axes (where the cameras look)."""
    a, b = np.zeros((3, 3)), np.zeros(3)
    for cam in cameras:
        d = cam.to_world[:3, 2] / np.linalg.norm(cam.to_world[:3, 2])
        p = np.eye(3) - np.outer(d, d)
        a += p
        b += p @ cam.origin
    if np.linalg.cond(a) > 1e8:
        return np.mean([c.origin for c in cameras], 0)
    return np.linalg.solve(a, b)


def _frame_margins(cam, points: np.ndarray) -> np.ndarray:
    """Distance (world units) of each point (N, 3) from the nearest side plane of the camera's
    frustum: positive inside the frustum, negative outside (or behind the camera)."""
    inv = np.linalg.inv(cam.to_world)
    local = points @ inv[:3, :3].T + inv[:3, 3]
    fx, fy, cx, cy = cam.intrinsics()
    # Inward normals of the four side planes (camera space: +X left, +Y up, +Z forward; as camera_rays).
    normals = np.array([[-1.0, 0.0, cx / fx], [1.0, 0.0, (cam.width - cx) / fx],
                        [0.0, -1.0, cy / fy], [0.0, 1.0, (cam.height - cy) / fy]])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    margin = (local @ normals.T).min(1)
    return np.where(local[:, 2] > 0, margin, -np.abs(margin) - 1e-9)


def uses_background_model(capture, cfg: NeuSConfig) -> bool:
    """Whether NeuS trains without masks (a bounding sphere and a background model): with
    `neus.background` model, or auto on a capture without alpha or masks (a `capture.background_color`
    key makes masks, so a keyed capture has them)."""
    return cfg.background == "model" or (cfg.background == "auto" and not capture.has_alpha)


def well_seen(points: np.ndarray, track: np.ndarray | None = None) -> np.ndarray:
    """Sparse points (N, 3) as float64, without those seen by fewer than 3 images when their track
    lengths are known (a track per point, not all 0)."""
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    if track is not None and len(track) == len(pts) and np.max(track, initial=0) > 0:
        pts = pts[np.asarray(track) >= 3]
    return pts


def support_from_points(points: np.ndarray, cameras, sphere: tuple, track: np.ndarray | None = None,
                        min_share: float = 0.2, max_below: float = 0.05,
                        seed: int = 0) -> tuple[np.ndarray, float] | None:
    """A supporting plane (a table) among sparse points: (unit normal towards the cameras, offset c;
    the plane is n.x = c) in the world, or None.

    RANSAC (400 planes through three points) over the points within 1.5 radii of the sphere's centre
    (those seen by 3 or more images, when tracks are known); a plane's inliers lie within 2% of the
    radius of it. The plane with the most inliers among those that nine in ten cameras look down on
    and that have at most max_below of the points beneath them (the cameras cannot see under a
    table; they do see the sides of a wide object under its flat top) counts as a support when it
    holds at least min_share of the points, crosses the sphere, and its inliers run out to the
    sphere (95th-percentile distance from the centre at least 0.9 radii: a table goes on beyond the
    object, a flat top of a small object stops short)."""
    from vq_mitsuba.geometry.mesh import share_beneath

    center, radius = np.asarray(sphere[0], np.float64), float(sphere[1])
    pts = well_seen(points, track)
    pts = pts[np.linalg.norm(pts - center, axis=1) < 1.5 * radius]
    if len(pts) < 20:
        return None
    rng = np.random.default_rng(seed)
    if len(pts) > 20000:
        pts = pts[rng.choice(len(pts), 20000, replace=False)]
    views = np.array([c.origin for c in cameras])
    tol = 0.02 * radius
    best, best_count = None, 0
    for _ in range(400):
        a, b, c = pts[rng.choice(len(pts), 3, replace=False)]
        n = np.cross(b - a, c - a)
        if np.linalg.norm(n) < 1e-12:
            continue
        n /= np.linalg.norm(n)
        off = float(n @ a)
        side = np.sign(views @ n - off)
        if max(np.mean(side > 0), np.mean(side < 0)) < 0.9:
            continue
        if share_beneath(pts, n, off, views, tol) > max_below:
            continue
        count = int(np.sum(np.abs(pts @ n - off) < tol))
        if count > best_count:
            best, best_count = (n, off), count
    if best is None or best_count < min_share * len(pts):
        return None
    n, off = best
    inliers = pts[np.abs(pts @ n - off) < tol]
    mean = inliers.mean(0)
    n_fit = np.linalg.eigh(np.cov((inliers - mean).T))[1][:, 0]  # least-squares refit
    n = n_fit if n_fit @ n >= 0 else -n_fit
    off = float(n @ mean)
    if np.mean(views @ n - off > 0) < 0.5:
        n, off = -n, -off
    reach = float(np.percentile(np.linalg.norm(inliers - center, axis=1), 95))
    if (abs(float(n @ center) - off) >= 0.9 * radius or reach < 0.9 * radius
            or share_beneath(pts, n, off, views, tol) > max_below):
        return None
    return n, off


def bounding_sphere(cameras, points: np.ndarray | None = None, track: np.ndarray | None = None,
                    min_views: float = 0.75, point_views: float = 0.3) -> tuple[np.ndarray, float, str]:
    """(centre, radius, what framed it) of the sphere the object is taken to live in, without masks.

    From the cameras: centred on the point closest to all optical axes, the largest sphere there
    that at least `min_views` of the views frame whole (the region the cameras all look at).
    With sparse points (N, 3) (and their track lengths: points seen by fewer than 3 images are
    left out when tracks are known): the points inside the frusta of at least `point_views` of the
    views, when there are 20 or more, give the sphere instead: centred between their 2nd and 98th
    percentiles per axis, radius 1.1 x their 95th-percentile distance from it, at most twice the
    cameras' sphere (stray points far off are background). `point_views` is lower than
    `min_views` because close-ups crop the object: asking 3 in 4 views to frame a point leaves out
    the ends of an object wider than most frames (as the visual hull's `neus.hull_min_views`)."""
    center = _look_center(cameras)
    need = max(1, int(math.ceil(min_views * len(cameras))))
    margins = np.array([_frame_margins(cam, center[None])[0] for cam in cameras])
    # the need-th largest margin: the sphere that `need` views frame whole
    r_cam = float(np.sort(margins)[::-1][need - 1])
    if r_cam <= 0:  # the look centre is outside too many views: frame what most views hold
        r_cam = 0.5 * min(float(np.linalg.norm(c.origin - center)) for c in cameras)
    source = "cameras"
    if points is not None and len(points):
        pts = well_seen(points, track)
        if len(pts):
            seen = np.sum([_frame_margins(cam, pts) > 0 for cam in cameras], 0)
            pts = pts[seen >= max(1, int(math.ceil(point_views * len(cameras))))]
        if len(pts) >= 20:
            lo, hi = np.percentile(pts, 2, axis=0), np.percentile(pts, 98, axis=0)
            c = 0.5 * (lo + hi)
            r = 1.1 * float(np.percentile(np.linalg.norm(pts - c, axis=1), 95))
            if r > 0:
                return c, min(r, 2.0 * r_cam), "sparse points"
    return center, r_cam, source


def box_footprint_px(cameras, center: np.ndarray, half: float) -> float:
    """The working box's width in pixels in the median view (its size over the distance to its centre)."""
    return float(np.median([2.0 * half * cam.focal_px() / max(float(np.linalg.norm(cam.origin - center)), 1e-12)
                            for cam in cameras]))
