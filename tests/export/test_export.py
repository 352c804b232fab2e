"""Exports that are right, not just written: the Mitsuba scene renders like `vq-mitsuba render`
in plain Mitsuba, the .glb passes the Khronos validator and re-imports, the textures hold the
field's values, and the envmap keeps its directions in Blender's convention."""

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from vq_mitsuba import cli
from vq_mitsuba.data.envmaps import texel_directions
from vq_mitsuba.eval import metrics as M
from vq_mitsuba.export.bake import bake, rasterise_uv
from vq_mitsuba.export.files import Y_UP_TO_BLENDER, envmap_for_blender, export_axes, world_to_y_up
from vq_mitsuba.export.formats import _planned_files, export_run
from vq_mitsuba.render.views import Renderer

ROOT = Path(__file__).resolve().parents[2]
VALIDATOR = ROOT / ".node" / "node_modules" / "gltf-validator"

# Renders the first sensor named NAME of an exported scene with Mitsuba alone: no vq_mitsuba.
PLAIN_MITSUBA = """
import sys
import numpy as np
import mitsuba as mi
mi.set_variant("llvm_ad_rgb")
scene = mi.load_file(sys.argv[1], spp=int(sys.argv[3]))
index = [s.id() for s in scene.sensors()].index(sys.argv[2])
np.save(sys.argv[4], np.array(mi.render(scene, sensor=index, seed=int(sys.argv[5]))))
assert not [m for m in sys.modules if m.startswith("vq_mitsuba")]
"""


