"""Camera files of photographed captures: COLMAP sparse models (binary and text) and the NeuS/IDR
`cameras_sphere.npz`, read into Mitsuba-convention `Camera`s, and written (for test data).

COLMAP and IDR use OpenCV camera axes (+X right, +Y down, +Z forward); a Mitsuba camera has +X
left and +Y up, so camera-to-world matrices differ by diag(-1, -1, 1). COLMAP puts pixel centres
at +0.5 as we do; IDR intrinsics put them at integer coordinates (NeuS casts rays through
integer pixel positions), so their principal point is shifted by half a pixel on reading.

Everything read is checked before any work (vq_mitsuba.data.checks, plus `check_lens` for the
distortion and `_check_colmap_image` for quaternions and image entries).
"""

from __future__ import annotations

import math
import struct
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path, PurePosixPath

import numpy as np

from vq_mitsuba.data.cameras import Camera
from vq_mitsuba.data.checks import check_intrinsics, check_pose, check_unique, collect, finite_number
from vq_mitsuba.errors import InputError, raise_all

OPENCV_TO_MITSUBA = np.diag([-1.0, -1.0, 1.0, 1.0])

# COLMAP camera models we read: id -> (name, parameter names)
MODELS = {
    0: ("SIMPLE_PINHOLE", ("f", "cx", "cy")),
    1: ("PINHOLE", ("fx", "fy", "cx", "cy")),
    2: ("SIMPLE_RADIAL", ("f", "cx", "cy", "k")),
    3: ("RADIAL", ("f", "cx", "cy", "k1", "k2")),
    4: ("OPENCV", ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2")),
    5: ("OPENCV_FISHEYE", ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4")),
}
MODEL_IDS = {name: i for i, (name, _) in MODELS.items()}
OTHER_MODELS = {6: "FULL_OPENCV", 7: "FOV", 8: "SIMPLE_RADIAL_FISHEYE", 9: "RADIAL_FISHEYE",
                10: "THIN_PRISM_FISHEYE"}
FISHEYE = "OPENCV_FISHEYE"  # equidistant projection, k1..k4 on the angle theta (COLMAP's and OpenCV's model)
DISTORTION = ("k1", "k2", "k3", "k4", "p1", "p2")


def camera_from_intrinsics(name: str, to_world: np.ndarray, fx: float, fy: float, cx: float, cy: float,
                           width: int, height: int) -> Camera:
    """A Camera from pixel intrinsics (pixel centres at +0.5)."""
    fov_x = math.degrees(2.0 * math.atan(0.5 * width / fx))
    centred = abs(cx - 0.5 * width) < 1e-9 and abs(cy - 0.5 * height) < 1e-9
    return Camera(name, np.asarray(to_world, np.float64), fov_x, int(width), int(height), focal_y_ratio=fy / fx,
                  principal=None if centred else (float(cx), float(cy)))


# --------------------------------------------------------------------------------------------
# Lens distortion (COLMAP's models, on normalised image coordinates)

@dataclass
class Lens:
    """One camera's lens: pinhole intrinsics plus distortion. The perspective models (COLMAP's
    SIMPLE_RADIAL, RADIAL, OPENCV; nerfstudio's PINHOLE and OPENCV) scale a point at radius r by
    1 + k1 r^2 + k2 r^4 + k3 r^6 + k4 r^8 and add the tangential p1, p2 terms; OPENCV_FISHEYE maps
    the angle theta = atan(r) to theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8)."""

    model: str
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    k1: float = 0.0
    k2: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    k3: float = 0.0
    k4: float = 0.0

    @property
    def distorted(self) -> bool:
        return self.model == FISHEYE or any(abs(getattr(self, n)) > 0 for n in DISTORTION)

    def params(self) -> list[float]:
        values = {"f": self.fx, "fx": self.fx, "fy": self.fy, "cx": self.cx, "cy": self.cy, "k": self.k1,
                  **{n: getattr(self, n) for n in DISTORTION}}
        return [values[n] for n in MODELS[MODEL_IDS[self.model]][1]]

    @staticmethod
    def from_params(model: str, width: int, height: int, params) -> Lens:
        names = MODELS[MODEL_IDS[model]][1]
        v = dict(zip(names, (float(p) for p in params)))
        fx = v.get("fx", v.get("f"))
        fy = v.get("fy", v.get("f"))
        return Lens(model, int(width), int(height), fx, fy, v["cx"], v["cy"], v.get("k1", v.get("k", 0.0)),
                    v.get("k2", 0.0), v.get("p1", 0.0), v.get("p2", 0.0), v.get("k3", 0.0), v.get("k4", 0.0))

    def _radial(self, x2: np.ndarray) -> np.ndarray:
        return 1.0 + x2 * (self.k1 + x2 * (self.k2 + x2 * (self.k3 + x2 * self.k4)))

    def distort(self, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Normalised undistorted coordinates -> distorted ones."""
        r2 = u * u + v * v
        if self.model == FISHEYE:
            r = np.sqrt(r2)
            theta = np.arctan(r)
            scale = np.where(r > 1e-12, theta * self._radial(theta * theta) / np.maximum(r, 1e-12), 1.0)
            return u * scale, v * scale
        radial = self._radial(r2) - 1.0
        du = u * radial + 2 * self.p1 * u * v + self.p2 * (r2 + 2 * u * u)
        dv = v * radial + 2 * self.p2 * u * v + self.p1 * (r2 + 2 * v * v)
        return u + du, v + dv

    def undistort(self, ud: np.ndarray, vd: np.ndarray, iterations: int = 12) -> tuple[np.ndarray, np.ndarray]:
        """Inverse of `distort` (Newton's method with a numerical Jacobian, as COLMAP does)."""
        u, v = ud.copy(), vd.copy()
        eps = 1e-9
        for _ in range(iterations):
            fu, fv = self.distort(u, v)
            ru, rv = fu - ud, fv - vd
            a, c = ((x - y) / eps for x, y in zip(self.distort(u + eps, v), (fu, fv)))
            b, d = ((x - y) / eps for x, y in zip(self.distort(u, v + eps), (fu, fv)))
            det = a * d - b * c
            det = np.where(np.abs(det) < 1e-12, 1e-12, det)
            u, v = u - (d * ru - b * rv) / det, v - (-c * ru + a * rv) / det
        return u, v

    def pixel_to_normalised(self, x, y):
        return (np.asarray(x, np.float64) - self.cx) / self.fx, (np.asarray(y, np.float64) - self.cy) / self.fy

    def normalised_to_pixel(self, u, v):
        return u * self.fx + self.cx, v * self.fy + self.cy


# Plausible distortion: over the whole image the lens keeps every point within a factor
# MAX_RADIAL_SCALE of its distance from the principal point, and stays one-to-one (a positive
# Jacobian), which undistortion needs. Wide-angle lenses that COLMAP's OPENCV model fits stay well
# inside (k1 = -0.25, k2 = 0.06 scale the corners of a 4:3 view 100 degrees wide by 0.74); k1 = 50
# on a 4:3 view 60 degrees wide scales them by 27.
MAX_RADIAL_SCALE = 2.0


def check_lens(path: Path, entry: str, lens: Lens) -> None:
    """A COLMAP camera: intrinsics (vq_mitsuba.data.checks), finite and plausible distortion."""
    check_intrinsics(path, entry, lens.fx, lens.fy, lens.cx, lens.cy, lens.width, lens.height)
    for name in DISTORTION:
        if not finite_number(getattr(lens, name)):
            raise InputError(path, f"{entry}: distortion {name} = {getattr(lens, name)!r} is not a finite number")
    if not lens.distorted:
        return
    xs, ys = np.meshgrid(np.linspace(0, lens.width, 17), np.linspace(0, lens.height, 17))
    u, v = lens.pixel_to_normalised(xs, ys)
    eps = 1e-6
    with np.errstate(all="ignore"):  # overflow becomes inf, refused below
        du, dv = lens.distort(u, v)
        r = np.hypot(u, v)
        ideal = np.arctan(r) if lens.model == FISHEYE else r  # a fisheye's own projection is no distortion
        scale = np.hypot(du, dv)[r > 1e-9] / ideal[r > 1e-9]
        (a, c), (b, d) = (((x - y) / eps for x, y in zip(moved, (du, dv)))
                          for moved in (lens.distort(u + eps, v), lens.distort(u, v + eps)))
        folds = not np.all(a * d - b * c > 0)
    coefficients = ", ".join(f"{n} = {getattr(lens, n):g}" for n in DISTORTION if n in ("k1", "k2", "p1", "p2")
                             or getattr(lens, n) != 0)
    if not np.all((scale >= 1 / MAX_RADIAL_SCALE) & (scale <= MAX_RADIAL_SCALE)):
        worst = scale[np.argmax(np.abs(np.log(np.nan_to_num(scale, nan=np.inf) + 1e-300)))]
        raise InputError(path, f"{entry}: implausible distortion ({coefficients}): it moves image points to "
                               f"{worst:.3g} times their distance from the principal point (a real lens stays "
                               f"within {1 / MAX_RADIAL_SCALE:g}..{MAX_RADIAL_SCALE:g})")
    if folds:
        raise InputError(path, f"{entry}: implausible distortion ({coefficients}): it folds the image over "
                               "(not one-to-one), so it cannot be undone")


def resample(image: np.ndarray, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Bilinear samples of `image` (H, W, C) at pixel positions x, y (pixel centres at +0.5), and a
    mask of the positions that lie inside the image."""
    from scipy.ndimage import map_coordinates

    h, w = image.shape[:2]
    inside = (x >= 0) & (x <= w) & (y >= 0) & (y <= h)
    coords = np.stack([np.clip(y - 0.5, 0, h - 1), np.clip(x - 0.5, 0, w - 1)])
    out = np.stack([map_coordinates(image[..., c], coords, order=1, mode="nearest") for c in range(image.shape[-1])], -1)
    return out.astype(np.float32), inside


def undistort_image(image: np.ndarray, lens: Lens) -> tuple[np.ndarray, np.ndarray]:
    """The image (H, W, C) as the pinhole camera of the same intrinsics sees it, and (H, W) the
    share of it that the distorted image covers (1 inside, 0 where no source pixel exists)."""
    ys, xs = np.meshgrid(np.arange(lens.height) + 0.5, np.arange(lens.width) + 0.5, indexing="ij")
    ud, vd = lens.distort(*lens.pixel_to_normalised(xs, ys))
    sx, sy = lens.normalised_to_pixel(ud, vd)
    out, inside = resample(image, sx, sy)
    return out, inside.astype(np.float32)


def distort_image(image: np.ndarray, lens: Lens) -> np.ndarray:
    """Inverse of `undistort_image`: what the distorted lens records of a pinhole image."""
    ys, xs = np.meshgrid(np.arange(lens.height) + 0.5, np.arange(lens.width) + 0.5, indexing="ij")
    u, v = lens.undistort(*lens.pixel_to_normalised(xs, ys))
    sx, sy = lens.normalised_to_pixel(u, v)
    out, _ = resample(image, sx, sy)
    return out


# --------------------------------------------------------------------------------------------
# COLMAP sparse models

@dataclass
class ColmapImage:
    name: str
    camera_id: int
    qvec: np.ndarray  # (w, x, y, z): world-to-camera rotation
    tvec: np.ndarray  # world-to-camera translation
    image_id: int = 0


def qvec_to_matrix(q) -> np.ndarray:
    w, x, y, z = np.asarray(q, np.float64) / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def matrix_to_qvec(r: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(r).as_quat()
    q = np.array([w, x, y, z])
    return q if q[0] >= 0 else -q


def colmap_model_dir(folder: Path) -> Path | None:
    """The folder holding cameras.bin/.txt and images.bin/.txt: `sparse/0`, `sparse`, or the folder."""
    for candidate in (folder / "sparse" / "0", folder / "sparse", folder):
        if any((candidate / f"cameras.{e}").is_file() for e in ("bin", "txt")):
            return candidate
    return None


def read_colmap(model: Path) -> tuple[dict[int, Lens], list[ColmapImage]]:
    """Cameras and registered images of a sparse model (binary preferred over text), checked."""
    binary = (model / "cameras.bin").is_file()
    ext = "bin" if binary else "txt"
    cameras_file, images_file = model / f"cameras.{ext}", model / f"images.{ext}"
    lenses = _read_colmap_file(cameras_file, _read_cameras_bin if binary else _read_cameras_txt)
    images = _read_colmap_file(images_file, _read_images_bin if binary else _read_images_txt)
    _check_colmap(cameras_file, images_file, lenses, images)
    return lenses, sorted(images, key=lambda i: i.name)


def _read_colmap_file(path: Path, reader):
    """`reader(path)`, with every way a file can be broken reported as an InputError naming it."""
    which = "binary" if path.suffix == ".bin" else "text"
    try:
        return reader(path)
    except InputError:
        raise
    except FileNotFoundError:
        raise InputError(path, "missing: a COLMAP model needs cameras and images files") from None
    except (OSError, struct.error, ValueError, IndexError, UnicodeDecodeError, OverflowError, MemoryError) as exc:
        raise InputError(path, f"cannot read the COLMAP {which} model ({type(exc).__name__}: {exc})") from None


def _check_colmap(cameras_file: Path, images_file: Path, lenses: dict[int, Lens], images: list[ColmapImage]) -> None:
    """Every camera and every image entry of a model; all problems reported at once."""
    problems: list[InputError] = []
    for cid, lens in lenses.items():
        collect(problems, check_lens, cameras_file, f"camera {cid} ({lens.model})", lens)
    if not images:
        problems.append(InputError(images_file, "the COLMAP model registers no images"))
    collect(problems, check_unique, images_file, "image name", [img.name for img in images])
    collect(problems, check_unique, images_file, "image id", [img.image_id for img in images])
    for img in images:
        collect(problems, _check_colmap_image, images_file, img, lenses)
    raise_all(problems, cameras_file.parent)


def _check_colmap_image(path: Path, img: ColmapImage, lenses: dict[int, Lens]) -> None:
    """One image entry: a name, a listed camera, a quaternion that normalises, a finite translation."""
    entry = f"image {img.image_id} ({img.name!r})"
    if not img.name.strip() or Path(img.name).is_absolute() or ".." in Path(img.name).parts:
        raise InputError(path, f"{entry}: the name must be a file name under images/")
    if img.camera_id not in lenses:
        raise InputError(path, f"{entry} refers to camera {img.camera_id}, which "
                               f"{path.with_name('cameras' + path.suffix).name} does not list")
    q = np.asarray(img.qvec, np.float64)
    largest = float(np.abs(q).max())
    norm = largest * float(np.linalg.norm(q / largest)) if 0 < largest < math.inf else largest  # no overflow
    if not 1e-6 <= norm <= 1e6:
        raise InputError(path, f"{entry}: quaternion (QW, QX, QY, QZ) = ({', '.join(f'{v:g}' for v in q)}) "
                               "is not a rotation (it must be finite and not zero)")
    t = np.asarray(img.tvec, np.float64)
    if not np.all(np.isfinite(t)):
        raise InputError(path, f"{entry}: translation (TX, TY, TZ) = ({', '.join(f'{v:g}' for v in t)}) "
                               "is not finite")
    check_pose(path, entry, colmap_to_world(img))


def _model(path: Path, model_id_or_name) -> str:
    if isinstance(model_id_or_name, int) or str(model_id_or_name).isdigit():
        mid = int(model_id_or_name)
        if mid in MODELS:
            return MODELS[mid][0]
        name = OTHER_MODELS.get(mid, f"model id {mid}")
    else:
        name = str(model_id_or_name)
        if name in MODEL_IDS:
            return name
    raise InputError(path, f"camera model {name} is not supported (use {', '.join(MODEL_IDS)}; COLMAP's "
                           "image_undistorter turns any model into PINHOLE)")


def _read_cameras_txt(path: Path) -> dict[int, Lens]:
    entries = []
    for number, line in enumerate(path.read_text().splitlines(), 1):
        if not line.strip() or line.startswith("#"):
            continue
        parts = line.split()
        try:
            cid, model, w, h = int(parts[0]), _model(path, parts[1]), int(parts[2]), int(parts[3])
            params = [float(p) for p in parts[4:]]
        except (ValueError, IndexError):
            raise InputError(path, f"line {number} ('{line[:60]}') is not CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]") \
                from None
        names = MODELS[MODEL_IDS[model]][1]
        if len(params) != len(names):
            raise InputError(path, f"camera {cid}: {model} has {len(names)} parameters ({' '.join(names)}), "
                                   f"got {len(params)}")
        entries.append((cid, Lens.from_params(model, w, h, params)))
    return _by_id(path, entries)


def _by_id(path: Path, entries: list[tuple[int, Lens]]) -> dict[int, Lens]:
    check_unique(path, "camera id", [cid for cid, _ in entries])
    return dict(entries)


def _read_images_txt(path: Path) -> list[ColmapImage]:
    """images.txt: two lines per image, the image line and its POINTS2D line (X Y POINT3D_ID
    triples, possibly empty). A second image line where a POINTS2D line belongs is refused: read
    as its points, every second image would be lost."""
    out = []
    points_of = None  # the image whose POINTS2D line comes next
    for number, line in enumerate(path.read_text().splitlines(), 1):
        if line.startswith("#"):
            continue
        parts = line.split()
        if points_of is not None:
            if not _points2d_line(parts):
                if _image_line(parts) is not None:
                    raise InputError(path, f"line {number} is an image line where the POINTS2D line of image "
                                           f"{points_of} belongs: images.txt holds two lines per image (the second "
                                           "lists X Y POINT3D_ID ... and may be empty)")
                raise InputError(path, f"line {number} ('{line[:60]}') is not the POINTS2D line of image "
                                       f"{points_of} (X Y POINT3D_ID triples, or empty)")
            points_of = None
            continue
        if not parts:
            continue
        image = _image_line(parts)
        if image is None:
            raise InputError(path, f"line {number} ('{line[:60]}') is not IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID "
                                   "NAME")
        out.append(image)
        points_of = image.image_id
    return out


def _image_line(parts: list[str]) -> ColmapImage | None:
    """An images.txt image line (IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME), or None."""
    try:
        if len(parts) < 10:
            raise ValueError
        return ColmapImage(" ".join(parts[9:]), int(parts[8]), np.array(parts[1:5], np.float64),
                           np.array(parts[5:8], np.float64), int(parts[0]))
    except ValueError:
        return None


def _points2d_line(parts: list[str]) -> bool:
    """Whether the tokens are X Y POINT3D_ID triples (none at all included). Only the ids are
    looked at (whole numbers, -1 for none); an image line has them only by chance (integral QX and
    TX and a name of three words or more)."""
    return len(parts) % 3 == 0 and all(t.removeprefix("-").isdigit() for t in parts[2::3])


def _read(f, fmt):
    size = struct.calcsize(fmt)
    data = f.read(size)
    if len(data) != size:
        raise ValueError("file ends early")
    return struct.unpack(fmt, data)


def _read_cameras_bin(path: Path) -> dict[int, Lens]:
    entries = []
    with open(path, "rb") as f:
        (n,) = _read(f, "<Q")
        for _ in range(n):
            cid, mid, w, h = _read(f, "<iiQQ")
            model = _model(path, mid)
            params = _read(f, "<" + "d" * len(MODELS[mid][1]))
            entries.append((cid, Lens.from_params(model, w, h, params)))
    return _by_id(path, entries)


def _read_images_bin(path: Path) -> list[ColmapImage]:
    out = []
    with open(path, "rb") as f:
        (n,) = _read(f, "<Q")
        for _ in range(n):
            values = _read(f, "<idddddddi")
            name = b""
            while (c := f.read(1)) not in (b"\x00", b""):
                name += c
            (npts,) = _read(f, "<Q")
            f.seek(24 * npts, 1)
            out.append(ColmapImage(name.decode(), values[8], np.array(values[1:5]), np.array(values[5:8]), values[0]))
    return out


def read_colmap_points(model: Path) -> tuple[np.ndarray, np.ndarray] | None:
    """The sparse points of a model (points3D.bin, else .txt): positions (N, 3) in the cameras' world
    and the number of images seeing each (its track length); None without a points file."""
    binary, text = model / "points3D.bin", model / "points3D.txt"
    path = binary if binary.is_file() else text if text.is_file() else None
    if path is None:
        return None
    return _read_colmap_file(path, _read_points_bin if path is binary else _read_points_txt)


def _read_points_bin(path: Path) -> tuple[np.ndarray, np.ndarray]:
    xyz, track = [], []
    with open(path, "rb") as f:
        (n,) = _read(f, "<Q")
        for _ in range(n):
            values = _read(f, "<QdddBBBdQ")
            xyz.append(values[1:4])
            track.append(values[8])
            f.seek(8 * values[8], 1)  # (image id, point index) pairs
    return _points(path, xyz, track)


def _read_points_txt(path: Path) -> tuple[np.ndarray, np.ndarray]:
    xyz, track = [], []
    for number, line in enumerate(path.read_text().splitlines(), 1):
        if not line.strip() or line.startswith("#"):
            continue
        parts = line.split()
        try:
            xyz.append([float(v) for v in parts[1:4]])
            if len(xyz[-1]) != 3 or len(parts) < 8:
                raise ValueError
        except ValueError:
            raise InputError(path, f"line {number} ('{line[:60]}') is not POINT3D_ID X Y Z R G B ERROR TRACK[]") \
                from None
        track.append((len(parts) - 8) // 2)
    return _points(path, xyz, track)


def _points(path: Path, xyz: list, track: list) -> tuple[np.ndarray, np.ndarray]:
    pts = np.asarray(xyz, np.float64).reshape(-1, 3)
    if not np.isfinite(pts).all():
        raise InputError(path, "holds a point with a non-finite coordinate")
    return pts, np.asarray(track, np.int64)


def colmap_to_world(img: ColmapImage) -> np.ndarray:
    """(4, 4) camera-to-world matrix, in OpenCV camera axes, of one registered image."""
    r = qvec_to_matrix(img.qvec)
    c2w = np.eye(4)
    c2w[:3, :3] = r.T
    c2w[:3, 3] = -r.T @ img.tvec
    return c2w


def colmap_camera(img: ColmapImage, lens: Lens) -> Camera:
    """The pinhole (undistorted) Mitsuba camera of one registered image, named by the image's path
    under images/ without its suffix (`a/000.png` is `a/000`, `b/000.png` `b/000`)."""
    name = str(PurePosixPath(img.name).with_suffix("")) if PurePosixPath(img.name).suffix else img.name
    return camera_from_intrinsics(name, colmap_to_world(img) @ OPENCV_TO_MITSUBA, lens.fx, lens.fy,
                                  lens.cx, lens.cy, lens.width, lens.height)


def write_colmap(model: Path, cameras: list[Camera], names: list[str], lens_of=None, binary: bool = True,
                 points: np.ndarray | None = None) -> None:
    """Write a sparse model: one camera entry per view (`lens_of(camera)` gives its Lens, default
    PINHOLE from the camera), images named `names`, optional 3D points (N, 3)."""
    model.mkdir(parents=True, exist_ok=True)
    lenses = []
    for cam in cameras:
        if lens_of is not None:
            lenses.append(lens_of(cam))
        else:
            fx, fy, cx, cy = cam.intrinsics()
            lenses.append(Lens("PINHOLE", cam.width, cam.height, fx, fy, cx, cy))
    poses = []
    for cam in cameras:
        c2w = cam.to_world @ OPENCV_TO_MITSUBA  # OpenCV camera-to-world
        r = c2w[:3, :3].T
        poses.append((matrix_to_qvec(r), -r @ c2w[:3, 3]))
    pts = np.zeros((0, 3)) if points is None else np.asarray(points, np.float64)
    if binary:
        with open(model / "cameras.bin", "wb") as f:
            f.write(struct.pack("<Q", len(lenses)))
            for i, lens in enumerate(lenses):
                f.write(struct.pack("<iiQQ", i + 1, MODEL_IDS[lens.model], lens.width, lens.height))
                f.write(struct.pack("<" + "d" * len(lens.params()), *lens.params()))
        with open(model / "images.bin", "wb") as f:
            f.write(struct.pack("<Q", len(names)))
            for i, (name, (q, t)) in enumerate(zip(names, poses)):
                f.write(struct.pack("<idddddddi", i + 1, *q, *t, i + 1))
                f.write(name.encode() + b"\x00")
                f.write(struct.pack("<Q", 0))
        with open(model / "points3D.bin", "wb") as f:
            f.write(struct.pack("<Q", len(pts)))
            for i, p in enumerate(pts):
                f.write(struct.pack("<QdddBBBdQ", i + 1, *p, 128, 128, 128, 0.0, 0))
    else:
        (model / "cameras.txt").write_text("# CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n" + "".join(
            f"{i + 1} {lens.model} {lens.width} {lens.height} " + " ".join(f"{p:.17g}" for p in lens.params()) + "\n"
            for i, lens in enumerate(lenses)))
        (model / "images.txt").write_text("# IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n" + "".join(
            f"{i + 1} " + " ".join(f"{v:.17g}" for v in (*q, *t)) + f" {i + 1} {name}\n\n"
            for i, (name, (q, t)) in enumerate(zip(names, poses))))
        (model / "points3D.txt").write_text("# POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[]\n" + "".join(
            f"{i + 1} {p[0]:.17g} {p[1]:.17g} {p[2]:.17g} 128 128 128 0\n" for i, p in enumerate(pts)))


# --------------------------------------------------------------------------------------------
# NeuS / IDR: cameras_sphere.npz

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
    """One matrix of the archive: numbers (no strings, no pickled objects), one of `shapes`, finite."""
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
    np.savez(path, **out)
