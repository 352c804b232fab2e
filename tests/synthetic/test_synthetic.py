"""Bundled synthetic scenes: files, both capture formats describing the same views, GT maps."""

from __future__ import annotations

import json
import math
import xml.etree.ElementTree as ET

import numpy as np
import pytest

from vq_mitsuba.synthetic import mitsuba_scenes as synthetic
from vq_mitsuba.data.cameras import BLENDER_ENV_TO_WORLD, Camera, nerf_to_camera
from vq_mitsuba.data.imageio import read_exr, read_image
from vq_mitsuba.errors import InputError

RES, N_TRAIN, N_TEST = 32, 4, 2
R = BLENDER_ENV_TO_WORLD[:3, :3]


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    out = tmp_path_factory.mktemp("demo")
    synthetic.make_scene("demo", out, resolution=RES, n_train=N_TRAIN, n_test=N_TEST, spp=16)
    return out


@pytest.fixture(scope="module")
def mi(demo):
    import mitsuba

    return mitsuba


def test_bundled_scenes_listed():
    assert {"demo", "texture", "balls", "polished", "tabletop", "sunlit"} <= set(synthetic.SCENES)
    for name in synthetic.SCENES:
        spec = synthetic.load_scene_spec(name)
        assert spec["materials"] and spec["shapes"]
    with pytest.raises(InputError, match="unknown synthetic scene"):
        synthetic.load_scene_spec("no_such_scene")


def test_writes_all_files(demo):
    names = [f"train_{i:03d}" for i in range(N_TRAIN)] + [f"test_{i:03d}" for i in range(N_TEST)]
    expected = ["transforms_train.json", "transforms_test.json", "mesh.ply", "scene.xml", "scene_test.xml",
                "scene.json", "envmaps/train.exr", "envmaps/sunset.exr", "envmaps/studio.exr",
                "meshes/sphere.ply", "meshes/torus.ply"]
    expected += [f"images/{n}.{ext}" for n in names for ext in ("exr", "png")]
    for n in names[N_TRAIN:]:
        expected += [f"gt/{n}_{k}.exr" for k in ("basecolor", "metallic", "roughness", "normal")]
        expected += [f"gt/{n}_material.png", f"gt/{n}_alpha.png"]
        expected += [f"relit/{env}/{n}.{ext}" for env in ("sunset", "studio") for ext in ("exr", "png")]
    missing = [p for p in expected if not (demo / p).is_file()]
    assert not missing
    rgb, alpha = read_image(demo / "images/train_000.exr")
    assert rgb.shape == (RES, RES, 3) and alpha is not None and rgb.max() > 0.05
    meta = json.loads((demo / "scene.json").read_text())
    assert meta["name"] == "demo" and meta["resolution"] == [RES, RES]
    assert [m["id"] for m in meta["materials"]] == [1, 2]
    assert {r["name"] for r in meta["relight"]} >= {"sunset", "studio"}


def test_xmls_load_without_emitter(demo, mi):
    for fname, count in (("scene.xml", N_TRAIN), ("scene_test.xml", N_TEST)):
        scene = mi.load_file(str(demo / fname))
        assert len(scene.sensors()) == count
        assert len(scene.shapes()) == 2
        assert not scene.emitters()
        assert list(scene.sensors()[0].film().size()) == [RES, RES]


def _xml_cameras(path):
    cams = []
    for s in ET.parse(path).getroot().iter("sensor"):
        m = np.array([float(x) for x in s.find("transform/matrix").get("value").split()]).reshape(4, 4)
        fov = float(next(f.get("value") for f in s.iter("float") if f.get("name") == "fov"))
        axis = next(f.get("value") for f in s.iter("string") if f.get("name") == "fov_axis")
        film = {i.get("name"): int(i.get("value")) for i in s.find("film").iter("integer")}
        assert axis == "x"
        cams.append(Camera(s.get("id"), m, fov, film["width"], film["height"]))
    return cams