def _bilinear(tex: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear lookup with texel centres at (i + 0.5) / S and row 0 at v = 0 (glTF / Mitsuba)."""
    s = tex.shape[0]
    x, y = uv[:, 0] * s - 0.5, uv[:, 1] * s - 0.5
    x0, y0 = np.clip(np.floor(x).astype(int), 0, s - 2), np.clip(np.floor(y).astype(int), 0, s - 2)
    fx, fy = np.clip(x - x0, 0, 1), np.clip(y - y0, 0, 1)
    if tex.ndim == 3:
        fx, fy = fx[:, None], fy[:, None]
    return ((tex[y0, x0] * (1 - fx) + tex[y0, x0 + 1] * fx) * (1 - fy)
            + (tex[y0 + 1, x0] * (1 - fx) + tex[y0 + 1, x0 + 1] * fx) * fy)


@pytest.fixture(scope="module")
def fitted(three_materials):
    return three_materials[1].load()


FIT_BRIEFLY = ["--quiet", "--set", "train.iterations=4", "--set", "train.batch_rays=128"]


@pytest.fixture(scope="module")
def nerf_run(tmp_path_factory):
    """(capture folder, RunDir): a tiny NeRF-format capture (transforms_*.json, mesh.ply, Blender's
    world) fitted for a few steps. Geometry and cameras are all the export tests below need."""
    from vq_mitsuba.run.run_dir import RunDir
    from vq_mitsuba.synthetic.mitsuba_scenes import make_scene

    root = tmp_path_factory.mktemp("nerf")
    data = make_scene("demo", root / "demo", resolution=16, n_train=4, n_test=2, spp=8)
    assert cli.main(["fit", str(data / "transforms_train.json"), "-o", str(root / "run"), *FIT_BRIEFLY]) == 0
    return data, RunDir(root / "run")


def _gltf_to_blender(v: np.ndarray) -> np.ndarray:
    """What Blender's glTF and OBJ importers make of Y-up (x, y, z): Blender's (x, -z, y)."""
    return np.stack([v[:, 0], -v[:, 2], v[:, 1]], 1)


def _own_test_camera(data: Path, size: int = 64):
    """The capture's first test view, as its transforms_test.json gives it (its own world), at size^2."""
    from vq_mitsuba.data.captures import load_cameras

    spec = json.loads((data / "transforms_test.json").read_text())
    spec.update(w=size, h=size, frames=spec["frames"][:1])
    path = data / f"transforms_test_{size}.json"
    path.write_text(json.dumps(spec))
    (camera,), world, _ = load_cameras(path)
    assert world == "blender"
    return path, camera, spec["frames"][0]


def _coverage(mesh, camera, rays: int = 64) -> np.ndarray:
    """(H, W) share of each pixel's jittered rays that hit `mesh` (in the camera's world)."""
    from vq_mitsuba.data.cameras import camera_rays
    from vq_mitsuba.render.shading import scene_for_mesh

    scene = scene_for_mesh(mesh, np.ones((8, 16, 3), np.float32), np.eye(4))
    rng = np.random.default_rng(0)
    hits = np.zeros(camera.height * camera.width)
    for _ in range(rays):
        o, d = camera_rays(camera, jitter=rng.random((camera.height * camera.width, 2)))
        hits += scene.trace(o, d).valid.cpu().numpy()
    return (hits / rays).reshape(camera.height, camera.width)


def _soft_iou(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.minimum(a, b).sum() / np.maximum(a, b).sum())


def test_rasteriser_covers_each_triangle_once():
    uvs = np.array([[0.1, 0.1], [0.9, 0.1], [0.1, 0.9], [0.9, 0.9]], np.float32)
    faces = np.array([[0, 1, 2], [1, 3, 2]])
    texel, tri, bary = rasterise_uv(uvs, faces, 32, grow_px=0.0)
    assert len(np.unique(texel)) == len(texel)
    # Every texel centre inside the square is covered, none outside it (grow 0).
    ys, xs = np.divmod(texel, 32)
    centres = np.stack([(xs + 0.5) / 32, (ys + 0.5) / 32], 1)
    assert np.all((centres >= 0.1 - 1e-6) & (centres <= 0.9 + 1e-6))
    assert len(texel) == 26 * 26
    assert np.allclose(bary.sum(1), 1.0, atol=1e-5) and bary.min() >= -1e-5
    recon = np.einsum("tk,tkc->tc", bary, uvs[faces[tri]])
    assert np.allclose(recon, centres, atol=1e-5)


def test_textures_hold_the_field_values(fitted):
    baked = bake(fitted, 256)
    # At the mesh's vertices (inside charts, on their borders too) a bilinear lookup of the
    # textures gives what the field gives there.
    pts = torch.as_tensor(baked.vertices)
    truth = fitted.materials_at(pts)
    for key in ("basecolor", "metallic", "roughness"):
        err = np.abs(_bilinear(getattr(baked, key), baked.uvs) - truth[key].numpy())
        assert np.median(err) < 0.01 and np.percentile(err, 95) < 0.05, (key, np.median(err), np.percentile(err, 95))
    ids = baked.material[np.clip((baked.uvs[:, 1] * 256).astype(int), 0, 255),
                         np.clip((baked.uvs[:, 0] * 256).astype(int), 0, 255)]
    assert np.mean(ids == truth["material"].numpy()) > 0.97
    assert baked.material[baked.coverage].min() >= 1 and baked.coverage.mean() > 0.3


def test_discrete_branch_bakes_one_brdf_per_material(fitted):
    baked = bake(fitted, 128, branch="discrete")
    covered = baked.coverage
    colours = np.round(baked.basecolor[covered], 4)
    assert len(np.unique(colours, axis=0)) == fitted.num_materials


def test_mitsuba_export_renders_like_vq_mitsuba_in_plain_mitsuba(three_materials, tmp_path):
    _, run = three_materials
    out = tmp_path / "mitsuba"
    summary = export_run(run.dir, "mitsuba", out, texture_size=512)
    assert set(summary["files"]) <= set(_planned_files("mitsuba", run.dir.name)), summary["files"]
    fitted = run.load()
    cam = run.cameras()["train"][0]
    spp = 1024
    plain = tmp_path / "plain.npy"
    subprocess.run([sys.executable, "-c", PLAIN_MITSUBA, str(out / "scene.xml"), cam.name, str(spp), str(plain), "1"],
                   check=True, capture_output=True, text=True)
    theirs = np.load(plain)
    renderer = Renderer(fitted)
    ours = renderer.render(cam, spp=spp, seed=0)
    ours_again = renderer.render(cam, spp=spp, seed=1)
    mask = ours["alpha"] > 0
    assert np.abs(theirs[..., 3] - ours["alpha"]).mean() < 0.01  # same coverage: same mesh and cameras
    rgb, rgb_again = (o.get("rgb_physical", o["rgb"]) for o in (ours, ours_again))  # a residual is not exported
    psnr = M.image_metrics(theirs[..., :3], rgb, mask)["psnr"]
    noise_floor = M.image_metrics(rgb_again, rgb, mask)["psnr"]
    # The two renderers differ by no more than two renders of ours with different seeds...
    assert psnr >= noise_floor - 1.0, (psnr, noise_floor)
    # ... and not on average (a texture off by a seam or a flipped v would shift it).
    mean_theirs, mean_ours = theirs[..., :3][mask].mean(0), rgb[mask].mean(0)
    assert np.allclose(mean_theirs, mean_ours, rtol=0.02), (mean_theirs, mean_ours)


@pytest.mark.skipif(shutil.which("node") is None or not VALIDATOR.is_dir(),
                    reason="the glTF validator is not installed (`make gltf-validator` needs node and npm)")
def test_glb_passes_the_khronos_validator_and_reimports(three_materials, tmp_path):
    import trimesh

    _, run = three_materials
    summary = export_run(run.dir, "gltf", tmp_path, texture_size=256)
    glb = tmp_path / summary["files"][0]
    report = json.loads(subprocess.run(["node", str(ROOT / "tools" / "validate_gltf.js"), str(glb)], check=True,
                                       capture_output=True, text=True).stdout)
    assert report["issues"]["numErrors"] == 0 and report["issues"]["numWarnings"] == 0, report["issues"]["messages"]
    scene = trimesh.load(glb)
    (mesh,) = scene.geometry.values()
    material = mesh.visual.material
    assert material.baseColorTexture.size == (256, 256) and material.metallicRoughnessTexture.size == (256, 256)
    assert material.metallicFactor == 1.0 and material.roughnessFactor == 1.0
    fitted = run.load()
    # Y up: the mesh comes back as the run's, turned into glTF's axes.
    rot = world_to_y_up(fitted.world)
    expect = np.asarray(fitted.mesh.bounds) @ rot.T
    assert np.allclose(np.sort(mesh.bounds, 0), np.sort(expect, 0), atol=1e-5)
    # The metallic-roughness texture carries roughness in G and metallic in B.
    mr = np.asarray(material.metallicRoughnessTexture.convert("RGB"), np.float32) / 255
    baked = bake(fitted, 256)
    cov = baked.coverage
    assert np.abs(mr[..., 1][cov] - baked.roughness[cov]).max() <= 0.5 / 255 + 1e-6
    assert np.abs(mr[..., 2][cov] - baked.metallic[cov]).max() <= 0.5 / 255 + 1e-6


def test_obj_export_reimports_with_its_pbr_material(three_materials, tmp_path):
    import trimesh

    _, run = three_materials
    summary = export_run(run.dir, "obj", tmp_path, texture_size=128)
    obj = tmp_path / summary["files"][0]
    mtl = obj.with_suffix(".mtl").read_text()
    for key in ("map_Kd", "map_Pr", "map_Pm"):
        assert key in mtl
    mesh = trimesh.load(obj, process=False)
    assert len(mesh.faces) == len(run.load().mesh.faces)
    assert mesh.visual.uv.min() >= 0 and mesh.visual.uv.max() <= 1
    assert (tmp_path / "envmap.exr").is_file() and (tmp_path / "envmap.hdr").is_file()


def test_envmap_for_blender_keeps_the_light_direction():
    h, w = 32, 64
    # A lobe towards world direction d in a Mitsuba-world run (its envmap frame the identity).
    d_world = np.array([0.3, 0.8, -0.52])
    d_world /= np.linalg.norm(d_world)
    from vq_mitsuba.data.cameras import BLENDER_ENV_TO_WORLD

    r_b = BLENDER_ENV_TO_WORLD[:3, :3]
    dirs = texel_directions(w, h) @ r_b  # texel directions in the map's own frame = Mitsuba world here
    env = np.exp(40 * (dirs @ d_world - 1))[..., None].repeat(3, -1) + 0.01
    world_to_blender = Y_UP_TO_BLENDER @ world_to_y_up("mitsuba")
    out = envmap_for_blender(env, np.eye(4), world_to_blender)
    row, col = np.unravel_index(np.argmax(out[..., 0]), out.shape[:2])
    d_out = texel_directions(out.shape[1], out.shape[0])[row, col]  # Blender-world direction of the peak
    assert np.degrees(np.arccos(np.clip(d_out @ (world_to_blender @ d_world), -1, 1))) < 4.0
    # A Blender-world run keeps its map (only upsampled).
    same = envmap_for_blender(env, BLENDER_ENV_TO_WORLD, np.eye(3), upsample=1)
    assert np.allclose(same, env, rtol=1e-5, atol=1e-6)


def test_export_command_line(three_materials, tmp_path, capsys):
    _, run = three_materials
    assert cli.main(["export", str(run.dir), "--format", "gltf", "--texture-size", "64", "-o", str(tmp_path / "g"),
                     "--quiet"]) == 0
    assert json.loads((tmp_path / "g" / "export.json").read_text())["texture_size"] == 64
    assert cli.main(["export", str(run.dir), "--format", "gltf", "--texture-size", "4", "-o", str(tmp_path / "bad")]) == 2
    assert "16..8192" in capsys.readouterr().err and not (tmp_path / "bad").exists()


def test_gltf_and_obj_of_a_nerf_capture_lie_in_its_own_world(nerf_run, tmp_path):
    """Imported as Blender's importers read them, the exported vertices are the capture's own
    mesh.ply vertices, and seen from the capture's own test camera the object covers what
    `vq-mitsuba render` of that view covers."""
    import trimesh
    from scipy.spatial import cKDTree

    data, run = nerf_run
    own = trimesh.load(data / "mesh.ply", process=False)
    tree = cKDTree(own.vertices)
    scale = float(np.ptp(own.vertices, 0).max())
    meshes = {}
    for fmt in ("gltf", "obj"):
        summary = export_run(run.dir, fmt, tmp_path / fmt, texture_size=16)
        assert summary["world"] == "blender"
        assert set(summary["files"]) | {"export.json"} <= set(_planned_files(fmt, run.dir.name)), summary["files"]
        loaded = trimesh.load(tmp_path / fmt / summary["files"][0], process=False, force="mesh")
        vertices = _gltf_to_blender(np.asarray(loaded.vertices, np.float64))
        dist, _ = tree.query(vertices)
        assert dist.max() < 1e-5 * scale, (fmt, dist.max())
        assert np.allclose(np.sort(vertices, 0)[[0, -1]], own.bounds, atol=1e-5 * scale)
        meshes[fmt] = trimesh.Trimesh(vertices, np.asarray(loaded.faces), process=False)
    path, camera, _ = _own_test_camera(data)
    assert cli.main(["render", str(run.dir), "--cameras", str(path), "-o", str(tmp_path / "r"), "--spp", "64",
                     "--quiet"]) == 0
    import imageio.v3 as iio

    rendered = iio.imread(tmp_path / "r" / f"{camera.name}_alpha.png").astype(np.float64) / 255
    assert rendered.mean() > 0.05  # the object is in view
    for fmt, mesh in meshes.items():
        assert _soft_iou(_coverage(mesh, camera), rendered) >= 0.98, fmt
    # the test tells a turned export apart: the same mesh a quarter turn about Blender's Z is far off
    turned = meshes["gltf"].copy()
    turned.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [0, 0, 1], own.centroid))
    assert _soft_iou(_coverage(turned, camera), rendered) < 0.9


