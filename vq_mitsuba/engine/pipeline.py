"""The pipeline `vq-mitsuba fit` runs, once, from here: the run folder's checks, the capture resolved
once (`vq_mitsuba.data.captures.open_capture`: the value every stage takes), the camera poses when
the capture is photos or a video without them (SfM), the geometry stage when the capture brings no
geometry (a geometry method, NeuS by default: `vq_mitsuba.geometry.stage`), then the material fit:
a resumed run checked against the capture, run.json and the warnings about the inputs, the training
loop and the residual
(`vq_mitsuba.engine.trainer.Trainer`) and the results (`vq_mitsuba.engine.products`).
`vq-mitsuba geometry` runs its pose and geometry stages."""

from __future__ import annotations

import copy
import math
import time
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from vq_mitsuba import messages
from vq_mitsuba.backend import device_record, init_mitsuba, torch_device
from vq_mitsuba.config import Config, PoseConfig
from vq_mitsuba.data.captures import Capture, CaptureSource, open_capture
from vq_mitsuba.engine.mesh_scale import mesh_scale_warning
from vq_mitsuba.engine.products import write_products
from vq_mitsuba.engine.trainer import Trainer, parse_snapshot_times
from vq_mitsuba.errors import InputError, warn
from vq_mitsuba.geometry import methods
from vq_mitsuba.geometry.stage import ensure_geometry, geometry_report, masked_by_mesh, run_geometry
from vq_mitsuba.geometry.poses import ensure_poses
from vq_mitsuba.models.fitted import material_networks
from vq_mitsuba.run.outputs import check_output_folder, removed_on_refusal
from vq_mitsuba.run.run_dir import RunDir

COVERAGE_WARNING = 0.9  # a share of the opaque pixels hitting the mesh below this is warned about


def geometry_method(geometry: str = "auto") -> str:
    """The geometry method a fit with `--geometry geometry` reconstructs with (when it does): the
    one named, or the default one for auto and given; a ValueError naming the modes for another."""
    if geometry not in methods.fit_modes():
        raise ValueError(f"geometry must be one of {methods.fit_modes()}, got {geometry!r}")
    return methods.DEFAULT if geometry in methods.MODES else geometry


def needs_reconstruction(capture: CaptureSource, geometry: str = "auto") -> bool:
    """Whether the fit reconstructs the geometry first: `--geometry METHOD` (a geometry method's
    name), photos or a video without poses, or `auto` on a capture without shapes, mesh.ply or --mesh."""
    geometry_method(geometry)  # refuses an unknown mode
    named = geometry not in methods.MODES
    if named and capture.mesh is not None:
        raise InputError(capture.mesh, f"--mesh gives known geometry but --geometry {geometry} asks to reconstruct "
                                       "it; drop one")
    if not capture.posed:
        return True
    if geometry == "given" or capture.mesh is not None:
        return False
    return named or not capture.has_geometry()


def check_fit_target(run: RunDir, resume: bool) -> None:
    """Refuse to fit into an edited run, or over a fitted one unless resuming it."""
    if run.is_run() and run.is_edit():
        raise InputError(run.dir, "holds an edited run (edits.json): fit into another folder")
    if run.has_checkpoint() and not resume:
        raise InputError(run.dir, "already holds a fitted run: pass --resume to continue it, or choose another -o")


def posed_capture(capture: CaptureSource, run: RunDir, cfg: PoseConfig,
                  log: Callable[[str], None] = messages.note) -> CaptureSource:
    """The capture to fit or reconstruct: photos or a video without poses posed into RUN/pose
    (`ensure_poses`, reused while the inputs are the same) and that capture resolved, any other
    capture as it is."""
    if capture.posed:
        return capture
    return ensure_poses(capture, run, cfg, log=log)


