"""The per-texel Mitsuba baseline: atlas, gradients, conventions, fitting, prediction, scoring."""

import math

import numpy as np
import pytest

from tiny_scene import write_sphere_capture
from vq_mitsuba.data.captures import load_capture
from vq_mitsuba.eval.texel import TexelConfig, TexelPredictor, TexelScene, _write_snapshot, fit_texel, load_snapshot
from vq_mitsuba.geometry.uv import uv_unwrap

TRUE_BASE = (0.7, 0.35, 0.2)  # write_sphere_capture's material
TRUE_ROUGH = 0.3


@pytest.fixture(scope="module")
def sphere(tmp_path_factory):
    return write_sphere_capture(tmp_path_factory.mktemp("texel_sphere"), size=24, n_views=8, spp=32)


@pytest.fixture(scope="module")
def fitted(sphere, tmp_path_factory):
    out = tmp_path_factory.mktemp("texel_fit")
    cfg = TexelConfig(resolution=32, spp=8, iterations=40, lr_texture=0.05)
    return fit_texel(sphere, out, cfg, time_limit_s=0, snapshot_s=(1e-9,))


def _constant_values(ts, base, metallic, roughness):
    import mitsuba as mi

    r = ts.resolution
    values = ts.initial_values()
    values["basecolor"] = mi.TensorXf(np.broadcast_to(np.float32(base), (r, r, 3)).copy())
    values["metallic"] = mi.TensorXf(np.full((r, r, 1), metallic, np.float32))
    values["roughness"] = mi.TensorXf(np.full((r, r, 1), roughness, np.float32))
    return values


def test_uv_atlas_keeps_faces_and_stays_in_the_unit_square():
    import trimesh

    mesh = trimesh.creation.icosphere(subdivisions=2, radius=0.5)
    vmap, faces, uvs = uv_unwrap(mesh.vertices, mesh.faces, 64)
    assert faces.shape == mesh.faces.shape
    assert np.array_equal(vmap[faces], mesh.faces)  # same triangles, same order, seams split vertices
    assert len(vmap) >= len(mesh.vertices) and uvs.shape == (len(vmap), 2)
    assert uvs.min() >= 0.0 and uvs.max() <= 1.0
    t = uvs[faces]
    area = 0.5 * np.abs((t[:, 1, 0] - t[:, 0, 0]) * (t[:, 2, 1] - t[:, 0, 1])
                        - (t[:, 2, 0] - t[:, 0, 0]) * (t[:, 1, 1] - t[:, 0, 1]))
    assert (area > 0).all() and area.sum() < 1.0


def test_voronoi_atlas_fallback_keeps_faces():
    """The atlas used where xatlas crashes: same triangles in the same order (each corner its own
    input vertex, possibly rotated within the triangle), UVs in the unit square, charts not flat."""
    import trimesh

    from vq_mitsuba.geometry.uv import _voronoi_atlas

    mesh = trimesh.creation.icosphere(subdivisions=3, radius=0.5)
    vmap, faces, uvs = _voronoi_atlas(mesh.vertices, mesh.faces)
    assert faces.shape == mesh.faces.shape
    np.testing.assert_array_equal(np.sort(vmap[faces], 1), np.sort(mesh.faces, 1))
    assert uvs.min() >= 0.0 and uvs.max() <= 1.0
    t = uvs[faces]
    area = 0.5 * np.abs((t[:, 1, 0] - t[:, 0, 0]) * (t[:, 2, 1] - t[:, 0, 1])
                        - (t[:, 2, 0] - t[:, 0, 0]) * (t[:, 1, 1] - t[:, 0, 1]))
    assert np.mean(area > 1e-10) > 0.99 and area.sum() < 1.0


