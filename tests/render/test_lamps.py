"""Point lamps beside the envmap: Mitsuba's own `point` emitter per pixel, gradients of the lamps'
positions and intensities against finite differences, and lamps that a fixed light does not train."""

import numpy as np
import pytest
import torch
import trimesh

import mitsuba as mi

from vq_mitsuba.backend import init_mitsuba
from vq_mitsuba.data.cameras import Camera, camera_rays, look_at
from vq_mitsuba.render.shading import ShadingScene

init_mitsuba()

BLACK = np.full((8, 16, 3), 1e-6, np.float32)  # an envmap that lights nothing
BASE, METAL, ROUGH = [0.6, 0.4, 0.2], 0.3, 0.35


def _sphere_on_slab():
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.5)
    slab = trimesh.creation.box(extents=[3, 3, 0.1])
    slab.apply_translation([0, 0, -0.6])
    return trimesh.util.concatenate([sphere, slab])


def _material(n):
    return {"basecolor": torch.tensor([BASE]).expand(n, 3), "metallic": torch.full((n,), METAL),
            "roughness": torch.full((n,), ROUGH)}


@pytest.mark.cpu_inputs
def test_point_lamp_matches_mitsubas_point_emitter_per_pixel(tmp_path):
    """A sphere on a slab that it shadows, lit by one point lamp: each pixel's radiance equals
    Mitsuba's `direct` render of the same scene with a `point` emitter, shadows included."""
    mesh = _sphere_on_slab()
    scene = ShadingScene(mesh.vertices, mesh.faces, BLACK, np.eye(4), normals=mesh.vertex_normals)
    position, intensity = torch.tensor([[0.8, -0.6, 1.2]]), torch.tensor([[3.0, 2.0, 1.0]])
    scene.lamps = lambda views: (position, intensity)
    cam = Camera("c", look_at([0, -2.5, 1.2], [0, 0, 0], [0, 0, 1]), 45.0, 48, 48)
    hits = scene.trace(*camera_rays(cam))
    v = hits.valid
    ours = scene.shade(hits.position[v], hits.normal[v], hits.wi[v], _material(int(v.sum())),
                       torch.tensor(BLACK), spp=2).numpy()
    mesh.export(tmp_path / "m.ply")
    bsdf = {"type": "principled", "base_color": {"type": "rgb", "value": BASE}, "metallic": METAL, "roughness": ROUGH}
    ref_scene = mi.load_dict({
        "type": "scene", "integrator": {"type": "direct", "hide_emitters": True},
        "m": {"type": "ply", "filename": str(tmp_path / "m.ply"), "bsdf": bsdf, "face_normals": False},
        "l": {"type": "point", "position": position[0].tolist(), "intensity": {"type": "rgb", "value": intensity[0].tolist()}},
    })
    ref = np.array(mi.render(ref_scene, sensor=mi.load_dict(cam.to_mitsuba_dict(64)))).reshape(-1, 4)
    inside = (ref[:, 3] > 0.999) & v.numpy()
    full = np.zeros((len(ref), 3))
    full[v.numpy()] = ours
    a, b = full[inside], ref[inside, :3]
    lit_a, lit_b = a.sum(1) > 1e-3, b.sum(1) > 1e-3
    assert 0.2 < lit_b.mean() < 0.9  # some of the slab lies in the sphere's shadow, the rest is lit
    assert np.mean(lit_a != lit_b) < 0.04  # shadow and terminator edges, antialiased in Mitsuba's render only
    both = lit_a & lit_b
    assert np.median(np.abs(a[both] - b[both]) / b[both]) < 0.01
    np.testing.assert_allclose(a.mean(0), b.mean(0), rtol=0.02)


