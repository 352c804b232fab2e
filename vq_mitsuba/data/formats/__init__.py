"""Capture formats, one module each, and the registry that `vq_mitsuba.data.captures` walks.

A format module names its layout in its docstring and is a `CaptureFormat`: a `PosedFormat` when
POSED, else an `UnposedFormat` (its NOUN, SEQUENTIAL, `pose_inputs` and `views_into` give the pose
stage what it needs); `tests/data/test_formats_conform.py` checks every registered one. It defines:

    KIND           the name `capture_kind` gives it ("xml", "json", "idr", "llff", "colmap", ...)
    DESCRIPTION    what a person gives, as messages and help name it ("a NeuS/IDR cameras_sphere.npz")
    SUFFIXES       the file suffixes it reads (empty for a folder)
    FOLDER_FILES   the files that make a folder a capture of this format, in the order looked for
    POSED          False for captures without camera poses (loading them is refused)
    detect(source)             whether `source` (a file, or a folder for COLMAP and photos) is one
    cameras(source)            (cameras, world) without reading the images (posed formats)
    load(source, mesh_arg, shrink, cache_dir)   the validated `Capture` (posed formats)
    points(source)             sparse points and their track lengths (posed formats; the attribute
                               is None where the format has none)
    sphere(source)             the region of interest as (centre, radius, what gives it) (likewise)
    has_geometry(source)       whether the capture brings its own geometry, reading no image
                               (posed formats)

and, where the format has one, `write_capture(...)` (the writer the synthetic scenes use:
`vq_mitsuba.synthetic.mitsuba_scenes` for the scene XML and the transforms json,
`vq_mitsuba.data.formats.copies` for the photographed formats' copies).

Adding a format is one new module and one line in FORMATS. The order matters twice: a capture
folder resolves to the first FOLDER_FILES entry it holds, walking FORMATS in order (a folder that
holds several is checked: vq_mitsuba.data.captures.check_one_capture), and a source is of the first
format whose `detect` accepts it.
"""

from __future__ import annotations

from pathlib import Path
from types import ModuleType
from typing import Callable, Optional, Protocol, runtime_checkable

from vq_mitsuba.data.formats import colmap, idr, llff, mitsuba_xml, nerf_synthetic, nerfstudio, photos, video


@runtime_checkable
class CaptureFormat(Protocol):
    """What every format module defines."""

    KIND: str
    DESCRIPTION: str
    SUFFIXES: tuple[str, ...]
    FOLDER_FILES: tuple[str, ...]
    POSED: bool

    def detect(self, source: Path) -> bool: ...


@runtime_checkable
class PosedFormat(CaptureFormat, Protocol):
    """What a format of posed captures defines besides: its cameras, its loader, and its sparse
    points and region of interest (None where it has none)."""

    points: Optional[Callable]
    sphere: Optional[Callable]

    def cameras(self, source: Path) -> tuple[list, str]: ...

    def has_geometry(self, source: Path) -> bool: ...

    def load(self, source: Path, mesh_arg, shrink=None, cache_dir=None): ...


@runtime_checkable
class UnposedFormat(CaptureFormat, Protocol):
    """What a format without camera poses defines for the pose stage (structure from motion)."""

    NOUN: str  # what its views are called ("photos")
    SEQUENTIAL: bool  # its views come in order (a video's frames): SfM matches neighbours

    def pose_inputs(self, source: Path, frames: int, fingerprint) -> tuple[dict, int]: ...

    def views_into(self, source: Path, images: Path, frames: int, log) -> tuple[list, dict | None]: ...


FORMATS: tuple[ModuleType, ...] = (nerf_synthetic, nerfstudio, mitsuba_xml, idr, llff, colmap, photos, video)


def format_of(source: Path) -> ModuleType:
    """The format module of a resolved capture path (`vq_mitsuba.data.captures.resolve_capture_path`)."""
    for fmt in FORMATS:
        if fmt.detect(source):
            return fmt
    raise ValueError(f"{source}: not a capture of any known format")


def folder_files() -> list[str]:
    """The file names that make a folder a capture, in the order they are looked for."""
    return [name for fmt in FORMATS for name in fmt.FOLDER_FILES]


def described() -> str:
    """Every format as a person gives it, in one phrase: "a Mitsuba scene .xml, ..., or a video"."""
    phrases = [fmt.DESCRIPTION for fmt in FORMATS]
    return ", ".join(phrases[:-1]) + " or " + phrases[-1]


def known_suffix(path: Path) -> bool:
    """Whether a capture file's suffix is one a format reads."""
    return any(path.suffix.lower() in fmt.SUFFIXES for fmt in FORMATS)
