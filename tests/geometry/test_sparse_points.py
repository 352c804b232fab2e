"""Sparse surface points triangulated from posed views (`geometry.sparse_points`), and NeuS's
SDF-is-zero term at them (neus.w_points)."""

import numpy as np
import pytest
import torch

from vq_mitsuba.data.cameras import Camera, camera_rays, look_at
from vq_mitsuba.data.captures import Capture
from vq_mitsuba.geometry import sparse_points as sp

RADIUS = 0.5


def _cameras(n: int, size: int, fov: float = 40.0) -> list[Camera]:
    golden = np.pi * (3 - np.sqrt(5))
    cams = []
    for i in range(n):
        z = 0.6 - 1.0 * (i + 0.5) / n
        r = np.sqrt(1 - z * z)
        d = np.array([r * np.cos(golden * i), r * np.sin(golden * i), z])
        cams.append(Camera(f"v{i}", look_at(2.5 * d, [0, 0, 0], [0, 0, 1]), fov, size, size))
    return cams


def textured_sphere(n_views: int = 16, size: int = 160, waves: int = 40, seed: int = 0) -> Capture:
    """A sphere (radius 0.5 at the origin) painted with a sum of random plane waves of the surface
    point (frequencies 4 to 40 a radian), seen by cameras around it: a texture that stays put on the
    surface from view to view and looks different everywhere."""
    rng = np.random.default_rng(seed)
    freq = rng.normal(size=(waves, 3))
    freq *= (rng.uniform(4, 40, waves) / np.linalg.norm(freq, axis=1))[:, None]
    phase = rng.uniform(0, 2 * np.pi, waves)
    cams = _cameras(n_views, size)
    images, alphas = [], []
    for cam in cams:
        o, d = camera_rays(cam)
        b = np.sum(o * d, 1)
        disc = b * b - (np.sum(o * o, 1) - RADIUS ** 2)
        hit = disc > 0
        t = -b - np.sqrt(np.maximum(disc, 0))
        n = (o + t[:, None] * d) / RADIUS
        paint = 0.5 + 0.5 * np.tanh(2.0 * np.sin(n @ freq.T + phase).mean(1) * np.sqrt(waves))
        value = (0.05 + 0.8 * paint) * (0.4 + 0.6 * np.clip(-np.sum(n * d, 1), 0, 1))
        images.append(np.where(hit[:, None], value[:, None] * np.array([1.0, 0.9, 0.8]), 0.0).reshape(size, size, 3))
        alphas.append(hit.reshape(size, size).astype(np.float32))
    return Capture(Path_("textured_sphere.json"), cams, np.stack(images).astype(np.float32), np.stack(alphas), True,
                   None, None, np.eye(4), "blender")


def Path_(name):
    from pathlib import Path

    return Path(name)


def test_the_projection_matrix_takes_points_on_the_cameras_rays_to_their_pixels():
    cam = Camera("c", look_at([1.0, -2.0, 0.7], [0.1, 0.0, 0.2], [0, 0, 1]), 47.0, 12, 9, focal_y_ratio=1.1,
                 principal=(5.5, 4.8))
    o, d = camera_rays(cam)  # one ray through each pixel centre, row by row
    depth = np.random.default_rng(1).uniform(0.5, 3.0, len(o))
    hom = np.column_stack([o + depth[:, None] * d, np.ones(len(o))]) @ cam.projection().T
    cols, rows = np.meshgrid(np.arange(12) + 0.5, np.arange(9) + 0.5)
    np.testing.assert_allclose(hom[:, :2] / hom[:, 2:], np.column_stack([cols.ravel(), rows.ravel()]), atol=1e-6)
    assert np.all(hom[:, 2] > 0)  # in front of the camera: positive depth


