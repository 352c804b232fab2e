#!/usr/bin/env python
"""The spread over seeds of `vq-mitsuba batch --eval` runs, per scene, for one or more batches
(e.g. two commits), as a markdown table and JSON.

    vq-mitsuba batch DATA/demo/scene.xml -o BEFORE --preset demo --seeds 0,1,2,3,4 --eval --threads-per-run 1
    python benchmarks/seed_spread.py before=BEFORE after=AFTER --out benchmarks/results/STUDY/seeds.json

For each batch and scene: the median, min, max and spread (max - min) over its seeds of every
figure `eval` writes (novel view, basecolor, metallic, roughness, relighting image scale, in dB),
the materials found (M) against the truth, each true metal's fitted roughness, each material's
fitted and true metallic, the fit's seconds (`fit.json`, the material stage and its residual), the
trial's choice (`decisions.trials`) and the prior's weighing (`decisions.prior`).
Fit times compare only between batches run the same way (`--threads-per-run`, alone on the
machine).
"""

from __future__ import annotations

import argparse
import json
import statistics
from pathlib import Path

from provenance import describe, provenance, write_result

FIGURES = [("view", ("novel_view", "psnr")), ("basecolor", ("basecolor", "psnr")), ("metallic", ("metallic", "psnr")),
           ("roughness", ("roughness", "psnr")), ("relit", ("relighting", "image_scale", "mean", "psnr"))]


def _get(d, path):
    for k in path:
        d = d.get(k) if isinstance(d, dict) else None
    return d


def read_run(run: Path) -> dict:
    """One run's figures (None where eval wrote none)."""
    metrics = json.loads((run / "metrics.json").read_text())
    fit = json.loads((run / "fit.json").read_text())
    mats = json.loads((run / "materials.json").read_text())
    seg = metrics.get("segmentation") or {}
    trial = fit["decisions"].get("trials") or {}
    prior = fit["decisions"].get("prior") or {}
    return {"run": run.name, "scene": metrics.get("scene"),
            **{name: _get(metrics, path) for name, path in FIGURES},
            "M": mats.get("num_materials"), "M_true": seg.get("num_materials_true"),
            "metals": {p["name"]: round(p["roughness"], 3) for p in metrics.get("per_material", [])
                       if (p.get("metallic_true") or 0) > 0.5},
            "metal_truth": {p["name"]: round(p["roughness_true"], 3) for p in metrics.get("per_material", [])
                            if (p.get("metallic_true") or 0) > 0.5},
            "metallic_per_material": {p["name"]: [round(p["metallic"], 3), p.get("metallic_true")]
                                      for p in metrics.get("per_material", [])},
            "fit_s": fit.get("seconds"), "residual_s": _get(fit, ("residual", "seconds")),
            "trial": trial.get("choice"), "trial_reason": trial.get("reason"),
            "prior": prior.get("choice"), "prior_mean_weight": prior.get("mean_weight")}


def spread(values: list[float]) -> dict:
    vals = [v for v in values if isinstance(v, (int, float))]
    if not vals:
        return {}
    return {"median": statistics.median(vals), "min": min(vals), "max": max(vals), "spread": max(vals) - min(vals)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("batches", nargs="+", help="LABEL=BATCH_FOLDER (a `vq-mitsuba batch --eval` output)")
    ap.add_argument("--out", type=Path, help="write the JSON here")
    args = ap.parse_args(argv)
    record = provenance()
    result = {}
    for item in args.batches:
        label, _, folder = item.partition("=")
        runs = [read_run(r) for r in sorted(Path(folder).iterdir()) if (r / "metrics.json").is_file()]
        by_scene: dict[str, list[dict]] = {}
        for r in runs:
            by_scene.setdefault(r["scene"], []).append(r)
        result[label] = {scene: {"runs": rs, **{name: spread([r[name] for r in rs]) for name, _ in FIGURES},
                                 "fit_s": spread([r["fit_s"] for r in rs])}
                         for scene, rs in by_scene.items()}
    print(describe(record))
    print("\n| batch | scene | seeds | " + " | ".join(f"{n} median (min-max)" for n, _ in FIGURES)
          + " | fit s median | M per seed | metal roughness per seed | trials |")
    print("|---|---|---:|" + "---:|" * (len(FIGURES) + 1) + "---|---|---|")
    for label, scenes in result.items():
        for scene, s in sorted(scenes.items()):
            cells = [f"{s[n]['median']:.2f} ({s[n]['min']:.2f}-{s[n]['max']:.2f})" if s[n] else "-" for n, _ in FIGURES]
            ms = " ".join(f"{r['M']}/{r['M_true']}" for r in s["runs"])
            metals = "; ".join(",".join(f"{v:.3f}" for v in r["metals"].values()) for r in s["runs"])
            tried = " ".join(r["trial"] or "-" for r in s["runs"])
            print(f"| {label} | {scene} | {len(s['runs'])} | " + " | ".join(cells)
                  + f" | {s['fit_s'].get('median', float('nan')):.0f} | {ms} | {metals} | {tried} |")
    if args.out:
        write_result(args.out, {**record, "batches": {item.partition("=")[0]: item.partition("=")[2]
                                                      for item in args.batches}, "results": result})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