def _points_on_sphere(n=200, seed=1):
    rng = np.random.default_rng(seed)
    nrm = rng.normal(size=(n, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    wi = nrm + 0.5 * rng.normal(size=(n, 3))
    wi /= np.linalg.norm(wi, axis=1, keepdims=True)
    wi = np.where((wi * nrm).sum(1, keepdims=True) < 0.1, nrm, wi)
    t = lambda a: torch.tensor(a, dtype=torch.float32)  # noqa: E731
    return t(0.5 * nrm), t(nrm), t(wi)


@pytest.mark.cpu_inputs
def test_lamp_gradients_match_finite_differences():
    """The gradients of a lamp's position and log-intensity, and of the material it lights, agree
    with central differences (the lamp's light has no random sample: exact up to rounding)."""
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.5)
    scene = ShadingScene(sphere.vertices, sphere.faces, BLACK, np.eye(4), normals=sphere.vertex_normals)
    p, n, wi = _points_on_sphere()
    w = torch.tensor([0.5, 1.0, 2.0])
    pos = torch.tensor([[0.7, -0.5, 0.9]], requires_grad=True)
    log_i = torch.tensor([[1.0, 0.5, 0.2]], requires_grad=True)
    base = torch.full((len(p), 3), 0.5, requires_grad=True)

    def loss(pos, log_i, base):
        scene.lamps = lambda views: (pos, torch.exp(log_i))
        mat = {"basecolor": base, "metallic": torch.full((len(p),), 0.2), "roughness": torch.full((len(p),), 0.4)}
        return (scene.lamp_radiance(p, n, wi, mat) * w).sum()

    loss(pos, log_i, base).backward()
    eps = 1e-3
    with torch.no_grad():
        for k in range(3):
            d = torch.zeros(1, 3)
            d[0, k] = eps
            fd = (loss(pos + d, log_i, base) - loss(pos - d, log_i, base)).item() / (2 * eps)
            assert pos.grad[0, k].item() == pytest.approx(fd, rel=0.02, abs=1e-3), f"position {k}"
            fd = (loss(pos, log_i + d, base) - loss(pos, log_i - d, base)).item() / (2 * eps)
            assert log_i.grad[0, k].item() == pytest.approx(fd, rel=0.01), f"log-intensity {k}"
        fd = (loss(pos, log_i, base + eps) - loss(pos, log_i, base - eps)).item() / (2 * eps)
    assert base.grad.sum().item() == pytest.approx(fd, rel=0.01)
    assert pos.grad.abs().sum() > 0 and log_i.grad.abs().min() > 0


@pytest.mark.cpu_inputs
def test_fixed_light_points_pass_no_gradient_to_the_lamps():
    """Points shaded under a fixed light (the discrete branch's) are lit by the lamps alike but
    train neither their position nor their intensity."""
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.5)
    scene = ShadingScene(sphere.vertices, sphere.faces, BLACK, np.eye(4), normals=sphere.vertex_normals)
    p, n, wi = _points_on_sphere(64)
    pos = torch.tensor([[0.7, -0.5, 0.9]], requires_grad=True)
    log_i = torch.zeros(1, 3, requires_grad=True)
    scene.lamps = lambda views: (pos, torch.exp(log_i))
    mat = _material(len(p))
    free = scene.lamp_radiance(p, n, wi, mat)
    fixed = scene.lamp_radiance(p, n, wi, mat, fixed_light=torch.ones(len(p), dtype=torch.bool))
    assert torch.allclose(free, fixed) and free.abs().sum() > 0
    fixed.sum().backward()
    assert pos.grad is None or pos.grad.abs().sum() == 0
    assert log_i.grad is None or log_i.grad.abs().sum() == 0
    free.sum().backward()
    assert pos.grad.abs().sum() > 0 and log_i.grad.abs().sum() > 0


class _Constant(torch.nn.Module):
    """A stand-in for a fitted field: the same principled parameters at every point."""

    def __init__(self):
        super().__init__()
        self.register_buffer("center", torch.zeros(3))

    def forward(self, p):
        n = p.shape[0]
        return {"basecolor": torch.tensor([BASE]).expand(n, 3), "metallic": torch.full((n,), METAL),
                "roughness": torch.full((n,), ROUGH), "z": torch.zeros(n, 4)}


