"""The run directory: every file a fit writes and everything else reads, in one place.

A run directory holds (docs/run_dir.md describes each file and its format):

    run.json             what was fitted: capture, world convention, envmap frame, device, format version
    config.yaml          the fully resolved configuration
    checkpoint.pt        networks, envmap and optimiser state (`fit --resume` continues from it)
    mesh.ply             the geometry used (given, or reconstructed by a geometry method beside geometry.json)
    neus.pt              a geometry method's own files, named by it (NeuS's checkpoint: `--resume` of the
                         geometry stage continues from it; `vq_mitsuba.geometry.methods`)
    geometry.json        the geometry stage's summary; geometry_loss.png its training curves
    pose/                photos or a video without poses, posed by SfM: a COLMAP capture and pose.json
    undistorted/         the capture's photos undistorted once (lens-distorted COLMAP captures)
    envmap.exr           the learned (or given) lighting, lat-long
    materials.json       the ranked codebook: M, each material's BRDF and pixel share, err_k
    materials_err.png    err_k against k with M marked
    materials_sheet.png  each ranked material as a sphere under the fitted light
    loss.png, fit.json   training curves and the fit's summary
    residual.pt          the view-dependent residual for novel views under the capture's light
    metrics.json         written by `vq-mitsuba eval`
    snapshots/           states kept at train.snapshot_s
    run.lock             while a command writes into the run: its owner (one process at a time)

An edited run (`vq-mitsuba edit`) holds only run.json, naming the fitted run it edits
(`edit_of`), and edits.json, its edit list; everything else is read from the fitted run.

Every file is written through `write_atomic` (a crash leaves the old file or the new one, never
half of one; a refused write, no permission or a full disk, is a `WriteError` naming the file);
JSON holds finite numbers only. What a RunDir parses (run.json, config.yaml) is parsed once per RunDir and kept.

Reading a finished run needs no training code: `RunDir(path).load()` builds the networks from
the checkpoint and returns a `FittedModel`.
"""

from __future__ import annotations

import copy
import json
import math
import os
import secrets
import threading
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from vq_mitsuba import messages
from vq_mitsuba.config import Config, load_config, read_yaml, save_config
from vq_mitsuba.errors import InputError, NumericalError, warn
from vq_mitsuba.models.material_edits import Edit
from vq_mitsuba.models.fields import PointLamps
from vq_mitsuba.models.fitted import FittedLamps, FittedModel, material_networks
from vq_mitsuba.models.residual import ResidualField
from vq_mitsuba.run.lock import RunLock
from vq_mitsuba.errors import WriteError, as_write_error  # WriteError: re-exported

FORMAT_VERSION = 1


def write_atomic(path: str | Path, write: Callable[[Path], None]) -> Path:
    """Call `write(tmp)` on a temporary file beside `path`, then move it into place: a crash
    leaves the old file or the new one, never half of one. The temporary name keeps the suffix,
    so writers that choose the format from it (PLY, NPZ, EXR) still can."""
    path = Path(path)
    # One temporary name per writer: two writers of one file (the editor's concurrent saves) must not
    # write into, or move away, each other's.
    tmp = path.with_name(f".{path.stem}.{os.getpid()}-{threading.get_ident()}-{secrets.token_hex(4)}.tmp{path.suffix}")
    try:
        write(tmp)
        os.replace(tmp, path)
    except OSError as exc:
        error = as_write_error(exc, path)
        if error is None:
            raise
        raise error from None
    finally:
        try:
            tmp.unlink(missing_ok=True)
        except OSError:
            pass
    return path


def _first_nonfinite(data, where: str = "") -> str | None:
    """Where in `data` (dicts and lists) a float is NaN or infinite, e.g. "materials[0].roughness"."""
    if isinstance(data, float):
        return None if math.isfinite(data) else (where or "the value")
    items = data.items() if isinstance(data, dict) else enumerate(data) if isinstance(data, (list, tuple)) else ()
    for key, value in items:
        found = _first_nonfinite(value, f"{where}[{key}]" if isinstance(key, int) else
                                 f"{where}.{key}" if where else str(key))
        if found:
            return found
    return None


