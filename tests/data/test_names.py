"""Names from a capture (vq_mitsuba.data.names): file-safe and unique whatever the capture says,
outputs written by them stay in their folder, exported XML holds them escaped; and the capture
loaders' silent misreadings (COLMAP text without POINTS2D lines, frames listed twice, CMYK JPEGs)
that now read right or are refused naming the line or frame."""

import json
import re
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from test_photo_captures import _refused
from vq_mitsuba.data.cameras import Camera, camera_to_nerf, look_at
from vq_mitsuba.data.imageio import write_png
from vq_mitsuba.data.names import MAX_NAME_LENGTH, safe_name, unique_names, view_names
from vq_mitsuba.errors import InputError

SAFE = re.compile(r"[A-Za-z0-9_-][A-Za-z0-9._-]*")


def _cameras(n=3, width=20, height=14):
    out = []
    for i in range(n):
        a = 2 * np.pi * i / n
        eye = 2.5 * np.array([np.sin(a), 0.5, np.cos(a)])
        out.append(Camera(f"v{i}", look_at(eye, [0, 0, 0], [0, 1, 0]), 42.0, width, height))
    return out


def _as_png(linear) -> np.ndarray:
    """Linear values as write_png stores them and read_image gives them back (8-bit sRGB)."""
    from vq_mitsuba.data.imageio import linear_to_srgb, srgb_to_linear

    return srgb_to_linear(np.round(linear_to_srgb(np.asarray(linear, np.float32)) * 255) / 255)


def _files_under(folder: Path) -> set[Path]:
    return {p for p in folder.rglob("*") if p.is_file()}


# --------------------------------------------------------------------------------------------
# The sanitiser

@pytest.mark.parametrize("raw, name", [
    ("r_0", "r_0"), ("view_01.a", "view_01.a"), ("../../../escaped_view", "escaped_view"),
    ("/tmp/abs/view", "tmp_abs_view"), ("a/000", "a_000"), ("a\\000", "a_000"), (".hidden", "hidden"),
    ("a..b", "a_b"), ('a"<&>b c', "a____b_c"), ("..", "view"), ("", "view"), ("./", "view"),
    ("vue_été", "vue__t_"),
])
def test_a_name_becomes_a_file_name(raw, name):
    assert safe_name(raw) == name


@settings(max_examples=200, deadline=None)
@given(st.lists(st.text(max_size=300) | st.sampled_from(["a", "A", "a_2", "../a", "a/", ".a", "a/000", "b/000"]),
                max_size=12))
def test_view_names_are_file_names_inside_their_folder_and_unique(raws):
    names = view_names(raws)
    assert len(names) == len(raws)
    assert len({n.casefold() for n in names}) == len(names)  # unique, also where case is ignored
    out = Path("/out/dir")
    for name in names:
        assert SAFE.fullmatch(name) and ".." not in name and 0 < len(name) <= MAX_NAME_LENGTH, name
        assert (out / f"{name}_rgb.exr").parent == out
    assert view_names(names) == names  # names already safe and unique stay as they are


def test_the_first_of_a_name_keeps_it_and_suffixes_avoid_the_names_taken():
    assert unique_names(["a", "A", "a_2", "a"]) == ["a", "A_3", "a_2", "a_4"]
    assert view_names(["a/000", "b/000", "000"]) == ["a_000", "b_000", "000"]
    long = "x" * (MAX_NAME_LENGTH + 20)
    assert view_names([long, long]) == ["x" * MAX_NAME_LENGTH, "x" * (MAX_NAME_LENGTH - 2) + "_2"]


# --------------------------------------------------------------------------------------------
# Scene XML sensor ids: named safely, and render writes inside -o

def _sensor_xml(sid: str, cam: Camera) -> str:
    from xml.sax.saxutils import quoteattr

    m = " ".join(f"{x:.9g}" for x in cam.to_world.ravel())
    return (f'  <sensor type="perspective" id={quoteattr(sid)}><float name="fov" value="{cam.fov_x_deg}"/>'
            f'<transform name="to_world"><matrix value="{m}"/></transform>'
            f'<film type="hdrfilm"><integer name="width" value="{cam.width}"/>'
            f'<integer name="height" value="{cam.height}"/></film></sensor>')


def _hostile_xml(folder: Path, ids: list[str], images: bool = False) -> Path:
    cams = _cameras(len(ids))
    folder.mkdir(parents=True, exist_ok=True)
    xml = folder / "scene.xml"
    xml.write_text('<scene version="3.0.0">\n' + "\n".join(_sensor_xml(s, c) for s, c in zip(ids, cams))
                   + "\n</scene>\n")
    if images:  # the capture's own files are found by its own ids
        for k, sid in enumerate(ids):
            write_png(folder / "images" / f"{sid}.png", np.full((14, 20, 3), 0.2 + 0.3 * k))
    return xml


