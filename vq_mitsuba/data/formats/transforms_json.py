"""What NeRF-synthetic and nerfstudio transforms jsons share: reading the json, its frames
(`file_path`, `transform_matrix`: camera-to-world in OpenGL axes), their names and image files,
and the mesh.ply beside the json. Which of the two a json is: `is_nerfstudio`.
"""

from __future__ import annotations

import json
import posixpath
from pathlib import Path

import numpy as np

from vq_mitsuba.data.checks import check_pose
from vq_mitsuba.data.formats.common import IMAGE_EXTS, load_mesh
from vq_mitsuba.data.lens import DISTORTION
from vq_mitsuba.errors import InputError

INTRINSIC_KEYS = ("fl_x", "fl_y", "cx", "cy", "camera_model") + DISTORTION


def is_nerfstudio(data: dict) -> bool:
    """Whether a transforms json gives pixel intrinsics (nerfstudio style) rather than NeRF-synthetic's
    camera_angle_x alone."""
    frames = data.get("frames") if isinstance(data.get("frames"), list) else []
    return any(k in data for k in INTRINSIC_KEYS) or any(
        isinstance(f, dict) and any(k in f for k in INTRINSIC_KEYS) for f in frames)


def nerfstudio_style(path: Path) -> bool:
    """Whether the json at `path` gives pixel intrinsics (`is_nerfstudio`); False for a file that is
    no json object (the NeRF-synthetic loader then says what is wrong with it)."""
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except Exception:  # any unreadable file is reported by the loader
        return False
    return isinstance(data, dict) and is_nerfstudio(data)


class _KeyTwice(Exception):
    """A json object that gives one key twice (json.loads would keep the last value)."""


def _once_each(pairs: list[tuple[str, object]]) -> dict:
    seen = {}
    for key, value in pairs:
        if key in seen:
            raise _KeyTwice(key)
        seen[key] = value
    return seen


def read_json(path: Path) -> dict:
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(path, f"cannot read json file ({exc})") from exc
    try:
        data = json.loads(text, object_pairs_hook=_once_each)
    except json.JSONDecodeError as exc:
        raise InputError(path, f"malformed json at line {exc.lineno}, column {exc.colno}: {exc.msg}") from exc
    except RecursionError:  # [[[[... deeper than the parser goes
        raise InputError(path, "malformed json: lists or objects nested too deep") from None
    except _KeyTwice as exc:
        raise InputError(path, f"malformed json: '{exc.args[0]}' is given twice in one object (which value is "
                               "meant?); each key may appear once") from None
    if not isinstance(data, dict):
        raise InputError(path, "malformed capture json: the top level must be an object")
    return data


def json_frames(path: Path, data: dict) -> list[dict]:
    frames = data.get("frames")
    if not isinstance(frames, list) or not frames:
        raise InputError(path, "no cameras: 'frames' is missing or empty")
    for i, frame in enumerate(frames):
        if not isinstance(frame, dict):
            raise InputError(path, f"frames[{i}] is not an object")
        if not isinstance(frame.get("file_path"), str) or not frame["file_path"]:
            raise InputError(path, f"frames[{i}] has no 'file_path'")
        if "transform_matrix" not in frame:
            raise InputError(path, f"frames[{i}] ({frame['file_path']}) has no 'transform_matrix'")
    first: dict[str, int] = {}
    for i, frame in enumerate(frames):  # one image counted twice would weigh twice in the fit
        key = frame_key(frame["file_path"])
        if key in first:
            raise InputError(path, f"frames[{i}] ({frame['file_path']}) lists the image of frames[{first[key]}] "
                                   f"({frames[first[key]]['file_path']}) again: each image may appear once")
        first[key] = i
    return frames


def frame_key(file_path: str) -> str:
    """A frame's image as a relative path spelled one way, without its image suffix (the frames
    "./a/../b/r_0" and "b/r_0.png" name one image)."""
    path = posixpath.normpath(file_path.replace("\\", "/"))
    return path[: -len(Path(path).suffix)] if Path(path).suffix.lower() in IMAGE_EXTS else path


def frame_matrices(path: Path, frames: list[dict]) -> list[np.ndarray]:
    out = []
    for i, frame in enumerate(frames):
        try:
            m = np.array(frame["transform_matrix"], dtype=np.float64)
        except (TypeError, ValueError, OverflowError):  # OverflowError: an integer beyond any float
            m = None
        if m is None or m.shape != (4, 4) or not np.all(np.isfinite(m)):
            raise InputError(path, f"frames[{i}] ({frame['file_path']}): malformed transform_matrix "
                                   "(expected 4x4 finite numbers)")
        if abs(np.linalg.det(m[:3, :3])) < 1e-12:
            raise InputError(path, f"frames[{i}] ({frame['file_path']}): degenerate transform_matrix")
        check_pose(path, f"frames[{i}] ({frame['file_path']})", m)
        out.append(m)
    return out


def frame_names(frames: list[dict]) -> list[str]:
    """The frames' names: their image file names without the image suffix, or, where two of these
    agree (train/r_0 and test/r_0), the relative paths (made file names by `named_views`)."""
    paths = [frame_key(f["file_path"]) for f in frames]
    stems = [posixpath.basename(p) for p in paths]
    return stems if len(set(stems)) == len(stems) else paths


def frame_image_candidates(path: Path, frame: dict) -> list[Path]:
    p = path.parent / frame["file_path"]
    if p.suffix.lower() in IMAGE_EXTS:
        return [p]
    return [p.parent / (p.name + ".exr"), p.parent / (p.name + ".png")]


def frame_image(path: Path, i: int, frame: dict) -> Path:
    candidates = frame_image_candidates(path, frame)
    for c in candidates:
        if c.is_file():
            return c
    expected = " or ".join(str(c) for c in candidates)
    raise InputError(candidates[0], f"image not found for frames[{i}] of {path.name} (expected {expected})")


def json_mesh(path: Path, mesh_arg: str | Path | None):
    if mesh_arg is not None:
        return load_mesh(mesh_arg)
    if (path.parent / "mesh.ply").exists():
        return load_mesh(path.parent / "mesh.ply")
    return None
