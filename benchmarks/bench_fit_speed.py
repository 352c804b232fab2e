#!/usr/bin/env python
"""Wall time of `vq-mitsuba fit` against its accuracy, as a user runs it, start-up included.

    python benchmarks/bench_fit_speed.py DATA --variant NAME[:KEY=VALUE,...] ... [--eval-spp 64]
        [--out benchmarks/out/fit_speed] [--seed 0] [--warmup]
    python benchmarks/bench_fit_speed.py --plot A/fit_speed.json B/fit_speed.json --out DIR

DATA is a dataset written by `vq-mitsuba make-scene NAME --renderer cycles` (e.g. `balls
--resolution 200 --n-train 100 --n-test 20`). Each variant runs `vq-mitsuba fit
DATA/transforms_train.json --mesh DATA/mesh.ply` in its own process with its `--set` overrides
(a variant named `defaults` with none), one after the other, and is timed from the command's
start to its exit. The fit's own `fit.json` splits that into the training loop and the rest
(start-up: reading the images and tracing the training pixels; the end: ranking and writing).
Each run is then scored by `vq_mitsuba.eval.evaluate` on the test views (novel view per
material, basecolor, roughness, relighting, segmentation, M). `--warmup` first runs a 30-step
fit so that the first variant does not pay Dr.Jit's one-off kernel compilation.

Writes OUT/fit_speed.json (rows of earlier variants of other names are kept) and OUT/fit_speed.png
(novel view, basecolor and relighting PSNR against wall time) and prints one row per variant;
`--plot A.json B.json` only draws and prints the rows of several such files together.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

from bench_scenes import figure_text
from bench_time_error import figures
from provenance import command_line, write_result
from vq_mitsuba.eval.evaluate import evaluate, json_safe
from vq_mitsuba.messages import quiet

REPO = Path(__file__).resolve().parent.parent

COLUMNS = [("wall_s", "wall s", ".0f"), ("startup_s", "start-up s", ".1f"), ("loop_s", "loop s", ".0f"),
           ("iterations", "iters", "d"), ("novel_psnr", "view", ".2f"), ("basecolor_psnr", "basecolor", ".2f"),
           ("roughness_psnr", "rough", ".2f"), ("metallic_psnr", "metal", ".2f"), ("relit_psnr", "relit", ".2f"),
           ("seg_micro_f1", "F1", ".3f"), ("materials_found", "M", "d")]


def parse_variant(text: str) -> tuple[str, list[str]]:
    name, _, rest = text.partition(":")
    return name, [kv for kv in rest.split(",") if kv]


def run_variant(data: Path, name: str, overrides: list[str], args, out: Path) -> dict:
    run_dir = out / "runs" / name
    if run_dir.exists():
        shutil.rmtree(run_dir)
    cmd = [sys.executable, "-m", "vq_mitsuba.cli", "fit", str(data / "transforms_train.json"),
           "--mesh", str(data / "mesh.ply"), "-o", str(run_dir), "--quiet",
           "--set", f"train.seed={args.seed}"]
    for kv in overrides:
        cmd += ["--set", kv]
    print(f"[{name}] {' '.join(cmd[2:])}", flush=True)
    t0 = time.perf_counter()
    env = {**os.environ, "PYTHONPATH": str(REPO)}  # a checkout of another revision times its own code
    subprocess.run(cmd, check=True, cwd=REPO, env=env)
    wall = time.perf_counter() - t0
    summary = json.loads((run_dir / "fit.json").read_text())
    with quiet():
        m = evaluate(run_dir, data, spp=args.eval_spp, output=run_dir / "metrics.json")
    row = {"variant": name, "overrides": overrides, "wall_s": wall, "loop_s": summary["seconds"],
           "startup_s": summary.get("startup_s"), **figures(m, summary["seconds"], summary["iterations"])}
    row["per_material"] = m.get("per_material")
    print(f"[{name}] " + "  ".join(f"{label} {figure_text(row.get(key), spec)}" for key, label, spec in COLUMNS), flush=True)
    return row


def plot(rows: list[dict], path: Path) -> None:
    """Novel view, basecolor and relighting PSNR against the fit's wall time, one point per run."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    keys = [("novel_psnr", "novel view PSNR (dB)"), ("basecolor_psnr", "basecolor PSNR (dB)"),
            ("relit_psnr", "relighting PSNR (dB)")]
    fig, axes = plt.subplots(1, len(keys), figsize=(5 * len(keys), 4))
    for ax, (key, label) in zip(axes, keys):
        for r in rows:
            if r.get(key) is None:
                continue
            ax.scatter(r["wall_s"], r[key], s=18)
            ax.annotate(r["variant"], (r["wall_s"], r[key]), fontsize=7, xytext=(3, 3), textcoords="offset points")
        ax.set_xlabel("fit wall time, start-up included (s)")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("data", type=Path, nargs="?", help="dataset folder (transforms_train.json, mesh.ply, test views)")
    ap.add_argument("--variant", action="append", default=[],
                    help="NAME or NAME:KEY=VALUE,KEY=VALUE (config overrides); repeatable; default: defaults")
    ap.add_argument("--eval-spp", type=int, default=64, help="samples per pixel of the scored renders")
    ap.add_argument("--seed", type=int, default=0, help="train.seed of every variant")
    ap.add_argument("--warmup", action="store_true", help="a 30-step fit first, not timed")
    ap.add_argument("--plot", type=Path, nargs="+", metavar="JSON",
                    help="no fit: draw OUT/fit_speed.png from the rows of these fit_speed.json files")
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks" / "out" / "fit_speed", help="output folder")
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    if args.plot:
        rows = [r for p in args.plot for r in json.loads(p.read_text())["rows"]]
        plot(rows, args.out / "fit_speed.png")
        for r in rows:
            print(f"[{r['variant']}] " + "  ".join(f"{label} {figure_text(r.get(key), spec)}" for key, label, spec in COLUMNS))
        print(f"wrote {args.out / 'fit_speed.png'}")
        return 0
    if args.data is None:
        ap.error("DATA is needed to fit (only --plot does without)")
    variants = [parse_variant(v) for v in (args.variant or ["defaults"])]
    if args.warmup:
        warm = args.out / "runs" / "_warmup"
        shutil.rmtree(warm, ignore_errors=True)
        subprocess.run([sys.executable, "-m", "vq_mitsuba.cli", "fit", str(args.data / "transforms_train.json"),
                        "--mesh", str(args.data / "mesh.ply"), "-o", str(warm), "--quiet",
                        "--set", "train.iterations=30", "--set", "train.bounce_after=0",
                        "--set", "vq.warmup_frac=0.5"], check=True, cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO)})
        shutil.rmtree(warm)
    rows = [run_variant(args.data, name, ov, args, args.out) for name, ov in variants]
    result = {"command": command_line(argv, __file__), "data": str(args.data), "eval_spp": args.eval_spp,
              "rows": rows}
    path = args.out / "fit_speed.json"
    old = json.loads(path.read_text())["rows"] if path.is_file() else []
    keep = [r for r in old if r["variant"] not in {r2["variant"] for r2 in rows}]
    result["rows"] = keep + rows
    write_result(path, json_safe(result), indent=1)
    plot(result["rows"], args.out / "fit_speed.png")
    print(f"wrote {path} and {args.out / 'fit_speed.png'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
