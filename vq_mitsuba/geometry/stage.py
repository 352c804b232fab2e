"""The geometry stage: a geometry method (`vq_mitsuba.geometry.methods`, NeuS by default) on a resolved
capture (`vq_mitsuba.data.captures.CaptureSource`), the mesh scored against a ground truth when one is
given, and the stage's one record in the run (geometry.json, then mesh.ply)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

from vq_mitsuba.config import Config
from vq_mitsuba.data.captures import CaptureSource
from vq_mitsuba.errors import InputError
from vq_mitsuba.geometry import methods
from vq_mitsuba.geometry.methods import Reconstruction
from vq_mitsuba.run.outputs import check_output_folder
from vq_mitsuba.run.run_dir import RunDir


def masked_by_mesh(capture, mesh=None):
    """The capture with each view's alpha the coverage of `mesh` (default: the capture's own) seen
    from its camera (`mesh_coverage`), has_alpha True: masks for a capture that has none, from the
    mesh a geometry method reconstructed without them (`Reconstruction.masks_from_mesh`)."""
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


def run_geometry(source: CaptureSource, run_dir: str | Path | RunDir, cfg: Config, method: str = methods.DEFAULT,
                 resume: bool = False, gt_mesh=None) -> Reconstruction:
    """The geometry `method` (a registered name) into the run on a posed capture (photos or a video
    are posed first: `vq_mitsuba.engine.pipeline.posed_capture`); score against gt_mesh if given.
    Writes the method's summary as geometry.json, with `background` "model" where the mesh was made
    without masks ("masks" otherwise), then mesh.ply; returns the `Reconstruction`."""
    from vq_mitsuba.data.captures import load_mesh

    chosen = methods.get(method)
    run = run_dir if isinstance(run_dir, RunDir) else RunDir(run_dir)
    check_geometry_target(run)
    gt = load_mesh(gt_mesh) if gt_mesh is not None else None
    result = chosen.reconstruct(source, run, cfg, resume=resume)
    result.method = chosen.name
    result.summary["background"] = "model" if result.masks_from_mesh else "masks"
    if gt is not None:
        from vq_mitsuba.geometry.mesh import mesh_metrics

        result.summary["metrics"] = mesh_metrics(result.mesh, gt)
        result.summary["gt_mesh"] = str(Path(gt_mesh).resolve())
    run.write_geometry_summary(result.summary)  # the stage's one record, then its product:
    run.write_mesh(result.mesh)  # a mesh.ply is a finished stage (fit --resume reuses it)
    return result


def ensure_geometry(source: CaptureSource, run_dir: str | Path | RunDir, cfg: Config, method: str = methods.DEFAULT,
                    resume: bool = False) -> Path:
    """The run's mesh.ply from the geometry `method`, reusing an existing one on resume; returns its path."""
    run = run_dir if isinstance(run_dir, RunDir) else RunDir(run_dir)
    if not (resume and run.has_mesh()):
        run_geometry(source, run, cfg, method, resume=resume)
    return run / RunDir.MESH


def geometry_report(run: RunDir, method: str = methods.DEFAULT) -> list[str]:
    """Lines for people about the run's geometry.json, by the method that wrote it ([] without one)."""
    return methods.get(method).report(run.geometry_summary())
