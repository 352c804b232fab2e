#!/usr/bin/env python
"""Benchmark: training steps per second of `fit` (and, with --eval-spp, the time of
`vq-mitsuba eval` on the fitted run), for one or more git revisions in one run.

    python benchmarks/bench_step_rate.py [--refs BASE HEAD] [--scene balls] [--resolution 128]
        [--data DIR] [--iterations 200] [--repeats 3] [--eval-spp 0] [--out benchmarks/out/step_rate]

Each revision is checked out into a temporary git worktree and `fit` runs from there in a child
process, on the same dataset and config (the preset of the scene's name in that revision), with a new
`train.seed` per repeat. Runs of the revisions alternate (A B A B ...), so that both see the
same machine load. The rate is measured after the first `--warmup` steps, which include Dr.Jit's
kernel compilation; a kernel that compiles again at every step (a size baked into it) still
shows. Every step simulates the bounce (`train.bounce_after=0` where a revision has that key),
so the steady-state step is timed in every revision. Prints the median steps per second of
each revision, its ratio to the first, and the training-batch PSNR at the end (the same
schedule, so the error is comparable); writes OUT/step_rate.json and OUT/step_rate.md. With
--eval-spp N, each fit is then scored by `vq_mitsuba.eval.evaluate` at N spp (all test views, fitted
light and every relighting envmap; the dataset needs relit views, as `make-scene` writes them),
and the median evaluation time and its novel-view, basecolor and relighting PSNR are printed
beside the step rate.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
# The environment as given, before `import vq_mitsuba` sets its OpenMP defaults in it: each revision's
# child runs with its own defaults (the spin set now slows a revision whose torch fights Dr.Jit).
GIVEN_ENV = dict(os.environ)


def child(args) -> int:
    """Runs inside a revision's worktree: one fit, then one JSON line on stdout. The parent puts
    the worktree on PYTHONPATH, ahead of the installed package: its vq_mitsuba is imported (checked)."""
    import vq_mitsuba
    from vq_mitsuba.config import load_config

    try:
        from vq_mitsuba.engine.pipeline import fit
    except ImportError:  # revisions before the pipeline module's name
        from vq_mitsuba.engine.fit import fit
    try:
        from vq_mitsuba.messages import quiet
    except ImportError:  # revisions before the one reporter: their bars go to the captured stderr
        from contextlib import nullcontext as quiet

    if not Path(vq_mitsuba.__file__).resolve().is_relative_to(Path(args.src).resolve()):
        raise SystemExit(f"imported {vq_mitsuba.__file__}, not the revision's copy in {args.src}")

    # The revision's preset of the scene's name: inside the package, or configs/ in older revisions.
    preset = next((p for p in (Path(args.src) / "vq_mitsuba" / "presets" / f"{args.scene}.yaml",
                               Path(args.src) / "configs" / f"{args.scene}.yaml") if p.is_file()), Path("-"))
    overrides = [f"train.iterations={args.iterations}", f"train.seed={args.seed}", "train.log_every=10",
                 f"train.checkpoint_every={args.iterations + 1}", "train.time_limit_s=0"]
    if "bounce_after" in vars(load_config(None).train):
        # Every step with the bounce, as in revisions before that key: the steady-state step is timed.
        overrides.append("train.bounce_after=0")
    cfg = load_config(preset if preset.is_file() else None, overrides)
    run = Path(args.run)
    with quiet():
        summary = fit(Path(args.data) / "transforms_train.json", run, cfg)
    import torch

    hist = torch.load(run / "checkpoint.pt", map_location="cpu", weights_only=False)["history"]
    start = next(h for h in hist if h["step"] >= args.warmup)
    end = hist[-1]
    rate = (end["step"] - start["step"]) / max(end["seconds"] - start["seconds"], 1e-9)
    result = {"steps_per_s": rate, "iterations": summary["iterations"], "seconds": summary["seconds"],
              "final_psnr": end["psnr"]}
    if args.eval_spp:
        import time

        from vq_mitsuba.eval.evaluate import evaluate

        t0 = time.perf_counter()
        with quiet():
            m = evaluate(run, Path(args.data), spp=args.eval_spp, meanshift_bandwidths=())
        result.update({"eval_s": time.perf_counter() - t0, "eval_novel_psnr": m["novel_view"]["psnr"],
                       "eval_basecolor_psnr": m["basecolor"]["psnr"],
                       "eval_relit_psnr": m["relighting"]["albedo_scale"]["mean"]["psnr"]})
    print("STEP_RATE " + json.dumps(result))
    return 0


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--refs", nargs="+", default=["HEAD"], help="git revisions to time (the first is the reference)")
    p.add_argument("--scene", default="balls", help="bundled scene (default balls)")
    p.add_argument("--resolution", type=int, default=128, help="image size of a generated dataset (default 128)")
    p.add_argument("--data", type=Path, help="an existing dataset folder (default: generate SCENE into "
                   "benchmarks/out/data/SCENE with the Mitsuba renderer, or reuse it)")
    p.add_argument("--iterations", type=int, default=200, help="steps per fit (default 200)")
    p.add_argument("--warmup", type=int, default=30, help="first steps left out of the rate (default 30)")
    p.add_argument("--repeats", type=int, default=3, help="fits per revision (default 3)")
    p.add_argument("--eval-spp", type=int, default=0, help="also time `vq-mitsuba eval` of each fitted run at "
                   "this many samples per pixel (default 0: no evaluation)")
    p.add_argument("--out", type=Path, default=REPO / "benchmarks" / "out" / "step_rate")
    # Internal: one fit inside a worktree.
    p.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--src", help=argparse.SUPPRESS)
    p.add_argument("--run", help=argparse.SUPPRESS)
    p.add_argument("--seed", type=int, default=0, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.child:
        return child(args)
    if args.warmup >= args.iterations:
        p.error(f"--warmup ({args.warmup}) must be below --iterations ({args.iterations})")

    from bench_scenes import ensure_dataset
    from provenance import command_line, describe, provenance, write_result
    from vq_mitsuba.backend import init_mitsuba

    init_mitsuba()  # the variant the children pick, for the provenance record

    data = args.data or ensure_dataset(args.scene, REPO / "benchmarks" / "out" / "data" / args.scene,
                                       args.resolution)
    if not (Path(data) / "transforms_train.json").is_file():
        p.error(f"{data}: no transforms_train.json (not a dataset folder)")
    commits = {}
    for ref in args.refs:
        res = subprocess.run(["git", "-C", str(REPO), "rev-parse", "--short", ref], capture_output=True, text=True)
        if res.returncode != 0:
            p.error(f"--refs: '{ref}' is not a revision of {REPO} ({res.stderr.strip()})")
        commits[ref] = res.stdout.strip()

    args.out.mkdir(parents=True, exist_ok=True)
    runs: dict[str, list[dict]] = {ref: [] for ref in args.refs}
    with tempfile.TemporaryDirectory(prefix="step_rate_") as tmp:
        trees = {}
        for i, ref in enumerate(args.refs):
            trees[ref] = Path(tmp) / f"tree{i}"
            subprocess.run(["git", "-C", str(REPO), "worktree", "add", "--detach", "-f", str(trees[ref]),
                            commits[ref]], check=True, capture_output=True)
        try:
            for rep in range(args.repeats):
                for ref in args.refs:
                    run_dir = Path(tmp) / f"run_{commits[ref]}_{rep}"
                    cmd = [sys.executable, str(Path(__file__).resolve()), "--child", "--src", str(trees[ref]),
                           "--run", str(run_dir), "--data", str(Path(data).resolve()), "--scene", args.scene,
                           "--iterations", str(args.iterations), "--warmup", str(args.warmup),
                           "--seed", str(1000 + rep), "--eval-spp", str(args.eval_spp)]
                    res = subprocess.run(cmd, capture_output=True, text=True, cwd=trees[ref],
                                         env={**GIVEN_ENV, "PYTHONPATH": str(trees[ref])})
                    line = [ln for ln in res.stdout.splitlines() if ln.startswith("STEP_RATE ")]
                    if res.returncode != 0 or not line:
                        sys.stderr.write(res.stdout[-2000:] + res.stderr[-4000:])
                        raise SystemExit(f"fit of {ref} ({commits[ref]}) failed, exit code {res.returncode}")
                    r = json.loads(line[0].split(" ", 1)[1])
                    runs[ref].append(r)
                    print(f"[{ref} {commits[ref]}] repeat {rep + 1}/{args.repeats}: "
                          f"{r['steps_per_s']:.2f} steps/s, train PSNR {r['final_psnr']:.2f} dB"
                          + (f", eval {r['eval_s']:.1f} s" if "eval_s" in r else ""))
        finally:
            for tree in trees.values():
                subprocess.run(["git", "-C", str(REPO), "worktree", "remove", "--force", str(tree)],
                               capture_output=True)

    ref0 = args.refs[0]
    med0 = statistics.median(r["steps_per_s"] for r in runs[ref0])
    rows = []
    for ref in args.refs:
        med = statistics.median(r["steps_per_s"] for r in runs[ref])
        rows.append({"ref": ref, "commit": commits[ref], "median_steps_per_s": med, "ratio": med / med0,
                     "median_final_psnr": statistics.median(r["final_psnr"] for r in runs[ref]), "runs": runs[ref]})
        if args.eval_spp:
            rows[-1].update({f"median_{k}": statistics.median(r[k] for r in runs[ref])
                             for k in ("eval_s", "eval_novel_psnr", "eval_basecolor_psnr", "eval_relit_psnr")})
    command = command_line(argv, __file__)
    result = {**provenance(command), "scene": args.scene, "data": str(data),
              "iterations": args.iterations, "warmup": args.warmup, "repeats": args.repeats,
              "eval_spp": args.eval_spp, "rows": rows}
    lines = [f"# Step rate of `fit` ({args.scene}, {args.iterations} steps, rate after step {args.warmup}, "
             f"median of {args.repeats})", "", f"`{command}`", "",
             f"Machine: {describe(result)}", "",
             "| revision | commit | steps/s (median) | ratio to first | train PSNR at the end (median) | steps/s of each run |",
             "|---|---|---:|---:|---:|---|"]
    for r in rows:
        each = ", ".join(f"{x['steps_per_s']:.2f}" for x in r["runs"])
        lines.append(f"| {r['ref']} | {r['commit']} | {r['median_steps_per_s']:.2f} | {r['ratio']:.2f} | "
                     f"{r['median_final_psnr']:.2f} | {each} |")
    if args.eval_spp:
        e0 = rows[0]["median_eval_s"]
        lines += ["", f"Evaluation of each fitted run (`vq_mitsuba.eval.evaluate`, {args.eval_spp} spp; PSNR in dB, "
                  "relighting: mean over the envmaps, albedo scale):", "",
                  "| revision | commit | eval s (median) | ratio to first | novel view | basecolor | relit | eval s of each run |",
                  "|---|---|---:|---:|---:|---:|---:|---|"]
        for r in rows:
            each = ", ".join(f"{x['eval_s']:.1f}" for x in r["runs"])
            lines.append(f"| {r['ref']} | {r['commit']} | {r['median_eval_s']:.1f} | {r['median_eval_s'] / e0:.2f} | "
                         f"{r['median_eval_novel_psnr']:.2f} | {r['median_eval_basecolor_psnr']:.2f} | "
                         f"{r['median_eval_relit_psnr']:.2f} | {each} |")
    text = "\n".join(lines) + "\n"
    write_result(args.out / "step_rate.json", result)
    (args.out / "step_rate.md").write_text(text)
    print(text)
    print(f"wrote {args.out / 'step_rate.json'} and {args.out / 'step_rate.md'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
