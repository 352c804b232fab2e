"""What the tool tells its user goes out here: `note` (a line of news: what a stage found or
chose) and `progress` (a bar over long work), both silenced at once by `quiet` (the commands'
`--quiet`); warnings go through `errors.warn` and are always shown, as are errors. A note is
written beside an open progress bar without breaking it."""

from __future__ import annotations

import sys
from contextlib import contextmanager

_QUIET = [False]  # the process's state: one command a process, its threads alike


def is_quiet() -> bool:
    return _QUIET[0]


@contextmanager
def quiet(flag: bool = True):
    """Within the block, notes and progress bars are silent when `flag`; the previous state after."""
    before = _QUIET[0]
    _QUIET[0] = bool(flag) or before
    try:
        yield
    finally:
        _QUIET[0] = before


def note(text: str) -> None:
    """One line for the user on stdout, unless quiet."""
    if is_quiet():
        return
    from tqdm import tqdm

    tqdm.write(text, file=sys.stdout)


def progress(iterable=None, disable: bool = False, **kwargs):
    """A tqdm progress bar, off when `disable` or quiet."""
    from tqdm import tqdm

    kwargs.setdefault("dynamic_ncols", True)
    return tqdm(iterable, disable=disable or is_quiet(), **kwargs)
