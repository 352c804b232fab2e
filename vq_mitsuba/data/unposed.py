"""Captures without camera poses: a folder of photos (vq_mitsuba.data.formats.photos) or a video
(vq_mitsuba.data.formats.video). What the loaders say of them, the name their runs go by, and a
cheap content key of their files.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

from vq_mitsuba.data.formats.video import is_video
from vq_mitsuba.errors import InputError


def capture_name(capture: str | Path) -> str:
    """The name a capture's runs are called by: its folder's (the folder itself when the capture is
    one, e.g. of photos; a capture file's folder), a video's file name without its suffix."""
    path = Path(capture).resolve()
    return path.name if path.is_dir() else path.stem if is_video(path) else path.parent.name


def unposed_error(source: Path) -> InputError:
    """What a loader says of photos or a video without poses."""
    what = "a video" if is_video(source) else "photos without camera poses"
    return InputError(source, f"{what}: `vq-mitsuba fit` finds the poses itself, or `vq-mitsuba pose {source.name} "
                              "-o OUT` writes them as a COLMAP capture OUT")


def fingerprint(path: Path, chunk: int = 1 << 20) -> str:
    """A cheap content key of a file: its size and a hash of its first and last MiB."""
    size = path.stat().st_size
    h = hashlib.sha1(str(size).encode())
    with open(path, "rb") as f:
        h.update(f.read(chunk))
        if size > chunk:
            f.seek(max(chunk, size - chunk))
            h.update(f.read(chunk))
    return f"{size}:{h.hexdigest()[:16]}"
