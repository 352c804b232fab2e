#!/usr/bin/env python
"""Benchmark: the bundled scenes fitted one after another against the same fits as one batch.

    .venv/bin/python benchmarks/batch_vs_serial.py [--scenes demo texture balls] [--resolution 64]
        [--iterations 600] [--seeds 0 1] [--out benchmarks/out/batch_vs_serial]

Makes each scene (`vq-mitsuba make-scene NAME --resolution R`, reused when there), then:
- serial: `vq-mitsuba fit` and `vq-mitsuba eval --gt` of each scene and seed in turn, each with every core
  (`--threads` = the machine's cores), as a person would run them;
- batch: `vq-mitsuba batch` of the same scenes with `--eval`, each run on one thread
  (`--threads-per-run 1`), as many at once as there are cores.
Prints and writes (OUT/batch_vs_serial.json) the wall time of each way and each run's figures
(novel-view and basecolor PSNR against the scene's ground truth): the batch should finish sooner at
the same accuracy. Run it alone on the machine: it is a timing.
"""

from __future__ import annotations

import argparse
import csv
import os
import subprocess
import sys
import time
from pathlib import Path

from provenance import describe, provenance, write_result

REPO = Path(__file__).resolve().parent.parent
CLI = [sys.executable, "-m", "vq_mitsuba.cli"]


def cli(*args: str) -> None:
    subprocess.run([*CLI, *args], check=True, cwd=REPO)


def figures(metrics_json: Path) -> dict:
    import json

    m = json.loads(metrics_json.read_text())
    return {"novel_view_psnr": m["novel_view"]["psnr"], "basecolor_psnr": m["basecolor"]["psnr"]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+", default=["demo", "texture", "balls"])
    ap.add_argument("--resolution", type=int, default=64)
    ap.add_argument("--iterations", type=int, default=600)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks" / "out" / "batch_vs_serial")
    args = ap.parse_args(argv)
    record = provenance()
    out = args.out.resolve()
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    settings = ["--set", f"train.iterations={args.iterations}"]
    data = {}
    for name in args.scenes:
        data[name] = out / "data" / name
        if not (data[name] / "scene.json").is_file():
            cli("make-scene", name, "--resolution", str(args.resolution), "-o", str(data[name]))

    serial, start = {}, time.perf_counter()
    for name in args.scenes:
        for seed in args.seeds:
            run = out / "serial" / f"{name}-s{seed}"
            t = time.perf_counter()
            cli("fit", str(data[name] / "scene.xml"), "-o", str(run), "--threads", str(cores), "--quiet", *settings,
                "--set", f"train.seed={seed}")
            cli("eval", str(run), "--gt", str(data[name]), "--threads", str(cores), "--quiet")
            serial[run.name] = {"wall_s": round(time.perf_counter() - t, 1), **figures(run / "metrics.json")}
    serial_s = time.perf_counter() - start

    start = time.perf_counter()
    subprocess.run([*CLI, "batch", *[str(data[n] / "scene.xml") for n in args.scenes], "-o", str(out / "batch"),
                    "--eval", "--threads-per-run", "1", "--seeds", ",".join(map(str, args.seeds)), "--quiet", *settings],
                   check=False, cwd=REPO)
    batch_s = time.perf_counter() - start
    with open(out / "batch" / "summary.csv") as f:
        rows = {r["run"]: r for r in csv.DictReader(f)}
    batch = {n: {"status": rows[n]["status"], "wall_s": float(rows[n]["wall_s"] or "nan"),
                 "novel_view_psnr": float(rows[n]["novel_view_psnr"] or "nan"),
                 "basecolor_psnr": float(rows[n]["basecolor_psnr"] or "nan")} for n in serial}

    print(describe(record))
    print(f"{'run':12s} {'serial PSNR view/basecolor':>28s} {'batch PSNR view/basecolor':>28s}")
    for n in serial:
        s, b = serial[n], batch[n]
        print(f"{n:12s} {s['novel_view_psnr']:13.2f} / {s['basecolor_psnr']:6.2f}      "
              f"{b['novel_view_psnr']:13.2f} / {b['basecolor_psnr']:6.2f}")
    print(f"wall time: serial {serial_s:.0f} s ({cores} threads a fit), batch {batch_s:.0f} s (1 thread a run, "
          f"{cores} at once, Ray's start included): batch / serial = {batch_s / serial_s:.2f}")
    write_result(out / "batch_vs_serial.json", {**record, "cores": cores, "iterations": args.iterations,
                                                "seeds": args.seeds,
                                                "resolution": args.resolution, "serial_s": round(serial_s, 1),
                                                "batch_s": round(batch_s, 1), "serial": serial, "batch": batch})
    return 0


if __name__ == "__main__":
    sys.exit(main())
