"""A capture fitted from its photos alone against the same capture fitted with its own cameras and masks.

    python benchmarks/photos_vs_posed.py --photos-run RUN_A --posed-run RUN_B --reference CAPTURE -o OUT.json

Both runs are made beforehand with `vq-mitsuba fit` (the same `--downscale` and `--holdout`) and
scored with `vq-mitsuba eval`. This script reads them and prints, beside the machine and versions:
- how many photos SfM placed and its mean reprojection error (`RUN_A/pose/pose.json`);
- the camera centres SfM found against the reference's, after the best similarity (Umeyama), as a
  share of the reference's object radius (`scale_mat_0` of a NeuS/IDR capture, else the cameras'
  distance to their centroid);
- each run's held-out novel-view PSNR / SSIM (with and without the residual) as `eval` scored it,
  and the wall time of each stage the runs recorded;
- with `--reference-masks`, both runs' held-out views rendered again and scored inside the
  reference's own masks (`mask/` or `masks/` of the reference capture), so that the photos run, which
  `eval` scores inside its own mesh's coverage, and the posed run are compared like for like.
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


def _reference_mask(folder: Path, name: str) -> Path:
    """The reference's mask of the view `name` (a NeuS/IDR capture numbers its views 000, 001...)."""
    for sub in ("mask", "masks"):
        for stem in ([f"{int(name):03d}", name] if name.isdigit() else [name]):
            for suffix in (".png", ".jpg", ".JPG"):
                if (folder / sub / (stem + suffix)).is_file():
                    return folder / sub / (stem + suffix)
    raise FileNotFoundError(f"no mask of view {name} under {folder}/mask or masks")


def held_out_in_reference_masks(run_dir: Path, reference: Path, spp: int = 64) -> dict:
    """Novel-view PSNR / SSIM of a run's held-out views inside the reference capture's masks."""
    from vq_mitsuba.data.imageio import read_mask
    from vq_mitsuba.data.resize import Shrink
    from vq_mitsuba.eval import metrics as M
    from vq_mitsuba.eval.evaluate import held_out_capture, straight_colours
    from vq_mitsuba.render.views import Renderer
    from vq_mitsuba.run.run_dir import RunDir

    run = RunDir(run_dir)
    held = held_out_capture(run)
    renderer = Renderer(run.load())
    rows = []
    for cam, image in zip(held.cameras, held.images):
        path = _reference_mask(reference, cam.name)
        mask = read_mask(path)
        mask = Shrink(1, max(image.shape[:2])).image(mask) if mask.shape != image.shape[:2] else mask
        mask = mask > 0.5
        physical, with_residual = straight_colours(renderer.render(cam, spp=spp))
        row = {"view": cam.name, "mask": path.name, **M.image_metrics(physical, image, mask)}
        if with_residual is not None:
            row.update({"residual_" + k: v for k, v in M.image_metrics(with_residual, image, mask).items()})
        rows.append(row)
    mean = lambda key: float(np.mean([r[key] for r in rows])) if rows and key in rows[0] else None  # noqa: E731
    return {"spp": spp, "psnr": mean("psnr"), "ssim": mean("ssim"), "residual_psnr": mean("residual_psnr"),
            "residual_ssim": mean("residual_ssim"), "views": rows}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--photos-run", type=Path, required=True, help="run fitted from the photos alone")
    parser.add_argument("--posed-run", type=Path, help="run fitted from the reference capture")
    parser.add_argument("--reference", type=Path, required=True, help="the capture with the reference cameras")
    parser.add_argument("-o", "--out", type=Path, required=True, help="JSON file written")
    parser.add_argument("--reference-masks", action="store_true",
                        help="also score both runs' held-out views inside the reference capture's masks")
    parser.add_argument("--spp", type=int, default=64, help="samples per pixel of those renders")
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
    if args.reference_masks:
        for key, run_dir in (("photos_run", args.photos_run), ("posed_run", args.posed_run)):
            if run_dir is not None:
                result[key]["in_reference_masks"] = held_out_in_reference_masks(run_dir, args.reference, args.spp)
    write_result(args.out, result)
    print(describe())
    c = result["centres"]
    print(f"placed {result['pose']['placed']} of {result['pose']['photos']}, "
          f"{result['pose']['mean_reprojection_error_px']} px; camera centres {100 * c['rms_share']:.2f} % RMS, "
          f"{100 * c['max_share']:.2f} % at most of the object radius ({c['matched']} views)")
    for key in ("photos_run", "posed_run"):
        if result[key]:
            scored = {k: v for k, v in result[key].items() if k != "in_reference_masks"}
            print(f"{key}: {json.dumps(scored)}")
            inside = result[key].get("in_reference_masks")
            if inside:
                print(f"{key} held-out inside the reference masks: {inside['psnr']:.2f} dB / {inside['ssim']:.3f}"
                      + (f" ({inside['residual_psnr']:.2f} dB with the residual)" if inside["residual_psnr"] else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
