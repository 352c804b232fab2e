"""Benchmark of the geometry stage: NeuS + mesh export on the bundled scenes, time against Chamfer.

    .venv/bin/python benchmarks/bench_geometry.py [--scenes demo texture balls] [--time-limit 600]
        [--checkpoint-every 60] [--resolution 128] [--n-train 64] [--test-views 4] [--set neus.key=value ...]

For each scene: a dataset with N training views at R x R (DATA/NAME with --data, e.g.
benchmarks/out/cycles128; otherwise data/NAME or data/geom_NAME when its scene.json matches,
else benchmarks/out/data/NAME, else generated into data/geom_NAME), NeuS from
its transforms_train.json (images and alpha masks only; Blender world) into
benchmarks/out/geometry/NAME, with a time limit on training. Every --checkpoint-every seconds of
training a mesh is extracted (128^3, outside the timed training) and scored; the final mesh is
scored against the dataset's mesh.ply: Chamfer distance as a fraction of the bounding-box
diagonal, normal consistency, F-scores, the shading-normal error per object (over the surface and
in the test views, as `normal_errors.py`), and NeuS novel-view PSNR (sRGB, black background) on
the first test views. Results: JSON + markdown in benchmarks/out/geometry/geometry_<commit>.{json,md}
(copy them into a study folder of benchmarks/results/ to keep them).

With --materials, the material stage then runs twice on the same training views with the same
config and seed: once on the NeuS mesh (the pipeline from images alone) and once on the dataset's
true mesh. Both runs are scored by `vq_mitsuba.eval.evaluate` on the test views, and the table gives
their basecolor PSNR and its difference (target: within 1.5 dB). --seeds repeats the pair with
other seeds; --reuse takes an existing NeuS mesh in the output folder instead of training again;
--true-from REPORT takes the true-mesh fits of an earlier report (same dataset, config and seeds).

    .venv/bin/python benchmarks/bench_geometry.py --scenes demo --reuse --materials --seeds 0 1
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

from normal_errors import table
from provenance import describe, provenance, write_json, write_result

ROOT = Path(__file__).resolve().parent.parent


def find_dataset(name: str, resolution: int, n_train: int, data_root: Path | None = None) -> Path:
    def ok(folder: Path) -> bool:
        meta = folder / "scene.json"
        if not meta.is_file():
            return False
        m = json.loads(meta.read_text())
        return m.get("resolution") == [resolution, resolution] and m.get("n_train") == n_train

    if data_root is not None:  # --data: that folder's dataset or an error, nothing generated
        folder = data_root / name
        if not ok(folder):
            raise SystemExit(f"{folder / 'scene.json'}: no dataset of {n_train} training views at {resolution} x "
                             f"{resolution} px there (see --n-train and --resolution)")
        return folder
    for folder in (ROOT / "data" / name, ROOT / "data" / f"geom_{name}", ROOT / "benchmarks" / "out" / "data" / name):
        if ok(folder):
            return folder
    from vq_mitsuba.synthetic import mitsuba_scenes as synthetic

    out = ROOT / "data" / f"geom_{name}"
    print(f"[{name}] generating {out} ({n_train} views at {resolution}x{resolution})")
    synthetic.make_scene(name, out, resolution=resolution, n_train=n_train)
    return out


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a - b) ** 2))
    return float(-10 * np.log10(max(mse, 1e-12)))


def novel_view_psnr(neus, data: Path, n_views: int) -> dict:
    import torch

    from vq_mitsuba.data.captures import load_capture
    from vq_mitsuba.geometry.neus import encode_srgb, render_view

    test = load_capture(data / "transforms_test.json", mesh=data / "mesh.ply")
    full, masked = [], []
    for k in range(min(n_views, len(test.cameras))):
        rgb, _ = render_view(neus, test.cameras[k])
        gt = encode_srgb(torch.from_numpy(test.images[k])).numpy()
        full.append(psnr(rgb, gt))
        fg = test.alpha[k] > 0.5
        masked.append(psnr(rgb[fg], gt[fg]))
    return {"psnr": float(np.mean(full)), "psnr_foreground": float(np.mean(masked)), "views": len(full)}


def _db(value: float | None) -> str:
    return "n/a" if value is None else f"{value:.2f}"


def material_runs(name: str, data: Path, neus_mesh: Path, args) -> list[dict]:
    """The material stage on the NeuS mesh and on the true mesh, same config and seed; scored."""
    import shutil

    from bench_scenes import scene_config
    from vq_mitsuba.eval.evaluate import evaluate
    from vq_mitsuba.engine.pipeline import fit

    earlier = true_mesh_rows(name, args.true_from) if args.true_from else {}
    rows = []
    for seed in args.seeds:
        row = {"seed": seed}
        if seed in earlier:
            row["true"] = {**earlier[seed], "from": str(args.true_from)}
        for geometry, mesh in (("neus", neus_mesh), ("true", data / "mesh.ply")):
            if geometry in row:
                continue
            cfg, _ = scene_config(name, [f"train.time_limit_s={args.material_time_limit}", f"train.seed={seed}",
                                         *args.material_set])
            if args.material_iterations is not None:
                cfg.train.iterations = min(cfg.train.iterations, args.material_iterations)
            run_dir = ROOT / args.out / name / f"materials_{geometry}_seed{seed}"
            if run_dir.exists():
                shutil.rmtree(run_dir)
            print(f"[{name}] materials on the {geometry} mesh (seed {seed}) -> {run_dir}", flush=True)
            summary = fit(data / "transforms_train.json", run_dir, cfg, mesh_path=mesh)
            m = evaluate(run_dir, data, spp=args.eval_spp, meanshift_bandwidths=())
            row[geometry] = {
                "run": str(run_dir), "fit_s": summary["seconds"], "iterations": summary["iterations"],
                "basecolor_psnr": m["basecolor"]["psnr"], "novel_psnr": m["novel_view"]["psnr"],
                "novel_residual_psnr": (m.get("novel_view_residual") or {}).get("psnr"),
                "metallic_psnr": m["metallic"]["psnr"], "roughness_psnr": m["roughness"]["psnr"],
                "relit_albedo_scale_psnr": m["relighting"]["albedo_scale"]["mean"]["psnr"],
            }
            print(f"[{name}] {geometry} mesh, seed {seed}: basecolor {row[geometry]['basecolor_psnr']:.2f} dB, "
                  f"view {row[geometry]['novel_psnr']:.2f} dB", flush=True)
        row["basecolor_gap_db"] = row["true"]["basecolor_psnr"] - row["neus"]["basecolor_psnr"]
        rows.append(row)
    return rows


def true_mesh_rows(name: str, report: Path) -> dict:
    """{seed: true-mesh row} of a scene in an earlier report (the same dataset, config and seeds)."""
    scenes = [r for r in json.loads(Path(report).read_text())["scenes"] if r["scene"] == name]
    return {row["seed"]: row["true"] for r in scenes for row in r.get("materials", [])}


def reused_scene(name: str, args) -> dict:
    """The result of an earlier NeuS run in the output folder (its bench.json and mesh)."""
    run_dir = ROOT / args.out / name
    bench = run_dir / "bench.json"
    if not (bench.is_file() and (run_dir / "mesh.ply").is_file()):
        raise SystemExit(f"--reuse: {run_dir} holds no finished NeuS run (bench.json and mesh.ply); run without --reuse")
    result = json.loads(bench.read_text())
    result["reused"] = True
    print(f"[{name}] reusing the NeuS mesh {run_dir / 'mesh.ply'} (Chamfer "
          f"{100 * result['final']['chamfer_rel']:.3f}%)", flush=True)
    return result


def run_scene(name: str, args, overrides: list[str]) -> dict:
    from normal_errors import score
    from vq_mitsuba.data.captures import load_capture, load_mesh
    from vq_mitsuba.geometry.mesh import mesh_metrics
    from vq_mitsuba.geometry.neus import extract_mesh, reconstruct
    from vq_mitsuba.config import load_config

    if args.reuse:  # the earlier run names its dataset
        result = reused_scene(name, args)
        if args.materials:
            result["materials"] = material_runs(name, Path(result["dataset"]), ROOT / args.out / name / "mesh.ply", args)
        return result
    data = find_dataset(name, args.resolution, args.n_train, args.data)
    run_dir = ROOT / args.out / name
    for stale in ("neus.pt", "mesh.ply", "geometry.json"):
        (run_dir / stale).unlink(missing_ok=True)
    cfg = load_config(None, [f"neus.time_limit_s={args.time_limit}"] + overrides).neus
    gt = load_mesh(data / "mesh.ply")
    t0 = time.perf_counter()
    capture = load_capture(data / "transforms_train.json")
    load_s = time.perf_counter() - t0
    load_before = os.getloadavg()
    curve = []

    def checkpoint(neus, step, seconds):
        t = time.perf_counter()
        m = mesh_metrics(extract_mesh(neus, 128)[0], gt, n_points=50000)
        curve.append({"step": step, "train_seconds": round(seconds, 1), "chamfer_rel": m["chamfer_rel"],
                      "normal_consistency": m["normal_consistency"]})
        print(f"[{name}] step {step} at {seconds:.0f} s: Chamfer {100 * m['chamfer_rel']:.3f}% "
              f"NC {m['normal_consistency']:.4f} (scored in {time.perf_counter() - t:.0f} s)", flush=True)

    print(f"[{name}] NeuS on {data}/transforms_train.json, training limit {args.time_limit:g} s", flush=True)
    result = reconstruct(capture, run_dir, cfg, callback=checkpoint,
                         callback_every_s=args.checkpoint_every)
    info, neus = result.summary, result.neus
    result.mesh.export(run_dir / "mesh.ply")
    # The hull-initialised start (step 0) and the final state belong on the curve too.
    normals = score(run_dir / "mesh.ply", data, "test", gt=gt)  # mesh_metrics, per object too, and in view
    final = {**normals["surface"], "in_view": normals["view"]}
    secs = info["seconds"]
    views = novel_view_psnr(neus, data, args.test_views) if args.test_views > 0 else {}
    result = {
        "scene": name, "dataset": str(data), "run": str(run_dir),
        "seconds": {"load_capture": round(load_s, 1), **secs,
                    "pipeline": round(load_s + secs["total"], 1)},
        "iterations": info["iterations"], "iterations_per_s": info["iterations_per_s"],
        "iterations_per_s_spread": info.get("iterations_per_s_spread"),
        "final": final, "novel_views": views, "curve": curve, "mesh": info["mesh"],
        "load_average": {"start": load_before, "end": os.getloadavg()},
    }
    spread = result["iterations_per_s_spread"]
    if spread and spread["max"] > 1.3 * spread["min"]:
        print(f"[{name}] warning: NeuS ran {spread['min']:.1f} to {spread['max']:.1f} steps/s over "
              f"{spread['window_s']:.0f} s windows; another process probably shared the CPU, so its "
              "time and its Chamfer at the time limit are not representative", flush=True)
    write_json(run_dir / "bench.json", result)
    if args.materials:
        result["materials"] = material_runs(name, data, run_dir / "mesh.ply", args)
    print(f"[{name}] final: Chamfer {100 * final['chamfer_rel']:.3f}% of the diagonal, NC "
          f"{final['normal_consistency']:.4f}, PSNR {views.get('psnr', float('nan')):.2f} dB, "
          f"{result['seconds']['pipeline']:.0f} s in all", flush=True)
    return result


def write_markdown(report: dict, path: Path) -> None:
    lines = [f"# Geometry benchmark (NeuS + mesh export), commit {report['commit']}", "",
             f"Command: `{report['command']}`", "",
             f"Machine: {describe(report)}; torch threads {report['threads']}.", "",
             "Targets: whole geometry stage <= 15 min on 2 cores, Chamfer <= 1% of the bounding-box diagonal.", "",
             "| scene | iterations | train s | total s | Chamfer (% diag) | normal consistency | "
             "shading normal deg (median / p90) | F@1% | novel-view PSNR (dB) | fg PSNR (dB) | load avg (start/end) | "
             "steps/s (min / median / max over 30 s) |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in report["scenes"]:
        f, v = r["final"], r["novel_views"]
        la = r["load_average"]
        sp = r.get("iterations_per_s_spread")
        rate = f"{sp['min']:.1f} / {sp['median']:.1f} / {sp['max']:.1f}" if sp else "n/a"
        lines.append(f"| {r['scene']}{' (earlier run)' if r.get('reused') else ''} | {r['iterations']} | {r['seconds']['train']:.0f} | {r['seconds']['pipeline']:.0f} | "
                     f"{100 * f['chamfer_rel']:.3f} | {f['normal_consistency']:.4f} | "
                     f"{f.get('shading_normal_deg_median', float('nan')):.2f} / "
                     f"{f.get('shading_normal_deg_p90', float('nan')):.2f} | {f['f_score@0.01']:.3f} | "
                     f"{v.get('psnr', float('nan')):.2f} | {v.get('psnr_foreground', float('nan')):.2f} | "
                     f"{la['start'][0]:.1f} / {la['end'][0]:.1f} | {rate} |")
    for r in report["scenes"]:
        if "in_view" in r["final"]:
            lines += ["", f"Shading-normal error of the {r['scene']} mesh, per object (degrees; surface: samples "
                      "over the surface; in view: pixels of the test views):", "",
                      table([{"mesh": r["run"] + "/mesh.ply", "surface": r["final"], "view": r["final"]["in_view"]}])]
    lines += ["", "Time against Chamfer (training seconds; meshes at 128^3 for the checkpoints, "
                  f"{report['mesh_resolution']}^3 for the final row):", ""]
    for r in report["scenes"]:
        lines.append(f"**{r['scene']}**: " + ", ".join(
            f"{c['train_seconds']:.0f} s: {100 * c['chamfer_rel']:.3f}%" for c in r["curve"])
            + f"; final ({r['seconds']['train']:.0f} s): {100 * r['final']['chamfer_rel']:.3f}%")
        lines.append("")
    runs = [(r["scene"], row) for r in report["scenes"] for row in r.get("materials", [])]
    if runs:
        lines += ["Material stage on the NeuS mesh (images alone) against the true mesh, same config and seed; "
                  "basecolor PSNR in sRGB after per-channel alignment (target: NeuS within 1.5 dB of true):", "",
                  "| scene | seed | iters (NeuS / true) | basecolor NeuS | basecolor true | gap (dB) | view NeuS | view true "
                  "| view NeuS + residual | relit NeuS | relit true |",
                  "|---|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
        for scene, row in runs:
            n, t = row["neus"], row["true"]
            lines.append(f"| {scene} | {row['seed']} | {n['iterations']} / {t['iterations']} | {n['basecolor_psnr']:.2f} | "
                         f"{t['basecolor_psnr']:.2f} | {row['basecolor_gap_db']:.2f} | {n['novel_psnr']:.2f} | "
                         f"{t['novel_psnr']:.2f} | {_db(n.get('novel_residual_psnr'))} | "
                         f"{n['relit_albedo_scale_psnr']:.2f} | {t['relit_albedo_scale_psnr']:.2f} |")
        for r in report["scenes"]:  # one seed's gap is as noisy as the material stage: the mean is the figure
            rows = r.get("materials", [])
            if len(rows) > 1:
                def mean(mesh: str, key: str) -> float | None:
                    values = [row[mesh].get(key) for row in rows]
                    return None if None in values else float(np.mean(values))

                gap = float(np.mean([row["basecolor_gap_db"] for row in rows]))
                lines.append(f"| {r['scene']} | mean of {len(rows)} | | {mean('neus', 'basecolor_psnr'):.2f} | "
                             f"{mean('true', 'basecolor_psnr'):.2f} | **{gap:.2f}** | "
                             f"{mean('neus', 'novel_psnr'):.2f} | {mean('true', 'novel_psnr'):.2f} | "
                             f"{_db(mean('neus', 'novel_residual_psnr'))} | "
                             f"{mean('neus', 'relit_albedo_scale_psnr'):.2f} | {mean('true', 'relit_albedo_scale_psnr'):.2f} |")
        lines.append("")
    path.write_text("\n".join(lines) + "\n")


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scenes", nargs="+", default=["demo", "texture", "balls"])
    p.add_argument("--time-limit", type=float, default=600.0, help="NeuS training seconds per scene")
    p.add_argument("--checkpoint-every", type=float, default=60.0, help="training seconds between scored meshes")
    p.add_argument("--resolution", type=int, default=128)
    p.add_argument("--n-train", type=int, default=64)
    p.add_argument("--data", type=Path, default=None,
                   help="folder of datasets named by scene (e.g. benchmarks/out/cycles128, Cycles renders); "
                        "default: data/NAME, data/geom_NAME or benchmarks/out/data/NAME, else a Mitsuba dataset "
                        "generated into data/geom_NAME")
    p.add_argument("--test-views", type=int, default=4, help="test views rendered for the novel-view PSNR")
    p.add_argument("--out", default="benchmarks/out/geometry")
    p.add_argument("--results", default="benchmarks/out/geometry", help="folder for the report (JSON and markdown)")
    p.add_argument("--set", action="append", default=[], metavar="neus.KEY=VALUE")
    p.add_argument("--quiet", action="store_true", help="no progress bars or notes")
    p.add_argument("--reuse", action="store_true", help="take the NeuS mesh already in OUT/NAME instead of training")
    p.add_argument("--materials", action="store_true",
                   help="fit and score the material stage on the NeuS mesh and on the true mesh")
    p.add_argument("--seeds", type=int, nargs="+", default=[0], help="material-stage seeds (one pair of runs each)")
    p.add_argument("--true-from", type=Path, default=None,
                   help="an earlier report whose true-mesh fits of the same seeds are taken instead of fitting again")
    p.add_argument("--material-time-limit", type=float, default=600.0, help="material fit seconds per run")
    p.add_argument("--material-iterations", type=int, default=None, help="cap on material fit iterations")
    p.add_argument("--material-set", action="append", default=[], metavar="KEY=VALUE",
                   help="material config override for both runs (repeatable)")
    p.add_argument("--eval-spp", type=int, default=None, help="evaluation render spp (default: the run's)")
    args = p.parse_args()

    import torch

    from vq_mitsuba.config import load_config
    from vq_mitsuba.messages import quiet

    cfg = load_config(None, args.set).neus
    report = {**provenance(), "threads": cfg.threads or torch.get_num_threads(),
              "time_limit_s": args.time_limit, "mesh_resolution": cfg.mesh_resolution, "overrides": args.set,
              "scenes": []}
    results = ROOT / args.results
    results.mkdir(parents=True, exist_ok=True)
    stem = results / f"geometry_{report['commit']}"
    with quiet(args.quiet):
        for name in args.scenes:
            report["scenes"].append(run_scene(name, args, args.set))
            write_result(stem.with_suffix(".json"), report)  # partial results survive a stop
            write_markdown(report, stem.with_suffix(".md"))
    print(stem.with_suffix(".md").read_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())
