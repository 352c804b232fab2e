"""The run directory: every file a fit writes and everything else reads, in one place.

A run directory holds (docs/run_dir.md describes each file and its format):

    run.json             what was fitted: capture, world convention, envmap frame, format version
    config.yaml          the fully resolved configuration
    checkpoint.pt        networks, envmap and optimiser state (`fit --resume` continues from it)
    mesh.ply             the geometry used (given, or reconstructed by NeuS beside geometry.json)
    envmap.exr           the learned (or given) lighting, lat-long
    materials.json       the ranked codebook: M, each material's BRDF and pixel share, err_k
    materials_err.png    err_k against k with M marked
    materials_sheet.png  each ranked material as a sphere under the fitted light
    loss.png, fit.json   training curves and the fit's summary
    metrics.json         written by `vq-mitsuba eval`
    snapshots/           states kept at train.snapshot_s

Reading a finished run needs no training code: `RunDir(path).load()` builds the networks from
the checkpoint and returns a `FittedModel`.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import torch
import yaml

from vq_mitsuba.config import Config, load_config, save_config
from vq_mitsuba.errors import InputError
from vq_mitsuba.models.fitted import FittedModel, material_networks

FORMAT_VERSION = 1


def write_json(path: Path, data: dict) -> None:
    """Write JSON atomically (a crash leaves the old file or the new one, never half of one)."""
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(data, indent=2))
    os.replace(tmp, path)


def save_torch(obj, path: Path) -> None:
    """torch.save atomically."""
    tmp = path.with_suffix(path.suffix + ".tmp")
    torch.save(obj, tmp)
    os.replace(tmp, path)


class RunDir:
    INFO = "run.json"
    CONFIG = "config.yaml"
    CHECKPOINT = "checkpoint.pt"
    MESH = "mesh.ply"
    ENVMAP = "envmap.exr"
    MATERIALS = "materials.json"
    ERR_PLOT = "materials_err.png"
    SHEET = "materials_sheet.png"
    LOSS_PLOT = "loss.png"
    FIT = "fit.json"
    METRICS = "metrics.json"
    GEOMETRY = "geometry.json"
    SNAPSHOTS = "snapshots"

    def __init__(self, path: str | Path):
        self.dir = Path(path)

    def __truediv__(self, name: str) -> Path:
        return self.dir / name

    def __repr__(self) -> str:
        return f"RunDir({str(self.dir)!r})"

    @property
    def checkpoint_path(self) -> Path:
        return self.dir / self.CHECKPOINT

    def has_checkpoint(self) -> bool:
        return self.checkpoint_path.is_file()

    def create(self) -> None:
        self.dir.mkdir(parents=True, exist_ok=True)

    # --- run.json: what was fitted, with the format version ---------------------------------
    def write_info(self, info: dict) -> None:
        write_json(self.dir / self.INFO, {"format": FORMAT_VERSION, **info})

    def info(self) -> dict:
        path = self.dir / self.INFO
        if not path.is_file():
            raise InputError(path, "not a fitted run directory (run.json missing); run `vq-mitsuba fit` first")
        try:
            info = json.loads(path.read_text())
        except json.JSONDecodeError as exc:
            raise InputError(path, f"not valid JSON ({exc})") from None
        version = info.get("format")
        if version != FORMAT_VERSION:
            raise InputError(path, f"run-directory format {version!r} is not the format {FORMAT_VERSION} this "
                                   "version of vq-mitsuba reads; fit the capture again")
        return info

    # --- configuration ------------------------------------------------------------------------
    def write_config(self, cfg: Config) -> None:
        save_config(cfg, self.dir / self.CONFIG)

    def saved_config(self) -> dict | None:
        """config.yaml as a mapping (None when there is none): the base a resumed fit starts from."""
        path = self.dir / self.CONFIG
        if not path.is_file():
            return None
        try:
            return yaml.safe_load(path.read_text()) or {}
        except yaml.YAMLError as exc:
            raise InputError(path, f"invalid YAML: {exc}") from None

    def config(self) -> Config:
        base = self.saved_config()
        if base is None:
            raise InputError(self.dir / self.CONFIG, "missing: the run directory is incomplete")
        return load_config(base=base)

    # --- geometry and lighting ---------------------------------------------------------------
    def write_mesh(self, mesh) -> None:
        mesh.export(self.dir / self.MESH)

    def mesh(self):
        from vq_mitsuba.data.captures import load_mesh

        return load_mesh(self.dir / self.MESH)

    def write_envmap(self, envmap: np.ndarray) -> None:
        from vq_mitsuba.data.imageio import write_exr

        write_exr(self.dir / self.ENVMAP, envmap)

    # --- network states -----------------------------------------------------------------------
    def save_state(self, state: dict, path: Path | None = None) -> None:
        save_torch(state, path or self.checkpoint_path)

    def load_state(self, path: str | Path | None = None, device=None) -> dict:
        path = Path(path) if path is not None else self.checkpoint_path
        if not path.is_file():
            raise InputError(path, "checkpoint missing: the run did not finish its first checkpoint")
        return torch.load(path, map_location=device, weights_only=False)

    def snapshot_path(self, elapsed_s: float, step: int) -> Path:
        (self.dir / self.SNAPSHOTS).mkdir(exist_ok=True)
        return self.dir / self.SNAPSHOTS / f"t{elapsed_s:07.1f}s_step{step:06d}.pt"

    # --- summaries ----------------------------------------------------------------------------
    def _read_json(self, name: str) -> dict | None:
        path = self.dir / name
        return json.loads(path.read_text()) if path.is_file() else None

    def write_materials(self, materials: dict) -> None:
        write_json(self.dir / self.MATERIALS, materials)

    def materials(self) -> dict | None:
        return self._read_json(self.MATERIALS)

    def write_fit_summary(self, summary: dict) -> None:
        write_json(self.dir / self.FIT, summary)

    def fit_summary(self) -> dict:
        return self._read_json(self.FIT) or {}

    # --- the fitted scene ---------------------------------------------------------------------
    def load(self, checkpoint: str | Path | None = None) -> FittedModel:
        """The fitted networks, lighting and mesh, from the checkpoint or another state file of
        this run (`checkpoint`, e.g. a snapshot)."""
        from vq_mitsuba.backend import init_mitsuba, torch_device

        info = self.info()
        cfg = self.config()
        init_mitsuba()
        device = torch_device()
        state = self.load_state(checkpoint, device)
        mesh = self.mesh()
        model, discrete = material_networks(cfg, mesh, device)
        model.load_state_dict(state["model"])
        model.eval()
        if state.get("discrete") is None:
            discrete = None
        if discrete is not None:
            discrete.load_state_dict(state["discrete"])
            discrete.eval()
            if not bool(discrete.initialised):
                discrete = None
        if state.get("envmap") is not None:
            envmap = torch.exp(state["envmap"]["log_radiance"]).cpu().numpy()
        else:
            envmap = state["envmap_fixed"].cpu().numpy()
        return FittedModel(cfg, model, discrete, envmap, np.asarray(info["envmap_to_world"]), info["world"], mesh,
                           int(state.get("step", -1)))