def json_safe(obj):
    """`obj` (dicts, lists, numbers) with each NaN / Inf float as the string "nan", "inf" or "-inf"
    (JSON has no literal for them) and numpy scalars as Python numbers."""
    if isinstance(obj, dict):
        return {k: json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    if isinstance(obj, (float, np.floating)):
        x = float(obj)
        return x if math.isfinite(x) else ("nan" if math.isnan(x) else ("inf" if x > 0 else "-inf"))
    if isinstance(obj, np.integer):
        return int(obj)
    return obj


def write_json(path: str | Path, data: dict) -> Path:
    """Write JSON atomically, with finite numbers only: a NaN or Inf is a NumericalError naming the
    file and the key, and nothing is written."""
    try:
        text = json.dumps(data, indent=2, allow_nan=False)
    except ValueError:
        raise NumericalError(path, f"not written: {_first_nonfinite(data)} is not a finite number "
                                   "(a JSON file of a run holds finite numbers only)") from None
    return write_atomic(path, lambda tmp: tmp.write_text(text))


def check_writable(folder: str | Path) -> None:
    """Refuse, before any work, an output folder that cannot be made or written (its nearest
    existing parent, when it does not exist yet) with a WriteError naming it."""
    folder = Path(folder).absolute()
    existing = next(p for p in (folder, *folder.parents) if p.exists())
    if not existing.is_dir():
        raise InputError(existing, "is a file, not a folder")
    if not os.access(existing, os.W_OK | os.X_OK):
        reason = "the file system is read-only" if _read_only(existing) else "permission denied"
        raise InputError(existing, f"cannot be written: {reason}")


def _read_only(path: Path) -> bool:
    try:
        return bool(os.statvfs(path).f_flag & os.ST_RDONLY)
    except (OSError, AttributeError):
        return False


def read_json(path: Path, missing: str) -> dict:
    """A JSON object from `path`; InputError naming the file when it is missing (`missing` says
    what that means), not JSON, or not an object."""
    if not path.is_file():
        raise InputError(path, missing)
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise InputError(path, f"not valid JSON ({exc})") from None
    except RecursionError:  # [[[[... deeper than the parser goes
        raise InputError(path, "not valid JSON (lists or objects nested too deep)") from None
    if not isinstance(data, dict):
        raise InputError(path, "expected a JSON object")
    return data


def save_torch(obj, path: str | Path) -> Path:
    """torch.save atomically."""
    return write_atomic(path, lambda tmp: torch.save(obj, tmp))


FITTED_PARTS = ("model", "discrete", "envmap", "envmap_fixed", "lamps")
WORLDS = ("mitsuba", "blender")
DEVICES_USED = ("cpu", "cuda")


def check_info(info: dict, path: Path) -> dict:
    """run.json's values as the readers need them (InputError naming the file and the key
    otherwise): finite numbers only, `capture` a path, `world` one of WORLDS, `envmap_to_world` a
    4 x 4 matrix, `device` (when there is one: runs before --device have none) what ran the fit
    (requested, used: one of DEVICES_USED, the Mitsuba variant, torch's device name), and in an
    edited run `edit_of` the fitted run's two paths."""
    bad = _first_nonfinite(info)
    if bad:
        raise InputError(path, f"'{bad}' is not a finite number; fit the capture again")

    def wrong(key: str, what: str):
        value = info.get(key)
        got = "missing" if key not in info else f"got {json.dumps(value)[:60]}"
        return InputError(path, f"'{key}' must be {what} ({got}); fit the capture again")

    if not isinstance(info.get("capture"), str) or not info["capture"]:
        raise wrong("capture", "the capture's path")
    if info.get("world") not in WORLDS:
        raise wrong("world", " or ".join(f"'{w}'" for w in WORLDS))
    matrix = info.get("envmap_to_world")
    if not (isinstance(matrix, list) and len(matrix) == 4 and all(
            isinstance(row, list) and len(row) == 4 and all(
                isinstance(v, (int, float)) and not isinstance(v, bool) for v in row) for row in matrix)):
        raise wrong("envmap_to_world", "a 4 x 4 matrix of numbers")
    device = info.get("device")  # written since --device; an older run.json has none
    if device is not None and not (isinstance(device, dict) and device.get("used") in DEVICES_USED
                                   and all(isinstance(device.get(k), str) for k in ("requested", "variant"))):
        raise wrong("device", "{\"requested\": ..., \"used\": \"cpu\" or \"cuda\", \"variant\": ..., ...}")
    if "edit_of" in info:
        ref = info["edit_of"]
        if not (isinstance(ref, dict) and all(isinstance(ref.get(k), str) for k in ("absolute", "relative"))):
            raise wrong("edit_of", "{\"absolute\": PATH, \"relative\": PATH}")
    return info


def check_edit_materials(edits: list[Edit], num_materials: int | None, path: Path) -> None:
    """Refuse an edit list that selects a material the fitted run does not have (InputError naming
    the file and the entry)."""
    for i, edit in enumerate(edits):
        missing = [k for k in edit.selection.materials if num_materials is None or k > num_materials]
        if missing:
            has = f"materials 1..{num_materials}" if num_materials else "no materials (no discrete branch)"
            raise InputError(path, f"edit {i + 1} selects material {missing[0]}, but the fitted run has {has}")


def load_module_state(module: torch.nn.Module, tensors, path: Path, part: str) -> None:
    """`module.load_state_dict(tensors)`, or an InputError naming the state file when the tensors do
    not fit the networks the config builds (another architecture, another file)."""
    if not isinstance(tensors, dict):
        raise InputError(path, f"'{part}' is not a state of networks: not a checkpoint of this run")
    try:
        module.load_state_dict(tensors)
    except (RuntimeError, KeyError, TypeError, ValueError) as exc:
        first = str(exc).strip().splitlines()
        detail = next((line.strip() for line in first[1:] if line.strip()), first[0] if first else "")
        raise InputError(path, f"'{part}' does not fit the networks of the run's config ({detail[:200]}): the "
                               "file belongs to another run or configuration (field and vq settings must stay "
                               "those of the fit)") from None


def nonfinite_tensors(state: dict) -> list[str]:
    """Names of the fitted tensors (networks, envmap) in a state that hold NaN or Inf."""
    bad = []
    for part in FITTED_PARTS:
        tensors = state.get(part)
        if tensors is None:
            continue
        items = tensors.items() if isinstance(tensors, dict) else [("", tensors)]
        for name, t in items:
            if torch.is_tensor(t) and t.is_floating_point() and not bool(torch.isfinite(t).all()):
                bad.append(f"{part}.{name}" if name else part)
    return bad


class RunDir:
    INFO = "run.json"
    CONFIG = "config.yaml"
    CHECKPOINT = "checkpoint.pt"
    MESH = "mesh.ply"
    GEOMETRY = "geometry.json"
    GEOMETRY_PLOT = "geometry_loss.png"
    POSE = "pose"  # the COLMAP capture SfM made of photos or a video without poses (geometry/poses.py)
    POSE_SUMMARY = "pose/pose.json"  # written last: the pose stage finished
    UNDISTORTED = "undistorted"
    ENVMAP = "envmap.exr"
    MATERIALS = "materials.json"
    ERR_PLOT = "materials_err.png"
    SHEET = "materials_sheet.png"
    LOSS_PLOT = "loss.png"
    FIT = "fit.json"
    METRICS = "metrics.json"
    RESIDUAL = "residual.pt"  # the residual field of novel views (models/residual.py), with its fit's step
    SNAPSHOTS = "snapshots"
    RENDERS = "renders"  # the default output folder of `vq-mitsuba render`
    EDITS = "edits.json"
    LOCK = "run.lock"  # the command writing into the run (pid, host): RunLock
    # Files only a run of vq-mitsuba holds: a folder with one of them is a run (maybe unfinished).
    # `markers()` adds the files of the geometry methods (their checkpoints), which they declare.
    MARKERS = (INFO, CONFIG, CHECKPOINT, GEOMETRY, POSE_SUMMARY)
    _method_files: tuple[str, ...] = ()

    def __init__(self, path: str | Path):
        self.dir = Path(path)
        self._info: dict | None = None
        self._config: Config | None = None
        self._source: RunDir | None = None

    def __truediv__(self, name: str) -> Path:
        return self.dir / name

    def __repr__(self) -> str:
        return f"RunDir({str(self.dir)!r})"

    @property
    def checkpoint_path(self) -> Path:
        return self.dir / self.CHECKPOINT

    @property
    def undistorted_dir(self) -> Path:
        """The cache of undistorted photos (shared by the fit and by `eval` of an edit)."""
        return self.source().dir / self.UNDISTORTED if self.is_run() else self.dir / self.UNDISTORTED

    def has_checkpoint(self) -> bool:
        return self.checkpoint_path.is_file()

    def is_run(self) -> bool:
        """run.json is there: the folder holds a fitted (or edited) run."""
        return (self.dir / self.INFO).is_file()

    @classmethod
    def declare_method_files(cls, names: tuple[str, ...]) -> None:
        """The names of the files the registered geometry methods keep in a run (their checkpoints;
        `vq_mitsuba.geometry.methods` declares them as methods register): markers of a run, and names
        no other command writes there."""
        cls._method_files = tuple(dict.fromkeys(names))

    @classmethod
    def method_files(cls) -> tuple[str, ...]:
        """The files the geometry methods registered so far keep in a run."""
        return cls._method_files

    @classmethod
    def markers(cls) -> tuple[str, ...]:
        """MARKERS and the geometry methods' files: a folder with one of them is a run."""
        return cls.MARKERS + cls._method_files

    def holds_run_files(self) -> bool:
        """Any file that only a run writes is there (a run, or one interrupted early)."""
        return any((self.dir / name).is_file() for name in self.markers())

    def lock(self, command: str, log: Callable[[str], None] = messages.note) -> RunLock:
        """`with run.lock("fit"):` this process alone writes into the run (the folder is made if
        missing, and removed again if the command leaves it empty); another process holding it is
        an InputError naming it, a lock left by a dead process is taken over with a note."""
        return RunLock(self.dir / self.LOCK, command, log)

    def create(self) -> None:
        self.dir.mkdir(parents=True, exist_ok=True)

    def write_file(self, name: str, write: Callable[[Path], None]) -> Path:
        """Any other file of the run (a plot, a picture), written atomically by `write(path)`."""
        return write_atomic(self.dir / name, write)

    # --- run.json: what was fitted, with the format version ---------------------------------
    def write_info(self, info: dict) -> None:
        info = {"format": FORMAT_VERSION, **info}
        write_json(self.dir / self.INFO, info)
        self._info, self._source = info, None

    def info(self) -> dict:
        if self._info is None:
            path = self.dir / self.INFO
            info = read_json(path, "not a fitted run directory (run.json missing); run `vq-mitsuba fit` first")
            version = info.get("format")
            if version != FORMAT_VERSION:
                raise InputError(path, f"run-directory format {version!r} is not the format {FORMAT_VERSION} this "
                                       "version of vq-mitsuba reads; fit the capture again")
            self._info = check_info(info, path)
        return self._info

    # --- edited runs ---------------------------------------------------------------------------
    def source(self) -> RunDir:
        """The fitted run this run edits, or the run itself when it is not an edit."""
        if self._source is None:
            self._source = self._find_source()
        return self._source

    def _find_source(self) -> RunDir:
        info = self.info()
        if "edit_of" not in info:
            return self
        ref = info["edit_of"]
        for candidate in (self.dir / ref["relative"], Path(ref["absolute"])):
            if (candidate / self.INFO).is_file():
                return RunDir(candidate)
        raise InputError(self.dir / self.INFO, f"edits the run {ref['absolute']}, which is not there any more "
                                               f"(nor at {ref['relative']} from this folder)")

    def is_edit(self) -> bool:
        return "edit_of" in self.info()

    def edits(self) -> list[Edit]:
        """The edit list (empty for a fitted run)."""
        path = self.dir / self.EDITS
        if not self.is_edit():
            return []
        data = read_json(path, "missing: an edited run stores its edit list here")
        entries = data.get("edits")
        if not isinstance(entries, list):
            raise InputError(path, "expected {\"edits\": [...]}")
        return [Edit.from_dict(e, path, i) for i, e in enumerate(entries)]

    def write_edit(self, source: RunDir, edits: list[Edit]) -> None:
        """Make this folder an edited run of the fitted run `source` with the edit list `edits`."""
        base = source.source()
        if self.dir.resolve() == base.dir.resolve():
            raise InputError(self.dir, "an edit writes a new run: choose an -o other than the fitted run")
        info = {k: v for k, v in base.info().items() if k not in ("format", "edit_of")}
        with self.lock("edit"):
            info["edit_of"] = {"absolute": str(base.dir.resolve()),
                               "relative": os.path.relpath(base.dir.resolve(), self.dir.resolve())}
            made = [p for p in (self.dir / self.EDITS, self.dir / self.INFO) if not p.exists()]
            try:  # both files or, for a new edited run, neither: no edits.json without run.json
                write_json(self.dir / self.EDITS, {"edits": [e.to_dict() for e in edits]})
                self.write_info(info)
            except BaseException:
                for path in made:
                    path.unlink(missing_ok=True)
                raise

    # --- the capture's cameras ------------------------------------------------------------------
    def cameras(self) -> dict[str, list]:
        """The capture's views in the run's world: {"train": [...], and "test" / "val" where a
        transforms_test.json / transforms_val.json lies beside the capture}. Names are unique over
        all splits: a test or val view named as an earlier split's view (NeRF's train/r_0 and
        test/r_0) is called "test_r_0" ("val_r_0")."""
        import dataclasses

        from vq_mitsuba.data.cameras import convert_world
        from vq_mitsuba.data.captures import load_cameras
        from vq_mitsuba.data.formats.nerf_synthetic import SPLIT_FILE
        from vq_mitsuba.data.names import unique_names

        info = self.source().info()
        capture = Path(info["capture"])
        options = self.source().config().capture
        splits = {"train": capture}
        if not capture.is_dir():
            splits.update({s: capture.parent / SPLIT_FILE.format(s) for s in ("test", "val")})
        out = {}
        for split, path in splits.items():
            if path.exists() and (split == "train" or path != capture):
                cameras, world, _ = load_cameras(path, options if split == "train" else None)
                out[split] = [convert_world(c, world, info["world"]) for c in cameras]
        if "train" not in out:
            raise InputError(capture, f"the capture of the run {self.dir} is not there any more")
        taken = {c.name.casefold() for c in out["train"]}
        for split in [s for s in out if s != "train"]:
            names = [f"{split}_{c.name}" if c.name.casefold() in taken else c.name for c in out[split]]
            names = unique_names(sorted(taken) + names)[len(taken):]  # against every name before
            out[split] = [dataclasses.replace(c, name=n) for c, n in zip(out[split], names)]
            taken |= {n.casefold() for n in names}
        return out

    # --- configuration ------------------------------------------------------------------------
    def write_config(self, cfg: Config) -> None:
        write_atomic(self.dir / self.CONFIG, lambda tmp: save_config(cfg, tmp))
        self._config = None

    def saved_config(self) -> dict | None:
        """config.yaml as a mapping (None when there is none): the base a resumed fit starts from."""
        path = self.dir / self.CONFIG
        if not path.is_file():
            return None
        data = read_yaml(path, "a run's config.yaml") or {}
        if not isinstance(data, dict):
            raise InputError(path, "expected a mapping of sections")
        return data

    def config(self) -> Config:
        """The run's resolved configuration: parsed once, and a copy of its own for each caller
        (a caller that changes its copy, e.g. a preview without the bounce, changes no other)."""
        if self.is_edit():
            return self.source().config()
        if self._config is None:
            base = self.saved_config()
            if base is None:
                raise InputError(self.dir / self.CONFIG, "missing: the run directory is incomplete")
            self._config = load_config(base=base)
        return copy.deepcopy(self._config)

    # --- geometry and lighting ---------------------------------------------------------------
    def write_mesh(self, mesh) -> None:
        write_atomic(self.dir / self.MESH, mesh.export)

    def has_mesh(self) -> bool:
        return (self.dir / self.MESH).is_file()

    def mesh(self):
        from vq_mitsuba.data.captures import load_mesh

        return load_mesh(self.source().dir / self.MESH)

    def write_envmap(self, envmap: np.ndarray) -> None:
        from vq_mitsuba.data.imageio import write_exr

        write_atomic(self.dir / self.ENVMAP, lambda tmp: write_exr(tmp, envmap))

    def write_geometry_summary(self, summary: dict) -> None:
        write_json(self.dir / self.GEOMETRY, summary)

    def _geometry_summary(self) -> dict:
        """geometry.json, or {} where the geometry stage has not written one."""
        path = self.dir / self.GEOMETRY
        return read_json(path, "") if path.is_file() else {}

    def geometry_summary(self) -> dict:
        """geometry.json, the geometry stage's record ({} where the stage has not written one)."""
        return self._geometry_summary()

    def masks_from_mesh(self) -> bool:
        """Whether the run's mesh was reconstructed without masks (geometry.json's background is
        "model", which the stage writes from `Reconstruction.masks_from_mesh`): the capture then has
        no masks, and its views are masked by the mesh's coverage. (An edited run: ask its source().)"""
        return self._geometry_summary().get("background") == "model"

    # --- network states -----------------------------------------------------------------------
    def save_state(self, state: dict, path: Path | None = None) -> None:
        """Write a state atomically, only when every fitted tensor in it is finite."""
        path = path or self.checkpoint_path
        bad = nonfinite_tensors(state)
        if bad:
            raise NumericalError(self.dir, f"{path.name} not written: non-finite values in {', '.join(bad[:5])}; "
                                           "the previous checkpoint is kept")
        save_torch(state, path)

    def load_state(self, path: str | Path | None = None, device=None) -> dict:
        path = Path(path) if path is not None else self.checkpoint_path
        if not path.is_file():
            raise InputError(path, "checkpoint missing: the run did not finish its first checkpoint")
        try:
            # tensors, numbers, strings and containers only: a pickle that would run code is refused
            state = torch.load(path, map_location=device, weights_only=True)
        except Exception as exc:  # a torn or foreign file
            raise InputError(path, f"not a readable checkpoint ({type(exc).__name__}: {exc})") from None
        if not isinstance(state, dict):
            raise InputError(path, f"not a vq-mitsuba state file (a torch file holding a {type(state).__name__}, "
                                   "not a dictionary of states)")
        bad = nonfinite_tensors(state)
        if bad:
            raise InputError(path, f"holds non-finite values in {', '.join(bad[:5])}: refusing to load it")
        return state

    def save_residual(self, field_state: dict, step: int) -> None:
        """The residual field fitted after the material fit's step `step` (finite tensors only)."""
        bad = [k for k, t in field_state.items() if t.is_floating_point() and not bool(torch.isfinite(t).all())]
        if bad:
            raise NumericalError(self.dir, f"{self.RESIDUAL} not written: non-finite values in {', '.join(bad[:5])}")
        save_torch({"step": int(step), "field": field_state}, self.dir / self.RESIDUAL)

    def residual_state(self, step: int, device=None) -> dict | None:
        """The residual field's state when the run has one fitted after step `step` (a run fitted
        before this stage has none; one left from before a resumed fit is another step's: None)."""
        path = self.source().dir / self.RESIDUAL
        if not path.is_file():
            return None
        state = self.load_state(path, device)
        if not isinstance(state.get("step"), int) or not isinstance(state.get("field"), dict):
            raise InputError(path, "not a residual state ('step' and 'field' missing): fit the run again, or remove "
                                   "the file")
        if state["step"] != step:
            return None
        if "finest" not in state["field"]:  # the field before the surface light field
            warn(f"{path}: a residual of an earlier version of the field, left out (`vq-mitsuba fit CAPTURE -o RUN "
                 "--resume` fits it again)")
            return None
        return state["field"]

    def snapshot_path(self, elapsed_s: float, step: int) -> Path:
        (self.dir / self.SNAPSHOTS).mkdir(exist_ok=True)
        return self.dir / self.SNAPSHOTS / f"t{elapsed_s:07.1f}s_step{step:06d}.pt"

    # --- summaries ----------------------------------------------------------------------------
    def _read_json(self, name: str) -> dict | None:
        path = self.dir / name
        return read_json(path, "missing") if path.is_file() else None

    def write_materials(self, materials: dict) -> None:
        write_json(self.dir / self.MATERIALS, materials)

    def materials(self) -> dict | None:
        """materials.json of the fitted run (an edit keeps its materials and their ids)."""
        return self.source()._read_json(self.MATERIALS)

    def write_fit_summary(self, summary: dict) -> None:
        write_json(self.dir / self.FIT, summary)

    def fit_summary(self) -> dict:
        return self._read_json(self.FIT) or {}

    def metrics(self) -> dict | None:
        """metrics.json of `vq-mitsuba eval` (None before the run is scored)."""
        return self._read_json(self.METRICS)

    def write_metrics(self, metrics: dict, path: str | Path | None = None) -> Path:
        """metrics.json of `vq-mitsuba eval` (or the file `path` a user named instead). A score that
        is not a finite number (PSNR of identical images, SSIM of an empty mask) is written as the
        string "inf", "-inf" or "nan", as `eval` writes them, so that no scoring work is lost."""
        return write_json(Path(path) if path is not None else self.dir / self.METRICS, json_safe(metrics))

    # --- the fitted scene ---------------------------------------------------------------------
    def load(self, checkpoint: str | Path | None = None) -> FittedModel:
        """The fitted networks, lighting and mesh, from the checkpoint or another state file of
        this run (`checkpoint`, e.g. a snapshot). An edited run is its fitted run with the edits."""
        from vq_mitsuba.backend import init_mitsuba, torch_device

        info = self.info()
        if "edit_of" in info:
            edits = self.edits()
            fitted = self.source().load(checkpoint)
            check_edit_materials(edits, fitted.num_materials, self.dir / self.EDITS)
            fitted.edits = edits
            return fitted
        cfg = self.config()
        init_mitsuba()
        device = torch_device()
        state_path = Path(checkpoint) if checkpoint is not None else self.checkpoint_path
        state = self.load_state(checkpoint, device)
        mesh = self.mesh()
        model, discrete = material_networks(cfg, mesh, device)
        load_module_state(model, state.get("model"), state_path, "model")
        model.eval()
        if state.get("discrete") is None:
            discrete = None
        if discrete is not None:
            load_module_state(discrete, state["discrete"], state_path, "discrete")
            discrete.eval()
            if not bool(discrete.initialised):
                discrete = None
        envmap = _envmap_of(state, state_path)
        fitted = FittedModel(cfg, model, discrete, envmap, np.asarray(info["envmap_to_world"]), info["world"], mesh,
                             int(state.get("step", -1)), lamps=_lamps_of(state, state_path))
        residual = self.residual_state(fitted.step, device) if checkpoint is None else None
        if residual is not None:
            fitted.residual = ResidualField(*mesh.bounds, finest=int(residual["finest"])).to(device)
            load_module_state(fitted.residual, residual, self.dir / self.RESIDUAL, "field")
            fitted.residual.eval()
        return fitted


def _lamps_of(state: dict, path: Path) -> FittedLamps | None:
    """The fitted point lamps of a state; None without."""
    lamps = state.get("lamps")
    if lamps is None:
        return None
    keys = ("center", "radius", "offset", "log_intensity", "in_camera", "camera_to_world")
    parts = [lamps.get(k) if isinstance(lamps, dict) else None for k in keys]
    if not all(torch.is_tensor(t) for t in parts) or parts[2].ndim != 2 or parts[2].shape[1] != 3 \
            or parts[3].shape != parts[2].shape or parts[0].numel() != 3:
        raise InputError(path, f"its lamps are not point lamps ({', '.join(keys)}): not a checkpoint of this run")
    in_camera = bool(parts[4])
    module = PointLamps(torch.zeros(3), 1.0, torch.zeros_like(parts[2]), 1.0,
                        camera_to_world=parts[5].cpu() if in_camera else None)
    load_module_state(module, {k: t.detach().float().cpu() if t.is_floating_point() else t.cpu()
                               for k, t in zip(keys, parts)}, path, "lamps")
    with torch.no_grad():
        position, intensity = module.placement()
    return FittedLamps(position.numpy(), intensity.numpy(), in_camera)


def _envmap_of(state: dict, path: Path) -> np.ndarray:
    """The lat-long radiance (H, W, 3) of a state: the learned one, or the capture's own."""
    learned = state.get("envmap")
    if learned is not None:
        log_radiance = learned.get("log_radiance") if isinstance(learned, dict) else None
        envmap = torch.exp(log_radiance).cpu().numpy() if torch.is_tensor(log_radiance) else None
    else:
        fixed = state.get("envmap_fixed")
        envmap = fixed.cpu().numpy() if torch.is_tensor(fixed) else None
    if envmap is None or envmap.ndim != 3 or envmap.shape[2] != 3 or min(envmap.shape[:2]) < 2:
        shape = "missing" if envmap is None else f"of shape {tuple(envmap.shape)}"
        raise InputError(path, f"the envmap is {shape}, not a lat-long RGB map: not a checkpoint of this run")
    return envmap
