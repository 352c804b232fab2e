#!/usr/bin/env python
"""Where the metallic prior's reading weakens the prior, per true material of a bundled scene:
the images' highlights alone (the reading before the first step) against the same reading kept
only where a highlight sits about the mirror direction of a light (`vq_mitsuba.engine.evidence`):
the scene's true light, and the light each given run learned (its envmap.exr).

    python benchmarks/highlight_reading.py DATASET [RUN ...] [--seed 0] [--json OUT.json]
    python benchmarks/highlight_reading.py data/sunlit runs/sunlit_s0

DATASET: a folder written by `vq-mitsuba make-scene` (its scene.xml, scene.json and meshes/).
Each hit is given the material of the nearest vertex of the scene's shapes. Prints, per material,
the share of its hits whose metallic term is weakened and their mean weight; writes them with the
command, commit, machine and versions to --json.
"""

from __future__ import annotations

import argparse
import copy
import json
from pathlib import Path

import numpy as np
import torch

from provenance import provenance, write_json


def material_of_hits(dataset: Path, positions: np.ndarray) -> tuple[np.ndarray, list[str]]:
    """(P,) index into the scene's material names of each hit's nearest shape vertex; the names."""
    import trimesh
    from scipy.spatial import cKDTree

    spec = json.loads((dataset / "scene.json").read_text())
    names = [m["name"] for m in spec["materials"]]
    verts, ids = [], []
    for shape in spec["shapes"]:
        mesh = trimesh.load(dataset / shape["file"], process=False)
        verts.append(np.asarray(mesh.vertices))
        ids.append(np.full(len(mesh.vertices), names.index(shape["material"])))
    _, nearest = cKDTree(np.concatenate(verts)).query(positions)
    return np.concatenate(ids)[nearest], names


def per_material(weight: torch.Tensor, material: np.ndarray, names: list[str]) -> dict:
    w = weight.numpy()
    return {name: {"hits": int((material == k).sum()), "share_weakened": float((w[material == k] < 1).mean()),
                   "mean_weight": float(w[material == k].mean())}
            for k, name in enumerate(names) if (material == k).any()}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("dataset", type=Path, help="a bundled scene's folder (make-scene's output)")
    parser.add_argument("runs", type=Path, nargs="*", help="finished fits of it whose learned light is read")
    parser.add_argument("--seed", type=int, default=0, help="train.seed of the reading's draws")
    parser.add_argument("--json", type=Path, help="write the figures here")
    args = parser.parse_args(argv)

    from vq_mitsuba.backend import init_mitsuba
    from vq_mitsuba.config import load_config
    from vq_mitsuba.data.captures import load_capture
    from vq_mitsuba.data.envmaps import load_envmap
    from vq_mitsuba.data.pixels import trace_training_pixels
    from vq_mitsuba.engine import evidence
    from vq_mitsuba.render.shading import scene_for_mesh

    init_mitsuba()
    cfg = load_config(None, [f"train.seed={args.seed}"])
    capture = load_capture(args.dataset / "scene.xml", split="train")
    true_light = load_envmap(args.dataset / "envmaps" / "train.exr")
    scene = scene_for_mesh(capture.mesh, true_light, capture.envmap_to_world)
    pool, _ = trace_training_pixels(scene, capture, cfg.train.alpha_threshold)
    lights = {"images alone": None, "true light": torch.as_tensor(true_light)}
    lights.update({f"learned ({run.name})": torch.as_tensor(load_envmap(run / "envmap.exr", hdr_only=False))
                   for run in args.runs})
    images = evidence.PriorReading(scene, capture, pool, cfg, None)  # the views are read once
    material, names = material_of_hits(args.dataset, images.pos.numpy())
    out = {}
    for label, env in lights.items():
        reading = copy.copy(images)  # `read` replaces its tint, grid and decision, never changes them in place
        if env is not None:
            reading.read(env, None)
        weight = reading.grid(reading.pos) if reading.grid is not None else torch.ones(len(reading.pos))
        out[label] = {"per_material": per_material(weight, material, names),
                      **{k: v for k, v in reading.decision.items() if k not in ("reason",)}}
        print(f"{label}:")
        for name, row in out[label]["per_material"].items():
            print(f"  {name:16s} {row['hits']:6d} hits  weakened {100 * row['share_weakened']:5.1f} %  "
                  f"mean weight {row['mean_weight']:.2f}")
    if args.json:
        write_json(args.json, {"provenance": provenance(), "dataset": str(args.dataset), "readings": out})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
