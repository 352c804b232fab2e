"""`vq-mitsuba fit` as one call: the run folder's checks, the camera poses when the capture is photos
or a video without them (SfM), the geometry stage when the capture brings no geometry (NeuS), then
the material fit (`vq_mitsuba.engine.trainer.fit`)."""

from __future__ import annotations

from pathlib import Path
from typing import Callable

from vq_mitsuba.config import Config
from vq_mitsuba.engine.trainer import check_fit_target, fit
from vq_mitsuba.errors import InputError
from vq_mitsuba.geometry.pipeline import capture_has_geometry, ensure_geometry, neus_psnr_line
from vq_mitsuba.geometry.poses import ensure_poses, is_unposed
from vq_mitsuba.run.outputs import check_output_folder, removed_on_refusal
from vq_mitsuba.run.run_dir import RunDir

GEOMETRY_MODES = ("auto", "neus", "given")


def needs_reconstruction(capture: str | Path, geometry: str = "auto", mesh: str | Path | None = None) -> bool:
    """Whether the fit reconstructs the geometry with NeuS first: `neus`, or `auto` on a capture
    without shapes, mesh.ply or --mesh."""
    if geometry not in GEOMETRY_MODES:
        raise ValueError(f"geometry must be one of {GEOMETRY_MODES}, got {geometry!r}")
    if geometry == "neus" and mesh is not None:
        raise InputError(mesh, "--mesh gives known geometry but --geometry neus asks to reconstruct it; drop one")
    if geometry == "given" or mesh is not None:
        return False
    return geometry == "neus" or not capture_has_geometry(capture)


def fit_capture(capture: str | Path, run_dir: str | Path, cfg: Config, geometry: str = "auto",
                mesh: str | Path | None = None, resume: bool = False, progress: bool = True,
                log: Callable[[str], None] = print) -> dict:
    """Fit a capture into RUN_DIR: refuse a folder of other files, an edited run, or a fitted run
    without `resume` before any work; pose photos or a video without poses (RUN_DIR/pose/, a COLMAP
    capture, reused while the inputs are the same) and fit that capture; reconstruct the mesh with
    NeuS when `needs_reconstruction` (RUN_DIR/mesh.ply, reused on resume); then fit the materials.
    Returns the fit's summary.
    The run's lock is held throughout: a second process fitting into RUN_DIR is refused."""
    run = RunDir(run_dir)
    check_output_folder(run.dir, "run", "fit")
    unposed = is_unposed(capture)
    if unposed and (mesh is not None or geometry == "given"):
        raise InputError(mesh or capture, "known geometry cannot be used with photos or a video without poses: "
                                          "their cameras come from SfM, in a frame and scale of its own; drop "
                                          f"{'--mesh' if mesh is not None else '--geometry given'}")
    reconstruct = unposed or needs_reconstruction(capture, geometry, mesh)
    check_fit_target(run, resume)
    with run.lock("fit", log):
        check_fit_target(run, resume)  # again, now that no other process writes here
        # A stage refused once it has read the capture (no pixel hits a --mesh, no geometry) removes
        # what it wrote (undistorted/, config.yaml, mesh.ply); the stages finished before are kept.
        if unposed:
            with removed_on_refusal(run.dir):
                capture = ensure_poses(capture, run, cfg.pose, progress=progress, log=log)
        if reconstruct:
            reused = resume and run.has_mesh()
            with removed_on_refusal(run.dir):
                mesh = ensure_geometry(capture, run, cfg.neus, resume=resume, progress=progress,
                                       capture_cfg=cfg.capture)
            log(f"geometry: {'reusing' if reused else 'reconstructed with NeuS:'} {mesh}")
            scores = run.neus_scores()
            if not reused and scores:
                log(neus_psnr_line(scores))
        with removed_on_refusal(run.dir):
            return fit(capture, run.dir, cfg, mesh_path=mesh, resume=resume, progress=progress)
