"""Study: NeuS's learning-rate decay driven by the step share alone, against the share of whichever
budget (steps or seconds) runs out first (the default).

    .venv/bin/python benchmarks/neus_decay.py DATASET [--time-limit 240] [--iterations 4000] [--seed 0]

Both variants train NeuS on DATASET/transforms_train.json (images and alpha masks) under the same
step and time budget, one after the other, and their meshes are scored against DATASET/mesh.ply
(Chamfer, and shading-normal error in the test views, as `normal_errors.py`). The two decays
differ only when the time limit ends the training before the steps: then the default has decayed
fully, while the step-driven one stops at a large rate. A limit below the run's natural length
shows that case; with time to spare both give the same run. Writes
benchmarks/out/neus_decay/neus_decay_seed<SEED>.json.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from normal_errors import score
from provenance import write_result

from vq_mitsuba.config import load_config
from vq_mitsuba.data.captures import load_capture, load_mesh
from vq_mitsuba.geometry import neus as neus_module
from vq_mitsuba.messages import quiet

ROOT = Path(__file__).resolve().parent.parent


def run(variant: str, data: Path, out: Path, overrides: list[str], gt) -> dict:
    cfg = load_config(None, overrides).neus
    original = neus_module.lr_factor
    if variant == "step_share":
        neus_module.lr_factor = lambda c, step, share: original(c, step, min(step / c.iterations, 1.0))
    try:
        with quiet():
            result = neus_module.reconstruct(load_capture(data / "transforms_train.json"), out / variant, cfg)
    finally:
        neus_module.lr_factor = original
    s = result.summary
    result.mesh.export(out / variant / "mesh.ply")
    normals = score(out / variant / "mesh.ply", data, "test", gt=gt)
    row = {"variant": variant, "iterations": s["iterations"], "stopped_by_time_limit": s["stopped_by_time_limit"],
           "train_s": s["seconds"]["train"], "iterations_per_s_spread": s["iterations_per_s_spread"],
           "chamfer_rel": normals["surface"]["chamfer_rel"], "surface": normals["surface"],
           "in_view": normals["view"]}
    v = normals["view"]
    print(f"{variant}: {s['iterations']} steps in {s['seconds']['train']:.0f} s, Chamfer "
          f"{100 * row['chamfer_rel']:.3f}%, in-view normal error mean / median / p90 "
          f"{v['mean']:.1f} / {v['median']:.1f} / {v['p90']:.1f} deg", flush=True)
    return row


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset", type=Path, help="a make-scene dataset (transforms_train.json, mesh.ply)")
    ap.add_argument("--time-limit", type=float, default=240.0, help="NeuS training seconds of each variant")
    ap.add_argument("--iterations", type=int, default=4000, help="NeuS step budget of each variant")
    ap.add_argument("--seed", type=int, default=0, help="neus.seed of both variants")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks/out/neus_decay", help="output folder")
    args = ap.parse_args()
    overrides = [f"neus.time_limit_s={args.time_limit}", f"neus.iterations={args.iterations}", f"neus.seed={args.seed}"]
    gt = load_mesh(args.dataset / "mesh.ply")
    rows = [run(v, args.dataset, args.out, overrides, gt) for v in ("larger_share", "step_share")]
    write_result(args.out / f"neus_decay_seed{args.seed}.json", {
        "dataset": str(args.dataset), "time_limit_s": args.time_limit, "iterations": args.iterations,
        "seed": args.seed, "runs": rows})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
