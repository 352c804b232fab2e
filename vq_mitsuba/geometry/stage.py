"""The geometry stage: NeuS on a resolved capture (`vq_mitsuba.data.captures.CaptureSource`), its
framing and sparse points, its scores, and its one record in the run (geometry.json, then mesh.ply)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from vq_mitsuba.config import NeuSConfig
from vq_mitsuba.data.captures import CaptureSource
from vq_mitsuba.errors import InputError
from vq_mitsuba.run.outputs import check_output_folder
from vq_mitsuba.run.run_dir import RunDir


def framing(capture: CaptureSource, cameras, seed: int = 0) -> tuple[tuple, tuple | None, np.ndarray | None]:
    """Where NeuS without masks looks for the object: (the sphere (centre, radius, what framed it),
    a supporting plane (normal, offset) or None, the sparse points seen by 3 or more images or None).
    The sphere: the region of interest the capture's files give (`CaptureSource.framing`: an IDR
    capture's), else `bounding_sphere` of the cameras and the capture's own sparse points (a COLMAP
    model's), which may also show the table the object stands on (`support_from_points`)."""
    from vq_mitsuba.geometry.neus import bounding_sphere, support_from_points, well_seen

    points, sphere = capture.framing()
    if sphere is None:
        sphere = bounding_sphere(cameras) if points is None else bounding_sphere(cameras, points[0], points[1])
    if points is None:
        return sphere, None, None
    support = support_from_points(points[0], cameras, sphere, points[1], seed=seed)
    return sphere, support, well_seen(points[0], points[1])


# Triangulated points are used when there are at least this many a training view: DTU's photos give
# about 25 (NeuS's held-out renders +0.40 / -0.06 dB on scan37 / scan24), tabletop's rendered
# surfaces 2.4 (its in-view normals' p90 17.9 -> 19.1 degrees with them); benchmarks/results/neus_points/.
MIN_POINTS_PER_VIEW = 10


def surface_points(source: CaptureSource, capture, cfg: NeuSConfig) -> tuple[np.ndarray | None, dict | None]:
    """The sparse points seen by 3 or more views that NeuS's SDF-is-zero term uses (neus.w_points)
    on a capture with masks (`capture`, the loaded training views of `source`), and where they came
    from: the capture's own (a COLMAP model's), else triangulated from its training views with their
    cameras (`sparse_points.triangulate`, its time recorded) and used when they number
    MIN_POINTS_PER_VIEW a view or more (smooth, rendered surfaces give few, and there they did not
    help). (None, None) with the term off."""
    from vq_mitsuba.geometry.neus import well_seen
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


def masked_by_mesh(capture, mesh=None):
    """The capture with each view's alpha the coverage of `mesh` (default: the capture's own) seen
    from its camera (`mesh_coverage`), has_alpha True: masks for a capture that has none, from the
    mesh NeuS reconstructed without them."""
    from vq_mitsuba.geometry.mesh import mesh_coverage

    mesh = capture.mesh if mesh is None else mesh
    return dataclasses.replace(capture, alpha=mesh_coverage(mesh, capture.cameras), has_alpha=True)


def check_geometry_target(run: RunDir) -> None:
    """Refuse, before any work, a folder the geometry stage must not write its mesh into: one of
    other files (`run.outputs`), an edited run, or a run whose materials were fitted
    on its mesh.ply (checkpoint.pt): a new mesh under that checkpoint would be rendered, exported
    and resumed as if it were the one fitted (also with --resume, which exports the mesh again)."""
    check_output_folder(run.dir, "run", "geometry")
    if run.is_run() and "edit_of" in (_read_info(run) or {}):
        raise InputError(run.dir, "holds an edited run (run.json, edits.json): the geometry stage writes into a new "
                                  "folder or a run of its own; choose another -o")
    if run.has_checkpoint():
        raise InputError(run.dir, f"holds a fitted run ({RunDir.CHECKPOINT}) whose materials were fitted on its "
                                  f"{RunDir.MESH}: the geometry stage would replace that mesh under them; choose a new "
                                  "-o (then fit that run)")


def _read_info(run: RunDir) -> dict | None:
    try:
        return run.info()
    except InputError:
        return None


def run_geometry(source: CaptureSource, run_dir: str | Path | RunDir, cfg: NeuSConfig, resume: bool = False,
                 progress: bool = True, gt_mesh=None):
    """NeuS + mesh export into the run on a posed capture (photos or a video are posed first:
    `vq_mitsuba.engine.pipeline.posed_capture`); score against gt_mesh if given. Returns the
    `Reconstruction` (its summary is the run's geometry.json)."""
    from vq_mitsuba.data.captures import load_mesh
    from vq_mitsuba.geometry.neus import reconstruct, uses_background_model

    run = run_dir if isinstance(run_dir, RunDir) else RunDir(run_dir)
    check_geometry_target(run)
    gt = load_mesh(gt_mesh) if gt_mesh is not None else None
    capture = source.load("train")
    if uses_background_model(capture, cfg):
        sphere, support, points = framing(source, capture.cameras, cfg.seed)
        found = {"source": "capture", "seconds": 0.0} if points is not None else None
    else:
        sphere = support = None
        points, found = surface_points(source, capture, cfg)
    result = reconstruct(capture, run, cfg, resume=resume, progress=progress, sphere=sphere, support=support,
                         points=points)
    if found is not None:
        result.summary["sparse_points"] = {**(result.summary.get("sparse_points") or {}), **found}
    result.summary["neus_psnr"] = neus_psnr(result.neus, capture, source)
    if gt is not None:
        from vq_mitsuba.geometry.mesh import mesh_metrics

        result.summary["metrics"] = mesh_metrics(result.mesh, gt)
        result.summary["gt_mesh"] = str(Path(gt_mesh).resolve())
    run.write_geometry_summary(result.summary)  # the stage's one record, then its product:
    run.write_mesh(result.mesh)  # a mesh.ply is a finished stage (fit --resume reuses it)
    return result


TRAIN_VIEWS_SCORED = 4  # training views NeuS renders at the end of the stage


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


def ensure_geometry(source: CaptureSource, run_dir: str | Path | RunDir, cfg: NeuSConfig, resume: bool = False,
                    progress: bool = True) -> Path:
    """The run's mesh.ply from NeuS, reusing an existing one on resume; returns its path."""
    run = run_dir if isinstance(run_dir, RunDir) else RunDir(run_dir)
    if not (resume and run.has_mesh()):
        run_geometry(source, run, cfg, resume=resume, progress=progress)
    return run / RunDir.MESH


def neus_psnr_line(scores: dict) -> str:
    """One line for people: how well NeuS renders its training and held-out views."""
    where = " inside the masks" if scores["inside_masks"] else ""
    line = f"NeuS renders its training views at {scores['train_views']:.2f} dB{where}"
    if scores["holdout_views"] is not None:
        line += f", its held-out views at {scores['holdout_views']:.2f} dB"
    return line