@pytest.mark.cpu_inputs
def test_renders_under_the_fitted_light_include_the_lamps_and_relit_ones_leave_them_out():
    """A run's lamps light its renders under its own light (as Mitsuba's `direct` with a `point`
    emitter does), not those under another envmap unless `keep_lamps`; an exposure scales them."""
    from vq_mitsuba.config import load_config
    from vq_mitsuba.models.fitted import FittedLamps, FittedModel
    from vq_mitsuba.render.views import Renderer

    mesh = _sphere_on_slab()
    lamps = FittedLamps(np.array([[0.8, -0.6, 1.2]]), np.array([[3.0, 2.0, 1.0]]))
    fitted = FittedModel(load_config(None, ["train.bounces=0"]), _Constant(), None, BLACK, np.eye(4), "mitsuba", mesh,
                         0, lamps=lamps)
    cam = Camera("c", look_at([0, -2.5, 1.2], [0, 0, 0], [0, 0, 1]), 45.0, 24, 24)
    own = Renderer(fitted).render(cam, spp=8, aa=4, seed=0)["rgb"]
    relit = Renderer(fitted, envmap=BLACK * 2).render(cam, spp=8, aa=4, seed=0)["rgb"]
    kept = Renderer(fitted, envmap=BLACK, keep_lamps=True, exposure_ev=1.0).render(cam, spp=8, aa=4, seed=0)["rgb"]
    assert own.mean() > 0.01 and relit.max() < 1e-4
    np.testing.assert_allclose(kept, 2 * own, rtol=1e-4, atol=1e-6)


@pytest.mark.cpu_inputs
def test_exported_mitsuba_scene_holds_the_lamps(tmp_path):
    """`export --format mitsuba` writes the fitted lamps as `point` emitters: Mitsuba's own render
    of the exported scene.xml, without its envmap, is as bright as the lamp alone predicts."""
    from vq_mitsuba.export.bake import BakedMesh
    from vq_mitsuba.export.mitsuba_scene import write_mitsuba

    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.5)
    lamps = np.array([[0.8, -0.6, 1.2, 3.0, 2.0, 1.0]])
    v = np.asarray(sphere.vertices, np.float32)
    baked = BakedMesh(v, np.asarray(sphere.faces), np.asarray(sphere.vertex_normals, np.float32),
                      np.full((len(v), 2), 0.5, np.float32), np.full((4, 4, 3), 0.5, np.float32),
                      np.zeros((4, 4), np.float32), np.full((4, 4), 0.5, np.float32), None, np.ones((4, 4), bool))
    cam = Camera("c", look_at([0, -2.5, 1.2], [0, 0, 0], [0, 0, 1]), 45.0, 24, 24)
    write_mitsuba(tmp_path, baked, BLACK, np.eye(4), [cam], 16, 2, "object", lamps)
    xml = (tmp_path / "scene.xml").read_text()
    assert xml.count('type="point"') == 1
    scene = mi.load_file(str(tmp_path / "scene.xml"))
    emitters = [e for e in scene.emitters() if not e.is_environment()]
    assert len(emitters) == 1
    image = np.array(mi.render(scene, spp=16))
    ours = ShadingScene(sphere.vertices, sphere.faces, BLACK, np.eye(4), normals=sphere.vertex_normals)
    ours.lamps = lambda views: (torch.tensor(lamps[:, :3], dtype=torch.float32), torch.tensor(lamps[:, 3:], dtype=torch.float32))
    hits = ours.trace(*camera_rays(cam))
    v = hits.valid
    mat = {"basecolor": torch.full((int(v.sum()), 3), 0.5), "metallic": torch.zeros(int(v.sum())),
           "roughness": torch.full((int(v.sum()),), 0.5)}
    rgb = ours.shade(hits.position[v], hits.normal[v], hits.wi[v], mat, torch.tensor(BLACK), spp=2).numpy()
    inside = image.reshape(-1, image.shape[-1])[v.numpy(), :3]
    np.testing.assert_allclose(inside.mean(0), rgb.mean(0), rtol=0.05)


def test_lamps_that_ride_with_the_camera_stand_at_each_views_camera():
    """A camera lamp's position is its offset (object radii) in the frame of the view's camera; a
    world lamp's is the centre plus its offset, whatever the view."""
    from vq_mitsuba.models.fields import PointLamps

    cams = np.stack([look_at([0, -2.5, 1.2], [0, 0, 0], [0, 0, 1]), look_at([2.0, 1.0, 0.5], [0, 0, 0], [0, 0, 1])])
    offsets = torch.tensor([[0.0, 0.2, 0.0], [0.1, 0.0, 0.0]])
    flash = PointLamps([0.1, 0.2, 0.3], 0.5, offsets, 2.0, camera_to_world=cams)
    views = torch.tensor([1, 0, 1])
    pos, inten = flash(views)
    assert pos.shape == (2, 3, 3) and torch.allclose(inten, torch.full((2, 3), 2.0))
    for k in range(2):
        for j, v in enumerate(views.tolist()):
            want = cams[v][:3, :3] @ (0.5 * offsets[k].numpy()) + cams[v][:3, 3]
            np.testing.assert_allclose(pos[k, j].detach().numpy(), want, atol=1e-6)
    with pytest.raises(ValueError, match="views"):
        flash(None)
    world = PointLamps([0.1, 0.2, 0.3], 0.5, offsets, 2.0)
    np.testing.assert_allclose(world(views)[0].detach().numpy(), [0.1, 0.2, 0.3] + 0.5 * offsets.numpy(), atol=1e-6)


