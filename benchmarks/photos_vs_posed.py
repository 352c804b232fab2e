"""A capture fitted from its photos alone against the same capture fitted with its own cameras and masks.

    python benchmarks/photos_vs_posed.py --photos-run RUN_A --posed-run RUN_B --reference CAPTURE -o OUT.json

Both runs are made beforehand with `vq-mitsuba fit` (the same `--downscale` and `--holdout`) and
scored with `vq-mitsuba eval`. This script reads them and prints, beside the machine and versions:
- how many photos SfM placed and its mean reprojection error (`RUN_A/pose/pose.json`);
- the camera centres SfM found against the reference's, after the best similarity (Umeyama), as a
  share of the reference's object radius (`scale_mat_0` of a NeuS/IDR capture, else the cameras'
  distance to their centroid);
- each run's held-out novel-view PSNR / SSIM (with and without the residual) and the wall time of
  each stage the runs recorded.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from provenance import command_line, describe, write_result


def umeyama(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """The similarity (s, R, t) taking src (N, 3) closest to dst in the least-squares sense."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    u, sig, vt = np.linalg.svd(xd.T @ xs / len(src))
    d = np.eye(3)
    d[2, 2] = np.sign(np.linalg.det(u @ vt))
    r = u @ d @ vt
    s = float(np.trace(np.diag(sig) @ d) / (xs ** 2).sum(1).mean())
    return s, r, mu_d - s * r @ mu_s


def _json(path: Path) -> dict:
    return json.loads(path.read_text()) if path.is_file() else {}


def _run_figures(run: Path) -> dict:
    metrics, fit, geometry = _json(run / "metrics.json"), _json(run / "fit.json"), _json(run / "geometry.json")
    pose = _json(run / "pose" / "pose.json")
    return {
        "novel_view": metrics.get("novel_view"), "novel_view_residual": metrics.get("novel_view_residual"),
        "seconds": {"pose": (pose.get("seconds") or {}).get("total"),
                    "neus": (geometry.get("seconds") or {}).get("total"), "materials": fit.get("seconds")},
        "neus_iterations": geometry.get("iterations"), "neus_stopped_by_time_limit": geometry.get("stopped_by_time_limit"),
        "fit_iterations": fit.get("iterations"),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--photos-run", type=Path, required=True, help="run fitted from the photos alone")
    parser.add_argument("--posed-run", type=Path, help="run fitted from the reference capture")
    parser.add_argument("--reference", type=Path, required=True, help="the capture with the reference cameras")
    parser.add_argument("-o", "--out", type=Path, required=True, help="JSON file written")
    args = parser.parse_args(argv)

    from vq_mitsuba.data.captures import load_cameras

    found = {c.name: c.origin for c in load_cameras(args.photos_run / "pose")[0]}
    reference = load_cameras(args.reference)[0]
    # a NeuS/IDR capture names its views 000, 001 ...; the photos keep their file stems
    by_index = {int(n): n for n in found if n.isdigit()}
    truth = {by_index.get(int(c.name), c.name) if c.name.isdigit() else c.name: c.origin for c in reference}
    names = sorted(set(found) & set(truth))
    src, dst = np.array([found[n] for n in names]), np.array([truth[n] for n in names])
    s, r, t = umeyama(src, dst)
    errors = np.linalg.norm(src @ (s * r).T + t - dst, axis=1)
    npz = args.reference / "cameras_sphere.npz" if args.reference.is_dir() else args.reference
    if npz.suffix == ".npz" and npz.is_file():
        radius = float(np.load(npz)["scale_mat_0"][0, 0])
    else:
        radius = float(np.linalg.norm(dst - dst.mean(0), axis=1).mean())
    pose = _json(args.photos_run / "pose" / "pose.json")
    result = {
        "command": command_line(argv, __file__),
        "pose": {"placed": pose.get("registered"), "photos": pose.get("images"),
                 "mean_reprojection_error_px": pose.get("mean_reprojection_error_px"),
                 "matcher": pose.get("matcher"), "seconds": pose.get("seconds")},
        "centres": {"matched": len(names), "object_radius": radius,
                    "rms_share": float(np.sqrt((errors ** 2).mean()) / radius),
                    "median_share": float(np.median(errors) / radius), "max_share": float(errors.max() / radius)},
        "photos_run": _run_figures(args.photos_run),
        "posed_run": _run_figures(args.posed_run) if args.posed_run else None,
    }
    write_result(args.out, result)
    print(describe())
    c = result["centres"]
    print(f"placed {result['pose']['placed']} of {result['pose']['photos']}, "
          f"{result['pose']['mean_reprojection_error_px']} px; camera centres {100 * c['rms_share']:.2f} % RMS, "
          f"{100 * c['max_share']:.2f} % at most of the object radius ({c['matched']} views)")
    for key in ("photos_run", "posed_run"):
        if result[key]:
            print(f"{key}: {json.dumps(result[key])}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
