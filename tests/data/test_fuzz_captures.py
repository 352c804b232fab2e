"""Fuzz of the capture loaders (Hypothesis): malformed json and XML, odd image sizes, bit depths and
channel layouts, mutated COLMAP text and binary models and NeuS/IDR archives. A capture either
loads with finite images in [0, 1]-ish ranges and finite cameras, or is refused with an InputError
naming a file; no other exception (no traceback) ever reaches the user."""

import copy
import json
import os
import re

import numpy as np
import pytest
from hypothesis import event, given
from hypothesis import strategies as st
from hypothesis.extra.numpy import array_shapes, arrays

from fuzzing import files_under, fuzz, python_text
from vq_mitsuba.data.captures import load_capture
from vq_mitsuba.errors import InputError

FUZZ = fuzz(60)  # benchmarks/stress.py raises the number of examples through VQM_FUZZ_EXAMPLES
FUZZ_FILES = fuzz(150)  # whole files changed: a few milliseconds an example

json_values = st.recursive(
    st.none() | st.booleans() | st.integers(-5, 5) | st.sampled_from([10 ** 400, -10 ** 400, 2 ** 63, -2 ** 64])
    | st.floats(allow_nan=True, allow_infinity=True)
    | st.text(max_size=8),
    lambda children: st.lists(children, max_size=5) | st.dictionaries(st.text(max_size=6), children, max_size=4),
    max_leaves=20)

good_matrix = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 3], [0, 0, 0, 1]]


frames = st.lists(st.fixed_dictionaries({
    "file_path": st.sampled_from(["./img", "img", "", "missing", "../img", "img.png"]) | st.text(max_size=5),
    "transform_matrix": st.sampled_from([good_matrix]) | json_values,
}) | json_values, max_size=3)

captures = st.fixed_dictionaries({
    "camera_angle_x": st.sampled_from([0.7, 0.0, -1.0, 4.0, float("nan")]) | json_values,
    "frames": frames | json_values,
}) | json_values


def _tally(outcome: str) -> str:
    """Count one example's outcome: a Hypothesis event, and a line "TEST OUTCOME" in the file
    $VQM_FUZZ_TALLY when set (benchmarks/stress.py counts them)."""
    event(outcome)
    if os.environ.get("VQM_FUZZ_TALLY"):
        test = os.environ.get("PYTEST_CURRENT_TEST", "?").split("::")[-1].split(" ")[0]
        with open(os.environ["VQM_FUZZ_TALLY"], "a") as f:
            f.write(f"{test} {outcome}\n")
    return outcome


def _load(load, *args, **kwargs):
    """`load(*args)`, or None when refused with an InputError; any other exception is tallied and raised."""
    try:
        return load(*args, **kwargs)
    except InputError as exc:
        assert exc.path is not None and exc.message and not python_text(exc.message), exc
        _tally("refused")
        return None
    except Exception:
        _tally("traceback")
        raise


def _check(folder):
    cap = _load(load_capture, folder / "transforms_train.json")
    if cap is None:
        return "refused"
    finite = bool(np.isfinite(cap.images).all() and np.isfinite(cap.alpha).all())
    _tally("loaded" if finite else "nonfinite")
    assert finite
    assert cap.images.min() >= 0 and 0 <= cap.alpha.min() and cap.alpha.max() <= 1
    return "loaded"


@pytest.fixture
def folder(tmp_path_factory):
    return tmp_path_factory.mktemp("fuzz")


@FUZZ
@given(data=captures)
def test_malformed_transforms_json_is_refused_by_name(folder, data):
    import imageio.v3 as iio

    iio.imwrite(folder / "img.png", np.full((4, 4, 4), 200, np.uint8))
    text = json.dumps(data, allow_nan=True)
    (folder / "transforms_train.json").write_text(text)
    _check(folder)


@FUZZ
@given(raw=st.binary(max_size=64), suffix=st.sampled_from([".json", ".xml"]))
def test_random_bytes_as_a_capture_file_are_refused(folder, raw, suffix):
    path = folder / f"capture{suffix}"
    path.write_bytes(raw)
    assert _load(load_capture, path) is None


@FUZZ
@given(height=st.integers(1, 6), width=st.integers(1, 6), channels=st.sampled_from([1, 2, 3, 4]),
       depth=st.sampled_from(["uint8", "uint16", "exr"]), second_size=st.booleans())
