"""Fuzz of the envmap readers (Hypothesis): EXR, Radiance HDR, PNG, JPEG and PFM files of any size
and content (NaN, infinities, negative, huge, black), truncated, with changed bytes, another
format's magic, or a header that claims another size. `load_envmap` returns a finite lat-long map
with some light, or refuses with an InputError naming the file, never another exception; a header
that claims more texels than a reader takes is refused by its size, before any pixel is read."""

import struct
import zlib

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from fuzzing import fuzz, python_text
from vq_mitsuba.data.envmaps import load_envmap
from vq_mitsuba.data.imageio import MAX_TEXELS
from vq_mitsuba.errors import InputError

FUZZ = fuzz(150)
SUFFIX = {"exr": ".exr", "hdr": ".hdr", "png": ".png", "png16": ".png", "jpeg": ".jpg", "pfm": ".pfm"}
texel_values = st.sampled_from([0.0, 0.5, 1.0, 7.0, -1e-3, -1.0, 1e-35, 3e38, 1e31, float("nan"), float("inf")])


def _write(path, kind: str, rgb: np.ndarray) -> None:
    """`rgb` (H, W, 3) as a file of `kind` (8- and 16-bit PNG, JPEG: clipped to [0, 1])."""
    if kind == "exr":
        from vq_mitsuba.data.imageio import write_exr

        write_exr(path, rgb)
    elif kind in ("png", "png16", "jpeg"):
        from PIL import Image

        clipped = np.clip(np.nan_to_num(rgb), 0, 1)
        if kind == "png16":
            import mitsuba as mi

            from vq_mitsuba.backend import init_mitsuba

            init_mitsuba()
            mi.Bitmap(np.round(clipped * 65535).astype(np.uint16), pixel_format=mi.Bitmap.PixelFormat.RGB).write(str(path))
        else:
            Image.fromarray(np.round(clipped * 255).astype(np.uint8)).save(path, format="PNG" if kind == "png" else "JPEG")
    else:
        import mitsuba as mi

        from vq_mitsuba.backend import init_mitsuba

        init_mitsuba()
        mi.Bitmap(np.ascontiguousarray(rgb, np.float32), pixel_format=mi.Bitmap.PixelFormat.RGB).write(str(path))


def _claimed_size(data: bytes, kind: str, width: int, height: int) -> bytes:
    """The file with its header saying width x height texels (its pixels as they were)."""
    if kind == "exr":
        for name in (b"dataWindow\0box2i\0", b"displayWindow\0box2i\0"):
            at = data.find(name) + len(name) + 4
            corner = [(side - 1 + 2 ** 31) % 2 ** 32 - 2 ** 31 for side in (width, height)]  # as int32 holds it
            data = data[:at] + struct.pack("<iiii", 0, 0, *corner) + data[at + 16:]
        return data
    if kind in ("png", "png16"):
        ihdr = struct.pack(">II", width, height) + data[24:29]
        return data[:16] + ihdr + struct.pack(">I", zlib.crc32(b"IHDR" + ihdr) & 0xFFFFFFFF) + data[33:]
    if kind == "hdr":
        head = data.find(b"\n\n") + 2
        return data[:head] + f"-Y {height} +X {width}".encode() + data[data.find(b"\n", head):]
    if kind == "pfm":
        first = data.find(b"\n") + 1
        return data[:first] + f"{width} {height}".encode() + data[data.find(b"\n", first):]
    return data


sizes = st.integers(0, 4) | st.sampled_from([5, 16, 65535, 1 << 16, 100_000, 2 ** 31 - 1, 2 ** 32 - 1])
damage = st.one_of(
    st.none(),
    st.tuples(st.just("truncate"), st.floats(0, 1)),
    st.tuples(st.just("bytes"), st.floats(0, 1), st.binary(min_size=1, max_size=8)),
    st.tuples(st.just("magic"), st.sampled_from([b"v/1\x01", b"\x89PNG\r\n\x1a\n", b"\xff\xd8", b"#?", b"PF\n",
                                                 b"PK\x03\x04", b"\x00", b""])),
    st.tuples(st.just("size"), sizes, sizes),
)


def _damaged(data: bytes, kind: str, change) -> bytes:
    if change is None:
        return data
    if change[0] == "truncate":
        return data[:int(change[1] * len(data))]
    if change[0] == "bytes":
        at = int(change[1] * len(data))
        return data[:at] + change[2] + data[at + len(change[2]):]
    if change[0] == "magic":
        return change[1] + data[len(change[1]) or 4:]
    return _claimed_size(data, kind, change[1], change[2])


def _load(path, **kwargs):
    """The map, or None when refused with an InputError naming `path` in words of the tool's own."""
    try:
        return load_envmap(path, **kwargs)
    except InputError as exc:
        assert exc.path == path and not python_text(exc.message), exc
        return None


@FUZZ
@given(kind=st.sampled_from(sorted(SUFFIX)), height=st.integers(1, 5), wide=st.booleans(),
       values=st.lists(texel_values, min_size=1, max_size=4), change=damage, exposure=st.sampled_from([0.0, 200.0]))
def test_damaged_envmaps_load_or_are_refused_by_name(tmp_path_factory, kind, height, wide, values, change, exposure):
    folder = tmp_path_factory.mktemp("env")
    width = 2 * height if wide else height + 1
    rgb = np.resize(np.asarray(values, np.float32), (height, width, 3))
    path = folder / f"env{SUFFIX[kind]}"
    _write(path, kind, rgb)
    path.write_bytes(_damaged(path.read_bytes(), kind, change))
    env = _load(path, exposure_ev=exposure, hdr_only=False)
    assert [p.name for p in folder.iterdir()] == [path.name]  # reading writes nothing
    if env is not None:
        assert env.dtype == np.float32 and env.ndim == 3 and env.shape[1] == 2 * env.shape[0] >= 4
        assert np.isfinite(env).all() and env.max() > 0
    if change is not None and change[0] == "size" and change[1] * change[2] > MAX_TEXELS and kind != "jpeg":
        assert env is None  # refused by the size its header claims, before any pixel is read


@pytest.mark.parametrize("kind", ["exr", "png", "png16", "hdr", "pfm"])
def test_a_header_claiming_a_huge_image_is_refused_by_its_size(tmp_path, kind):
    """A 4 x 2 envmap whose header says 100000 x 50000 texels (found by the envmap fuzz: EXR, 16-bit
    PNG and PFM readers tried to allocate what the header says): refused by its size, naming the file."""
    path = tmp_path / f"env{SUFFIX[kind]}"
    _write(path, kind, np.ones((2, 4, 3), np.float32))
    path.write_bytes(_claimed_size(path.read_bytes(), kind, 100_000, 50_000))
    with pytest.raises(InputError) as refused:
        load_envmap(path, hdr_only=False)
    message = refused.value.message
    assert refused.value.path == path and "100000" in message and "50000" in message, refused.value


@pytest.mark.parametrize("sides", [b"4 0", b"0 2", b"4 0x2", b"-4 2"])
def test_a_pfm_header_without_a_texel_is_refused(tmp_path, sides):
    """Found by the envmap fuzz: a PFM whose header says 4 x 0 made Mitsuba's reader divide by zero,
    and the process died of a floating-point exception (no message, no exit status 2)."""
    path = tmp_path / "env.pfm"
    path.write_bytes(b"PF\n" + sides + b"\n-1.0\n" + bytes(96))
    with pytest.raises(InputError, match="texels: no image") as refused:
        load_envmap(path, hdr_only=False)
    assert refused.value.path == path