def test_export_axes_undo_the_loaders_world_conversion():
    """A run held in Mitsuba's world of a capture in Blender's world: the export's axes take a run
    point to where Blender's importer puts the capture's own point."""
    from vq_mitsuba.data.cameras import world_rotation

    rng = np.random.default_rng(1)
    own = rng.normal(size=(20, 3))  # points in the capture's Blender world
    for run_world in ("blender", "mitsuba"):
        in_run = own @ world_rotation("blender", run_world).T  # what the loader made of them
        exported = in_run @ export_axes(run_world, "blender").T
        assert np.allclose(_gltf_to_blender(exported), own), run_world
    # a Mitsuba-world capture is exported as it is, Y up already
    assert np.allclose(export_axes("mitsuba", "mitsuba"), np.eye(3))


def test_export_refuses_to_write_into_a_run_and_leaves_no_empty_folder(nerf_run, tmp_path, capsys):
    data, run = nerf_run
    envmap = next((data / "envmaps").glob("*.exr"))
    learned = (run.dir / "envmap.exr").read_bytes()
    before = sorted(p.name for p in run.dir.iterdir())
    for fmt in ("gltf", "obj", "mitsuba"):
        assert cli.main(["export", str(run.dir), "--format", fmt, "--envmap", str(envmap), "-o", str(run.dir),
                         "--quiet"]) == 2
        err = capsys.readouterr().err
        assert "holds a fitted run" in err and "another -o" in err and str(run.dir) in err, err
    assert (run.dir / "envmap.exr").read_bytes() == learned
    assert sorted(p.name for p in run.dir.iterdir()) == before
    # a refused export leaves no folder behind
    continuous = tmp_path / "continuous"
    assert cli.main(["fit", str(data / "transforms_train.json"), "-o", str(continuous), "--preset", "continuous",
                     *FIT_BRIEFLY]) == 0
    out = tmp_path / "out" / "discrete"
    assert cli.main(["export", str(continuous), "--format", "gltf", "--branch", "discrete", "-o", str(out),
                     "--quiet"]) == 2
    assert "no discrete branch" in capsys.readouterr().err
    assert not out.exists() and not (tmp_path / "out").exists()


