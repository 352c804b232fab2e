"""View names: what a capture calls its views, made safe to use as file names.

A view's name comes from the capture (a sensor id, a frame's file path, a COLMAP image name) and
ends up in file names (`render`'s `NAME_rgb.exr`, ...) and in exported scene files. Every loader's
names pass through `view_names` once, for the whole capture before any split, so the train and
held-out views of one capture never share a name and a name is the same whichever split asks."""

from __future__ import annotations

import re
from typing import Sequence

MAX_NAME_LENGTH = 96  # characters; leaves room for suffixes such as "_segmentation.png" in 255
_UNSAFE = re.compile(r"[^A-Za-z0-9._-]")
_DOTS = re.compile(r"\.{2,}")


def safe_name(raw: str) -> str:
    """One name as a file name: the parts of a path ('/' or '\\' separated, without '', '.' and
    '..') joined by '_', every character other than an ASCII letter, digit, '-', '_' or '.'
    replaced by '_', runs of dots by '_', no leading dot, at most MAX_NAME_LENGTH characters;
    "view" when nothing is left."""
    parts = [p for p in re.split(r"[/\\]", str(raw)) if p not in ("", ".", "..")]
    name = _DOTS.sub("_", _UNSAFE.sub("_", "_".join(parts))).lstrip(".")
    return name[:MAX_NAME_LENGTH] or "view"


def view_names(raw_names: Sequence[str]) -> list[str]:
    """The safe names (`safe_name`) of a capture's views, made unique (`unique_names`); COLMAP's
    `a/000.png` and `b/000.png` are already apart as `a_000` and `b_000`."""
    return unique_names([safe_name(n) for n in raw_names])


def unique_names(names: Sequence[str]) -> list[str]:
    """Names unique even where file names ignore case: the first of a name keeps it, later ones
    get "_2", "_3", ... (kept within MAX_NAME_LENGTH)."""
    taken = {n.casefold() for n in names}
    seen: set[str] = set()
    out = []
    for name in names:
        key = name.casefold()
        if key in seen:
            k = 2
            while True:
                suffix = f"_{k}"
                candidate = name[:MAX_NAME_LENGTH - len(suffix)] + suffix
                if candidate.casefold() not in taken:
                    break
                k += 1
            name, key = candidate, candidate.casefold()
            taken.add(key)
        seen.add(key)
        out.append(name)
    return out
