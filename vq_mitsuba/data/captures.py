"""Captures: posed reference images plus optional known geometry and lighting.

A capture is one of the formats in vq_mitsuba.data.formats, each a module whose docstring shows
the folder layout it reads: a Mitsuba scene XML (`mitsuba_xml`; Mitsuba world), a NeRF-synthetic
`transforms_*.json` (`nerf_synthetic`; OpenGL camera axes, Blender world with Z up), a nerfstudio
`transforms.json` (`nerfstudio`: pixel intrinsics, lens distortion, masks), a photographed
capture (`colmap`, `idr` for NeuS/IDR, `llff`), or photos or a video without poses (`photos`,
`video`, which the loaders refuse: vq_mitsuba.geometry.poses finds their poses). `open_capture`
resolves a path once into a `CaptureSource`, the one value the pose, geometry and material stages
take: its format (found in the registry `FORMATS`), what it says of its geometry and framing, and
its images, read once and kept for every split; `load_capture` and `load_cameras` are the one-call
forms.
Known geometry besides an XML's shapes: a `mesh=` argument, else a `mesh.ply` in the capture's
folder, in the capture's world. Images are shrunk as they are read (capture.downscale,
capture.max_size: vq_mitsuba.data.resize). Views are named by vq_mitsuba.data.names (file-safe,
unique). Everything is validated before returning, and every problem is an InputError naming the
offending file.
"""

from __future__ import annotations

import errno
import functools
from dataclasses import dataclass, field, replace
from pathlib import Path
from types import ModuleType

import numpy as np

from vq_mitsuba.config import CaptureConfig
from vq_mitsuba.data.cameras import Camera
from vq_mitsuba.data.checks import check_viewpoints
from vq_mitsuba.data.dataset_dir import DatasetDir
from vq_mitsuba.data.formats import FORMATS, described, folder_files, format_of, known_suffix
from vq_mitsuba.data.formats.common import Capture, load_mesh
from vq_mitsuba.data.names import view_names
from vq_mitsuba.data.resize import Shrink
from vq_mitsuba.data.unposed import unposed_error
from vq_mitsuba.errors import InputError, warn

# re-exported: the loaded capture and mesh (vq_mitsuba.data.formats.common)
__all__ = ["Capture", "CaptureSource", "open_capture", "load_mesh", "load_capture", "load_cameras", "named_views", "capture_kind",
           "resolve_capture_path", "check_one_capture", "split_indices", "finish_capture"]


def _read_errors_named(read):
    """`read` with an OSError from the file system (a name longer than it takes, a folder this process
    may not read) as the InputError naming the file; a full or read-only disk (the undistorted
    photos' cache) stays a write error."""

    @functools.wraps(read)
    def reading(first, *args, **kwargs):
        try:
            return read(first, *args, **kwargs)
        except OSError as exc:
            if exc.errno in (errno.ENOSPC, errno.EDQUOT, errno.EROFS):
                raise
            where = exc.filename if exc.filename is not None else getattr(first, "source", first)
            raise InputError(where, f"cannot be read ({exc.strerror or exc})") from None

    return reading


