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
DESCRIPTION = "a folder of photos (JPEG / PNG)"  # what a person gives, in messages and help
POSED = False  # loading refuses it (vq_mitsuba.data.unposed.unposed_error)
NOUN = "photos"  # what its views are called
SEQUENTIAL = False  # views in no order: SfM matches every pair while they are few
MIN_IMAGES = 3  # SfM needs three images to place any of them with confidence
PHOTO_SUFFIXES = (".jpg", ".jpeg", ".png")
EXIF_ORIENTATION = 0x0112


def detect(source: Path) -> bool:
    return source.is_dir() and bool(photo_files(source))


def pose_inputs(source: Path, frames: int, fingerprint) -> tuple[dict, int]:
    """(what posing the photos depends on: each file's name and content key; how many views they give)."""
    photos = photo_files(source)
    if len(photos) < MIN_IMAGES:
        raise InputError(source, f"holds {len(photos)} photo{'s' * (len(photos) != 1)} (JPEG / PNG): structure from "
                                 f"motion needs at least {MIN_IMAGES}, and 20 or more around the object work best")
    return {"files": [[p.name, fingerprint(p)] for p in photos]}, len(photos)


def views_into(source: Path, images: Path, frames: int, log) -> tuple[list[str], dict | None]:
    """Copy the photos upright into `images`; all must share one size (one camera). Returns (their
    names, None)."""
    sizes: dict[tuple[int, int], list[str]] = {}
    for photo in photo_files(source):
        sizes.setdefault(copy_upright(photo, images / photo.name), []).append(photo.name)
    if len(sizes) > 1:
        listed = "; ".join(f"{w}x{h}: {len(n)} ({', '.join(n[:3])}{', ...' if len(n) > 3 else ''})"
                           for (w, h), n in sorted(sizes.items(), key=lambda kv: -len(kv[1])))
        raise InputError(source, f"the photos differ in size ({listed}): vq-mitsuba needs one size and one camera "
                                 "for all views (turn them alike, or leave the odd ones out)")
    return sorted(n for names in sizes.values() for n in names), None


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
