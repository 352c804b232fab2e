#!/usr/bin/env python
"""Benchmark of error against run time, on Cycles ground truth, with the per-texel baseline.

    python benchmarks/bench_time_error.py [--data benchmarks/out/cycles] [--scenes demo texture balls]
        [--methods vqnerf continuous texel] [--budgets 30,60,120,240,480] [--eval-spp 64]
        [--capture json|xml] [--fit-per-budget] [--out benchmarks/out/time_error] [--compare OLD.json]

Datasets: DATA/NAME, written by `vq-mitsuba make-scene NAME --renderer cycles -o DATA/NAME` (this
script renders a missing one that way, at --resolution). Each method fits the training views
once, with a time limit of the largest budget, and keeps its state at every budget (fit seconds,
excluding the copies); every kept state is then scored by `vq_mitsuba.eval.evaluate` on the test views:
novel view, basecolor (per-channel lstsq alignment), metallic, roughness, relighting under every
held-aside envmap (albedo scale and per-image scale). With --fit-per-budget each budget gets a
fit of its own with that time limit instead, so that the schedules (learning-rate decay, prior
and barrier, frequency annealing) run their course in the budget, as when a user sets
`train.time_limit_s`; its final state is scored. Methods:

- `vqnerf`: `vq-mitsuba fit` with its defaults (the preset of the scene's name when present): its final state
  also gives the segmentation and the MeanShift baseline on its continuous maps;
- `continuous`: the same with `--preset continuous` (the continuous branch alone);
- `texel`: per-texel principled textures on an xatlas UV map and an envmap, optimised with
  Mitsuba's own differentiable path tracer (`vq_mitsuba.eval.texel`).

Writes OUT/time_error.json, OUT/time_error.md and OUT/time_error.png (error against seconds), and
with --compare (or an older OUT/time_error.json) prints new / old ratios of matching points.
Single runs; the fit clocks of methods in one invocation are comparable (same machine, same
load), across invocations only roughly. Each method first gets an unscored warm-up fit of
--warmup seconds per scene (default 10), so that the one-off cost of its first fit in a process
(Dr.Jit compiling its kernels or loading them from the disk cache) does not fall on the first
budget only.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
from pathlib import Path

from bench_scenes import figure_text, scene_config
from provenance import command_line, describe, provenance, write_result
from vq_mitsuba.eval.evaluate import evaluate, evaluate_predictor, json_safe
from vq_mitsuba.engine.pipeline import fit
from vq_mitsuba.messages import quiet

REPO = Path(__file__).resolve().parent.parent

METHODS = {
    "vqnerf": "vq-mitsuba fit with its defaults (both branches, dropout ranking)",
    "continuous": "vq-mitsuba fit --preset continuous (the continuous branch alone)",
    "texel": "per-texel principled textures (xatlas UVs) + envmap, Mitsuba prb + mi.ad.Adam",
}

FIGURES = [
    ("seconds", "fit s", ".0f"), ("iterations", "iters", "d"),
    ("novel_psnr", "view PSNR", ".2f"), ("basecolor_psnr", "albedo PSNR", ".2f"),
    ("metallic_psnr", "metal PSNR", ".2f"), ("roughness_psnr", "rough PSNR", ".2f"),
    ("relit_psnr", "relit PSNR (albedo scale)", ".2f"), ("relit_image_psnr", "relit PSNR (image scale)", ".2f"),
    ("seg_micro_f1", "seg micro-F1", ".3f"), ("meanshift_best_f1", "MeanShift best micro-F1", ".3f"),
]


def ensure_cycles_dataset(name: str, data_dir: Path, resolution: int) -> Path:
    if (data_dir / "scene.json").is_file():
        meta = json.loads((data_dir / "scene.json").read_text())
        if meta.get("renderer") != "cycles":
            print(f"[{name}] note: {data_dir} was rendered by {meta.get('renderer', 'mitsuba')}, not Cycles")
        size = meta.get("resolution")
        if size is not None and list(size) != [resolution, resolution]:
            raise SystemExit(f"{data_dir / 'scene.json'}: the dataset is {size[0]} x {size[1]} px, not the "
                             f"--resolution {resolution} asked for; pass --resolution {size[0]}, or another --data "
                             f"folder to render it at {resolution} px")
        return data_dir
    print(f"[{name}] rendering the Cycles ground truth into {data_dir} ({resolution} px)")
    subprocess.run([sys.executable, "-m", "vq_mitsuba.cli", "make-scene", name, "--renderer", "cycles",
                    "--resolution", str(resolution), "-o", str(data_dir)], check=True)
    return data_dir


def figures(m: dict, seconds: float, iterations: int) -> dict:
    rel = m["relighting"]
    fig = {"seconds": seconds, "iterations": iterations,
           "novel_psnr": m["novel_view"]["psnr"], "basecolor_psnr": m["basecolor"]["psnr"],
           "metallic_psnr": m["metallic"]["psnr"], "roughness_psnr": m["roughness"]["psnr"],
           "relit_psnr": rel["albedo_scale"]["mean"]["psnr"] if rel["albedo_scale"]["mean"] else None,
           "relit_image_psnr": rel["image_scale"]["mean"]["psnr"] if rel["image_scale"]["mean"] else None}
    seg = m.get("segmentation") or {}
    fig["seg_micro_f1"], fig["seg_macro_f1"] = seg.get("micro_f1"), seg.get("macro_f1")
    fig["materials_found"], fig["materials_true"] = seg.get("num_materials_found"), seg.get("num_materials_true")
    ms = {k: v for k, v in (m.get("meanshift") or {}).items() if isinstance(v, dict)}
    if ms:
        best = max(ms, key=lambda k: ms[k]["micro_f1"])
        fig["meanshift_best_f1"], fig["meanshift_best_bandwidth"] = ms[best]["micro_f1"], float(best)
    return fig


def fresh_run(name: str, data: Path, label: str, args, out: Path) -> tuple[Path, Path]:
    """The capture file to fit (--capture) and the run folder OUT/runs/NAME/LABEL, emptied."""
    run_dir = out / "runs" / name / label
    if run_dir.exists():
        shutil.rmtree(run_dir)
    return data / ("transforms_train.json" if args.capture == "json" else "scene.xml"), run_dir


def ours_config(name: str, method: str, args, overrides: list[str], last: list[str] = ()):
    """The config of one of our methods: the preset of the method (`continuous`, or the defaults),
    the preset of the scene's name, `overrides`, the user's --set, then `last`."""
    cfg, _ = scene_config(name, overrides + list(args.set) + list(last),
                          preset="continuous" if method == "continuous" else None)
    return cfg


def run_ours(name: str, data: Path, method: str, budgets: list[float], args, out: Path, tag: str = "") -> list[dict]:
    import torch

    overrides = [f"train.time_limit_s={max(budgets)}"]
    if len(budgets) > 1:
        overrides.append("train.snapshot_s=" + ",".join(f"{b:g}" for b in budgets))
    cfg = ours_config(name, method, args, overrides)
    capture, run_dir = fresh_run(name, data, method + tag, args, out)
    print(f"[{name}/{method}] fitting {capture} -> {run_dir} ({cfg.train.iterations} iterations planned, "
          f"time limit {max(budgets):g} s)")
    summary = fit(capture, run_dir, cfg)
    states = []
    for snap in sorted((run_dir / "snapshots").glob("*.pt")):
        st = torch.load(snap, map_location="cpu", weights_only=False)
        states.append((float(st["elapsed_s"]), int(st["step"]), snap))
    final_s = float(summary["seconds"])
    if states and states[-1][1] == int(summary["iterations"]):
        # The fit ended at the last budget: score its final checkpoint instead of that snapshot, since
        # only the checkpoint has the end-of-fit steps (the discrete branch's ranking and its M).
        states.pop()
    if not states or final_s > states[-1][0] + 1.0:  # the end of the fit, when it is not a snapshot already
        states.append((final_s, int(summary["iterations"]), None))
    rows = []
    for i, (sec, step, snap) in enumerate(states):
        last = i == len(states) - 1
        print(f"[{name}/{method}] scoring the state at {sec:.0f} s ({step} iterations)")
        m = evaluate(run_dir, data, spp=args.eval_spp, checkpoint=snap,
                     meanshift_bandwidths=(0.2, 0.3, 0.5) if last and method == "vqnerf" else (),
                     output=run_dir / f"metrics_{sec:07.1f}s.json")
        rows.append({"scene": name, "method": method, "final": last, **figures(m, sec, step)})
    return rows


def warm_up(name: str, data: Path, method: str, args, out: Path) -> None:
    """An unscored fit of `args.warmup` seconds, so that the timed fits after it do not pay the
    one-off costs of a method's first fit in a process (Dr.Jit kernel compilation or loading from
    its disk cache, first-touch allocations); without it the first budget of each method is
    charged for them."""
    capture, run_dir = fresh_run(name, data, method + "_warmup", args, out)
    print(f"[{name}/{method}] warm-up fit of {args.warmup:g} s (not scored)")
    if method == "texel":
        from vq_mitsuba.eval.texel import fit_texel

        with quiet():
            fit_texel(capture, run_dir, texel_config(args), time_limit_s=args.warmup)
    else:
        # Every kernel of the timed fits is built here: the bounce from the first step on.
        cfg = ours_config(name, method, args, [f"train.time_limit_s={args.warmup}"], ["train.bounce_after=0"])
        with quiet():
            fit(capture, run_dir, cfg)
    shutil.rmtree(run_dir)


def texel_config(args):
    """The baseline's TexelConfig with the user's --texel-set overrides (values parsed as YAML)."""
    import dataclasses

    import yaml

    from vq_mitsuba.eval.texel import TexelConfig

    fields = {f.name for f in dataclasses.fields(TexelConfig)}
    changes = {}
    for item in args.texel_set:
        key, sep, value = item.partition("=")
        if not sep or key not in fields:
            raise SystemExit(f"--texel-set {item!r}: expected KEY=VALUE with KEY one of {', '.join(sorted(fields))}")
        changes[key] = yaml.safe_load(value)
    return TexelConfig(**changes)


def run_texel(name: str, data: Path, budgets: list[float], args, out: Path, tag: str = "") -> list[dict]:
    from vq_mitsuba.eval.texel import TexelPredictor, fit_texel

    capture, run_dir = fresh_run(name, data, "texel" + tag, args, out)
    print(f"[{name}/texel] fitting {capture} -> {run_dir} (time limit {max(budgets):g} s)")
    result = fit_texel(capture, run_dir, texel_config(args), time_limit_s=max(budgets), snapshot_s=budgets)
    rows = []
    snaps = result["snapshots"]
    for i, (sec, its, path) in enumerate(snaps):
        print(f"[{name}/texel] scoring the state at {sec:.0f} s ({its} iterations)")
        m = evaluate_predictor(TexelPredictor(path), data, spp=args.eval_spp,
                               meanshift_bandwidths=(), run_label=str(path),
                               output=run_dir / f"metrics_{sec:07.1f}s.json")
        rows.append({"scene": name, "method": "texel", "final": i == len(snaps) - 1, **figures(m, sec, its)})
    return rows


def markdown(result: dict) -> str:
    lines = [f"# Error against fit time on Cycles ground truth ({result['date']})", "",
             f"Command: `{result['command']}`", "",
             f"Machine: {describe(result)}", "",
             f"Evaluation: {result['eval_spp']} spp, basecolor aligned per channel (lstsq), metallic and roughness "
             "unaligned, relighting mean over the held-aside envmaps. "
             f"Warm-up fit before the timed ones: {result.get('warmup_s', 0):g} s per scene and method. Methods: "
             + "; ".join(f"`{k}`: {v}" for k, v in METHODS.items() if k in result["methods"]), "",
             "| scene | method | " + " | ".join(label for _, label, _ in FIGURES) + " |",
             "|---|---|" + "---:|" * len(FIGURES)]
    for r in result["rows"]:
        lines.append(f"| {r['scene']} | {r['method']} | " + " | ".join(figure_text(r.get(k), f) for k, _, f in FIGURES) + " |")
    lines += ["", "At equal fit time (the states kept at the same budget):", "",
              "| scene | budget s | " + " | ".join(f"{m} albedo / relit" for m in result["methods"]) + " |",
              "|---|---:|" + "---:|" * len(result["methods"])]
    for scene in result["scenes"]:
        for b in result["budgets"]:
            cells = []
            for meth in result["methods"]:
                r = _at_budget(result["rows"], scene, meth, b)
                cells.append(f"{figure_text(r.get('basecolor_psnr'))} / {figure_text(r.get('relit_psnr'))}" if r else "-")
            lines.append(f"| {scene} | {b:g} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def _at_budget(rows: list[dict], scene: str, method: str, budget: float) -> dict | None:
    """The state kept at `budget` seconds (the first at or after it; a fit that ended earlier gives its end),
    or with --fit-per-budget the end of that budget's own fit."""
    cands = sorted((r for r in rows if r["scene"] == scene and r["method"] == method), key=lambda r: r["seconds"])
    own = [r for r in cands if r.get("budget") is not None]
    if own:
        return next((r for r in own if abs(r["budget"] - budget) < 1e-6), None)
    for r in cands:
        if r["seconds"] >= budget - 1e-6:
            return r
    return cands[-1] if cands and cands[-1]["final"] and cands[-1]["seconds"] < budget else None


