"""A photographed-size capture from images alone: the stages' wall time, peak memory and the
held-out novel-view scores of `fit --geometry neus` on a NeuS/IDR (or COLMAP) folder.

    .venv/bin/python benchmarks/bench_real_capture.py data/big/neus [--downscale 4] [--holdout 8]
        [-o benchmarks/out/real_capture]

Make the capture with `vq-mitsuba make-scene demo --resolution 1600x1200 --n-train 49 --n-test 1
--photo-formats -o data/big`. The fit runs as its own process under `/usr/bin/time -v` (peak
resident memory of the whole run); the NeuS and material stages' seconds come from the run's
geometry.json and fit.json. Writes OUT/real_capture_<commit>.json.
"""

from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("capture")
    p.add_argument("--downscale", type=int, default=4)
    p.add_argument("--holdout", type=int, default=8)
    p.add_argument("--run", default=str(ROOT / "runs" / "real_capture"))
    p.add_argument("-o", "--output", default=str(ROOT / "benchmarks" / "out" / "real_capture"))
    args = p.parse_args()

    from provenance import provenance, write_result

    cli = str(Path(sys.executable).parent / "vq-mitsuba")
    fit = ["/usr/bin/time", "-v", cli, "fit", args.capture, "-o", args.run, "--geometry", "neus", "--quiet",
           "--downscale", str(args.downscale), "--holdout", str(args.holdout)]
    t0 = time.perf_counter()
    done = subprocess.run(fit, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if done.returncode != 0:
        sys.exit(f"fit failed:\n{done.stdout}\n{done.stderr}")
    peak_kb = int(re.search(r"Maximum resident set size \(kbytes\): (\d+)", done.stderr).group(1))
    run = Path(args.run)
    geometry = json.loads((run / "geometry.json").read_text())
    fitted = json.loads((run / "fit.json").read_text())
    t0 = time.perf_counter()
    subprocess.run([cli, "eval", args.run, "--quiet"], check=True, capture_output=True, text=True)
    eval_s = time.perf_counter() - t0
    metrics = json.loads((run / "metrics.json").read_text())
    record = {
        "fit_command": " ".join(fit[2:]), "wall_s": round(wall, 1), "peak_rss_gb": round(peak_kb / 2**20, 2),
        "stages_s": {"neus_train": geometry["seconds"]["train"], "neus_hull": geometry["seconds"]["setup_and_hull"],
                     "mesh_export": geometry["seconds"]["mesh_export"], "materials": fitted["seconds"],
                     "other (loading, undistortion, start-up)": None},
        "neus_iterations": geometry["iterations"], "fit_iterations": fitted["iterations"],
        "holdout": {"views": len(metrics["views"]), "psnr": metrics["novel_view"]["psnr"],
                    "ssim": metrics["novel_view"]["ssim"], "coverage_iou": metrics["coverage_iou"],
                    "eval_s": round(eval_s, 1)},
    }
    stages = record["stages_s"]
    stages["other (loading, undistortion, start-up)"] = round(
        wall - stages["neus_train"] - stages["neus_hull"] - stages["mesh_export"] - stages["materials"], 1)
    for k, v in stages.items():
        print(f"{k:40s} {v:8.1f} s")
    print(f"{'whole fit (wall)':40s} {wall:8.1f} s   peak memory {record['peak_rss_gb']:.2f} GB")
    print(f"held-out views: {record['holdout']['views']}, PSNR {record['holdout']['psnr']:.2f} dB, "
          f"SSIM {record['holdout']['ssim']:.4f}")
    out = Path(args.output)
    out.mkdir(parents=True, exist_ok=True)
    path = write_result(out / f"real_capture_{provenance()['commit']}.json", record)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