def test_sensor_ids_with_separators_become_safe_view_names(tmp_path):
    from vq_mitsuba.data.captures import load_cameras, load_capture

    ids = ["../../../escaped_view", str(tmp_path / "abs" / "abs_view"), "view"]
    xml = _hostile_xml(tmp_path / "deep" / "cap", ids)
    cameras, _, _ = load_cameras(xml)
    assert [c.name for c in cameras] == ["escaped_view", view_names([ids[1]])[0], "view"]
    # the images are still found under the capture's own ids: images/<id>.png
    xml = _hostile_xml(tmp_path / "imgs" / "cap", ["a b", "a_b", "c&d"], images=True)
    capture = load_capture(xml)
    assert [c.name for c in capture.cameras] == ["a_b", "a_b_2", "c_d"]
    assert np.allclose(capture.images[:, 0, 0, 0], _as_png([0.2, 0.5, 0.8]), atol=1e-6)


def test_render_writes_every_view_inside_its_output_folder(tmp_path, three_materials):
    from vq_mitsuba.cli import main

    _, run = three_materials
    ids = ["../../../escaped_view", str(tmp_path / "abs" / "abs_view")]
    xml = _hostile_xml(tmp_path / "a" / "b" / "cap", ids)
    (tmp_path / "abs").mkdir()
    out = tmp_path / "a" / "b" / "cap" / "out"
    before = _files_under(tmp_path)
    assert main(["render", str(run.dir), "--cameras", str(xml), "-o", str(out), "--spp", "2", "--quiet"]) == 0
    written = _files_under(tmp_path) - before
    assert written and all(out in p.parents for p in written), sorted(written)
    assert (out / "escaped_view_rgb.exr").is_file()
    assert not list((tmp_path / "abs").iterdir())


def test_render_views_keeps_any_callers_names_inside_the_folder(tmp_path, monkeypatch):
    """render_views itself never joins a name with separators to its folder."""
    from vq_mitsuba.render import views

    class Flat:
        def __init__(self, *args, **kwargs):
            pass

        def render(self, camera, spp=None, relight=()):
            h, w = camera.height, camera.width
            return {"rgb": np.zeros((h, w, 3), np.float32), "alpha": np.ones((h, w), np.float32),
                    "basecolor": np.zeros((h, w, 3), np.float32), "metallic": np.zeros((h, w), np.float32),
                    "roughness": np.zeros((h, w), np.float32), "normal": np.zeros((h, w, 3), np.float32),
                    "relit": [np.zeros((h, w, 3), np.float32) for _ in relight]}

    class Fitted:
        world = "mitsuba"

    monkeypatch.setattr(views, "Renderer", Flat)
    cams = [Camera(n, c.to_world, 42.0, 8, 6) for n, c in zip(["../up", "/abs/x", "../up"], _cameras(3))]
    out = tmp_path / "x" / "out"
    views.render_views(Fitted(), cams, "mitsuba", out)
    assert all(out in p.parents for p in _files_under(tmp_path))
    assert {p.name for p in out.glob("*_rgb.exr")} == {"up_rgb.exr", "abs_x_rgb.exr", "up_2_rgb.exr"}
    with pytest.raises(InputError, match="cannot name a folder"):
        views.render_views(Fitted(), cams, "mitsuba", out, more_envmaps=[("..", None)])


# --------------------------------------------------------------------------------------------
# COLMAP names from subfolders, and the held-out split

def _colmap(folder: Path, names: list[str], binary: bool = True, points2d: bool = True):
    from vq_mitsuba.data.formats.colmap import write_colmap

    cams = _cameras(len(names))
    model = folder / "sparse" / "0"
    write_colmap(model, cams, names, binary=binary)
    for k, name in enumerate(names):
        write_png(folder / "images" / name, np.full((14, 20, 3), (k + 1) / (len(names) + 1)))
    if not binary and not points2d:  # the image lines alone, one after the other
        text = (model / "images.txt").read_text()
        (model / "images.txt").write_text(text.replace("\n\n", "\n"))
    return model


