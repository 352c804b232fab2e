"""Where the geometry stage plugs in: whether a capture has geometry, and running NeuS for a run."""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET
from pathlib import Path

from vq_mitsuba.config import CaptureConfig, NeuSConfig

UNDISTORTED = "undistorted"  # a run's cache of undistorted photos (COLMAP captures with lens distortion)


def capture_has_geometry(path: str | Path) -> bool:
    """True when a capture brings its own geometry: <shape> elements in a scene XML, or a
    mesh.ply beside a transforms json. Cheap: reads no images."""
    from vq_mitsuba.data.captures import resolve_capture_path

    source = resolve_capture_path(path)
    if source.suffix.lower() == ".xml":
        try:
            root = ET.parse(source).getroot()
        except (ET.ParseError, OSError):
            return True  # let the capture loader report the problem
        return any(True for _ in root.iter("shape"))
    return ((source if source.is_dir() else source.parent) / "mesh.ply").exists()


def run_geometry(capture_path, run_dir, cfg: NeuSConfig, resume: bool = False, progress: bool = True,
                 gt_mesh=None, capture_cfg: CaptureConfig | None = None) -> dict:
    """Load the capture, run NeuS + mesh export into run_dir; score against gt_mesh if given."""
    from vq_mitsuba.data.captures import load_capture, load_mesh
    from vq_mitsuba.geometry.neus import reconstruct

    gt = load_mesh(gt_mesh) if gt_mesh is not None else None
    capture = load_capture(capture_path, options=capture_cfg, split="train", cache_dir=Path(run_dir) / UNDISTORTED)
    info = reconstruct(capture, run_dir, cfg, resume=resume, progress=progress)
    info.pop("_neus", None)
    if gt is not None:
        from vq_mitsuba.geometry.mesh import mesh_metrics

        mesh = load_mesh(Path(run_dir) / "mesh.ply")
        info["metrics"] = mesh_metrics(mesh, gt)
        info["gt_mesh"] = str(Path(gt_mesh).resolve())
        (Path(run_dir) / "geometry.json").write_text(json.dumps(info, indent=2))
    return info


def ensure_geometry(capture_path, run_dir, cfg: NeuSConfig, resume: bool = False, progress: bool = True,
                    capture_cfg: CaptureConfig | None = None) -> Path:
    """RUN_DIR/mesh.ply from NeuS, reusing an existing one on resume; returns its path."""
    run_dir = Path(run_dir)
    mesh = run_dir / "mesh.ply"
    if resume and mesh.is_file():
        return mesh
    run_geometry(capture_path, run_dir, cfg, resume=resume, progress=progress, capture_cfg=capture_cfg)
    return mesh
