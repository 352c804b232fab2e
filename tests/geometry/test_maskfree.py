"""Geometry without masks: NeuS in a bounding sphere with a background model, and the masks the
material fit gets from the reconstructed mesh."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import trimesh

from vq_mitsuba.config import CaptureConfig, load_config
from vq_mitsuba.data.cameras import Camera, look_at
from vq_mitsuba.data.captures import Capture, finish_capture
from vq_mitsuba.errors import InputError
from vq_mitsuba.geometry.mesh import marching_cubes, mesh_coverage, support_plane
from vq_mitsuba.geometry.neus import bounding_sphere, mesh_export, support_from_points, train, uses_background_model
from vq_mitsuba.geometry.neus import extract_mesh, render_view
from vq_mitsuba.geometry.neus import neus_for


def orbit(n: int, dist: float, size: int = 40, center=(0.0, 0.0, 0.0), fov: float = 40.0, y_range=(0.85, -0.85),
          up=(0.0, 1.0, 0.0)) -> list[Camera]:
    """n cameras on a golden spiral around `center` (heights y_range of the unit sphere), looking at it."""
    golden = np.pi * (3 - np.sqrt(5))
    cams = []
    for i in range(n):
        y = y_range[0] + (y_range[1] - y_range[0]) * (i + 0.5) / n
        r = np.sqrt(1 - y * y)
        origin = np.asarray(center) + dist * np.array([r * np.cos(golden * i), y, r * np.sin(golden * i)])
        cams.append(Camera(f"view_{i:02d}", look_at(origin, center, up), fov, size, size))
    return cams


def textured_env(height: int = 32, seed: int = 3) -> np.ndarray:
    """A lat-long map of 8 x 16 blocks of random colours over a vertical gradient: a busy backdrop."""
    rng = np.random.default_rng(seed)
    blocks = rng.uniform(0.05, 1.0, size=(8, 16, 3))
    env = np.repeat(np.repeat(blocks, height // 8, 0), 2 * height // 16, 1)
    v = (np.arange(height) + 0.5)[:, None, None] / height
    return (env * (0.6 + 0.8 * (1 - v))).astype(np.float32)


def _box_ball_and_env(out: Path, ball_y: float):
    """The box and the ball (written as out/box.ply, out/ball.ply) and the busy environment
    (out/env.exr) as a Mitsuba emitter: (box, ball, env)."""
    from vq_mitsuba.data.imageio import write_exr

    out.mkdir(parents=True, exist_ok=True)
    box = trimesh.creation.box((0.5, 0.35, 0.5))
    box.apply_translation((0.2, -0.1, 0.05))
    ball = trimesh.creation.icosphere(3, 0.28)
    ball.apply_translation((-0.22, ball_y, -0.05))
    box.export(out / "box.ply")
    ball.export(out / "ball.ply")
    write_exr(out / "env.exr", textured_env())
    return box, ball, {"type": "envmap", "filename": str(out / "env.exr")}


def textured_backdrop_scene(out: Path, n_views: int = 16, size: int = 40, spp: int = 32):
    """A box and a ball (Mitsuba world) under a busy environment that is also the visible backdrop.
    Each view is rendered twice (the objects with alpha, and the environment alone) and composited,
    so the true alpha is known. Returns (images (N, H, W, 3) linear, true alpha, cameras, mesh)."""
    import mitsuba as mi

    from vq_mitsuba.backend import init_mitsuba

    init_mitsuba()
    box, ball, env = _box_ball_and_env(out, ball_y=0.1)

    def principled(rgb, roughness):
        return {"type": "principled", "base_color": {"type": "rgb", "value": rgb}, "roughness": roughness}

    objects = mi.load_dict({
        "type": "scene", "integrator": {"type": "path", "max_depth": 3, "hide_emitters": True}, "env": env,
        "box": {"type": "ply", "filename": str(out / "box.ply"), "bsdf": principled([0.8, 0.6, 0.2], 0.5)},
        "ball": {"type": "ply", "filename": str(out / "ball.ply"), "bsdf": principled([0.2, 0.4, 0.8], 0.3)}})
    backdrop = mi.load_dict({"type": "scene", "integrator": {"type": "path", "max_depth": 1}, "env": env})
    cams = orbit(n_views, 2.4, size)
    images, alphas = [], []
    for i, cam in enumerate(cams):
        sensor = mi.load_dict(cam.to_mitsuba_dict(spp))
        fg = np.array(mi.render(objects, sensor=sensor, seed=i))
        bg = np.array(mi.render(backdrop, sensor=sensor, seed=1000 + i))[..., :3]
        images.append(fg[..., :3] + (1.0 - fg[..., 3:4]) * bg)  # premultiplied colour over the backdrop
        alphas.append(fg[..., 3])
    return (np.stack(images).astype(np.float32), np.stack(alphas).astype(np.float32), cams,
            trimesh.util.concatenate([box, ball]))


@pytest.fixture(scope="module")
def backdrop_views(tmp_path_factory):
    return textured_backdrop_scene(tmp_path_factory.mktemp("backdrop"))


def unmasked(images, cams) -> Capture:
    return Capture(Path("textured_backdrop.xml"), cams, images, np.ones(images.shape[:3], np.float32), False,
                   None, None, np.eye(4), "mitsuba")


def tiny_cfg(**kw):
    base = dict(batch_rays=256, n_samples=16, levels=3, base_res=8, max_res=24, hidden=32, hull_resolution=48,
                march_steps=64, mesh_resolution=48, checkpoint_every=0, warmup=10, threads=1)
    base.update(kw)
    return load_config(None, [f"neus.{k}={v}" for k, v in base.items()]).neus


def iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / max((a | b).sum(), 1))


# --------------------------------------------------------------------------------------------
# When the mode is on, and the sphere


def test_background_model_switches_on_exactly_without_masks_and_background_colour():
    cams = orbit(4, 2.5, 16)
    images = np.full((4, 16, 16, 3), 0.2, np.float32)
    images[:, 5:11, 5:11] = 0.8
    bare = unmasked(images, cams)
    masked = dataclasses.replace(bare, alpha=(images[..., 0] > 0.5).astype(np.float32), has_alpha=True)
    keyed = finish_capture(bare, CaptureConfig(background_color="0.48,0.48,0.48"))  # sRGB of 0.2 linear
    assert keyed.has_alpha
    for capture, auto in ((bare, True), (masked, False), (keyed, False)):
        assert uses_background_model(capture, tiny_cfg()) is auto
        assert uses_background_model(capture, tiny_cfg(background="model")) is True
        assert uses_background_model(capture, tiny_cfg(background="masks")) is False
    assert neus_for(bare, tiny_cfg()).box.mask_free and not neus_for(masked, tiny_cfg()).box.mask_free
    with pytest.raises(InputError, match="neus.background is masks"):
        neus_for(bare, tiny_cfg(background="masks"))
    with pytest.raises(InputError, match="expects one of|must be one of|background"):
        tiny_cfg(background="sometimes")


def test_bounding_sphere_from_the_cameras_is_what_they_all_frame():
    center = np.array([0.3, -0.2, 0.1])
    cams = orbit(12, 3.0, 32, center=center)
    c, r, source = bounding_sphere(cams)
    assert source == "cameras"
    np.testing.assert_allclose(c, center, atol=1e-6)
    # square images with a 40-degree field of view: the sphere touching the frame is 3 sin(20 deg)
    assert r == pytest.approx(3.0 * np.sin(np.radians(20.0)), rel=1e-6)


def test_bounding_sphere_from_sparse_points_ignores_the_background_points():
    cams = orbit(12, 3.0, 32)
    rng = np.random.default_rng(0)
    obj_center = np.array([0.2, 0.1, -0.1])
    d = rng.normal(size=(400, 3))
    obj = obj_center + 0.3 * d / np.linalg.norm(d, axis=1, keepdims=True)  # a ball of radius 0.3
    far = rng.uniform(-8, 8, size=(300, 3))
    far = far[np.linalg.norm(far, axis=1) > 5]  # walls and clutter no view frames with the others
    c, r, source = bounding_sphere(cams, np.concatenate([obj, far]))
    assert source == "sparse points"
    np.testing.assert_allclose(c, obj_center, atol=0.03)
    assert 0.3 < r < 0.4  # 1.1 x the 95th-percentile distance
    # Points seen by fewer than three images do not count when tracks are known.
    track = np.r_[np.full(len(obj), 5), np.full(len(far), 2)]
    noisy = np.concatenate([obj, rng.uniform(-1, 1, size=(len(far), 3))])
    c2, r2, _ = bounding_sphere(cams, noisy, track)
    np.testing.assert_allclose(c2, obj_center, atol=0.03)
    assert r2 < 0.4
    # Too few points: the cameras' sphere.
    assert bounding_sphere(cams, obj[:5])[2] == "cameras"


def table_points(rng, n_table: int = 600, n_object: int = 300, top: float = -0.3) -> tuple[np.ndarray, np.ndarray]:
    """Sparse points of a table top y = top (a disc of radius 2) and of a box (0.5 wide) standing on it."""
    r, a = 2.0 * np.sqrt(rng.uniform(size=n_table)), rng.uniform(0, 2 * np.pi, n_table)
    table = np.stack([r * np.cos(a), np.full(n_table, top), r * np.sin(a)], 1)
    box = trimesh.creation.box((0.5, 0.5, 0.5))
    box.apply_translation((0.0, top + 0.25, 0.0))
    return table, trimesh.sample.sample_surface(box, n_object, seed=1)[0]


def test_support_from_points_finds_the_table_not_the_top_of_the_object():
    rng = np.random.default_rng(2)
    table, box = table_points(rng)
    above = orbit(12, 3.0, 32, y_range=(0.85, 0.2))
    sphere = (np.zeros(3), 1.0, "test")
    n, c = support_from_points(np.concatenate([table, box]), above, sphere)
    assert n[1] > 0.999 and c == pytest.approx(-0.3, abs=0.01)
    # The box's top is a plane the cameras look down on too, but it stops well inside the sphere.
    assert support_from_points(box, above, sphere) is None
    # Cameras below the table as well: no support.
    assert support_from_points(np.concatenate([table, box]), orbit(12, 3.0, 32), sphere) is None
    # Points seen by fewer than three images do not count when tracks are known.
    track = np.r_[np.full(len(table), 2), np.full(len(box), 4)]
    assert support_from_points(np.concatenate([table, box]), above, sphere, track) is None


def test_the_wide_flat_top_of_an_object_is_no_support():
    """A slab wider than the sphere (DTU scan37's brick): its top is flat, runs out to the sphere and
    faces the cameras like a table, but the cameras see its sides beneath it; the table under it is
    the support."""
    rng = np.random.default_rng(3)
    slab = trimesh.creation.box((2.4, 0.6, 2.4))
    slab.apply_translation((0.0, -0.3, 0.0))
    pts, faces = trimesh.sample.sample_surface(slab, 1500, seed=4)
    pts = pts[slab.face_normals[faces][:, 1] > -0.5]  # its underside is not seen
    above = orbit(12, 3.0, 32, y_range=(0.85, 0.2))
    sphere = (np.zeros(3), 1.0, "test")
    assert support_from_points(pts, above, sphere) is None
    table, _ = table_points(rng, n_table=1500, top=-0.6)
    n, c = support_from_points(np.concatenate([table, pts]), above, sphere)
    assert n[1] > 0.999 and c == pytest.approx(-0.6, abs=0.01)


def test_framing_reads_colmap_points_and_the_idr_scale_matrix(tmp_path):
    from vq_mitsuba.data.formats.colmap import read_colmap_points, write_colmap
    from vq_mitsuba.data.formats.idr import write_idr
    from vq_mitsuba.data.captures import open_capture
    from vq_mitsuba.geometry.neus.method import framing as framing_of

    def framing(path, cams):
        return framing_of(open_capture(path), cams)

    cams = orbit(10, 3.0, 32)
    rng = np.random.default_rng(1)
    pts = np.array([0.1, 0.0, 0.2]) + rng.uniform(-0.25, 0.25, size=(200, 3))
    for binary in (True, False):
        folder = tmp_path / ("bin" if binary else "txt")
        write_colmap(folder / "sparse" / "0", cams, [f"{c.name}.png" for c in cams], binary=binary, points=pts)
        xyz, track = read_colmap_points(folder / "sparse" / "0")
        np.testing.assert_allclose(xyz, pts)
        assert (track == 0).all()  # written without tracks
        (folder / "images").mkdir()
        (c, r, source), support, seen = framing(folder, cams)
        assert source == "sparse points" and np.linalg.norm(c - [0.1, 0.0, 0.2]) < 0.05 and 0.3 < r < 0.5
        assert support is None and len(seen) == len(pts)  # no tracks: every point
    assert read_colmap_points(tmp_path) is None
    # A model of an object on a table, photographed from above: the table is found as the support.
    above = orbit(12, 3.0, 32, y_range=(0.85, 0.2))
    table, box = table_points(rng)
    write_colmap(tmp_path / "table" / "sparse" / "0", above, [f"{c.name}.png" for c in above],
                 points=np.concatenate([table, box]))
    (tmp_path / "table" / "images").mkdir()
    (c, r, source), (n, off), _ = framing(tmp_path / "table", above)
    assert source == "sparse points" and n[1] > 0.999 and off == pytest.approx(-0.3, abs=0.01)
    (tmp_path / "idr").mkdir()
    write_idr(tmp_path / "idr" / "cameras_sphere.npz", cams, np.array([0.5, -0.25, 1.0]), 0.75)
    (c, r, source), support, seen = framing(tmp_path / "idr" / "cameras_sphere.npz", cams)
    assert source == "scale_mat_0" and r == pytest.approx(0.75) and support is None and seen is None
    np.testing.assert_allclose(c, [0.5, -0.25, 1.0])


def test_a_known_support_bounds_the_foreground_and_starts_the_background():
    import torch

    cams = orbit(6, 2.5, 16, y_range=(0.85, 0.2))
    capture = unmasked(np.full((6, 16, 16, 3), 0.5, np.float32), cams)
    neus = neus_for(capture, tiny_cfg(), sphere=(np.array([0.0, 0.1, 0.0]), 0.5, "test"),
                support=(np.array([0.0, 2.0, 0.0]), -0.1))  # the plane y = -0.05, its normal unnormalised
    n, c = neus.box.plane
    assert torch.allclose(n, torch.tensor([0.0, 1.0, 0.0])) and c == pytest.approx(-0.3)  # box units
    res = neus.box.hull.shape[0]
    y = (torch.arange(res) + 0.5) / res * 2 - 1
    assert not neus.box.hull[:, y < -0.3, :].any() and neus.box.hull[:, (y > -0.25) & (y < 0.25), :].any()
    o = torch.tensor([[0.0, 2.0, 0.0], [-2.0, 0.5, 0.0], [0.0, -2.0, 0.0]])
    d = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    end = neus._foreground_end(o, d)
    # down onto the plane; across above it to the sphere's exit; up from below: the sphere's exit
    assert torch.allclose(end, torch.tensor([2.3, 2.0 + 0.75 ** 0.5, 3.0]), atol=1e-5)
    neus.refresh_occupancy([1.0] * neus.cfg.levels)
    near, far = neus.intervals(o, d)
    assert far[0] <= 2.3 + 1e-5


# --------------------------------------------------------------------------------------------
# The mesh: coverage masks, supporting plane


def test_mesh_coverage_is_the_silhouette_of_the_mesh():
    cams = orbit(3, 2.5, 24)
    sphere = trimesh.creation.icosphere(4, 0.5)
    cov = mesh_coverage(sphere, cams, samples=2)
    assert cov.shape == (3, 24, 24) and cov.dtype == np.float32
    assert set(np.unique(cov)) <= {0.0, 0.25, 0.5, 0.75, 1.0}
    # the disc of the sphere's silhouette: angular radius asin(0.5 / 2.5) of a 40-degree view
    f = 12 / np.tan(np.radians(20))
    r_px = f * np.tan(np.arcsin(0.5 / 2.5))
    ys, xs = (np.mgrid[0:24 * 8, 0:24 * 8] + 0.5) / 8
    disc = (np.hypot(xs - 12, ys - 12) < r_px).reshape(24, 8, 24, 8).mean((1, 3))  # each pixel's share
    for c in cov:
        assert c.sum() == pytest.approx(np.pi * r_px ** 2, rel=0.03)
        assert np.abs(c - disc).max() < 0.3  # 2 x 2 samples a pixel: quarters


def _slab_and_ball(res: int = 64):
    """SDF (box units, [-1, 1]^3) of a ball resting on a table top z = -0.3 that runs out of the
    unit sphere, cropped to the sphere."""
    axis = np.linspace(-1, 1, res)
    x, y, z = np.meshgrid(axis, axis, axis, indexing="ij")
    ball = np.sqrt(x ** 2 + y ** 2 + (z - 0.05) ** 2) - 0.35
    table = np.maximum(z + 0.3, -(z + 0.6))  # a slab from z = -0.6 to -0.3
    sdf = np.minimum(ball, table)
    return np.maximum(sdf, np.sqrt(x ** 2 + y ** 2 + z ** 2) - 1.0).astype(np.float32), axis


def test_a_supporting_plane_is_found_and_cut_and_an_object_face_is_not():
    vol, axis = _slab_and_ball()
    mesh = marching_cubes(vol, (-1, -1, -1), (1, 1, 1))
    above = np.array([[2.0 * np.cos(a), 2.0 * np.sin(a), 1.5] for a in np.linspace(0, 2 * np.pi, 12)])
    plane = support_plane(mesh, above, tol=0.05)
    assert plane is not None
    n, c = plane
    assert n[2] > 0.99 and c == pytest.approx(-0.3, abs=0.03)
    # Sparse points on the ball and the top keep it a support; points the cameras found on the
    # slab's sides, beneath its top, make it the flat top of a wide object, and the support is the
    # plane of its underside, which nothing was seen beneath (DTU scan37's brick on its table).
    rng = np.random.default_rng(5)
    a = rng.uniform(0, 2 * np.pi, 300)
    on_top = np.stack([0.9 * np.cos(a) * rng.uniform(size=300), 0.9 * np.sin(a) * rng.uniform(size=300), np.full(300, -0.3)], 1)
    sides = np.stack([0.8 * np.cos(a[:60]), 0.8 * np.sin(a[:60]), rng.uniform(-0.6, -0.35, 60)], 1)
    plane = support_plane(mesh, above, tol=0.05, points=on_top)
    assert plane is not None and plane[0][2] > 0.99
    n, c = support_plane(mesh, above, tol=0.05, points=np.concatenate([on_top, sides]))
    assert n[2] > 0.99 and c == pytest.approx(-0.6, abs=0.03)
    assert support_plane(mesh, above, tol=0.05, points=np.concatenate([on_top, sides, sides - [0, 0, 0.3]])) is None
    # Cameras all around (below the plane too): a face of the object, not a table.
    around = np.concatenate([above, above * [1, 1, -1]])
    assert support_plane(mesh, around, tol=0.05) is None
    # A box well inside the sphere, seen from above only: its top face stops short of the sphere.
    x, y, z = np.meshgrid(axis, axis, axis, indexing="ij")
    box = np.maximum(np.maximum(np.abs(x), np.abs(y)), np.abs(z)) - 0.4
    assert support_plane(marching_cubes(box, (-1, -1, -1), (1, 1, 1)), above, tol=0.05) is None


def test_mask_free_export_keeps_the_object_without_its_table(monkeypatch):
    """NeuS's export without masks: the table plane is cut, the ball is the one piece kept."""
    cams = [dataclasses.replace(c, to_world=look_at(2.0 * np.array([np.cos(a), 0.6, np.sin(a)]), [0, 0, 0],
                                                    [0, 1, 0])) for c, a in zip(orbit(8, 2.0, 16),
                                                                                 np.linspace(0, 6.2, 8))]
    capture = unmasked(np.full((8, 16, 16, 3), 0.5, np.float32), cams)
    neus = neus_for(capture, tiny_cfg(mesh_resolution=64, normal_smoothing=0), sphere=(np.zeros(3), 1.0, "test"))
    vol, _ = _slab_and_ball(64)
    vol = np.transpose(vol, (0, 2, 1))[:, :, ::-1].copy()  # the table's up is +Y here (the cameras' up)
    monkeypatch.setattr(mesh_export, "sdf_volume", lambda neus, res: vol)
    mesh, support = extract_mesh(neus)
    assert support is not None and support["normal"][1] > 0.99
    radii = np.linalg.norm(np.asarray(mesh.vertices) - [0, 0.05, 0], axis=1)
    assert mesh.is_watertight and np.percentile(radii, 95) < 0.4  # the ball alone, cut flat at its foot
    assert np.asarray(mesh.vertices)[:, 1].min() > -0.3


# --------------------------------------------------------------------------------------------
# NeuS without masks on a busy backdrop


def _mask_free_run(images, true_alpha, cams, iterations: int):
    capture = unmasked(images, cams)
    neus = neus_for(capture, tiny_cfg(iterations=iterations, seed=0))
    assert neus.box.mask_free and neus.box.sphere_source == "cameras"
    summary = train(neus, None)
    mesh, _ = extract_mesh(neus)
    derived = mesh_coverage(mesh, cams) > 0.5
    fg_opacity = np.stack([render_view(neus, c)[1] for c in cams])
    return summary, derived, fg_opacity


def test_mask_free_neus_masks_agree_with_the_true_alpha(backdrop_views):
    """300 steps at the tiny settings (about 25 s on one thread): the mesh's coverage has a mask IoU
    of 0.84-0.86 with the true alpha (seeds 0-3; the box and the ball are still rounded, the gap
    between them partly filled) and the background model takes the backdrop: the foreground
    opacity is about 0.02 on the backdrop's pixels and 0.96 on the object's. The bounds leave room
    for other machines' arithmetic (threads reduce in another order)."""
    images, true_alpha, cams, _ = backdrop_views
    summary, derived, acc = _mask_free_run(images, true_alpha, cams, 300)
    assert all(h["mask"] == 0.0 for h in summary["history"])
    truth = true_alpha > 0.5
    assert iou(derived, truth) > 0.78
    assert acc[true_alpha < 0.01].mean() < 0.08 and acc[true_alpha > 0.99].mean() > 0.9


@pytest.mark.slow
def test_mask_free_neus_masks_converge_towards_the_true_alpha(backdrop_views):
    """1500 steps (about 3 minutes): mask IoU 0.913 with the true alpha (seed 0), foreground opacity
    0.004 on the backdrop and 0.993 on the object."""
    images, true_alpha, cams, _ = backdrop_views
    summary, derived, acc = _mask_free_run(images, true_alpha, cams, 1500)
    truth = true_alpha > 0.5
    assert iou(derived, truth) > 0.87
    assert np.percentile(acc[true_alpha < 0.01], 90) < 0.05 and acc[true_alpha > 0.99].mean() > 0.95


def write_unmasked_xml_capture(out: Path, images: np.ndarray, cams: list[Camera]) -> Path:
    """A Mitsuba scene XML of the views (RGB EXRs, no alpha) with no shapes: a capture to reconstruct."""
    from vq_mitsuba.data.cameras import principal_xml
    from vq_mitsuba.data.imageio import write_exr

    (out / "images").mkdir(parents=True, exist_ok=True)
    sensors = []
    for cam, image in zip(cams, images):
        write_exr(out / "images" / f"{cam.name}.exr", image)
        m = " ".join(f"{x:.9g}" for x in cam.to_world.ravel())
        sensors.append(f'  <sensor type="perspective" id="{cam.name}">\n'
                       f'    <float name="fov" value="{cam.fov_x_deg!r}"/>\n    <string name="fov_axis" value="x"/>\n'
                       + principal_xml(cam, "    ") +
                       f'    <transform name="to_world"><matrix value="{m}"/></transform>\n'
                       f'    <film type="hdrfilm"><integer name="width" value="{cam.width}"/>'
                       f'<integer name="height" value="{cam.height}"/></film>\n  </sensor>')
    (out / "scene.xml").write_text('<scene version="3.0.0">\n' + "\n".join(sensors) + "\n</scene>\n")
    return out / "scene.xml"


def test_fit_without_masks_fits_inside_the_reconstructed_mesh(backdrop_views, tmp_path, monkeypatch):
    """fit on a capture with neither masks nor geometry: NeuS without masks, then the material fit
    on the views masked by the mesh's coverage (has_alpha), also after --resume. The capture is
    resolved once and its images read once for the geometry stage, its held-out scores and the
    material fit."""
    from vq_mitsuba.data import captures
    from vq_mitsuba.data.captures import load_capture
    from vq_mitsuba.data.formats import mitsuba_xml
    from vq_mitsuba.engine.pipeline import fit_capture
    from vq_mitsuba.run.run_dir import RunDir

    images, true_alpha, cams, _ = backdrop_views
    xml = write_unmasked_xml_capture(tmp_path / "capture", images, cams)
    assert not load_capture(xml).has_alpha
    neus = dict(iterations=40, batch_rays=128, n_samples=12, levels=2, base_res=8, max_res=16, hidden=16,
                hull_resolution=32, march_steps=32, mesh_resolution=32, checkpoint_every=0, warmup=5)
    settings = [f"neus.{k}={v}" for k, v in neus.items()] + [
        "train.iterations=4", "train.batch_rays=256", "train.checkpoint_every=1000", "train.bounce_after=1000",
        "capture.holdout=4", "render.spp=4"]
    cfg = load_config(None, settings)
    run = RunDir(tmp_path / "run")
    calls = []

    def counted(module, name):
        inner = getattr(module, name)
        monkeypatch.setattr(module, name, lambda *a, **k: calls.append(name) or inner(*a, **k))
    for module, name in ((captures, "resolve_capture_path"), (captures, "format_of"), (mitsuba_xml, "detect"),
                         (mitsuba_xml, "has_geometry"), (mitsuba_xml, "cameras"), (mitsuba_xml, "load")):
        counted(module, name)
    fit_capture(xml, run.dir, cfg, log=lambda _: None)
    assert sorted(calls) == ["detect", "format_of", "has_geometry", "load", "resolve_capture_path"], calls
    geometry = json.loads((run.dir / RunDir.GEOMETRY).read_text())
    assert geometry["background"] == "model" and geometry["bounding_sphere"]["from"] == "cameras"
    assert run.masks_from_mesh()
    train = [c for i, c in enumerate(cams) if i % 4 != 3]
    coverage = mesh_coverage(run.mesh(), train)
    info = run.info()
    # the fit's opaque pixels are the mesh's coverage, not every pixel of the views
    assert info["opaque_pixels"] == int((coverage >= cfg.train.alpha_threshold).sum())
    assert info["opaque_pixels"] < 0.6 * coverage.size and info["geometry_coverage"] > 0.95
    # the held-out views are scored inside the mesh's coverage too
    from vq_mitsuba.eval.evaluate import evaluate_holdout

    metrics = evaluate_holdout(run.dir)
    assert len(metrics["views"]) == 4 and metrics["coverage_iou"] > 0.9


def table_scene(out: Path, n_views: int = 16, size: int = 40, spp: int = 32):
    """The box and the ball standing on a checkered table top y = -0.275 that runs far beyond them,
    under the busy environment, seen from above. Returns (images, true alpha of the two objects alone,
    cameras)."""
    import mitsuba as mi

    from vq_mitsuba.backend import init_mitsuba

    init_mitsuba()
    box, ball, env = _box_ball_and_env(out, ball_y=0.005)

    def rgb(value):
        return {"type": "rgb", "value": value}

    objects = {"box": {"type": "ply", "filename": str(out / "box.ply"),
                       "bsdf": {"type": "principled", "base_color": rgb([0.8, 0.6, 0.2]), "roughness": 0.5}},
               "ball": {"type": "ply", "filename": str(out / "ball.ply"),
                        "bsdf": {"type": "principled", "base_color": rgb([0.2, 0.4, 0.8]), "roughness": 0.3}}}
    t = mi.ScalarTransform4f
    table = {"type": "rectangle", "to_world": t().translate([0, -0.275, 0]) @ t().rotate([1, 0, 0], -90) @ t().scale(3.0),
             "bsdf": {"type": "diffuse", "reflectance": {"type": "checkerboard", "color0": rgb([0.7, 0.3, 0.3]),
                                                         "color1": rgb([0.2, 0.5, 0.6]), "to_uv": t().scale([4, 4, 1])}}}
    full = mi.load_dict({"type": "scene", "integrator": {"type": "path", "max_depth": 3}, "env": env, "table": table,
                         **objects})
    alone = mi.load_dict({"type": "scene", "integrator": {"type": "path", "max_depth": 1, "hide_emitters": True},
                          "env": env, **objects})
    cams = orbit(n_views, 2.4, size, y_range=(0.85, 0.2))
    images, alphas = [], []
    for i, cam in enumerate(cams):
        sensor = mi.load_dict(cam.to_mitsuba_dict(spp))
        images.append(np.array(mi.render(full, sensor=sensor, seed=i))[..., :3])
        alphas.append(np.array(mi.render(alone, sensor=sensor, seed=i))[..., 3])
    return np.stack(images).astype(np.float32), np.stack(alphas).astype(np.float32), cams


@pytest.mark.slow
def test_mask_free_neus_on_a_table_with_the_table_known(tmp_path):
    """Objects on a table, its plane known (as the sparse points of a COLMAP model give it): the
    table is the background model's, the mesh stops at the plane. 600 steps at the tiny settings:
    mask IoU 0.78 (0.75 without the plane, when the objects' blob bulges into the table; 0.79 and
    0.69 after 1500 steps)."""
    images, true_alpha, cams = table_scene(tmp_path)
    neus = neus_for(unmasked(images, cams), tiny_cfg(iterations=600), support=(np.array([0.0, 1.0, 0.0]), -0.275))
    train(neus, None)
    mesh, support = extract_mesh(neus)
    assert support is not None and support["from"] == "sparse points"
    assert np.asarray(mesh.vertices)[:, 1].min() > -0.275
    assert iou(mesh_coverage(mesh, cams) > 0.5, true_alpha > 0.5) > 0.72


def test_a_checkpoint_resumes_only_in_its_own_mode(tmp_path):
    from vq_mitsuba.geometry.neus import reconstruct

    cams = orbit(6, 2.5, 16)
    images = np.full((6, 16, 16, 3), 0.3, np.float32)
    images[:, 5:11, 5:11] = 0.8
    bare = unmasked(images, cams)
    cfg = tiny_cfg(iterations=2, checkpoint_every=1, mesh_resolution=24, hull_resolution=24, normal_smoothing=0)
    result = reconstruct(bare, tmp_path, cfg)
    summary = result.summary
    assert summary["background"] == "model" and summary["bounding_sphere"]["from"] == "cameras"
    assert summary["bounding_sphere"]["radius"] == pytest.approx(result.neus.box.half)
    masked = dataclasses.replace(bare, alpha=(images[..., 0] > 0.5).astype(np.float32), has_alpha=True)
    with pytest.raises(InputError, match="made without masks"):
        reconstruct(masked, tmp_path, dataclasses.replace(cfg, iterations=3), resume=True)
    again = reconstruct(bare, tmp_path, dataclasses.replace(cfg, iterations=3), resume=True)
    assert again.summary["iterations"] == 3