@pytest.mark.parametrize("split", ["train", "test"])
def test_json_and_xml_describe_the_same_views(demo, split):
    data = json.loads((demo / f"transforms_{split}.json").read_text())
    xml_cams = _xml_cameras(demo / ("scene.xml" if split == "train" else "scene_test.xml"))
    assert [f["file_path"] for f in data["frames"]] == [f"./images/{c.name}" for c in xml_cams]
    rng = np.random.default_rng(0)
    pts_b = rng.uniform(-0.5, 0.5, size=(50, 3))  # Blender world
    for frame, cam_x in zip(data["frames"], xml_cams):
        cam_j = nerf_to_camera(cam_x.name, frame["transform_matrix"], data["camera_angle_x"], RES, RES)
        assert cam_x.fov_x_deg == pytest.approx(math.degrees(data["camera_angle_x"]))
        np.testing.assert_allclose(cam_x.project(pts_b @ R), cam_j.project(pts_b), atol=1e-4)


def test_meshes_agree_between_worlds(demo, mi):
    import trimesh

    merged = trimesh.load(demo / "mesh.ply", process=False)
    parts = [np.array(mi.traverse(s)["vertex_positions"]).reshape(-1, 3)
             for s in mi.load_file(str(demo / "scene.xml")).shapes()]
    mi_world = np.concatenate(parts)
    assert len(mi_world) == len(merged.vertices)
    # Same point sets: Mitsuba-world vertices mapped by R are the Blender-world ones.
    np.testing.assert_allclose(np.sort((mi_world @ R.T).sum(1)), np.sort(np.asarray(merged.vertices).sum(1)),
                               atol=1e-5)


