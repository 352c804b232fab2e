"""Photographed captures: a COLMAP folder (`sparse/0` binary or text, `images/`, optional
`masks/`), the NeuS/IDR layout (`cameras_sphere.npz`, `image/`, `mask/`) or an LLFF folder
(`poses_bounds.npy`, `images/`, optional `masks/`); `read_views` also reads a nerfstudio
transforms.json's photos.

Cameras keep fx != fy and an off-centre principal point. Images taken through a distorting lens
(COLMAP's SIMPLE_RADIAL, RADIAL, OPENCV, OPENCV_FISHEYE; nerfstudio's OPENCV, OPENCV_FISHEYE) are
undistorted once into the pinhole camera of the same intrinsics; the result is cached. Each photo
is shrunk (capture.downscale, capture.max_size) before the next one is read. The world is the
capture's own; its up direction (for the envmap's frame) is the cameras' mean up vector.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np

from vq_mitsuba.data.cameras import Camera
from vq_mitsuba.data.imageio import read_image, read_mask
from vq_mitsuba.data.photo_formats import (Lens, camera_from_intrinsics, check_idr_views, colmap_camera,
                                           colmap_model_dir, idr_camera, read_colmap, read_idr, undistort_image)
from vq_mitsuba.data.resize import Shrink
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


def _llff_images(folder: Path) -> tuple[Path, list[Path]]:
    """LLFF's photos: images/, else the least reduced images_N/ there is."""
    reduced = sorted((p for p in folder.glob("images_*") if p.is_dir() and p.name[7:].isdigit()),
                     key=lambda p: int(p.name[7:]))
    for image_dir in [folder / "images"] + reduced:
        if _images_in(image_dir):
            return image_dir, _images_in(image_dir)
    raise InputError(folder / "images", "no images (an LLFF capture keeps its photos in images/, in the order "
                                        "of poses_bounds.npy's rows)")


def _llff_views(npy: Path) -> tuple[list[Camera], list[Path], list[Path | None]]:
    """The views of an LLFF folder. The focal length scales with the photos' size when it differs
    from the one poses_bounds.npy gives (as LLFF's loader does for images_N/)."""
    from vq_mitsuba.data.checks import check_intrinsics, collect
    from vq_mitsuba.data.imageio import image_size
    from vq_mitsuba.data.llff import llff_to_world, read_poses_bounds

    folder = npy.parent
    image_dir, images = _llff_images(folder)
    poses, _ = read_poses_bounds(npy)
    if len(poses) != len(images):
        raise InputError(npy, f"holds {len(poses)} poses for {len(images)} images in {image_dir.name}/")
    width, height = image_size(images[0])
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
        found = {p.stem: p for p in _images_in(folder / "masks")}
        if len(found) != len(images):
            raise InputError(folder / "masks", f"holds {len(found)} masks for {len(images)} images in "
                                               f"{image_dir.name}/ (one per photo, the same file name stem)")
        missing = [p.name for p in images if p.stem not in found]
        if missing:
            raise InputError(folder / "masks", f"has no mask for {missing[0]} (masks/{Path(missing[0]).stem}.png)")
        masks = [found[p.stem] for p in images]
    return cameras, images, masks


def photo_cameras(source: Path, kind: str) -> list[Camera]:
    """The pinhole cameras of a photographed capture (no images read beyond the first one's size)."""
    if kind == "idr":
        return _idr_views(source)[0]
    if kind == "llff":
        return _llff_views(source)[0]
    return _colmap_views(source)[0]


def up_frame(cameras: list[Camera]) -> np.ndarray:
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


def _undistorted(path: Path, rgb: np.ndarray, alpha: np.ndarray, lens: Lens, cache: Path | None, shrink: Shrink):
    """Undistort one photo and its mask, then shrink them, reusing the cached result for the same
    file, lens and shrink. A cached file that cannot be read back whole (torn, another file) is
    made again; it is written under a temporary name and renamed, so a crash leaves none half-written."""
    key = hashlib.sha1(f"{path.resolve()}|{path.stat().st_mtime_ns}|{lens}|{shrink}".encode()).hexdigest()[:16]
    cached = cache / f"{path.stem}-{key}.npz" if cache is not None else None
    if cached is not None and cached.is_file():
        try:
            with np.load(cached) as data:
                rgb_c, alpha_c = data["rgb"].astype(np.float32), data["alpha"].astype(np.float32)
            if rgb_c.ndim == 3 and rgb_c.shape[2] == 3 and alpha_c.shape == rgb_c.shape[:2] \
                    and np.isfinite(rgb_c).all() and np.isfinite(alpha_c).all():
                return rgb_c, alpha_c
        except Exception:  # any unreadable cache file is made again below
            pass
    both, inside = undistort_image(np.concatenate([rgb, alpha[..., None]], -1), lens)
    del rgb, alpha
    both[..., 3] *= inside
    both = shrink.image(both, path)
    out_rgb, out_alpha = both[..., :3], both[..., 3]
    if cached is not None:
        cache.mkdir(parents=True, exist_ok=True)
        tmp = cached.with_name(f".{cached.stem}.tmp.npz")
        np.savez(tmp, rgb=out_rgb.astype(np.float16), alpha=out_alpha.astype(np.float16))
        tmp.replace(cached)
    return out_rgb, out_alpha