CYCLES_PYTHON = ROOT / ".venv-cycles" / "bin" / "python"


@pytest.mark.skipif(not CYCLES_PYTHON.is_file(), reason="Blender (bpy) is not installed: `make cycles`")
def test_glb_renders_in_blender_cycles_like_vq_mitsuba(three_materials, tmp_path):
    """The .glb imported by Blender's own glTF importer, lit by the exported envmap and rendered
    by Cycles, looks like our render: axes, UVs, colour spaces and the envmap's frame survive.
    (Cycles' principled BSDF is not Mitsuba's: a few percent apart, see benchmarks/results/renderer_gap.)"""
    from vq_mitsuba.data.cameras import OPENGL_TO_MITSUBA
    from vq_mitsuba.synthetic.cycles import read_passes

    _, run = three_materials
    fitted = run.load()
    summary = export_run(run.dir, "gltf", tmp_path, texture_size=256)
    cam = run.cameras()["train"][0]
    to_blender = np.eye(4)
    to_blender[:3, :3] = Y_UP_TO_BLENDER @ export_axes(fitted.world, summary["world"])
    job = {"glb": str(tmp_path / summary["files"][0]), "envmap": str(tmp_path / "envmap.exr"),
           "camera": {"name": cam.name, "transform_matrix": (to_blender @ cam.to_world @ OPENGL_TO_MITSUBA).tolist(),
                      "camera_angle_x": float(np.radians(cam.fov_x_deg)), "width": cam.width, "height": cam.height},
           "samples": 256, "max_bounces": fitted.cfg.train.bounces, "output": str(tmp_path / "cycles.exr")}
    (tmp_path / "job.json").write_text(json.dumps(job))
    proc = subprocess.run([str(CYCLES_PYTHON), str(ROOT / "tests" / "blender_glb.py"), str(tmp_path / "job.json")],
                          capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-3000:]
    info = json.loads(proc.stdout.strip().splitlines()[-1])
    assert [256, 256] in info["images"] and {"Base Color", "Metallic", "Roughness"} <= set(info["linked_sockets"])
    cycles = read_passes(tmp_path / "cycles.exr")["Combined"]
    ours = Renderer(fitted).render(cam, spp=256, seed=0)
    assert np.abs(cycles[..., 3] - ours["alpha"]).mean() < 0.02  # same silhouette: axes and camera agree
    mask = ours["alpha"] > 0.5
    rgb = ours.get("rgb_physical", ours["rgb"])  # a run's residual is not exported
    psnr = M.image_metrics(cycles[..., :3], rgb, mask)["psnr"]
    assert psnr > 24.0, psnr
    ratio = cycles[..., :3][mask].mean(0) / rgb[mask].mean(0)
    assert np.all(np.abs(ratio - 1) < 0.12), ratio


