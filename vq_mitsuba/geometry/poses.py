"""Camera poses for photos or a video that come without them: structure from motion with COLMAP
(pycolmap), written as a COLMAP capture that the capture loaders read (vq_mitsuba.data.formats.colmap).

    OUT/images/     the photos (turned upright where their EXIF orientation says so), or the video's kept frames
    OUT/sparse/0/   the largest model: cameras.bin (one SIMPLE_RADIAL camera), images.bin, points3D.bin, ...
    OUT/pose.json   what was done: the inputs, the matcher, registered / total images, the mean reprojection error

The steps: SIFT features on the CPU (on images of at most SIFT_MAX_SIDE pixels), matching
(`pose.matcher`: sequential pairs of neighbours in order for a video and for more than
EXHAUSTIVE_MAX photos, every pair otherwise), incremental mapping with one camera shared by all
images (they must share one size), and the model that places the most images. Fewer placed
images than max(MIN_IMAGES, pose.min_registered x the images) is an InputError naming how many.

The model keeps COLMAP's frame and scale, which are arbitrary: the loaders use its cameras as
they are, NeuS frames the object from the cameras (and masks), and points3D.bin holds the sparse
points for stages that frame the object by them. Run again on the same inputs with the same
settings, OUT is reused (pose.json records them); the work happens in a folder beside OUT that
replaces it once done, so an interrupted run leaves no half-written model. OUT is replaced only
when it is a posed capture of the same source holding nothing else (`run.outputs`' rule).
"""

from __future__ import annotations

import math
import os
import shutil
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Callable

from vq_mitsuba import messages
from vq_mitsuba.backend import import_pycolmap
from vq_mitsuba.config import PoseConfig
from vq_mitsuba.data.captures import CaptureSource, open_capture
from vq_mitsuba.data.formats import colmap
from vq_mitsuba.data.formats.photos import MIN_IMAGES
from vq_mitsuba.data.unposed import fingerprint
from vq_mitsuba.errors import InputError
from vq_mitsuba.run.run_dir import RunDir, read_json, write_json

SUMMARY = "pose.json"
EXHAUSTIVE_MAX = 100  # photos up to which `auto` matches every pair (4950 pairs); over it, neighbours in name order
SIFT_MAX_SIDE = 2000  # SIFT runs on images scaled down to this long side (phone photos: 4032 px, 4x the time)
SIFT_MAX_FEATURES = 4096  # per image; matching a pair costs the product of two images' counts
CAMERA_MODEL = "SIMPLE_RADIAL"  # focal length, principal point, one radial term: what a phone needs, few unknowns
SUMMARY_VERSION = 1


def ensure_poses(capture: CaptureSource, run: RunDir, cfg: PoseConfig,
                 log: Callable[[str], None] = messages.note) -> CaptureSource:
    """The run's posed COLMAP capture RUN/pose of an unposed capture (made, or reused when it was
    made from the same inputs), opened with the capture's options."""
    pose_capture(capture, run / RunDir.POSE, cfg, log=log)
    return open_capture(run / RunDir.POSE, options=capture.options, cache_dir=capture.cache_dir)


