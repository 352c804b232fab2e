"""How each object's metallic and roughness evolve during a fit: reads a run's snapshots.

    .venv/bin/vq-mitsuba fit benchmarks/out/data/balls/scene.xml -o runs/traj \\
        --set train.time_limit_s=600 --set train.snapshot_s=$(seq -s, 30 30 600)
    .venv/bin/python benchmarks/material_trajectory.py runs/traj benchmarks/out/data/balls [--every 1]

For a bundled synthetic scene (make-scene output: scene.xml names each shape's mesh file and
material), points are sampled on every shape's true surface and the run's continuous field is
queried there at each snapshot. Printed per snapshot: fit seconds, step, the metallic gate
(`field.metallic_delay`), then per material the mean metallic before the gate (what the network
would give with the gate open) and the mean roughness, and the brightest envmap texel.
"""

from __future__ import annotations

import argparse
import re
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run", type=Path, help="run directory with snapshots/ (train.snapshot_s)")
    ap.add_argument("dataset", type=Path, help="the make-scene dataset the run was fitted to")
    ap.add_argument("--every", type=int, default=1, help="print every n-th snapshot")
    ap.add_argument("--points", type=int, default=1500, help="surface samples per shape")
    args = ap.parse_args()

    import torch
    import trimesh

    from vq_mitsuba.errors import InputError
    from vq_mitsuba.render.views import load_run

    snaps = sorted((args.run / "snapshots").glob("*.pt"))
    if not snaps:
        raise InputError(args.run / "snapshots", "no snapshots: fit with --set train.snapshot_s=...")
    points: dict[str, list] = {}
    for shape in ET.parse(args.dataset / "scene.xml").getroot().findall("shape"):
        fn, ref = shape.find("string"), shape.find("ref")
        if fn is None or ref is None:
            continue
        mesh = trimesh.load(args.dataset / fn.get("value"), process=False)
        pts, _ = trimesh.sample.sample_surface(mesh, args.points, seed=0)
        points.setdefault(ref.get("id").removeprefix("mat_"), []).append(pts)
    names = list(points)
    pts = {n: torch.tensor(np.concatenate(p), dtype=torch.float32) for n, p in points.items()}
    print("| s | step | gate | " + " | ".join(f"{n} m / r" for n in names) + " | env max |")
    print("|---:|---:|---:|" + "---:|" * len(names) + "---:|")
    name = re.compile(r"t([\d.]+)s_step\d+\.pt")  # fit.py's snapshot names
    rows = [(p, "%.0f" % float(name.fullmatch(p.name).group(1))) for p in snaps[:: max(args.every, 1)]]
    final = args.run / "checkpoint.pt"
    if final.is_file():  # the finished (or latest) state, as the last row
        rows.append((final, "end"))
    for path, seconds in rows:
        fitted = load_run(args.run, path)
        model = fitted.model
        gate = float(model.metallic_gate)
        model.metallic_gate.fill_(1.0)
        cells = []
        with torch.no_grad():
            for n in names:
                o = model(pts[n].to(model.center.device))
                cells.append(f"{float(o['metallic'].mean()):.2f} / {float(o['roughness'].mean()):.2f}")
        env_max = float(fitted.envmap.max())
        print(f"| {seconds} | {fitted.step} | {gate:.2f} | " + " | ".join(cells) + f" | {env_max:.1f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
