"""COLMAP: a sparse model (binary or text) and the photos it registers, in COLMAP's world.

    images/a/000.png      the photos, named as images.bin/.txt names them (one size for all
                          after undistortion)
    masks/a/000.png.png   optional masks, for all photos or none (or masks/a/000.png)
    sparse/0/cameras.bin  the lenses (SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV,
    sparse/0/images.bin   OPENCV_FISHEYE), the registered images' poses and, optionally,
    sparse/0/points3D.bin the sparse points (each also as .txt; the model may lie in sparse/ or
                          the folder itself)
    mesh.ply              known geometry (optional), in COLMAP's world

COLMAP uses OpenCV camera axes (+X right, +Y down, +Z forward; vq_mitsuba.data.cameras.
OPENCV_TO_MITSUBA) and puts pixel centres at +0.5 as we do. Photos taken through a distorting
lens are undistorted once into the pinhole camera of the same intrinsics (vq_mitsuba.data.lens).
Everything read is checked before any work (vq_mitsuba.data.checks, `check_lens`, and
`_check_colmap_image` for quaternions and image entries).
"""

from __future__ import annotations

import io
import math
import struct
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path, PurePosixPath

import numpy as np

from vq_mitsuba.data.cameras import OPENCV_TO_MITSUBA, Camera, camera_from_intrinsics
from vq_mitsuba.data.checks import check_pose, check_unique, collect
from vq_mitsuba.data.formats.common import Capture, mesh_beside, known_mesh, moved_camera, read_views, up_frame
from vq_mitsuba.data.imageio import write_png, written
from vq_mitsuba.data.lens import MODEL_IDS, MODELS, Lens, check_lens, distort_rgba
from vq_mitsuba.errors import InputError, raise_all

KIND = "colmap"
SUFFIXES = ()  # a folder
FOLDER_FILES = ()
DESCRIPTION = "a COLMAP model (in sparse/0/, sparse/ or the folder)"  # what a person gives, in messages and help
POSED = True
sphere = None  # no region of interest (points: the sparse model's)
has_geometry = mesh_beside  # known geometry: a mesh.ply in the capture's folder
# COLMAP's models we do not read, named when refused
OTHER_MODELS = {6: "FULL_OPENCV", 7: "FOV", 8: "SIMPLE_RADIAL_FISHEYE", 9: "RADIAL_FISHEYE",
                10: "THIN_PRISM_FISHEYE"}


def detect(source: Path) -> bool:
    return source.is_dir() and colmap_model_dir(source) is not None


def cameras(folder: Path) -> tuple[list[Camera], str]:
    """(the registered images' pinhole cameras, "mitsuba")."""
    return _colmap_views(folder)[0], "mitsuba"


def load(folder: Path, mesh_arg, shrink=None, cache_dir=None) -> Capture:
    """The capture: the registered photos, undistorted (and cached in `cache_dir`) where their lens
    distorts, masks multiplied into alpha, each shrunk as it is read; the envmap's up is the
    cameras' mean up."""
    cameras, paths, masks, lenses = _colmap_views(folder)
    images, alpha, has_alpha = read_views(folder, cameras, paths, masks, lenses, cache_dir, shrink)
    return Capture(folder, cameras, images, alpha, has_alpha, known_mesh(mesh_arg, folder), None, up_frame(cameras),
                   "mitsuba")


def points(folder: Path) -> tuple[np.ndarray, np.ndarray] | None:
    """The model's sparse points (`read_colmap_points`), None without a points file."""
    return read_colmap_points(colmap_model_dir(folder))


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
        # a photo missing with its mask is the photo missing, not a mask
        images_file = model / ("images.bin" if (model / "cameras.bin").is_file() else "images.txt")  # as read_colmap
        raise_all([InputError(p, f"image missing: {images_file.name} registers it but images/ has no such file")
                   for p, m in zip(paths, masks) if m is None and not p.is_file()], image_dir)
        missing = next(p for p, m in zip(paths, masks) if m is None)
        raise InputError(folder / "masks", f"has masks for some images but not for {missing.name}: "
                                           "give every image a mask or none")
    return cameras, paths, masks, used


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