def pose_capture(capture: str | Path | CaptureSource, out: str | Path, cfg: PoseConfig | None = None,
                 log: Callable[[str], None] = messages.note) -> dict:
    """Find the camera poses of a folder of photos or a video and write the COLMAP capture OUT
    (images/, sparse/0/, pose.json); returns pose.json's content (with "reused" true when OUT
    already held the result for the same inputs and settings)."""
    cfg = cfg or PoseConfig()
    capture = open_capture(capture)
    source, fmt = capture.source, capture.format
    if capture.posed:
        raise InputError(source, f"already has camera poses ({fmt.KIND} capture): fit it as it is")
    out = Path(out)
    inputs = _inputs(source, fmt, cfg)
    previous = _previous(out, source)
    if previous is not None and previous.get("inputs") == inputs:
        _check_registered(out, previous["registered"], previous["images"], cfg, fmt.NOUN)
        log(f"pose: reusing {out} ({previous['registered']} of {previous['images']} {fmt.NOUN} placed)")
        return dict(previous, reused=True)
    if previous is not None:
        _check_replaceable(out)
    work = out.parent / f".{out.name}.pose-tmp"
    with _scratch(work):
        t0 = time.perf_counter()
        images = work / colmap.IMAGES
        images.mkdir()
        names, video = fmt.views_into(source, images, cfg.frames, log)
        t_images = time.perf_counter() - t0
        matcher = inputs["matcher"]
        model, seconds = _sfm(work, names, matcher, log)
        registered = model.num_reg_images() if model is not None else 0
        _check_registered(source, registered, len(names), cfg, fmt.NOUN)
        model.write(str(_mkdir(work / colmap.MODEL)))
        placed = {model.image(i).name for i in model.reg_image_ids()}
        summary = {
            "version": SUMMARY_VERSION, "source": str(source.resolve()), "kind": fmt.KIND, "inputs": inputs,
            "matcher": matcher, "camera_model": CAMERA_MODEL, "images": len(names), "registered": registered,
            "unregistered": [n for n in names if n not in placed],
            "mean_reprojection_error_px": round(float(model.compute_mean_reprojection_error()), 4),
            "points3D": int(model.num_points3D()),
            "seconds": {"images": round(t_images, 2), **seconds, "total": round(time.perf_counter() - t0, 2)},
        }
        if video is not None:
            summary["video"] = video
        (work / "database.db").unlink(missing_ok=True)
        write_json(work / SUMMARY, summary)
        if out.exists():
            shutil.rmtree(out)
        os.replace(work, out)
    log(f"pose: placed {registered} of {len(names)} {fmt.NOUN}, mean reprojection error "
        f"{summary['mean_reprojection_error_px']:.2f} px, {summary['points3D']} points ({matcher} matching, "
        f"{summary['seconds']['total']:.1f} s): {out}")
    return dict(summary, reused=False)


def _inputs(source: Path, fmt, cfg: PoseConfig) -> dict:
    """What the result depends on: the files (names and content keys) and the settings that change it."""
    inputs, views = fmt.pose_inputs(source, cfg.frames, fingerprint)
    return {**inputs, "matcher": _matcher(cfg.matcher, fmt.SEQUENTIAL, views)}


def _matcher(choice: str, sequential: bool, count: int) -> str:
    if choice != "auto":
        return choice
    return "sequential" if sequential or count > EXHAUSTIVE_MAX else "exhaustive"


OWN_ENTRIES = (*colmap.OWN_ENTRIES, SUMMARY)  # what a posed capture holds: pose replaces only these


def _previous(out: Path, source: Path) -> dict | None:
    """The summary of an earlier result in OUT made from `source` ({} when it is older or
    incomplete: made again); None for a new or empty folder. A folder holding other files, a
    pose.json that cannot be read, or the poses of other photos are refused: pose never empties
    a folder it cannot tell it made for these photos."""
    if not out.exists():
        return None
    if not out.is_dir():
        raise InputError(out, "is a file; the posed capture goes into a folder")
    if not (out / SUMMARY).is_file():
        if any(out.iterdir()):
            raise InputError(out, "holds other files and no posed capture (pose.json): choose a new or empty folder")
        return None
    try:
        summary = read_json(out / SUMMARY, "missing")
    except InputError as exc:
        raise InputError(out / SUMMARY, f"cannot be read ({exc.message}): pose would replace {out} without knowing "
                                        "what it holds; move the folder away or choose a new one with -o") from None
    if summary.get("source") != str(source.resolve()):
        raise InputError(out, f"holds the poses of other photos ({summary.get('source', 'a source not named')}, in "
                              f"{SUMMARY}): pose {source} into a new or empty folder with -o")
    if summary.get("version") != SUMMARY_VERSION or not colmap.has_model(out):
        return {}  # an older or incomplete result: made again
    return summary


def _check_replaceable(out: Path) -> None:
    """Refuse, before any work, to pose again into OUT when it holds files pose did not write."""
    other = sorted(p.name for p in out.iterdir() if p.name not in OWN_ENTRIES)
    if other:
        shown = ", ".join(other[:3]) + (", ..." if len(other) > 3 else "")
        raise InputError(out, f"holds files pose did not write ({shown}) beside an earlier posed capture: posing "
                              "again replaces the folder; move them away or choose a new folder with -o")


