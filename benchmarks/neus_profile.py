"""Benchmark: where a NeuS training step's time goes, by operation, and how far it is from its floor.

    .venv/bin/python benchmarks/neus_profile.py CAPTURE [--downscale N] [--set neus.KEY=VALUE ...]
        [--steps 8] [--threads 2] [--out benchmarks/out/neus_profile]

(`PYTHONPATH=FOLDER` profiles the checkout in FOLDER, e.g. a `git worktree` of an earlier commit.)

Builds NeuS on the capture (its auto grid, occupancy opened at half-way), takes warm-up steps, then
profiles --steps whole steps (ray batch, occupancy march, render, losses, backward, optimiser) with
torch.profiler. Each operation's self time is put in one of four groups: the matrix products of the
networks (mm, addmm, bmm), the feature grid's lookup and its gradient (the compiled kernel, or the
torch lookup's gather and scatter), the optimiser, and everything else (elementwise passes,
indexing, the march). The floor printed is the time of the matrix products plus the grid lookup:
what a step costs with every elementwise pass fused away at the same network sizes. Printed and
written to OUT/neus_profile_<capture folder>_<profiled commit>.json with the machine and versions.
"""

from __future__ import annotations

import argparse
import subprocess
import time
from collections import defaultdict
from pathlib import Path

from provenance import describe, write_result

GROUPS = {
    "matrix products": ("aten::mm", "aten::addmm", "aten::bmm"),
    "grid lookup": ("_Lookup", "_LookupBackward", "aten::index_select", "aten::scatter_add_", "aten::index_add_",
                    "aten::bitwise_xor", "aten::bitwise_and"),
    "optimiser": ("aten::_fused_adam_", "Optimizer.step#Adam.step", "Optimizer.zero_grad#Adam.zero_grad"),
}


def group_of(name: str) -> str:
    return next((group for group, names in GROUPS.items() if name in names), "elementwise and other")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("capture", help="a capture NeuS can read (transforms JSON, COLMAP or NeuS/IDR folder)")
    ap.add_argument("--set", action="append", default=[], metavar="neus.KEY=VALUE", help="config override")
    ap.add_argument("--downscale", type=int, default=1, help="shrink the capture's images by this factor")
    ap.add_argument("--steps", type=int, default=8, help="profiled training steps")
    ap.add_argument("--threads", type=int, default=2, help="torch CPU threads")
    ap.add_argument("--out", default="benchmarks/out/neus_profile", help="folder for the JSON")
    args = ap.parse_args()

    import torch
    from torch.profiler import ProfilerActivity, profile

    from vq_mitsuba.config import CaptureConfig, load_config
    from vq_mitsuba.data.captures import load_capture
    from vq_mitsuba.geometry import neus as module
    from vq_mitsuba.run.loop import Progress

    # An earlier checkout (PYTHONPATH=ITS_FOLDER) may have NeuS as one module, without the kernel.
    NeuS = getattr(module, "neus_for", None) or module.NeuS  # NeuS took a capture before `neus_for`
    # the training loop's class in this or an earlier layout (one module; fit.py; training.py)
    training_class = getattr(module, "NeuSTraining", None) or getattr(module, "_NeuSFit", None) or module.fit._NeuSFit
    lookup = module.grid_kernel.status() if hasattr(module, "grid_kernel") else "torch lookup"

    torch.set_num_threads(args.threads)
    cfg = load_config(None, args.set).neus
    capture = load_capture(args.capture, options=CaptureConfig(downscale=args.downscale))
    neus = NeuS(capture, cfg)
    fit = training_class(neus, None)
    fit.loop = type("Clock", (), {"clock": staticmethod(time.perf_counter)})
    neus.refresh_occupancy(neus.level_weights(0.5))

    def step(i: int) -> None:
        fit.loop_step(Progress(step=1000 + i, seconds=0.0, step_share=0.5, time_share=0.5))

    for i in range(5):
        step(i)
    t0 = time.perf_counter()
    for i in range(args.steps):
        step(i)
    wall_ms = (time.perf_counter() - t0) / args.steps * 1000
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        for i in range(args.steps):
            step(i)
    ops = {e.key: e.self_cpu_time_total / 1000 / args.steps for e in prof.key_averages()}  # ms a step
    total = sum(ops.values())
    groups = defaultdict(float)
    for name, ms in ops.items():
        groups[group_of(name)] += ms
    top = sorted(ops.items(), key=lambda kv: -kv[1])[:15]
    floor = groups["matrix products"] + groups["grid lookup"]
    points = neus.cfg.batch_rays * neus.cfg.n_samples  # the batch auto chose
    profiled = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=Path(module.__file__).parent,
                              capture_output=True, text=True).stdout.strip()
    result = {"profiled_commit": profiled, "capture": args.capture, "downscale": args.downscale, "threads": args.threads, "steps": args.steps,
              "grid": neus.grid, "grid_lookup": lookup, "sample_points_per_step": points,
              "ms_per_step_unprofiled": wall_ms, "ms_per_step_profiled": total,
              "groups_ms": dict(groups), "top_ops_ms": dict(top), "floor_ms": floor,
              "sample_points_per_s": points / (wall_ms / 1000)}
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    name = Path(args.capture).resolve().name if Path(args.capture).is_dir() else Path(args.capture).resolve().parent.name
    write_result(out / f"neus_profile_{name}_{profiled}.json", result)
    print(describe())
    print(f"grid {neus.grid['levels']} levels to {neus.grid['max_res']} ({result['grid_lookup']}); "
          f"{points} sample points a step")
    print(f"{wall_ms:.1f} ms a step ({result['sample_points_per_s'] / 1e3:.0f} k sample points/s); profiled "
          f"{total:.1f} ms:")
    for name, ms in sorted(groups.items(), key=lambda kv: -kv[1]):
        print(f"  {name:<22} {ms:6.1f} ms  {100 * ms / total:4.1f} %")
    print(f"floor (matrix products + grid lookup): {floor:.1f} ms, {total / floor:.2f}x below the step")
    print("top operations (ms a step): " + ", ".join(f"{k} {v:.2f}" for k, v in top[:8]))


if __name__ == "__main__":
    main()