@dataclass(frozen=True)
class CaptureSource:
    """A capture resolved once (`open_capture`): the path as given, the file or folder it resolved
    to, its format module, the known geometry given with it (`mesh`, None: the capture's own), the
    options it is read with (size, background keying, held-out views) and where undistorted photos
    are cached. The stages ask it, never the path: `posed`, `has_geometry`, `framing`, `cameras`
    and `load` (the images read once on the first `load`, then every split and `with_mesh` copy
    taken from that read)."""

    given: Path
    source: Path
    format: ModuleType
    options: CaptureConfig
    mesh: Path | None = None
    cache_dir: Path | None = None
    _read: dict = field(default_factory=dict, repr=False, compare=False)  # shared by with_mesh copies

    @property
    def posed(self) -> bool:
        """False for photos or a video without camera poses (the pose stage poses them)."""
        return bool(self.format.POSED)

    def _posed_format(self) -> ModuleType:
        if not self.posed:
            raise unposed_error(self.source)
        return self.format

    @_read_errors_named
    def has_geometry(self) -> bool:
        """Whether the fit has geometry without reconstructing it: a `mesh` given, or the capture's own
        (a scene XML's shapes, a mesh.ply in its folder). Reads no image."""
        return self.mesh is not None or (self.posed and self.format.has_geometry(self.source))

    @_read_errors_named
    def framing(self) -> tuple[tuple[np.ndarray, np.ndarray] | None, tuple[np.ndarray, float, str] | None]:
        """What the capture's own files say of where the object is: (its sparse points (N, 3) and each
        one's track length, or None; the region of interest (centre, radius, what gives it), or None)."""
        if "framing" not in self._read:
            fmt = self.format
            points = fmt.points(self.source) if self.posed and fmt.points is not None else None
            sphere = fmt.sphere(self.source) if self.posed and fmt.sphere is not None else None
            self._read["framing"] = (points, sphere)
        return self._read["framing"]

    @_read_errors_named
    def cameras(self, split: str = "all") -> tuple[list[Camera], str]:
        """The cameras of a split at the size they are read, without reading images: (cameras, world)."""
        cameras, world = self._posed_format().cameras(self.source)
        shrink = Shrink.of(self.options)
        cameras = [shrink.camera(c, self.source) for c in named_views(cameras)]
        return [cameras[i] for i in split_indices(len(cameras), self.options.holdout, split)], world

    @_read_errors_named
    def load(self, split: str = "all") -> Capture:
        """The validated capture of a split ("all", "train" without the held-out views, "holdout"):
        the images are read on the first call, each view checked and named."""
        if "capture" not in self._read:
            fmt = self._posed_format()
            capture = fmt.load(self.source, self.mesh, Shrink.of(self.options), self.cache_dir)
            check_viewpoints(self.source, capture.cameras)
            capture.cameras = named_views(capture.cameras)
            self._read["capture"], self._read["mesh"] = capture, self.mesh
        capture = self._read["capture"]
        if self.mesh != self._read["mesh"]:
            capture = replace(capture, mesh=load_mesh(self.mesh))
        return finish_capture(capture, self.options, split)

    def with_mesh(self, mesh: str | Path | None) -> CaptureSource:
        """The same capture with other known geometry (e.g. the mesh NeuS made), its images not read again."""
        return replace(self, mesh=None if mesh is None else Path(mesh), _read=self._read)


@_read_errors_named
def open_capture(path: str | Path | CaptureSource, mesh: str | Path | None = None,
                 options: CaptureConfig | None = None, cache_dir: str | Path | None = None) -> CaptureSource:
    """Resolve a capture once (a scene XML, transforms json, NeuS/IDR cameras_sphere.npz, LLFF
    poses_bounds.npy, a COLMAP folder, photos or a video, or a folder holding one) into the value the
    stages take. `options` (config section `capture`) sets the downscale and maximum size (applied to
    each image as it is read), the background keying and the held-out views; undistorted photos are
    cached in `cache_dir` when given. A CaptureSource is returned as it is."""
    if isinstance(path, CaptureSource):
        return path
    source = resolve_capture_path(path)
    return CaptureSource(Path(path), source, format_of(source), options or CaptureConfig(),
                         None if mesh is None else Path(mesh), None if cache_dir is None else Path(cache_dir))


def load_capture(path: str | Path, mesh: str | Path | None = None, options: CaptureConfig | None = None,
                 split: str = "all", cache_dir: str | Path | None = None) -> Capture:
    """Load and validate a capture's split in one call (`open_capture(...).load(split)`)."""
    return open_capture(path, mesh, options, cache_dir).load(split)


def load_cameras(path: str | Path, options: CaptureConfig | None = None,
                 split: str = "all") -> tuple[list[Camera], str, Path]:
    """Cameras only (no images needed), for rendering novel views: (cameras, world, source)."""
    capture = open_capture(path, options=options)
    cameras, world = capture.cameras(split)
    return cameras, world, capture.source


def named_views(cameras: list[Camera]) -> list[Camera]:
    """The cameras under their file-safe, unique view names (vq_mitsuba.data.names.view_names),
    given to all views of a capture before any split. The loaders find each view's files by the
    capture's own names; everything after loading knows a view by this name."""
    return [replace(c, name=n) for c, n in zip(cameras, view_names([c.name for c in cameras]))]


def capture_kind(source: Path) -> str:
    """The KIND of a resolved capture's format: "xml", "json", "idr" (cameras_sphere.npz), "llff"
    (poses_bounds.npy) or "colmap" (a folder with a sparse model); "photos" (a folder of photos
    without poses) or "video" (no poses either)."""
    return format_of(source).KIND


def resolve_capture_path(path: str | Path) -> Path:
    """The capture for `path`: the file itself, a folder's transforms_train.json / transforms.json /
    scene.xml / cameras_sphere.npz / poses_bounds.npy (the formats' FOLDER_FILES), or the folder
    itself when it holds a COLMAP sparse model or, failing all these, photos (a capture without
    poses, as a video file is). A folder holding several posed captures reads the first and says so,
    or is refused when they disagree (`check_one_capture`)."""
    path = Path(path)
    if path.is_dir():
        found = [path / name for name in dict.fromkeys(folder_files()) if (path / name).is_file()]
        found += [path] if any(fmt.POSED and fmt.detect(path) for fmt in FORMATS) else []  # a COLMAP model
        if len(found) > 1:
            check_one_capture(path, found)
        if found:
            return found[0]
        if any(fmt.detect(path) for fmt in FORMATS):  # photos
            return path
        raise InputError(path, f"capture folder holds no capture of a known format (expected {described()})")
    if not path.exists():
        raise InputError(path, "capture file not found")
    if not known_suffix(path):
        raise InputError(path, f"unknown capture format (expected {described()})")
    return path


