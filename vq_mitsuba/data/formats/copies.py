"""A rendered capture written again in the formats photographed captures come in: NeuS/IDR
(`cameras_sphere.npz`, `image/`, `mask/`), COLMAP (`sparse/0`, `images/`, `masks/`), nerfstudio
(`transforms.json` with per-frame intrinsics and OPENCV distortion, `images/`, `masks/`) and LLFF
(`poses_bounds.npy`, `images/`, `masks/`). All but NeuS/IDR lie in another similarity frame (scale,
rotation, offset; `format_frames`), and COLMAP and nerfstudio optionally through distorting lenses.
Each format's own `write_capture` writes its copy. Used by `make-scene --photo-formats` and the
round-trip tests."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from vq_mitsuba.data.cameras import MITSUBA_TO_BLENDER
from vq_mitsuba.data.formats import colmap, idr, llff, nerfstudio
from vq_mitsuba.data.formats.common import Capture
from vq_mitsuba.data.imageio import written
from vq_mitsuba.data.lens import Lens

# The COLMAP copy's world: x_colmap = SCALE * ROTATION @ x + OFFSET (an arbitrary similarity, as
# COLMAP's gauge is arbitrary).
COLMAP_SCALE = 3.7
COLMAP_OFFSET = np.array([1.5, -0.4, 2.25])
OPENCV_DISTORTION = {"k1": -0.08, "k2": 0.02, "p1": 0.002, "p2": -0.001}
# The nerfstudio copy's world: Z up, as nerfstudio orients its captures, scaled and moved.
NERFSTUDIO_SCALE = 0.8
NERFSTUDIO_OFFSET = np.array([0.3, -0.2, 0.1])


def colmap_similarity() -> np.ndarray:
    """(4, 4) world -> COLMAP-world similarity of the written copy."""
    a, b = math.radians(30.0), math.radians(-20.0)
    rz = np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])
    rx = np.array([[1, 0, 0], [0, math.cos(b), -math.sin(b)], [0, math.sin(b), math.cos(b)]])
    m = np.eye(4)
    m[:3, :3] = COLMAP_SCALE * rz @ rx
    m[:3, 3] = COLMAP_OFFSET
    return m


def nerfstudio_similarity() -> np.ndarray:
    """(4, 4) world -> nerfstudio-world similarity of the written copy (Y up becomes Z up)."""
    m = np.eye(4)
    m[:3, :3] = NERFSTUDIO_SCALE * MITSUBA_TO_BLENDER
    m[:3, 3] = NERFSTUDIO_OFFSET
    return m


def format_frames() -> dict[str, np.ndarray]:
    """Each copy's (4, 4) similarity from the capture's world to its own, by folder name."""
    sim = colmap_similarity()
    return {"neus": np.eye(4), "colmap": sim, "colmap_opencv": sim, "nerfstudio": nerfstudio_similarity(),
            "llff": sim}


def opencv_lens(camera) -> Lens:
    fx, fy, cx, cy = camera.intrinsics()
    return Lens("OPENCV", camera.width, camera.height, fx, fy, cx, cy, **OPENCV_DISTORTION)


def nerfstudio_lens(camera, index: int) -> Lens:
    """The nerfstudio copy's lens of view `index`: OPENCV, k1 varying from view to view."""
    fx, fy, cx, cy = camera.intrinsics()
    distortion = dict(OPENCV_DISTORTION, k1=OPENCV_DISTORTION["k1"] * (1.0 + 0.25 * (index % 3 - 1)))
    return Lens("OPENCV", camera.width, camera.height, fx, fy, cx, cy, **distortion)


def write_photo_formats(capture: Capture, out: Path, distort: bool = True) -> dict[str, Path]:
    """Write `capture`'s views (images with alpha, cameras, mesh) as OUT/neus (NeuS/IDR), OUT/colmap
    (binary model, PINHOLE), OUT/colmap_opencv (text model, OPENCV lens, distorted photos),
    OUT/nerfstudio (transforms.json, per-frame intrinsics and OPENCV lenses, distorted photos, masks
    by mask_path) and OUT/llff (poses_bounds.npy; views cropped to centre their principal point)."""
    out = Path(out)
    names = [f"{i:03d}" for i in range(len(capture.cameras))]
    if capture.mesh is not None:
        centre = capture.mesh.bounding_sphere.primitive.center
        radius = float(capture.mesh.bounding_sphere.primitive.radius)
    else:
        centre, radius = np.zeros(3), 1.0
    folders = {"neus": idr.write_capture(capture, out / "neus", names, centre, radius)}
    sim = colmap_similarity()
    folders["colmap"] = colmap.write_capture(capture, out / "colmap", names, sim)
    if distort:
        folders["colmap_opencv"] = colmap.write_capture(capture, out / "colmap_opencv", names, sim, binary=False,
                                                        lens_of=opencv_lens)
    lenses = [nerfstudio_lens(c, i) if distort else Lens("PINHOLE", c.width, c.height, *c.intrinsics())
              for i, c in enumerate(capture.cameras)]
    folders["nerfstudio"] = nerfstudio.write_capture(capture, out / "nerfstudio", names, nerfstudio_similarity(),
                                                     lenses, distort)
    folders["llff"] = llff.write_capture(capture, out / "llff", names, sim, centre, radius)
    if capture.mesh is not None:  # the known geometry beside each copy, in its world
        frames = format_frames()
        for name, folder in folders.items():
            moved_mesh = capture.mesh.copy()
            moved_mesh.apply_transform(frames[name])
            written(folder / "mesh.ply", lambda: moved_mesh.export(folder / "mesh.ply"))
    return folders
