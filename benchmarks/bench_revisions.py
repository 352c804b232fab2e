#!/usr/bin/env python
"""Benchmark: whole default fits and their scores, git revision against revision, on the same datasets.

    .venv/bin/python benchmarks/bench_revisions.py --refs BASE HEAD --data DATA [DATA ...]
        [--preset NAME] [--seeds 0 1] [--eval-spp 64] [--out benchmarks/out/revisions]

Each revision is checked out into a temporary git worktree; for every dataset (a folder written by
`vq-mitsuba make-scene`, fitted from its scene.xml, so with its true mesh) and seed, `vq-mitsuba fit`
then `vq-mitsuba eval --gt DATA` run from that worktree in child processes (its vq_mitsuba imported,
checked), revisions alternating (A B A B ...) so that both see the same machine load. Timed: the
fit's wall time (start-up, material steps, ranking, residual, files), the material loop's seconds
and the residual's (fit.json), and eval's wall time (every test view under the fitted light and
each relighting envmap). Scored: novel-view, basecolor and relighting PSNR, M. Printed as a table
of medians over seeds with each revision's ratio to the first, and written to OUT/revisions.json
with the machine and versions.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from provenance import ROOT, describe, provenance, write_result


def run_child(tree: Path, args: list[str]) -> float:
    """`python -m vq_mitsuba.cli ARGS` from the worktree `tree`; its wall seconds."""
    env = {**os.environ, "PYTHONPATH": str(tree)}
    check = subprocess.run([sys.executable, "-c", "import vq_mitsuba; print(vq_mitsuba.__file__)"], cwd=tree,
                           env=env, capture_output=True, text=True)
    if not Path(check.stdout.strip()).resolve().is_relative_to(tree.resolve()):
        raise SystemExit(f"imported {check.stdout.strip()}, not the revision's copy in {tree}")
    t0 = time.perf_counter()
    res = subprocess.run([sys.executable, "-m", "vq_mitsuba.cli", *args], cwd=tree, env=env, capture_output=True,
                         text=True)
    if res.returncode != 0:
        raise SystemExit(f"{' '.join(args)} failed in {tree}:\n{res.stderr[-3000:]}")
    return time.perf_counter() - t0


def scores(metrics: dict) -> dict:
    """The figures compared: novel view, basecolor and relighting PSNR (mean over the envmaps, the
    render scaled by the basecolor alignment)."""
    relit = ((metrics.get("relighting") or {}).get("albedo_scale") or {}).get("mean") or {}
    return {"novel_view_psnr": metrics["novel_view"]["psnr"], "basecolor_psnr": metrics["basecolor"]["psnr"],
            "relight_psnr": relit.get("psnr")}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--refs", nargs="+", default=["HEAD"], help="git revisions (the first is the reference)")
    ap.add_argument("--data", nargs="+", type=Path, required=True, help="make-scene dataset folders")
    ap.add_argument("--preset", help="fit preset (default: none, the defaults)")
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 1], help="train.seed values (default 0 1)")
    ap.add_argument("--eval-spp", type=int, default=64, help="eval's samples per pixel (default 64)")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "out" / "revisions")
    args = ap.parse_args()
    work = Path(tempfile.mkdtemp(prefix="revisions-"))
    trees = {}
    for ref in args.refs:
        trees[ref] = work / f"tree-{len(trees)}"
        subprocess.run(["git", "worktree", "add", "--detach", str(trees[ref]), ref], cwd=ROOT, check=True,
                       capture_output=True)
    rows = []
    try:
        for data in args.data:
            for seed in args.seeds:
                for ref in args.refs:
                    run = work / f"{data.name}-{len(rows)}"
                    fit_args = ["fit", str((data / "scene.xml").resolve()), "-o", str(run), "--quiet",
                                "--set", f"train.seed={seed}"] + (["--preset", args.preset] if args.preset else [])
                    fit_s = run_child(trees[ref], fit_args)
                    eval_s = run_child(trees[ref], ["eval", str(run), "--gt", str(data.resolve()), "--spp",
                                                    str(args.eval_spp), "--quiet", "--meanshift", "none"])
                    summary = json.loads((run / "fit.json").read_text())
                    metrics = json.loads((run / "metrics.json").read_text())
                    materials = run / "materials.json"
                    row = {"data": data.name, "seed": seed, "ref": ref, "fit_wall_s": fit_s, "eval_wall_s": eval_s,
                           "material_loop_s": summary["seconds"], "steps_per_s": summary["iterations_per_s"],
                           "residual_s": (summary.get("residual") or {}).get("seconds"),
                           "M": json.loads(materials.read_text()).get("num_materials") if materials.is_file()
                           else None, **scores(metrics)}
                    rows.append(row)
                    print(json.dumps(row), flush=True)
    finally:
        for tree in trees.values():
            subprocess.run(["git", "worktree", "remove", "--force", str(tree)], cwd=ROOT, capture_output=True)
    keys = ["fit_wall_s", "material_loop_s", "residual_s", "eval_wall_s", "novel_view_psnr", "basecolor_psnr",
            "relight_psnr"]
    table = {}
    for data in args.data:
        for ref in args.refs:
            mine = [r for r in rows if r["data"] == data.name and r["ref"] == ref]
            table[f"{data.name} {ref}"] = {k: statistics.median([r[k] for r in mine if r.get(k) is not None])
                                           for k in keys if any(r.get(k) is not None for r in mine)}
    print("\n| dataset, revision | " + " | ".join(keys) + " |")
    print("|---|" + "---:|" * len(keys))
    for name, med in table.items():
        base = table[f"{name.split()[0]} {args.refs[0]}"]
        cells = []
        for k in keys:
            if k not in med:
                cells.append("-")
            elif k.endswith("_s"):
                cells.append(f"{med[k]:.1f} ({med[k] / base[k]:.2f}x)" if base.get(k) else f"{med[k]:.1f}")
            else:
                cells.append(f"{med[k]:.2f}")
        print(f"| {name} | " + " | ".join(cells) + " |")
    record = provenance()
    path = write_result(args.out / "revisions.json", {**record, "refs": args.refs, "seeds": args.seeds,
                                                      "eval_spp": args.eval_spp, "runs": rows, "medians": table})
    print(describe(record))
    print(f"written {path}")


if __name__ == "__main__":
    main()
