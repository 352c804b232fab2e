"""Photos made smaller as they are read, one at a time, so that a capture of many large photos never
holds them all at full size: `capture.downscale` N averages N x N blocks (the image cropped to a
multiple of N), then `capture.max_size` caps the longest side, each output pixel the exact
area-weighted mean of the input pixels it covers. Cameras scale with the exact size ratio on each
axis (fx, cx with the width; fy, cy with the height; pixel centres at +0.5)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vq_mitsuba.data.cameras import Camera, camera_from_intrinsics
from vq_mitsuba.errors import InputError

MIN_SIDE = 4  # pixels: a smaller view is no image to fit


def downscaled_camera(camera: Camera, factor: int) -> Camera:
    """The camera of the image downscaled by an integer factor (cropped to a multiple of it)."""
    if factor <= 1:
        return camera
    fx, fy, cx, cy = camera.intrinsics()
    return camera_from_intrinsics(camera.name, camera.to_world, fx / factor, fy / factor, cx / factor, cy / factor,
                                  camera.width // factor, camera.height // factor)


@dataclass(frozen=True)
class Shrink:
    """How images are made smaller as they are read (config section `capture`)."""

    downscale: int = 1
    max_size: int = 0  # 0: no limit

    @classmethod
    def of(cls, options) -> Shrink:
        """From a CaptureConfig (or anything with `downscale` and `max_size`)."""
        return cls(max(1, int(options.downscale)), max(0, int(getattr(options, "max_size", 0))))

    @property
    def active(self) -> bool:
        return self.downscale > 1 or self.max_size > 0

    def size(self, width: int, height: int, path: Path | None = None) -> tuple[int, int]:
        """(width, height) of an image of width x height once read; an InputError naming `path`
        when that leaves fewer than MIN_SIDE pixels a side."""
        f = self.downscale
        w, h = width // f, height // f
        if f > 1 and (w < MIN_SIDE or h < MIN_SIDE):
            raise InputError(path, f"--downscale {f} leaves {w}x{h} pixels of {width}x{height} images")
        if self.max_size > 0 and max(w, h) > self.max_size:
            s = self.max_size / max(w, h)
            w, h = (self.max_size, max(1, round(h * s))) if w >= h else (max(1, round(w * s)), self.max_size)
            if min(w, h) < MIN_SIDE:
                raise InputError(path, f"capture.max_size {self.max_size} leaves {w}x{h} pixels of {width}x{height} "
                                       "images")
        return w, h

    def image(self, array: np.ndarray, path: Path | None = None) -> np.ndarray:
        """An (H, W) or (H, W, C) float image at `size` (the input itself when nothing changes)."""
        h, w = array.shape[:2]
        tw, th = self.size(w, h, path)
        f = self.downscale
        if f > 1:
            hc, wc = h // f * f, w // f * f
            array = array[:hc, :wc].reshape(hc // f, f, wc // f, f, *array.shape[2:]).mean((1, 3), dtype=np.float32)
        if array.shape[:2] != (th, tw):
            array = area_resize(array, tw, th)
        return np.ascontiguousarray(array, dtype=np.float32)

    def decode_reduction(self, path: Path) -> int:
        """The factor (1, 2, 4 or 8) by which the JPEG decoder may shrink the photo at `path` on its
        own before `image` finishes the job (`after`): the decode of a large JPEG at a fraction of
        its size takes a fraction of the time."""
        if not self.active or Path(path).suffix.lower() not in (".jpg", ".jpeg"):
            return 1
        from vq_mitsuba.data.imageio import image_size, jpeg_reduction

        width, height = image_size(path)
        target = self.size(width, height, path)
        r = jpeg_reduction(width, height, target)
        while r > 1 and self.downscale > 1 and self.downscale % r:
            r //= 2
        return r

    def after(self, reduction: int) -> Shrink:
        """What is left to do to an image already shrunk by `reduction` (see `decode_reduction`)."""
        if reduction <= 1:
            return self
        return Shrink(max(1, self.downscale // reduction), self.max_size)

    def camera(self, camera: Camera, path: Path | None = None) -> Camera:
        """The camera of the image `image` makes of a camera.width x camera.height one."""
        tw, th = self.size(camera.width, camera.height, path)
        camera = downscaled_camera(camera, self.downscale)
        return camera if (camera.width, camera.height) == (tw, th) else camera.scaled(tw, th)


def _area_weights(n_in: int, n_out: int):
    """(n_out, n_in) sparse matrix: output pixel i is the mean of input span [i, i + 1) * n_in / n_out,
    each input pixel weighted by the length of its overlap (n_out <= n_in)."""
    from scipy.sparse import csr_matrix

    scale = n_in / n_out
    j = np.arange(n_in, dtype=np.float64)
    first = np.minimum(np.floor(j / scale), n_out - 1)
    second = np.minimum(np.floor((j + 1) / scale), n_out - 1)
    in_first = np.minimum((first + 1) * scale, j + 1) - j  # share of input pixel j inside output `first`
    rows = np.concatenate([first, second])
    cols = np.concatenate([j, j])
    vals = np.concatenate([in_first, np.where(second > first, 1.0 - in_first, 0.0)]) / scale
    keep = vals > 0
    return csr_matrix((vals[keep].astype(np.float32), (rows[keep].astype(np.int64), cols[keep].astype(np.int64))),
                      shape=(n_out, n_in))


def area_resize(array: np.ndarray, width: int, height: int) -> np.ndarray:
    """Shrink an (H, W) or (H, W, C) image to width x height by exact area averaging."""
    h, w = array.shape[:2]
    if width > w or height > h:
        raise ValueError(f"area_resize shrinks: {w}x{h} -> {width}x{height}")
    flat = np.asarray(array, dtype=np.float32).reshape(h, w, -1)
    c = flat.shape[-1]
    rows = _area_weights(h, height) @ flat.reshape(h, w * c)  # (height, w * c)
    cols = _area_weights(w, width) @ rows.reshape(height, w, c).transpose(1, 0, 2).reshape(w, height * c)
    out = np.asarray(cols, dtype=np.float32).reshape(width, height, c).transpose(1, 0, 2)
    return out.reshape(height, width, *array.shape[2:])