def test_corresponding_pixels_meet_the_epipolar_constraint_and_triangulate_back():
    rng = np.random.default_rng(2)
    cams = _cameras(3, 100)
    pts = rng.uniform(-0.4, 0.4, (20, 3))
    pix = [c.project(pts) for c in cams]
    f = sp.fundamental(cams[0], cams[1])
    ha, hb = (np.column_stack([p, np.ones(20)]) for p in pix[:2])
    assert np.max(np.abs(np.sum(hb * (ha @ f.T), 1))) / np.abs(f).max() < 1e-6
    for k in range(20):
        x = sp.triangulate_track([c.projection() for c in cams], np.array([p[k] for p in pix]))
        np.testing.assert_allclose(x, pts[k], atol=1e-8)


def test_tracks_chain_matches_and_drop_chains_that_meet_a_view_twice():
    matches = {(0, 1): np.array([[0, 0], [1, 1]]), (1, 2): np.array([[0, 3], [1, 4]]),
               (0, 2): np.array([[1, 5]])}  # feature 1 of view 0 meets view 2 twice (4 and 5)
    tracks = sp.tracks(matches, [2, 2, 6])
    assert sorted(map(sorted, tracks)) == [[(0, 0), (1, 0), (2, 3)]]


def test_triangulated_points_lie_on_the_textured_sphere():
    cap = textured_sphere()
    found = sp.triangulate(cap.cameras, cap.images, cap.alpha)
    pts, track = found["points"], found["track"]
    assert len(pts) >= 40 and track.min() >= sp.MIN_VIEWS and found["pairs"] > 0
    off = np.abs(np.linalg.norm(pts, axis=1) - RADIUS) / RADIUS
    assert np.median(off) < 0.01 and np.mean(off < 0.03) > 0.95


def _sphere_points(n: int, radius: float, seed: int = 0) -> np.ndarray:
    d = np.random.default_rng(seed).normal(size=(n, 3))
    return radius * d / np.linalg.norm(d, axis=1, keepdims=True)


def test_neus_uses_the_points_inside_its_hull_and_they_pull_the_surface_onto_them():
    from test_geometry import RADIUS as TRUE_RADIUS, sdf_world, small_cfg, sphere_capture
    from vq_mitsuba.geometry.neus import neus_for, train
    from vq_mitsuba.geometry.neus.training import points_report

    capture = sphere_capture()
    on_surface = _sphere_points(300, TRUE_RADIUS)
    stray = np.array([[5.0, 0.0, 0.0], [0.0, 0.0, -4.0]])  # outside the box: never used
    errors = {}
    for w in (0.0, 50.0):
        cfg = small_cfg(init="sphere", init_radius=0.5, iterations=60, seed=1, w_points=w)
        neus = neus_for(capture, cfg, points=np.concatenate([on_surface, stray]))
        if w > 0:
            assert len(neus.surface_points) == len(on_surface)
        else:
            assert neus.surface_points is None  # the term off: no points kept
        train(neus, None)
        errors[w] = np.abs(sdf_world(neus, on_surface)).mean()
        report = points_report(neus)
        assert report["given"] == len(on_surface) + 2
        assert report["used"] == (len(on_surface) if w > 0 else 0)
    assert errors[50.0] < 0.8 * errors[0.0]  # the same steps: the points pull the zero set onto them


def test_triangulated_points_are_used_where_they_are_dense_enough(monkeypatch):
    from types import SimpleNamespace

    from vq_mitsuba.config import NeuSConfig
    from vq_mitsuba.geometry.neus import method as neus_method

    source = SimpleNamespace(framing=lambda: (None, None))  # a capture without points of its own
    cap = textured_sphere()
    points, info = neus_method.surface_points(source, cap, NeuSConfig())
    n = info["given"]
    assert info["source"] == "triangulated" and n < neus_method.MIN_POINTS_PER_VIEW * len(cap.cameras)
    assert points is None and info["used"] == 0 and f"{n} points over 16 views" in info["skipped"]
    monkeypatch.setattr(neus_method, "MIN_POINTS_PER_VIEW", 2)
    points, info = neus_method.surface_points(source, cap, NeuSConfig())
    assert len(points) == n and "skipped" not in info and info["seconds"] > 0
    assert neus_method.surface_points(source, cap, NeuSConfig(w_points=0.0)) == (None, None)