def fit_capture(capture: str | Path, run_dir: str | Path, cfg: Config, geometry: str = "auto",
                mesh: str | Path | None = None, resume: bool = False,
                log: Callable[[str], None] = messages.note) -> dict:
    """Fit a capture into RUN_DIR: refuse a folder of other files, an edited run, or a fitted run
    without `resume` before any work; pose photos or a video without poses (RUN_DIR/pose/, a COLMAP
    capture, reused while the inputs are the same) and fit that capture; reconstruct the mesh with
    the geometry method (`geometry_method`) when `needs_reconstruction` (RUN_DIR/mesh.ply, reused on
    resume); then fit the materials.
    Returns the fit's summary (fit.json).
    The run's lock is held throughout: a second process fitting into RUN_DIR is refused."""
    parse_snapshot_times(cfg.train.snapshot_s)
    run = RunDir(run_dir)
    check_output_folder(run.dir, "run", "fit")
    if resume and not run.dir.is_dir():
        raise InputError(run.dir, "no run to resume (the folder does not exist)")
    capture = open_capture(capture, mesh, cfg.capture, cache_dir=run.dir / RunDir.UNDISTORTED)
    if not capture.posed and (mesh is not None or geometry == "given"):
        raise InputError(mesh or capture.given, "known geometry cannot be used with photos or a video without "
                                                "poses: their cameras come from SfM, in a frame and scale of its "
                                                f"own; drop {'--mesh' if mesh is not None else '--geometry given'}")
    reconstruct = needs_reconstruction(capture, geometry)
    method = methods.get(geometry_method(geometry))
    with run.lock("fit", log):
        check_fit_target(run, resume)  # once no other process writes here
        # A stage refused once it has read the capture (no pixel hits a --mesh, no geometry) removes
        # what it wrote (undistorted/, config.yaml, mesh.ply); the stages finished before are kept.
        with removed_on_refusal(run.dir):
            capture = posed_capture(capture, run, cfg.pose, log=log)
        if reconstruct:
            reused = resume and run.has_mesh()
            with removed_on_refusal(run.dir):
                mesh = ensure_geometry(capture, run, cfg, method.name, resume=resume)
            log(f"geometry: {'reusing' if reused else f'reconstructed with {method.label}:'} {mesh}")
            if not reused:
                for line in geometry_report(run, method.name):  # its training and its own scores
                    log(line)
            capture = capture.with_mesh(mesh)
        with removed_on_refusal(run.dir):
            return fit_materials(capture, run, cfg, resume=resume)


def fit(capture_path: str | Path, run_dir: str | Path, cfg: Config, mesh_path: str | Path | None = None,
        resume: bool = False) -> dict:
    """`vq-mitsuba fit --geometry given`: the capture's own geometry or `mesh_path`, no reconstruction."""
    return fit_capture(capture_path, run_dir, cfg, geometry="given", mesh=mesh_path, resume=resume)


def geometry_capture(capture: str | Path, run_dir: str | Path, cfg: Config, resume: bool = False,
                     gt_mesh: str | Path | None = None,
                     method: str = methods.DEFAULT) -> methods.Reconstruction:
    """`vq-mitsuba geometry`: the geometry `method` (NeuS by default) and the mesh into RUN_DIR under
    the run's lock, photos or a video posed first (`posed_capture`); returns the `Reconstruction`."""
    methods.get(method)  # an unknown method is refused before any work
    run = RunDir(run_dir)
    if resume and not run.dir.is_dir():
        raise InputError(run.dir, "no run to resume (the folder does not exist)")
    capture = open_capture(capture, options=cfg.capture, cache_dir=run.dir / RunDir.UNDISTORTED)
    with run.lock("geometry"), removed_on_refusal(run.dir):
        capture = posed_capture(capture, run, cfg.pose)
        return run_geometry(capture, run, cfg, method, resume=resume, gt_mesh=gt_mesh)


