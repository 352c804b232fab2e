"""NeRF-synthetic `transforms_*.json`: a horizontal field of view and one camera-to-world matrix
per frame (OpenGL camera axes), in Blender's world (Z up).

    transforms_train.json  camera_angle_x (radians), frames: file_path (the image, its suffix
    transforms_test.json   optional), transform_matrix (4x4 camera-to-world); optional 'w', 'h'
    train/r_0.png          the frames' images (.png or .exr), one size for all, alpha optional
    mesh.ply               known geometry (optional), in the json's world

A transforms json with pixel intrinsics is nerfstudio's (vq_mitsuba.data.formats.nerfstudio).
`write_capture` writes the synthetic scenes' transforms json (vq_mitsuba.synthetic.mitsuba_scenes).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from vq_mitsuba.data.cameras import BLENDER_ENV_TO_WORLD, Camera, camera_to_nerf, nerf_to_camera
from vq_mitsuba.data.checks import MAX_FOV_DEG, MIN_FOV_DEG, check_camera, check_size, finite_number
from vq_mitsuba.data.formats.common import Capture, mesh_beside, has_suffix, shrunk_entry, stack_images
from vq_mitsuba.data.formats.transforms_json import (frame_image, frame_image_candidates, frame_matrices, frame_names,
                                                     json_frames, json_mesh, nerfstudio_style, read_json)
from vq_mitsuba.data.imageio import read_image, written
from vq_mitsuba.data.resize import Shrink
from vq_mitsuba.errors import InputError, raise_all

KIND = "json"
SUFFIXES = (".json",)
SPLIT_FILE = "transforms_{}.json"  # a split's cameras: transforms_train.json, transforms_test.json
FOLDER_FILES = (SPLIT_FILE.format("train"), "transforms.json")  # the file a capture folder holds, in this order
DESCRIPTION = "a NeRF-synthetic transforms_train.json (or transforms_*.json)"  # what a person gives, in messages and help
POSED = True
points = sphere = None  # no sparse points, no region of interest
has_geometry = mesh_beside  # known geometry: a mesh.ply in the capture's folder


def detect(source: Path) -> bool:
    return has_suffix(source, SUFFIXES) and not nerfstudio_style(source)


def cameras(path: Path) -> tuple[list[Camera], str]:
    """(the frames' cameras, "blender"); the image size from 'w' / 'h', else the first image."""
    data = read_json(path)
    frames = json_frames(path, data)
    angle = _json_angle(path, data)
    width, height = _json_image_size(path, data, frames)
    return _json_cameras(path, frames, frame_matrices(path, frames), angle, width, height), "blender"


def load(path: Path, mesh_arg: str | Path | None, shrink: Shrink | None = None, cache_dir=None) -> Capture:
    """The capture: the frames' cameras and images (one size, each shrunk as it is read), the mesh."""
    shrink = shrink or Shrink()
    data = read_json(path)
    frames = json_frames(path, data)
    angle = _json_angle(path, data)
    matrices = frame_matrices(path, frames)

    entries, first, problems = [], None, []
    for i, frame in enumerate(frames):
        try:
            img_path = frame_image(path, i, frame)
            rgb, alpha = read_image(img_path)
            h, w = rgb.shape[:2]
            if first is None:
                first = (img_path, w, h)
            elif (w, h) != first[1:]:
                raise InputError(img_path, f"image size {w}x{h} differs from {first[0].name} "
                                           f"({first[1]}x{first[2]}); all frames must share one size")
            entries.append(shrunk_entry(shrink, img_path, rgb, alpha))
            del rgb, alpha  # the full-size photo goes before the next one is read
        except InputError as exc:
            problems.append(exc)
    raise_all(problems, path)
    images, alpha, has_alpha = stack_images(entries)
    width, height = first[1], first[2]
    cameras = _json_cameras(path, frames, matrices, angle, width, height)
    return Capture(path, cameras, images, alpha, has_alpha, json_mesh(path, mesh_arg), None,
                   BLENDER_ENV_TO_WORLD.copy(), "blender")


def _json_angle(path: Path, data: dict) -> float:
    if "camera_angle_x" not in data:
        raise InputError(path, "missing 'camera_angle_x' (horizontal field of view in radians; or nerfstudio's "
                               "'fl_x' / 'fl_y' focal lengths in pixels)")
    angle = data["camera_angle_x"]
    if not finite_number(angle) or not (MIN_FOV_DEG <= math.degrees(angle) <= MAX_FOV_DEG):
        raise InputError(path, f"'camera_angle_x' must be a number of radians in (0, pi) (a field of view of "
                               f"{MIN_FOV_DEG:g}..{MAX_FOV_DEG:g} degrees), got {angle!r}")
    return float(angle)


def _json_cameras(path: Path, frames: list[dict], matrices: list[np.ndarray], angle: float, width: int,
                  height: int) -> list[Camera]:
    """The frames' cameras, each checked (vq_mitsuba.data.checks)."""
    cameras = []
    for i, (name, matrix) in enumerate(zip(frame_names(frames), matrices)):
        cameras.append(nerf_to_camera(name, matrix, angle, width, height))
        check_camera(path, f"frames[{i}] ({frames[i]['file_path']})", cameras[-1])
    return cameras


def _json_image_size(path: Path, data: dict, frames: list[dict]) -> tuple[int, int]:
    """(width, height) for cameras-only loading: 'w'/'h' keys, else the first image found."""
    w, h = data.get("w"), data.get("h")
    if w is not None and h is not None:
        check_size(path, "'w' and 'h'", w, h)
        return int(w), int(h)
    for frame in frames:
        for c in frame_image_candidates(path, frame):
            if c.is_file():
                rgb, _ = read_image(c)
                return int(rgb.shape[1]), int(rgb.shape[0])
    raise InputError(path, "cannot tell the image size: no 'w'/'h' keys and no frame image exists")


def write_capture(path: Path, cameras: list[Camera], files: list[str], fov_x_deg: float) -> None:
    """A transforms json of `cameras` (Mitsuba camera axes, Blender world), frame i's file_path
    files[i]; camera_angle_x is the cameras' field of view (they share one), fov_x_deg without cameras."""
    frames = []
    angle = None
    for cam, file in zip(cameras, files):
        m, angle = camera_to_nerf(cam)
        frames.append({"file_path": file, "transform_matrix": m.tolist()})
    data = {"camera_angle_x": angle if angle is not None else math.radians(fov_x_deg), "frames": frames}
    written(path, lambda: path.write_text(json.dumps(data, indent=2)))
