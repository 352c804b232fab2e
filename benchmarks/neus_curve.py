"""Study: NeuS's own held-out renders against its training seconds (the curve, not one point).

    .venv/bin/python benchmarks/neus_curve.py CAPTURE --downscale 4 --holdout 8 --every 60 \
        [--set neus.key=value ...] [--name NAME] -o benchmarks/out/neus_curve

The geometry stage as `vq-mitsuba geometry` runs it (the training views, the capture's sparse or
triangulated points), with a callback every --every seconds of training that renders every
held-out view with NeuS and scores it against its photo (sRGB PSNR inside the masks); the
callback's time is not training time. Written to OUT/NAME.json beside the machine and versions:
the curve (step, training seconds, held-out PSNR), the steps and seconds of the stage, and the
final held-out and training-view PSNR the stage itself records in geometry.json.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from provenance import command_line, describe, write_result

ROOT = Path(__file__).resolve().parent.parent


def plot(path: str, runs: list[str]) -> None:
    import json

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 4))
    for run in runs:
        r = json.loads(Path(run).read_text())
        curve = r["curve"]
        ax.plot([c["train_seconds"] for c in curve], [c["holdout_psnr"] for c in curve], marker="o", ms=3,
                label=f"{r['name']} ({r['commit']}): {r['steps']} steps")
    ax.set_xlabel("NeuS training seconds")
    ax.set_ylabel("held-out PSNR inside the masks (dB)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)


def main(argv: list[str] | None = None) -> int:
    import sys

    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["--plot"]:
        plot(argv[1], argv[2:])
        return 0
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("capture", help="a masked capture (e.g. a NeuS/IDR folder)")
    ap.add_argument("--downscale", type=int, default=4)
    ap.add_argument("--holdout", type=int, default=8)
    ap.add_argument("--every", type=float, default=60.0, help="training seconds between held-out scores")
    ap.add_argument("--set", action="append", default=[], help="KEY=VALUE config overrides")
    ap.add_argument("--name", default="run", help="name of this curve (its JSON and run folder)")
    ap.add_argument("-o", "--output", default=str(ROOT / "benchmarks" / "out" / "neus_curve"))
    args = ap.parse_args(argv)

    from vq_mitsuba.config import CaptureConfig, load_config
    from vq_mitsuba.data.captures import open_capture
    from vq_mitsuba.geometry.neus import reconstruct
    from vq_mitsuba.geometry.neus.training import view_psnr
    from vq_mitsuba.geometry.neus.method import neus_psnr, surface_points
    from vq_mitsuba.messages import quiet

    out = Path(args.output)
    out.mkdir(parents=True, exist_ok=True)
    run = out / args.name
    for stale in ("neus.pt", "mesh.ply", "geometry.json"):
        (run / stale).unlink(missing_ok=True)
    cfg = load_config(None, list(args.set)).neus
    source = open_capture(args.capture, options=CaptureConfig(downscale=args.downscale, holdout=args.holdout))
    train = source.load("train")
    held = source.load("holdout")
    points, _ = surface_points(source, train, cfg)
    curve = []

    def score(neus, step, seconds):
        t = time.perf_counter()
        per_view = view_psnr(neus, held, list(range(len(held.cameras))))
        psnr = float(np.mean(list(per_view.values())))
        curve.append({"step": step, "train_seconds": round(seconds, 1), "holdout_psnr": psnr})
        print(f"[{args.name}] step {step} at {seconds:.0f} s: held out {psnr:.2f} dB "
              f"(scored in {time.perf_counter() - t:.0f} s)", flush=True)

    t0 = time.perf_counter()
    with quiet():
        result = reconstruct(train, run, cfg, callback=score, callback_every_s=args.every, points=points)
    wall = time.perf_counter() - t0
    info = result.summary
    final = neus_psnr(result.neus, train, source)
    curve.append({"step": info["iterations"], "train_seconds": round(info["seconds"]["train"], 1),
                  "holdout_psnr": final["holdout_views"]})
    row = {"name": args.name, "keys": args.set, "steps": info["iterations"], "steps_decided": info.get("steps"),
           "train_s": info["seconds"]["train"], "stage_wall_s": round(wall, 1),
           "steps_per_s": info["iterations_per_s"], "steps_per_s_spread": info["iterations_per_s_spread"],
           "training_rays": info["training_rays"], "batch_rays": info["config"]["batch_rays"],
           "n_samples": info["config"]["n_samples"], "stopped_by_plateau": info.get("stopped_by_plateau"),
           "plateau": info.get("plateau"),
           "holdout_psnr": final["holdout_views"], "train_views_psnr": final["train_views"],
           "per_view": final["per_view"], "curve": curve}
    print(f"[{args.name}] {row['steps']} steps in {row['train_s']:.0f} s ({row['steps_per_s']:.1f}/s): held out "
          f"{row['holdout_psnr']:.2f} dB, training views {row['train_views_psnr']:.2f} dB", flush=True)
    write_result(out / f"{args.name}.json", {"command": command_line(), "capture": args.capture,
                                              "downscale": args.downscale, "holdout": args.holdout, **row})
    print(describe())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
