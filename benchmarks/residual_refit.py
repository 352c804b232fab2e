"""Refit the residual of a finished run with this checkout's residual stage, then score its
held-out views with and without it (`vq-mitsuba eval`).

    python benchmarks/residual_refit.py RUN [--iterations N] [--spp S] [--gt DATASET] -o OUT.json

The run's materials and light are those of its checkpoint (frozen, as in the fit); its
residual.pt is replaced. The run must have held-out views (`fit --holdout K`), or a synthetic
dataset's test views are given (`--gt`). Prints and writes
the training hits' PSNR before and after, the residual's seconds, and the held-out PSNR/SSIM
without and with the residual.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from provenance import describe, provenance, write_result


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", help="a finished run directory with held-out views")
    ap.add_argument("--iterations", type=int, default=None, help="residual.iterations (default: the config's)")
    ap.add_argument("--spp", type=int, default=None, help="eval samples per pixel (default: render.spp)")
    ap.add_argument("--gt", help="score on this synthetic dataset's test views (eval --gt)")
    ap.add_argument("-o", "--output", required=True, help="result JSON")
    args = ap.parse_args(argv)
    record = provenance()

    from vq_mitsuba.cli import main as cli_main
    from vq_mitsuba.data.captures import open_capture
    from vq_mitsuba.engine.pipeline import load_training_capture
    from vq_mitsuba.engine.trainer import Trainer
    from vq_mitsuba.run.run_dir import RunDir

    run = RunDir(args.run)
    cfg = run.config()
    if args.iterations is not None:
        cfg.residual.iterations = args.iterations
    source = open_capture(run.info()["capture"], run.dir / RunDir.MESH, cfg.capture, run.undistorted_dir)
    capture = load_training_capture(source, run)
    trainer = Trainer(capture, run, cfg)
    trainer.resume(run.load_state(run.checkpoint_path))
    t0 = time.perf_counter()
    info = trainer.model.fit_residual(run, trainer.data, trainer.step)
    seconds = time.perf_counter() - t0
    metrics_path = Path(args.output).with_suffix(".metrics.json")
    eval_args = ["eval", str(run.dir), "--quiet", "-o", str(metrics_path)]
    if args.spp:
        eval_args += ["--spp", str(args.spp)]
    if args.gt:
        eval_args += ["--gt", args.gt]
    if cli_main(eval_args) != 0:
        print(f"eval of {run.dir} failed", file=sys.stderr)
        return 1
    metrics = json.loads(metrics_path.read_text())
    result = {"run": str(run.dir), "residual": info, "residual_seconds": seconds,
              "novel_view": metrics["novel_view"], "novel_view_residual": metrics["novel_view_residual"],
              "per_view": metrics.get("views") or metrics.get("per_view")}
    write_result(args.output, {**record, **result})
    print(describe(record))
    nv, nvr = metrics["novel_view"], metrics["novel_view_residual"]
    print(f"training hits kept aside: {info['psnr_check_hits_before']:.2f} -> {info['psnr_check_hits_after']:.2f} dB; "
          f"held out: {nv['psnr']:.2f} -> {nvr['psnr']:.2f} dB PSNR ({nvr['psnr'] - nv['psnr']:+.2f}), "
          f"SSIM {nv['ssim']:.3f} -> {nvr['ssim']:.3f}; residual {seconds:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
