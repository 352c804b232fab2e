"""NeuS as a geometry method (`vq_mitsuba.geometry.methods`, registered as "neus"): on a posed
capture, its framing without masks or its sparse points with them, the training and mesh export
(`training.reconstruct`), and its own scores: its renders of a few training views and of the
held-out ones against their photos (geometry.json's `neus_psnr`). Its settings are the config's
`neus` section; its checkpoint in the run is neus.pt.

This module imports NeuS's training code only when it reconstructs: registering NeuS (the CLI's
choices, a run's marker files) costs no import of it."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from vq_mitsuba.config import Config, NeuSConfig
from vq_mitsuba.geometry.methods import Framing, Reconstruction, register
from vq_mitsuba.geometry.neus import CHECKPOINT
from vq_mitsuba.run.run_dir import RunDir

if TYPE_CHECKING:
    from vq_mitsuba.data.captures import CaptureSource

TRAIN_VIEWS_SCORED = 4  # training views NeuS renders at the end of the stage
# Triangulated points are used when there are at least this many a training view: DTU's photos give
# about 25 (NeuS's held-out renders +0.40 / -0.06 dB on scan37 / scan24), tabletop's rendered
# surfaces 2.4 (its in-view normals' p90 17.9 -> 19.1 degrees with them); benchmarks/results/neus_points/.
MIN_POINTS_PER_VIEW = 10


@register("neus")
class NeuSMethod:
    """NeuS (Wang et al. 2021) on posed images, with masks or without (`vq_mitsuba.geometry.neus`)."""

    name = "neus"
    label = "NeuS"
    files = (CHECKPOINT,)
    seed_key = "neus.seed"

    def reconstruct(self, source: CaptureSource, run: RunDir, cfg: Config, resume: bool = False) -> Reconstruction:
        """NeuS and its mesh on the training views of `source`, into `run` (neus.pt,
        geometry_loss.png), scored on its own renders."""
        from vq_mitsuba.geometry.neus.framing import uses_background_model
        from vq_mitsuba.geometry.neus.training import reconstruct

        neus_cfg = cfg.neus
        capture = source.load("train")
        if uses_background_model(capture, neus_cfg):
            sphere, support, points = framing(source, capture.cameras, neus_cfg.seed)
            found = {"source": "capture", "seconds": 0.0} if points is not None else None
        else:
            sphere = support = None
            points, found = surface_points(source, capture, neus_cfg)
        resumed = resume and (run / CHECKPOINT).is_file()
        trained = reconstruct(capture, run, neus_cfg, resume=resume, sphere=sphere,
                              support=support, points=points)
        summary = trained.summary
        if found is not None:
            summary["sparse_points"] = {**(summary.get("sparse_points") or {}), **found}
        scores = summary["neus_psnr"] = neus_psnr(trained.neus, capture, source)
        box = trained.neus.box
        written = [run / name for name in (CHECKPOINT, RunDir.GEOMETRY_PLOT) if (run / name).is_file()]
        return Reconstruction(
            trained.mesh, summary, masks_from_mesh=box.mask_free, scores=scores, files=tuple(written),
            framing=Framing(tuple(float(c) for c in box.center), float(box.half),
                            box.sphere_source if box.mask_free else "visual hull"),
            resumed=resumed, model=trained.neus)

    def report(self, summary: dict) -> list[str]:
        """Its training (steps and seconds) and its renders' PSNR, from its geometry.json."""
        if "iterations" not in summary or "seconds" not in summary:
            return []
        s = summary["seconds"]
        lines = [f"NeuS: {summary['iterations']} iterations in {s['train']:.1f} s (+{s['setup_and_hull']:.1f} s "
                 f"visual hull, {s['mesh_export']:.1f} s mesh export)"]
        if summary.get("neus_psnr"):
            lines.append(neus_psnr_line(summary["neus_psnr"]))
        return lines


def framing(capture: CaptureSource, cameras, seed: int = 0) -> tuple[tuple, tuple | None, np.ndarray | None]:
    """Where NeuS without masks looks for the object: (the sphere (centre, radius, what framed it),
    a supporting plane (normal, offset) or None, the sparse points seen by 3 or more images or None).
    The sphere: the region of interest the capture's files give (`CaptureSource.framing`: an IDR
    capture's), else `bounding_sphere` of the cameras and the capture's own sparse points (a COLMAP
    model's), which may also show the table the object stands on (`support_from_points`)."""
    from vq_mitsuba.geometry.neus.framing import bounding_sphere, support_from_points, well_seen

    points, sphere = capture.framing()
    if sphere is None:
        sphere = bounding_sphere(cameras) if points is None else bounding_sphere(cameras, points[0], points[1])
    if points is None:
        return sphere, None, None
    support = support_from_points(points[0], cameras, sphere, points[1], seed=seed)
    return sphere, support, well_seen(points[0], points[1])


def surface_points(source: CaptureSource, capture, cfg: NeuSConfig) -> tuple[np.ndarray | None, dict | None]:
    """The sparse points seen by 3 or more views that NeuS's SDF-is-zero term uses (neus.w_points)
    on a capture with masks (`capture`, the loaded training views of `source`), and where they came
    from: the capture's own (a COLMAP model's), else triangulated from its training views with their
    cameras (`sparse_points.triangulate`, its time recorded) and used when they number
    MIN_POINTS_PER_VIEW a view or more (smooth, rendered surfaces give few, and there they did not
    help). (None, None) with the term off."""
    from vq_mitsuba.geometry.neus.framing import well_seen
    from vq_mitsuba.geometry.sparse_points import triangulate

    if cfg.w_points <= 0:
        return None, None
    own, _ = source.framing()
    if own is not None:
        return well_seen(own[0], own[1]), {"source": "capture", "seconds": 0.0}
    found = triangulate(capture.cameras, capture.images, capture.alpha if capture.has_alpha else None)
    info = {"source": "triangulated", "seconds": round(found["seconds"], 2), "pairs": found["pairs"]}
    views = len(capture.cameras)
    if len(found["points"]) < MIN_POINTS_PER_VIEW * views:
        n = len(found["points"])
        return None, {**info, "given": n, "used": 0,
                      "skipped": f"{n} points over {views} views: under {MIN_POINTS_PER_VIEW} a view"}
    return found["points"], info


def neus_psnr(neus, capture, source: CaptureSource) -> dict:
    """How well NeuS renders the photos it trained on (`capture`, a few views spread over them) and,
    with `capture.holdout`, the views of `source` kept out of training: mean and per-view sRGB PSNR
    (inside the masks where there are masks), for geometry.json."""
    from vq_mitsuba.geometry.neus.training import sample_views, view_psnr

    train = view_psnr(neus, capture, sample_views(len(capture.cameras), TRAIN_VIEWS_SCORED))
    held = {}
    if source.options.holdout > 0:
        holdout = source.load("holdout")
        held = view_psnr(neus, holdout, list(range(len(holdout.cameras))))

    def mean(values: dict) -> float | None:
        return float(np.mean(list(values.values()))) if values else None

    return {"train_views": mean(train), "holdout_views": mean(held), "inside_masks": bool(capture.has_alpha),
            "per_view": {**train, **held}}


def neus_psnr_line(scores: dict) -> str:
    """One line for people: how well NeuS renders its training and held-out views."""
    where = " inside the masks" if scores["inside_masks"] else ""
    line = f"NeuS renders its training views at {scores['train_views']:.2f} dB{where}"
    if scores["holdout_views"] is not None:
        line += f", its held-out views at {scores['holdout_views']:.2f} dB"
    return line
