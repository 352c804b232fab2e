"""Benchmark: NeuS training-step time of this checkout against an earlier commit's, in one process.

    .venv/bin/python benchmarks/neus_step_rate.py CAPTURE [--ref COMMIT] [--set neus.KEY=VALUE ...]
        [--rounds 5] [--steps 15] [--threads 2] [--out benchmarks/out/neus_step_rate]

The reference is NeuS as it was at COMMIT (`vq_mitsuba/geometry/neus.py`, or the package of that
name; `git show`), loaded beside this checkout's as a second module; both build a NeuS on the same capture with the same config and seed,
open the occupancy grid at half-way, and take training steps (the full step: ray batch, occupancy
march, render, losses, backward, optimiser) in alternating rounds of --steps steps, so that a
neighbour's load falls on both alike. Printed and written to OUT/neus_step_rate_<commit>.json with the
machine and versions: the median seconds per step of each, their ratio, and each one's loss and
training-ray PSNR over the last round (the same model, so close but not equal: the random ray
batches are the same, the arithmetic is not). A whole-stage time against mesh error is
`bench_geometry.py`'s.
"""

from __future__ import annotations

import argparse
import importlib.util
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from provenance import ROOT, describe, provenance, write_result


def load_reference(commit: str):
    """NeuS as it was at `commit`, as a module of its own: `vq_mitsuba/geometry/neus.py`, or the
    `vq_mitsuba/geometry/neus/` package (its own imports pointed at the copy)."""
    def git(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=True)

    folder = Path(tempfile.mkdtemp())
    name = f"neus_{commit}"
    single = git("show", f"{commit}:vq_mitsuba/geometry/neus.py")
    if single.returncode == 0:
        path = folder / f"{name}.py"
        path.write_text(single.stdout)
    else:
        package = "vq_mitsuba/geometry/neus"
        files = git("ls-tree", "--name-only", f"{commit}:{package}")
        if files.returncode != 0:
            raise SystemExit(f"{commit} has neither {package}.py nor {package}/")
        (folder / name).mkdir()
        for file in files.stdout.split():
            text = git("show", f"{commit}:{package}/{file}").stdout
            (folder / name / file).write_text(text.replace("vq_mitsuba.geometry.neus", name))
        path = folder / name / "__init__.py"
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # dataclasses (and a package's own imports) look the module up while it executes
    spec.loader.exec_module(module)
    return module


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("capture", help="a capture with masks (transforms JSON, COLMAP or NeuS/IDR folder)")
    ap.add_argument("--ref", default="c9f7280", help="commit whose NeuS is the reference")
    ap.add_argument("--set", action="append", default=[], metavar="neus.KEY=VALUE", help="config override for both")
    ap.add_argument("--downscale", type=int, default=1, help="shrink the capture's images by this factor")
    ap.add_argument("--rounds", type=int, default=5, help="alternating rounds per implementation")
    ap.add_argument("--steps", type=int, default=15, help="training steps per round")
    ap.add_argument("--threads", type=int, default=2, help="torch CPU threads")
    ap.add_argument("--out", default="benchmarks/out/neus_step_rate", help="folder for the JSON")
    args = ap.parse_args()

    import torch

    from vq_mitsuba.config import CaptureConfig, load_config
    from vq_mitsuba.data.captures import load_capture
    from vq_mitsuba.geometry.neus import rays as current_rays, training as current_fit
    from vq_mitsuba.run.loop import Progress

    torch.set_num_threads(args.threads)
    cfg = load_config(None, args.set).neus
    capture = load_capture(args.capture, options=CaptureConfig(downscale=args.downscale))
    fits = {}
    current = type("Current", (), {"neus_for": staticmethod(current_rays.neus_for),
                                   "NeuSTraining": current_fit.NeuSTraining})
    for name, module in (("reference", load_reference(args.ref)), ("current", current)):
        neus = (getattr(module, "neus_for", None) or module.NeuS)(capture, cfg)  # NeuS took a capture before
        # the training loop's class in this or an earlier layout (one module; fit.py; training.py)
        fit_class = getattr(module, "NeuSTraining", None) or getattr(module, "_NeuSFit", None) or module.fit._NeuSFit
        fit = fit_class(neus, None)
        fit.loop = type("Clock", (), {"clock": staticmethod(time.perf_counter)})
        neus.refresh_occupancy(neus.level_weights(0.5))
        fits[name] = fit
    seconds = {name: [] for name in fits}
    last = {}
    for r in range(args.rounds + 1):  # round 0 warms up and is not counted
        for name, fit in fits.items():
            t0 = time.perf_counter()
            for i in range(args.steps):
                fit.loop_step(Progress(step=1000 + r * args.steps + i, seconds=0.0, step_share=0.5, time_share=0.5))
            if r > 0:
                seconds[name].append((time.perf_counter() - t0) / args.steps)
            recent = fit.history[-args.steps:]
            last[name] = {"loss": statistics.mean(h["loss"] for h in recent),
                          "psnr": statistics.mean(h["psnr"] for h in recent)}
    med = {name: statistics.median(v) for name, v in seconds.items()}
    result = {"reference_commit": args.ref, "threads": args.threads, "rounds": args.rounds, "steps": args.steps,
              "grid": fits["current"].neus.grid, "sample_points_per_step": fits["current"].cfg.batch_rays
              * fits["current"].cfg.n_samples,
              "seconds_per_step": {name: {"median": med[name], "rounds": v} for name, v in seconds.items()},
              "speedup": med["reference"] / med["current"], "last_round": last}
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    write_result(out / f"neus_step_rate_{provenance()['commit']}.json", result)
    print(describe())
    for name in fits:
        print(f"{name:>9}: {med[name] * 1000:7.1f} ms/step (median of {args.rounds}), last round loss "
              f"{last[name]['loss']:.4f}, PSNR {last[name]['psnr']:.2f} dB")
    print(f"speed-up {result['speedup']:.2f}x; grid {result['grid']['levels']} levels to {result['grid']['max_res']}")


if __name__ == "__main__":
    main()