def fit_materials(capture: CaptureSource, run: RunDir, cfg: Config, resume: bool = False) -> dict:
    """The material fit on the capture's known geometry (its own, or `capture.mesh`) in a checked,
    locked run: returns the summary written to RUN_DIR/fit.json."""
    t_start = time.perf_counter()
    if resume and not run.has_checkpoint():
        # Interrupted before the first checkpoint (e.g. right after the geometry stage): start the
        # material fit from the beginning, keeping what the folder already holds (mesh.ply).
        messages.note(f"{run.checkpoint_path}: no checkpoint yet; the material fit starts from the beginning")
        resume = False
    capture = load_training_capture(capture, run)  # every input check happens here, first
    state = None
    if resume:
        state, cfg = _resume_point(run, capture, cfg)
        if state is None:
            return run.fit_summary()
    run.create()
    if not resume:  # a resumed run's config.yaml is written with its next checkpoint
        run.write_config(cfg)
    run.write_mesh(capture.mesh)
    trainer = Trainer(capture, run, cfg)
    _warn_about_inputs(capture, trainer.data.stats)
    run.write_info({"capture": str(Path(capture.source).resolve()), "world": capture.world,
                    "envmap_to_world": np.asarray(capture.envmap_to_world).tolist(),
                    "learned_envmap": trainer.model.learn_env, "n_views": len(capture.cameras), **trainer.data.stats,
                    "device": device_record()})
    if resume:
        _resume_trainer(trainer, state, run)
    startup = time.perf_counter() - t_start
    summary = trainer.train()
    summary["startup_s"] = startup
    write_products(trainer, summary)
    return summary


def load_training_capture(source: CaptureSource, run: RunDir) -> Capture:
    """The training views with their geometry (masked by the mesh when the geometry stage made it
    without masks)."""
    capture = source.load("train")
    if capture.mesh is None:
        raise InputError(capture.source, "no known geometry: the capture has no shapes and no mesh "
                         "(pass --mesh PATH, put mesh.ply in the capture's folder, or reconstruct it from the images "
                         f"with `fit --geometry {methods.DEFAULT}` or `vq-mitsuba geometry`)")
    if not capture.has_alpha and run.masks_from_mesh():
        capture = masked_by_mesh(capture)
    return capture


def _resume_point(run: RunDir, capture: Capture, cfg: Config) -> tuple[dict | None, Config]:
    """(the checkpoint to resume from, the config to resume with), refused before any work when the
    run was fitted to another capture or mesh or with networks the config does not build; (None,
    cfg) when the run is already fitted as far as train.iterations asks (and has its residual, when
    residual.iterations asks for one: a fitted run without it resumes at its last step, so that its
    results, the residual included, are written again)."""
    info = run.info()
    if Path(info["capture"]) != Path(capture.source).resolve():
        raise InputError(run.dir, f"was fitted to {info['capture']}, not {Path(capture.source).resolve()}; "
                                  "resume it with that capture, or choose another -o")
    if run.has_mesh():
        old, new = np.asarray(run.mesh().vertices), np.asarray(capture.mesh.vertices)
        scale = float(np.abs(new).max()) if new.size else 1.0
        if old.shape != new.shape or not np.allclose(old, new, atol=1e-5 * max(scale, 1e-6)):
            raise InputError(run.dir, f"was fitted on another mesh than the one given now ({len(old)} vertices "
                                      f"in {RunDir.MESH}, {len(new)} now); resume with the run's geometry, "
                                      "or choose another -o")
    init_mitsuba()
    state = run.load_state(device=torch_device())  # read once: the trainer resumes from it
    check_resumable(state, cfg, capture, run.checkpoint_path)
    done = int(state["step"])
    # the schedule steps done (more than the steps where the pace ran faster: train.stop)
    position = float((state.get("skips") or {}).get("pace", {}).get("position", done))
    if position < cfg.train.iterations:
        return state, cfg
    # nothing to train: config.yaml keeps matching the checkpoint
    if run.fit_summary().get("iterations") == done:
        if cfg.residual.iterations > 0 and run.residual_state(done) is None:
            messages.note(f"{run.dir}: already fitted ({done} iterations); its residual is missing or of an "
                          "earlier version: fitting it again")
        else:
            messages.note(f"{run.dir}: already fitted ({done} iterations; train.iterations="
                          f"{cfg.train.iterations} asks for no more): nothing to do, the run is unchanged")
            return None, cfg
    discrete = state.get("discrete")
    if cfg.vq.enabled and not (isinstance(discrete, dict) and bool(discrete.get("initialised", False))):
        raise InputError(run.dir, f"already has {done} steps, and its discrete branch has not started yet: "
                                  f"train.iterations={cfg.train.iterations} asks for no more steps, so the "
                                  "fit would end without materials; resume with train.iterations above "
                                  f"{done}")
    cfg = copy.deepcopy(cfg)
    cfg.train.iterations = max(done, int(math.floor(position)))
    return state, cfg