@pytest.mark.parametrize("binary", [True, False])
def test_colmap_images_of_one_file_name_in_two_folders_keep_apart(tmp_path, binary):
    from vq_mitsuba.config import CaptureConfig
    from vq_mitsuba.data.captures import load_cameras, load_capture

    names = ["a/000.png", "b/000.png", "a/001.png", "b/001.png"]
    _colmap(tmp_path, names, binary)
    capture = load_capture(tmp_path)
    assert [c.name for c in capture.cameras] == ["a_000", "a_001", "b_000", "b_001"]  # COLMAP's order: by name
    order = sorted(range(4), key=lambda k: names[k])  # each view its own photo
    assert np.allclose(capture.images[:, 3, 3, 1], _as_png([(k + 1) / 5 for k in order]), atol=1e-6)
    # the held-out views have the same names whichever loader asks for them
    options = CaptureConfig(holdout=2)
    held = load_capture(tmp_path, options=options, split="holdout")
    cams, _, _ = load_cameras(tmp_path, options, split="holdout")
    train = load_capture(tmp_path, options=options, split="train")
    assert [c.name for c in held.cameras] == [c.name for c in cams] == ["a_001", "b_001"]
    assert [c.name for c in train.cameras] == ["a_000", "b_000"]


# --------------------------------------------------------------------------------------------
# COLMAP images.txt without its POINTS2D lines

def test_colmap_text_without_points2d_lines_is_refused_naming_the_line(tmp_path):
    from vq_mitsuba.data.captures import load_capture

    names = [f"{k:03d}.png" for k in range(6)]
    model = _colmap(tmp_path, names, binary=False, points2d=False)
    _refused(lambda: load_capture(tmp_path), model / "images.txt", "line 3 is an image line where the POINTS2D "
             "line of image 1 belongs")


def test_colmap_text_with_points2d_lines_reads_every_image(tmp_path):
    """POINTS2D lines with points, some at whole pixels (they look like numbers of an image line)."""
    from vq_mitsuba.data.captures import load_capture

    names = [f"{k:03d}.png" for k in range(6)]
    model = _colmap(tmp_path, names, binary=False)
    lines = (model / "images.txt").read_text().split("\n")
    points = ["", "12 7 -1 3 4 2 5.5 6.25 -1 8 9 1", "1.5 2.5 -1"]
    out, k = [], 0
    for line in lines:
        if line and not line.startswith("#"):
            out += [line, points[k % 3]]
            k += 1
    (model / "images.txt").write_text("\n".join(out) + "\n")
    capture = load_capture(tmp_path)
    assert [c.name for c in capture.cameras] == [f"{k:03d}" for k in range(6)]
    # a POINTS2D line that is neither points nor an image is named too
    (model / "images.txt").write_text("\n".join(out[:1] + ["12 7 x"] + out[2:]) + "\n")
    _refused(lambda: load_capture(tmp_path), model / "images.txt", "line 2 ('12 7 x') is not the POINTS2D line")


# --------------------------------------------------------------------------------------------
# Frames listed twice in a transforms json

def _nerf_json(folder: Path, file_paths: list[str], images: list[str]) -> Path:
    cams = _cameras(len(file_paths))
    for k, name in enumerate(images):
        write_png(folder / name, np.full((14, 20, 3), 0.5))
    frames = [{"file_path": p, "transform_matrix": camera_to_nerf(c)[0].tolist()} for p, c in zip(file_paths, cams)]
    path = folder / "transforms_train.json"
    path.write_text(json.dumps({"camera_angle_x": 0.7, "frames": frames}))
    return path


def test_a_frame_listed_twice_in_a_nerf_json_is_refused_naming_both(tmp_path):
    from vq_mitsuba.data.captures import load_cameras, load_capture

    path = _nerf_json(tmp_path, ["./images/r_0", "images/r_1", "images/x/../r_0.png"],
                      ["images/r_0.png", "images/r_1.png"])
    for call in (lambda: load_capture(path), lambda: load_cameras(path)):
        _refused(call, path, "frames[2] (images/x/../r_0.png) lists the image of frames[0] (./images/r_0) again")


def test_frames_of_one_file_name_in_two_folders_are_named_by_their_paths(tmp_path):
    from vq_mitsuba.data.captures import load_capture

    path = _nerf_json(tmp_path, ["./train/r_0", "./test/r_0", "./train/r_1"],
                      ["train/r_0.png", "test/r_0.png", "train/r_1.png"])
    assert [c.name for c in load_capture(path).cameras] == ["train_r_0", "test_r_0", "train_r_1"]
    path = _nerf_json(tmp_path / "plain", ["./images/r_0", "./images/r_1"], ["images/r_0.png", "images/r_1.png"])
    assert [c.name for c in load_capture(path).cameras] == ["r_0", "r_1"]


