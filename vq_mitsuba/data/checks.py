"""What a capture file says about its cameras, checked before any work is done: each check raises
one InputError naming the file and the entry (camera, image, frame, matrix) at fault.

Beyond finiteness, the bounds are wide enough for any real camera and tight enough that no value
overflows on its way to Dr.Jit (float32):
- image size: 1 to MAX_IMAGE_SIDE pixels a side;
- focal lengths: positive, giving a field of view of MIN_FOV_DEG to MAX_FOV_DEG on each axis (a
  pinhole camera cannot see 180 degrees; a fisheye needs a model vq-mitsuba does not read);
- principal point: inside the image widened by half its size on each side;
- camera positions: within MAX_DISTANCE of the world origin along each axis (capture units are
  arbitrary; farther is a broken file, or a model to rescale, since float32 keeps few digits there).
"""

from __future__ import annotations

import math
from collections import Counter
from pathlib import Path
from typing import Callable

import numpy as np

from vq_mitsuba.errors import InputError

MAX_IMAGE_SIDE = 100_000
MIN_FOV_DEG = 0.01
MAX_FOV_DEG = 170.0
MAX_DISTANCE = 1e6


def finite_number(value) -> bool:
    """Whether `value` is a real, finite number (bools and strings are not)."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)):
        return False
    try:
        return math.isfinite(float(value))
    except OverflowError:  # an int too large for a float
        return False


def check_size(path: Path, entry: str, width, height) -> None:
    """Image width and height: whole numbers of 1 to MAX_IMAGE_SIDE pixels."""
    for name, value in (("width", width), ("height", height)):
        if not finite_number(value) or value != int(value) or not 1 <= value <= MAX_IMAGE_SIDE:
            raise InputError(path, f"{entry}: image {name} {value!r} is not a whole number of pixels in "
                                   f"1..{MAX_IMAGE_SIDE}")


def check_intrinsics(path: Path, entry: str, fx, fy, cx, cy, width, height) -> None:
    """Pixel intrinsics (pixel centres at +0.5) of an image of width x height: see the module's bounds."""
    check_size(path, entry, width, height)
    for name, value in (("fx", fx), ("fy", fy), ("cx", cx), ("cy", cy)):
        if not finite_number(value):
            raise InputError(path, f"{entry}: {name} = {value!r} is not a finite number")
    for name, focal, side in (("fx", fx, width), ("fy", fy, height)):
        if focal <= 0:
            raise InputError(path, f"{entry}: focal length {name} = {focal:g} must be positive")
        fov = math.degrees(2.0 * math.atan(0.5 * side / focal))
        if not MIN_FOV_DEG <= fov <= MAX_FOV_DEG:
            raise InputError(path, f"{entry}: focal length {name} = {focal:g} pixels gives a field of view of "
                                   f"{fov:.4g} degrees over {side} pixels; a pinhole camera needs "
                                   f"{MIN_FOV_DEG:g}..{MAX_FOV_DEG:g}")
    for name, value, side in (("cx", cx, width), ("cy", cy, height)):
        if not -0.5 * side <= value <= 1.5 * side:
            raise InputError(path, f"{entry}: principal point {name} = {value:g} lies far outside the image "
                                   f"(0..{side} pixels)")


def check_pose(path: Path, entry: str, to_world) -> None:
    """A (4, 4) camera-to-world matrix: finite, an invertible 3x3 part, a position within MAX_DISTANCE."""
    m = np.asarray(to_world, dtype=np.float64)
    if m.shape != (4, 4) or not np.all(np.isfinite(m)):
        raise InputError(path, f"{entry}: the camera pose is not a finite 4x4 matrix")
    rot = m[:3, :3]
    scale = np.abs(rot).max()
    if scale == 0 or abs(np.linalg.det(rot / scale)) < 1e-9:
        raise InputError(path, f"{entry}: the camera's rotation is degenerate (a singular 3x3 part)")
    distance = float(np.abs(m[:3, 3]).max())  # along the farthest axis (a norm could overflow)
    if not distance <= MAX_DISTANCE:
        raise InputError(path, f"{entry}: the camera sits {distance:.3g} units from the origin; more than "
                               f"{MAX_DISTANCE:g} is a broken file or a model to rescale")


def check_camera(path: Path, entry: str, camera) -> None:
    """A built `Camera`: its intrinsics and its pose (the last check every loader makes)."""
    check_intrinsics(path, entry, *camera.intrinsics(), camera.width, camera.height)
    check_pose(path, entry, camera.to_world)


def check_viewpoints(path: Path, cameras) -> None:
    """Two or more cameras that all sit at one point and all look one way (within a millionth of
    the capture's size and a thousandth of a radian) show the object from one viewpoint only:
    nothing to fit a shape from. Refused, naming the capture (a broken pose export, most often)."""
    if len(cameras) < 2:
        return
    centres = np.array([c.to_world[:3, 3] for c in cameras], dtype=np.float64)
    forwards = np.array([c.to_world[:3, 2] / np.linalg.norm(c.to_world[:3, 2]) for c in cameras], dtype=np.float64)
    size = 1.0 + float(np.abs(centres).max())
    spread = float(np.abs(centres - centres[0]).max())
    turn = float(np.arccos(np.clip((forwards @ forwards[0]).min(), -1.0, 1.0)))
    if spread <= 1e-6 * size and turn <= 1e-3:
        centre = ", ".join(f"{v:.4g}" for v in centres[0])
        raise InputError(path, f"all {len(cameras)} cameras share one pose (centre {centre}, the same view "
                               "direction): the capture shows the object from one viewpoint only, with nothing to "
                               "fit a shape from; check how its poses were made")


def check_unique(path: Path, what: str, values) -> None:
    """Entries that must be listed once (image names, camera ids)."""
    twice = [v for v, n in Counter(values).items() if n > 1]
    if twice:
        raise InputError(path, f"{what} {twice[0]} is listed {Counter(values)[twice[0]]} times"
                               + (f" (and {len(twice) - 1} more {what}s twice)" if len(twice) > 1 else "")
                               + ": each may appear once")


def collect(problems: list[InputError], check: Callable, *args) -> None:
    """Run one check, adding its InputError to `problems` instead of raising it."""
    try:
        check(*args)
    except InputError as exc:
        problems.append(exc)