# What the pose stage writes, a capture this module reads: the photos in IMAGES, the model in MODEL.
IMAGES, MODEL = "images", Path("sparse") / "0"
OWN_ENTRIES = (IMAGES, MODEL.parts[0])  # the layout's top-level entries


def _holds_cameras(model: Path) -> bool:
    return any((model / f"cameras.{e}").is_file() for e in ("bin", "txt"))


def has_model(folder: Path) -> bool:
    """Whether FOLDER/MODEL holds a model's cameras (the layout the pose stage writes)."""
    return _holds_cameras(folder / MODEL)


def colmap_model_dir(folder: Path) -> Path | None:
    """The folder holding cameras.bin/.txt and images.bin/.txt: `sparse/0`, `sparse`, or the folder."""
    return next((c for c in (folder / MODEL, folder / MODEL.parent, folder) if _holds_cameras(c)), None)


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


@contextmanager
def _written_binary(path: Path):
    """A buffer whose bytes become `path` once filled (a refused write names the file: `written`)."""
    buffer = io.BytesIO()
    yield buffer
    written(path, lambda: path.write_bytes(buffer.getvalue()))


def _written_text(path: Path, text: str) -> None:
    written(path, lambda: path.write_text(text))


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
        with _written_binary(model / "cameras.bin") as f:
            f.write(struct.pack("<Q", len(lenses)))
            for i, lens in enumerate(lenses):
                f.write(struct.pack("<iiQQ", i + 1, MODEL_IDS[lens.model], lens.width, lens.height))
                f.write(struct.pack("<" + "d" * len(lens.params()), *lens.params()))
        with _written_binary(model / "images.bin") as f:
            f.write(struct.pack("<Q", len(names)))
            for i, (name, (q, t)) in enumerate(zip(names, poses)):
                f.write(struct.pack("<idddddddi", i + 1, *q, *t, i + 1))
                f.write(name.encode() + b"\x00")
                f.write(struct.pack("<Q", 0))
        with _written_binary(model / "points3D.bin") as f:
            f.write(struct.pack("<Q", len(pts)))
            for i, p in enumerate(pts):
                f.write(struct.pack("<QdddBBBdQ", i + 1, *p, 128, 128, 128, 0.0, 0))
    else:
        _written_text(model / "cameras.txt", "# CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n" + "".join(
            f"{i + 1} {lens.model} {lens.width} {lens.height} " + " ".join(f"{p:.17g}" for p in lens.params()) + "\n"
            for i, lens in enumerate(lenses)))
        _written_text(model / "images.txt", "# IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n" + "".join(
            f"{i + 1} " + " ".join(f"{v:.17g}" for v in (*q, *t)) + f" {i + 1} {name}\n\n"
            for i, (name, (q, t)) in enumerate(zip(names, poses))))
        _written_text(model / "points3D.txt", "# POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[]\n" + "".join(
            f"{i + 1} {p[0]:.17g} {p[1]:.17g} {p[2]:.17g} 128 128 128 0\n" for i, p in enumerate(pts)))


def write_capture(capture: Capture, folder: Path, names: list[str], sim: np.ndarray, binary: bool = True,
                  lens_of=None) -> Path:
    """`capture`'s views as a COLMAP folder in the frame of the similarity `sim` (world -> its
    world): images/NAME.png (seen through `lens_of(camera)` when given, else PINHOLE),
    masks/NAME.png.png, a binary or text model in sparse/0 with some of the mesh's vertices as
    its points."""
    moved = [moved_camera(c, sim) for c in capture.cameras]
    files = [f"{n}.png" for n in names]
    for i, f in enumerate(files):
        rgb, alpha = distort_rgba(capture.images[i], capture.alpha[i],
                                  lens_of(capture.cameras[i]) if lens_of is not None else None)
        write_png(folder / "images" / f, np.clip(rgb, 0, None))
        write_png(folder / "masks" / f"{f}.png", alpha, srgb=False)
    pts = None
    if capture.mesh is not None:
        v = np.asarray(capture.mesh.vertices)[:: max(1, len(capture.mesh.vertices) // 200)]
        pts = v @ sim[:3, :3].T + sim[:3, 3]
    write_colmap(folder / "sparse" / "0", moved, files, lens_of=lens_of, binary=binary, points=pts)
    return folder
