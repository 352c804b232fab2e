"""A rendered capture written again in the formats photographed captures come in: NeuS/IDR
(`cameras_sphere.npz`, `image/`, `mask/`), COLMAP (`sparse/0`, `images/`, `masks/`), nerfstudio
(`transforms.json` with per-frame intrinsics and OPENCV distortion, `images/`, `masks/`) and LLFF
(`poses_bounds.npy`, `images/`, `masks/`). All but NeuS/IDR lie in another similarity frame (scale,
rotation, offset; `format_frames`), and COLMAP and nerfstudio optionally through distorting lenses.
Used by `make-scene --photo-formats` and the round-trip tests."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from vq_mitsuba.data.cameras import MITSUBA_TO_BLENDER
from vq_mitsuba.data.captures import Capture
from vq_mitsuba.data.imageio import write_png
from vq_mitsuba.data.llff import write_poses_bounds
from vq_mitsuba.data.nerfstudio import write_transforms_json
from vq_mitsuba.data.photo_formats import Lens, camera_from_intrinsics, distort_image, write_colmap, write_idr

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


def nerfstudio_lens(camera, index: int) -> Lens:
    """The nerfstudio copy's lens of view `index`: OPENCV, k1 varying from view to view."""
    fx, fy, cx, cy = camera.intrinsics()
    distortion = dict(OPENCV_DISTORTION, k1=OPENCV_DISTORTION["k1"] * (1.0 + 0.25 * (index % 3 - 1)))
    return Lens("OPENCV", camera.width, camera.height, fx, fy, cx, cy, **distortion)


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


def _distorted(rgb: np.ndarray, alpha: np.ndarray, lens: Lens | None) -> tuple[np.ndarray, np.ndarray]:
    if lens is None:
        return rgb, alpha
    both = distort_image(np.concatenate([rgb, alpha[..., None]], -1), lens)
    return both[..., :3], both[..., 3]


def write_photo_formats(capture: Capture, out: Path, distort: bool = True) -> dict[str, Path]:
    """Write `capture`'s views (images with alpha, cameras, mesh) as OUT/neus (NeuS/IDR), OUT/colmap
    (binary model, PINHOLE), OUT/colmap_opencv (text model, OPENCV lens, distorted photos),
    OUT/nerfstudio (transforms.json, per-frame intrinsics and OPENCV lenses, distorted photos, masks
    by mask_path) and OUT/llff (poses_bounds.npy; views cropped to centre their principal point)."""
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
            rgb, alpha = _distorted(capture.images[i], capture.alpha[i],
                                    lens_of(capture.cameras[i]) if lens_of is not None else None)
            write_png(folder / "images" / f, np.clip(rgb, 0, None))
            write_png(folder / "masks" / f"{f}.png", alpha, srgb=False)
        pts = None
        if capture.mesh is not None:
            v = np.asarray(capture.mesh.vertices)[:: max(1, len(capture.mesh.vertices) // 200)]
            pts = v @ sim[:3, :3].T + sim[:3, 3]
        write_colmap(folder / "sparse" / "0", moved, files, lens_of=lens_of, binary=binary, points=pts)
        folders[folder_name] = folder
    folders["nerfstudio"] = _write_nerfstudio(capture, out / "nerfstudio", names, distort)
    folders["llff"] = _write_llff(capture, out / "llff", names, centre, radius)
    if capture.mesh is not None:  # the known geometry beside each copy, in its world
        frames = format_frames()
        for name, folder in folders.items():
            moved_mesh = capture.mesh.copy()
            moved_mesh.apply_transform(frames[name])
            moved_mesh.export(folder / "mesh.ply")
    return folders


def _write_nerfstudio(capture: Capture, folder: Path, names: list[str], distort: bool) -> Path:
    sim = nerfstudio_similarity()
    lenses = [nerfstudio_lens(c, i) if distort else Lens("PINHOLE", c.width, c.height, *c.intrinsics())
              for i, c in enumerate(capture.cameras)]
    for i, name in enumerate(names):
        rgb, alpha = _distorted(capture.images[i], capture.alpha[i], lenses[i] if distort else None)
        write_png(folder / "images" / f"{name}.png", np.clip(rgb, 0, None))
        write_png(folder / "masks" / f"{name}.png", alpha, srgb=False)
    write_transforms_json(folder / "transforms.json", [_moved(c, sim) for c in capture.cameras],
                          [f"images/{n}.png" for n in names], lenses, [f"masks/{n}.png" for n in names],
                          applied_transform=sim)
    return folder


def _write_llff(capture: Capture, folder: Path, names: list[str], centre: np.ndarray, radius: float) -> Path:
    sim = colmap_similarity()
    scale = float(np.cbrt(np.linalg.det(sim[:3, :3])))
    cameras, bounds = [], []
    for i, (cam, name) in enumerate(zip(capture.cameras, names)):
        x0, y0, x1, y1 = llff_window(cam)
        fx, fy, cx, cy = cam.intrinsics()
        cameras.append(_moved(camera_from_intrinsics(cam.name, cam.to_world, fx, fy, cx - x0, cy - y0, x1 - x0,
                                                     y1 - y0), sim))
        distance = float(np.linalg.norm(cam.origin - centre))
        bounds.append((scale * max(distance - radius, 0.05 * distance), scale * (distance + radius)))
        write_png(folder / "images" / f"{name}.png", np.clip(capture.images[i, y0:y1, x0:x1], 0, None))
        write_png(folder / "masks" / f"{name}.png", capture.alpha[i, y0:y1, x0:x1], srgb=False)
    write_poses_bounds(folder / "poses_bounds.npy", cameras, bounds)
    return folder
