#!/usr/bin/env python
"""How close to the ground truth can a perfect fit get? Re-render a dataset's test views with
its true scene (scene_test.xml, materials known) under its training envmap, at a given spp and
another seed, and print the PSNR against the dataset's images: the ceiling that the dataset's
own Monte Carlo noise puts on novel-view PSNR.

    python benchmarks/noise_ceiling.py DATASET [--spp 1024] [--views 6]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("dataset", help="a folder written by `vq-mitsuba make-scene` (Mitsuba renderer)")
    p.add_argument("--spp", type=int, default=1024, help="samples per pixel of the re-render (default 1024)")
    p.add_argument("--views", type=int, default=6, help="number of test views (default 6)")
    args = p.parse_args(argv)

    import json

    import mitsuba as mi

    from vq_mitsuba import envmaps
    from vq_mitsuba import metrics as M
    from vq_mitsuba.capture.imageio import read_exr
    from vq_mitsuba.rendering import init_mitsuba

    init_mitsuba()
    root = Path(args.dataset)
    meta = json.loads((root / "scene.json").read_text())
    scene = mi.load_file(str(root / "scene_test.xml"))
    env = read_exr(root / "envmaps" / "train.exr")[..., :3]
    d = {"type": "scene", "integrator": {"type": "path", "max_depth": int(meta.get("max_depth", 4)),
                                         "hide_emitters": True},
         "envmap": envmaps.to_mitsuba_dict(env, blender_world=False)}
    for s in scene.shapes():
        d[s.id()] = s
    truth = mi.load_dict(d)
    values = []
    for i, sensor in enumerate(scene.sensors()[:args.views]):
        img = np.array(mi.render(truth, sensor=sensor, spp=args.spp, seed=7919 + i))
        gt = read_exr(root / "images" / f"{sensor.id()}.exr")
        values.append(M.psnr(M.srgb(img[..., :3]), M.srgb(gt[..., :3]), gt[..., 3] > 0.5))
        print(f"{sensor.id()}: {values[-1]:.2f} dB")
    print(f"median over {len(values)} views: {np.median(values):.2f} dB (re-render at {args.spp} spp against "
          f"the dataset's {meta.get('spp')} spp images, foreground, sRGB)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
