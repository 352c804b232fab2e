#!/usr/bin/env python
"""Where a true-mesh fit's minutes go, stage by stage, and what each way of spending fewer costs.

    python benchmarks/fit_minutes.py --variants default "name=key=value,key=value" ...
        [--scenes tabletop] [--seeds 0] [--data benchmarks/out/cycles200] [--resolution 200]
        [--n-train 100] [--n-test 10] [--eval-spp 64] [--warmup] [--out benchmarks/out/fit_minutes]
    python benchmarks/fit_minutes.py --report OUT/fit_minutes.json [...] [--out DIR]

A variant is `default` (the shipped configuration) or `NAME=KEY=VALUE[,KEY=VALUE...]`, its `--set`
items. Each fit is `vq-mitsuba fit DATA/NAME/transforms_train.json --mesh DATA/NAME/mesh.ply`
(with the scene's preset when there is one), one process at a time, timed from the command's start
to its exit; the stages' seconds come from its fit.json (start-up, material steps, residual: its
prediction render and its own steps), the rest of the wall time is the process's start and the
end's ranking and writing. Scored by `vq_mitsuba.eval.evaluate` on the test views (novel view,
basecolor, metallic, roughness, relighting, F1, M). Datasets as `skip_study.py` renders them
(Cycles; `make cycles`).

Writes OUT/fit_minutes.json (a row per scene, variant and seed) and OUT/fit_minutes.md (the rows,
and each variant's medians over the seeds against `default`). Run it on an otherwise idle machine.
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import time
from pathlib import Path

from bench_scenes import figure_text
from bench_time_error import figures
from provenance import command_line, describe, provenance, write_result
from skip_study import add_dataset_arguments, ensure_cycles_dataset, fit_command, run_fit, warmup_fit
from variants import parse_variant

REPO = Path(__file__).resolve().parent.parent
COLUMNS = [("wall_s", "wall s", ".0f"), ("startup_s", "start s", ".1f"), ("steps_s", "steps s", ".0f"),
           ("iterations", "steps", ".0f"), ("residual_predict_s", "res. render s", ".0f"),
           ("residual_fit_s", "res. fit s", ".0f"), ("residual_gain_db", "res. dB", ".2f"),
           ("novel_psnr", "view", ".2f"), ("novel_residual_psnr", "view + res.", ".2f"),
           ("basecolor_psnr", "basecolor", ".2f"),
           ("metallic_psnr", "metallic", ".2f"), ("roughness_psnr", "roughness", ".2f"),
           ("relit_psnr", "relit", ".2f"), ("seg_micro_f1", "F1", ".3f"), ("materials_found", "M", ".0f")]


def fit_one(name: str, data: Path, variant: str, overrides: list[str], seed: int, args) -> dict:
    run_dir = args.out / "runs" / name / variant / f"s{seed}"
    if run_dir.exists():
        shutil.rmtree(run_dir)
    cmd = fit_command(name, data, run_dir, overrides + [f"train.seed={seed}"])
    t0 = time.perf_counter()
    run_fit(cmd)
    return {"run_dir": run_dir, "wall_s": time.perf_counter() - t0}


def score(name: str, data: Path, variant: str, overrides: list[str], seed: int, fitted: dict, args) -> dict:
    from vq_mitsuba.eval.evaluate import evaluate
    from vq_mitsuba.messages import quiet

    run_dir = fitted["run_dir"]
    summary = json.loads((run_dir / "fit.json").read_text())
    with quiet():
        m = evaluate(run_dir, data, spp=args.eval_spp, meanshift_bandwidths=(), output=run_dir / "metrics.json")
    res = summary.get("residual") or {}
    row = {"scene": name, "variant": variant, "seed": seed, "overrides": overrides, "wall_s": fitted["wall_s"],
           "startup_s": summary.get("startup_s"), "steps_s": summary["seconds"],
           **figures(m, summary["seconds"], summary["iterations"]),
           "novel_residual_psnr": (m.get("novel_view_residual") or {}).get("psnr"),
           "residual_predict_s": (res["seconds"] - res["fit_s"]) if "fit_s" in res else None,
           "residual_fit_s": res.get("fit_s"),
           "residual_gain_db": (res["psnr_check_hits_after"] - res["psnr_check_hits_before"]) if res else None,
           "residual": res, "decisions": {k: {"choice": v.get("choice"), "reason": v.get("reason")}
                                          for k, v in summary.get("decisions", {}).items()}}
    print(f"[{name}/{variant}/s{seed}] " + "  ".join(f"{label} {figure_text(row.get(key), spec)}"
                                                    for key, label, spec in COLUMNS), flush=True)
    return row


def median(values: list) -> float | None:
    values = [v for v in values if v is not None]
    return statistics.median(values) if values else None


def markdown(rows: list[dict]) -> str:
    head = "| scene | variant | seed | " + " | ".join(label for _, label, _ in COLUMNS) + " |"
    lines = [head, "|---|---|---:|" + "---:|" * len(COLUMNS)]
    for r in rows:
        lines.append(f"| {r['scene']} | {r['variant']} | {r['seed']} | "
                     + " | ".join(figure_text(r.get(k), spec) for k, _, spec in COLUMNS) + " |")
    lines += ["", "Medians over the seeds, and against `default` (time ratio: default's wall time over the "
                  "variant's; score differences in dB):", "",
              "| scene | variant | seeds | wall s | speed-up | view | view + res. | basecolor | metallic | roughness "
              "| relit |",
              "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    keys = ["novel_psnr", "novel_residual_psnr", "basecolor_psnr", "metallic_psnr", "roughness_psnr", "relit_psnr"]
    for scene in dict.fromkeys(r["scene"] for r in rows):
        groups = {v: [r for r in rows if r["scene"] == scene and r["variant"] == v]
                  for v in dict.fromkeys(r["variant"] for r in rows if r["scene"] == scene)}
        med = {v: {k: median([r.get(k) for r in g]) for k in ["wall_s", *keys]} for v, g in groups.items()}
        base = med.get("default")
        for v, m in med.items():
            cells = [f"{m['wall_s']:.0f}"]
            if base and v != "default":
                cells.append(f"{base['wall_s'] / m['wall_s']:.2f}x")
                cells += ["" if m[k] is None or base[k] is None else f"{m[k] - base[k]:+.2f}" for k in keys]
            else:
                cells += [""] + [figure_text(m[k], ".2f") for k in keys]
            lines.append(f"| {scene} | {v} | {len(groups[v])} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--variants", nargs="+", default=["default"],
                    help="default, or NAME=KEY=VALUE[,KEY=VALUE...]: the --set items of a variant")
    add_dataset_arguments(ap, ["tabletop"], [0], 10)
    ap.add_argument("--report", type=Path, nargs="+", metavar="JSON",
                    help="no fit: the table of these fit_minutes.json files, their rows together")
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks" / "out" / "fit_minutes",
                    help="folder of the runs, fit_minutes.json and fit_minutes.md")
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    if args.report:
        table = markdown([row for path in args.report for row in json.loads(path.read_text())["rows"]])
        (args.out / "fit_minutes.md").write_text(table)
        print(table)
        return 0
    variants = dict(parse_variant(v) for v in args.variants)
    record = provenance(command_line(argv, __file__))
    print(f"$ {record['command']}\n{describe(record)}", flush=True)
    datasets = {name: ensure_cycles_dataset(name, args.data / name, args) for name in args.scenes}
    if args.warmup:
        name = args.scenes[0]
        warmup_fit(name, datasets[name], args.out, ["train.iterations=30", "residual.iterations=0"])
    rows = []
    path = args.out / "fit_minutes.json"
    result = {**record, "settings": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
              "variants": variants, "rows": rows}
    from vq_mitsuba.eval.evaluate import json_safe

    for seed in args.seeds:
        for name, data in datasets.items():
            for variant, overrides in variants.items():
                fitted = fit_one(name, data, variant, overrides, seed, args)
                rows.append(score(name, data, variant, overrides, seed, fitted, args))
                write_result(path, json_safe(result), indent=1)  # a stopped study keeps its rows
    table = markdown(rows)
    (args.out / "fit_minutes.md").write_text(table)
    print(table)
    print(f"wrote {path} and {args.out / 'fit_minutes.md'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
