"""Photographed captures: a COLMAP folder (`sparse/0` binary or text, `images/`, optional
`masks/`) or the NeuS/IDR layout (`cameras_sphere.npz`, `image/`, `mask/`).

Cameras keep fx != fy and an off-centre principal point. Images taken through a distorting lens
(COLMAP's SIMPLE_RADIAL, RADIAL, OPENCV) are undistorted once into the pinhole camera of the same
intrinsics; the result is cached. The world is the capture's own; its up direction (for the
envmap's frame) is the cameras' mean up vector.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np

from vq_mitsuba.data.cameras import Camera
from vq_mitsuba.data.imageio import read_image, read_mask
from vq_mitsuba.data.photo_formats import (Lens, check_idr_views, colmap_camera, colmap_model_dir, idr_camera,
                                           read_colmap, read_idr, undistort_image)
from vq_mitsuba.errors import InputError, raise_all

PHOTO_EXTS = (".png", ".jpg", ".jpeg", ".exr")


def _images_in(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.suffix.lower() in PHOTO_EXTS) if folder.is_dir() else []


def _idr_views(npz: Path) -> tuple[list[Camera], list[Path], list[Path] | None]:
    folder = npz.parent
    # NeuS names the folders image/ and mask/; copies of DTU made for other tools use images/ and masks/.
    image_dir = next((folder / d for d in ("image", "images") if _images_in(folder / d)), folder / "image")
    images = _images_in(image_dir)
    if not images:
        raise InputError(folder / "image", "no images (the NeuS/IDR layout keeps them in image/, e.g. 000.png)")
    mask_dir = next((folder / d for d in ("mask", "masks") if _images_in(folder / d)), folder / "mask")
    masks = _images_in(mask_dir)
    if masks and len(masks) != len(images):
        raise InputError(mask_dir, f"holds {len(masks)} masks for {len(images)} images in {image_dir.name}/")
    views, _ = read_idr(npz, len(images))
    from vq_mitsuba.data.imageio import image_size

    w, h = image_size(images[0])
    check_idr_views(npz, views, w, h)
    cameras = [idr_camera(p.stem, k, c2w, w, h) for p, (k, c2w) in zip(images, views)]
    return cameras, images, masks or None


def _colmap_views(folder: Path) -> tuple[list[Camera], list[Path], list[Path | None], list[Lens]]:
    model = colmap_model_dir(folder)
    lenses, registered = read_colmap(model)
    image_dir = folder / "images"
    if not image_dir.is_dir():
        raise InputError(image_dir, "missing: a COLMAP capture keeps its photos in images/")
    cameras, paths, masks, used = [], [], [], []
    for img in registered:
        lens = lenses[img.camera_id]
        cameras.append(colmap_camera(img, lens))
        paths.append(image_dir / img.name)
        mask = None
        for candidate in (folder / "masks" / f"{img.name}.png", (folder / "masks" / img.name).with_suffix(".png")):
            if candidate.is_file():
                mask = candidate
                break
        masks.append(mask)
        used.append(lens)
    if any(m is not None for m in masks) and not all(m is not None for m in masks):
        missing = next(p for p, m in zip(paths, masks) if m is None)
        raise InputError(folder / "masks", f"has masks for some images but not for {missing.name}: "
                                           "give every image a mask or none")
    return cameras, paths, masks, used


def photo_cameras(source: Path, kind: str) -> list[Camera]:
    """The pinhole cameras of a photographed capture (no images read beyond the first one's size)."""
    if kind == "idr":
        return _idr_views(source)[0]
    return _colmap_views(source)[0]


def _up(cameras: list[Camera]) -> np.ndarray:
    """(4, 4) envmap-to-world rotation taking the envmap's up (+Y) to the cameras' mean up vector."""
    up = np.mean([c.to_world[:3, 1] for c in cameras], 0)
    if np.linalg.norm(up) < 1e-6:
        return np.eye(4)
    up /= np.linalg.norm(up)
    y = np.array([0.0, 1.0, 0.0])
    axis = np.cross(y, up)
    s, c = np.linalg.norm(axis), float(y @ up)
    out = np.eye(4)
    if s < 1e-9:
        out[:3, :3] = np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
        return out
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]]) / s
    out[:3, :3] = np.eye(3) + s * k + (1 - c) * k @ k
    return out


def _undistorted(path: Path, rgb: np.ndarray, alpha: np.ndarray, lens: Lens, cache: Path | None):
    """Undistort one photo and its mask, reusing the cached result for the same file and lens."""
    key = hashlib.sha1(f"{path.resolve()}|{path.stat().st_mtime_ns}|{lens}".encode()).hexdigest()[:16]
    cached = cache / f"{path.stem}-{key}.npz" if cache is not None else None
    if cached is not None and cached.is_file():
        data = np.load(cached)
        return data["rgb"].astype(np.float32), data["alpha"].astype(np.float32)
    both, inside = undistort_image(np.concatenate([rgb, alpha[..., None]], -1), lens)
    out_rgb, out_alpha = both[..., :3], both[..., 3] * inside
    if cached is not None:
        cache.mkdir(parents=True, exist_ok=True)
        np.savez(cached, rgb=out_rgb.astype(np.float16), alpha=out_alpha.astype(np.float16))
    return out_rgb, out_alpha


def load_photo_views(source: Path, kind: str, cache_dir):
    """(cameras, images (N, H, W, 3) linear, alpha (N, H, W), has_alpha, capture folder,
    envmap-to-world) of a photographed capture; every unreadable file is reported at once."""
    if kind == "idr":
        cameras, paths, masks = _idr_views(source)
        lenses = [None] * len(paths)
        masks = masks or [None] * len(paths)
        folder = source.parent
    else:
        cameras, paths, masks, lenses = _colmap_views(source)
        folder = source
    cache = Path(cache_dir) if cache_dir is not None else None
    images, alphas, problems = [], [], []
    has_alpha = any(m is not None for m in masks)
    for cam, path, mask_path, lens in zip(cameras, paths, masks, lenses):
        try:
            rgb, alpha = read_image(path)
            if rgb.shape[:2] != (cam.height, cam.width):
                raise InputError(path, f"image is {rgb.shape[1]}x{rgb.shape[0]} but its camera says "
                                       f"{cam.width}x{cam.height}")
            if mask_path is not None:
                mask = read_mask(mask_path)
                if mask.shape != rgb.shape[:2]:
                    raise InputError(mask_path, f"mask is {mask.shape[1]}x{mask.shape[0]}, its image "
                                                f"{rgb.shape[1]}x{rgb.shape[0]}")
                alpha = mask if alpha is None else alpha * mask
            if alpha is not None:
                has_alpha = True
            alpha = np.ones(rgb.shape[:2], np.float32) if alpha is None else alpha
            if lens is not None and lens.distorted:
                rgb, alpha = _undistorted(path, rgb, alpha, lens, cache)
            images.append(rgb)
            alphas.append(alpha)
        except InputError as exc:
            problems.append(exc)
    raise_all(problems, source)
    if len({im.shape for im in images}) > 1:
        raise InputError(source, "the photos differ in size; vq-mitsuba needs one size for all views "
                                 "(COLMAP's image_undistorter can write them so)")
    return cameras, np.stack(images), np.stack(alphas), has_alpha, folder, _up(cameras)
