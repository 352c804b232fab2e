"""NeuS / IDR: `cameras_sphere.npz` (DTU as NeuS and IDR ship it), in the capture's own world.

    cameras_sphere.npz  world_mat_i = K [R | t] (3x4 or 4x4) for view i, and scale_mat_i taking
                        the unit sphere to the region of interest (optional)
    image/000.png       the photos in sorted file-name order (or images/), one size for all
    mask/000.png        optional masks, one per photo (or masks/)
    mesh.ply            known geometry (optional)

The projection matrices use OpenCV camera axes (vq_mitsuba.data.cameras.OPENCV_TO_MITSUBA) and
put pixel centres at integer coordinates (NeuS casts rays through integer pixel positions), so
their principal point is shifted by half a pixel on reading. The archive is read without pickles
and every matrix is checked before any work.
"""

from __future__ import annotations

from contextlib import contextmanager
from pathlib import Path

import numpy as np

from vq_mitsuba.data.cameras import OPENCV_TO_MITSUBA, Camera, camera_from_intrinsics
from vq_mitsuba.data.checks import check_intrinsics, check_pose, collect
from vq_mitsuba.data.formats.common import (Capture, mesh_beside, common_image_size, has_suffix, images_in, known_mesh,
                                            missing_numbered, numpy_file_kind, paired_masks, read_views,
                                            up_frame)
from vq_mitsuba.data.imageio import write_png, written
from vq_mitsuba.errors import InputError, raise_all

KIND = "idr"
SUFFIXES = (".npz",)
FOLDER_FILES = ("cameras_sphere.npz",)
DESCRIPTION = "a NeuS/IDR cameras_sphere.npz"  # what a person gives, in messages and help
POSED = True
MAX_MATRIX_BYTES = 1 << 16  # what a matrix of the archive may unpack to (a 4x4 of any dtype takes far less)
points = None  # no sparse points (sphere: scale_mat_0's region of interest)
has_geometry = mesh_beside  # known geometry: a mesh.ply in the capture's folder


def detect(source: Path) -> bool:
    return has_suffix(source, SUFFIXES)


def cameras(npz: Path) -> tuple[list[Camera], str]:
    """(the views' pinhole cameras, "mitsuba"); the first photo is read for its size."""
    return _idr_views(npz)[0], "mitsuba"


def load(npz: Path, mesh_arg, shrink=None, cache_dir=None) -> Capture:
    """The capture: the photos, masks multiplied into alpha, each shrunk as it is read; the
    envmap's up is the cameras' mean up."""
    cameras, paths, masks = _idr_views(npz)
    images, alpha, has_alpha = read_views(npz, cameras, paths, masks or [None] * len(paths), [None] * len(paths),
                                          cache_dir, shrink)
    return Capture(npz, cameras, images, alpha, has_alpha, known_mesh(mesh_arg, npz.parent), None, up_frame(cameras),
                   "mitsuba")


def sphere(npz: Path) -> tuple[np.ndarray, float, str] | None:
    """The region of interest (`read_idr_sphere`) and what gives it, None without scale_mat_0."""
    found = read_idr_sphere(npz)
    return None if found is None else (*found, "scale_mat_0")


def _idr_views(npz: Path) -> tuple[list[Camera], list[Path], list[Path] | None]:
    folder = npz.parent
    # NeuS names the folders image/ and mask/; copies of DTU made for other tools use images/ and masks/.
    image_dir = next((folder / d for d in ("image", "images") if images_in(folder / d)), folder / "image")
    images = images_in(image_dir)
    if not images:
        raise InputError(folder / "image", "no images (the NeuS/IDR layout keeps them in image/, e.g. 000.png)")
    mask_dir = next((folder / d for d in ("mask", "masks") if images_in(folder / d)), folder / "mask")
    masks = images_in(mask_dir)
    paired_masks(image_dir, images, mask_dir, masks)
    _no_view_without_image(npz, image_dir, images)
    views, _ = read_idr(npz, len(images))
    w, h = common_image_size(images)
    check_idr_views(npz, views, w, h)
    cameras = [idr_camera(p.stem, k, c2w, w, h) for p, (k, c2w) in zip(images, views)]
    return cameras, images, masks or None


