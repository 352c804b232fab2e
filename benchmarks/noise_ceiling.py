#!/usr/bin/env python
"""How close to the ground truth can a perfect fit get? Re-render a dataset's test views with
its true scene (scene_test.xml, materials known) in Mitsuba under its training envmap, at a given
spp and another seed, and print the PSNR against the dataset's images: the ceiling that the
dataset's own Monte Carlo noise puts on novel-view PSNR. With --envs, the same for the relit
views under those envmaps (`all`: every one under DATASET/relit/), the ceiling on `eval`'s
relighting PSNR; on a Cycles dataset it also holds the two renderers' model differences.

    python benchmarks/noise_ceiling.py DATASET [--spp 1024] [--views 6] [--envs all | NAME ...]
        [--json OUT.json]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from provenance import command_line, write_result


def true_scene(root: Path, meta: dict, shapes: dict, env_name: str):
    """The dataset's true shapes (from scene_test.xml) under its envmaps/ENV_NAME.exr, rendered as
    the dataset was: path tracing to its max_depth, the emitter hidden."""
    import mitsuba as mi

    from vq_mitsuba.data import envmaps
    from vq_mitsuba.data.imageio import read_exr

    env = read_exr(root / "envmaps" / f"{env_name}.exr")[..., :3]
    return mi.load_dict({"type": "scene", "integrator": {"type": "path", "max_depth": int(meta.get("max_depth", 4)),
                                                         "hide_emitters": True},
                         "envmap": envmaps.to_mitsuba_dict(env, blender_world=False), **shapes})


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("dataset", help="a folder written by `vq-mitsuba make-scene` (either renderer)")
    p.add_argument("--spp", type=int, default=1024, help="samples per pixel of the re-render (default 1024)")
    p.add_argument("--views", type=int, default=6, help="number of test views (default 6)")
    p.add_argument("--envs", nargs="*", default=[], metavar="NAME",
                   help="also the relit views under these envmaps (`all`: every one in DATASET/relit)")
    p.add_argument("--json", type=Path, help="also write the per-view PSNRs and their means here")
    args = p.parse_args(argv)

    import json

    import mitsuba as mi

    from vq_mitsuba.eval import metrics as M
    from vq_mitsuba.data.imageio import read_exr
    from vq_mitsuba.backend import init_mitsuba

    init_mitsuba()
    mi.set_log_level(mi.LogLevel.Error)  # not the sampler's note that it rounds spp up
    root = Path(args.dataset)
    meta = json.loads((root / "scene.json").read_text())
    scene = mi.load_file(str(root / "scene_test.xml"))
    shapes = {s.id(): s for s in scene.shapes()}
    sensors = scene.sensors()[:args.views]
    masks = [read_exr(root / "images" / f"{s.id()}.exr")[..., 3] > 0.5 for s in sensors]
    envs = sorted(d.name for d in (root / "relit").glob("*") if d.is_dir()) if args.envs == ["all"] else args.envs
    for name in envs:
        if not (root / "envmaps" / f"{name}.exr").is_file() or not (root / "relit" / name).is_dir():
            p.error(f"{root}: no envmaps/{name}.exr with relit/{name}/ views")
    summary = {}
    for name in ["train"] + envs:
        truth = true_scene(root, meta, shapes, name)
        values = []
        ref_dir = root / "images" if name == "train" else root / "relit" / name
        for i, (sensor, mask) in enumerate(zip(sensors, masks)):
            img = np.array(mi.render(truth, sensor=sensor, spp=args.spp, seed=7919 + i))
            gt = read_exr(ref_dir / f"{sensor.id()}.exr")
            values.append(M.psnr(M.srgb(img[..., :3]), M.srgb(gt[..., :3]), mask))
            if name == "train":
                print(f"{sensor.id()}: {values[-1]:.2f} dB")
        summary[name] = values
        print(f"{'view (train envmap)' if name == 'train' else 'relit ' + name}: median {np.median(values):.2f}, "
              f"mean {np.mean(values):.2f} dB over {len(values)} views")
    relit_mean = float(np.mean([np.mean(summary[n]) for n in envs])) if envs else None
    if envs:
        print(f"relit, mean over {len(envs)} envmaps of the per-view means (as `eval`): {relit_mean:.2f} dB")
    if args.json:
        write_result(args.json, {
            "command": command_line(argv, __file__),
            "dataset": str(root), "renderer": meta.get("renderer", "mitsuba"), "dataset_spp": meta.get("spp"),
            "spp": args.spp, "views": [s.id() for s in sensors],
            "psnr": {n: {"per_view": v, "mean": float(np.mean(v)), "median": float(np.median(v))}
                     for n, v in summary.items()},
            "relit_mean": relit_mean,
        }, indent=1)
    print(f"(re-render at {args.spp} spp against the dataset's {meta.get('spp')} spp images "
          f"({meta.get('renderer', 'mitsuba')}), foreground, sRGB, no scale alignment)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
