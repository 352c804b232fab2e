#!/usr/bin/env python
"""What each of the fit's scene rules buys: the old defaults, each rule alone, all together.

    python benchmarks/skip_study.py [--scenes demo texture balls tabletop] [--seeds 0 1]
        [--variants old bounce envmap stop sampling all] [--data benchmarks/out/cycles200]
        [--resolution 200] [--n-train 100] [--n-test 20] [--iterations N] [--eval-spp 64]
        [--warmup] [--out benchmarks/out/skip_study]
    python benchmarks/skip_study.py --plot OUT/skip_study.json [OUT2/skip_study.json ...] [--out DIR]

The rules (`vq_mitsuba/engine/skips.py`), each with one config key (auto or forced):
`train.bounce` (the bounce off where secondary rays (almost) never meet the object),
`envmap.final_height` (the learned envmap stops at the rung the fitted roughness resolves),
`train.stop` (the schedule speeds up on plateaus of held-aside pixels and ends when done) and
`train.sampling` (rays drawn by their running error). Variants:

- `old`: every rule forced off (train.bounce=on, envmap.final_height=full, train.stop=iterations,
  train.sampling=uniform): the fit before the rules;
- `bounce`, `envmap`, `stop`, `sampling`: `old` with that one rule automatic;
- `all`: every rule automatic;
- `default`: the shipped configuration, no key forced.

Datasets: DATA/NAME, `vq-mitsuba make-scene NAME --renderer cycles` at --resolution with
--n-train / --n-test views (rendered here when missing; Cycles needs `make cycles`). Each fit is
`vq-mitsuba fit DATA/NAME/transforms_train.json --mesh DATA/NAME/mesh.ply` (with
the preset of the scene's name when there is one, as `make demo` and `bench_time_error.py` fit), one process per
fit, timed from the command's start to its exit (start-up and the end's ranking and residual
included), run through `vq-mitsuba batch` (one batch of the scenes per variant and seed, each fit
on every core, so one after another on one machine; `--address` for a Ray cluster), then scored by
`vq_mitsuba.eval.evaluate` on the test views: novel view, basecolor, relighting (albedo scale,
mean over the held-aside probes), segmentation micro-F1 and M.
`--warmup` first runs one short unscored fit so that the first timed fit does not pay Dr.Jit's
kernel compilation alone.

Writes OUT/skip_study.json (a row per scene, variant and seed with the fit's `decisions` from
fit.json and its training curve), OUT/skip_study.md (means over the seeds, with each variant's
speed-up and score changes against `old`), OUT/skip_study.png (basecolor, relighting and novel
view PSNR against wall time, a point per fit, variant means joined to `old`) and
OUT/skip_study_curves.png (the training-batch PSNR against fit seconds, from each run's
loss curve). Single processes one after the other: run it on an otherwise idle machine.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

from bench_scenes import figure_text
from bench_time_error import figures
from provenance import command_line, describe, provenance, write_result
from vq_mitsuba.config import presets

REPO = Path(__file__).resolve().parent.parent
SCENES = ["demo", "texture", "balls", "tabletop"]

RULES = {  # variant -> (key, automatic value, forced-off value)
    "bounce": ("train.bounce", "auto", "on"),
    "envmap": ("envmap.final_height", "auto", "full"),
    "stop": ("train.stop", "auto", "iterations"),
    "sampling": ("train.sampling", "auto", "uniform"),
}
VARIANTS = ["old", *RULES, "all", "default"]

COLUMNS = [("wall_s", "wall s", ".0f"), ("startup_s", "start-up s", ".1f"), ("iterations", "iters", ".0f"),
           ("novel_psnr", "view", ".2f"), ("basecolor_psnr", "basecolor", ".2f"), ("relit_psnr", "relit", ".2f"),
           ("seg_micro_f1", "F1", ".3f"), ("materials_found", "M", ".1f")]
SCORES = ["novel_psnr", "basecolor_psnr", "relit_psnr", "seg_micro_f1", "materials_found"]


def variant_overrides(variant: str) -> list[str]:
    """The --set items of a variant: each rule automatic when the variant names it (or is `all`),
    forced off otherwise; none for `default` (the shipped configuration)."""
    if variant not in VARIANTS:
        raise SystemExit(f"unknown variant {variant!r} (known: {', '.join(VARIANTS)})")
    if variant == "default":
        return []
    return [f"{key}={auto if variant in (name, 'all') else off}" for name, (key, auto, off) in RULES.items()]


def ensure_cycles_dataset(name: str, data_dir: Path, args) -> Path:
    """DATA/NAME rendered by Cycles at the asked size (rendered here when missing)."""
    if (data_dir / "scene.json").is_file():
        meta = json.loads((data_dir / "scene.json").read_text())
        if meta.get("renderer") != "cycles":
            print(f"[{name}] note: {data_dir} was rendered by {meta.get('renderer', 'mitsuba')}, not Cycles")
        size = meta.get("resolution")
        if size is not None and list(size) != [args.resolution, args.resolution]:
            raise SystemExit(f"{data_dir / 'scene.json'}: {size[0]} x {size[1]} px, not --resolution "
                             f"{args.resolution}; pass --resolution {size[0]} or another --data")
        return data_dir
    print(f"[{name}] rendering the Cycles ground truth into {data_dir}", flush=True)
    subprocess.run([sys.executable, "-m", "vq_mitsuba.cli", "make-scene", name, "--renderer", "cycles",
                    "--resolution", str(args.resolution), "--n-train", str(args.n_train),
                    "--n-test", str(args.n_test), "-o", str(data_dir)], check=True, cwd=REPO)
    return data_dir


def fit_command(name: str, data: Path, run_dir: Path, overrides: list[str]) -> list[str]:
    cmd = [sys.executable, "-m", "vq_mitsuba.cli", "fit", str(data / "transforms_train.json"),
           "--mesh", str(data / "mesh.ply"), "-o", str(run_dir), "--quiet"]
    if name in presets():
        cmd += ["--preset", name]
    for kv in overrides:
        cmd += ["--set", kv]
    return cmd


def run_fit(cmd: list[str]) -> None:
    """Run a `fit_command` with this checkout's code."""
    subprocess.run(cmd, check=True, cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO)})