def _no_view_without_image(npz: Path, image_dir: Path, images: list[Path]) -> None:
    """Refuses an archive with more views (world_mat_i) than photos: views pair with photos in sorted
    order, so a photo missing would give the next ones its pose. Names it when the file names show which."""
    with _open_npz(npz) as data:
        count = len(images)
        while f"world_mat_{count}" in data.files:
            count += 1
    if count == len(images):
        return
    what = f"{npz.name} holds {count} views (world_mat_0..{count - 1}) for {len(images)} images in {image_dir.name}/"
    missing = missing_numbered(images, count, first=0)
    if missing is not None:
        raise InputError(missing, f"image missing: {what}")
    raise InputError(npz, f"{what.removeprefix(npz.name + ' ')}: one photo per view (an image missing?)")


def read_idr(path: Path, count: int) -> tuple[list[tuple[np.ndarray, np.ndarray]], list[np.ndarray]]:
    """(K 3x3 with pixel centres at +0.5, camera-to-world in OpenCV axes) of views 0..count-1, and
    their scale matrices (normalised -> world), each matrix checked for its shape, dtype and values."""
    with _open_npz(path) as data:
        views, scales = [], []
        for i in range(count):
            if f"world_mat_{i}" not in data.files:
                raise InputError(path, f"has no world_mat_{i}, but the capture has {count} images")
            p = _idr_matrix(path, data, f"world_mat_{i}", ((3, 4), (4, 4)))[:3, :4]
            scale = _idr_matrix(path, data, f"scale_mat_{i}", ((4, 4),)) if f"scale_mat_{i}" in data.files \
                else np.eye(4)
            _check_invertible(path, f"scale_mat_{i}", scale[:3, :3])
            views.append(_decompose(path, i, p))
            scales.append(scale)
    return views, scales


def read_idr_sphere(path: Path) -> tuple[np.ndarray, float] | None:
    """(centre, radius) in the world of the sphere that scale_mat_0 maps the unit sphere to: the
    region of interest IDR and NeuS normalise to; None when the archive has no scale_mat_0."""
    with _open_npz(path) as data:
        if "scale_mat_0" not in data.files:
            return None
        scale = _idr_matrix(path, data, "scale_mat_0", ((4, 4),))
    _check_invertible(path, "scale_mat_0", scale[:3, :3])
    return scale[:3, 3].copy(), float(abs(np.linalg.det(scale[:3, :3])) ** (1.0 / 3.0))


@contextmanager
def _open_npz(path: Path):
    """The npz archive (no pickles: an object array is refused when read, not run). The file is
    opened here so that an archive numpy cannot parse is closed too."""
    kind = numpy_file_kind(path, "npz")
    if kind != "npz":
        raise InputError(path, "is a Python pickle, which is never loaded" if kind == "pickle" else
                               "is a single .npy array, not an .npz archive of named matrices (world_mat_0, ...)")
    try:
        f = open(path, "rb")
    except OSError as exc:
        raise InputError(path, f"cannot read ({exc.strerror or exc})") from None
    with f:
        try:
            data = np.load(f, allow_pickle=False)
        except Exception as exc:  # numpy, zipfile and OS errors differ
            raise InputError(path, f"cannot read ({type(exc).__name__}: {exc})") from None
        if not isinstance(data, np.lib.npyio.NpzFile):
            raise InputError(path, "not an .npz archive of named matrices (world_mat_0, scale_mat_0, ...)")
        with data:
            yield data


def _idr_matrix(path: Path, data, key: str, shapes: tuple[tuple[int, int], ...]) -> np.ndarray:
    """One matrix of the archive: numbers (no strings, no pickled objects), one of `shapes`, finite;
    a member that would unpack to more than MAX_MATRIX_BYTES is refused before it is read."""
    member = data.zip.NameToInfo.get(f"{key}.npy")
    if member is not None and member.file_size > MAX_MATRIX_BYTES:
        raise InputError(path, f"{key} unpacks to {member.file_size} bytes, far more than a matrix takes (a damaged "
                               "archive?)")
    try:
        raw = data[key]
    except ValueError as exc:
        if "allow_pickle" in str(exc):
            raise InputError(path, f"{key} is an array of Python objects (a pickle), which is never loaded: "
                                   "save it as an array of numbers") from None
        raise InputError(path, f"{key}: cannot read ({exc})") from None
    except Exception as exc:  # a damaged member of the archive
        raise InputError(path, f"{key}: cannot read ({type(exc).__name__}: {exc})") from None
    if raw.dtype.kind not in "biuf":
        raise InputError(path, f"{key} holds {raw.dtype} values, not numbers")
    if raw.shape not in shapes:
        raise InputError(path, f"{key} has shape {raw.shape}; expected " + " or ".join(f"{r}x{c}" for r, c in shapes))
    m = raw.astype(np.float64)
    if not np.all(np.isfinite(m)):
        raise InputError(path, f"{key} holds non-finite values")
    return m


