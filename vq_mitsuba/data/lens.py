"""Lenses: pinhole intrinsics plus the distortion of COLMAP's camera models (also nerfstudio's),
their plausibility check, and undistorting a photo into the pinhole camera of the same
intrinsics (cached) or distorting a pinhole image (for test data).
"""

from __future__ import annotations

import hashlib
import os
import secrets
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vq_mitsuba.data.checks import check_intrinsics, finite_number
from vq_mitsuba.data.resize import Shrink
from vq_mitsuba.errors import InputError

# COLMAP camera models we read: id -> (name, parameter names)
MODELS = {
    0: ("SIMPLE_PINHOLE", ("f", "cx", "cy")),
    1: ("PINHOLE", ("fx", "fy", "cx", "cy")),
    2: ("SIMPLE_RADIAL", ("f", "cx", "cy", "k")),
    3: ("RADIAL", ("f", "cx", "cy", "k1", "k2")),
    4: ("OPENCV", ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2")),
    5: ("OPENCV_FISHEYE", ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4")),
}
MODEL_IDS = {name: i for i, (name, _) in MODELS.items()}
FISHEYE = "OPENCV_FISHEYE"  # equidistant projection, k1..k4 on the angle theta (COLMAP's and OpenCV's model)
DISTORTION = ("k1", "k2", "k3", "k4", "p1", "p2")


@dataclass
class Lens:
    """One camera's lens: pinhole intrinsics plus distortion. The perspective models (COLMAP's
    SIMPLE_RADIAL, RADIAL, OPENCV; nerfstudio's PINHOLE and OPENCV) scale a point at radius r by
    1 + k1 r^2 + k2 r^4 + k3 r^6 + k4 r^8 and add the tangential p1, p2 terms; OPENCV_FISHEYE maps
    the angle theta = atan(r) to theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8)."""

    model: str
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    k1: float = 0.0
    k2: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    k3: float = 0.0
    k4: float = 0.0

    @property
    def distorted(self) -> bool:
        return self.model == FISHEYE or any(abs(getattr(self, n)) > 0 for n in DISTORTION)

    def params(self) -> list[float]:
        values = {"f": self.fx, "fx": self.fx, "fy": self.fy, "cx": self.cx, "cy": self.cy, "k": self.k1,
                  **{n: getattr(self, n) for n in DISTORTION}}
        return [values[n] for n in MODELS[MODEL_IDS[self.model]][1]]

    @staticmethod
    def from_params(model: str, width: int, height: int, params) -> Lens:
        names = MODELS[MODEL_IDS[model]][1]
        v = dict(zip(names, (float(p) for p in params)))
        fx = v.get("fx", v.get("f"))
        fy = v.get("fy", v.get("f"))
        return Lens(model, int(width), int(height), fx, fy, v["cx"], v["cy"], v.get("k1", v.get("k", 0.0)),
                    v.get("k2", 0.0), v.get("p1", 0.0), v.get("p2", 0.0), v.get("k3", 0.0), v.get("k4", 0.0))

    def _radial(self, x2: np.ndarray) -> np.ndarray:
        return 1.0 + x2 * (self.k1 + x2 * (self.k2 + x2 * (self.k3 + x2 * self.k4)))

    def distort(self, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Normalised undistorted coordinates -> distorted ones."""
        r2 = u * u + v * v
        if self.model == FISHEYE:
            r = np.sqrt(r2)
            theta = np.arctan(r)
            scale = np.where(r > 1e-12, theta * self._radial(theta * theta) / np.maximum(r, 1e-12), 1.0)
            return u * scale, v * scale
        radial = self._radial(r2) - 1.0
        du = u * radial + 2 * self.p1 * u * v + self.p2 * (r2 + 2 * u * u)
        dv = v * radial + 2 * self.p2 * u * v + self.p1 * (r2 + 2 * v * v)
        return u + du, v + dv

    def undistort(self, ud: np.ndarray, vd: np.ndarray, iterations: int = 12) -> tuple[np.ndarray, np.ndarray]:
        """Inverse of `distort` (Newton's method with a numerical Jacobian, as COLMAP does)."""
        u, v = ud.copy(), vd.copy()
        eps = 1e-9
        for _ in range(iterations):
            fu, fv = self.distort(u, v)
            ru, rv = fu - ud, fv - vd
            a, c = ((x - y) / eps for x, y in zip(self.distort(u + eps, v), (fu, fv)))
            b, d = ((x - y) / eps for x, y in zip(self.distort(u, v + eps), (fu, fv)))
            det = a * d - b * c
            det = np.where(np.abs(det) < 1e-12, 1e-12, det)
            u, v = u - (d * ru - b * rv) / det, v - (-c * ru + a * rv) / det
        return u, v

    def pixel_to_normalised(self, x, y):
        return (np.asarray(x, np.float64) - self.cx) / self.fx, (np.asarray(y, np.float64) - self.cy) / self.fy

    def normalised_to_pixel(self, u, v):
        return u * self.fx + self.cx, v * self.fy + self.cy


# Plausible distortion: over the whole image the lens keeps every point within a factor
# MAX_RADIAL_SCALE of its distance from the principal point, and stays one-to-one (a positive
# Jacobian), which undistortion needs. Wide-angle lenses that COLMAP's OPENCV model fits stay well
# inside (k1 = -0.25, k2 = 0.06 scale the corners of a 4:3 view 100 degrees wide by 0.74); k1 = 50
# on a 4:3 view 60 degrees wide scales them by 27.
MAX_RADIAL_SCALE = 2.0


def check_lens(path: Path, entry: str, lens: Lens) -> None:
    """A COLMAP camera: intrinsics (vq_mitsuba.data.checks), finite and plausible distortion."""
    check_intrinsics(path, entry, lens.fx, lens.fy, lens.cx, lens.cy, lens.width, lens.height)
    for name in DISTORTION:
        if not finite_number(getattr(lens, name)):
            raise InputError(path, f"{entry}: distortion {name} = {getattr(lens, name)!r} is not a finite number")
    if not lens.distorted:
        return
    xs, ys = np.meshgrid(np.linspace(0, lens.width, 17), np.linspace(0, lens.height, 17))
    u, v = lens.pixel_to_normalised(xs, ys)
    eps = 1e-6
    with np.errstate(all="ignore"):  # overflow becomes inf, refused below
        du, dv = lens.distort(u, v)
        r = np.hypot(u, v)
        ideal = np.arctan(r) if lens.model == FISHEYE else r  # a fisheye's own projection is no distortion
        scale = np.hypot(du, dv)[r > 1e-9] / ideal[r > 1e-9]
        (a, c), (b, d) = (((x - y) / eps for x, y in zip(moved, (du, dv)))
                          for moved in (lens.distort(u + eps, v), lens.distort(u, v + eps)))
        folds = not np.all(a * d - b * c > 0)
    coefficients = ", ".join(f"{n} = {getattr(lens, n):g}" for n in DISTORTION if n in ("k1", "k2", "p1", "p2")
                             or getattr(lens, n) != 0)
    if not np.all((scale >= 1 / MAX_RADIAL_SCALE) & (scale <= MAX_RADIAL_SCALE)):
        worst = scale[np.argmax(np.abs(np.log(np.nan_to_num(scale, nan=np.inf) + 1e-300)))]
        raise InputError(path, f"{entry}: implausible distortion ({coefficients}): it moves image points to "
                               f"{worst:.3g} times their distance from the principal point (a real lens stays "
                               f"within {1 / MAX_RADIAL_SCALE:g}..{MAX_RADIAL_SCALE:g})")
    if folds:
        raise InputError(path, f"{entry}: implausible distortion ({coefficients}): it folds the image over "
                               "(not one-to-one), so it cannot be undone")


def resample(image: np.ndarray, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Bilinear samples of `image` (H, W, C) at pixel positions x, y (pixel centres at +0.5), and a
    mask of the positions that lie inside the image."""
    from scipy.ndimage import map_coordinates

    h, w = image.shape[:2]
    inside = (x >= 0) & (x <= w) & (y >= 0) & (y <= h)
    coords = np.stack([np.clip(y - 0.5, 0, h - 1), np.clip(x - 0.5, 0, w - 1)])
    out = np.stack([map_coordinates(image[..., c], coords, order=1, mode="nearest") for c in range(image.shape[-1])], -1)
    return out.astype(np.float32), inside


def undistort_image(image: np.ndarray, lens: Lens) -> tuple[np.ndarray, np.ndarray]:
    """The image (H, W, C) as the pinhole camera of the same intrinsics sees it, and (H, W) the
    share of it that the distorted image covers (1 inside, 0 where no source pixel exists)."""
    ys, xs = np.meshgrid(np.arange(lens.height) + 0.5, np.arange(lens.width) + 0.5, indexing="ij")
    ud, vd = lens.distort(*lens.pixel_to_normalised(xs, ys))
    sx, sy = lens.normalised_to_pixel(ud, vd)
    out, inside = resample(image, sx, sy)
    return out, inside.astype(np.float32)


def distort_image(image: np.ndarray, lens: Lens) -> np.ndarray:
    """Inverse of `undistort_image`: what the distorted lens records of a pinhole image."""
    ys, xs = np.meshgrid(np.arange(lens.height) + 0.5, np.arange(lens.width) + 0.5, indexing="ij")
    u, v = lens.undistort(*lens.pixel_to_normalised(xs, ys))
    sx, sy = lens.normalised_to_pixel(u, v)
    out, _ = resample(image, sx, sy)
    return out


def undistort_photo(path: Path, rgb: np.ndarray, alpha: np.ndarray, lens: Lens, cache: Path | None, shrink: Shrink):
    """Undistort one photo and its mask, then shrink them, reusing the cached result for the same
    file, lens and shrink. A cached file that cannot be read back whole (torn, another file) is
    made again; it is written under a temporary name and renamed, so a crash leaves none half-written."""
    key = hashlib.sha1(f"{path.resolve()}|{path.stat().st_mtime_ns}|{lens}|{shrink}".encode()).hexdigest()[:16]
    cached = cache / f"{path.stem}-{key}.npz" if cache is not None else None
    if cached is not None and cached.is_file():
        try:
            with np.load(cached) as data:
                rgb_c, alpha_c = data["rgb"].astype(np.float32), data["alpha"].astype(np.float32)
            if rgb_c.ndim == 3 and rgb_c.shape[2] == 3 and alpha_c.shape == rgb_c.shape[:2] \
                    and np.isfinite(rgb_c).all() and np.isfinite(alpha_c).all():
                return rgb_c, alpha_c
        except Exception:  # any unreadable cache file is made again below
            pass
    both, inside = undistort_image(np.concatenate([rgb, alpha[..., None]], -1), lens)
    del rgb, alpha
    both[..., 3] *= inside
    both = shrink.image(both, path)
    out_rgb, out_alpha = both[..., :3], both[..., 3]
    if cached is not None:
        cache.mkdir(parents=True, exist_ok=True)
        tmp = cached.with_name(f".{cached.stem}.{os.getpid()}-{secrets.token_hex(4)}.tmp.npz")  # one per writer
        np.savez(tmp, rgb=out_rgb.astype(np.float16), alpha=out_alpha.astype(np.float16))
        tmp.replace(cached)
    return out_rgb, out_alpha


def distort_rgba(rgb: np.ndarray, alpha: np.ndarray, lens: Lens | None) -> tuple[np.ndarray, np.ndarray]:
    """An image and its alpha as `lens` records them (`distort_image`); unchanged without a lens."""
    if lens is None:
        return rgb, alpha
    both = distort_image(np.concatenate([rgb, alpha[..., None]], -1), lens)
    return both[..., :3], both[..., 3]
