"""Pool the material-stage pairs of several geometry benchmark reports: per scene and NeuS run
(its output folder), each seed's basecolor on the NeuS mesh and on the true mesh, and the mean
gap. One seed's gap is as noisy as the material stage (on Cycles `demo` the true mesh alone gave
38.2 to 40.6 dB at one seed), so the mean over seeds, pooled across reports, is the figure to
quote.

    .venv/bin/python benchmarks/geometry_summary.py benchmarks/results/geometry_cycles_demo_*.json

A NeuS run's settings are read from its geometry.json when the folder is still there.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("reports", type=Path, nargs="+", help="geometry_*.json files written by bench_geometry.py")
    args = ap.parse_args()
    groups: dict[tuple[str, str], list[tuple[str, dict]]] = defaultdict(list)
    used = []
    for path in args.reports:
        try:
            report = json.loads(path.read_text())
        except (OSError, json.JSONDecodeError) as exc:
            print(f"{path}: not a readable geometry report ({exc})", file=sys.stderr)
            return 2
        for scene in report.get("scenes", []):
            for row in scene.get("materials", []):
                groups[(scene["scene"], scene["run"])].append((path.name, row))
                if path.name not in used:
                    used.append(path.name)
    if not groups:
        print("no material-stage pairs in these reports (run bench_geometry.py with --materials)", file=sys.stderr)
        return 1
    print("| scene | NeuS run | reflect | seeds | basecolor NeuS (mean) | basecolor true (mean) | gap per seed | mean gap |")
    print("|---|---|---|---|---:|---:|---|---:|")
    for (scene, run), rows in sorted(groups.items()):
        rows.sort(key=lambda r: r[1]["seed"])
        geo = Path(run) / "geometry.json"
        reflect = json.loads(geo.read_text())["config"].get("reflect", False) if geo.is_file() else "?"
        gaps = [r["basecolor_gap_db"] for _, r in rows]
        shown = Path(run).relative_to(ROOT) if Path(run).is_relative_to(ROOT) else run
        print(f"| {scene} | {shown} | {reflect} | {', '.join(str(r['seed']) for _, r in rows)} | "
              f"{np.mean([r['neus']['basecolor_psnr'] for _, r in rows]):.2f} | "
              f"{np.mean([r['true']['basecolor_psnr'] for _, r in rows]):.2f} | "
              f"{', '.join(f'{g:.2f}' for g in gaps)} | **{np.mean(gaps):.2f}** |")
    print("\nFrom: " + ", ".join(used))
    return 0


if __name__ == "__main__":
    sys.exit(main())
