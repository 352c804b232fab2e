#!/usr/bin/env python
"""Mean over seeds of bench_time_error.py runs (one --out folder per seed), as a markdown table.

    python benchmarks/seed_means.py benchmarks/out/default_vs_continuous_s0 benchmarks/out/default_vs_continuous_s1

Prints per scene and method the mean of each figure over the seeds, M found / true, and the
difference of each method's basecolor and relighting PSNR to the last method's.
"""

from __future__ import annotations

import argparse
import json
import statistics
from pathlib import Path

KEYS = [("basecolor_psnr", "basecolor PSNR"), ("relit_psnr", "relighting PSNR"), ("novel_psnr", "novel view PSNR"),
        ("metallic_psnr", "metallic PSNR"), ("roughness_psnr", "roughness PSNR"), ("seg_micro_f1", "seg. micro-F1"),
        ("iterations", "steps")]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("outs", nargs="+", type=Path, help="bench_time_error.py --out folders, one per seed")
    args = ap.parse_args(argv)
    runs = [json.loads((o / "time_error.json").read_text()) for o in args.outs]
    methods, scenes = runs[0]["methods"], runs[0]["scenes"]
    rows = {}
    for run in runs:
        for r in run["rows"]:
            rows.setdefault((r["scene"], r["method"]), []).append(r)
    print(f"Mean of {len(runs)} seeds ({', '.join(str(o) for o in args.outs)})\n")
    print("| scene | method | " + " | ".join(label for _, label in KEYS) + " | M found (true) per seed |")
    print("|---|---|" + "---:|" * (len(KEYS) + 1))
    for scene in scenes:
        for m in methods:
            rs = rows.get((scene, m), [])
            cells = []
            for k, _ in KEYS:
                vals = [r[k] for r in rs if isinstance(r.get(k), (int, float))]
                cells.append(f"{statistics.mean(vals):.3f}" if k == "seg_micro_f1" and vals else
                             f"{statistics.mean(vals):.0f}" if k == "iterations" and vals else
                             f"{statistics.mean(vals):.2f}" if vals else "-")
            found = ", ".join(f"{r.get('materials_found')} ({r.get('materials_true')})" for r in rs
                              if r.get("materials_found") is not None) or "-"
            print(f"| {scene} | {m} | " + " | ".join(cells) + f" | {found} |")
    ref = methods[-1]
    print(f"\nDifference to `{ref}` (dB, mean over seeds):\n")
    for scene in scenes:
        for m in methods[:-1]:
            parts = []
            for k in ("basecolor_psnr", "relit_psnr"):
                a = [r[k] for r in rows.get((scene, m), [])]
                b = [r[k] for r in rows.get((scene, ref), [])]
                if a and b:
                    parts.append(f"{k} {statistics.mean(a) - statistics.mean(b):+.2f}")
            print(f"- {scene}, {m}: " + ", ".join(parts))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