def test_image_layouts_load_or_are_refused(folder, height, width, channels, depth, second_size):
    """Two frames of the given layout (the second of another size when asked)."""
    import mitsuba as mi

    from vq_mitsuba.backend import init_mitsuba
    from vq_mitsuba.data.imageio import write_exr

    init_mitsuba()
    rng = np.random.default_rng(height * 100 + width * 10 + channels)
    frames_json = []
    for i in range(2):
        h, w = (height + 1, width) if (second_size and i == 1) else (height, width)
        name = f"f{i}"
        if depth == "exr":
            img = rng.random((h, w, max(3, channels))).astype(np.float32)
            write_exr(folder / f"{name}.exr", img)
        else:
            top = 255 if depth == "uint8" else 65535
            img = rng.integers(0, top + 1, (h, w, channels)).astype(depth)
            fmt = {1: mi.Bitmap.PixelFormat.Y, 2: mi.Bitmap.PixelFormat.YA, 3: mi.Bitmap.PixelFormat.RGB,
                   4: mi.Bitmap.PixelFormat.RGBA}[channels]
            mi.Bitmap(img, pixel_format=fmt).write(str(folder / f"{name}.png"))
            (folder / f"{name}.exr").unlink(missing_ok=True)
        moved = [[1, 0, 0, 0.1 * i], *good_matrix[1:]]  # two viewpoints: one pose twice is refused
        frames_json.append({"file_path": f"./{name}", "transform_matrix": moved})
    (folder / "transforms_train.json").write_text(json.dumps({"camera_angle_x": 0.7, "frames": frames_json}))
    outcome = _check(folder)
    assert outcome == ("refused" if second_size else "loaded")


# --------------------------------------------------------------------------------------------
# Photographed captures: COLMAP (text and binary) and NeuS/IDR, three 8x6 views


PHOTO_W, PHOTO_H = 8, 6
SPECIAL = [float("nan"), float("inf"), float("-inf"), 0.0, -0.0, -1.0, 1e-300, 1e300, 50.0, -50.0, 2.0 ** 63]


def _photo_cameras():
    from vq_mitsuba.data.cameras import Camera, look_at

    return [Camera(f"v{i}", look_at([3 * np.sin(i), 0.5, 3 * np.cos(i)], [0, 0, 0], [0, 1, 0]), 50.0, PHOTO_W, PHOTO_H)
            for i in range(3)]


def _photos(folder, sub, names):
    from vq_mitsuba.data.imageio import write_png

    for name in names:
        if not (folder / sub / name).is_file():
            write_png(folder / sub / name, np.full((PHOTO_H, PHOTO_W, 3), 0.4), alpha=np.ones((PHOTO_H, PHOTO_W)))


def _check_photo(folder):
    """Loads with finite cameras and images, or is refused with an InputError naming a file."""
    cap = _load(load_capture, folder, cache_dir=folder / "undistorted")
    if cap is None:
        return "refused"
    values = [cap.images, cap.alpha] + [np.r_[c.to_world.ravel(), c.intrinsics(), c.fov_x_deg] for c in cap.cameras]
    finite = all(np.isfinite(v).all() for v in values)
    _tally("loaded" if finite else "nonfinite")
    assert finite
    for cam in cap.cameras:
        fx, fy, _, _ = cam.intrinsics()
        assert fx > 0 and fy > 0 and 0 < cam.fov_x_deg < 180
    return "loaded"


def _colmap_base(folder, binary):
    """A valid model: camera 1 OPENCV (mild distortion), cameras 2 and 3 PINHOLE."""
    from vq_mitsuba.data.formats.colmap import write_colmap
    from vq_mitsuba.data.lens import Lens

    def lens_of(cam):
        fx, fy, cx, cy = cam.intrinsics()
        if cam.name == "v0":
            return Lens("OPENCV", cam.width, cam.height, fx, fy, cx, cy, -0.05, 0.01, 0.001, -0.001)
        return Lens("PINHOLE", cam.width, cam.height, fx, fy, cx, cy)

    names = ["a.png", "b.png", "c.png"]
    _photos(folder, "images", names)
    model = folder / "sparse" / "0"
    for old in model.glob("*"):
        old.unlink()
    write_colmap(model, _photo_cameras(), names, lens_of=lens_of, binary=binary)
    return model


tokens = (st.sampled_from(["nan", "inf", "-inf", "0", "-1", "1e300", "1e-300", "50", "-0", "", "x", "OPENCV",
                           "PINHOLE", "FULL_OPENCV", "1", "3", "99", "4294967296", "a.png", "../a.png",
                           "<delete line>", "<repeat line>"])
          | st.text(max_size=4) | st.floats().map(repr) | st.integers().map(str))
