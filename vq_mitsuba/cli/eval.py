"""`vq-mitsuba eval`: a run's scores against a synthetic dataset's ground truth or its held-out views
(`vq_mitsuba.eval.evaluate`)."""

from __future__ import annotations

import argparse
from pathlib import Path

from vq_mitsuba.cli.common import capture_flags, nonempty_path, output_option, positive_int
from vq_mitsuba.errors import InputError


def bandwidths(text: str) -> tuple[float, ...]:
    if text.strip().lower() in ("", "none", "off"):
        return ()
    try:
        values = tuple(float(x) for x in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not a comma-separated list of numbers") from None
    if any(v <= 0 for v in values):
        raise argparse.ArgumentTypeError("bandwidths must be positive")
    return values


def add_parser(sub, shared) -> None:
    e = sub.add_parser(
        "eval", parents=[shared["threads"], shared["device"], output_option("metrics JSON path (default: RUN_DIR/metrics.json)"),
                         shared["quiet"], shared["size"]],
        help="score a fitted run: its held-out views, or a synthetic dataset's ground truth (--gt)",
        description="Render the dataset's test views and compare inside the ground-truth "
                    "foreground: novel-view PSNR/SSIM, basecolor PSNR/SSIM after per-channel scale alignment, "
                    "metallic/roughness PSNR, and relighting PSNR/SSIM under each held-aside envmap (albedo-scale "
                    "and image-scale variants). DATASET is a folder written by `vq-mitsuba make-scene` "
                    "(its test cameras, gt/, relit/ and envmaps/); without --gt, the run's "
                    "held-out views (fit --holdout K) are scored, at the fit's size unless --downscale / "
                    "--max-size say otherwise. The MeanShift baseline segments the continuous branch's BRDF maps "
                    "(it needs ground-truth material ids).")
    e.add_argument("run_dir", help="a run directory written by `vq-mitsuba fit`")
    e.add_argument("--gt", type=nonempty_path, metavar="DATASET", help="the ground-truth dataset folder (default: the held-out views)")
    e.add_argument("--spp", type=positive_int, help="render samples per pixel (default: render.spp of the run's config)")
    e.add_argument("--scale", choices=["lstsq", "median"], default="lstsq",
                   help="basecolor scale alignment: lstsq (NeRFactor) or median (TensoIR)")
    e.add_argument("--meanshift", type=bandwidths, default=(0.2, 0.3, 0.5), metavar="BW,BW,...",
                   help="MeanShift baseline bandwidths (default 0.2,0.3,0.5; 'none' skips it)")
    e.set_defaults(func=run)


def run(args) -> int:
    from vq_mitsuba.eval.evaluate import evaluate, evaluate_holdout, format_table
    from vq_mitsuba.run.outputs import check_metrics_file
    from vq_mitsuba.run.run_dir import RunDir, check_writable

    if args.output is not None:
        check_metrics_file(args.output)
    check_writable(Path(args.output).parent if args.output else args.run_dir)
    size = {k: getattr(args, k) for k in ("downscale", "max_size") if getattr(args, k) is not None}
    capture_flags(args)  # checked before any work
    if args.gt is not None and size:
        raise InputError(None, "--downscale and --max-size resize the held-out photos of a real capture (eval "
                               "without --gt); a synthetic dataset's ground truth is scored at its own size")
    if args.gt is None:  # a real capture: the held-out views
        metrics = evaluate_holdout(args.run_dir, spp=args.spp, output=args.output, **size)
        print(f"held-out views ({len(metrics['views'])}): novel view PSNR {metrics['novel_view']['psnr']:.2f} dB, "
              f"SSIM {metrics['novel_view']['ssim']:.4f} (inside the masks)")
    else:
        metrics = evaluate(args.run_dir, args.gt, spp=args.spp, scale_method=args.scale,
                           output=args.output, meanshift_bandwidths=args.meanshift)
        print(format_table(metrics))
    print(f"metrics written to {args.output or RunDir(args.run_dir) / RunDir.METRICS}")
    return 0