def test_gt_maps(demo):
    ids = set()
    for i in range(N_TEST):
        import imageio.v3 as iio

        mat = iio.imread(demo / f"gt/test_{i:03d}_material.png")
        alpha = iio.imread(demo / f"gt/test_{i:03d}_alpha.png")
        assert mat.shape == (RES, RES) and mat.dtype == np.uint8
        ids |= set(np.unique(mat).tolist())
        for a in (alpha, (read_image(demo / f"images/test_{i:03d}.exr")[1] * 255).round()):
            assert a[0, 0] == 0 and a[0, -1] == 0 and a[-1, 0] == 0 and a[-1, -1] == 0
            assert a[RES // 2, RES // 2] == 255
        assert np.all((mat > 0) == (alpha >= 128)) or np.mean((mat > 0) != (alpha >= 128)) < 0.02
        normal = read_exr(demo / f"gt/test_{i:03d}_normal.exr")
        norms = np.linalg.norm(normal[mat > 0], axis=-1)
        np.testing.assert_allclose(norms, 1.0, atol=1e-3)
        metallic = read_exr(demo / f"gt/test_{i:03d}_metallic.exr")[..., 0]
        rough = read_exr(demo / f"gt/test_{i:03d}_roughness.exr")[..., 0]
        base = read_exr(demo / f"gt/test_{i:03d}_basecolor.exr")
        # Pixels of material 1 (away from the other material's silhouette) carry its exact values.
        full = (alpha == 255) & (mat == 1)
        exact = ((np.abs(metallic - 0.0) < 1e-6) & (np.abs(rough - 0.8) < 1e-6)
                 & np.all(np.abs(base - np.array([0.8, 0.32, 0.07])) < 1e-6, -1))
        assert full.sum() > 10 and exact[full].mean() > 0.85
        full2 = (alpha == 255) & (mat == 2)
        if full2.any():
            assert np.median(metallic[full2]) == pytest.approx(0.8) and np.median(rough[full2]) == pytest.approx(0.3)
    assert ids == {0, 1, 2}


def test_gt_normals_face_the_camera(demo):
    import imageio.v3 as iio

    data = json.loads((demo / "transforms_test.json").read_text())
    cam = nerf_to_camera("test_000", data["frames"][0]["transform_matrix"], data["camera_angle_x"], RES, RES)
    normal = read_exr(demo / "gt/test_000_normal.exr")
    mat = iio.imread(demo / "gt/test_000_material.png")
    forward = cam.to_world[:3, 2]  # Mitsuba camera looks along +Z
    assert np.mean(normal[mat > 0] @ forward < 0.05) > 0.95


def _lit(mi, demo, env_path):
    # Beside scene.xml: an <include>d file's relative paths resolve from the including file.
    wrapper = demo / f"_lit_{env_path.stem}.xml"
    wrapper.write_text(f"""<scene version="3.0.0">
    <include filename="scene.xml"/>
    <integrator type="path"><integer name="max_depth" value="4"/>
        <boolean name="hide_emitters" value="true"/></integrator>
    <emitter type="envmap"><string name="filename" value="{env_path}"/></emitter>
</scene>""")
    try:
        return mi.load_file(str(wrapper))
    finally:
        wrapper.unlink()


def _blocks(img, b=8):
    h, w = img.shape[:2]
    return img.reshape(h // b, b, w // b, b, 3).mean((1, 3))


def test_identity_envmap_in_mitsuba_world_relights_the_same(demo, mi, tmp_path):
    """scene.xml + the train EXR with identity to_world renders what images/ holds (Blender world + R)."""
    from vq_mitsuba.data import envmaps

    env = envmaps.load_envmap(demo / "envmaps" / "train.exr")
    envmaps.save_envmap(tmp_path / "rotated.exr", envmaps.rotate_z(env, 180.0))
    same = _lit(mi, demo, demo / "envmaps" / "train.exr")
    rotated = _lit(mi, demo, tmp_path / "rotated.exr")
    diff, total = np.zeros(2), 0.0
    for k in range(N_TRAIN):
        ref, ref_alpha = read_image(demo / f"images/train_{k:03d}.exr")  # 16 spp: compare 8x8 blocks
        ref_b = _blocks(ref)
        total += ref_b.sum()
        for j, scene in enumerate((same, rotated)):
            img = np.array(mi.render(scene, sensor=k, spp=256, seed=7))
            np.testing.assert_allclose(img[..., 3], ref_alpha, atol=0.25)
            diff[j] += np.abs(_blocks(img[..., :3]) - ref_b).sum()
    err_same, err_rotated = diff / total
    assert err_same < 0.08, (err_same, err_rotated)
    assert err_rotated > 3 * err_same, (err_same, err_rotated)


def test_box_faces_are_flat_outward_and_closed():
    import trimesh

    v, f, n = synthetic.build_shape({"name": "b", "type": "box", "extents": [0.6, 0.4, 0.1], "max_edge": 0.05,
                                     "center": [0.1, 0.0, -0.05]})
    mesh = trimesh.Trimesh(v, f, process=False)
    assert np.allclose(v.min(0), [-0.2, -0.2, -0.1]) and np.allclose(v.max(0), [0.4, 0.2, 0.0])
    assert np.allclose(mesh.face_normals, n[f[:, 0]])  # vertex normals are the flat face normals
    centre = v.mean(0)
    assert ((mesh.triangles_center - centre) * mesh.face_normals).sum(1).min() > 0  # outward
    assert mesh.edges_unique_length.max() <= 0.05 * math.sqrt(2) + 1e-9  # fine enough for a pattern
    merged = trimesh.Trimesh(v, f)  # vertices merged: a closed surface of the box's volume
    assert merged.is_watertight and merged.volume == pytest.approx(0.6 * 0.4 * 0.1, rel=1e-6)


@pytest.mark.parametrize("pattern", ["waves", "noise"])
def test_patterns_blend_their_colours_and_vary(pattern):
    colors = [[0.1, 0.2, 0.3], [0.8, 0.6, 0.4]]
    pts = np.random.default_rng(0).uniform(-0.5, 0.5, (4000, 3))
    spec = {"pattern": pattern, "frequency": 8.0, "softness": 0.3, "colors": colors}
    c = synthetic.eval_base_color(spec, pts)
    lo, hi = np.min(colors, 0), np.max(colors, 0)
    assert (c >= lo - 1e-9).all() and (c <= hi + 1e-9).all()
    t = (c[:, 0] - 0.1) / 0.7  # the blend weight: both colours occur, and everything between
    assert t.min() < 0.1 and t.max() > 0.9 and ((t > 0.2) & (t < 0.8)).mean() > 0.05
    assert np.array_equal(c, synthetic.eval_base_color(spec, pts))  # deterministic: both renderers agree


def test_shapes_sharing_a_material_keep_their_ground_truth(tmp_path):
    """tabletop's aluminium rod and studs share one BSDF (which Mitsuba would merge into one shape
    without an id): every material appears in the material maps of its test views."""
    synthetic.make_scene("tabletop", tmp_path, resolution=64, n_train=1, n_test=3, spp=4)
    import imageio.v3 as iio

    ids = set()
    for k in range(3):
        ids |= set(np.unique(iio.imread(tmp_path / "gt" / f"test_{k:03d}_material.png")).tolist())
    assert ids == {0, 1, 2, 3, 4, 5}
