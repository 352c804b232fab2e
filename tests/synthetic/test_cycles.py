"""`make-scene --renderer cycles`: job file and pass conversion (always), and a tiny Cycles render
checked against the Mitsuba generator (only where .venv-cycles with bpy exists: `make cycles`)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from vq_mitsuba.synthetic import cycles

from vq_mitsuba.synthetic import mitsuba_scenes as synthetic
from vq_mitsuba.data.cameras import camera_to_nerf
from vq_mitsuba.data.imageio import read_exr
from vq_mitsuba.cli import main
from vq_mitsuba.errors import InputError

RES, N_TRAIN, N_TEST, SPP = 32, 1, 2, 64


def _shapes(spec):
    out = []
    for s in spec["shapes"]:
        v, f, n = synthetic.build_shape(s)
        out.append({"name": s["name"], "material": s["material"], "vertices": v, "faces": f, "normals": n})
    return out


def _cams(n_train=2, n_test=1, res=16):
    return synthetic.make_cameras([0.0, 0.0, 0.0], 0.7, n_train, n_test, res, seed=3)


# --------------------------------------------------------------------------------------------
# Pure Python: no bpy needed
# --------------------------------------------------------------------------------------------
def test_job_materials_shapes_and_cameras(tmp_path):
    spec = synthetic.load_scene_spec("texture")
    shapes = _shapes(spec)
    train, test, _ = _cams()
    renders = [{"camera": c.name, "envmap": tmp_path / "e.exr", "output": tmp_path / f"{c.name}.exr"}
               for c in train + test]
    job = json.loads(json.dumps(cycles.build_job(spec, shapes, train + test, renders, spp=32, seed=5)))
    # Material k of the spec has id k + 1, the numbering of the Mitsuba generator's material png.
    assert [m["id"] for m in job["materials"]] == list(range(1, len(spec["materials"]) + 1))
    assert [m["name"] for m in job["materials"]] == [m["name"] for m in spec["materials"]]
    by_name = {m["name"]: m for m in job["materials"]}
    assert by_name["striped"]["vertex_colors"] and by_name["striped"]["base_color"] is None
    assert by_name["steel"]["base_color"] == [0.62, 0.62, 0.64] and by_name["steel"]["metallic"] == 1.0
    # The patterned basecolor is baked per vertex exactly as the Mitsuba generator bakes it.
    sphere = next(s for s in job["shapes"] if s["name"] == "striped_sphere")
    v = np.asarray(sphere["vertices"])
    expected = synthetic.eval_base_color(spec["materials"][0]["base_color"], shapes[0]["vertices"])
    np.testing.assert_allclose(np.asarray(sphere["colors"]), expected, atol=1e-6)
    assert len(np.unique(np.round(expected, 3), axis=0)) > 3  # really varies over the sphere
    np.testing.assert_allclose(v, shapes[0]["vertices"], atol=1e-6)
    assert np.asarray(sphere["faces"]).shape == shapes[0]["faces"].shape
    torus = next(s for s in job["shapes"] if s["name"] == "torus")
    assert torus["colors"] is None
    # Cameras: the NeRF camera-to-world (OpenGL axes, Blender world) of transforms_*.json.
    for cam, jc in zip(train + test, job["cameras"]):
        m, angle = camera_to_nerf(cam)
        np.testing.assert_allclose(jc["transform_matrix"], m)
        assert jc["camera_angle_x"] == pytest.approx(math.radians(synthetic.FOV_X_DEG))
        assert (jc["width"], jc["height"]) == (16, 16)
        # The camera looks along its -Z at the scene centre.
        fwd = -np.asarray(jc["transform_matrix"])[:3, 2]
        to_center = -np.asarray(jc["transform_matrix"])[:3, 3]
        assert np.dot(fwd, to_center / np.linalg.norm(to_center)) > 0.999
    assert job["render"]["samples"] == 32 and job["render"]["seed"] == 5
    assert job["render"]["max_bounces"] == synthetic.MAX_DEPTH - 2 and job["render"]["denoise"] is False
    assert [r["output"] for r in job["renders"]] == [str(r["output"]) for r in renders]


def test_job_rejects_bad_input(tmp_path):
    spec = synthetic.load_scene_spec("demo")
    shapes = _shapes(spec)
    train, test, _ = _cams()
    with pytest.raises(InputError, match="unknown camera"):
        cycles.build_job(spec, shapes, train, [{"camera": "nope", "envmap": "e.exr", "output": "o.exr"}], spp=8)
    bad = [dict(shapes[0], faces=shapes[0]["faces"] + len(shapes[0]["vertices"]))]
    with pytest.raises(InputError, match="out of range"):
        cycles.build_job(spec, bad, train, [], spp=8)
    with pytest.raises(InputError, match="unknown material"):
        cycles.build_job(spec, [dict(shapes[0], material="gold")], train, [], spp=8)


def _passes(alpha, ids, h=2, w=3):
    base = np.zeros((h, w, 4), np.float32)
    base[..., :3] = np.array([0.8, 0.4, 0.2], np.float32) * alpha[..., None]
    normal = np.zeros((h, w, 3), np.float32)
    normal[..., 2] = 0.5 * alpha  # coverage-weighted average of unit normals
    return {"Combined": np.concatenate([np.zeros((h, w, 3), np.float32), alpha[..., None]], -1),
            "Normal": normal, cycles.INDEX_PASS: ids.astype(np.float32), "basecolor": base,
            "metallic": 0.3 * alpha, "roughness": 0.6 * alpha}


def test_gt_maps_divide_by_coverage_and_threshold_ids():
    alpha = np.array([[1.0, 0.6, 0.4], [0.0, 1.0, 0.25]], np.float32)
    ids = np.array([[1, 2, 2], [0, 2, 1]])
    gt = cycles.gt_maps(_passes(alpha, ids), n_materials=2)
    cov = alpha > 0
    np.testing.assert_allclose(gt["basecolor"][cov], np.tile([0.8, 0.4, 0.2], (cov.sum(), 1)), atol=1e-6)
    np.testing.assert_allclose(gt["metallic"][cov], 0.3, atol=1e-6)
    np.testing.assert_allclose(gt["roughness"][cov], 0.6, atol=1e-6)
    assert gt["basecolor"][~cov].max() == 0 and gt["metallic"][~cov].max() == 0
    np.testing.assert_allclose(gt["normal"][cov], np.tile([0, 0, 1.0], (cov.sum(), 1)), atol=1e-6)
    np.testing.assert_array_equal(gt["material"], [[1, 2, 0], [0, 2, 0]])  # coverage < 0.5 -> background
    np.testing.assert_allclose(gt["alpha"], alpha)
    with pytest.raises(InputError, match="ids outside"):
        cycles.gt_maps(_passes(alpha, ids + 5), n_materials=2)
    p = _passes(alpha, ids)
    del p["roughness"]
    with pytest.raises(InputError, match="roughness"):
        cycles.gt_maps(p, n_materials=2)


def test_read_passes_groups_multilayer_channels(tmp_path):
    import OpenEXR

    h, w = 3, 4
    rng = np.random.default_rng(0)
    comb = rng.uniform(size=(h, w, 4)).astype(np.float32)
    nrm = rng.uniform(-1, 1, size=(h, w, 3)).astype(np.float32)
    idx = rng.integers(0, 3, size=(h, w)).astype(np.float32)
    channels = {f"ViewLayer.Combined.{c}": np.ascontiguousarray(comb[..., i]) for i, c in enumerate("RGBA")}
    channels.update({f"ViewLayer.Normal.{c}": np.ascontiguousarray(nrm[..., i]) for i, c in enumerate("XYZ")})
    channels["ViewLayer.Material Index.X"] = idx
    channels["ViewLayer.metallic.V"] = np.ascontiguousarray(comb[..., 0])
    path = tmp_path / "layers.exr"
    with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}, channels) as f:
        f.write(str(path))
    p = cycles.read_passes(path)
    np.testing.assert_array_equal(p["Combined"], comb)  # R, G, B, A order restored
    np.testing.assert_array_equal(p["Normal"], nrm)
    np.testing.assert_array_equal(p[cycles.INDEX_PASS], idx)
    np.testing.assert_array_equal(p["metallic"], comb[..., 0])
    with pytest.raises(InputError, match="missing"):
        cycles.read_passes(tmp_path / "none.exr")


def test_load_probe_clamps_tiny_negatives(tmp_path):
    from vq_mitsuba.data.imageio import write_exr

    img = np.full((4, 8, 3), 0.5, np.float32)
    img[0, 0, 1] = -0.001
    write_exr(tmp_path / "p.exr", img)
    out = cycles.load_probe(tmp_path / "p.exr")
    assert out.min() == 0.0 and out[1, 1, 0] == 0.5
    img[1, 1, 1] = np.inf
    write_exr(tmp_path / "q.exr", img)
    with pytest.raises(InputError, match="non-finite"):
        cycles.load_probe(tmp_path / "q.exr")
    img[1, 1, 1] = -0.5  # clearly negative: refused, not clamped
    write_exr(tmp_path / "r.exr", img)
    with pytest.raises(InputError, match="negative"):
        cycles.load_probe(tmp_path / "r.exr")


def test_missing_environment_is_a_clear_error(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv(cycles.ENV_VAR, str(tmp_path / "no-venv" / "bin" / "python"))
    with pytest.raises(InputError, match="make cycles"):
        cycles.check_environment()
    out = tmp_path / "ds"
    assert main(["make-scene", "demo", "--renderer", "cycles", "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert "make cycles" in err and "no-venv" in err
    assert not out.exists()  # refused before any work
    # An environment without bpy is refused too.
    fake = tmp_path / "venv" / "bin" / "python"
    fake.parent.mkdir(parents=True)
    fake.write_text("")
    monkeypatch.setenv(cycles.ENV_VAR, str(fake))
    with pytest.raises(InputError, match="no bpy"):
        cycles.check_environment()


# --------------------------------------------------------------------------------------------
# A real Cycles render (needs .venv-cycles)
# --------------------------------------------------------------------------------------------
needs_bpy = pytest.mark.skipif(cycles.bpy_dir() is None,
                               reason=f"no bpy in {cycles.cycles_python()} (run `make cycles` to test the Cycles "
                                      "renderer)")


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    if cycles.bpy_dir() is None:
        pytest.skip("no .venv-cycles")
    root = tmp_path_factory.mktemp("cycles")
    cy = cycles.make_scene_cycles("demo", root / "cy", resolution=RES, n_train=N_TRAIN, n_test=N_TEST, spp=SPP)
    mi = synthetic.make_scene("demo", root / "mi", resolution=RES, n_train=N_TRAIN, n_test=N_TEST, spp=SPP)
    return cy, mi


def _names():
    return [f"train_{i:03d}" for i in range(N_TRAIN)] + [f"test_{i:03d}" for i in range(N_TEST)]


def _alpha_png(path):
    import imageio.v3 as iio

    return np.asarray(iio.imread(path)).astype(np.float64) / 255.0


def _interior(mask):
    """mask and its 8 neighbours: drops pixels that mix two materials."""
    m = np.pad(mask, 1)
    out = np.ones_like(mask)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            out &= m[1 + dy:1 + dy + mask.shape[0], 1 + dx:1 + dx + mask.shape[1]]
    return out


@pytest.mark.slow  # over 10 s: CI runs it after the default suite (.ci/run)
@needs_bpy
def test_layout_matches_the_mitsuba_generator(rendered):
    cy, mi = rendered
    meta = json.loads((cy / "scene.json").read_text())
    assert meta["renderer"] == "cycles" and meta["resolution"] == [RES, RES]
    relit = [r["name"] for r in meta["relight"]]
    probes = sorted(cycles.blender_probes())
    assert len(probes) == 8 and relit == ["sunset", "studio"] + [f"blender_{p}" for p in probes]
    test_names = _names()[N_TRAIN:]
    expected = ["transforms_train.json", "transforms_test.json", "mesh.ply", "scene.xml", "scene_test.xml",
                "envmaps/train.exr", "meshes/sphere.ply", "meshes/torus.ply"]
    expected += [f"envmaps/{r}.exr" for r in relit]
    expected += [f"images/{n}.{ext}" for n in _names() for ext in ("exr", "png")]
    for n in test_names:
        expected += [f"gt/{n}_{k}.exr" for k in ("basecolor", "metallic", "roughness", "normal")]
        expected += [f"gt/{n}_material.png", f"gt/{n}_alpha.png"]
        expected += [f"relit/{r}/{n}.{ext}" for r in relit for ext in ("exr", "png")]
    assert not [p for p in expected if not (cy / p).is_file()]
    assert not (cy / cycles.WORK_DIR).exists()
    # Every file of the Mitsuba generator's dataset has its Cycles counterpart, cameras identical.
    mi_files = {str(p.relative_to(mi)) for p in mi.rglob("*") if p.is_file()}
    assert not [p for p in mi_files if not (cy / p).is_file()]
    for split in ("train", "test"):
        a = json.loads((cy / f"transforms_{split}.json").read_text())
        b = json.loads((mi / f"transforms_{split}.json").read_text())
        assert a == b
    assert (cy / "scene.xml").read_text() == (mi / "scene.xml").read_text()


@pytest.mark.slow  # over 10 s: CI runs it after the default suite (.ci/run)
@needs_bpy
def test_alpha_and_material_ids_agree_with_mitsuba(rendered):
    cy, mi = rendered
    for n in _names()[N_TRAIN:]:
        a, b = _alpha_png(cy / f"gt/{n}_alpha.png") > 0.5, _alpha_png(mi / f"gt/{n}_alpha.png") > 0.5
        iou = (a & b).sum() / (a | b).sum()
        assert iou > 0.95, (n, iou)
        assert 0.1 < a.mean() < 0.9  # the objects are in frame, not filling it
        import imageio.v3 as iio

        ids_c, ids_m = iio.imread(cy / f"gt/{n}_material.png"), iio.imread(mi / f"gt/{n}_material.png")
        assert set(np.unique(ids_c)) == {0, 1, 2}
        assert (ids_c == ids_m).mean() > 0.95
    for n in _names():  # the image alpha is the coverage too
        a, b = read_exr(cy / f"images/{n}.exr")[..., 3] > 0.5, read_exr(mi / f"images/{n}.exr")[..., 3] > 0.5
        assert (a & b).sum() / (a | b).sum() > 0.95


@pytest.mark.slow  # over 10 s: CI runs it after the default suite (.ci/run)
@needs_bpy
def test_aov_maps_equal_the_scene_materials(rendered):
    import imageio.v3 as iio

    cy, _ = rendered
    spec = synthetic.load_scene_spec("demo")
    for n in _names()[N_TRAIN:]:
        ids = np.asarray(iio.imread(cy / f"gt/{n}_material.png"))
        inside = _alpha_png(cy / f"gt/{n}_alpha.png") > 0.999
        base = read_exr(cy / f"gt/{n}_basecolor.exr")
        metal = read_exr(cy / f"gt/{n}_metallic.exr")[..., 0]
        rough = read_exr(cy / f"gt/{n}_roughness.exr")[..., 0]
        normal = read_exr(cy / f"gt/{n}_normal.exr")
        for k, m in enumerate(spec["materials"], start=1):
            sel = inside & _interior(ids == k)  # away from the silhouette and the sphere/torus boundary
            assert sel.sum() >= 3
            np.testing.assert_allclose(base[sel], np.tile(m["base_color"], (sel.sum(), 1)), atol=2e-3)
            np.testing.assert_allclose(metal[sel], m["metallic"], atol=2e-3)
            np.testing.assert_allclose(rough[sel], m["roughness"], atol=2e-3)
        np.testing.assert_allclose(np.linalg.norm(normal[inside], axis=-1), 1.0, atol=1e-3)


@pytest.mark.slow  # over 10 s: CI runs it after the default suite (.ci/run)
@needs_bpy
def test_normals_agree_with_mitsuba(rendered):
    cy, mi = rendered
    for n in _names()[N_TRAIN:]:
        inside = (_alpha_png(cy / f"gt/{n}_alpha.png") > 0.999) & (_alpha_png(mi / f"gt/{n}_alpha.png") > 0.999)
        a, b = read_exr(cy / f"gt/{n}_normal.exr")[inside], read_exr(mi / f"gt/{n}_normal.exr")[inside]
        cos = np.clip(np.sum(a * b, -1), -1, 1)
        assert np.degrees(np.arccos(cos)).mean() < 2.0


# Mitsuba's principled BSDF is not Cycles' (Burley vs Lambert diffuse under energy-conserving
# layering, Schlick vs F82 metals), so the images differ by a few per cent: measured on the demo
# at 32x32 / 64 spp, per-channel mean-colour ratios Cycles / Mitsuba were 0.91-1.00 and per-pixel
# luminance correlations >= 0.966. A wrongly oriented envmap gives ratios 0.36-2.6 and
# correlations below 0 (mirrored u, 90 or 180 deg about Z, flipped v all checked).
MEAN_TOL = 0.15
MIN_CORR = 0.9


@pytest.mark.slow  # over 10 s: CI runs it after the default suite (.ci/run)
@needs_bpy
def test_images_match_mitsuba_renders_of_the_same_views(rendered):
    cy, mi = rendered
    stems = [f"images/{n}" for n in _names()] + [f"relit/{e}/{n}" for e in ("sunset", "studio")
                                                  for n in _names()[N_TRAIN:]]
    for stem in stems:
        a, b = read_exr(cy / f"{stem}.exr"), read_exr(mi / f"{stem}.exr")
        both = (a[..., 3] > 0.999) & (b[..., 3] > 0.999)
        ratio = a[..., :3][both].mean(0) / b[..., :3][both].mean(0)
        assert np.all(np.abs(ratio - 1.0) < MEAN_TOL), (stem, ratio)
        corr = np.corrcoef(a[..., :3][both].mean(-1), b[..., :3][both].mean(-1))[0, 1]
        assert corr > MIN_CORR, (stem, corr)
        assert np.all(a[..., :3][a[..., 3] == 0] == 0)  # transparent film: premultiplied black background


@pytest.mark.slow  # over 10 s: CI runs it after the default suite (.ci/run)
@needs_bpy
def test_capture_loads_for_fit(rendered):
    from vq_mitsuba.data.captures import load_capture

    cy, _ = rendered
    for path in (cy / "transforms_train.json", cy / "scene.xml"):
        cap = load_capture(path)
        assert cap.images.shape == (N_TRAIN, RES, RES, 3) and cap.mesh is not None and cap.has_alpha


@pytest.mark.slow  # over 10 s: CI runs it after the default suite (.ci/run)
@needs_bpy
def test_patterned_basecolor_matches_the_mitsuba_generator(tmp_path):
    """The texture scene's striped basecolor (baked per vertex) reaches Cycles' shading and AOV:
    the AOV equals the Mitsuba generator's map inside the striped object (it once came out black)."""
    from vq_mitsuba.data.imageio import read_image

    kw = dict(resolution=24, n_train=1, n_test=1, spp=4)
    cy = cycles.make_scene_cycles("texture", tmp_path / "cy", **kw)
    mi = synthetic.make_scene("texture", tmp_path / "mi", **kw)
    bc_cy, _ = read_image(cy / "gt" / "test_000_basecolor.exr")
    bc_mi, _ = read_image(mi / "gt" / "test_000_basecolor.exr")
    import imageio.v3 as iio

    ids = np.asarray(iio.imread(mi / "gt" / "test_000_material.png"))
    striped = _interior(ids == 1)  # material 1 of synthetic/scenes/texture.yaml: the striped sphere
    assert striped.sum() > 20
    assert bc_cy[striped].max() > 0.5  # not black
    diff = np.abs(bc_cy[striped] - bc_mi[striped]).max(-1)  # stripe edges mix colours within a pixel
    assert diff.mean() < 0.05 and np.mean(diff < 0.1) > 0.9
