"""Study: NeuS settings on a masked real capture, scored by how well NeuS renders its photos.

    .venv/bin/python benchmarks/neus_variants.py CAPTURE --downscale 8 --holdout 8 \
        --variant base= --variant hash="neus.levels=8 neus.max_res=512 neus.hash_log2=19" \
        [--set neus.iterations=600] [--set neus.time_limit_s=0] -o benchmarks/out/neus_variants

Each variant runs `vq-mitsuba geometry CAPTURE` with the shared `--set` keys and then its own, one
after the other (never side by side), into OUT/NAME. Its NeuS model then renders views of the
capture (sRGB, on black), scored against the photos inside the capture's masks: a sample of the
training views and every held-out view (`capture.holdout`). Printed and written to
OUT/neus_variants.json beside the machine and versions: per variant, the steps, training seconds,
steps per second, the mean PSNR of the training and of the held-out views, and the visual hull's
share of each held-out view's foreground that NeuS could render at all (opacity above 0.5).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import shlex
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from provenance import command_line, describe, write_result

ROOT = Path(__file__).resolve().parent.parent


def score(capture_path: str, run: Path, downscale: int, holdout: int, train_views: int) -> dict:
    import torch

    from vq_mitsuba.config import CaptureConfig, NeuSConfig
    from vq_mitsuba.data.captures import load_capture, split_indices
    from vq_mitsuba.geometry.neus import neus_for, render_view
    from vq_mitsuba.geometry.neus.training import sample_views, view_psnr

    options = CaptureConfig(downscale=downscale, holdout=holdout)
    train = load_capture(capture_path, options=options, split="train")
    every = load_capture(capture_path, options=CaptureConfig(downscale=downscale))
    state = torch.load(run / "neus.pt", map_location="cpu", weights_only=False)
    names = {f.name for f in dataclasses.fields(NeuSConfig)}
    cfg = NeuSConfig(**{k: v for k, v in state["config"].items() if k in names})
    neus = neus_for(train, cfg)  # the same box and hull as training: the training views
    neus.model.load_state_dict(state["model"])
    neus.refresh_occupancy([1.0] * cfg.levels)
    kept = split_indices(len(every.cameras), holdout, "train")
    held = split_indices(len(every.cameras), holdout, "holdout")
    sample = [kept[i] for i in sample_views(len(kept), train_views)]
    out = {"train_views": view_psnr(neus, every, sample), "holdout_views": view_psnr(neus, every, held),
           "holdout_rendered_share": {}}
    for v in held:
        _, acc = render_view(neus, every.cameras[v])
        out["holdout_rendered_share"][every.cameras[v].name] = float((acc[every.alpha[v] > 0.5] > 0.5).mean())
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("capture", help="a masked capture NeuS can read (e.g. a NeuS/IDR folder)")
    ap.add_argument("--variant", action="append", required=True,
                    help='NAME="KEY=VALUE ..." (config keys of this variant; NAME= for the defaults)')
    ap.add_argument("--set", action="append", default=[], help="KEY=VALUE for every variant")
    ap.add_argument("--downscale", type=int, default=8)
    ap.add_argument("--holdout", type=int, default=8)
    ap.add_argument("--train-views", type=int, default=4, help="training views scored per variant")
    ap.add_argument("-o", "--output", default=str(ROOT / "benchmarks" / "out" / "neus_variants"))
    args = ap.parse_args(argv)
    out = Path(args.output)
    out.mkdir(parents=True, exist_ok=True)
    results = []
    for spec in args.variant:
        name, _, keys = spec.partition("=")
        sets = list(args.set) + shlex.split(keys)
        run = out / name
        cmd = [sys.executable, "-m", "vq_mitsuba.cli", "geometry", args.capture, "-o", str(run), "--quiet",
               "--downscale", str(args.downscale), "--holdout", str(args.holdout)]
        for kv in sets:
            cmd += ["--set", kv]
        t0 = time.perf_counter()
        subprocess.run(cmd, check=True)
        wall = time.perf_counter() - t0
        g = json.loads((run / "geometry.json").read_text())
        s = score(args.capture, run, args.downscale, args.holdout, args.train_views)
        row = {"variant": name, "keys": sets, "wall_s": wall, "steps": g["iterations"],
               "train_s": g["seconds"]["train"], "steps_per_s": g["iterations_per_s"],
               "box_half_size": g["box_half_size"],
               "psnr_train_mean": float(np.mean(list(s["train_views"].values()))),
               "psnr_holdout_mean": float(np.mean(list(s["holdout_views"].values()))),
               "holdout_rendered_share_mean": float(np.mean(list(s["holdout_rendered_share"].values()))), **s}
        results.append(row)
        print(f"{name:>12}: {row['steps']} steps in {row['train_s']:.0f} s ({row['steps_per_s']:.2f}/s), "
              f"PSNR in masks: training views {row['psnr_train_mean']:.2f} dB, held out "
              f"{row['psnr_holdout_mean']:.2f} dB; held-out foreground rendered "
              f"{100 * row['holdout_rendered_share_mean']:.1f} %", flush=True)
    write_result(out / "neus_variants.json", {"command": command_line(), "capture": args.capture,
                                               "downscale": args.downscale, "holdout": args.holdout,
                                               "results": results})
    print(describe())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