def _resume_trainer(trainer: Trainer, state: dict, run: RunDir) -> None:
    try:
        trainer.resume(state)
    except (RuntimeError, KeyError, TypeError, ValueError) as exc:  # the optimiser's or the rules' state
        raise InputError(run.checkpoint_path, f"cannot be resumed with the config now ({type(exc).__name__}: "
                                              f"{str(exc).splitlines()[0][:200] if str(exc) else ''}); resume "
                                              "with the run's own settings, or choose another -o") from None
    if trainer.finished:
        messages.note(f"{run.dir}: {trainer.step} iterations were done before; writing the run's results")


def _warn_about_inputs(capture: Capture, stats: dict) -> None:
    """Inputs that load but look wrong: few pixels hitting the mesh, a mesh of implausible size."""
    if stats["geometry_coverage"] < COVERAGE_WARNING and not capture.has_alpha:
        warn(f"the images have no alpha, so every pixel counts as the object's, and "
             f"{100 * (1 - stats['geometry_coverage']):.1f}% of them (the background) miss the mesh and are not "
             "fitted; with alpha masks (RGBA PNG or EXR) the fit also knows the object's outline")
    elif stats["geometry_coverage"] < COVERAGE_WARNING:
        warn(f"only {100 * stats['geometry_coverage']:.1f}% of opaque pixels hit the mesh; "
             "the geometry may not match the images (units, world axes?)")
    scale_warning = mesh_scale_warning(capture.mesh, capture.cameras)
    if scale_warning:
        warn(scale_warning)


def check_resumable(state: dict, cfg: Config, capture: Capture, path: Path) -> None:
    """Refuse, before any work, a checkpoint whose networks the config does not build (another
    field or vq architecture, vq.enabled changed, another kind of state file): InputError naming it."""
    from vq_mitsuba.run.run_dir import load_module_state

    if not isinstance(state.get("step"), int) or "optim" not in state:
        raise InputError(path, "not a checkpoint a fit resumes from ('step' or 'optim' missing)")
    model, discrete = material_networks(cfg, capture.mesh, torch.device("cpu"))  # load_state_dict copies across devices
    load_module_state(model, state.get("model"), path, "model")
    if (discrete is None) != (state.get("discrete") is None):
        raise InputError(path, f"was fitted with vq.enabled={str(discrete is None).lower()}, not "
                               f"{str(cfg.vq.enabled).lower()}: resume with the run's own vq.enabled")
    if discrete is not None:
        load_module_state(discrete, state["discrete"], path, "discrete")
    lamps = state.get("lamps") or {}
    had = len(lamps.get("offset", []))  # (K, 3): one row a lamp
    if had != cfg.lamps.count:
        raise InputError(path, f"was fitted with lamps.count={had}, not {cfg.lamps.count}: resume with the run's own "
                               "lamps.count")
    had = "camera" if bool(lamps.get("in_camera", False)) else "world"
    if cfg.lamps.count > 0 and had != cfg.lamps.frame:
        raise InputError(path, f"was fitted with lamps.frame={had}, not {cfg.lamps.frame}: resume with the run's own "
                               "lamps.frame")
    if (capture.envmap is None) != (state.get("envmap") is not None):
        raise InputError(path, "was fitted with " + ("a learned" if state.get("envmap") is not None else "the "
                               "capture's own") + " envmap, and the capture now says otherwise: resume with the "
                               "run's capture, or choose another -o")
