"""Shading-normal error of reconstructed meshes against a bundled dataset's true mesh, per object.

    .venv/bin/python benchmarks/normal_errors.py DATASET MESH [MESH ...] [--views test] [--json OUT]

Two measures, both in degrees (mean / median / p90):
- surface: samples spread evenly over the predicted surface, each against its nearest true sample
  (`vq_mitsuba.geometry.mesh.mesh_metrics`); hidden faces count as much as seen ones;
- in view: every pixel of the dataset's test (or training) cameras where both meshes are hit
  (`vq_mitsuba.eval.normals.view_normal_errors`): the surface as the material stage sees it.
Objects come from the dataset's scene.json.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from provenance import write_result


def score(mesh_path: Path, dataset: Path, views: str, gt=None) -> dict:
    """Both measures for one mesh (`gt`: the dataset's mesh.ply when already loaded)."""
    from vq_mitsuba.data.captures import load_capture, load_mesh
    from vq_mitsuba.eval.normals import scene_object_labels, view_normal_errors
    from vq_mitsuba.geometry.mesh import mesh_metrics

    gt = load_mesh(dataset / "mesh.ply") if gt is None else gt
    pred = load_mesh(mesh_path)
    labels = scene_object_labels(dataset)
    lab, names = labels if labels else (None, None)
    surface = mesh_metrics(pred, gt, gt_face_labels=lab, label_names=names)
    cams = load_capture(dataset / f"transforms_{views}.json").cameras
    view = view_normal_errors(pred, gt, cams, lab, names)
    return {"mesh": str(mesh_path), "surface": surface, "view": view}


def table(results: list[dict]) -> str:
    lines = []
    for r in results:
        s, v = r["surface"], r["view"]
        lines += [f"{r['mesh']}: Chamfer {100 * s['chamfer_rel']:.3f} % of the diagonal, in-view coverage "
                  f"{100 * v['coverage']:.1f} %", "",
                  "| object | surface mean / median / p90 (deg) | in view mean / median / p90 (deg) | pixels |",
                  "|---|---|---|---:|",
                  f"| all | {s['shading_normal_deg_mean']:.1f} / {s['shading_normal_deg_median']:.1f} / "
                  f"{s['shading_normal_deg_p90']:.1f} | {v['mean']:.1f} / {v['median']:.1f} / {v['p90']:.1f} | "
                  f"{v['count']} |"]
        for name, st in s.get("shading_normal_deg_by_object", {}).items():
            vo = v.get("by_object", {}).get(name, {})
            lines.append(f"| {name} | {st['mean']:.1f} / {st['median']:.1f} / {st['p90']:.1f} | "
                         f"{vo.get('mean', float('nan')):.1f} / {vo.get('median', float('nan')):.1f} / "
                         f"{vo.get('p90', float('nan')):.1f} | {vo.get('count', 0)} |")
        lines.append("")
    return "\n".join(lines)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("dataset", type=Path, help="bundled dataset folder (mesh.ply, scene.json, transforms_*.json)")
    p.add_argument("meshes", type=Path, nargs="+", help="reconstructed meshes (same world as the dataset)")
    p.add_argument("--views", choices=("test", "train"), default="test", help="cameras of the in-view measure")
    p.add_argument("--json", type=Path, default=None, help="write the figures to this JSON file")
    args = p.parse_args()
    results = [score(m, args.dataset, args.views) for m in args.meshes]
    print(table(results))
    if args.json:
        write_result(args.json, {"dataset": str(args.dataset), "views": args.views, "meshes": results})
    return 0


if __name__ == "__main__":
    sys.exit(main())
