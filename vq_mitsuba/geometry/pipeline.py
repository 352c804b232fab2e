"""Where the geometry stage plugs in: whether a capture has geometry, and running NeuS for a run."""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET
from pathlib import Path

from ..errors import InputError
from .config import NeuSConfig, apply_overrides, from_dict


def capture_has_geometry(path: str | Path) -> bool:
    """True when a capture brings its own geometry: <shape> elements in a scene XML, or a
    mesh.ply beside a transforms json. Cheap: reads no images."""
    from ..capture.dataset import resolve_capture_path

    source = resolve_capture_path(path)
    if source.suffix.lower() == ".xml":
        try:
            root = ET.parse(source).getroot()
        except (ET.ParseError, OSError):
            return True  # let the capture loader report the problem
        return any(True for _ in root.iter("shape"))
    return (source.parent / "mesh.ply").exists()


def load_neus_config(overrides: list[str] | None = None, config_file: str | Path | None = None) -> NeuSConfig:
    """Defaults, then the `neus:` section of a YAML file (if any), then neus.key=value overrides."""
    cfg = NeuSConfig()
    if config_file is not None:
        from ..config import read_config_file

        path = Path(config_file)
        section = read_config_file(path).get("neus")
        if section is not None:
            if not isinstance(section, dict):
                raise InputError(path, "the `neus` section must be a mapping of keys to values")
            try:
                cfg = from_dict(section)
            except InputError as exc:
                raise InputError(path, exc.message) from exc
    return apply_overrides(cfg, overrides)


def run_geometry(capture_path, run_dir, overrides: list[str] | None = None, config_file=None, resume: bool = False,
                 progress: bool = True, gt_mesh=None) -> dict:
    """Load the capture, run NeuS + mesh export into run_dir; score against gt_mesh if given."""
    from ..capture.dataset import load_capture, load_mesh
    from .neus import reconstruct

    cfg = load_neus_config(overrides, config_file)  # bad keys fail before the images are read
    gt = load_mesh(gt_mesh) if gt_mesh is not None else None
    capture = load_capture(capture_path)
    info = reconstruct(capture, run_dir, cfg, resume=resume, progress=progress)
    info.pop("_neus", None)
    if gt is not None:
        from .mesh import mesh_metrics

        mesh = load_mesh(Path(run_dir) / "mesh.ply")
        info["metrics"] = mesh_metrics(mesh, gt)
        info["gt_mesh"] = str(Path(gt_mesh).resolve())
        (Path(run_dir) / "geometry.json").write_text(json.dumps(info, indent=2))
    return info


def ensure_geometry(capture_path, run_dir, overrides: list[str] | None = None, config_file=None,
                    resume: bool = False, progress: bool = True) -> Path:
    """RUN_DIR/mesh.ply from NeuS, reusing an existing one on resume; returns its path."""
    run_dir = Path(run_dir)
    mesh = run_dir / "mesh.ply"
    if resume and mesh.is_file():
        return mesh
    run_geometry(capture_path, run_dir, overrides, config_file=config_file, resume=resume, progress=progress)
    return mesh