@pytest.mark.cpu_inputs
def test_a_fitted_flash_lights_each_render_from_its_camera():
    """A run's flash (a lamp in the camera's frame) renders each view as a world lamp standing at
    that view's camera would."""
    from vq_mitsuba.config import load_config
    from vq_mitsuba.models.fitted import FittedLamps, FittedModel
    from vq_mitsuba.render.views import Renderer

    mesh = _sphere_on_slab()
    cfg = load_config(None, ["train.bounces=0"])
    offset, intensity = np.array([[0.1, 0.3, 0.0]]), np.array([[5.0, 4.0, 3.0]])
    flash = FittedModel(cfg, _Constant(), None, BLACK, np.eye(4), "mitsuba", mesh, 0,
                        lamps=FittedLamps(offset, intensity, in_camera=True))
    for eye in ([0, -2.5, 1.2], [2.0, 1.0, 0.8]):
        cam = Camera("c", look_at(eye, [0, 0, 0], [0, 0, 1]), 45.0, 16, 16)
        at = cam.to_world[:3, :3] @ offset[0] + cam.to_world[:3, 3]
        world = FittedModel(cfg, _Constant(), None, BLACK, np.eye(4), "mitsuba", mesh, 0,
                            lamps=FittedLamps(at[None], intensity))
        a = Renderer(flash).render(cam, spp=4, aa=1, seed=0)["rgb"]
        b = Renderer(world).render(cam, spp=4, aa=1, seed=0)["rgb"]
        assert a.mean() > 0.01
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)


def test_glb_holds_the_lamps_as_punctual_lights(tmp_path):
    """`export --format gltf` writes world lamps as KHR_lights_punctual point lights at their
    positions turned into the file's axes, colour and intensity (cd at 683 lm/W) from their RGB
    intensity; the Khronos validator, where installed, finds nothing wrong."""
    import json
    import shutil
    import struct
    import subprocess
    from pathlib import Path

    from vq_mitsuba.export.bake import BakedMesh
    from vq_mitsuba.export.gltf import write_glb

    sphere = trimesh.creation.icosphere(subdivisions=2, radius=0.5)
    v = np.asarray(sphere.vertices, np.float32)
    baked = BakedMesh(v, np.asarray(sphere.faces), np.asarray(sphere.vertex_normals, np.float32),
                      np.full((len(v), 2), 0.5, np.float32), np.full((4, 4, 3), 0.5, np.float32),
                      np.zeros((4, 4), np.float32), np.full((4, 4), 0.5, np.float32), None, np.ones((4, 4), bool))
    axes = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
    lamps = np.array([[0.8, -0.6, 1.2, 3.0, 2.0, 1.0]])
    glb = write_glb(tmp_path / "o.glb", baked, axes, "o", lamps)
    data = glb.read_bytes()
    length, = struct.unpack("<I", data[12:16])
    doc = json.loads(data[20:20 + length])
    assert doc["extensionsUsed"] == ["KHR_lights_punctual"]
    (light,) = doc["extensions"]["KHR_lights_punctual"]["lights"]
    assert light["type"] == "point" and light["color"] == pytest.approx([1.0, 2 / 3, 1 / 3])
    assert light["intensity"] == pytest.approx(683.0 * 3.0)
    node = doc["nodes"][1]
    assert node["extensions"]["KHR_lights_punctual"]["light"] == 0 and doc["scenes"][0]["nodes"] == [0, 1]
    assert node["translation"] == pytest.approx((axes @ lamps[0, :3]).tolist())
    root = Path(__file__).resolve().parents[2]
    validator = root / ".node" / "node_modules" / "gltf-validator"
    if shutil.which("node") is not None and validator.is_dir():
        report = json.loads(subprocess.run(["node", str(root / "tools" / "validate_gltf.js"), str(glb)], check=True,
                                           capture_output=True, text=True).stdout)
        assert report["issues"]["numErrors"] == 0, report["issues"]["messages"]
