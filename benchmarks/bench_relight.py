"""Rendering many lightings: one `render` pass with several --envmap files against one pass per
lighting, on the same views, seeds and spp (so the images are identical and only time differs).

    .venv/bin/python benchmarks/bench_relight.py runs/demo [--views 20] [--size 200] [--repeats 3]
        [-o benchmarks/out/relight]

The views are the run's test cameras, then its training cameras, at SIZE x SIZE pixels; the
lightings are the fitted envmap's folder files (envmaps/ beside the capture) plus mirrored copies,
five in all. Prints the median seconds of both ways and their ratio, checks that every image is
the same, and writes OUT/relight_<commit>.json.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("run_dir")
    p.add_argument("--views", type=int, default=20)
    p.add_argument("--size", type=int, default=200)
    p.add_argument("--lightings", type=int, default=5)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("-o", "--output", default=str(ROOT / "benchmarks" / "out" / "relight"))
    args = p.parse_args()

    from provenance import provenance, write_result
    from vq_mitsuba.data.envmaps import load_envmap
    from vq_mitsuba.data.imageio import read_exr
    from vq_mitsuba.run.run_dir import RunDir
    from vq_mitsuba.messages import quiet
    from vq_mitsuba.render.views import render_views

    run = RunDir(args.run_dir)
    fitted = run.load()
    splits = run.cameras()
    cams = (splits.get("test", []) + splits["train"])[: args.views]
    cams = [c.scaled(args.size, round(args.size * c.height / c.width)) for c in cams]
    folder = Path(run.source().info()["capture"]).parent / "envmaps"
    files = sorted(folder.glob("*.exr"))
    envs = [(f.stem, load_envmap(f)) for f in files]
    envs += [(f"{n}_mirrored", e[:, ::-1].copy()) for n, e in envs]
    envs = envs[: args.lightings]
    if len(envs) < args.lightings:
        sys.exit(f"need {args.lightings} lightings, found {len(envs)} in {folder}")
    with quiet():  # no bars: the renders are timed
        render_views(fitted, cams[:1], fitted.world, Path(tempfile.mkdtemp()), envmap=envs[0][1],
                     spp=16)  # warm-up: kernels compiled once
    separate, shared = [], []
    for _ in range(args.repeats):
        with tempfile.TemporaryDirectory() as tmp, quiet():
            tmp = Path(tmp)
            t0 = time.perf_counter()
            for name, env in envs:
                render_views(fitted, cams, fitted.world, tmp / "separate" / name, envmap=env)
            separate.append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            render_views(fitted, cams, fitted.world, tmp / "shared", envmap=envs[0][1], more_envmaps=envs[1:])
            shared.append(time.perf_counter() - t0)
            for i, (name, _) in enumerate(envs):
                for cam in cams:
                    a = read_exr(tmp / "separate" / name / f"{cam.name}_rgb.exr")
                    b = read_exr(tmp / "shared" / ("" if i == 0 else name) / f"{cam.name}_rgb.exr")
                    if not np.array_equal(a, b):
                        sys.exit(f"images differ: {name} {cam.name}")
    s, h = statistics.median(separate), statistics.median(shared)
    print(f"{len(cams)} views x {len(envs)} lightings at {cams[0].width}x{cams[0].height}, "
          f"render.spp {fitted.cfg.render.spp}: one pass per lighting {s:.1f} s, one pass for all {h:.1f} s, "
          f"ratio {h / s:.2f} (median of {args.repeats}); images identical")
    out = Path(args.output)
    out.mkdir(parents=True, exist_ok=True)
    path = write_result(out / f"relight_{provenance()['commit']}.json",
                        {"views": len(cams), "lightings": [n for n, _ in envs],
                         "size": [cams[0].width, cams[0].height], "spp": fitted.cfg.render.spp,
                         "separate_s": separate, "shared_s": shared, "ratio": h / s})
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
