"""Fuzz of the capture loaders (Hypothesis): malformed json and XML, odd image sizes, bit depths and
channel layouts. A capture either loads with finite images in [0, 1]-ish ranges, or is refused
with an InputError naming a file; no other exception (no traceback) ever reaches the user."""

import json
import os

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

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


def _check(folder):
    try:
        cap = load_capture(folder / "transforms_train.json")
    except InputError as exc:
        assert exc.path is not None or exc.message, exc
        return "refused"
    assert np.isfinite(cap.images).all() and np.isfinite(cap.alpha).all()
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
    with pytest.raises(InputError):
        load_capture(path)


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
        frames_json.append({"file_path": f"./{name}", "transform_matrix": good_matrix})
    (folder / "transforms_train.json").write_text(json.dumps({"camera_angle_x": 0.7, "frames": frames_json}))
    outcome = _check(folder)
    assert outcome == ("refused" if second_size else "loaded")