def test_texture_gradient_matches_finite_difference(sphere):
    """Mitsuba's prb gradient with respect to the red texels of half the atlas against central
    differences (same random numbers for both sides)."""
    import drjit as dr
    import mitsuba as mi

    ts = TexelScene(load_capture(sphere), TexelConfig(resolution=32, spp=64))
    r = ts.resolution
    mask = np.zeros((r, r, 3), np.float32)
    mask[:, : r // 2, 0] = 1.0
    base = np.array(ts.initial_values()["basecolor"])
    h = 0.02

    def mean_image(values, seed):
        ts.apply(values)
        return dr.mean(ts.render(0, seed), axis=None)

    def derivatives(objective):
        values = ts.initial_values()
        dr.enable_grad(values["basecolor"])
        dr.backward(objective(values, 3))
        grad = np.array(dr.grad(values["basecolor"]))
        assert np.abs(grad[..., 1:]).sum() > 0  # green and blue texels are seen too
        fd = []
        for sign in (1, -1):
            v = ts.initial_values()
            v["basecolor"] = mi.TensorXf(base + sign * h * mask)
            fd.append(float(np.array(objective(v, 3))))
        return float(np.sum(grad * mask)), (fd[0] - fd[1]) / (2 * h)

    # The prb gradient pass draws its own samples: the mean image's derivative agrees with the
    # finite difference up to Monte Carlo noise.
    analytic, numeric = derivatives(mean_image)
    assert analytic > 0 and analytic == pytest.approx(numeric, rel=0.06)
    # The L2 loss's finite difference with common random numbers also holds the covariance of the
    # noise with its derivative (biased by 5-15 % at 64 spp): only the descent direction is checked.
    analytic, numeric = derivatives(lambda v, seed: ts.loss(v, [0], seed))
    assert analytic * numeric > 0 and 0.7 < analytic / numeric < 1.4


def test_other_views_reuse_the_compiled_kernels(sphere):
    """The one sensor is moved through opaque parameters: a new view compiles nothing new."""
    import drjit as dr
    import mitsuba as mi

    ts = TexelScene(load_capture(sphere), TexelConfig(resolution=16, spp=4))
    opt = mi.ad.Adam(lr=0.05, mask_updates=True)
    for name, value in ts.initial_values().items():
        opt[name] = value
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        for step in range(5):
            dr.backward(ts.loss(opt, [step], seed=step))
            opt.step()
            jit = [k for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT]
            if step >= 2:  # views 2, 3, 4 were never rendered before
                assert jit and all(k.get("cache_hit") == 1 and not k.get("cache_disk") for k in jit), step
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)


def test_true_materials_reproduce_the_capture(sphere):
    """Conventions (sensor, envmap orientation, premultiplied alpha): the capture's own material
    in the texel scene matches the reference images far better than the initial grey, a wrong
    roughness, or the right material under the envmap turned by 90 degrees."""
    import dataclasses

    from vq_mitsuba.render.views import rotate_about_up

    capture = load_capture(sphere)
    views = list(range(len(capture.cameras)))
    ts = TexelScene(capture, TexelConfig(resolution=16, spp=64))
    truth = float(np.array(ts.loss(_constant_values(ts, TRUE_BASE, 0.0, TRUE_ROUGH), views, seed=1)))
    grey = float(np.array(ts.loss(ts.initial_values(), views, seed=1)))
    rough = float(np.array(ts.loss(_constant_values(ts, TRUE_BASE, 0.0, 0.9), views, seed=1)))
    turned = TexelScene(dataclasses.replace(capture, envmap_to_world=rotate_about_up(capture.envmap_to_world, 90)),
                        TexelConfig(resolution=16, spp=64))
    wrong_env = float(np.array(turned.loss(_constant_values(turned, TRUE_BASE, 0.0, TRUE_ROUGH), views, seed=1)))
    assert truth < 0.25 * grey and truth < 0.8 * rough and truth < 0.5 * wrong_env


def test_fit_lowers_the_loss_and_moves_basecolor_towards_truth(fitted, sphere):
    snaps = fitted["snapshots"]
    assert fitted["iterations"] == 40 and len(snaps) == 2 and snaps[0][1] == 1 and snaps[1][1] == 40
    assert fitted["loss_last"] < 0.7 * fitted["loss_first"]
    arrays, meta = load_snapshot(snaps[-1][2])
    assert meta["world"] == "mitsuba" and meta["iterations"] == 40 and not meta["learned_envmap"]
    assert arrays["basecolor"].shape == (32, 32, 3) and arrays["metallic"].shape == (32, 32)
    assert arrays["roughness"].min() >= 0.02 and arrays["basecolor"].max() <= 1.0

    pred = TexelPredictor(snaps[-1][2])
    cam = load_capture(sphere).cameras[0]
    out = pred.renderer(None).render(cam, spp=4, aa=4, seed=0)
    fg = out["alpha"] == 1.0
    err = np.abs(out["basecolor"][fg].mean(0) - np.array(TRUE_BASE)).mean()
    err_init = np.abs(0.5 - np.array(TRUE_BASE)).mean()
    assert err < 0.6 * err_init