text_edits = st.lists(st.tuples(st.sampled_from(["cameras.txt", "images.txt"]), st.integers(0, 12),
                                st.integers(0, 14), tokens), min_size=1, max_size=4)


@FUZZ
@given(edits=text_edits)
def test_mutated_colmap_text_models_load_or_are_refused(folder, edits):
    model = _colmap_base(folder, binary=False)
    for name, line, token, value in edits:
        lines = (model / name).read_text().split("\n")
        i = line % len(lines)
        if value in ("<delete line>", "<repeat line>"):
            lines[i:i + 1] = [] if value == "<delete line>" else [lines[i]] * 2
        else:
            parts = lines[i].split(" ")
            parts[token % len(parts):token % len(parts) + 1] = [value]
            lines[i] = " ".join(parts)
        (model / name).write_text("\n".join(lines))
    _check_photo(folder)


binary_edits = st.lists(st.tuples(
    st.sampled_from(["cameras.bin", "images.bin"]),
    st.sampled_from(["double", "int32", "uint64", "bytes", "truncate", "append"]),
    st.integers(0, 200),
    st.sampled_from(SPECIAL) | st.floats(),
    st.binary(min_size=1, max_size=12)), min_size=1, max_size=4)


@FUZZ
@given(edits=binary_edits)
def test_mutated_colmap_binary_models_load_or_are_refused(folder, edits):
    import struct

    model = _colmap_base(folder, binary=True)
    for name, kind, pos, number, raw in edits:
        data = bytearray((model / name).read_bytes())
        pos = pos % (len(data) + 1)
        if kind == "truncate":
            data = data[:pos]
        elif kind == "append":
            data += raw
        elif kind == "bytes":
            data[pos:pos + len(raw)] = raw
        else:
            fmt = {"double": "<d", "int32": "<i", "uint64": "<Q"}[kind]
            value = number if kind == "double" else (int(number) if np.isfinite(number) else -1)
            limit = 2 ** 31 if kind == "int32" else 2 ** 64
            value = value if kind == "double" else value % limit - (limit // 2 if kind == "int32" else 0)
            data[pos:pos + struct.calcsize(fmt)] = struct.pack(fmt, value)
        (model / name).write_bytes(bytes(data))
    _check_photo(folder)


numeric_arrays = arrays(dtype=st.sampled_from([np.float64, np.float32, np.int64, np.bool_, np.complex128, "<U3"]),
                        shape=array_shapes(min_dims=0, max_dims=3, max_side=5))
entry_values = st.one_of(
    st.none(),  # the entry removed
    numeric_arrays,
    st.just("object"),
    st.tuples(st.integers(0, 3), st.integers(0, 3), st.sampled_from(SPECIAL) | st.floats()),  # one entry changed
    st.sampled_from(SPECIAL).map(lambda f: ("scaled", f)),
)
archive_edits = st.lists(st.tuples(st.sampled_from(["world_mat_0", "world_mat_1", "world_mat_2", "scale_mat_0",
                                                    "scale_mat_2", "camera_mat_0"]), entry_values),
                         min_size=1, max_size=4)


def _edited(base, value):
    if value is None or isinstance(value, np.ndarray):
        return value
    if isinstance(value, str):
        return np.array([np.eye(4), "x"], dtype=object)
    usable = isinstance(base, np.ndarray) and base.shape == (4, 4) and base.dtype.kind in "biuf"
    m = np.array(base if usable else np.eye(4), np.float64)
    if value[0] == "scaled":
        with np.errstate(all="ignore"):
            return m * value[1]
    i, j, number = value
    m[i, j] = number
    return m


@FUZZ
@given(edits=archive_edits, garbage=st.one_of(st.none(), st.binary(max_size=40)))
def test_mutated_neus_archives_load_or_are_refused(folder, edits, garbage):
    from vq_mitsuba.data.formats.idr import write_idr

    _photos(folder, "image", ["000.png", "001.png", "002.png"])
    npz = folder / "cameras_sphere.npz"
    write_idr(npz, _photo_cameras(), np.zeros(3), 1.5)
    entries = dict(np.load(npz))
    for key, value in edits:
        entries[key] = _edited(entries.get(key), value)
    np.savez(npz, **{k: v for k, v in entries.items() if v is not None})
    if garbage is not None:  # a damaged archive
        npz.write_bytes(npz.read_bytes()[:len(garbage) * 20] + garbage)
    _check_photo(folder)


def test_an_archive_member_that_unpacks_to_far_more_than_a_matrix_is_refused_unread(folder):
    """A 130 KB cameras_sphere.npz whose world_mat_0 unpacks to 128 MB (numpy unpacks a member whole
    before its shape can be checked): refused naming the file and the member, with nothing of that
    size allocated."""
    import tracemalloc

    _photos(folder, "image", ["000.png", "001.png", "002.png"])
    matrices = {f"world_mat_{i}": np.eye(4) for i in range(3)}
    np.savez_compressed(folder / "cameras_sphere.npz", **{**matrices, "world_mat_0": np.zeros(1 << 24)})
    assert (folder / "cameras_sphere.npz").stat().st_size < 1 << 20
    tracemalloc.start()
    try:
        with pytest.raises(InputError, match="world_mat_0 unpacks to 134217856 bytes") as refused:
            load_capture(folder)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert refused.value.path == folder / "cameras_sphere.npz" and peak < 16 << 20


# nerfstudio transforms.json: any value for any intrinsic key, at the top level or per frame
ns_keys = st.sampled_from(["fl_x", "fl_y", "cx", "cy", "w", "h", "k1", "k2", "k3", "k4", "p1", "p2",
                           "camera_model", "camera_angle_x", "mask_path", "applied_transform"])
ns_values = st.sampled_from([30.0, 0.0, -1.0, 1e12, float("nan"), 24, 16, "OPENCV", "OPENCV_FISHEYE", "PINHOLE",
                             "FOV", "image.png", 0.05, [[1, 0, 0, 0]]]) | json_values


@FUZZ
@given(top=st.dictionaries(ns_keys, ns_values, max_size=5),
       per_frame=st.lists(st.dictionaries(ns_keys, ns_values, max_size=3), min_size=3, max_size=3))
def test_mutated_nerfstudio_json_loads_or_is_refused(folder, top, per_frame):
    from vq_mitsuba.data.cameras import camera_to_nerf

    _photos(folder, "images", ["000.png", "001.png", "002.png"])
    frames = [{"file_path": f"images/{i:03d}.png", "transform_matrix": camera_to_nerf(c)[0].tolist(), **extra}
              for i, (c, extra) in enumerate(zip(_photo_cameras(), per_frame))]
    data = {"camera_model": "OPENCV", "fl_x": 20.0, "fl_y": 20.0, "cx": PHOTO_W / 2, "cy": PHOTO_H / 2, **top,
            "frames": frames}
    (folder / "transforms.json").write_text(json.dumps(data, allow_nan=True))
    _check_photo(folder)


@FUZZ
@given(shape=st.just((3, 17)) | st.tuples(st.integers(0, 4), st.integers(14, 18)),
       edits=st.lists(st.tuples(st.integers(0, 2), st.integers(0, 16),
                                st.floats(allow_nan=True, allow_infinity=True)), max_size=3))
def test_mutated_llff_poses_load_or_are_refused(folder, shape, edits):
    from vq_mitsuba.data.formats.llff import write_poses_bounds

    _photos(folder, "images", ["000.png", "001.png", "002.png"])
    npy = folder / "poses_bounds.npy"
    write_poses_bounds(npy, _photo_cameras(), [(0.5, 6.0)] * 3)
    rows = np.load(npy)
    for i, j, value in edits:
        rows[i, j] = value
    n, m = shape
    out = np.zeros((n, m))
    out[:min(n, 3), :min(m, 17)] = rows[:min(n, 3), :min(m, 17)]
    np.save(npy, out if (n, m) != (3, 17) else rows)
    _check_photo(folder)


# --------------------------------------------------------------------------------------------
# Mitsuba scene XML: any attribute value, element or byte of a valid scene changed

XML_SCENE = """<?xml version="1.0" encoding="utf-8"?>
<scene version="3.0.0">
    <default name="spp" value="4"/>
    <sensor type="perspective" id="a">
        <float name="fov" value="40"/>
        <transform name="to_world"><lookat origin="0, 0, 4" target="0, 0, 0" up="0, 1, 0"/></transform>
        <sampler type="independent"><integer name="sample_count" value="$spp"/></sampler>
        <film type="hdrfilm"><integer name="width" value="8"/><integer name="height" value="6"/></film>
    </sensor>
    <sensor type="perspective" id="b">
        <float name="fov" value="40"/>
        <transform name="to_world"><lookat origin="3, 0, 3" target="0, 0, 0" up="0, 1, 0"/></transform>
        <sampler type="independent"><integer name="sample_count" value="$spp"/></sampler>
        <film type="hdrfilm"><integer name="width" value="8"/><integer name="height" value="6"/></film>
    </sensor>
    <shape type="sphere" id="ball"><float name="radius" value="0.5"/></shape>
    <emitter type="envmap"><string name="filename" value="env.exr"/><float name="scale" value="1"/></emitter>
</scene>
"""

xml_tokens = (st.sampled_from(["nan", "inf", "-inf", "-1", "0", "1e300", "1e-300", "99999999999", "4294967297",
                               "-2147483649", "", " ", "x", "1, 2", "../../a", "/dev/zero", "images", "env.exr",
                               "$spp", "$nothere", "$", "perspective", "thinlens", "orthographic", "envmap", "point",
                               "sphere", "ply", "rectangle", "a", "b", "ball", "hdrfilm", "specfilm"])
              | st.text(max_size=6) | st.floats().map(repr) | st.integers().map(str))
xml_edits = st.lists(st.one_of(
    st.tuples(st.just("attr"), st.integers(0, 60), xml_tokens),
    st.tuples(st.just("drop"), st.integers(0, 30)),
    st.tuples(st.just("copy"), st.integers(0, 30)),
    st.tuples(st.just("tag"), st.integers(0, 30), st.sampled_from(["sensor", "shape", "emitter", "film", "float",
                                                                   "integer", "string", "ref", "bsdf", "include"])),
), min_size=1, max_size=4)
xml_bytes = st.one_of(st.none(), st.tuples(st.just("truncate"), st.integers(0, 1500)),
                      st.tuples(st.just("bytes"), st.integers(0, 1500), st.binary(min_size=1, max_size=6)),
                      st.tuples(st.just("entities"), st.integers(1, 9)))


def _xml_edited(edits) -> str:
    import xml.etree.ElementTree as ET

    root = ET.fromstring(XML_SCENE)
    for edit in edits:
        parents = {child: parent for parent in root.iter() for child in parent}
        elements = [e for e in root.iter() if e is not root]
        if edit[0] == "attr":
            pairs = [(e, name) for e in root.iter() for name in sorted(e.attrib)]
            element, name = pairs[edit[1] % len(pairs)]
            element.set(name, edit[2])
        elif elements:
            element = elements[edit[1] % len(elements)]
            parent = parents[element]
            if edit[0] == "drop":
                parent.remove(element)
            elif edit[0] == "copy":
                parent.insert(list(parent).index(element), ET.fromstring(ET.tostring(element)))
            else:
                element.tag = edit[2]
    return ET.tostring(root, encoding="unicode")


def _xml_bytes(text: str, change) -> bytes:
    data = text.encode()
    if change is None:
        return data
    if change[0] == "truncate":
        return data[:change[1] % (len(data) + 1)]
    if change[0] == "bytes":
        pos = change[1] % (len(data) + 1)
        return data[:pos] + change[2] + data[pos + len(change[2]):]
    # nested entities ("billion laughs"), the deepest one in a sensor's id
    depth = change[1]
    entities = "".join(f'<!ENTITY e{i} "{("&e%d;" % (i - 1)) * 10 if i else "lol"}">' for i in range(depth + 1))
    return (f"<!DOCTYPE scene [{entities}]>\n" + text.replace('id="a"', f'id="&e{depth};"')).encode()


@pytest.fixture(scope="module")
def xml_folder(tmp_path_factory):
    """A scene's folder without its XML: images/a.png, images/b.png and env.exr."""
    from vq_mitsuba.data.imageio import write_exr

    folder = tmp_path_factory.mktemp("xml_scene")
    _photos(folder, "images", ["a.png", "b.png"])
    write_exr(folder / "env.exr", np.full((4, 8, 3), 0.5, np.float32))
    return folder


def test_the_fuzzed_xml_scene_loads_as_written(xml_folder):
    (xml_folder / "scene.xml").write_text(XML_SCENE)
    cap = load_capture(xml_folder / "scene.xml")
    assert [c.name for c in cap.cameras] == ["a", "b"] and cap.mesh is not None and cap.envmap is not None


@FUZZ_FILES
@given(edits=xml_edits, change=xml_bytes)
def test_mutated_xml_scenes_load_or_are_refused(xml_folder, edits, change):
    xml = xml_folder / "scene.xml"
    xml.write_bytes(_xml_bytes(_xml_edited(edits), change))
    before = files_under(xml_folder)
    cap = _load(load_capture, xml)
    assert files_under(xml_folder) == before  # reading a capture writes nothing
    if cap is not None:
        values = [cap.images, cap.alpha] + [np.r_[c.to_world.ravel(), c.intrinsics()] for c in cap.cameras]
        assert all(np.isfinite(v).all() for v in values)
        assert cap.envmap is None or np.isfinite(cap.envmap).all()
        _tally("loaded")


# --------------------------------------------------------------------------------------------
# Every file of a valid capture of each format damaged: truncated, its first bytes (the magic)
# changed, grown, emptied, or replaced by another file of the capture


def _nerf_synthetic(folder):
    from vq_mitsuba.data.cameras import camera_to_nerf

    _photos(folder, "train", ["r_0.png", "r_1.png", "r_2.png"])
    frames = [{"file_path": f"./train/r_{i}", "transform_matrix": camera_to_nerf(c)[0].tolist()}
              for i, c in enumerate(_photo_cameras())]
    (folder / "transforms_train.json").write_text(json.dumps({"camera_angle_x": 0.8, "frames": frames}, indent=1))
    return folder / "transforms_train.json"


def _nerfstudio(folder):
    from vq_mitsuba.data.cameras import camera_to_nerf

    _photos(folder, "images", ["000.png", "001.png", "002.png"])
    _photos(folder, "masks", ["000.png", "001.png", "002.png"])
    frames = [{"file_path": f"images/{i:03d}.png", "mask_path": f"masks/{i:03d}.png",
               "transform_matrix": camera_to_nerf(c)[0].tolist()} for i, c in enumerate(_photo_cameras())]
    data = {"camera_model": "OPENCV", "fl_x": 20.0, "fl_y": 20.0, "cx": PHOTO_W / 2, "cy": PHOTO_H / 2,
            "w": PHOTO_W, "h": PHOTO_H, "k1": 0.01, "frames": frames}
    (folder / "transforms.json").write_text(json.dumps(data, indent=1))
    return folder / "transforms.json"


def _xml(folder):
    from vq_mitsuba.data.imageio import write_exr

    _photos(folder, "images", ["a.png", "b.png"])
    write_exr(folder / "env.exr", np.full((4, 8, 3), 0.5, np.float32))
    (folder / "scene.xml").write_text(XML_SCENE)
    return folder / "scene.xml"


def _idr(folder):
    from vq_mitsuba.data.formats.idr import write_idr

    _photos(folder, "image", ["000.png", "001.png", "002.png"])
    _photos(folder, "mask", ["000.png", "001.png", "002.png"])
    write_idr(folder / "cameras_sphere.npz", _photo_cameras(), np.zeros(3), 1.5)
    return folder / "cameras_sphere.npz"


def _llff(folder):
    from vq_mitsuba.data.formats.llff import write_poses_bounds

    _photos(folder, "images", ["000.png", "001.png", "002.png"])
    write_poses_bounds(folder / "poses_bounds.npy", _photo_cameras(), [(0.5, 6.0)] * 3)
    return folder / "poses_bounds.npy"


def _colmap(binary):
    def write(folder):
        _colmap_base(folder, binary)
        _photos(folder, "masks", ["a.png.png", "b.png.png", "c.png.png"])
        return folder
    return write


CAPTURES = {"nerf_synthetic": _nerf_synthetic, "nerfstudio": _nerfstudio, "xml": _xml, "idr": _idr, "llff": _llff,
            "colmap_bin": _colmap(True), "colmap_txt": _colmap(False)}


@pytest.fixture(scope="module")
def valid_captures(tmp_path_factory):
    """Each format's valid capture (its folder, the path given to the loader), checked to load."""
    out = {}
    for kind, write in CAPTURES.items():
        folder = tmp_path_factory.mktemp(kind)
        out[kind] = folder, write(folder)
        assert load_capture(out[kind][1], cache_dir=tmp_path_factory.mktemp("cache")).cameras
    return out


file_damage = st.one_of(
    st.tuples(st.just("truncate"), st.floats(0, 1)),
    st.tuples(st.just("magic"), st.binary(min_size=1, max_size=8)),
    st.tuples(st.just("append"), st.binary(min_size=1, max_size=64)),
    st.tuples(st.just("bytes"), st.floats(0, 1), st.binary(min_size=1, max_size=8)),
    st.tuples(st.just("empty")),
    st.tuples(st.just("swap"), st.integers(0, 40)),
    st.tuples(st.just("size"), st.sampled_from([0, 1, 7, 9, 65535, 2 ** 31 - 1, 2 ** 32 - 1]),
              st.sampled_from([0, 1, 5, 65535, 2 ** 31 - 1, 2 ** 32 - 1])),  # a PNG's header size
    st.tuples(st.just("nest"), st.sampled_from([b"[", b'{"a": ', b"<a>", b"<shape>"])),  # nested 50000 deep
)


def _damaged(data: bytes, damage, files) -> bytes:
    import struct
    import zlib

    kind = damage[0]
    if kind == "truncate":
        return data[:int(damage[1] * len(data))]
    if kind == "magic":
        return damage[1] + data[len(damage[1]):]
    if kind == "append":
        return data + damage[1]
    if kind == "bytes":
        pos = int(damage[1] * len(data))
        return data[:pos] + damage[2] + data[pos + len(damage[2]):]
    if kind == "empty":
        return b""
    if kind == "swap":
        return files[damage[1] % len(files)].read_bytes()
    if kind == "nest":
        return (b'<scene version="3.0.0">' if damage[1] == b"<shape>" else b"") + damage[1] * 50000
    if data[12:16] != b"IHDR":  # "size" changes only a PNG
        return data
    ihdr = struct.pack(">II", damage[1], damage[2]) + data[24:29]
    return data[:16] + ihdr + struct.pack(">I", zlib.crc32(b"IHDR" + ihdr) & 0xFFFFFFFF) + data[33:]


@FUZZ_FILES
@given(kind=st.sampled_from(sorted(CAPTURES)), image=st.booleans(), which=st.integers(0, 40), damage=file_damage)
def test_damaged_capture_files_are_refused_by_name(valid_captures, tmp_path_factory, kind, image, which, damage):
    """Half the examples damage the file of cameras (the json, XML, archive or model), half an image,
    mask or envmap."""
    import shutil

    base, given_path = valid_captures[kind]
    folder = tmp_path_factory.mktemp("damaged")
    shutil.copytree(base, folder, dirs_exist_ok=True)
    files = sorted(p for p in folder.rglob("*") if p.is_file())
    chosen = [p for p in files if (p.suffix in (".png", ".exr")) == image]
    target = chosen[which % len(chosen)]
    target.write_bytes(_damaged(target.read_bytes(), damage, files))
    before = files_under(folder)
    cap = _load(load_capture, folder / given_path.relative_to(base), cache_dir=folder / "undistorted")
    assert files_under(folder) - before <= {"undistorted"} | {p for p in files_under(folder) if
                                                                p.startswith("undistorted/")}
    if cap is not None:
        values = [cap.images, cap.alpha] + [np.r_[c.to_world.ravel(), c.intrinsics()] for c in cap.cameras]
        assert all(np.isfinite(v).all() for v in values)
        _tally("loaded")


# Transforms jsons (NeRF-synthetic and nerfstudio): any value of a valid one replaced, a key given twice

json_leaves = st.sampled_from([10 ** 400, -10 ** 400, 2 ** 64, -1, 0, 1e308, -1e308, 1e-300, float("nan"),
                               float("inf"), None, True, "", "x", "../../x", [], {}, [1, 2], [[1e400] * 4] * 4])


def _leaves(data, out=None):
    """Every (container, key) of a json value whose value is not a container itself."""
    out = [] if out is None else out
    for key in (range(len(data)) if isinstance(data, list) else sorted(data)):
        if isinstance(data[key], (list, dict)) and data[key]:
            _leaves(data[key], out)
        else:
            out.append((data, key))
    return out


def _objects(data, out=None):
    """Every json object (dict) in `data`, outermost first."""
    out = [] if out is None else out
    if isinstance(data, dict):
        out.append(data)
    for value in (data.values() if isinstance(data, dict) else data if isinstance(data, list) else []):
        _objects(value, out)
    return out


@FUZZ_FILES
@given(kind=st.sampled_from(["nerf_synthetic", "nerfstudio"]),
       edits=st.lists(st.tuples(st.integers(0, 300), json_leaves, st.booleans()), max_size=3),
       twice=st.none() | st.integers(0, 300))
def test_transforms_jsons_with_any_value_changed_load_or_are_refused(valid_captures, tmp_path_factory, kind, edits,
                                                                      twice):
    import shutil

    base, given_path = valid_captures[kind]
    folder = tmp_path_factory.mktemp("json")
    shutil.copytree(base, folder, dirs_exist_ok=True)
    path = folder / given_path.name
    data = json.loads(path.read_text())
    for which, value, named in edits:  # named: a value under a key (not one of a matrix's numbers)
        leaves = [(c, k) for c, k in _leaves(data) if isinstance(c, dict) or not named]
        container, key = leaves[which % len(leaves)]
        container[key] = copy.deepcopy(value)  # never the strategy's own list, edited by the next example
    objects = [o for o in _objects(data) if o]
    if twice is not None and objects:  # one key of one object given twice (the first value, then another)
        obj = objects[twice % len(objects)]
        key = sorted(obj)[twice % len(obj)]
        obj["__twice__"] = 0.5
        text = json.dumps(data, allow_nan=True).replace('"__twice__"', json.dumps(key))
    else:
        text = json.dumps(data, allow_nan=True)
    path.write_text(text)
    if _check_photo(folder) == "loaded":
        assert twice is None  # a key given twice is refused: which value would be meant?


@pytest.mark.parametrize("text, words", [
    ('{"camera_angle_x": 0.7, "frames": [{"file_path": "img", "transform_matrix": '
     '[[1, 0, 0, 1%s], [0, 1, 0, 0], [0, 0, 1, 3], [0, 0, 0, 1]]}]}' % ("0" * 400),
     "frames[0] (img): malformed transform_matrix"),
    ('{"camera_angle_x": 0.7, "camera_angle_x": 0.9, "frames": []}', "'camera_angle_x' is given twice"),
])
def test_json_values_beyond_a_float_and_keys_given_twice_are_refused(tmp_path, text, words):
    """Found by the json fuzz: an integer too large for a float in a transform_matrix ended in
    OverflowError, and of a key given twice the last value was taken without a word."""
    (tmp_path / "transforms_train.json").write_text(text)
    _photos(tmp_path, "", ["img.png"])
    with pytest.raises(InputError, match=re.escape(words)) as refused:
        load_capture(tmp_path / "transforms_train.json")
    assert refused.value.path == tmp_path / "transforms_train.json"


def test_json_nested_deeper_than_the_parser_goes_is_refused_by_name(tmp_path):
    """Found by the damaged-file fuzz: a transforms json of 50000 nested lists ended in RecursionError.
    The other json files a user may hand the tool (a dataset's scene.json for `eval --gt`, a run's
    run.json) are refused alike."""
    from vq_mitsuba.data.dataset_dir import DatasetDir
    from vq_mitsuba.run.run_dir import RunDir

    deep = "[" * 50000
    (tmp_path / "transforms_train.json").write_text('{"frames": ' + deep)
    with pytest.raises(InputError, match="nested too deep") as refused:
        load_capture(tmp_path / "transforms_train.json")
    assert refused.value.path == tmp_path / "transforms_train.json"
    dataset = DatasetDir(tmp_path)
    dataset.info_path.write_text(deep)
    with pytest.raises(InputError, match="nested too deep") as refused:
        dataset.info()
    assert refused.value.path == dataset.info_path
    (tmp_path / RunDir.INFO).write_text(deep)
    with pytest.raises(InputError, match="nested too deep") as refused:
        RunDir(tmp_path).info()
    assert refused.value.path == tmp_path / RunDir.INFO


def test_xml_nested_deeper_than_a_scene_is_refused_before_mitsuba_parses_it(tmp_path):
    """A scene.xml of 50000 nested <shape> elements: Mitsuba's parser recursed until the process
    died (a segmentation fault, no message at all); refused naming the file."""
    (tmp_path / "scene.xml").write_text('<scene version="3.0.0">' + '<shape type="sphere">' * 50000
                                        + "</shape>" * 50000 + "</scene>")
    with pytest.raises(InputError, match="elements nest more than 64 levels deep") as refused:
        load_capture(tmp_path / "scene.xml")
    assert refused.value.path == tmp_path / "scene.xml"


def test_a_name_longer_than_the_file_system_takes_is_refused_by_name(tmp_path, capsys):
    """A sensor id or frame file_path of 300 characters (found by the XML fuzz: an id made of nested
    entities), and such a capture path on the command line: refused naming the file, exit 2."""
    from vq_mitsuba import cli

    long_name = "n" * 300
    _photos(tmp_path, "images", ["b.png"])
    (tmp_path / "scene.xml").write_text(XML_SCENE.replace('id="a"', f'id="{long_name}"').split("    <emitter")[0]
                                        + "</scene>")
    with pytest.raises(InputError, match="File name too long") as refused:
        load_capture(tmp_path / "scene.xml")
    assert long_name in str(refused.value.path)
    (tmp_path / "transforms_train.json").write_text(json.dumps(
        {"camera_angle_x": 0.7, "frames": [{"file_path": long_name, "transform_matrix": good_matrix}]}))
    with pytest.raises(InputError, match="File name too long") as refused:
        load_capture(tmp_path / "transforms_train.json")
    assert long_name in str(refused.value.path)
    assert cli.main(["fit", str(tmp_path / long_name), "-o", str(tmp_path / "run")]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: {tmp_path / long_name}") and "Traceback" not in err
    assert not (tmp_path / "run").exists()