def plot(result: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    keys = [("basecolor_psnr", "basecolor PSNR (dB)"), ("relit_psnr", "relighting PSNR (dB)"),
            ("novel_psnr", "novel-view PSNR (dB)")]
    scenes = result["scenes"]
    fig, axes = plt.subplots(len(scenes), len(keys), figsize=(4.2 * len(keys), 3.2 * len(scenes)), squeeze=False)
    for i, scene in enumerate(scenes):
        for j, (key, label) in enumerate(keys):
            ax = axes[i][j]
            for meth in result["methods"]:
                pts = sorted((r["seconds"], r[key]) for r in result["rows"]
                             if r["scene"] == scene and r["method"] == meth and r.get(key) is not None)
                if pts:
                    ax.plot([p[0] for p in pts], [p[1] for p in pts], "o-", label=meth)
            ax.set_xscale("log")
            ax.set_xlabel("fit seconds")
            ax.set_ylabel(label)
            ax.set_title(scene)
            ax.grid(True, alpha=0.3)
            if i == 0 and j == 0:
                ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def compare(new: dict, old: dict) -> str:
    # Results before benchmarks/provenance.py keep the commit inside "machine".
    lines = [f"new / old (old: commit {old.get('commit') or old.get('machine', {}).get('commit')}, {old.get('date')})"]
    for r in new["rows"]:
        for b in old.get("budgets", []):
            o = _at_budget(old["rows"], r["scene"], r["method"], b)
            if o is None or abs(o["seconds"] - r["seconds"]) > 0.2 * b or _at_budget(new["rows"], r["scene"], r["method"], b) is not r:
                continue
            parts = []
            for k in ("basecolor_psnr", "relit_psnr", "novel_psnr"):
                if isinstance(r.get(k), (int, float)) and isinstance(o.get(k), (int, float)) and o[k]:
                    parts.append(f"{k} {r[k] / o[k]:.3f}")
            lines.append(f"  {r['scene']}/{r['method']} @ {b:g} s: " + ", ".join(parts))
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    ap.add_argument("--data", type=Path, default=REPO / "benchmarks" / "out" / "cycles",
                    help="folder of Cycles datasets DATA/NAME (rendered when missing)")
    ap.add_argument("--scenes", nargs="+", default=["demo", "texture", "balls"])
    ap.add_argument("--methods", nargs="+", default=["vqnerf", "continuous", "texel"], choices=list(METHODS))
    ap.add_argument("--budgets", default="30,60,120,240,480", help="fit seconds at which states are scored")
    ap.add_argument("--eval-spp", type=int, default=64, help="samples per pixel of the scoring renders")
    ap.add_argument("--resolution", type=int, default=64, help="image size of the datasets (rendered here when missing; an existing one of another size is an error)")
    ap.add_argument("--capture", choices=("json", "xml"), default="json",
                    help="fit the NeRF-synthetic transforms_train.json (Blender world) or the scene.xml")
    ap.add_argument("--fit-per-budget", action="store_true",
                    help="one fit per budget with that time limit (schedules complete in the budget), "
                         "instead of states kept along one fit of the largest budget")
    ap.add_argument("--warmup", type=float, default=10.0,
                    help="seconds of an unscored fit per scene and method before the timed ones, so that "
                         "one-off costs (kernel compilation) do not fall on the first budget (0: none)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="config override for the vqnerf and continuous methods (repeatable)")
    ap.add_argument("--texel-set", action="append", default=[], metavar="KEY=VALUE",
                    help="TexelConfig override for the per-texel baseline, e.g. lr_end_exponential=1.0 (repeatable)")
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks" / "out" / "time_error")
    ap.add_argument("--compare", type=Path, help="an earlier time_error.json (default: the one in OUT)")
    ap.add_argument("--append", action="store_true",
                    help="keep the rows of OUT/time_error.json for other scenes and methods (re-run or extend a part)")
    ap.add_argument("--quiet", action="store_true", help="no progress bars or notes")
    args = ap.parse_args(argv)
    budgets = sorted(float(b) for b in args.budgets.split(",") if b.strip())
    args.out.mkdir(parents=True, exist_ok=True)
    json_path = args.out / "time_error.json"
    old_path = args.compare or (json_path if json_path.is_file() else None)
    old = json.loads(old_path.read_text()) if old_path and old_path.is_file() else None

    from vq_mitsuba.backend import init_mitsuba

    init_mitsuba()  # the variant is part of the provenance record
    result = {**provenance(command_line(argv, __file__)),
              "scenes": args.scenes, "methods": args.methods, "budgets": budgets,
              "eval_spp": args.eval_spp, "capture": args.capture, "fit_per_budget": args.fit_per_budget,
              "warmup_s": args.warmup, "rows": []}
    if args.append and old is not None:
        if old.get("budgets") != budgets or old.get("eval_spp") != args.eval_spp \
                or bool(old.get("fit_per_budget")) != args.fit_per_budget:
            raise SystemExit(f"--append: {old_path} has other budgets, eval spp or --fit-per-budget")
        rerun = {(s_, m_) for s_ in args.scenes for m_ in args.methods}
        result["rows"] = [r for r in old["rows"] if (r["scene"], r["method"]) not in rerun]
        result["scenes"] = list(dict.fromkeys(old["scenes"] + args.scenes))
        result["methods"] = list(dict.fromkeys(old["methods"] + args.methods))
        result["command"] += f" (appended to the results of `{old['command']}`)"
    with quiet(args.quiet):
        for name in args.scenes:
            data = ensure_cycles_dataset(name, args.data / name, args.resolution)
            for method in args.methods:
                if args.warmup > 0:
                    warm_up(name, data, method, args, args.out)
                runner = (lambda bs, tag: run_texel(name, data, bs, args, args.out, tag)) if method == "texel" else \
                    (lambda bs, tag: run_ours(name, data, method, bs, args, args.out, tag))
                if args.fit_per_budget:
                    rows = []
                    for b in budgets:
                        rows += [{**r, "budget": b} for r in runner([b], f"_{b:g}s")]
                else:
                    rows = runner(budgets, "")
                result["rows"] += rows
                # Written after every method: an interrupted benchmark keeps what it measured.
                write_result(json_path, json_safe(result))
                (args.out / "time_error.md").write_text(markdown(result))
                plot(result, args.out / "time_error.png")
    print(markdown(result))
    print(f"wrote {json_path}, {args.out / 'time_error.md'}, {args.out / 'time_error.png'}")
    if old is not None:
        print(compare(result, old))
    return 0


if __name__ == "__main__":
    sys.exit(main())