def warmup_fit(name: str, data: Path, out: Path, overrides: list[str]) -> None:
    """One short unscored fit, so that the first timed fit does not pay Dr.Jit's kernel compilation alone."""
    warm = out / "runs" / "_warmup"
    shutil.rmtree(warm, ignore_errors=True)
    run_fit(fit_command(name, data, warm, overrides))
    shutil.rmtree(warm)


def add_dataset_arguments(ap: argparse.ArgumentParser, scenes: list[str], seeds: list[int], n_test: int) -> None:
    """The options naming the scenes, seeds and Cycles datasets of a study, and how they are scored."""
    ap.add_argument("--scenes", nargs="+", default=scenes, help="bundled Cycles scenes to fit")
    ap.add_argument("--seeds", nargs="+", type=int, default=seeds, help="train.seed of each fit")
    ap.add_argument("--data", type=Path, default=REPO / "benchmarks" / "out" / "cycles200",
                    help="folder of the Cycles datasets (DATA/NAME)")
    ap.add_argument("--resolution", type=int, default=200, help="image side of the rendered scenes, px")
    ap.add_argument("--n-train", type=int, default=100, help="training views per scene")
    ap.add_argument("--n-test", type=int, default=n_test, help="test views per scene")
    ap.add_argument("--eval-spp", type=int, default=64, help="samples per pixel of the scored renders")
    ap.add_argument("--warmup", action="store_true", help="a short unscored fit first")


def training_curve(run_dir: Path) -> list[list[float]]:
    """[seconds, training-batch PSNR] of the run's loss curve (its checkpoint's history)."""
    import torch

    state = torch.load(run_dir / "checkpoint.pt", map_location="cpu", weights_only=False)
    return [[h["seconds"], h["psnr"]] for h in state.get("history", [])]


def fit_batch(datasets: dict[str, Path], variant: str, seed: int, args) -> dict[str, dict]:
    """Fit every scene under `variant` and `seed` as one `vq-mitsuba batch` (vq_mitsuba/batch.py), each
    run on every core so that on one machine they run, and are timed, one at a time; returns
    {scene: (run folder, the fit's wall seconds, its overrides)}."""
    from vq_mitsuba.batch import run_batch
    from vq_mitsuba.messages import quiet

    out = args.out / "runs" / variant / f"s{seed}"
    if out.exists():
        shutil.rmtree(out)
    overrides = variant_overrides(variant) + ([f"train.iterations={args.iterations}"] if args.iterations else [])
    own = {str(data / "transforms_train.json"): ["--mesh", str(data / "mesh.ply")] + (
        ["--preset", name] if name in presets() else [])
        for name, data in datasets.items()}
    print(f"[{variant}/s{seed}] batch of {', '.join(datasets)}: {' '.join(overrides) or 'no key forced'}", flush=True)
    with quiet():
        rows = run_batch(list(own), out, seeds=[seed], fit_args=[x for kv in overrides for x in ("--set", kv)],
                         capture_args=own, threads=len(os.sched_getaffinity(0)), address=args.address)
    failed = [f"{r['run']}: {r.get('message')}" for r in rows if r.get("status") != "done"]
    if failed:
        raise SystemExit("fits failed:\n" + "\n".join(failed))
    walls = {r["run"]: r["wall_s"] for r in rows}
    return {name: {"run_dir": out / f"{name}-s{seed}", "wall_s": walls[f"{name}-s{seed}"],
                   "overrides": overrides + [f"train.seed={seed}"]} for name in datasets}


