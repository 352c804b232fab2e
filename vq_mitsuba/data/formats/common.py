"""What the capture formats share: the `Capture` a loader returns, known meshes, reading and
stacking the reference images (each shrunk as it is read: vq_mitsuba.data.resize), and the views
of photographed captures (photos and masks read, undistorted when their lens distorts).
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from vq_mitsuba.data.cameras import Camera
from vq_mitsuba.data.imageio import image_size, read_image, read_mask
from vq_mitsuba.data.lens import Lens, undistort_photo
from vq_mitsuba.data.resize import Shrink
from vq_mitsuba.errors import InputError, raise_all

if TYPE_CHECKING:
    import trimesh

IMAGE_EXTS = (".exr", ".png", ".jpg", ".jpeg")
PHOTO_EXTS = (".png", ".jpg", ".jpeg", ".exr")


@dataclass
class Capture:
    source: Path  # the XML or json file
    cameras: list[Camera]  # Mitsuba-convention cameras, in the capture's world
    images: np.ndarray  # (N, H, W, 3) float32 linear RGB
    alpha: np.ndarray  # (N, H, W) float32 in [0, 1]; all ones when images have no alpha
    has_alpha: bool
    mesh: trimesh.Trimesh | None  # known geometry in world space, or None
    envmap: np.ndarray | None  # known lighting: (H, W, 3) float32 lat-long linear, or None
    envmap_to_world: np.ndarray  # (4, 4) float64
    world: str  # "mitsuba" or "blender"

    @property
    def height(self) -> int:
        return int(self.images.shape[1])

    @property
    def width(self) -> int:
        return int(self.images.shape[2])


def load_mesh(path: str | Path):
    """A PLY/OBJ mesh as a trimesh.Trimesh (vertices kept as stored, and the file's vertex normals
    when it has them: they are the shading normals), validated."""
    import trimesh

    path = Path(path)
    if not path.is_file():
        raise InputError(path, "mesh file not found")
    try:
        # Not force="mesh": that path drops the normals stored in the file.
        loaded = trimesh.load(str(path), process=False)
    except Exception as exc:  # trimesh raises many kinds on bad files
        raise InputError(path, f"cannot read mesh file ({type(exc).__name__}: {exc})") from exc
    if isinstance(loaded, trimesh.Scene):  # several objects, or an empty file
        geoms = [g for g in loaded.geometry.values() if isinstance(g, trimesh.Trimesh)]
        loaded = trimesh.util.concatenate(geoms) if geoms else trimesh.Trimesh()
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0 or len(loaded.vertices) == 0:
        raise InputError(path, "mesh file is empty (no triangles)")
    if not np.all(np.isfinite(loaded.vertices)):
        raise InputError(path, "mesh has non-finite vertex positions")
    return loaded


def has_suffix(source: Path, suffixes: tuple[str, ...]) -> bool:
    """Whether `source` is a file path (not a folder) whose suffix is one of `suffixes`."""
    return source.suffix.lower() in suffixes and not source.is_dir()


MESH_FILE = "mesh.ply"  # the known geometry a capture's folder may hold beside its cameras


def mesh_beside(source: Path) -> bool:
    """Whether a capture brings its own geometry as a mesh.ply in its folder (reads nothing)."""
    return ((source if source.is_dir() else source.parent) / MESH_FILE).exists()


def known_mesh(mesh_arg: str | Path | None, folder: Path):
    """The known geometry of a photographed capture: the `mesh=` argument, else the folder's
    mesh.ply, else None."""
    mesh_file = mesh_arg if mesh_arg is not None else (folder / MESH_FILE if (folder / MESH_FILE).is_file() else None)
    return load_mesh(mesh_file) if mesh_file else None


def ensure_variant():
    """mitsuba, with the project's variant selected (vq_mitsuba.backend.init_mitsuba)."""
    import mitsuba as mi

    from vq_mitsuba.backend import init_mitsuba

    init_mitsuba()
    return mi


def find_image(stem: Path) -> Path | None:
    """`stem.exr` if it exists, else `stem.png` (None when neither does)."""
    for ext in (".exr", ".png"):
        candidate = stem.parent / (stem.name + ext)
        if candidate.is_file():
            return candidate
    return None


def shrunk_entry(shrink: Shrink, path: Path, rgb: np.ndarray, alpha: np.ndarray | None):
    """(path, rgb, alpha) at the size `shrink` gives, alpha checked first (averaging would hide a bad value)."""
    if alpha is not None and (alpha.min() < 0.0 or alpha.max() > 1.0):
        raise InputError(path, f"alpha outside [0, 1] (range {alpha.min():g}..{alpha.max():g})")
    if not shrink.active:
        return path, rgb, alpha
    return path, shrink.image(rgb, path), None if alpha is None else shrink.image(alpha, path)


