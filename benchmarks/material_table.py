#!/usr/bin/env python
"""Each true material of scored runs, truth against fit: the continuous field's metallic and
roughness averaged over the material's pixels, their mean absolute error, and the discrete
materials that segmentation maps to it (each one's metallic, roughness and share of the pixels).

    python benchmarks/material_table.py [LABEL=]RUN ... [--json OUT.json]
    python benchmarks/material_table.py before=runs/s0 after=runs/s0_new

Each RUN is a finished fit scored by `vq-mitsuba eval RUN --gt DATASET` (its metrics.json with
`per_material` and `segmentation.mapping`, its materials.json). Prints one block per run: its
figures (novel view, basecolor, metallic, roughness, relighting PSNR), M and the table; writes
them with the command, commit, machine and versions to --json.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from provenance import provenance, write_json
from variants import labelled_runs

FIGURES = ("novel_view", "basecolor", "metallic", "roughness")


def read_run(run: Path) -> dict:
    """The run's figures, M and per true material table (see the module's docstring)."""
    try:
        metrics = json.loads((run / "metrics.json").read_text())
        materials = json.loads((run / "materials.json").read_text())
    except (OSError, ValueError) as exc:
        raise SystemExit(f"{run}: not a scored run ({exc}); run `vq-mitsuba eval {run} --gt DATASET` first")
    mapping = {int(k): v for k, v in metrics.get("segmentation", {}).get("mapping", {}).items()}
    names = {p["id"]: p["name"] for p in metrics["per_material"]}
    discrete: dict[str, list] = {}
    for m in materials["materials"]:
        true = names.get(mapping.get(m["id"]), "unmapped")
        discrete.setdefault(true, []).append({"metallic": round(m["metallic"], 3), "roughness": round(m["roughness"], 3),
                                              "pixel_share": round(m["pixel_fraction"], 3)})
    rows = {}
    for p in metrics["per_material"]:
        rows[p["name"]] = {k: round(p[k], 3) for k in ("metallic", "metallic_true", "roughness", "roughness_true",
                                                      "metallic_mae", "roughness_mae")}
        rows[p["name"]]["pixels"] = p["pixels"]
        rows[p["name"]]["discrete"] = discrete.get(p["name"], [])
    figures = {k: round(metrics[k]["psnr"], 2) for k in FIGURES if isinstance(metrics.get(k), dict)}
    relit = metrics.get("relighting", {}).get("image_scale", {}).get("mean", {}).get("psnr")
    if relit is not None:
        figures["relighting"] = round(relit, 2)
    return {"run": str(run), "M": materials["num_materials"], "figures": figures, "materials": rows}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", nargs="+", help="scored runs, each RUN or LABEL=RUN")
    parser.add_argument("--json", type=Path, help="write the tables here")
    args = parser.parse_args(argv)
    out = {}
    for label, run in labelled_runs(args.runs):
        out[label] = row = read_run(run)
        print(f"{label}: M {row['M']}, " + ", ".join(f"{k} {v:.2f}" for k, v in row["figures"].items()))
        for name, m in row["materials"].items():
            codes = "; ".join(f"{d['metallic']:.3f}/{d['roughness']:.2f} ({100 * d['pixel_share']:.0f} %)"
                              for d in m["discrete"])
            print(f"  {name:14s} metallic {m['metallic']:.3f} ({m['metallic_true']:.3f})  roughness "
                  f"{m['roughness']:.3f} ({m['roughness_true']:.3f}, MAE {m['roughness_mae']:.3f})  discrete: {codes}")
    if args.json:
        write_json(args.json, {**provenance(), "runs": out})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