def read_views(source: Path, cameras: list[Camera], paths: list[Path], masks: list[Path | None],
               lenses: list[Lens | None], cache_dir=None, shrink: Shrink | None = None):
    """(images (N, H, W, 3) linear, alpha (N, H, W), has_alpha) of the views: each photo read, its
    mask multiplied into its alpha, undistorted when its lens distorts, and shrunk before the next
    one is read (`shrink`: capture.downscale / max_size); every unreadable file reported at once."""
    shrink = shrink or Shrink()
    cache = Path(cache_dir) if cache_dir is not None else None
    images, alphas, problems = [], [], []
    has_alpha = any(m is not None for m in masks)
    for cam, path, mask_path, lens in zip(cameras, paths, masks, lenses):
        try:
            distorted = lens is not None and lens.distorted
            r = 1 if distorted else shrink.decode_reduction(path)  # large JPEGs: decoded at a fraction
            rgb, alpha = read_image(path, r)
            if (rgb.shape[0] * r, rgb.shape[1] * r) != (cam.height, cam.width):
                raise InputError(path, f"image is {rgb.shape[1] * r}x{rgb.shape[0] * r} but its camera says "
                                       f"{cam.width}x{cam.height}")
            if mask_path is not None:
                rm = r if r == 1 or shrink.decode_reduction(mask_path) >= r else 1
                mask = read_mask(mask_path, rm)
                if (mask.shape[0] * rm, mask.shape[1] * rm) != (cam.height, cam.width):
                    raise InputError(mask_path, f"mask is {mask.shape[1] * rm}x{mask.shape[0] * rm}, its image "
                                                f"{cam.width}x{cam.height}")
                if rm != r:  # a mask the decoder cannot shrink alike: brought to the image's scale
                    mask = Shrink(r).image(mask, mask_path)
                alpha = mask if alpha is None else alpha * mask
            if alpha is not None:
                has_alpha = True
            alpha = np.ones(rgb.shape[:2], np.float32) if alpha is None else alpha
            if distorted:
                rgb, alpha = _undistorted(path, rgb, alpha, lens, cache, shrink)
            elif shrink.active:
                rgb, alpha = shrink.after(r).image(rgb, path), shrink.after(r).image(alpha, path)
            images.append(rgb)
            alphas.append(alpha)
        except InputError as exc:
            problems.append(exc)
    raise_all(problems, source)
    if len({im.shape for im in images}) > 1:
        raise InputError(source, "the photos differ in size; vq-mitsuba needs one size for all views "
                                 "(COLMAP's image_undistorter can write them so)")
    return np.stack(images), np.stack(alphas), has_alpha


def load_photo_views(source: Path, kind: str, cache_dir, shrink: Shrink | None = None):
    """(cameras, images (N, H, W, 3) linear, alpha (N, H, W), has_alpha, capture folder,
    envmap-to-world) of a photographed capture (COLMAP, NeuS/IDR or LLFF), at the size `shrink`
    gives; every unreadable file is reported at once."""
    if kind == "idr":
        cameras, paths, masks = _idr_views(source)
        lenses = [None] * len(paths)
        masks = masks or [None] * len(paths)
        folder = source.parent
    elif kind == "llff":
        cameras, paths, masks = _llff_views(source)
        lenses = [None] * len(paths)
        folder = source.parent
    else:
        cameras, paths, masks, lenses = _colmap_views(source)
        folder = source
    images, alphas, has_alpha = read_views(source, cameras, paths, masks, lenses, cache_dir, shrink)
    return cameras, images, alphas, has_alpha, folder, up_frame(cameras)
