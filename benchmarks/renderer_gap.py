#!/usr/bin/env python
"""How differently do Cycles and Mitsuba shade the same material? Re-render a Cycles dataset's
first test views with its true scene (scene_test.xml) in Mitsuba under the training envmap, and
print, per ground-truth material (gt/*_material.png), the ratio of the Cycles pixels' sum to
Mitsuba's, per linear RGB channel. A fit in Mitsuba's `principled` BSDF reproduces a Cycles
image only by moving the basecolor by about that ratio; where two materials' ratios differ, no
per-channel alignment of the basecolor (as `eval` does) removes the difference, and the
basecolor PSNR against the truth is capped.

    .venv/bin/python benchmarks/renderer_gap.py DATASET [--views 6] [--spp 256] [--json OUT.json]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from provenance import command_line, write_result


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("dataset", type=Path, help="a folder written by `vq-mitsuba make-scene --renderer cycles`")
    p.add_argument("--views", type=int, default=6, help="number of test views (default 6)")
    p.add_argument("--spp", type=int, default=256, help="samples per pixel of the Mitsuba re-render (default 256)")
    p.add_argument("--json", type=Path, help="also write the ratios here")
    args = p.parse_args(argv)

    import mitsuba as mi
    from noise_ceiling import true_scene

    from vq_mitsuba.eval.evaluate import load_ground_truth
    from vq_mitsuba.backend import init_mitsuba

    root = args.dataset
    for need in ("scene.json", "scene_test.xml", "envmaps/train.exr"):
        if not (root / need).is_file():
            p.error(f"{root}: no {need} (expected a dataset written by `vq-mitsuba make-scene`)")
    init_mitsuba()
    mi.set_log_level(mi.LogLevel.Error)
    meta = json.loads((root / "scene.json").read_text())
    names = {i + 1: m.get("name", f"material {i + 1}") for i, m in enumerate(meta.get("materials", []))}
    scene = mi.load_file(str(root / "scene_test.xml"))
    shapes = {s.id(): s for s in scene.shapes()}
    truth = true_scene(root, meta, shapes, "train")
    sums: dict[int, list[np.ndarray]] = {}
    for i, sensor in enumerate(scene.sensors()[:args.views]):
        mine = np.array(mi.render(truth, sensor=sensor, spp=args.spp, seed=11 + i))[..., :3]
        gt = load_ground_truth(root, sensor.id())
        if "material" not in gt:
            p.error(f"{root / 'gt' / (sensor.id() + '_material.png')}: missing (the per-material split needs "
                    "the dataset's material labels)")
        theirs, labels = gt["rgb"], gt["material"]
        for m in np.unique(labels):
            if m == 0:
                continue
            k = labels == m
            s = sums.setdefault(int(m), [np.zeros(3), np.zeros(3), 0])
            s[0] += theirs[k].sum(0)
            s[1] += mine[k].sum(0)
            s[2] += int(k.sum())
    rows = []
    print(f"{root} ({meta.get('renderer', 'mitsuba')} images), {args.views} test views, Mitsuba at {args.spp} spp; "
          "Cycles / Mitsuba per channel (linear):")
    for m, (theirs, mine, n) in sorted(sums.items()):
        mat = meta["materials"][m - 1] if 0 < m <= len(meta.get("materials", [])) else {}
        ratio = theirs / np.maximum(mine, 1e-12)
        rows.append({"id": m, "name": names.get(m, f"material {m}"), "pixels": n, "ratio_rgb": ratio.tolist(),
                     "metallic": mat.get("metallic"), "roughness": mat.get("roughness")})
        print(f"  {rows[-1]['name']:<18} metallic {mat.get('metallic')!s:<5} roughness {mat.get('roughness')!s:<5} "
              f"{n:>7} px: {ratio[0]:.3f} {ratio[1]:.3f} {ratio[2]:.3f}")
    if args.json:
        write_result(args.json, {
            "command": command_line(argv, __file__),
            "dataset": str(root), "renderer": meta.get("renderer", "mitsuba"), "views": args.views,
            "spp": args.spp, "materials": rows})
    return 0


if __name__ == "__main__":
    sys.exit(main())
