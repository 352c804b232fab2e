#!/usr/bin/env python
"""Benchmark: generate, fit and evaluate the bundled synthetic scenes; record the machine.

    python benchmarks/bench_scenes.py [--scenes demo texture balls] [--time-limit 600]
        [--iterations N] [--resolution 128] [--out benchmarks/out] [--compare OLD.json]
        [--threads-per-run N] [--address ADDR]

For each scene: `make_scene` into OUT/data/NAME (reused when its scene.json has the same
resolution). Then one `vq-mitsuba batch` (vq_mitsuba/batch.py) fits every scene from its scene.xml
into OUT/runs/NAME-s0 (old runs there are deleted first) with the preset of the scene's name if there is one, and
evaluates each on its test views. Each run reserves --threads-per-run CPU threads (default: every
core, so on one machine the fits run one after another, timed alone; fewer run several at once;
--address spreads them over a Ray cluster). Writes OUT/bench_scenes.json and OUT/bench_scenes.md and
prints the table; when an older JSON exists (OUT/bench_scenes.json, or --compare), prints new / old
ratios. All figures are single runs. See benchmarks/README.md.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import sys
from pathlib import Path

from provenance import command_line, describe, provenance, write_result
from vq_mitsuba.synthetic import mitsuba_scenes as synthetic
from vq_mitsuba.batch import run_batch
from vq_mitsuba.config import load_config, preset_path, presets
from vq_mitsuba.eval.evaluate import format_table, json_safe
from vq_mitsuba.messages import quiet
from vq_mitsuba.run.run_dir import RunDir

REPO = Path(__file__).resolve().parent.parent

# Headline figures: (key, label, number format). Ratios new/old are printed for these.
FIGURES = [
    ("fit_s", "fit s", ".1f"), ("iterations", "iters", "d"), ("it_per_s", "it/s", ".2f"),
    ("novel_psnr", "view PSNR", ".2f"), ("novel_ssim", "view SSIM", ".3f"),
    ("basecolor_psnr", "albedo PSNR", ".2f"), ("basecolor_ssim", "albedo SSIM", ".3f"),
    ("metallic_psnr", "metal PSNR", ".2f"), ("roughness_psnr", "rough PSNR", ".2f"),
    ("relit_albedo_scale_psnr", "relit PSNR (albedo scale)", ".2f"),
    ("relit_image_scale_psnr", "relit PSNR (image scale)", ".2f"),
    ("seg_micro_f1", "seg micro-F1", ".3f"), ("seg_macro_f1", "seg macro-F1", ".3f"),
    ("materials_found", "M found", "d"), ("materials_true", "M true", "d"),
]


def scene_config(name: str, overrides: list[str], preset: str | None = None):
    """A bundled scene's fit config: the named preset (if any), the preset of the scene's name when
    there is one, then the overrides. Returns (config, the preset file's path or None)."""
    path = preset_path(name) if name in presets() else None
    return load_config(path, overrides, preset=preset), path


def ensure_dataset(name: str, out: Path, resolution: int) -> Path:
    meta = out / "scene.json"
    if meta.is_file() and json.loads(meta.read_text()).get("resolution") == [resolution, resolution]:
        print(f"[{name}] reusing dataset {out}")
        return out
    print(f"[{name}] generating dataset {out} at {resolution}x{resolution}")
    return synthetic.make_scene(name, out, resolution=resolution)


def headline(m: dict, fit_summary: dict) -> dict:
    """The flat figures of one scene (the JSON keeps the full metrics too)."""
    rel = m["relighting"]
    fig = {
        "fit_s": fit_summary["seconds"], "iterations": fit_summary["iterations"],
        "it_per_s": fit_summary["iterations_per_s"],
        "novel_psnr": m["novel_view"]["psnr"], "novel_ssim": m["novel_view"]["ssim"],
        "basecolor_psnr": m["basecolor"]["psnr"], "basecolor_ssim": m["basecolor"]["ssim"],
        "metallic_psnr": m["metallic"]["psnr"], "roughness_psnr": m["roughness"]["psnr"],
    }
    seg = m.get("segmentation") or {}
    fig["seg_micro_f1"], fig["seg_macro_f1"] = seg.get("micro_f1"), seg.get("macro_f1")
    fig["materials_found"], fig["materials_true"] = seg.get("num_materials_found"), seg.get("num_materials_true")
    for variant in ("albedo_scale", "image_scale"):
        fig[f"relit_{variant}_psnr"] = rel[variant]["mean"]["psnr"] if rel[variant]["mean"] else None
        for env, v in rel[variant]["envs"].items():
            fig[f"relit_{env}_{variant}_psnr"] = v["psnr"]
    return fig


def run_scenes(args, out: Path) -> list[dict]:
    """Fit and evaluate every scene as one batch; each scene's record, in the order of --scenes."""
    data = {name: ensure_dataset(name, out / "data" / name, args.resolution) for name in args.scenes}
    common = [x for item in [f"train.time_limit_s={args.time_limit}", *args.set] for x in ("--set", item)]
    own, planned = {}, {}
    for name in args.scenes:
        cfg, preset = scene_config(name, [f"train.time_limit_s={args.time_limit}", *args.set])
        planned[name] = min(cfg.train.iterations, args.iterations or cfg.train.iterations)
        own[str(data[name] / "scene.xml")] = (["--config", str(preset)] if preset else []) + \
            ["--set", f"train.iterations={planned[name]}"]
    runs = out / "runs"
    if runs.exists():
        shutil.rmtree(runs)  # fresh fits, not the batch's resume
    threads = args.threads_per_run or len(os.sched_getaffinity(0))
    print(f"fitting {', '.join(args.scenes)} as one batch into {runs} ({threads} threads a run, time limit "
          f"{args.time_limit:g} s)")
    rows = run_batch(list(own), runs, fit_args=common, capture_args=own, threads=threads, evaluate=True,
                     eval_args=["--spp", str(args.spp)] if args.spp else [], address=args.address)
    failed = [f"{r['run']}: {r.get('message')}" for r in rows if r.get("status") != "done"]
    if failed:
        raise SystemExit("runs failed:\n" + "\n".join(failed))
    scenes = []
    for name in args.scenes:
        run = RunDir(runs / f"{name}-s0")
        m = json.loads((run / RunDir.METRICS).read_text())
        print(f"[{name}]\n{format_table(m)}")
        preset = scene_config(name, [])[1]
        scenes.append({
            "scene": name, "resolution": args.resolution, "dataset": str(data[name]), "run": str(run.dir),
            "config": str(preset.relative_to(REPO)) if preset else "defaults",
            "time_limit_s": args.time_limit, "iterations_planned": planned[name],
            "n_test_views": m["n_views"], "eval_spp": m["render"]["spp"], "eval_seconds": m["seconds"],
            "alignment": m["alignment"],
            "figures": headline(m, run.fit_summary()),
        })
    return scenes


def figure_text(x, spec: str = ".2f") -> str:
    if x is None or isinstance(x, str):
        return "-" if x is None else x
    if not math.isfinite(x):
        return str(x)
    return f"{int(x)}" if spec == "d" else f"{x:{spec}}"


def markdown(result: dict) -> str:
    scenes = result["scenes"]
    lines = [f"# bench_scenes ({result['date']})", "",
             "Single runs (no repeats): differences of a few tenths of a dB are within run-to-run noise.",
             f"Fit time limit {result['settings']['time_limit_s']:g} s, resolution {result['settings']['resolution']}, "
             f"iteration cap {result['settings']['iterations'] or 'none'}; images and albedo in sRGB, albedo "
             "aligned per channel (lstsq); metallic / roughness linear.", "",
             "| scene | " + " | ".join(label for _, label, _ in FIGURES) + " |",
             "|---|" + "---:|" * len(FIGURES)]
    for s in scenes:
        cells = [figure_text(s["figures"].get(k), spec) for k, _, spec in FIGURES]
        lines.append(f"| {s['scene']} | " + " | ".join(cells) + " |")
    lines += ["", "Relighting PSNR per envmap (albedo scale / image scale):", "",
              "| scene | env | albedo scale | image scale |", "|---|---|---:|---:|"]
    for s in scenes:
        f = s["figures"]
        envs = [k[len("relit_"):-len("_albedo_scale_psnr")] for k in f
                if k.endswith("_albedo_scale_psnr") and k != "relit_albedo_scale_psnr"]
        for env in envs:
            lines.append(f"| {s['scene']} | {env} | {figure_text(f[f'relit_{env}_albedo_scale_psnr'])} | "
                         f"{figure_text(f[f'relit_{env}_image_scale_psnr'])} |")
    lines += ["", "Machine: " + describe(result), "",
              f"Command: `{result['command']}`", ""]
    return "\n".join(lines)


def compare(new: dict, old: dict) -> str:
    """new / old ratios of the headline figures of the scenes both results hold."""
    old_by = {s["scene"]: s["figures"] for s in old.get("scenes", [])}
    rows = []
    for s in new["scenes"]:
        prev = old_by.get(s["scene"])
        if prev is None:
            continue
        cells = []
        for key, label, _ in FIGURES:
            a, b = s["figures"].get(key), prev.get(key)
            ok = isinstance(a, (int, float)) and isinstance(b, (int, float)) and b not in (0, 0.0) \
                and math.isfinite(a) and math.isfinite(b)
            cells.append(f"{label} {a / b:.3f}" if ok else f"{label} -")
        rows.append(f"{s['scene']}: " + ", ".join(cells))
    if not rows:
        return "no scene in common with the previous results"
    return f"new / old (old from {old.get('date', '?')}, {old.get('machine', {}).get('cpu', '?')}):\n" + "\n".join(rows)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scenes", nargs="+", default=list(synthetic.SCENES), choices=synthetic.SCENES,
                   help="scenes to run (default: all bundled)")
    p.add_argument("--time-limit", type=float, default=600.0, metavar="SECONDS",
                   help="fit time limit per scene (train.time_limit_s; default 600)")
    p.add_argument("--iterations", type=int, help="cap on fit iterations (default: the config's)")
    p.add_argument("--resolution", type=int, default=128, help="image size of the generated datasets (default 128)")
    p.add_argument("--spp", type=int, help="evaluation render spp (default: the run's render.spp)")
    p.add_argument("--out", default=str(REPO / "benchmarks" / "out"), help="output folder (default benchmarks/out)")
    p.add_argument("--compare", help="previous bench_scenes.json (default: OUT/bench_scenes.json if it exists)")
    p.add_argument("--quiet", action="store_true", help="no progress bars or notes")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="config override for every scene, e.g. --set vq.enabled=false (ablations; repeatable)")
    p.add_argument("--threads-per-run", type=int, help="CPU threads each fit reserves (default: every core)")
    p.add_argument("--address", help="run the fits on this Ray cluster (default: this machine)")
    args = p.parse_args(argv)

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    json_path = out / "bench_scenes.json"
    old_path = Path(args.compare) if args.compare else json_path
    old = json.loads(old_path.read_text()) if old_path.is_file() else None

    with quiet(args.quiet):
        scenes = run_scenes(args, out)
    result = {
        **provenance(command_line(argv, __file__)),
        "settings": {"scenes": args.scenes, "time_limit_s": args.time_limit, "iterations": args.iterations,
                     "overrides": args.set, "threads_per_run": args.threads_per_run,
                     "resolution": args.resolution, "eval_spp": args.spp},
        "note": "single runs: no repeats, no error bars",
        "scenes": scenes,
    }
    write_result(json_path, json_safe(result))
    md = markdown(result)
    (out / "bench_scenes.md").write_text(md)
    print()
    print(md)
    print(f"written: {json_path}, {out / 'bench_scenes.md'}")
    if old is not None:
        print(compare(result, old))
    return 0


if __name__ == "__main__":
    sys.exit(main())