def stack_images(entries: list[tuple[Path, np.ndarray, np.ndarray | None]]):
    """(images, alpha, has_alpha) from (path, rgb, alpha) triples of one size."""
    with_alpha = [a is not None for _, _, a in entries]
    if any(with_alpha) and not all(with_alpha):
        has = next(p for p, _, a in entries if a is not None)
        lacks = next(p for p, _, a in entries if a is None)
        raise InputError(lacks, f"image has no alpha channel but {has.name} has one; "
                                "either all images carry an alpha mask or none does")
    images = np.stack([rgb for _, rgb, _ in entries]).astype(np.float32, copy=False)
    if all(with_alpha):
        alpha = np.stack([a for _, _, a in entries]).astype(np.float32, copy=False)
        for p, _, a in entries:
            if a.min() < 0.0 or a.max() > 1.0:
                raise InputError(p, f"alpha outside [0, 1] (range {a.min():g}..{a.max():g})")
        return images, alpha, True
    return images, np.ones(images.shape[:3], dtype=np.float32), False


def images_in(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.suffix.lower() in PHOTO_EXTS) if folder.is_dir() else []


def numpy_file_kind(path: Path, expected: str) -> str:
    """What a NumPy file (`expected`: "npy" or "npz") is by its first bytes: "npy", "npz" (a zip
    archive) or "pickle" (never loaded); an InputError naming the file when it is none of them."""
    try:
        with open(path, "rb") as f:
            head = f.read(8)
    except OSError as exc:
        raise InputError(path, f"cannot read ({exc.strerror or exc})") from None
    if head.startswith(b"\x93NUMPY"):
        return "npy"
    if head.startswith((b"PK\x03\x04", b"PK\x05\x06")):
        return "npz"
    if head.startswith(b"\x80"):
        return "pickle"
    what = "an .npz archive of arrays" if expected == "npz" else "a NumPy .npy array"
    raise InputError(path, f"not a valid .{expected} file: it does not start like {what} (empty, truncated, or "
                           "another kind of file?)")


def common_image_size(images: list[Path]) -> tuple[int, int]:
    """(width, height) that the photos of a capture share, read from each file's header; a photo of
    another size than most of them is refused by name (the majority size wins, so one odd photo is
    the one blamed, wherever it sorts)."""
    sizes = [image_size(p) for p in images]
    (width, height), count = Counter(sizes).most_common(1)[0]
    odd = [InputError(p, f"image is {w}x{h}, but {count} of the {len(images)} photos are {width}x{height}: all "
                         "views need one size") for p, (w, h) in zip(images, sizes) if (w, h) != (width, height)]
    raise_all(odd, images[0].parent)
    return width, height


def paired_masks(image_dir: Path, images: list[Path], mask_dir: Path, masks: list[Path]) -> None:
    """Masks paired with photos in sorted order: refused when the counts differ, naming the photo
    (or mask) missing where the file names show which."""
    if not masks or len(masks) == len(images):
        return
    image_stems, mask_stems = {p.stem for p in images}, {p.stem for p in masks}
    no_image = [m for m in masks if m.stem not in image_stems]
    no_mask = [p for p in images if p.stem not in mask_stems]
    counts = f"{mask_dir.name}/ holds {len(masks)} masks for {len(images)} images in {image_dir.name}/"
    if len(masks) > len(images) and no_image and len(no_image) < len(masks):
        raise InputError(image_dir / no_image[0].name, f"image missing: {mask_dir.name}/{no_image[0].name} has no "
                                                       f"photo of its name ({counts})")
    if len(masks) < len(images) and no_mask and len(no_mask) < len(images):
        raise InputError(mask_dir / no_mask[0].name, f"mask missing: {image_dir.name}/{no_mask[0].name} has no "
                                                     f"mask of its name ({counts})")
    raise InputError(mask_dir, f"holds {len(masks)} masks for {len(images)} images in {image_dir.name}/")


def missing_numbered(images: list[Path], count: int, first: int | None = None) -> Path | None:
    """The first photo missing from numbered photos (000.png, 001.png, ...; one prefix, width and
    suffix) that `count` views expect, numbered from `first` (unknown: only a gap between two photos
    is named); None when the names do not show which."""
    import re

    found = [re.fullmatch(r"(.*?)(\d+)", p.stem) for p in images]
    if not images or not all(found) or len({(m[1], len(m[2]), p.suffix) for m, p in zip(found, images)}) != 1:
        return None
    numbers = {int(m[2]) for m in found}
    start = min(numbers) if first is None else first
    gaps = [n for n in range(start, start + count) if n not in numbers and (first is not None or n < max(numbers))]
    prefix, width, suffix = found[0][1], len(found[0][2]), images[0].suffix
    return images[0].with_name(f"{prefix}{gaps[0]:0{width}d}{suffix}") if gaps else None


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
                rgb, alpha = undistort_photo(path, rgb, alpha, lens, cache, shrink)
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


def moved_camera(camera, sim: np.ndarray):
    """The camera in the similarity's frame (rotation and origin; the scale leaves the axes unit)."""
    s = np.cbrt(np.linalg.det(sim[:3, :3]))
    m = np.eye(4)
    m[:3, :3] = sim[:3, :3] / s @ camera.to_world[:3, :3]
    m[:3, 3] = sim[:3, :3] @ camera.origin + sim[:3, 3]
    return replace(camera, to_world=m)
