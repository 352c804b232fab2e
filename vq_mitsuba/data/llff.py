"""LLFF's `poses_bounds.npy` (LLFF's forward-facing and 360 captures, NeRD's real objects), read
into Mitsuba-convention camera matrices, checked, and written (for test data).

The file is an (N, 17) array, one row per image in sorted file-name order: a 3x5 matrix flattened
row by row, [R | t | hwf], then the near and far depth bounds. R's columns are the camera's down,
right and back axes in world coordinates, t its position; hwf = (height, width, focal) in pixels of
the images the poses were made for, the principal point at the image centre. A Mitsuba camera's
axes are (left, up, forward) = (-right, -down, -back); OpenGL's are (right, up, back).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from vq_mitsuba.data.checks import check_pose, check_size, collect, finite_number
from vq_mitsuba.errors import InputError, raise_all

COLUMNS = 17  # 3x5 pose [R | t | hwf] row by row, near, far


def llff_to_world(pose: np.ndarray) -> np.ndarray:
    """(4, 4) Mitsuba camera-to-world of one (3, 5) LLFF pose."""
    pose = np.asarray(pose, np.float64)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = -pose[:, 1], -pose[:, 0], -pose[:, 2], pose[:, 3]
    return m


def world_to_llff(to_world: np.ndarray, height: float, width: float, focal: float) -> np.ndarray:
    """Inverse of `llff_to_world`: the (3, 5) LLFF pose [down, right, back, t, hwf] of a Mitsuba camera."""
    m = np.asarray(to_world, np.float64)
    return np.stack([-m[:3, 1], -m[:3, 0], -m[:3, 2], m[:3, 3], [height, width, focal]], 1)


def read_poses_bounds(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(poses (N, 3, 5), bounds (N, 2)) of a poses_bounds.npy, every row checked (all problems at once)."""
    try:
        raw = np.load(path, allow_pickle=False)
    except ValueError as exc:
        if "allow_pickle" in str(exc):
            raise InputError(path, "is an array of Python objects (a pickle), which is never loaded: save it as "
                                   "an array of numbers") from None
        raise InputError(path, f"cannot read ({exc})") from None
    except Exception as exc:  # numpy and OS errors differ
        raise InputError(path, f"cannot read ({type(exc).__name__}: {exc})") from None
    if not isinstance(raw, np.ndarray):
        raw.close()
        raise InputError(path, "is an .npz archive; poses_bounds.npy is one N x 17 array")
    if raw.dtype.kind not in "biuf":
        raise InputError(path, f"holds {raw.dtype} values, not numbers")
    if raw.ndim != 2 or raw.shape[1] != COLUMNS or raw.shape[0] == 0:
        raise InputError(path, f"has shape {raw.shape}; expected N x {COLUMNS} (one row per image: a 3x5 pose "
                               "[R | t | height, width, focal] row by row, then near and far)")
    rows = raw.astype(np.float64)
    problems: list[InputError] = []
    for i, row in enumerate(rows):
        collect(problems, _check_row, path, i, row)
    raise_all(problems, path)
    return rows[:, :15].reshape(-1, 3, 5), rows[:, 15:]


def _check_row(path: Path, i: int, row: np.ndarray) -> None:
    entry = f"row {i}"
    if not np.all(np.isfinite(row)):
        raise InputError(path, f"{entry} holds non-finite values")
    pose = row[:15].reshape(3, 5)
    h, w, f = pose[:, 4]
    check_size(path, f"{entry} (height, width)", float(w), float(h))
    if not (finite_number(float(f)) and f > 0):
        raise InputError(path, f"{entry}: focal length {f:g} must be positive")
    near, far = row[15:]
    if not 0 <= near <= far or far <= 0:
        raise InputError(path, f"{entry}: bounds near = {near:g}, far = {far:g} (need 0 <= near <= far, far > 0)")
    check_pose(path, entry, llff_to_world(pose))


def write_poses_bounds(path: Path, cameras, bounds) -> None:
    """poses_bounds.npy of centred cameras with one focal length (fx = fy), the bounds (N, 2)."""
    rows = []
    for cam, (near, far) in zip(cameras, bounds):
        fx, fy, cx, cy = cam.intrinsics()
        if abs(fy - fx) > 1e-6 * fx or abs(cx - cam.width / 2) > 1e-6 or abs(cy - cam.height / 2) > 1e-6:
            raise ValueError(f"camera {cam.name}: LLFF holds centred cameras with one focal length")
        pose = world_to_llff(cam.to_world, cam.height, cam.width, fx)
        rows.append(np.concatenate([pose.ravel(), [near, far]]))
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    np.save(path, np.asarray(rows, np.float64))
