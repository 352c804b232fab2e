#!/usr/bin/env python
"""Benchmark of the discrete branch: material count, segmentation, MeanShift and ablations.

    python benchmarks/bench_discrete.py [--scenes demo texture balls] [--variants continuous vq ...]
        [--resolution 64] [--iterations N] [--time-limit S] [--spp N] [--out benchmarks/out]

For each scene and variant (a set of config overrides, listed in VARIANTS): fit from the
dataset's scene.xml (datasets are generated or reused as in bench_scenes.py), evaluate on the test
views, and collect: the number of materials found against the truth, segmentation micro/macro F1,
basecolor PSNR of the continuous branch and of the discrete branch, novel-view and relighting
PSNR, fit seconds. Every evaluation also scores the MeanShift baseline (bandwidths 0.2, 0.3,
0.5) on that run's continuous BRDF maps. Writes OUT/bench_discrete.json and .md and prints
new / old ratios against an earlier JSON. Single runs.
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
import sys
from pathlib import Path

from bench_scenes import figure_text, ensure_dataset, scene_config
from provenance import command_line, describe, provenance, write_result
from vq_mitsuba.synthetic import mitsuba_scenes as synthetic
from vq_mitsuba.eval.evaluate import evaluate, format_table, json_safe
from vq_mitsuba.engine.pipeline import fit
from vq_mitsuba.messages import quiet

REPO = Path(__file__).resolve().parent.parent

# name -> (overrides, what it tests). "vq" is the full method with this project's defaults.
VARIANTS = {
    "continuous": (["vq.enabled=false"], "continuous branch alone (--preset continuous)"),
    "vq": ([], "the defaults: joint training, dropout ranking, L_chr"),
    "no_ranking": (["ablation.no_ranking=true"], "ablation: M = M0, no dropout ranking"),
    "no_chr": (["loss.w_chr=0"], "ablation: no chromaticity loss"),
    "sm_paper": (["loss.w_sm=0.05"], "with L_sm at the paper's weight 0.05 (default 0)"),
    "single_branch": (["ablation.single_branch=true"], "ablation: discrete branch alone after warm-up"),
    "separate": (["ablation.separate=true"], "ablation: discrete branch trained on detached latents"),
    "shared_light": (["ablation.shared_light=true"], "ablation: the discrete loss also trains the light"),
}

FIGURES = [
    ("materials_found", "M found", "d"), ("materials_true", "M true", "d"),
    ("seg_micro_f1", "micro-F1", ".3f"), ("seg_macro_f1", "macro-F1", ".3f"),
    ("basecolor_psnr", "albedo PSNR (cont.)", ".2f"), ("basecolor_d_psnr", "albedo PSNR (discr.)", ".2f"),
    ("novel_psnr", "view PSNR", ".2f"), ("relit_psnr", "relit PSNR (albedo scale)", ".2f"),
    ("fit_s", "fit s", ".1f"), ("iterations", "iters", "d"),
]


def figures(m: dict, summary: dict) -> dict:
    seg = m.get("segmentation") or {}
    d = m.get("discrete_branch") or {}
    rel = m["relighting"]["albedo_scale"]["mean"]
    return {
        "materials_found": seg.get("num_materials_found"), "materials_true": seg.get("num_materials_true"),
        "seg_micro_f1": seg.get("micro_f1"), "seg_macro_f1": seg.get("macro_f1"),
        "basecolor_psnr": m["basecolor"]["psnr"], "basecolor_d_psnr": (d.get("basecolor") or {}).get("psnr"),
        "novel_psnr": m["novel_view"]["psnr"], "relit_psnr": rel["psnr"] if rel else None,
        "fit_s": summary["seconds"], "iterations": summary["iterations"],
    }


def run_one(scene: str, variant: str, data: Path, args, out: Path) -> dict:
    overrides, _ = VARIANTS[variant]
    cfg, _ = scene_config(scene, [f"train.time_limit_s={args.time_limit}", *overrides, *args.set])
    if args.iterations is not None:
        cfg.train.iterations = args.iterations
    run_dir = out / "runs_discrete" / scene / variant
    if run_dir.exists():
        shutil.rmtree(run_dir)
    print(f"[{scene}/{variant}] fitting ({cfg.train.iterations} iterations; {' '.join(overrides)})")
    summary = fit(data / "scene.xml", run_dir, cfg)
    m = evaluate(run_dir, data, spp=args.spp, meanshift_bandwidths=(0.2, 0.3, 0.5))
    print(format_table(m))
    row = {"scene": scene, "variant": variant, "overrides": overrides, "run": str(run_dir),
           "figures": figures(m, summary)}
    if m.get("meanshift"):
        row["meanshift"] = {bw: v for bw, v in m["meanshift"].items() if isinstance(v, dict)}
    return row


def markdown(result: dict) -> str:
    lines = [f"# bench_discrete ({result['date']})", "",
             f"Resolution {result['settings']['resolution']}, iterations {result['settings']['iterations'] or 'config'}, "
             f"fit time limit {result['settings']['time_limit_s']:g} s (0: none); single runs. Albedo PSNR in sRGB after "
             "per-channel lstsq alignment (each branch aligned on its own); segmentation pooled over the test views.", "",
             "| scene | variant | " + " | ".join(label for _, label, _ in FIGURES) + " |",
             "|---|---|" + "---:|" * len(FIGURES)]
    for r in result["rows"]:
        lines.append(f"| {r['scene']} | {r['variant']} | "
                     + " | ".join(figure_text(r["figures"].get(k), spec) for k, _, spec in FIGURES) + " |")
    ms_rows = [r for r in result["rows"] if r.get("meanshift")]
    if ms_rows:
        lines += ["", "MeanShift baseline on each run's continuous maps:", "",
                  "| scene | run | bandwidth | micro-F1 | macro-F1 | clusters |", "|---|---|---:|---:|---:|---:|"]
        for r in ms_rows:
            for bw, v in r["meanshift"].items():
                lines.append(f"| {r['scene']} | {r['variant']} | {bw} | {v['micro_f1']:.3f} | {v['macro_f1']:.3f} | "
                             f"{v['num_materials_found']} |")
    lines += ["", "Variants: " + "; ".join(f"`{k}`: {VARIANTS[k][1]}" for k in result["settings"]["variants"]),
              "", "Machine: " + describe(result), "",
              f"Command: `{result['command']}`", ""]
    return "\n".join(lines)


def compare(new: dict, old: dict) -> str:
    old_by = {(r["scene"], r["variant"]): r["figures"] for r in old.get("rows", [])}
    rows = []
    for r in new["rows"]:
        prev = old_by.get((r["scene"], r["variant"]))
        if prev is None:
            continue
        cells = []
        for key, label, _ in FIGURES:
            a, b = r["figures"].get(key), prev.get(key)
            ok = all(isinstance(x, (int, float)) and math.isfinite(x) for x in (a, b)) and b != 0
            cells.append(f"{label} {a / b:.3f}" if ok else f"{label} -")
        rows.append(f"{r['scene']}/{r['variant']}: " + ", ".join(cells))
    return ("new / old:\n" + "\n".join(rows)) if rows else "nothing in common with the previous results"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scenes", nargs="+", default=list(synthetic.SCENES), choices=synthetic.SCENES)
    p.add_argument("--variants", nargs="+", default=["continuous", "vq"], choices=list(VARIANTS),
                   help="variants to run (default: continuous vq); all: " + ", ".join(VARIANTS))
    p.add_argument("--resolution", type=int, default=64, help="dataset image size (default 64)")
    p.add_argument("--iterations", type=int, help="fit iterations (default: the scene's config)")
    p.add_argument("--time-limit", type=float, default=0.0, metavar="SECONDS", help="fit time limit (0: none)")
    p.add_argument("--spp", type=int, help="evaluation render spp (default: the run's render.spp)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="extra override for every run")
    p.add_argument("--out", default=str(REPO / "benchmarks" / "out"))
    p.add_argument("--compare", help="previous bench_discrete.json (default: OUT/bench_discrete.json)")
    p.add_argument("--quiet", action="store_true", help="no progress bars or notes")
    args = p.parse_args(argv)
    args.command = command_line(argv, __file__)

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    json_path = out / "bench_discrete.json"
    old_path = Path(args.compare) if args.compare else json_path
    old = json.loads(old_path.read_text()) if old_path.is_file() else None
    rows = []
    with quiet(args.quiet):
        for scene in args.scenes:
            data = ensure_dataset(scene, out / f"data_{args.resolution}" / scene, args.resolution)
            for v in args.variants:
                rows.append(run_one(scene, v, data, args, out))
                write_results(args, rows, json_path, out)  # after every run: an interrupted benchmark keeps its rows
    result = write_results(args, rows, json_path, out)
    print(markdown(result))
    if old is not None:
        print(compare(result, old))
    return 0


def write_results(args, rows: list[dict], json_path: Path, out: Path) -> dict:
    result = {
        **provenance(args.command),
        "settings": {"scenes": args.scenes, "variants": args.variants, "resolution": args.resolution,
                     "iterations": args.iterations, "time_limit_s": args.time_limit, "eval_spp": args.spp,
                     "overrides": args.set},
        "rows": rows,
    }
    write_result(json_path, json_safe(result))
    (out / "bench_discrete.md").write_text(markdown(result))
    return result


if __name__ == "__main__":
    sys.exit(main())
