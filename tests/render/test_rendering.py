"""Deferred shading through Mitsuba: agreement with Mitsuba's integrator, gradients, conventions."""

import numpy as np
import pytest
import torch
import trimesh

import drjit as dr
import mitsuba as mi

from vq_mitsuba.data.cameras import BLENDER_ENV_TO_WORLD, Camera, look_at
from vq_mitsuba.backend import init_mitsuba
from vq_mitsuba.data.cameras import camera_rays
from vq_mitsuba.models.fitted import FittedModel
from vq_mitsuba.render.shading import ShadingScene, envmap_padded

init_mitsuba()

SPHERE = trimesh.creation.icosphere(subdivisions=4, radius=0.5)


def _env(h=16, seed=0):
    rng = np.random.default_rng(seed)
    env = (0.3 + 0.4 * rng.random((h, 2 * h, 3))).astype(np.float32)
    env[h // 3, h // 2] = 40.0  # a small bright "sun"
    return env


def _scene(env, to_world=np.eye(4)):
    return ShadingScene(SPHERE.vertices, SPHERE.faces, env, to_world, normals=SPHERE.vertex_normals)


def _points(n=256, seed=1):
    """Points on the sphere with outward normals, seen from random directions above the surface."""
    rng = np.random.default_rng(seed)
    nrm = rng.normal(size=(n, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    wi = nrm + rng.normal(size=(n, 3)) * 0.5
    wi /= np.linalg.norm(wi, axis=1, keepdims=True)
    wi = np.where((wi * nrm).sum(1, keepdims=True) < 0.1, nrm, wi)
    t = lambda a: torch.tensor(a, dtype=torch.float32)
    return t(0.5 * nrm), t(nrm), t(wi)


def _two_spheres(subdivisions=4):
    """Two spheres one above the other, 0.02 apart, so that they light each other."""
    a = trimesh.creation.icosphere(subdivisions=subdivisions, radius=0.5)
    b = a.copy()
    b.apply_translation([0.0, 0.0, 1.02])
    return trimesh.util.concatenate([a, b])


def _two_spheres_camera(size):
    """A camera that sees both of `_two_spheres`, `size` pixels square."""
    return Camera("c", look_at([2.2, 0.3, 0.5], [0, 0, 0.5], [0, 0, 1]), 45.0, size, size)


def _touching_spheres(env, size=40):
    """Two spheres that light each other, the scene over them and a camera that sees both."""
    both = _two_spheres()
    scene = ShadingScene(both.vertices, both.faces, env, np.eye(4), normals=both.vertex_normals)
    return scene, _two_spheres_camera(size)


def test_camera_rays_of_chosen_pixels_are_those_of_the_whole_image():
    from vq_mitsuba.data.cameras import Camera, look_at

    cam = Camera("c", look_at([0.3, 2.0, 1.5], [0, 0, 0], [0, 1, 0]), 35.0, 7, 5)
    jitter = np.random.default_rng(1).random((35, 2))
    o_all, d_all = camera_rays(cam, jitter)
    pick = np.array([0, 6, 17, 34, 17])
    o, d = camera_rays(cam, jitter[pick], pixels=pick)
    assert np.array_equal(o, o_all[pick]) and np.allclose(d, d_all[pick], atol=1e-7)


def test_envmap_padding_matches_mitsuba_layout():
    env = _env(4)
    emitter = mi.load_dict({"type": "envmap", "bitmap": mi.Bitmap(env)})
    data = np.array(mi.traverse(emitter)["data"])
    assert data.shape == (4, 10, 3)
    np.testing.assert_allclose(envmap_padded(torch.tensor(env)).numpy(), data, rtol=1e-6)


@pytest.mark.cpu_inputs
def test_shading_matches_mitsuba_direct_integrator():
    """Mean radiance of a principled sphere equals Mitsuba's own `direct` render (statistical)."""
    env = _env()
    scene = _scene(env)
    cam = Camera("c", look_at([0, -2.0, 0.4], [0, 0, 0], [0, 0, 1]), 40.0, 48, 48)
    hits = scene.trace(*camera_rays(cam))
    v = hits.valid
    n = int(v.sum())
    base, metal, rough = [0.6, 0.4, 0.2], 0.3, 0.35
    material = {"basecolor": torch.tensor([base]).expand(n, 3), "metallic": torch.full((n,), metal),
                "roughness": torch.full((n,), rough)}
    ours = scene.shade(hits.position[v], hits.normal[v], hits.wi[v], material, torch.tensor(env), spp=128).numpy()
    ref_scene = mi.load_dict({
        "type": "scene", "integrator": {"type": "direct", "hide_emitters": True},
        "s": {"type": "sphere", "radius": 0.5, "bsdf": {"type": "principled", "base_color": {"type": "rgb", "value": base},
                                                        "metallic": metal, "roughness": rough}},
        "env": {"type": "envmap", "bitmap": mi.Bitmap(env)},
    })
    ref = np.array(mi.render(ref_scene, sensor=mi.load_dict(cam.to_mitsuba_dict(512)))).reshape(-1, 4)
    full = np.zeros((ref.shape[0], 3))
    full[v.numpy()] = ours
    inside = (ref[:, 3] > 0.999) & v.numpy()
    np.testing.assert_allclose(full[inside].mean(0), ref[inside, :3].mean(0), rtol=0.02)


def _loss(scene, env, p, n, wi, base, metal, rough, spp=64, seed=3):
    gen = torch.Generator().manual_seed(seed)
    rgb = scene.shade(p, n, wi, {"basecolor": base, "metallic": metal, "roughness": rough}, env, spp, generator=gen)
    return (rgb * torch.tensor([0.5, 1.0, 2.0])).sum()


@pytest.mark.cpu_inputs
def test_gradients_nonzero_and_match_finite_differences():
    """Torch gradients reach basecolor, metallic, roughness and envmap (no silent zeros) and
    agree with central differences of the same estimator (fixed random numbers)."""
    env0 = _env()
    scene = _scene(env0)
    p, n, wi = _points()
    N = p.shape[0]
    base = torch.full((N, 3), 0.5, requires_grad=True)
    metal = torch.full((N,), 0.2, requires_grad=True)
    rough = torch.full((N,), 0.5, requires_grad=True)
    env = torch.tensor(env0, requires_grad=True)
    _loss(scene, env, p, n, wi, base, metal, rough).backward()
    for name, g in [("basecolor", base.grad), ("metallic", metal.grad), ("roughness", rough.grad), ("envmap", env.grad)]:
        assert g is not None and torch.isfinite(g).all() and g.abs().sum() > 0, name

    eps = 1e-2
    with torch.no_grad():
        def f(db=0.0, dm=0.0, dr_=0.0, denv=0.0):
            e = env.detach().clone()
            e[env0.shape[0] // 3, env0.shape[0] // 2] += denv
            return _loss(scene, e, p, n, wi, base.detach() + db, metal.detach() + dm, rough.detach() + dr_, spp=1024).item()

        fd_base = (f(db=eps) - f(db=-eps)) / (2 * eps)
        fd_rough = (f(dr_=eps) - f(dr_=-eps)) / (2 * eps)
        fd_env = (f(denv=1.0) - f(denv=-1.0)) / 2.0
    # Same sum of partial derivatives, estimated with more samples (the BSDF sampling is detached,
    # so the estimator of the gradient is compared with the derivative of the expectation).
    base2 = base.detach().clone().requires_grad_(True)
    rough2 = rough.detach().clone().requires_grad_(True)
    env2 = torch.tensor(env0, requires_grad=True)
    _loss(scene, env2, p, n, wi, base2, metal.detach(), rough2, spp=1024).backward()
    assert base2.grad.sum().item() == pytest.approx(fd_base, rel=0.03)
    assert rough2.grad.sum().item() == pytest.approx(fd_rough, rel=0.15)
    sun = env2.grad[env0.shape[0] // 3, env0.shape[0] // 2].sum().item()
    assert sun == pytest.approx(fd_env, rel=0.05)


@pytest.mark.cpu_inputs
def test_bright_texel_lights_the_expected_side():
    """Envmap orientation: a bright texel in direction d lights the sphere's side facing d.

    Mitsuba convention (identity to_world): the image centre is +Z, the top row +Y. Blender
    convention (BLENDER_ENV_TO_WORLD, as Cycles): the image centre is +X, u = 0.25 is +Y, the top row +Z.
    """
    h = 16
    for to_world, texel, direction in [
        (np.eye(4), (h // 2, h), np.array([0.0, 0.0, 1.0])),  # centre -> +Z
        (np.eye(4), (slice(0, 2), slice(None)), np.array([0.0, 1.0, 0.0])),  # top rows -> +Y
        (BLENDER_ENV_TO_WORLD, (h // 2, h), np.array([1.0, 0.0, 0.0])),  # Blender: centre -> +X
        (BLENDER_ENV_TO_WORLD, (slice(0, 2), slice(None)), np.array([0.0, 0.0, 1.0])),  # Blender: top rows -> +Z
        (BLENDER_ENV_TO_WORLD, (h // 2, h // 2), np.array([0.0, 1.0, 0.0])),  # Blender: u=0.25 -> +Y
    ]:
        env = np.full((h, 2 * h, 3), 0.01, np.float32)
        env[texel] = 1000.0
        scene = _scene(env, to_world)
        nrm = torch.tensor(np.stack([direction, -direction]), dtype=torch.float32)
        p = 0.5 * nrm
        material = {"basecolor": torch.full((2, 3), 0.8), "metallic": torch.zeros(2), "roughness": torch.ones(2)}
        rgb = scene.shade(p, nrm, nrm, material, torch.tensor(env), spp=256)
        lit, dark = rgb[0].mean().item(), rgb[1].mean().item()
        assert lit > 20 * dark, (to_world.tolist(), texel, lit, dark)



@pytest.mark.cpu_inputs
def test_extreme_inputs_stay_finite():
    """Extreme HDR lighting, roughness at its floor, black basecolor, grazing views."""
    env0 = _env()
    env0[2, 3] = 1e5
    scene = _scene(env0)
    p, n, wi = _points(64)
    # Grazing: view direction nearly in the tangent plane.
    t = torch.linalg.cross(n, torch.tensor([[0.3, 0.5, 0.8]]).expand_as(n))
    t = t / t.norm(dim=1, keepdim=True)
    wi_graze = torch.nn.functional.normalize(t + 1e-3 * n, dim=1)
    N = p.shape[0]
    for base_v, rough_v, view in [(0.0, 0.001, wi), (1.0, 0.001, wi_graze), (0.5, 1.0, wi_graze), (0.0, 0.02, wi)]:
        base = torch.full((N, 3), base_v, requires_grad=True)
        metal = torch.full((N,), 0.5, requires_grad=True)
        rough = torch.full((N,), rough_v, requires_grad=True)
        env = torch.tensor(env0, requires_grad=True)
        rgb = scene.shade(p, n, view, {"basecolor": base, "metallic": metal, "roughness": rough}, env, spp=16)
        assert torch.isfinite(rgb).all() and (rgb >= 0).all()
        rgb.sum().backward()
        for g in (base.grad, metal.grad, rough.grad, env.grad):
            assert torch.isfinite(g).all()


@pytest.mark.cpu_inputs
def test_no_kernel_recompiles_after_warm_up():
    """Random batches reuse the compiled kernels, whatever their size (sizes are not baked in):
    the bounce's second shading call gets a different number of lanes at every step."""
    env0 = _env()
    scene = _scene(env0)
    p, n, wi = _points(512)
    env = torch.tensor(env0, requires_grad=True)
    tint = torch.tensor([0.4, 0.5, 0.6], requires_grad=True)

    def material(points):  # a differentiable material for the bounce
        m = points.shape[0]
        return {"basecolor": tint.expand(m, 3), "metallic": torch.full((m,), 0.1), "roughness": torch.full((m,), 0.6)}

    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        for step, size in enumerate((128, 128, 96, 160, 112)):
            idx = torch.randint(0, 512, (size,))
            base = torch.rand(size, 3, requires_grad=True)
            mat = {"basecolor": base, "metallic": torch.rand(size), "roughness": torch.rand(size)}
            rgb = scene.shade(p[idx], n[idx], wi[idx], mat, env, spp=4, material_fn=material)
            rgb.sum().backward()
            history = dr.kernel_history()
            if step >= 2:
                misses = [k for k in history if k.get("type") == dr.KernelType.JIT and not k.get("cache_hit")]
                assert not misses, f"{len(misses)} kernels compiled at step {step} ({size} points)"
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)


@pytest.mark.cpu_inputs
def test_one_bounce_matches_mitsuba_path_depth_3():
    """Two touching spheres light each other: with `material_fn`, shading equals Mitsuba's `path`
    integrator at max_depth 3 (direct + one bounce); without it, Mitsuba's `direct`."""
    env = _env()
    scene, cam = _touching_spheres(env)
    base, metal, rough = [0.8, 0.7, 0.6], 0.6, 0.25
    hits = scene.trace(*camera_rays(cam))
    v = hits.valid
    assert int(v.sum()) > 200  # the camera sees both spheres

    def material(points):
        m = points.shape[0]
        return {"basecolor": torch.tensor([base]).expand(m, 3), "metallic": torch.full((m,), metal),
                "roughness": torch.full((m,), rough)}

    mat = material(hits.position[v])
    args = (hits.position[v], hits.normal[v], hits.wi[v], mat, torch.tensor(env))
    with torch.no_grad():
        one_bounce = scene.shade(*args, spp=256, material_fn=material).numpy()
        direct = scene.shade(*args, spp=256).numpy()
    bsdf = {"type": "principled", "base_color": {"type": "rgb", "value": base}, "metallic": metal, "roughness": rough}
    shapes = {f"s{i}": {"type": "sphere", "radius": 0.5, "center": c, "bsdf": bsdf}
              for i, c in enumerate([[0, 0, 0], [0, 0, 1.02]])}
    for integrator, ours in ((("path", 3), one_bounce), (("direct", None), direct)):
        integ = {"type": integrator[0], "hide_emitters": True}
        if integrator[1]:
            integ["max_depth"] = integrator[1]
        ref_scene = mi.load_dict({"type": "scene", "integrator": integ, **shapes,
                                  "env": {"type": "envmap", "bitmap": mi.Bitmap(env)}})
        ref = np.array(mi.render(ref_scene, sensor=mi.load_dict(cam.to_mitsuba_dict(1024)))).reshape(-1, 4)
        full = np.zeros((ref.shape[0], 3))
        full[v.numpy()] = ours
        inside = (ref[:, 3] > 0.999) & v.numpy()
        np.testing.assert_allclose(full[inside].mean(0), ref[inside, :3].mean(0), rtol=0.02, err_msg=integrator[0])
    assert one_bounce.mean() > 1.03 * direct.mean()  # the bounce matters in this scene


@pytest.mark.cpu_inputs
def test_bounce_light_changes_the_image_but_trains_nothing():
    """The light bounced off the object is incoming light for the step: the image depends on the
    material it bounced off (central differences of the same estimator are positive), but no
    gradient flows into that material, and the primary material's gradient is unchanged."""
    env = torch.tensor(_env())
    scene, cam = _touching_spheres(env.numpy(), size=32)
    hits = scene.trace(*camera_rays(cam))
    v = hits.valid
    m = int(v.sum())

    def loss(tint, base, bounce=True):
        def material(points):
            k = points.shape[0]
            return {"basecolor": tint.expand(k, 3), "metallic": torch.full((k,), 0.0),
                    "roughness": torch.full((k,), 0.7)}
        gen = torch.Generator().manual_seed(3)
        mat = {"basecolor": base.expand(m, 3), "metallic": torch.full((m,), 0.0), "roughness": torch.full((m,), 0.3)}
        rgb = scene.shade(hits.position[v], hits.normal[v], hits.wi[v], mat, env, spp=64, generator=gen,
                          material_fn=material if bounce else None)
        return (rgb * torch.tensor([1.0, 2.0, 3.0])).sum()

    tint = torch.tensor([0.5, 0.4, 0.3], requires_grad=True)
    base = torch.tensor([0.6, 0.6, 0.6], requires_grad=True)
    loss(tint, base).backward()
    assert tint.grad is None and (base.grad > 0).all()
    eps = 1e-2
    with torch.no_grad():
        for c in range(3):
            d = torch.zeros(3)
            d[c] = eps
            fd = (loss(tint.detach() + d, base) - loss(tint.detach() - d, base)).item() / (2 * eps)
            assert fd > 0, c
            fd_base = (loss(tint, base + d) - loss(tint, base - d)).item() / (2 * eps)
            assert base.grad[c].item() == pytest.approx(fd_base, rel=0.02), c


def test_stratified_samples_cover_each_stratum_once_per_group():
    from vq_mitsuba.data.cameras import pixel_jitter
    from vq_mitsuba.render.shading import stratified_samples

    n, spp, groups = 7, 16, 2
    u = stratified_samples(n, spp, groups, torch.Generator().manual_seed(0), "cpu")
    assert u.shape == (5, n * spp) and (u >= 0).all() and (u < 1).all()
    m = spp // groups
    for dim in range(5):
        sets = u[dim].reshape(n * groups, m)
        strata = torch.sort(torch.floor(((sets - sets[:, :1]) % 1.0) * m + 1e-4), dim=1).values
        assert torch.equal(strata, torch.arange(m, dtype=strata.dtype).expand_as(strata)), dim
    # Not square / not divisible: plain uniform numbers of the right shape.
    assert stratified_samples(3, 6, 4, None, "cpu").shape == (5, 18)
    # Pixel jitter: ray k of 4 lands in cell k of the 2x2 grid.
    rng = np.random.default_rng(0)
    for k in range(4):
        off = pixel_jitter(100, k, 4, rng)
        assert ((off[:, 0] >= 0.5) == bool(k % 2)).all() and ((off[:, 1] >= 0.5) == bool(k // 2)).all()


def test_mesh_without_normals_gets_smooth_vertex_normals():
    """A mesh given without normals shades with interpolated vertex normals, not facets."""
    coarse = trimesh.creation.icosphere(subdivisions=1, radius=0.5)
    scene = ShadingScene(coarse.vertices, coarse.faces, _env(), np.eye(4))
    rng = np.random.default_rng(0)
    o = np.zeros((200, 3), dtype=np.float32)
    o[:, :2] = rng.uniform(-0.3, 0.3, (200, 2))
    o[:, 2] = -2.0
    d = np.tile(np.array([[0.0, 0.0, 1.0]], dtype=np.float32), (200, 1))
    hits = scene.trace(o, d)
    assert bool(hits.valid.all())
    # On a sphere the interpolated vertex normal points along the hit position; a facet's does not.
    radial = torch.nn.functional.normalize(hits.position, dim=-1)
    angle = torch.rad2deg(torch.arccos((radial * hits.normal).sum(-1).clamp(-1, 1)))
    assert float(angle.max()) < 0.5


class _ConstantMaterial(torch.nn.Module):
    """A stand-in for a fitted field: the same principled parameters at every point."""

    def __init__(self, base, metal, rough):
        super().__init__()
        self.register_buffer("center", torch.zeros(3))
        self.base, self.metal, self.rough = base, metal, rough

    def forward(self, p):
        n = p.shape[0]
        return {"basecolor": torch.tensor([self.base]).expand(n, 3), "metallic": torch.full((n,), self.metal),
                "roughness": torch.full((n,), self.rough), "z": torch.zeros(n, 4)}


@pytest.mark.cpu_inputs
def test_renderer_matches_mitsuba_direct_render(monkeypatch, tmp_path):
    """`Renderer.render` (several primary rays per pixel, shaded in chunks) gives Mitsuba's own
    `direct` render of the same sphere: coverage per pixel and mean colour; tracing the passes
    one at a time changes only the noise."""
    from vq_mitsuba.render import views as render_mod
    from vq_mitsuba.config import load_config

    env = _env()
    base, metal, rough = [0.6, 0.4, 0.2], 0.3, 0.35
    cfg = load_config(None, ["render.chunk=3000"])  # several chunks, so hits of one pixel span chunks
    fitted = FittedModel(cfg, _ConstantMaterial(base, metal, rough), None, env, np.eye(4), "mitsuba", SPHERE, 0)
    cam = Camera("c", look_at([0, -2.0, 0.4], [0, 0, 0], [0, 0, 1]), 40.0, 32, 32)
    ply = tmp_path / "sphere.ply"
    SPHERE.export(ply)
    out = render_mod.Renderer(fitted).render(cam, spp=256, aa=16, seed=0)
    ref_scene = mi.load_dict({
        "type": "scene", "integrator": {"type": "direct", "hide_emitters": True},
        "s": {"type": "ply", "filename": str(ply), "bsdf": {
            "type": "principled", "base_color": {"type": "rgb", "value": base}, "metallic": metal, "roughness": rough}},
        "env": {"type": "envmap", "bitmap": mi.Bitmap(env)},
    })
    ref = np.array(mi.render(ref_scene, sensor=mi.load_dict(cam.to_mitsuba_dict(1024)))).reshape(32, 32, 4)
    edge = (ref[..., 3] > 0.01) & (ref[..., 3] < 0.99)
    assert edge.sum() > 20  # the silhouette crosses pixels: fractional coverage is tested
    np.testing.assert_allclose(out["alpha"], ref[..., 3], atol=0.15)
    assert abs(out["alpha"].sum() - ref[..., 3].sum()) < 0.01 * ref[..., 3].sum()
    np.testing.assert_allclose(out["rgb"].reshape(-1, 3).mean(0), ref[..., :3].reshape(-1, 3).mean(0), rtol=0.02)
    inside = out["alpha"] > 0
    np.testing.assert_allclose(out["basecolor"][inside], np.broadcast_to(base, (int(inside.sum()), 3)), atol=1e-6)

    monkeypatch.setattr(render_mod, "MAX_RAYS", 32 * 32)  # one primary-ray pass per trace
    one = render_mod.Renderer(fitted).render(cam, spp=256, aa=16, seed=0)
    np.testing.assert_array_equal(one["alpha"], out["alpha"])
    np.testing.assert_allclose(one["normal"], out["normal"], atol=1e-5)
    np.testing.assert_allclose(one["rgb"].reshape(-1, 3).mean(0), out["rgb"].reshape(-1, 3).mean(0), rtol=0.02)


@pytest.mark.cpu_inputs
def test_relight_pass_gives_each_lighting_its_own_render():
    """`Renderer.render(..., relight=...)` returns, for every other lighting, the image its own
    `render` gives with the same seed (bounce included), while the material field runs once
    per chunk for the primary hits and once for the bounce hits, however many lightings."""
    from vq_mitsuba.render import views as render_mod
    from vq_mitsuba.config import load_config

    cam, both = _two_spheres_camera(24), _two_spheres(subdivisions=3)
    calls = []

    class Counted(_ConstantMaterial):
        def forward(self, p):
            calls.append(p.shape[0])
            return super().forward(p)

    cfg = load_config(None, ["render.chunk=4000", "train.bounces=1"])
    fitted = FittedModel(cfg, Counted([0.7, 0.6, 0.5], 0.2, 0.3), None, _env(seed=0), np.eye(4), "mitsuba", both, 0)
    lights = [render_mod.Renderer(fitted, env) for env in (None, _env(seed=1), _env(h=8, seed=2) * 3.0)]
    alone = [r.render(cam, spp=32, aa=4, seed=5)["rgb"] for r in lights]
    calls_alone = len(calls)
    calls.clear()
    shared = lights[0].render(cam, spp=32, aa=4, seed=5, relight=lights[1:])
    assert len(shared["relit"]) == 2
    for got, want in zip([shared["rgb"], *shared["relit"]], alone):
        np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-7)
    assert not np.allclose(alone[1], alone[2])  # the lightings differ, so the test can tell them apart
    assert calls_alone == 3 * len(calls) and len(calls) >= 2  # primary and bounce hits, once each

    other = FittedModel(cfg, fitted.model, None, _env(), np.eye(4), "mitsuba", both, 0)
    with pytest.raises(ValueError, match="same fitted run"):
        lights[0].render(cam, spp=4, aa=1, relight=[render_mod.Renderer(other)])


def _welch_rejections(a: np.ndarray, b: np.ndarray, alpha: float = 0.01) -> np.ndarray:
    """Per-pixel, per-channel Welch t-tests of two stacks of independent renders (K, H, W, C) with
    a Bonferroni correction over all tests: True where the means differ at level `alpha`."""
    from scipy import stats

    k1, k2 = len(a), len(b)
    m1, m2 = a.mean(0), b.mean(0)
    v1, v2 = a.var(0, ddof=1) / k1, b.var(0, ddof=1) / k2
    se2 = np.maximum(v1 + v2, 1e-12)
    t = (m1 - m2) / np.sqrt(se2)
    df = se2 ** 2 / np.maximum(v1 ** 2 / (k1 - 1) + v2 ** 2 / (k2 - 1), 1e-30)
    p = 2 * stats.t.sf(np.abs(t), df)
    return p < alpha / t.size


@pytest.mark.cpu_inputs
@pytest.mark.parametrize("two_spheres", [False, True])
def test_renderer_matches_mitsuba_per_pixel(tmp_path, two_spheres):
    """Every pixel of `Renderer.render` (its own pixel sampling, coverage, MIS shading and, for two
    spheres that light each other, the bounce) has the expectation of Mitsuba's own integrator on
    the same scene (`direct`; `path` at max_depth 3 for the bounce): a per-pixel Welch test over
    independent renders finds no pixel that differs, while a slightly rougher material is found
    to differ (the test can fail)."""
    from vq_mitsuba.config import load_config
    from vq_mitsuba.render.views import Renderer

    env = _env()
    base, metal, rough = [0.6, 0.4, 0.2], 0.5, 0.3
    cfg = load_config(None, ["train.bounces=1"])
    mesh = _two_spheres(subdivisions=3) if two_spheres else SPHERE
    cam = _two_spheres_camera(24) if two_spheres else \
        Camera("c", look_at([0, -2.0, 0.4], [0, 0, 0], [0, 0, 1]), 40.0, 24, 24)
    ply = tmp_path / "mesh.ply"
    mesh.export(ply)

    def ours(r, seeds):
        fitted = FittedModel(cfg, _ConstantMaterial(base, metal, r), None, env, np.eye(4), "mitsuba", mesh, 0)
        renderer = Renderer(fitted)
        return np.stack([renderer.render(cam, spp=64, aa=16, seed=s)["rgb"] for s in seeds])

    integrator = {"type": "path", "max_depth": 3} if two_spheres else {"type": "direct"}
    ref_scene = mi.load_dict({
        "type": "scene", "integrator": {**integrator, "hide_emitters": True},
        "s": {"type": "ply", "filename": str(ply), "bsdf": {
            "type": "principled", "base_color": {"type": "rgb", "value": base}, "metallic": metal, "roughness": rough}},
        "env": {"type": "envmap", "bitmap": mi.Bitmap(env)},
    })
    sensor = mi.load_dict(cam.to_mitsuba_dict(64))
    ref = np.stack([np.array(mi.render(ref_scene, sensor=sensor, seed=100 + s))[..., :3] for s in range(10)])
    same = _welch_rejections(ours(rough, range(10)), ref)
    assert same.sum() == 0, np.argwhere(same)[:10]
    rougher = _welch_rejections(ours(rough + 0.15, range(10)), ref)
    assert rougher.sum() >= 10  # the highlight pixels


def test_render_under_several_envmaps_in_one_pass_matches_one_at_a_time(three_materials, tmp_path):
    from vq_mitsuba.cli import main
    from vq_mitsuba.data.imageio import read_exr, write_exr

    capture, run = three_materials
    envs = []
    for name, colour in (("warm", (3.0, 1.5, 0.5)), ("cool", (0.4, 0.9, 2.5))):
        env = np.ones((16, 32, 3), np.float32) * np.asarray(colour, np.float32)
        env[:4] *= 4.0  # a brighter sky band
        write_exr(tmp_path / f"{name}.exr", env)
        envs.append(tmp_path / f"{name}.exr")
    args = ["--cameras", str(capture), "--spp", "16", "--quiet"]
    assert main(["render", str(run.dir), *args, "--envmap", str(envs[0]), "--envmap", str(envs[1]),
                 "-o", str(tmp_path / "both")]) == 0
    for env in envs:
        assert main(["render", str(run.dir), *args, "--envmap", str(env), "-o", str(tmp_path / env.stem)]) == 0
    for view in ("view_00", "view_05"):
        assert np.array_equal(read_exr(tmp_path / "both" / f"{view}_rgb.exr"), read_exr(tmp_path / "warm" / f"{view}_rgb.exr"))
        assert np.array_equal(read_exr(tmp_path / "both" / "cool" / f"{view}_rgb.exr"),
                              read_exr(tmp_path / "cool" / f"{view}_rgb.exr"))
        assert not np.array_equal(read_exr(tmp_path / "both" / f"{view}_rgb.exr"),
                                  read_exr(tmp_path / "both" / "cool" / f"{view}_rgb.exr"))
    assert main(["render", str(run.dir), *args, "--envmap", str(envs[0]), "--envmap", str(envs[0]),
                 "-o", str(tmp_path / "same")]) == 2  # two lightings, one folder name


@pytest.mark.cpu_inputs
def test_fixed_light_points_shade_alike_but_do_not_train_the_light():
    """Two copies of the same points in one call, the second with `fixed_light`: the radiance is
    that of the call without it (same samples), and the envmap gets exactly the gradient of the
    first copy alone."""
    env0 = _env()
    scene, cam = _touching_spheres(env0)
    hits = scene.trace(*camera_rays(cam))
    v = torch.nonzero(hits.valid)[:, 0][::3]
    n = len(v)

    def material(points):
        m = points.shape[0]
        return {"basecolor": torch.full((m, 3), 0.4), "metallic": torch.full((m,), 0.2),
                "roughness": torch.full((m,), 0.4)}

    def run(fixed, rows):
        env = torch.tensor(env0, requires_grad=True)
        p, nrm, wi = (t[v].repeat(2, 1) for t in (hits.position, hits.normal, hits.wi))
        base = torch.full((2 * n, 3), 0.5, requires_grad=True)
        mat = {"basecolor": base, "metallic": torch.full((2 * n,), 0.3), "roughness": torch.full((2 * n,), 0.3)}
        rgb = scene.shade(p, nrm, wi, mat, env, 16,
                          generator=torch.Generator().manual_seed(3), material_fn=material, fixed_light=fixed)
        rgb[rows].sum().backward()
        return rgb.detach(), env.grad.clone(), base.grad.clone()

    free, g_env_first, g_base_first = run(None, slice(0, n))
    assert g_env_first.abs().sum() > 0
    both, g_env, g_base = run(torch.arange(2 * n) >= n, slice(None))
    assert torch.equal(both, free)
    assert torch.allclose(g_env, g_env_first, rtol=1e-5, atol=1e-7)
    assert torch.allclose(g_base[:n], g_base_first[:n]) and (g_base[n:].abs().sum(1) > 0).any()
    _, g_env_none, _ = run(torch.ones(2 * n, dtype=torch.bool), slice(None))
    assert float(g_env_none.abs().max()) == 0.0


def test_envmap_lookup_gives_mitsubas_envmap_radiance():
    """The light's radiance shading looks up in torch is Mitsuba's `envmap`: at texture coordinates
    (`eval_direction`, the seam and the poles included) and along world directions under a rotated
    to_world (`eval`)."""
    from vq_mitsuba.render.shading import direction_uv, envmap_lookup

    env = _env(8) * np.linspace(0.5, 2.0, 16, dtype=np.float32)[None, :, None]
    to_world = trimesh.transformations.rotation_matrix(0.7, [0.3, 1.0, 0.2])
    scene = _scene(env, to_world)
    rng = np.random.default_rng(3)
    n = 4000
    uv = rng.random((n, 2)).astype(np.float32)
    uv[:40, 0], uv[40:80, 0], uv[80:120, 1], uv[120:160, 1] = 0.0, np.nextafter(np.float32(1), 0), 0.0, 1.0
    ds = dr.zeros(mi.DirectionSample3f, n)
    ds.uv = mi.Point2f(mi.Float(uv[:, 0]), mi.Float(uv[:, 1]))
    theirs = np.array(scene.emitter.eval_direction(dr.zeros(mi.Interaction3f, n), ds, True))
    padded = envmap_padded(torch.tensor(env))
    ours = envmap_lookup(padded, torch.tensor(uv)).numpy()
    np.testing.assert_allclose(ours, theirs.reshape(n, 3) if theirs.shape[0] == n else theirs.T, rtol=1e-5, atol=1e-5)
    d = rng.normal(size=(n, 3)).astype(np.float32)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    si = dr.zeros(mi.SurfaceInteraction3f, n)
    si.wi = mi.Vector3f(*(mi.Float(-d[:, i]) for i in range(3)))
    theirs = np.array(scene.emitter.eval(si, True))
    ours = envmap_lookup(padded, direction_uv(torch.tensor(d), scene.world_to_env)).numpy()
    np.testing.assert_allclose(ours, theirs.reshape(n, 3) if theirs.shape[0] == n else theirs.T, rtol=1e-5, atol=1e-4)


def test_shading_and_its_gradients_are_the_same_every_run():
    """Two identical shading calls, Dr.Jit on every core, give the same colours and the same
    gradients to the bit, the envmap's included (scattered from several threads it was summed in
    another order each run)."""
    assert dr.thread_count() >= 2  # the case that was not reproducible
    scene = _scene(_env(16))
    p, nrm, wi = _points(2000)

    def run():
        env = torch.tensor(_env(16), requires_grad=True)
        mat = {"basecolor": torch.full((len(p), 3), 0.6, requires_grad=True),
               "metallic": torch.full((len(p),), 0.5, requires_grad=True),
               "roughness": torch.full((len(p),), 0.3, requires_grad=True)}
        rgb = scene.shade(p, nrm, wi, mat, env, 16, torch.Generator().manual_seed(0))
        rgb.square().sum().backward()
        return [rgb.detach(), env.grad] + [mat[k].grad for k in sorted(mat)]

    first, second = run(), run()
    assert first[1].abs().sum() > 0
    for a, b in zip(first, second):
        assert torch.equal(a, b)
    # Without gradients the kernel takes the light from Mitsuba's envmap itself: the same colours.
    with torch.no_grad():
        mat = {"basecolor": torch.full((len(p), 3), 0.6), "metallic": torch.full((len(p),), 0.5),
               "roughness": torch.full((len(p),), 0.3)}
        plain = scene.shade(p, nrm, wi, mat, torch.tensor(_env(16)), 16, torch.Generator().manual_seed(0))
    torch.testing.assert_close(plain, first[0], rtol=1e-5, atol=1e-6)


@pytest.mark.cpu_inputs
def test_the_shading_steps_run_alone_give_what_shade_gives():
    """`lanes`, `set_light`, `sample`, `bounce_light` and `radiance` called one by one, with the
    same random numbers, give `shade`'s samples bit for bit, bounce and light gradients included."""
    from vq_mitsuba.render.shading import stratified_samples

    env = torch.tensor(_env(), requires_grad=True)
    both = _two_spheres(subdivisions=3)
    scene = ShadingScene(both.vertices, both.faces, env.detach().numpy(), np.eye(4), normals=both.vertex_normals)
    hits = scene.trace(*camera_rays(_two_spheres_camera(24)))
    v = hits.valid
    n, spp = int(v.sum()), 4

    def material(points):
        m = points.shape[0]
        return {"basecolor": torch.full((m, 3), 0.6), "metallic": torch.full((m,), 0.3),
                "roughness": torch.full((m,), 0.4)}

    whole = scene.shade(hits.position[v], hits.normal[v], hits.wi[v], material(hits.position[v]), env, spp,
                        torch.Generator().manual_seed(3), reduce=False, material_fn=material)
    gen = torch.Generator().manual_seed(3)
    rep = lambda t: t.repeat_interleave(spp, dim=0)  # noqa: E731
    lanes = scene.lanes(rep(hits.position[v]), rep(hits.normal[v]), rep(hits.wi[v]),
                        {k: rep(t) for k, t in material(hits.position[v]).items()})
    scene.set_light(env)
    sampled = scene.sample(lanes, stratified_samples(n, spp, 1, gen, lanes.chans.device))
    bounce = scene.bounce_light(sampled, material, env, gen)
    steps = scene.radiance(lanes, sampled, env, bounce)
    assert torch.equal(steps.view(n, spp, 3), whole)
    assert bool((bounce.abs().sum(1) > 0).any())  # some samples meet the other sphere
    (g_whole,) = torch.autograd.grad(whole.sum(), env)
    (g_steps,) = torch.autograd.grad(steps.sum(), env)
    assert torch.equal(g_whole, g_steps) and float(g_whole.abs().sum()) > 0


@pytest.mark.cpu_inputs
def test_the_sampling_step_alone_shadows_what_the_sphere_hides():
    """On a convex sphere an emitter sample is lit exactly when it leaves the surface outwards, and
    no BSDF sample meets the object."""
    scene = _scene(_env())
    p, nrm, wi = _points(512)
    m = len(p)
    lanes = scene.lanes(p, nrm, wi, {"basecolor": torch.full((m, 3), 0.5), "metallic": torch.zeros(m),
                                     "roughness": torch.full((m,), 0.5)})
    scene.set_light(torch.tensor(_env()))
    at = dict(zip(scene.SAMPLED, scene.sample(lanes, torch.rand(5, m, generator=torch.Generator().manual_seed(0)))))
    d = torch.stack([at["dx"], at["dy"], at["dz"]], -1)
    cos = (d * nrm).sum(-1)
    sure = (cos.abs() > 0.1) & (at["ds_pdf"] > 0)  # away from the horizon, where facets and normals differ
    assert int(sure.sum()) > 300
    assert torch.equal(at["lit"][sure] > 0.5, cos[sure] > 0)
    assert float(at["hit"].sum()) == 0.0