def score_one(name: str, data: Path, variant: str, seed: int, fitted: dict, args) -> dict:
    """The row of one fitted scene: its wall time, figures on the test views and decisions."""
    from vq_mitsuba.eval.evaluate import evaluate
    from vq_mitsuba.messages import quiet

    run_dir = fitted["run_dir"]
    summary = json.loads((run_dir / "fit.json").read_text())
    with quiet():
        m = evaluate(run_dir, data, spp=args.eval_spp, meanshift_bandwidths=(), output=run_dir / "metrics.json")
    decisions = summary.get("decisions", {})
    row = {"scene": name, "variant": variant, "seed": seed, "overrides": fitted["overrides"],
           "wall_s": fitted["wall_s"], "startup_s": summary.get("startup_s"), "loop_s": summary["seconds"],
           **figures(m, summary["seconds"], summary["iterations"]),
           "decisions": {k: {"choice": v.get("choice"), "reason": v.get("reason")} for k, v in decisions.items()},
           "curve": training_curve(run_dir)}
    print(f"[{name}/{variant}/s{seed}] " + "  ".join(f"{label} {figure_text(row.get(key), spec)}"
                                                    for key, label, spec in COLUMNS), flush=True)
    for rule, d in row["decisions"].items():
        print(f"    {rule}: {d['choice']}: {d['reason']}", flush=True)
    return row


def means(rows: list[dict]) -> dict[tuple[str, str], dict]:
    """(scene, variant) -> the mean of each column over the seeds (None where a seed has none)."""
    out: dict[tuple[str, str], dict] = {}
    for scene in dict.fromkeys(r["scene"] for r in rows):
        for variant in dict.fromkeys(r["variant"] for r in rows if r["scene"] == scene):
            group = [r for r in rows if r["scene"] == scene and r["variant"] == variant]
            mean = {"seeds": len(group)}
            for key, _, _ in COLUMNS:
                vals = [r.get(key) for r in group]
                mean[key] = sum(vals) / len(vals) if vals and all(v is not None for v in vals) else None
            out[scene, variant] = mean
    return out


def markdown(rows: list[dict]) -> str:
    table = means(rows)
    lines = ["| scene | variant | seeds | " + " | ".join(label for _, label, _ in COLUMNS)
             + " | speed-up | basecolor | relit | view | F1 |",
             "|---|---|---:|" + "---:|" * len(COLUMNS) + "---:|---:|---:|---:|---:|"]
    for (scene, variant), m in table.items():
        old = table.get((scene, "old"))
        cells = [figure_text(m[key], spec) for key, _, spec in COLUMNS]
        if old and variant != "old" and old["wall_s"] and m["wall_s"]:
            delta = [f"{old['wall_s'] / m['wall_s']:.2f}x"] + [
                "" if m[k] is None or old[k] is None else f"{m[k] - old[k]:+.2f}" if k != "seg_micro_f1"
                else f"{m[k] - old[k]:+.3f}" for k in ("basecolor_psnr", "relit_psnr", "novel_psnr", "seg_micro_f1")]
        else:
            delta = [""] * 5
        lines.append(f"| {scene} | {variant} | {m['seeds']} | " + " | ".join(cells + delta) + " |")
    lines += ["", "Means over the seeds; PSNR in dB; the last five columns against `old` (its wall time over "
                  "the variant's; score differences). Decisions of each fit (fit.json):", ""]
    for r in rows:
        d = r.get("decisions", {})
        lines.append(f"- {r['scene']} / {r['variant']} / seed {r['seed']}: "
                     + "; ".join(f"{k} {v['choice']} ({v['reason']})" for k, v in d.items()))
    return "\n".join(lines) + "\n"


