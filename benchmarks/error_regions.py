"""Where a fitted run loses basecolor PSNR: silhouette band or interior, per material, and the
shading normals' error there.

    .venv/bin/python benchmarks/error_regions.py DATASET RUN_DIR [RUN_DIR ...] [--views 8] [--band 2]

For each run the first test views of DATASET are rendered (16 spp, 4 primary rays per pixel) and
its basecolor is aligned per channel (least squares, as `eval`). Inside the ground-truth mask,
pixels within --band pixels of the silhouette form the band, the rest the interior. Printed per
run: basecolor PSNR (sRGB) of all / interior / band pixels, the band's share of the squared
error, the share of foreground pixels the run's geometry misses, and the angle between the
rendered and the true world normals in the interior; then per ground-truth material its interior
basecolor PSNR and normal error; then the interior split at the true basecolor's edges (pixels
where its sRGB gradient exceeds --edge, e.g. a texture's stripes, where a surface slightly off
the truth shows the texture shifted from view to view), and the interior away from those edges
binned by normal error: each bin's share of the pixels, basecolor PSNR and share of the squared
error. Meant for comparing a run on a reconstructed mesh with one on the
true mesh (`bench_geometry.py --materials` leaves both).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np


def angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    cos = (a * b).sum(-1) / (np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1) + 1e-9)
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def psnr_of(se: list[np.ndarray]) -> float:
    e = np.concatenate(se)
    return float("nan") if e.size == 0 else float(-10 * np.log10(max(e.mean(), 1e-12)))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("dataset", type=Path)
    ap.add_argument("runs", type=Path, nargs="+")
    ap.add_argument("--views", type=int, default=8, help="first test views used")
    ap.add_argument("--band", type=int, default=2, help="silhouette band width in pixels")
    ap.add_argument("--edge", type=float, default=0.05,
                    help="gradient of the true sRGB basecolor (per pixel) above which a pixel is a texture edge")
    args = ap.parse_args()

    from scipy import ndimage

    from vq_mitsuba.eval import metrics as M
    from vq_mitsuba.data.captures import load_cameras
    from vq_mitsuba.eval.evaluate import RunPredictor, dataset_root, load_ground_truth
    from vq_mitsuba.data.cameras import MITSUBA_TO_BLENDER
    from vq_mitsuba.data.cameras import convert_world

    root = dataset_root(args.dataset)
    cameras, cam_world, _ = load_cameras(root / "transforms_test.json")
    cameras = cameras[: args.views]
    gts = [load_ground_truth(root, c.name) for c in cameras]
    masks = np.stack([g["mask"] for g in gts])
    inner = [ndimage.binary_erosion(g["mask"], iterations=args.band) for g in gts]
    for run in args.runs:
        pred = RunPredictor(run)
        renderer = pred.renderer(None)
        maps = [renderer.render(convert_world(c, cam_world, pred.world), spp=16, aa=4, seed=i)
                for i, c in enumerate(cameras)]
        _, scale = M.scale_align(np.stack([m["basecolor"] for m in maps]), np.stack([g["basecolor"] for g in gts]),
                                 masks, method="lstsq")
        err = [((M.srgb(m["basecolor"] * scale) - M.srgb(g["basecolor"])) ** 2).mean(-1) for m, g in zip(maps, gts)]
        normals = [m["normal"] @ MITSUBA_TO_BLENDER.T if pred.world == "mitsuba" else m["normal"] for m in maps]
        band_se = [e[g["mask"] & ~i] for e, g, i in zip(err, gts, inner)]
        all_se = [e[g["mask"]] for e, g in zip(err, gts)]
        missed = np.mean([((m["alpha"] < 0.5) & g["mask"]).sum() / max(g["mask"].sum(), 1) for m, g in zip(maps, gts)])
        ang = np.concatenate([angle_deg(n[i], g["normal"][i]) for n, g, i in zip(normals, gts, inner)])
        print(f"{run}: basecolor PSNR all {psnr_of(all_se):.2f}, interior {psnr_of([e[i] for e, i in zip(err, inner)]):.2f}, "
              f"band {psnr_of(band_se):.2f} dB; band share of the squared error "
              f"{np.concatenate(band_se).sum() / max(np.concatenate(all_se).sum(), 1e-12):.2f}; foreground missed "
              f"{100 * missed:.2f} %; interior normal error median {np.median(ang):.2f} deg, p90 {np.percentile(ang, 90):.2f} deg")
        for k in sorted(int(x) for x in np.unique(np.concatenate([g["material"][g["mask"]] for g in gts])) if x > 0):
            sel = [i & (g["material"] == k) for g, i in zip(gts, inner)]
            a = np.concatenate([angle_deg(n[s], g["normal"][s]) for n, g, s in zip(normals, gts, sel)])
            print(f"    material {k}: interior basecolor PSNR {psnr_of([e[s] for e, s in zip(err, sel)]):.2f} dB, "
                  f"normal error median {np.median(a):.2f} deg, p90 {np.percentile(a, 90):.2f} deg")
        edges = [np.hypot(*np.gradient(M.srgb(g["basecolor"]).mean(-1))) > args.edge for g in gts]
        total = max(sum(e[i].sum() for e, i in zip(err, inner)), 1e-12)
        on = [e[i & d] for e, i, d in zip(err, inner, edges)]
        off = [e[i & ~d] for e, i, d in zip(err, inner, edges)]
        print(f"    interior on texture edges ({100 * sum(x.size for x in on) / max(sum(i.sum() for i in inner), 1):.1f} % "
              f"of its pixels): basecolor PSNR {psnr_of(on):.2f} dB, {sum(x.sum() for x in on) / total:.2f} of its "
              f"squared error; away from them {psnr_of(off):.2f} dB")
        ang_off = np.concatenate([angle_deg(n[i & ~d], g["normal"][i & ~d]) for n, g, i, d in zip(normals, gts, inner, edges)])
        se_off = np.concatenate(off)
        for lo, hi in ((0, 1), (1, 2), (2, 4), (4, 8), (8, 180)):
            sel = (ang_off >= lo) & (ang_off < hi)
            if sel.any():
                print(f"      normal error {lo}-{hi} deg: {100 * sel.mean():.1f} % of those pixels, basecolor PSNR "
                      f"{psnr_of([se_off[sel]]):.2f} dB, {se_off[sel].sum() / total:.2f} of the interior's squared error")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
