#!/usr/bin/env python
"""How close to the ground truth can a perfect fit get? Re-render a dataset's test views with
its true scene (scene_test.xml, materials known) in Mitsuba under its training envmap, at a given
spp and another seed, and print the PSNR against the dataset's images: the ceiling that the
dataset's own Monte Carlo noise puts on novel-view PSNR. With --envs, the same for the relit
views under those envmaps (`all`: every one under DATASET/relit/), the ceiling on `eval`'s
relighting PSNR; on a Cycles dataset it also holds the two renderers' model differences.
With --roughness MATERIAL=R1,R2,..., the same views re-rendered with that material's roughness
at each value, scored on its pixels alone: how far a wrong roughness shows in the views beside
the noise (on a Mitsuba dataset, the truth's own score is the noise ceiling).

    python benchmarks/noise_ceiling.py DATASET [--spp 1024] [--views 6] [--envs all | NAME ...]
        [--roughness MATERIAL=R1,R2 ...] [--json OUT.json]
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


def roughness_scores(root: Path, meta: dict, shapes: dict, sensors, masks, specs: list[str], spp: int, parser) -> dict:
    """{material: {"truth": r, "pixels": n, "psnr": {value: dB}}}: the test views under the training
    envmap with the material's roughness at each value, scored on its pixels (gt/<view>_material.png)."""
    import imageio.v3 as iio
    import mitsuba as mi

    from vq_mitsuba.data.imageio import read_exr
    from vq_mitsuba.eval import metrics as M

    materials = {m["name"]: m for m in meta["materials"]}
    out = {}
    for spec in specs:
        name, _, values = spec.partition("=")
        if name not in materials:
            parser.error(f"--roughness {spec}: {root / 'scene.json'} has no material '{name}' "
                         f"(it has {', '.join(materials)})")
        try:
            values = [float(v) for v in values.split(",") if v.strip()]
        except ValueError:
            parser.error(f"--roughness {spec}: expects MATERIAL=R1,R2,... with numbers")
        truth = true_scene(root, meta, shapes, "train")
        params = mi.traverse(truth)
        keys = [f"{sh['name']}.bsdf.roughness.value" for sh in meta["shapes"] if sh["material"] == name]
        if not keys or any(k not in params for k in keys):
            parser.error(f"--roughness {spec}: the shapes of {name} have no plain roughness to vary")
        sel = [m & (np.asarray(iio.imread(root / "gt" / f"{s.id()}_material.png")) == materials[name]["id"])
               for s, m in zip(sensors, masks)]
        gts = [read_exr(root / "images" / f"{s.id()}.exr")[..., :3] for s in sensors]
        n_pixels = sum(int(m.sum()) for m in sel)
        scores = {}
        for value in values:
            for k in keys:
                params[k] = value
            params.update()
            imgs = [np.array(mi.render(truth, sensor=s, spp=spp, seed=7919 + i))[..., :3]
                    for i, s in enumerate(sensors)]
            pred = np.concatenate([M.srgb(im)[m] for im, m in zip(imgs, sel)])
            ref = np.concatenate([M.srgb(g)[m] for g, m in zip(gts, sel)])
            scores[f"{value:g}"] = float(10 * np.log10(1.0 / np.mean((pred - ref) ** 2)))
            print(f"{name} at roughness {value:g} (truth {materials[name]['roughness']:g}): "
                  f"{scores[f'{value:g}']:.2f} dB on its {n_pixels} pixels")
        out[name] = {"truth": materials[name]["roughness"], "pixels": n_pixels, "psnr": scores}
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("dataset", help="a folder written by `vq-mitsuba make-scene` (either renderer)")
    p.add_argument("--spp", type=int, default=1024, help="samples per pixel of the re-render (default 1024)")
    p.add_argument("--views", type=int, default=6, help="number of test views (default 6)")
    p.add_argument("--envs", nargs="*", default=[], metavar="NAME",
                   help="also the relit views under these envmaps (`all`: every one in DATASET/relit)")
    p.add_argument("--roughness", action="append", default=[], metavar="MATERIAL=R1,R2",
                   help="also render with this material's roughness at each value, scored on its pixels")
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
    by_roughness = roughness_scores(root, meta, shapes, sensors, masks, args.roughness, args.spp, p)
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
            "relit_mean": relit_mean, "roughness": by_roughness,
        }, indent=1)
    print(f"(re-render at {args.spp} spp against the dataset's {meta.get('spp')} spp images "
          f"({meta.get('renderer', 'mitsuba')}), foreground, sRGB, no scale alignment)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
