"""Errors shown to users: one message naming the file and what is wrong with it."""

from __future__ import annotations

from pathlib import Path


class InputError(Exception):
    """Bad user input, reported before any work is done."""

    def __init__(self, path: str | Path | None, message: str):
        self.path = None if path is None else Path(path)
        self.message = message
        super().__init__(f"{self.path}: {message}" if self.path is not None else message)


class NumericalError(InputError):
    """A fit that cannot go on (losses or gradients not finite step after step); `path` is the
    run directory, whose checkpoint holds the last finite state."""


def raise_all(problems: list[InputError], capture: str | Path) -> None:
    """Report every problem found in a capture at once (one InputError; nothing if none)."""
    if len(problems) == 1:
        raise problems[0]
    if problems:
        raise InputError(capture, f"{len(problems)} problems in this capture:\n  " + "\n  ".join(map(str, problems)))