def test_predictor_renders_texture_values_as_maps(fitted, sphere, tmp_path):
    arrays, meta = load_snapshot(fitted["snapshots"][-1][2])
    arrays["basecolor"][:] = (0.2, 0.4, 0.6)
    arrays["metallic"][:] = 0.3
    arrays["roughness"][:] = 0.7
    path = tmp_path / "snapshot_const.npz"
    _write_snapshot(path, arrays, meta)
    pred = TexelPredictor(path)
    assert pred.world == "mitsuba" and pred.num_materials is None and pred.default_spp > 0
    with pytest.raises(Exception):
        TexelPredictor(path, world="blender")
    cam = load_capture(sphere).cameras[2]
    out = pred.renderer(None).render(cam, spp=8, aa=4, seed=1)
    h, w = cam.height, cam.width
    assert out["rgb"].shape == (h, w, 3) and out["basecolor"].shape == (h, w, 3) and out["normal"].shape == (h, w, 3)
    assert out["alpha"].shape == out["metallic"].shape == out["roughness"].shape == (h, w)
    fg, bg = out["alpha"] == 1.0, out["alpha"] == 0.0
    assert fg.sum() > 50 and bg.sum() > 50
    np.testing.assert_allclose(out["basecolor"][fg], np.broadcast_to([0.2, 0.4, 0.6], (fg.sum(), 3)), atol=1e-5)
    np.testing.assert_allclose(out["metallic"][fg], 0.3, atol=1e-5)
    np.testing.assert_allclose(out["roughness"][fg], 0.7, atol=1e-5)
    np.testing.assert_allclose(np.linalg.norm(out["normal"][fg], axis=-1), 1.0, atol=1e-4)
    # Normals face the camera; colour is premultiplied over black.
    view_dir = cam.to_world[:3, 2]
    assert (out["normal"][fg] @ view_dir < 0).mean() > 0.99
    a = np.pad(out["alpha"], 1)
    far = sum(a[1 + dy:1 + dy + h, 1 + dx:1 + dx + w] for dy in (-1, 0, 1) for dx in (-1, 0, 1)) == 0
    assert far.sum() > 50 and np.abs(out["rgb"][far]).max() == 0.0
    assert np.isfinite(out["rgb"]).all() and out["rgb"][fg].mean() > 0.01
    # A brighter envmap brightens the render (relighting uses the given envmap).
    bright = pred.renderer(arrays["envmap"] * 2.0).render(cam, spp=8, aa=1, seed=1)
    assert bright["rgb"][fg].mean() == pytest.approx(2.0 * out["rgb"][fg].mean(), rel=0.02)


def test_evaluate_predictor_scores_a_texel_snapshot(tmp_path):
    from vq_mitsuba.eval.evaluate import evaluate_predictor
    from vq_mitsuba.synthetic.mitsuba_scenes import make_scene

    data = make_scene("demo", tmp_path / "demo", resolution=16, n_train=4, n_test=2, spp=8)
    res = fit_texel(data / "transforms_train.json", tmp_path / "fit", TexelConfig(resolution=32, iterations=3),
                    time_limit_s=0)
    pred = TexelPredictor(res["snapshots"][-1][2])
    assert pred.world == "blender"
    m = evaluate_predictor(pred, data, spp=4, aa=1, meanshift_bandwidths=())
    assert m["n_views"] == 2
    for v in (m["novel_view"]["psnr"], m["basecolor"]["psnr"], m["roughness"]["psnr"], m["normal"]["mae_deg"]):
        assert math.isfinite(v)
    # The atlas mesh is the capture's geometry in the right world (a wrong world is off by tens of
    # degrees; at 16 px with one ray per pixel, edge pixels alone cost a few degrees).
    assert m["normal"]["mae_deg"] < 15.0
    assert m["relighting"]["albedo_scale"]["envs"]
    assert all(math.isfinite(e["psnr"]) for e in m["relighting"]["image_scale"]["envs"].values())