def _check_invertible(path: Path, key: str, m: np.ndarray) -> None:
    """A 3x3 block that a projection or a scale needs to invert (condition number below 1e12)."""
    with np.errstate(all="ignore"):
        cond = np.linalg.cond(m)
    if not cond < 1e12:
        raise InputError(path, f"{key} is singular (its 3x3 part cannot be inverted)")


def _decompose(path: Path, i: int, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    from scipy.linalg import rq

    m = p[:, :3]
    _check_invertible(path, f"world_mat_{i}", m)
    k, r = rq(m)
    fix = np.diag(np.sign(np.diag(k)))  # a positive diagonal for K
    k, r = k @ fix, fix @ r
    t = np.linalg.solve(k, p[:, 3])
    if np.linalg.det(r) < 0:  # P is known up to its sign
        r, t = -r, -t
    k = k / k[2, 2]
    if abs(k[0, 1]) > 1e-6 * k[0, 0]:
        raise InputError(path, f"world_mat_{i}: skewed pixels (K[0,1] = {k[0, 1]:.3g}) are not supported")
    k = k.copy()
    k[0, 2] += 0.5  # IDR's pixel centres sit at integer coordinates
    k[1, 2] += 0.5
    c2w = np.eye(4)
    c2w[:3, :3] = r.T
    c2w[:3, 3] = -r.T @ t
    return k, c2w


def check_idr_views(path: Path, views: list[tuple[np.ndarray, np.ndarray]], width: int, height: int) -> None:
    """The intrinsics and poses that `read_idr` decomposed, for images of width x height; all at once."""
    problems: list[InputError] = []
    for i, (k, c2w) in enumerate(views):
        collect(problems, check_intrinsics, path, f"world_mat_{i}", k[0, 0], k[1, 1], k[0, 2], k[1, 2], width, height)
        collect(problems, check_pose, path, f"world_mat_{i}", c2w)
    raise_all(problems, path)


def idr_camera(name: str, k: np.ndarray, c2w_opencv: np.ndarray, width: int, height: int) -> Camera:
    return camera_from_intrinsics(name, c2w_opencv @ OPENCV_TO_MITSUBA, k[0, 0], k[1, 1], k[0, 2], k[1, 2],
                                  width, height)


def write_idr(path: Path, cameras: list[Camera], centre: np.ndarray, radius: float) -> None:
    """cameras_sphere.npz: world_mat_i = K [R | t] (IDR's pixel convention) and scale_mat_i taking
    the unit sphere to the sphere (centre, radius) that holds the object."""
    out = {}
    scale = np.diag([radius, radius, radius, 1.0])
    scale[:3, 3] = centre
    for i, cam in enumerate(cameras):
        fx, fy, cx, cy = cam.intrinsics()
        k = np.array([[fx, 0, cx - 0.5], [0, fy, cy - 0.5], [0, 0, 1]])
        c2w = cam.to_world @ OPENCV_TO_MITSUBA
        w2c = np.linalg.inv(c2w)
        p = np.eye(4)
        p[:3, :4] = k @ w2c[:3, :4]
        out[f"world_mat_{i}"] = p
        out[f"scale_mat_{i}"] = scale
    written(path, lambda: np.savez(path, **out))


def write_capture(capture: Capture, folder: Path, names: list[str], centre: np.ndarray, radius: float) -> Path:
    """`capture`'s views as a NeuS/IDR folder in the capture's own world: image/NAME.png,
    mask/NAME.png and cameras_sphere.npz whose scale matrices take the unit sphere to (centre,
    radius)."""
    for i, name in enumerate(names):
        write_png(folder / "image" / f"{name}.png", capture.images[i])
        write_png(folder / "mask" / f"{name}.png", capture.alpha[i], srgb=False)
    write_idr(folder / "cameras_sphere.npz", capture.cameras, centre, radius)
    return folder
