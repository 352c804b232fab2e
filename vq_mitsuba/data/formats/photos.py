"""A folder of photos without camera poses (`vq_mitsuba.geometry.poses` finds them with structure
from motion and writes a COLMAP capture).

    IMG_0001.JPG   the photos themselves (JPEG or PNG, directly in the folder; anything else,
    IMG_0002.JPG   hidden files included, is ignored), no camera file

Photos are copied for SfM as they are, except those whose EXIF orientation says they are stored
turned: those are written upright (the loaders and COLMAP then read the pixels as the
photographer saw them).
"""

from __future__ import annotations

import shutil
from pathlib import Path

from vq_mitsuba.errors import InputError

KIND = "photos"
SUFFIXES = ()  # a folder
FOLDER_FILES = ()
POSED = False  # loading refuses it (vq_mitsuba.data.unposed.unposed_error)
PHOTO_SUFFIXES = (".jpg", ".jpeg", ".png")
EXIF_ORIENTATION = 0x0112


def detect(source: Path) -> bool:
    return source.is_dir() and bool(photo_files(source))


def photo_files(folder: Path) -> list[Path]:
    """The photos directly in `folder` (JPEG / PNG, hidden files left out), sorted by name."""
    if not folder.is_dir():
        return []
    return sorted(p for p in folder.iterdir()
                  if p.is_file() and p.suffix.lower() in PHOTO_SUFFIXES and not p.name.startswith("."))


def copy_upright(src: Path, dst: Path) -> tuple[int, int]:
    """Copy a photo to `dst`; one stored turned (EXIF orientation 2..8) is written upright with
    its other EXIF tags kept (PNG losslessly, JPEG at quality 95). Returns its upright
    (width, height); an unreadable photo is an InputError naming it."""
    from PIL import Image, ImageOps, UnidentifiedImageError

    try:
        with Image.open(src) as im:
            orientation = im.getexif().get(EXIF_ORIENTATION, 1)
            if orientation in (None, 1):
                im.load()  # a truncated or foreign file fails here, before SfM
                shutil.copyfile(src, dst)
                return im.size
            upright = ImageOps.exif_transpose(im)
            options = {"exif": upright.info["exif"]} if "exif" in upright.info else {}
            if src.suffix.lower() in (".jpg", ".jpeg"):
                upright.convert("RGB").save(dst, "JPEG", quality=95, **options)
            else:
                upright.save(dst, "PNG", **options)
            return upright.size
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as exc:
        raise InputError(src, f"cannot read the photo ({type(exc).__name__}: {exc})") from None
