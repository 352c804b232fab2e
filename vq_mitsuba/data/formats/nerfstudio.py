"""nerfstudio / instant-ngp / Polycam / Record3D `transforms.json`: a NeRF-synthetic json whose
intrinsics are pixels rather than a field of view, given at the top level or per frame (a frame's
own key wins): `fl_x`, `fl_y`, `cx`, `cy`, `w`, `h`, the distortion `k1`..`k4`, `p1`, `p2` and
`camera_model` (PINHOLE or OPENCV: perspective, k1..k4 on r^2..r^8 plus p1, p2, as nerfstudio reads
them; OPENCV_FISHEYE: k1..k4 on the angle). A frame's `mask_path` names a mask multiplied into its
alpha. `applied_transform` (nerfstudio's record of the transform it applied to COLMAP's poses) is
checked and otherwise left alone: the frames' `transform_matrix` are already in the json's world,
and the run works in that world.

Cameras are OpenGL (as NeRF-synthetic); the world is taken as nerfstudio's own, Z up ("blender"),
so that a relighting envmap in Blender's convention lights it as Blender would. When the cameras'
mean up vector is far from +Z (a capture not oriented by nerfstudio), the envmap's frame follows
the cameras' mean up instead, as for COLMAP captures.

    transforms.json    frames: file_path, transform_matrix (camera-to-world, OpenGL axes), optional
                       mask_path and per-frame intrinsics; intrinsics at the top level
    images/0001.jpg    the frames' photos (any folder the file_paths name), one size after undistortion
    masks/0001.png     the masks the frames' mask_path name (optional, all frames or none)
    mesh.ply           known geometry (optional), in the json's world
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Callable

import numpy as np

from vq_mitsuba.data.cameras import BLENDER_ENV_TO_WORLD, OPENGL_TO_MITSUBA, Camera, camera_from_intrinsics
from vq_mitsuba.data.checks import check_size, finite_number
from vq_mitsuba.data.formats.common import Capture, mesh_beside, has_suffix, moved_camera, read_views, up_frame
from vq_mitsuba.data.formats.transforms_json import (frame_image, frame_matrices, frame_names, json_frames,
                                                     json_mesh, nerfstudio_style, read_json)
from vq_mitsuba.data.imageio import write_png, written
from vq_mitsuba.data.lens import DISTORTION, FISHEYE, Lens, check_lens, distort_rgba
from vq_mitsuba.errors import InputError, raise_all

KIND = "json"
SUFFIXES = (".json",)
FOLDER_FILES = ("transforms.json",)
DESCRIPTION = "a nerfstudio transforms.json"  # what a person gives, in messages and help
POSED = True
points = sphere = None  # no sparse points, no region of interest
has_geometry = mesh_beside  # known geometry: a mesh.ply in the capture's folder
CAMERA_MODELS = ("PINHOLE", "OPENCV", FISHEYE)
UP_COS = math.cos(math.radians(45.0))  # mean camera up within this of +Z: Blender's envmap frame


def detect(source: Path) -> bool:
    return has_suffix(source, SUFFIXES) and nerfstudio_style(source)


def cameras(path: Path) -> tuple[list[Camera], str]:
    """(the frames' pinhole cameras, "blender")."""
    data = read_json(path)
    frames = json_frames(path, data)
    return _cameras_and_lenses(path, data, frames)[0], "blender"


def load(path: Path, mesh_arg, shrink=None, cache_dir=None) -> Capture:
    """The capture: distorted photos undistorted (and cached), masks multiplied into alpha, each
    photo shrunk as it is read."""
    data = read_json(path)
    frames = json_frames(path, data)
    cameras, lenses = _cameras_and_lenses(path, data, frames)
    masks = mask_paths(path, frames)
    problems, paths = [], []
    for i, frame in enumerate(frames):
        try:
            paths.append(frame_image(path, i, frame))
        except InputError as exc:
            problems.append(exc)
    raise_all(problems, path)
    images, alpha, has_alpha = read_views(path, cameras, paths, masks, lenses, cache_dir, shrink)
    return Capture(path, cameras, images, alpha, has_alpha, json_mesh(path, mesh_arg), None, envmap_frame(cameras),
                   "blender")


def _cameras_and_lenses(path: Path, data: dict, frames: list[dict]):
    """(cameras, lenses) of the json's frames."""
    return nerfstudio_cameras(path, data, frames, frame_matrices(path, frames), frame_names(frames),
                              lambda i: frame_image(path, i, frames[i]))


def _angle(path: Path, entry: str, name: str, value) -> float:
    if not finite_number(value) or not 0 < value < math.pi:
        raise InputError(path, f"{entry}: '{name}' must be a number of radians in (0, pi), got {value!r}")
    return float(value)


def frame_lens(path: Path, data: dict, i: int, frame: dict, size_of: Callable[[], tuple[int, int]]) -> Lens:
    """The lens of frames[i], each key the frame's own or else the top level's, checked.
    `size_of()` gives the image's (width, height) when 'w' / 'h' are not given."""
    entry = f"frames[{i}] ({frame['file_path']})"

    def get(key, default=None):
        return frame[key] if key in frame else data.get(key, default)

    model = get("camera_model", "OPENCV")
    if model not in CAMERA_MODELS:
        raise InputError(path, f"{entry}: camera_model {model!r} is not supported (use {', '.join(CAMERA_MODELS)})")
    w, h = get("w"), get("h")
    if w is None or h is None:
        w, h = size_of()
    check_size(path, f"{entry}: 'w' and 'h'", w, h)
    w, h = int(w), int(h)
    fx, fy = get("fl_x"), get("fl_y")
    if fx is None:
        if get("camera_angle_x") is None:
            raise InputError(path, f"{entry}: no focal length: 'fl_x' is missing (in the frame and at the top level)")
        fx = 0.5 * w / math.tan(0.5 * _angle(path, entry, "camera_angle_x", get("camera_angle_x")))
    if fy is None:
        angle_y = get("camera_angle_y")
        fy = fx if angle_y is None else 0.5 * h / math.tan(0.5 * _angle(path, entry, "camera_angle_y", angle_y))
    values = {"fl_x": fx, "fl_y": fy, "cx": get("cx", 0.5 * w), "cy": get("cy", 0.5 * h),
              **{k: get(k, 0.0) for k in DISTORTION}}
    for name, value in values.items():
        if not finite_number(value):
            raise InputError(path, f"{entry}: '{name}' = {value!r} is not a finite number")
    lens = Lens(model, w, h, float(values["fl_x"]), float(values["fl_y"]), float(values["cx"]), float(values["cy"]),
                **{k: float(values[k]) for k in DISTORTION})
    if model == FISHEYE:
        lens.p1 = lens.p2 = 0.0  # the fisheye model has no tangential terms
    check_lens(path, entry, lens)
    return lens


def check_applied_transform(path: Path, data: dict) -> None:
    """'applied_transform', when given: a 3x4 or 4x4 matrix of finite numbers."""
    if "applied_transform" not in data:
        return
    try:
        m = np.array(data["applied_transform"], dtype=np.float64)
    except (TypeError, ValueError, OverflowError):
        m = None
    if m is None or m.shape not in ((3, 4), (4, 4)) or not np.all(np.isfinite(m)):
        raise InputError(path, "'applied_transform' must be a 3x4 or 4x4 matrix of finite numbers")


def nerfstudio_cameras(path: Path, data: dict, frames: list[dict], matrices: list[np.ndarray], names: list[str],
                       image_of: Callable[[int], Path]) -> tuple[list[Camera], list[Lens]]:
    """The pinhole cameras (Mitsuba convention) and lenses of the frames; `image_of(i)` is frame i's
    image file (read for its size only when 'w' / 'h' are missing). All problems at once."""
    from vq_mitsuba.data.imageio import image_size

    check_applied_transform(path, data)
    cameras, lenses, problems = [], [], []
    for i, (frame, matrix, name) in enumerate(zip(frames, matrices, names)):
        try:
            lens = frame_lens(path, data, i, frame, lambda: image_size(image_of(i)))
        except InputError as exc:
            problems.append(exc)
            continue
        lenses.append(lens)
        cameras.append(camera_from_intrinsics(name, matrix @ OPENGL_TO_MITSUBA, lens.fx, lens.fy, lens.cx, lens.cy,
                                              lens.width, lens.height))
    raise_all(problems, path)
    return cameras, lenses


def mask_paths(path: Path, frames: list[dict]) -> list[Path | None]:
    """Each frame's mask file (its 'mask_path'), or None for every frame when none has one."""
    given = [i for i, f in enumerate(frames) if "mask_path" in f]
    for i in given:
        if not isinstance(frames[i]["mask_path"], str) or not frames[i]["mask_path"]:
            raise InputError(path, f"frames[{i}] ({frames[i]['file_path']}): 'mask_path' must be a file path")
    if given and len(given) < len(frames):
        lacking = next(i for i in range(len(frames)) if i not in set(given))
        raise InputError(path, f"frames[{lacking}] ({frames[lacking]['file_path']}) has no 'mask_path' but "
                               f"frames[{given[0]}] has one: give every frame a mask or none")
    return [path.parent / f["mask_path"] for f in frames] if given else [None] * len(frames)


def envmap_frame(cameras: list[Camera]) -> np.ndarray:
    """(4, 4) envmap-to-world: Blender's when the cameras' mean up is near +Z, else along that up."""
    up = np.mean([c.to_world[:3, 1] for c in cameras], 0)
    norm = float(np.linalg.norm(up))
    if norm > 1e-6 and up[2] / norm >= UP_COS:
        return BLENDER_ENV_TO_WORLD.copy()
    return up_frame(cameras)


def write_transforms_json(path: Path, cameras: list[Camera], files: list[str], lenses: list[Lens],
                          masks: list[str] | None = None, applied_transform: np.ndarray | None = None) -> None:
    """A nerfstudio transforms.json with per-frame intrinsics and distortion (for test data):
    `files` / `masks` are the frames' file_path / mask_path, relative to the json's folder."""
    import json

    frames = []
    for i, (cam, name, lens) in enumerate(zip(cameras, files, lenses)):
        frame = {"file_path": name, "transform_matrix": (cam.to_world @ OPENGL_TO_MITSUBA).tolist(),
                 "camera_model": lens.model, "fl_x": lens.fx, "fl_y": lens.fy, "cx": lens.cx, "cy": lens.cy,
                 "w": lens.width, "h": lens.height, **{k: getattr(lens, k) for k in DISTORTION}}
        if masks is not None:
            frame["mask_path"] = masks[i]
        frames.append(frame)
    data = {"camera_model": lenses[0].model if lenses else "OPENCV", "frames": frames}
    if applied_transform is not None:
        data["applied_transform"] = np.asarray(applied_transform, np.float64)[:3, :4].tolist()
    written(path, lambda: Path(path).write_text(json.dumps(data, indent=1)))


def write_capture(capture: Capture, folder: Path, names: list[str], sim: np.ndarray, lenses: list[Lens],
                  distort: bool) -> Path:
    """`capture`'s views as a nerfstudio folder in the frame of the similarity `sim` (world -> its
    world): images/NAME.png seen through `lenses` when `distort`, masks/NAME.png, transforms.json
    with per-frame intrinsics and the similarity as its applied_transform."""
    for i, name in enumerate(names):
        rgb, alpha = distort_rgba(capture.images[i], capture.alpha[i], lenses[i] if distort else None)
        write_png(folder / "images" / f"{name}.png", np.clip(rgb, 0, None))
        write_png(folder / "masks" / f"{name}.png", alpha, srgb=False)
    write_transforms_json(folder / "transforms.json", [moved_camera(c, sim) for c in capture.cameras],
                          [f"images/{n}.png" for n in names], lenses, [f"masks/{n}.png" for n in names],
                          applied_transform=sim)
    return folder
