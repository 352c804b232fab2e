"""Fuzz of the capture loaders (Hypothesis): malformed json and XML, odd image sizes, bit depths and
channel layouts, mutated COLMAP text and binary models and NeuS/IDR archives. A capture either
loads with finite images in [0, 1]-ish ranges and finite cameras, or is refused with an InputError
naming a file; no other exception (no traceback) ever reaches the user."""

import json
import os

import numpy as np
import pytest
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import array_shapes, arrays

from vq_mitsuba.data.captures import load_capture
from vq_mitsuba.errors import InputError

# benchmarks/stress.py raises the number of examples through VQM_FUZZ_EXAMPLES.
FUZZ = settings(max_examples=int(os.environ.get("VQM_FUZZ_EXAMPLES", "60")), deadline=None,
                suppress_health_check=[HealthCheck.function_scoped_fixture])

json_values = st.recursive(
    st.none() | st.booleans() | st.integers(-5, 5) | st.floats(allow_nan=True, allow_infinity=True)
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
        assert exc.path is not None or exc.message, exc
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
