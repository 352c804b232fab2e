"""Errors shown to users: one message naming the file and what is wrong with it.

`InputError`: bad input, refused before any work (the command exits with 2).
`RunFailure`: a run that could not go on mid-way (losses that are not finite, a full disk); what
was written before it is kept (exit 3)."""

from __future__ import annotations

import errno
import warnings
from pathlib import Path


class UserError(Exception):
    """A failure told to the user as one line: the file it concerns (if any) and what is wrong."""

    exit_code = 1

    def __init__(self, path: str | Path | None, message: str):
        self.path = None if path is None else Path(path)
        self.message = message
        super().__init__(f"{self.path}: {message}" if self.path is not None else message)


class InputError(UserError):
    """Bad user input, reported before any work is done."""

    exit_code = 2


class RunFailure(UserError):
    """A command that stopped mid-way; the files it wrote before are kept."""

    exit_code = 3


class NumericalError(RunFailure):
    """A fit that cannot go on (losses or gradients not finite step after step); `path` is the
    run directory, whose checkpoint holds the last finite state."""


def raise_all(problems: list[InputError], capture: str | Path) -> None:
    """Report every problem found in a capture at once (one InputError; nothing if none)."""
    if len(problems) == 1:
        raise problems[0]
    if problems:
        raise InputError(capture, f"{len(problems)} problems in this capture:\n  " + "\n  ".join(map(str, problems)))


class Notice(UserWarning):
    """vq-mitsuba's own warning about an input or a run that goes on (the CLI shows each as one
    `warning:` line on stderr)."""


def warn(message: str) -> None:
    """Warn through Python's warnings (`Notice`): a library caller can filter or record it, and the
    CLI prints it to stderr, never among a command's results on stdout."""
    warnings.warn(message, Notice, stacklevel=2)


# Writes that the machine refuses (no permission, a read-only or full disk) as one user message.
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
