#!/usr/bin/env python
"""Where a material step's time goes: the steps of a true-mesh fit with both branches and the
bounce on, timed part by part, for one or more config variants alternately.

    python benchmarks/step_parts.py DATASET [--variants default "NAME=KEY=VALUE[,KEY=VALUE]" ...]
        [--steps 150] [--warmup 40] [--repeats 2] [--json OUT.json]

DATASET: a folder with transforms_train.json and mesh.ply (`make-scene`'s output). Each variant
builds the fit's trainer (trials off, the discrete branch and the bounce from the first step),
runs `--warmup` steps (kernel compilation), then times `--steps` steps: the wall time and the time
inside each part (the shading scene's sampling kernel, its radiance kernel and the bounce's
secondary shading, which calls both again: parts nest, so their shares do not add up to 100 %;
the networks' forward passes, the backward pass, Adam). Variants alternate over `--repeats`
rounds; the median steps per second of each is printed. Run it alone on the machine.
"""

from __future__ import annotations

import argparse
import collections
import functools
import statistics
import tempfile
import time
from pathlib import Path

from provenance import describe, provenance, write_json
from variants import parse_variant


def time_steps(dataset: Path, overrides: list[str], steps: int, warmup: int) -> dict:
    import torch

    from vq_mitsuba.backend import shading_threads
    from vq_mitsuba.config import load_config
    from vq_mitsuba.data.captures import load_capture
    from vq_mitsuba.engine.schedule import schedule_at
    from vq_mitsuba.engine.trainer import Trainer
    from vq_mitsuba.render.shading import ShadingScene
    from vq_mitsuba.run.loop import Progress
    from vq_mitsuba.run.run_dir import RunDir

    cfg = load_config(None, ["train.trials=off", "train.bounce_after=0", "vq.warmup_frac=0", *overrides])
    capture = load_capture(dataset / "transforms_train.json", mesh=dataset / "mesh.ply", split="train")
    parts: dict[str, float] = collections.defaultdict(float)
    undo = []

    def timed(owner, name: str, label: str) -> None:
        original = getattr(owner, name)

        @functools.wraps(original)
        def wrapper(*a, **k):
            t = time.perf_counter()
            try:
                return original(*a, **k)
            finally:
                parts[label] += time.perf_counter() - t
        setattr(owner, name, wrapper)
        undo.append((owner, name, original))

    with tempfile.TemporaryDirectory() as tmp:
        trainer = Trainer(capture, RunDir(Path(tmp) / "run"), cfg)
        timed(ShadingScene, "sample", "sampling kernel")
        timed(ShadingScene, "radiance", "radiance kernel (forward)")
        timed(ShadingScene, "bounce_light", "bounce (secondary shading)")
        timed(trainer.model.field, "forward", "material field forward")
        timed(trainer.model.discrete, "forward", "discrete branch forward")
        timed(trainer.optim, "step", "Adam")
        timed(torch.Tensor, "backward", "backward")
        try:
            def run(n: int) -> None:
                for _ in range(n):
                    p = Progress(trainer.step, 0.0, min(0.5, trainer.step / cfg.train.iterations), 0.0)
                    trainer.train_step(schedule_at(cfg, p))
                    trainer.pace.advance()
            with shading_threads():
                run(warmup)
                parts.clear()
                t0 = time.perf_counter()
                run(steps)
                wall = time.perf_counter() - t0
        finally:
            for owner, name, original in reversed(undo):
                setattr(owner, name, original)
    return {"steps": steps, "wall_s": wall, "steps_per_s": steps / wall,
            "parts_ms_per_step": {k: 1000 * v / steps for k, v in parts.items()}}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dataset", type=Path, help="a folder with transforms_train.json and mesh.ply")
    ap.add_argument("--variants", nargs="+", default=["default"], help="default or NAME=KEY=VALUE[,KEY=VALUE...]")
    ap.add_argument("--steps", type=int, default=150, help="steps timed per run")
    ap.add_argument("--warmup", type=int, default=40, help="steps before the timing (kernel compilation)")
    ap.add_argument("--repeats", type=int, default=2, help="rounds over the variants")
    ap.add_argument("--json", type=Path, help="write the runs and medians here")
    args = ap.parse_args(argv)
    record = provenance()
    print(describe(record))
    variants = [parse_variant(v) for v in args.variants]
    runs = {name: [] for name, _ in variants}
    for _ in range(args.repeats):
        for name, overrides in variants:
            r = time_steps(args.dataset, overrides, args.steps, args.warmup)
            runs[name].append(r)
            print(f"{name}: {r['steps_per_s']:.2f} steps/s; " + ", ".join(
                f"{k} {v:.1f} ms" for k, v in sorted(r["parts_ms_per_step"].items(), key=lambda kv: -kv[1])))
    medians = {name: statistics.median(r["steps_per_s"] for r in rs) for name, rs in runs.items()}
    first = medians[variants[0][0]]
    for name, rate in medians.items():
        print(f"{name}: median {rate:.2f} steps/s, {rate / first:.2f}x {variants[0][0]}")
    if args.json:
        write_json(args.json, {**record, "dataset": str(args.dataset), "runs": runs, "median_steps_per_s": medians})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