def plot(rows: list[dict], out: Path) -> None:
    """OUT/skip_study.png (scores against wall time) and OUT/skip_study_curves.png (training curves)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scenes = list(dict.fromkeys(r["scene"] for r in rows))
    variants = [v for v in VARIANTS if any(r["variant"] == v for r in rows)]
    colour = {v: f"C{i}" for i, v in enumerate(VARIANTS)}
    keys = [("basecolor_psnr", "basecolor PSNR (dB)"), ("relit_psnr", "relighting PSNR (dB)"),
            ("novel_psnr", "novel view PSNR (dB)")]
    table = means(rows)
    fig, axes = plt.subplots(len(scenes), len(keys), figsize=(4.6 * len(keys), 3.4 * len(scenes)), squeeze=False)
    for i, scene in enumerate(scenes):
        for j, (key, label) in enumerate(keys):
            ax = axes[i][j]
            for v in variants:
                pts = [(r["wall_s"], r[key]) for r in rows if r["scene"] == scene and r["variant"] == v
                       and r.get(key) is not None]
                if not pts:
                    continue
                ax.scatter(*zip(*pts), s=16, color=colour[v], alpha=0.6, label=v if (i, j) == (0, 0) else None)
                m, old = table[scene, v], table.get((scene, "old"))
                if m[key] is not None:
                    ax.scatter(m["wall_s"], m[key], s=60, marker="*", color=colour[v])
                    if old and v != "old" and old[key] is not None:
                        ax.plot([old["wall_s"], m["wall_s"]], [old[key], m[key]], color=colour[v], lw=0.8, alpha=0.7)
            ax.set_title(f"{scene}: {label.split(' (')[0]}", fontsize=9)
            ax.set_xlabel("fit wall time, start-up included (s)", fontsize=8)
            ax.set_ylabel(label, fontsize=8)
            ax.grid(alpha=0.3)
    if variants:
        fig.legend(loc="upper center", ncol=len(variants), fontsize=8)
    fig.tight_layout(rect=(0, 0, 1, 0.97))
    fig.savefig(out / "skip_study.png", dpi=110)
    plt.close(fig)

    fig, axes = plt.subplots(1, len(scenes), figsize=(4.6 * len(scenes), 3.4), squeeze=False)
    for ax, scene in zip(axes[0], scenes):
        for v in variants:
            for r in rows:
                if r["scene"] == scene and r["variant"] == v and r.get("curve"):
                    s, p = zip(*r["curve"])
                    ax.plot(s, p, color=colour[v], lw=0.9, alpha=0.8,
                            label=v if r["seed"] == min(q["seed"] for q in rows if q["variant"] == v) else None)
        ax.set_title(f"{scene}: training-batch PSNR", fontsize=9)
        ax.set_xlabel("fit seconds (training loop)", fontsize=8)
        ax.set_ylabel("PSNR (dB)", fontsize=8)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / "skip_study_curves.png", dpi=110)
    plt.close(fig)


def report(rows: list[dict], out: Path) -> None:
    """OUT/skip_study.md and the plots of `rows`; the table printed."""
    table = markdown(rows)
    (out / "skip_study.md").write_text(table)
    plot(rows, out)
    print(table)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_dataset_arguments(ap, SCENES, [0, 1], 20)
    ap.add_argument("--variants", nargs="+", default=VARIANTS, choices=VARIANTS,
                    help="old: every rule off; one rule alone; all: every rule automatic; default: no key forced")
    ap.add_argument("--iterations", type=int, default=0, help="train.iterations of every fit (0: the config's)")
    ap.add_argument("--plot", type=Path, nargs="+", metavar="JSON",
                    help="no fit: the table and plots of these skip_study.json files, their rows together")
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks" / "out" / "skip_study",
                    help="folder of the runs, skip_study.json and the plots")
    ap.add_argument("--address", help="fit on this Ray cluster (default: this machine, one fit at a time)")
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    if args.plot:
        report([row for path in args.plot for row in json.loads(path.read_text())["rows"]], args.out)
        return 0
    record = provenance(command_line(argv, __file__))
    print(f"$ {record['command']}\n{describe(record)}", flush=True)
    datasets = {name: ensure_cycles_dataset(name, args.data / name, args) for name in args.scenes}
    if args.warmup:
        name = args.scenes[0]
        warmup_fit(name, datasets[name], args.out, ["train.iterations=30", "train.bounce=on", "train.bounce_after=0",
                                                    "vq.warmup_frac=0.5", "residual.iterations=0"])
    rows = []
    path = args.out / "skip_study.json"
    result = {**record, "settings": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
              "variants": {v: variant_overrides(v) for v in args.variants}, "rows": rows}
    from vq_mitsuba.eval.evaluate import json_safe

    for seed in args.seeds:  # every scene once before the next seed: a stopped study covers them all
        for variant in args.variants:
            fitted = fit_batch(datasets, variant, seed, args)
            for name in args.scenes:
                rows.append(score_one(name, datasets[name], variant, seed, fitted[name], args))
            write_result(path, json_safe(result), indent=1)  # after each batch: a stopped study keeps its rows
    report(rows, args.out)
    print(f"wrote {path}, {args.out / 'skip_study.md'}, {args.out / 'skip_study.png'} and "
          f"{args.out / 'skip_study_curves.png'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
