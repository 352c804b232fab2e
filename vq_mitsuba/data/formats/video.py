"""A video without camera poses (`vq_mitsuba.geometry.poses` picks frames of it and finds their
poses with structure from motion).

    clip.mp4   one video file (.mp4, .mov, .avi, .mkv, .webm)

Its frames are decoded with the ffmpeg that imageio-ffmpeg ships (rotation metadata applied by
ffmpeg); `pick_frames` keeps the sharpest frame (variance of the Laplacian of the grey image) of
each of N equal time windows.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

import numpy as np

from vq_mitsuba import messages
from vq_mitsuba.errors import InputError

VIDEO_SUFFIXES = (".mp4", ".mov", ".avi", ".mkv", ".webm")
KIND = "video"
SUFFIXES = VIDEO_SUFFIXES
FOLDER_FILES = ()
DESCRIPTION = "a video"  # what a person gives, in messages and help
POSED = False  # loading refuses it (vq_mitsuba.data.unposed.unposed_error)
NOUN = "video frames"  # what its views are called
SEQUENTIAL = True  # views in time order: SfM matches neighbours
SHARPNESS_SIDE = 640  # sharpness is measured on frames block-averaged to about this long side


def detect(source: Path) -> bool:
    return is_video(source) and not source.is_dir()


def is_video(path: Path) -> bool:
    return path.suffix.lower() in VIDEO_SUFFIXES


def sharpness(rgb: np.ndarray) -> float:
    """Variance of the Laplacian of the grey image (uint8 RGB (H, W, 3)), block-averaged first to a
    long side of about SHARPNESS_SIDE pixels: motion blur and defocus lower it."""
    from scipy.ndimage import laplace

    grey = rgb.astype(np.float32) @ np.array([0.299, 0.587, 0.114], np.float32)
    f = max(1, max(grey.shape) // SHARPNESS_SIDE)
    if f > 1:
        h, w = grey.shape[0] // f * f, grey.shape[1] // f * f
        grey = grey[:h, :w].reshape(h // f, f, w // f, f).mean((1, 3))
    return float(laplace(grey).var())


def pose_inputs(source: Path, frames: int, fingerprint) -> tuple[dict, int]:
    """(what posing the video depends on: the file's name and content key, the frames kept; how many
    views that gives)."""
    return {"files": [[source.name, fingerprint(source)]], "frames": frames}, frames


def views_into(source: Path, images: Path, frames: int, log) -> tuple[list[str], dict]:
    """The sharpest frame of each of `frames` time windows into `images`: (their names, what
    `pick_frames` did)."""
    done = pick_frames(source, images, frames, log=log)
    return sorted(p.name for p in images.iterdir()), done


def pick_frames(video: Path, folder: Path, count: int,
                log: Callable[[str], None] = messages.note) -> dict:
    """Decode `video` once, keep the sharpest frame of each of `count` equal time windows and write
    them to folder/frame_NNNNNN.jpg (NNNNNN the frame's index in the video). Returns what was done:
    frames decoded, fps, duration, the kept frames' indices, times and sharpness."""
    import imageio_ffmpeg
    from PIL import Image

    check_video_stream(video)
    try:
        reader = imageio_ffmpeg.read_frames(str(video))
        meta = next(reader)
        width, height = meta["size"]
        fps, duration = float(meta.get("fps") or 0), float(meta.get("duration") or 0)
        total = int(round(fps * duration)) if fps > 0 and duration > 0 else 0
        if not total:  # no duration in the file: count the frames (one more decoding pass)
            total = imageio_ffmpeg.count_frames_and_secs(str(video))[0]
    except (RuntimeError, OSError, StopIteration, KeyError, ValueError) as exc:
        raise InputError(video, f"ffmpeg cannot read the video ({_last_line(exc)})") from None
    best: dict[int, tuple[float, int, np.ndarray | None]] = {}  # window -> (sharpness, frame index, pixels)
    decoded = 0
    folder.mkdir(parents=True, exist_ok=True)

    def flush(window: int) -> None:
        score, index, pixels = best[window]
        if pixels is not None:
            Image.fromarray(pixels).save(folder / f"frame_{index:06d}.jpg", quality=95)
            best[window] = (score, index, None)

    try:
        with messages.progress(total=total, desc="video frames", unit="frame") as bar:
            for raw in reader:
                frame = np.frombuffer(raw, np.uint8).reshape(height, width, 3)
                window = min(count - 1, decoded * count // max(total, 1))
                score = sharpness(frame)
                if window not in best or score > best[window][0]:
                    best[window] = (score, decoded, frame.copy())
                if window - 1 in best:
                    flush(window - 1)  # the previous window is complete
                decoded += 1
                bar.update(1)
    except RuntimeError as exc:
        raise InputError(video, f"ffmpeg stopped reading the video after {decoded} frames ({_last_line(exc)})") \
            from None
    finally:
        reader.close()
    if not best:
        raise InputError(video, "the video holds no frame ffmpeg can decode")
    for window in best:
        flush(window)
    kept = sorted(best.values(), key=lambda b: b[1])
    log(f"video: kept {len(kept)} of {decoded} frames (the sharpest of each of {len(kept)} time windows)")
    return {"frames_decoded": decoded, "fps": fps, "duration_s": duration, "size": [int(width), int(height)],
            "kept": [{"frame": i, "time_s": round(i / fps, 4) if fps else None, "sharpness": round(s, 3)}
                     for s, i, _ in kept]}


def check_video_stream(video: Path) -> None:
    """Refuse, in a sentence naming the file, what ffmpeg cannot open or what holds no video stream
    (a sound file named .mp4): ffmpeg's own text says neither plainly."""
    import re
    import subprocess

    import imageio_ffmpeg

    try:
        probe = subprocess.run([imageio_ffmpeg.get_ffmpeg_exe(), "-hide_banner", "-nostdin", "-i", str(video)],
                               capture_output=True, text=True, errors="replace", timeout=120)
    except (OSError, subprocess.TimeoutExpired) as exc:
        raise InputError(video, f"ffmpeg cannot read the file ({type(exc).__name__})") from None
    streams = re.findall(r"Stream #[^ ]*: (\w+):", probe.stderr)
    if not streams:
        raise InputError(video, f"ffmpeg cannot read the video: it holds no streams (a damaged file, or another kind "
                                f"of file named {video.suffix}?)")
    if "Video" not in streams:
        kinds = " and ".join(sorted({k.lower() for k in streams}))
        raise InputError(video, f"holds no video stream (only {kinds}): there are no frames to pose")


def _last_line(exc: Exception) -> str:
    text = str(exc).strip()
    return text.splitlines()[-1] if text else type(exc).__name__