def _check_registered(source: Path, registered: int, total: int, cfg: PoseConfig, noun: str) -> None:
    need = max(MIN_IMAGES, math.ceil(cfg.min_registered * total - 1e-9))
    if registered < need:
        raise InputError(source, f"structure from motion placed {registered} of {total} {noun} (at least "
                                 f"{need} needed, pose.min_registered {cfg.min_registered:g}): the images need "
                                 "texture, sharp focus and overlap (each part of the object in three or more, "
                                 "taken a few steps apart around it)")


@contextmanager
def _scratch(folder: Path):
    """A new empty folder, removed again unless the body moved it away."""
    if folder.exists():
        shutil.rmtree(folder)
    folder.mkdir(parents=True)
    try:
        yield folder
    finally:
        if folder.exists():
            shutil.rmtree(folder, ignore_errors=True)


def _mkdir(folder: Path) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    return folder


def _threads() -> int:
    """The CPU threads COLMAP may use: torch's count (vq-mitsuba --threads), at most the cores."""
    import torch

    from vq_mitsuba.backend import available_cores

    return max(1, min(torch.get_num_threads(), available_cores()))


@contextmanager
def _quiet_colmap():
    """COLMAP's log lines (thousands of them) only when they are errors."""
    pycolmap = import_pycolmap()

    level = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = 2
    try:
        yield
    finally:
        pycolmap.logging.minloglevel = level


def _sfm(work: Path, names: list[str], matcher: str, log: Callable[[str], None]):
    """COLMAP on work/images: (the model placing the most images or None, seconds per step)."""
    pycolmap = import_pycolmap()

    threads, db, images = _threads(), work / "database.db", work / colmap.IMAGES
    seconds = {}
    bar = messages.progress(total=3, desc="pose", unit="step")
    with _quiet_colmap(), bar:
        t = time.perf_counter()
        bar.set_postfix_str(f"SIFT features of {len(names)} images")
        reader = pycolmap.ImageReaderOptions(camera_model=CAMERA_MODEL)
        extraction = pycolmap.FeatureExtractionOptions(num_threads=threads, max_image_size=SIFT_MAX_SIDE)
        extraction.sift.max_num_features = SIFT_MAX_FEATURES
        pycolmap.extract_features(db, images, image_names=names, camera_mode=pycolmap.CameraMode.SINGLE,
                                  reader_options=reader, extraction_options=extraction, device=pycolmap.Device.cpu)
        seconds["features"] = round(time.perf_counter() - t, 2)
        bar.update(1)

        t = time.perf_counter()
        bar.set_postfix_str(f"{matcher} matching")
        matching = pycolmap.FeatureMatchingOptions(num_threads=threads)
        if matcher == "sequential":
            pycolmap.match_sequential(db, matching_options=matching, device=pycolmap.Device.cpu)
        else:
            pycolmap.match_exhaustive(db, matching_options=matching, device=pycolmap.Device.cpu)
        seconds["matching"] = round(time.perf_counter() - t, 2)
        bar.update(1)

        t = time.perf_counter()
        placed = [0]

        def placing(count: int):
            def callback():
                placed[0] += count
                bar.set_postfix_str(f"mapping: {placed[0]} images placed")
            return callback

        pycolmap.set_random_seed(0)
        mapping = pycolmap.IncrementalPipelineOptions(num_threads=threads)
        models = pycolmap.incremental_mapping(db, images, _mkdir(work / "models"), options=mapping,
                                              initial_image_pair_callback=placing(2),
                                              next_image_callback=placing(1))
        seconds["mapping"] = round(time.perf_counter() - t, 2)
        bar.update(1)
    shutil.rmtree(work / "models", ignore_errors=True)
    sizes = sorted((m.num_reg_images() for m in models.values()), reverse=True)
    if len(sizes) > 1 and sizes[1] >= MIN_IMAGES:
        log(f"pose: SfM made {len(sizes)} separate models ({', '.join(map(str, sizes))} images): the largest is kept; "
            "the photos of the others overlap too little with it")
    return max(models.values(), key=lambda m: m.num_reg_images(), default=None), seconds