def test_a_frame_listed_twice_in_a_nerfstudio_json_is_refused(tmp_path):
    from vq_mitsuba.data.captures import load_capture
    from vq_mitsuba.data.formats.nerfstudio import write_transforms_json
    from vq_mitsuba.data.lens import Lens

    cams = _cameras(3)
    lenses = [Lens("PINHOLE", 20, 14, *c.intrinsics()) for c in cams]
    for name in ("a", "b"):
        write_png(tmp_path / "images" / f"{name}.png", np.full((14, 20, 3), 0.5))
    path = tmp_path / "transforms.json"
    write_transforms_json(path, cams, ["images/a.png", "images/b.png", "./images/a.png"], lenses)
    _refused(lambda: load_capture(path), path, "frames[2] (./images/a.png) lists the image of frames[0]",
             "each image may appear once")


# --------------------------------------------------------------------------------------------
# CMYK JPEGs

def test_a_cmyk_jpeg_is_read_as_its_rgb_without_alpha(tmp_path):
    from PIL import Image

    from vq_mitsuba.data.imageio import read_image, srgb_to_linear

    rng = np.random.default_rng(0)
    cmyk = rng.integers(0, 256, (16, 24, 4), dtype=np.uint8)
    cmyk[..., 3] = np.linspace(0, 255, 24).astype(np.uint8)[None]  # K varies: read as alpha it would be a mask
    path = tmp_path / "cmyk.jpg"
    Image.fromarray(cmyk, "CMYK").save(path, quality=95)
    with Image.open(path) as im:
        assert im.mode == "CMYK"
        expected = srgb_to_linear(np.asarray(im.convert("RGB"), np.float32) / 255)
    rgb, alpha = read_image(path)
    assert alpha is None and np.array_equal(rgb, expected)
    half, alpha = read_image(path, 2)  # decoded at half size by the JPEG decoder
    assert alpha is None and half.shape == (8, 12, 3)
    # in a capture: no mask, every pixel opaque
    from vq_mitsuba.data.captures import load_capture

    (tmp_path / "cap" / "images").mkdir(parents=True)
    Image.fromarray(cmyk[:14, :20], "CMYK").save(tmp_path / "cap" / "images" / "c.jpg", quality=95)
    capture = load_capture(_nerf_json(tmp_path / "cap", ["./images/c.jpg"], []))
    assert not capture.has_alpha and np.all(capture.alpha == 1)


# --------------------------------------------------------------------------------------------
# mesh.ply: known geometry in the folder of every capture but a scene XML

def test_mesh_ply_counts_beside_every_capture_but_a_scene_xml(tmp_path):
    import trimesh

    from vq_mitsuba.data.captures import load_capture, open_capture

    def capture_has_geometry(path):
        return open_capture(path).has_geometry()

    box = trimesh.creation.box()
    colmap = tmp_path / "colmap"
    _colmap(colmap, ["a.png", "b.png", "c.png"])
    nerf = _nerf_json(tmp_path / "nerf", ["./images/a", "./images/b"], ["images/a.png", "images/b.png"])
    xml = _hostile_xml(tmp_path / "xml", ["a", "b"], images=True)
    for capture in (colmap, nerf, xml):
        folder = capture if capture.is_dir() else capture.parent
        assert load_capture(capture).mesh is None and not capture_has_geometry(capture)
        box.export(folder / "mesh.ply")
        with_mesh = load_capture(capture).mesh
        assert (with_mesh is not None) == (capture is not xml) == capture_has_geometry(capture)


# --------------------------------------------------------------------------------------------
# Mitsuba export: every attribute escaped

def test_exported_scene_xml_is_well_formed_and_holds_the_names(tmp_path):
    from vq_mitsuba.export.bake import BakedMesh
    from vq_mitsuba.export.mitsuba_scene import write_mitsuba

    names = ['a"b', "c<d>&e", "it's", 'a"b']  # the last twice: a train and a test view may share a name
    cams = [Camera(n, c.to_world, 42.0, 20, 14) for n, c in zip(names, _cameras(4))]
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
    tex = np.full((4, 4), 0.5, np.float32)
    baked = BakedMesh(v, np.array([[0, 1, 2]]), np.tile([[0, 0, 1]], (3, 1)).astype(np.float32), v[:, :2],
                      np.full((4, 4, 3), 0.5, np.float32), tex, tex, None, np.ones((4, 4), bool))
    out = tmp_path / "out"
    out.mkdir()
    write_mitsuba(out, baked, np.ones((8, 16, 3), np.float32), np.eye(4), cams, spp=4, max_depth=2,
                  name='ob"j&<x>')
    root = ET.parse(out / "scene.xml").getroot()
    assert [s.get("id") for s in root.iter("sensor")] == ['a"b', "c<d>&e", "it's", 'a"b_2']
    shape = root.find("shape")
    assert shape.get("id") == 'ob"j&<x>' and shape.find("string").get("value") == 'ob"j&<x>.ply'