def check_one_capture(folder: Path, found: list[Path]) -> None:
    """A folder that holds several posed captures (`found`, the first the one read): refused (an
    InputError naming them) when they disagree on the number of views, else a warning naming the one
    read and the others. A make-scene dataset's transforms_train.json and scene.xml that agree (the
    same views in two worlds, as make-scene writes them) pass without a word."""

    def described(source: Path) -> str:
        return f"the {format_of(source).DESCRIPTION.removeprefix('a ')}" if source == folder else source.name

    counts, unread = {}, []
    for source in found:
        try:
            counts[source] = len(format_of(source).cameras(source)[0])
        except InputError as exc:
            unread.append(f"{described(source)} ({exc.message})")
    if found[0] not in counts:
        return  # the capture read is itself unreadable: its own loader says why
    views = {described(s): n for s, n in counts.items()}
    if len(set(views.values())) > 1:
        listed = ", ".join(f"{name} ({n} views)" for name, n in views.items())
        raise InputError(folder, f"holds captures of several formats that disagree: {listed}; give the file (or "
                                 "folder) of the one to read, or move the others away")
    pair = {p.name for p in found} == {DatasetDir.TRANSFORMS_TRAIN, DatasetDir.SCENE_XML}
    if pair and DatasetDir(folder).is_dataset() and not unread:
        return
    others = [described(s) for s in found[1:] if s in counts] + unread
    warn(f"{folder}: reading {described(found[0])} ({counts[found[0]]} views); {' and '.join(others)} "
         f"{'is' if len(others) == 1 else 'are'} also there, not read (give its path to read it instead)")


def split_indices(count: int, holdout: int, split: str) -> list[int]:
    """The views of a split: with holdout K, every K-th view (K-1, 2K-1, ...) is held out."""
    if split not in ("all", "train", "holdout"):
        raise ValueError(f"unknown split {split!r}")
    held = {i for i in range(count) if holdout > 0 and i % holdout == holdout - 1}
    if split == "all":
        return list(range(count))
    return [i for i in range(count) if (i in held) == (split == "holdout")]


def finish_capture(capture: Capture, options: CaptureConfig, split: str = "all") -> Capture:
    """Apply the size (the loaders shrank the images as they read them; here the cameras follow),
    background keying and the split to a loaded capture."""
    from vq_mitsuba.config import background_rgb

    images, alpha, has_alpha = capture.images, capture.alpha, capture.has_alpha
    key = background_rgb(options)
    if key is not None:
        if has_alpha:
            raise InputError(capture.source, "capture.background_color keys out a backdrop, but this capture "
                                             "already has masks (alpha or a mask folder): drop one")
        from vq_mitsuba.data.imageio import linear_to_srgb

        dist = np.linalg.norm(linear_to_srgb(np.clip(images, 0, 1)) - np.asarray(key, np.float32), axis=-1)
        tol = options.background_tolerance
        alpha = np.clip((dist - tol) / max(tol, 1e-6), 0.0, 1.0).astype(np.float32)
        has_alpha = True
        if not (alpha > 0.5).any():
            raise InputError(capture.source, f"every pixel lies within {tol} of the background colour {key}: "
                                             "nothing left to fit (check capture.background_color)")
    cameras = [Shrink.of(options).camera(c, capture.source) for c in capture.cameras]
    for cam in cameras:
        if (cam.height, cam.width) != images.shape[1:3]:  # a loader that did not shrink its images
            raise AssertionError(f"view {cam.name}: camera {cam.width}x{cam.height}, image "
                                 f"{images.shape[2]}x{images.shape[1]}")
    keep = split_indices(len(cameras), options.holdout, split)
    if not keep:
        raise InputError(capture.source, f"capture.holdout {options.holdout} leaves no {split} view of {len(cameras)}")
    if options.holdout > 0 and split == "train" and len(keep) == len(cameras):
        raise InputError(capture.source, f"capture.holdout {options.holdout} holds out none of {len(cameras)} views")
    if len(keep) < len(cameras):  # a copy only when views are left out
        cameras, images, alpha = [cameras[i] for i in keep], images[keep], alpha[keep]
    return Capture(capture.source, cameras, np.ascontiguousarray(images), np.ascontiguousarray(alpha), has_alpha,
                   capture.mesh, capture.envmap, capture.envmap_to_world, capture.world)