@pytest.mark.skipif(not CYCLES_PYTHON.is_file(), reason="Blender (bpy) is not installed: `make cycles`")
def test_glb_of_a_nerf_capture_renders_in_blender_from_the_captures_own_camera(nerf_run, tmp_path):
    """The .glb of a NeRF-capture run, imported by Blender's glTF importer and rendered by Cycles from
    the capture's own test camera (its transforms_test.json matrix, untouched), shows the object
    where `vq-mitsuba render` of that view does, in about the same colours."""
    import imageio.v3 as iio

    from vq_mitsuba.synthetic.cycles import read_passes

    data, run = nerf_run
    summary = export_run(run.dir, "gltf", tmp_path, texture_size=64)
    path, camera, frame = _own_test_camera(data)
    job = {"glb": str(tmp_path / summary["files"][0]), "envmap": str(tmp_path / "envmap.exr"),
           "camera": {"name": camera.name, "transform_matrix": frame["transform_matrix"],
                      "camera_angle_x": json.loads(path.read_text())["camera_angle_x"],
                      "width": camera.width, "height": camera.height},
           "samples": 128, "max_bounces": run.load().cfg.train.bounces, "output": str(tmp_path / "cycles.exr")}
    (tmp_path / "job.json").write_text(json.dumps(job))
    proc = subprocess.run([str(CYCLES_PYTHON), str(ROOT / "tests" / "blender_glb.py"), str(tmp_path / "job.json")],
                          capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-3000:]
    cycles = read_passes(tmp_path / "cycles.exr")["Combined"]
    assert cli.main(["render", str(run.dir), "--cameras", str(path), "-o", str(tmp_path / "r"), "--spp", "128",
                     "--quiet"]) == 0
    alpha = iio.imread(tmp_path / "r" / f"{camera.name}_alpha.png").astype(np.float64) / 255
    assert alpha.mean() > 0.05
    assert _soft_iou(np.clip(cycles[..., 3], 0, 1), alpha) >= 0.98
    shown = Renderer(run.load()).render(camera, spp=128, seed=0)
    ours = shown.get("rgb_physical", shown["rgb"])  # a run's residual, if any, is not exported
    mask = (alpha > 0.99) & (cycles[..., 3] > 0.99)  # inside the silhouette: colour, not coverage
    ratio = cycles[..., :3][mask].mean(0) / ours[mask].mean(0)
    assert np.all(np.abs(ratio - 1) < 0.15), ratio
    assert M.image_metrics(cycles[..., :3], ours, mask)["psnr"] > 20.0

