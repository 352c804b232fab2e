#!/usr/bin/env python
"""Lamps recovered by fits of scenes lit by them: each fitted lamp against the scene's own, and the
run's figures beside it.

    python benchmarks/lamp_recovery.py [LABEL=]RUN ... [--json OUT.json]
    python benchmarks/lamp_recovery.py lamp=runs/lamp_s0 none=runs/nolamp_s0 --json lamps.json

Each RUN is a finished fit of a `make-scene` dataset (its capture's folder holds scene.json, whose
`lamps` give the truth: Blender-world positions, or camera-frame ones for a flash) scored by
`vq-mitsuba eval RUN --gt DATASET`. Prints per run its time, M and figures (novel view, with the
residual, basecolor, metallic, roughness, relighting) and, per lamp, the position error as a share
of the object's size (its bounding box's diagonal) and the ratio of fitted to true power (the mean
of the RGB intensities); writes them with the command, commit, machine and versions to --json.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from provenance import provenance, write_json
from variants import labelled_runs

# Blender world = R @ Mitsuba world (vq_mitsuba.data.cameras.BLENDER_ENV_TO_WORLD's rotation)
R_BLENDER_FROM_MITSUBA = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])


def _psnr(metrics: dict, key: str) -> float | None:
    value = metrics.get(key)
    return round(value["psnr"], 2) if isinstance(value, dict) and "psnr" in value else None


def read_run(run: Path) -> dict:
    """The run's time, M, figures and each lamp against the truth (see the module's docstring)."""
    try:
        fit = json.loads((run / "fit.json").read_text())
        metrics = json.loads((run / "metrics.json").read_text())
        info = json.loads((run / "run.json").read_text())
    except (OSError, ValueError) as exc:
        raise SystemExit(f"{run}: not a scored run ({exc}); run `vq-mitsuba eval {run} --gt DATASET` first")
    scene = json.loads((Path(info["capture"]).parent / "scene.json").read_text())
    relit = metrics.get("relighting", {}).get("albedo_scale", {}).get("mean", {}).get("psnr")
    row = {"run": str(run), "seconds": round(fit["seconds"], 1),
           "M": metrics.get("segmentation", {}).get("num_materials_found"),
           "figures": {"novel_view": _psnr(metrics, "novel_view"), "novel_view_residual": _psnr(metrics, "novel_view_residual"),
                       "basecolor": _psnr(metrics, "basecolor"), "metallic": _psnr(metrics, "metallic"),
                       "roughness": _psnr(metrics, "roughness"), "relighting": None if relit is None else round(relit, 2)},
           "lamps_fitted": fit["decisions"].get("lamps", {}).get("choice", "none"), "lamps": []}
    import trimesh

    size = float(np.linalg.norm(np.ptp(trimesh.load(run / "mesh.ply", process=False).bounds, axis=0)))
    fitted = fit["decisions"].get("lamps", {}).get("lamps", [])
    for true, got in zip(scene.get("lamps", []), fitted):
        want = np.asarray(true["position"], dtype=float)
        if true.get("frame", "world") == "world" and info.get("world") == "mitsuba":
            want = R_BLENDER_FROM_MITSUBA.T @ want
        err = float(np.linalg.norm(np.asarray(got["position"]) - want))
        row["lamps"].append({"frame": true.get("frame", "world"), "true_position": want.round(4).tolist(),
                             "position": np.round(got["position"], 4).tolist(),
                             "position_error_of_size": round(err / size, 4),
                             "true_intensity": true["intensity"], "intensity": np.round(got["intensity"], 3).tolist(),
                             "power_ratio": round(float(np.mean(got["intensity"]) / np.mean(true["intensity"])), 3)})
    return row


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", nargs="+", help="scored runs, each RUN or LABEL=RUN")
    parser.add_argument("--json", type=Path, help="write the rows here")
    args = parser.parse_args(argv)
    out = {}
    for label, run in labelled_runs(args.runs):
        out[label] = row = read_run(run)
        figures = ", ".join(f"{k} {v:.2f}" for k, v in row["figures"].items() if v is not None)
        print(f"{label}: {row['seconds']} s, M {row['M']}, lamps {row['lamps_fitted']}; {figures}")
        for lamp in row["lamps"]:
            print(f"  {lamp['frame']} lamp: position {lamp['position']} (true {lamp['true_position']}, error "
                  f"{100 * lamp['position_error_of_size']:.1f} % of the size), power x{lamp['power_ratio']:.3f}")
    if args.json:
        write_json(args.json, {**provenance(), "runs": out})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
