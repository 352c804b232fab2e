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

from vq_mitsuba.data.cameras import Camera, camera_from_intrinsics
from vq_mitsuba.data.checks import check_intrinsics, check_pose, check_size, collect, finite_number
from vq_mitsuba.data.formats.common import (Capture, mesh_beside, common_image_size, has_suffix, images_in, known_mesh,
                                            missing_numbered, moved_camera, numpy_file_kind, paired_masks,
                                            read_views, up_frame)
from vq_mitsuba.data.imageio import write_png, written
from vq_mitsuba.errors import InputError, raise_all

KIND = "llff"
SUFFIXES = (".npy",)
FOLDER_FILES = ("poses_bounds.npy",)
DESCRIPTION = "an LLFF poses_bounds.npy"  # what a person gives, in messages and help
POSED = True
points = sphere = None  # no sparse points, no region of interest
has_geometry = mesh_beside  # known geometry: a mesh.ply in the capture's folder
COLUMNS = 17  # 3x5 pose [R | t | hwf] row by row, near, far


def detect(source: Path) -> bool:
    return has_suffix(source, SUFFIXES)


def cameras(npy: Path) -> tuple[list[Camera], str]:
    """(the views' pinhole cameras, "mitsuba"); the first photo is read for its size."""
    return _llff_views(npy)[0], "mitsuba"


def load(npy: Path, mesh_arg, shrink=None, cache_dir=None) -> Capture:
    """The capture: the photos, masks multiplied into alpha, each shrunk as it is read; the
    envmap's up is the cameras' mean up."""
    cameras, paths, masks = _llff_views(npy)
    images, alpha, has_alpha = read_views(npy, cameras, paths, masks, [None] * len(paths), cache_dir, shrink)
    return Capture(npy, cameras, images, alpha, has_alpha, known_mesh(mesh_arg, npy.parent), None, up_frame(cameras),
                   "mitsuba")


def _llff_images(folder: Path) -> tuple[Path, list[Path]]:
    """LLFF's photos: images/, else the least reduced images_N/ there is."""
    reduced = sorted((p for p in folder.glob("images_*") if p.is_dir() and p.name[7:].isdigit()),
                     key=lambda p: int(p.name[7:]))
    for image_dir in [folder / "images"] + reduced:
        if images_in(image_dir):
            return image_dir, images_in(image_dir)
    raise InputError(folder / "images", "no images (an LLFF capture keeps its photos in images/, in the order "
                                        "of poses_bounds.npy's rows)")


def _llff_views(npy: Path) -> tuple[list[Camera], list[Path], list[Path | None]]:
    """The views of an LLFF folder. The focal length scales with the photos' size when it differs
    from the one poses_bounds.npy gives (as LLFF's loader does for images_N/)."""
    folder = npy.parent
    image_dir, images = _llff_images(folder)
    poses, _ = read_poses_bounds(npy)
    paired_masks(image_dir, images, folder / "masks", images_in(folder / "masks"))  # names a missing photo
    if len(poses) != len(images):
        what = f"holds {len(poses)} poses for {len(images)} images in {image_dir.name}/"
        missing = missing_numbered(images, len(poses)) if len(poses) > len(images) else None
        if missing is not None:
            raise InputError(missing, f"image missing: {npy.name} {what}")
        raise InputError(npy, what + (" (one row per photo: an image missing?)" if len(poses) > len(images) else ""))
    width, height = common_image_size(images)
    cameras, problems = [], []
    for i, (pose, path) in enumerate(zip(poses, images)):
        h, w, f = pose[:, 4]
        sx, sy = width / w, height / h
        if abs(sx - sy) > 0.01 * max(sx, sy):
            problems.append(InputError(npy, f"row {i} ({path.name}): the photos are {width}x{height} but the pose is "
                                            f"for {w:g}x{h:g} images, another aspect ratio"))
            continue
        entry = f"row {i} ({path.name})"
        collect(problems, check_intrinsics, npy, entry, f * sx, f * sy, width / 2, height / 2, width, height)
        cameras.append(camera_from_intrinsics(path.stem, llff_to_world(pose), f * sx, f * sy, width / 2, height / 2,
                                              width, height))
    raise_all(problems, npy)
    masks: list[Path | None] = [None] * len(images)
    if (folder / "masks").is_dir():
        found = {p.stem: p for p in images_in(folder / "masks")}
        if len(found) != len(images):
            raise InputError(folder / "masks", f"holds {len(found)} masks for {len(images)} images in "
                                               f"{image_dir.name}/ (one per photo, the same file name stem)")
        missing = [p.name for p in images if p.stem not in found]
        if missing:
            raise InputError(folder / "masks", f"has no mask for {missing[0]} (masks/{Path(missing[0]).stem}.png)")
        masks = [found[p.stem] for p in images]
    return cameras, images, masks


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
    if numpy_file_kind(path, "npy") == "pickle":
        raise InputError(path, "is a Python pickle, which is never loaded: save the poses as an array of numbers")
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
    written(path, lambda: np.save(path, np.asarray(rows, np.float64)))


def llff_window(camera) -> tuple[int, int, int, int]:
    """(x0, y0, x1, y1): the crop of a view whose principal point is its centre (LLFF's cameras are
    centred); the principal point must lie a whole number of half pixels off the image centre."""
    _, _, cx, cy = camera.intrinsics()
    bounds = []
    for c, side in ((cx, camera.width), (cy, camera.height)):
        twice = 2.0 * c - side
        n = round(twice)
        if abs(twice - n) > 1e-6:
            raise ValueError(f"camera {camera.name}: the principal point is not a whole number of half pixels "
                             "off the centre; an LLFF copy cannot centre it by cropping")
        bounds.append((n, side) if n > 0 else (0, side + n))
    (x0, x1), (y0, y1) = bounds
    return x0, y0, x1, y1


def write_capture(capture: Capture, folder: Path, names: list[str], sim: np.ndarray, centre: np.ndarray,
                  radius: float) -> Path:
    """`capture`'s views as an LLFF folder in the frame of the similarity `sim` (world -> its
    world): images/NAME.png and masks/NAME.png cropped to centre their principal point
    (`llff_window`), poses_bounds.npy with bounds from the sphere (centre, radius) that holds
    the object."""
    scale = float(np.cbrt(np.linalg.det(sim[:3, :3])))
    cameras, bounds = [], []
    for i, (cam, name) in enumerate(zip(capture.cameras, names)):
        x0, y0, x1, y1 = llff_window(cam)
        fx, fy, cx, cy = cam.intrinsics()
        cameras.append(moved_camera(camera_from_intrinsics(cam.name, cam.to_world, fx, fy, cx - x0, cy - y0, x1 - x0,
                                                           y1 - y0), sim))
        distance = float(np.linalg.norm(cam.origin - centre))
        bounds.append((scale * max(distance - radius, 0.05 * distance), scale * (distance + radius)))
        write_png(folder / "images" / f"{name}.png", np.clip(capture.images[i, y0:y1, x0:x1], 0, None))
        write_png(folder / "masks" / f"{name}.png", capture.alpha[i, y0:y1, x0:x1], srgb=False)
    write_poses_bounds(folder / "poses_bounds.npy", cameras, bounds)
    return folder
