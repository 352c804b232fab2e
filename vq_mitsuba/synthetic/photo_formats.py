"""A rendered capture written again in the formats photographed captures come in: NeuS/IDR
(`cameras_sphere.npz`, `image/`, `mask/`) and COLMAP (`sparse/0`, `images/`, `masks/`), the
latter in another similarity frame (scale, rotation, offset) and optionally through a distorting
OPENCV lens. Used by `make-scene --photo-formats` and the round-trip tests."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from vq_mitsuba.data.captures import Capture
from vq_mitsuba.data.imageio import write_png
from vq_mitsuba.data.photo_formats import Lens, distort_image, write_colmap, write_idr

# The COLMAP copy's world: x_colmap = SCALE * ROTATION @ x + OFFSET (an arbitrary similarity, as
# COLMAP's gauge is arbitrary).
COLMAP_SCALE = 3.7
COLMAP_OFFSET = np.array([1.5, -0.4, 2.25])
OPENCV_DISTORTION = {"k1": -0.08, "k2": 0.02, "p1": 0.002, "p2": -0.001}


def colmap_similarity() -> np.ndarray:
    """(4, 4) world -> COLMAP-world similarity of the written copy."""
    a, b = math.radians(30.0), math.radians(-20.0)
    rz = np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])
    rx = np.array([[1, 0, 0], [0, math.cos(b), -math.sin(b)], [0, math.sin(b), math.cos(b)]])
    m = np.eye(4)
    m[:3, :3] = COLMAP_SCALE * rz @ rx
    m[:3, 3] = COLMAP_OFFSET
    return m


def _moved(camera, sim: np.ndarray):
    """The camera in the similarity's frame (rotation and origin; the scale leaves the axes unit)."""
    from dataclasses import replace

    s = np.cbrt(np.linalg.det(sim[:3, :3]))
    m = np.eye(4)
    m[:3, :3] = sim[:3, :3] / s @ camera.to_world[:3, :3]
    m[:3, 3] = sim[:3, :3] @ camera.origin + sim[:3, 3]
    return replace(camera, to_world=m)


def opencv_lens(camera) -> Lens:
    fx, fy, cx, cy = camera.intrinsics()
    return Lens("OPENCV", camera.width, camera.height, fx, fy, cx, cy, **OPENCV_DISTORTION)


def write_photo_formats(capture: Capture, out: Path, distort: bool = True) -> dict[str, Path]:
    """Write `capture`'s views (images with alpha, cameras, mesh) as OUT/neus (NeuS/IDR), OUT/colmap
    (binary model, PINHOLE) and OUT/colmap_opencv (text model, OPENCV lens, distorted photos)."""
    out = Path(out)
    names = [f"{i:03d}" for i in range(len(capture.cameras))]
    # NeuS / IDR, in the capture's own world
    neus = out / "neus"
    for i, name in enumerate(names):
        write_png(neus / "image" / f"{name}.png", capture.images[i])
        write_png(neus / "mask" / f"{name}.png", capture.alpha[i], srgb=False)
    if capture.mesh is not None:
        centre = capture.mesh.bounding_sphere.primitive.center
        radius = float(capture.mesh.bounding_sphere.primitive.radius)
    else:
        centre, radius = np.zeros(3), 1.0
    write_idr(neus / "cameras_sphere.npz", capture.cameras, centre, radius)
    # COLMAP, in another similarity frame
    sim = colmap_similarity()
    moved = [_moved(c, sim) for c in capture.cameras]
    folders = {"neus": neus}
    variants = [("colmap", True, None)] + ([("colmap_opencv", False, opencv_lens)] if distort else [])
    for folder_name, binary, lens_of in variants:
        folder = out / folder_name
        files = [f"{n}.png" for n in names]
        for i, f in enumerate(files):
            rgb, alpha = capture.images[i], capture.alpha[i]
            if lens_of is not None:
                both = distort_image(np.concatenate([rgb, alpha[..., None]], -1), lens_of(capture.cameras[i]))
                rgb, alpha = both[..., :3], both[..., 3]
            write_png(folder / "images" / f, np.clip(rgb, 0, None))
            write_png(folder / "masks" / f"{f}.png", alpha, srgb=False)
        pts = None
        if capture.mesh is not None:
            v = np.asarray(capture.mesh.vertices)[:: max(1, len(capture.mesh.vertices) // 200)]
            pts = v @ sim[:3, :3].T + sim[:3, 3]
        write_colmap(folder / "sparse" / "0", moved, files, lens_of=lens_of, binary=binary, points=pts)
        folders[folder_name] = folder
    if capture.mesh is not None:  # the known geometry beside each copy, in its world
        capture.mesh.export(neus / "mesh.ply")
        moved_mesh = capture.mesh.copy()
        moved_mesh.apply_transform(sim)
        for name in folders:
            if name != "neus":
                moved_mesh.export(folders[name] / "mesh.ply")
    return folders
