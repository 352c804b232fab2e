"""Image I/O in linear RGB: sRGB PNG (alpha = mask) and EXR through OpenEXR."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from vq_mitsuba.errors import InputError, WriteError, as_write_error


LUMINANCE = (0.2126, 0.7152, 0.0722)  # Rec. 709 weights of linear R, G, B


def srgb_to_linear(srgb: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1 sRGB decoding; input in [0, 1]."""
    srgb = np.asarray(srgb, dtype=np.float32)
    return np.where(srgb <= 0.04045, srgb / 12.92, ((srgb + 0.055) / 1.055) ** 2.4).astype(np.float32)


def linear_to_srgb(linear: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1 sRGB encoding; output clipped to [0, 1]."""
    x = np.clip(np.asarray(linear, dtype=np.float32), 0.0, 1.0)
    return np.where(x <= 0.0031308, x * 12.92, 1.055 * np.power(x, 1.0 / 2.4) - 0.055).astype(np.float32)


# What each image format's files start with: a file is known by these bytes, never by its name alone.
MAGIC = {"exr": (b"\x76\x2f\x31\x01",), "png": (b"\x89PNG\r\n\x1a\n",), "jpeg": (b"\xff\xd8",),
         "hdr": (b"#?",), "pfm": (b"PF\n", b"Pf\n", b"PF\r", b"Pf\r", b"PF ", b"Pf ")}
KIND_OF_SUFFIX = {".exr": "exr", ".png": "png", ".jpg": "jpeg", ".jpeg": "jpeg", ".hdr": "hdr", ".pic": "hdr",
                  ".pfm": "pfm"}
KIND_NAMES = {"exr": "OpenEXR", "png": "PNG", "jpeg": "JPEG", "hdr": "Radiance HDR", "pfm": "PFM"}


def file_kind(path: str | Path) -> str | None:
    """The image format a file's first bytes show ("exr", "png", "jpeg", "hdr", "pfm"), or None."""
    try:
        with open(path, "rb") as f:
            head = f.read(16)
    except OSError as exc:
        raise InputError(path, f"cannot read file ({exc.strerror or exc})") from None
    return next((kind for kind, starts in MAGIC.items() if head.startswith(starts)), None)


def checked_kind(path: str | Path) -> str:
    """The image format of `path`, which its bytes and its suffix must agree on: an InputError naming
    the file when they do not (another kind of file renamed, or a truncated one) or the suffix is unknown,
    or when its header claims more than MAX_TEXELS texels (`check_claimed_size`)."""
    path = Path(path)
    named = KIND_OF_SUFFIX.get(path.suffix.lower())
    if named is None:
        raise InputError(path, f"unsupported image format '{path.suffix}' (one of {', '.join(KIND_OF_SUFFIX)})")
    found = file_kind(path)
    if found != named:
        raise _not_a(path, named, found)
    check_claimed_size(path, named)
    return named


# The most texels an image file may have (16384 x 16384): a decoder allocates what the header
# claims, so a damaged or hostile header of a few bytes could ask for any amount of memory.
MAX_TEXELS = 1 << 28


def claimed_size(path: Path, kind: str) -> tuple[int, int] | None:
    """(width, height) as an EXR, PNG or PFM header states it, read without decoding a pixel (None for
    other formats, whose readers bound it themselves: Pillow's JPEG limit, the .hdr header check, or a
    header that cannot be read, which the decoder then reports)."""
    try:
        if kind == "exr":
            import OpenEXR

            with OpenEXR.File(str(path), header_only=True) as exr:
                low, high = exr.header()["dataWindow"]
            return int(high[0]) - int(low[0]) + 1, int(high[1]) - int(low[1]) + 1
        with open(path, "rb") as f:
            head = f.read(64)
        if kind == "png" and head[12:16] == b"IHDR":
            return int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")
        if kind == "pfm":  # each side as Mitsuba reads it: the whole number its text starts with ("0x2" is 0)
            sides = [re.match(rb"[-+]?\d+", field) for field in head.split(maxsplit=3)[1:3]]
            return int(sides[0].group()), int(sides[1].group())
    except Exception:  # an unreadable header: the decoder says what is wrong
        return None
    return None


def check_claimed_size(path: Path, kind: str) -> None:
    """An InputError naming the file when its header claims no texel or more than MAX_TEXELS (a
    side of 0 made Mitsuba's PFM reader divide by zero: the process died of a floating-point exception)."""
    size = claimed_size(path, kind)
    if size is not None and min(size) < 1:
        raise InputError(path, f"its header says {size[0]} x {size[1]} texels: no image (a damaged file?)")
    if size is not None and size[0] * size[1] > MAX_TEXELS:
        raise InputError(path, f"its header says {size[0]} x {size[1]} texels, more than an image may have "
                               f"({MAX_TEXELS} texels, 16384 x 16384): a damaged file?")


def _not_a(path: Path, named: str, found: str | None) -> InputError:
    def a(kind: str) -> str:
        return ("an " if kind == "exr" else "a ") + KIND_NAMES[kind]

    what = f"{a(found)} file" if found else "empty, truncated or another kind of file"
    return InputError(path, f"not {a(named)} image: the file does not start like one ({what} named {path.suffix}?)")


def _read_8_or_16_bit(path: Path, reduce: int = 1) -> np.ndarray:
    """PNG / JPEG pixels as stored: uint8, or uint16 for 16-bit PNGs (which Pillow would cut to 8 bits).

    `reduce` 2, 4 or 8 asks a JPEG whose sides it divides for 1/reduce of its width and height,
    decoded at that scale by the JPEG decoder itself (each pixel the mean of a reduce x reduce block)."""
    import imageio.v3 as iio  # ships with scikit-image

    png = checked_kind(path) == "png"
    with open(path, "rb") as f:
        head = f.read(26)
    if not png:
        from PIL import Image

        with Image.open(path) as im:
            if reduce > 1:
                w, h = im.size
                if w % reduce or h % reduce:  # callers ask only where jpeg_reduction allows
                    raise ValueError(f"cannot decode at 1/{reduce} scale")
                im.draft(im.mode, (w // reduce, h // reduce))
                if im.size != (w // reduce, h // reduce):
                    raise ValueError(f"cannot decode at 1/{reduce} scale")
            # A CMYK JPEG's fourth channel is black, not alpha: Pillow converts it to RGB.
            return np.asarray(im if im.mode in ("L", "RGB") else im.convert("RGB"))
    if png and len(head) > 24 and head[24] == 16:
        import mitsuba as mi

        from vq_mitsuba.backend import init_mitsuba

        init_mitsuba()
        return np.array(mi.Bitmap(str(path)))
    if png:
        from PIL import Image

        with Image.open(path) as im:
            if "transparency" in im.info:  # a tRNS chunk (palette or colour-key PNG): its transparency is alpha
                return np.asarray(im.convert("LA" if im.mode in ("1", "L", "I") else "RGBA"))
    return np.asarray(iio.imread(path))


def read_image(path: str | Path, reduce: int = 1) -> tuple[np.ndarray, np.ndarray | None]:
    """Read an image as linear float32 RGB (H, W, 3) and its alpha (H, W) or None.

    PNG/JPEG are decoded from sRGB; EXR is taken as linear. Raises InputError naming the file.
    `reduce` > 1: a JPEG decoded at 1/reduce scale (see `jpeg_reduction`).
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "image file not found")
    suffix = path.suffix.lower()
    try:
        if suffix not in (".exr", ".png", ".jpg", ".jpeg"):
            raise InputError(path, f"unsupported image format '{suffix}' (use .exr or .png)")
        if checked_kind(path) == "exr":
            data = read_exr(path)
        else:
            raw = _read_8_or_16_bit(path, reduce)
            scale = 65535.0 if raw.dtype == np.uint16 else 255.0
            data = raw.astype(np.float32) / scale
            if data.ndim == 2:
                data = data[..., None]
            if data.shape[-1] in (1, 2):  # grey or grey + alpha
                data = np.concatenate([np.repeat(data[..., :1], 3, -1), data[..., 1:]], -1)
            data = np.concatenate([srgb_to_linear(data[..., :3]), data[..., 3:4]], -1)
    except InputError:
        raise
    except Exception as exc:  # decoder errors differ per library
        raise InputError(path, f"cannot read image ({type(exc).__name__}: {exc})") from exc
    if data.ndim != 3 or data.shape[-1] < 3:
        raise InputError(path, f"expected an RGB or RGBA image, got shape {data.shape}")
    rgb = np.ascontiguousarray(data[..., :3], dtype=np.float32)
    alpha = np.ascontiguousarray(data[..., 3], dtype=np.float32) if data.shape[-1] >= 4 else None
    if not np.all(np.isfinite(rgb)) or (alpha is not None and not np.all(np.isfinite(alpha))):
        raise InputError(path, "image contains non-finite pixels (NaN or Inf)")
    return clamp_tiny_negatives(rgb, path), alpha


# Lossy EXR compression and denoisers leave slightly negative texels (Blender's own studio-light
# probes hold some down to -0.002): those are clamped to 0; anything more negative is an error.
NEGATIVE_TOLERANCE = 1e-2


def clamp_tiny_negatives(rgb: np.ndarray, path) -> np.ndarray:
    low = float(rgb.min()) if rgb.size else 0.0
    if low < -NEGATIVE_TOLERANCE:
        raise InputError(path, f"image contains negative pixel values (down to {low:.3g})")
    return np.maximum(rgb, 0.0) if low < 0 else rgb


def read_exr(path: str | Path) -> np.ndarray:
    """Read an EXR file as float32 (H, W, C) with channels R, G, B[, A] (or Y as grey); a file that
    does not start like an EXR is an InputError naming it (`checked_kind`)."""
    import OpenEXR

    found = file_kind(path)
    if found != "exr":
        raise _not_a(Path(path), "exr", found)
    check_claimed_size(Path(path), "exr")
    with OpenEXR.File(str(path)) as f:
        channels = f.channels()
        if "RGBA" in channels:
            return np.asarray(channels["RGBA"].pixels, dtype=np.float32)
        if "RGB" in channels:
            return np.asarray(channels["RGB"].pixels, dtype=np.float32)
        names = list(channels)
        if "Y" in channels:
            y = np.asarray(channels["Y"].pixels, dtype=np.float32)[..., None]
            return np.concatenate([y, y, y], -1)
        if len(names) == 1:
            y = np.asarray(channels[names[0]].pixels, dtype=np.float32)[..., None]
            return np.concatenate([y, y, y], -1)
        raise ValueError(f"no RGB channels (found {names})")


def written(path: str | Path, write) -> None:
    """Run `write()` to make `path` (its folder made first). A write the machine refuses (a full or
    read-only disk, no permission) is a WriteError naming the file, and its partial file is removed."""
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        write()
        return
    except OSError as exc:
        error = as_write_error(exc, path)
        if error is None:
            raise
    except RuntimeError as exc:  # OpenEXR says why in words ('... "FILE". No space left on device.'), no errno
        reason = str(exc).strip().split('". ')[-1].rstrip(".") or type(exc).__name__
        error = WriteError(path, f"cannot be written: {reason} (files written before are kept)")
    try:
        path.unlink(missing_ok=True)
    except OSError:
        pass
    raise error from None


def write_exr(path: str | Path, image: np.ndarray) -> None:
    """Write float32 (H, W), (H, W, 3) or (H, W, 4) as a linear EXR (half floats are not used)."""
    import OpenEXR

    image = np.ascontiguousarray(image, dtype=np.float32)
    if image.ndim == 2:
        channels = {"Y": image}
    elif image.shape[-1] == 3:
        channels = {"RGB": image}
    elif image.shape[-1] == 4:
        channels = {"RGBA": image}
    elif image.shape[-1] == 1:
        channels = {"Y": np.ascontiguousarray(image[..., 0])}
    else:
        raise ValueError(f"cannot write an image of shape {image.shape} as EXR")
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}

    def write():
        with OpenEXR.File(header, channels) as f:
            f.write(str(path))

    written(path, write)


def write_png(path: str | Path, image: np.ndarray, alpha: np.ndarray | None = None, srgb: bool = True) -> None:
    """Write an 8-bit PNG. Linear RGB is sRGB-encoded unless srgb=False (data maps, ids)."""
    import imageio.v3 as iio

    image = np.asarray(image)
    if image.dtype == np.uint8:
        out = image
    else:
        x = linear_to_srgb(image) if srgb else np.clip(image, 0.0, 1.0)
        out = np.round(x * 255.0).astype(np.uint8)
    if alpha is not None:
        a = np.round(np.clip(alpha, 0.0, 1.0) * 255.0).astype(np.uint8)
        if out.ndim == 2:
            out = np.repeat(out[..., None], 3, -1)
        out = np.concatenate([out, a[..., None]], -1)
    encoded = iio.imwrite("<bytes>", out, extension=Path(path).suffix.lower() or ".png")
    written(path, lambda: Path(path).write_bytes(encoded))


def read_mask(path: str | Path, reduce: int = 1) -> np.ndarray:
    """A mask image (PNG/JPEG grey, RGB or RGBA; EXR) as (H, W) float32 in [0, 1], read as data
    (no sRGB decoding): the brightest colour channel, times alpha when there is one; `reduce` as
    for `read_image`."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "mask file not found")
    try:
        if checked_kind(path) == "exr":
            data = read_exr(path)
        else:
            raw = _read_8_or_16_bit(path, reduce)
            data = raw.astype(np.float32) / (65535.0 if raw.dtype == np.uint16 else 255.0)
    except InputError:
        raise
    except Exception as exc:
        raise InputError(path, f"cannot read mask ({type(exc).__name__}: {exc})") from exc
    if data.ndim == 2:
        data = data[..., None]
    colour = data[..., :3] if data.shape[-1] >= 3 else data[..., :1]
    mask = colour.max(-1) * (data[..., 3] if data.shape[-1] == 4 else 1.0)
    if not np.all(np.isfinite(mask)):
        raise InputError(path, "mask contains non-finite values")
    return np.clip(mask, 0.0, 1.0).astype(np.float32)


def image_size(path: str | Path) -> tuple[int, int]:
    """(width, height) of an image file, reading only what its format needs."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "image file not found")
    try:
        if checked_kind(path) == "exr":
            data = read_exr(path)
            return int(data.shape[1]), int(data.shape[0])
        from PIL import Image

        with Image.open(path) as im:
            return int(im.size[0]), int(im.size[1])
    except InputError:
        raise
    except Exception as exc:
        raise InputError(path, f"cannot read image ({type(exc).__name__}: {exc})") from exc


def jpeg_reduction(width: int, height: int, target: tuple[int, int]) -> int:
    """The largest of 8, 4, 2 (else 1) by which the JPEG decoder may shrink a width x height JPEG
    still at least `target` (width, height) pixels: it must divide both sides exactly."""
    for r in (8, 4, 2):
        if width % r == 0 and height % r == 0 and width // r >= target[0] and height // r >= target[1]:
            return r
    return 1
