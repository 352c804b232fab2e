"""Writes that the machine refuses (no permission, a read-only or full disk) as one user message."""

from __future__ import annotations

import errno
from pathlib import Path

from vq_mitsuba.errors import RunFailure

# errno -> what the user is told; any other OSError is a bug or a missing input, reported as such
DISK_ERRORS = {
    errno.EACCES: "permission denied",
    errno.EPERM: "operation not permitted",
    errno.EROFS: "the file system is read-only",
    errno.ENOSPC: "no space left on the device",
    errno.EDQUOT: "disk quota exceeded",
}


class WriteError(RunFailure):
    """A file or folder that could not be written; the files written before it are kept."""


def as_write_error(exc: BaseException, path: str | Path | None = None) -> WriteError | None:
    """The WriteError for an OSError of DISK_ERRORS (naming `path`, else the file the error names),
    or None for any other exception."""
    if not isinstance(exc, OSError) or exc.errno not in DISK_ERRORS:
        return None
    where = path if path is not None else (exc.filename or None)
    return WriteError(where, f"cannot be written: {DISK_ERRORS[exc.errno]} (files written before are kept)")
