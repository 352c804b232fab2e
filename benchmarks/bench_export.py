"""Export fidelity and bake time: does the exported Mitsuba scene, rendered by plain Mitsuba,
look like `vq-mitsuba render` of the same run, and how long does a 1024^2 bake take?

    .venv/bin/python benchmarks/bench_export.py RUN_DIR [RUN_DIR ...] [--spp 4096] [--texture-size 1024]
        [--repeats 3] [--views 4] [-o benchmarks/out/export]

For each run (fitted or edited):
- bake: `export --format mitsuba` at the texture size, `--repeats` times; median seconds, split
  into UV unwrap, rasterisation, field evaluation and padding;
- fidelity: the first `--views` test cameras of the run's capture (transforms_test.json beside
  it, else the training cameras) rendered by Mitsuba alone (a child process that imports no
  vq_mitsuba) from the exported scene.xml, and by vq-mitsuba's renderer, both at --spp samples
  per pixel. PSNR / SSIM in sRGB over the foreground, beside the noise floor: two renders of
  ours with different seeds at the same spp (the difference that noise alone makes);
- glTF: the .glb of the same run through the Khronos validator (errors, warnings);
- edits, with --gt DATASET (the run's make-scene dataset, one per run): for every ranked
  material K, `edit --material K --preset gold` rendered against the run on the test views
  (same seed, --edit-spp): the share of changed pixels (sRGB change > 2/255) inside K's region
  (pixels where any primary ray hits K; also with K's majority pixels and their 4-neighbours),
  with direct light only and with the run's interreflections; and `--pick` at the most interior pixel of each ground-truth material in
  the first test view: does it select the ranked material that most of that ground-truth
  material's pixels get?
Writes OUT/export_<commit>.json and .md.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent

PLAIN = """
import sys
import numpy as np
import mitsuba as mi
mi.set_variant("llvm_ad_rgb")
scene = mi.load_file(sys.argv[1], spp=int(sys.argv[2]))
ids = [s.id() for s in scene.sensors()]
for name in sys.argv[4:]:
    np.save(f"{sys.argv[3]}/{name}.npy", np.array(mi.render(scene, sensor=ids.index(name), seed=7)))
assert not [m for m in sys.modules if m.startswith("vq_mitsuba")]
"""


def edit_checks(run, dataset: Path, n_views: int, spp: int) -> dict:
    from vq_mitsuba.data.imageio import linear_to_srgb
    from vq_mitsuba.edit import build_edit, edit_run
    from vq_mitsuba.render.views import Renderer

    fitted = run.load()
    views = run.cameras()["test"][:n_views]
    srgb = lambda x: linear_to_srgb(np.clip(x, 0, 1))  # noqa: E731
    per_material = []
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(1, fitted.num_materials + 1):
            edited = edit_run(run, Path(tmp) / f"k{k}", build_edit(run, fitted, materials=[k], preset="gold")).load()
            shares = {}
            for bounces in (0, fitted.cfg.train.bounces):
                fitted.cfg.train.bounces = edited.cfg.train.bounces = bounces
                changed_in, changed_grown, changed_all = 0, 0, 0
                for cam in views:
                    a = Renderer(fitted).render(cam, spp=spp, seed=0)
                    b = Renderer(edited).render(cam, spp=spp, seed=0)
                    changed = np.abs(srgb(a["rgb"]) - srgb(b["rgb"])).max(-1) > 2 / 255
                    r = a["material"] == k
                    grown = r | np.roll(r, 1, 0) | np.roll(r, -1, 0) | np.roll(r, 1, 1) | np.roll(r, -1, 1)
                    changed_in += int((changed & (a["material_share"][..., k] > 0)).sum())
                    changed_grown += int((changed & grown).sum())
                    changed_all += int(changed.sum())
                key = "direct" if bounces == 0 else "bounces"
                shares[key] = changed_in / max(changed_all, 1)
                shares[key + "_majority"] = changed_grown / max(changed_all, 1)
            fitted.cfg.train.bounces = edited.cfg.train.bounces = run.config().train.bounces
            per_material.append({"material": k, "inside_share_direct": shares["direct"],
                                 "inside_share_direct_majority_mask": shares["direct_majority"],
                                 "inside_share_bounces": shares.get("bounces", shares["direct"])})
    # --pick at the most interior pixel of each ground-truth material of the first test view.
    from scipy.ndimage import distance_transform_edt

    cam = views[0]
    import imageio.v3 as iio

    gt_ids = np.asarray(iio.imread(dataset / "gt" / f"{cam.name}_material.png")).astype(int)
    gt_ids = gt_ids[..., 0] if gt_ids.ndim == 3 else gt_ids
    pred = Renderer(fitted).render(cam, spp=spp, seed=0)["material"]
    picks = []
    for g in np.unique(gt_ids[gt_ids > 0]):
        region = gt_ids == g
        if region.sum() < 9:
            continue
        y, x = np.unravel_index(np.argmax(distance_transform_edt(region)), region.shape)
        chosen = build_edit(run, fitted, picks=[f"{cam.name}:{x},{y}"], sets=["roughness=0.5"]).selection.materials[0]
        majority = int(np.bincount(pred[region]).argmax())
        picks.append({"gt_material": int(g), "pixel": [int(x), int(y)], "picked": chosen, "majority": majority})
    return {"per_material": per_material,
            "inside_share_direct_min": min(m["inside_share_direct"] for m in per_material),
            "inside_share_direct_majority_mask_min": min(m["inside_share_direct_majority_mask"] for m in per_material),
            "inside_share_bounces_min": min(m["inside_share_bounces"] for m in per_material),
            "picks": picks, "pick_tried": len(picks), "pick_right": sum(p["picked"] == p["majority"] for p in picks)}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("runs", nargs="+")
    p.add_argument("--spp", type=int, default=4096)
    p.add_argument("--texture-size", type=int, default=1024)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--views", type=int, default=4)
    p.add_argument("--gt", nargs="*", default=[], help="each run's make-scene dataset (enables the edit checks)")
    p.add_argument("--edit-spp", type=int, default=64)
    p.add_argument("-o", "--output", default=str(ROOT / "benchmarks" / "out" / "export"))
    args = p.parse_args()

    from provenance import provenance, write_result

    from vq_mitsuba.run.run_dir import RunDir
    from vq_mitsuba.eval import metrics as M
    from vq_mitsuba.export.formats import export_run
    from vq_mitsuba.messages import quiet
    from vq_mitsuba.render.views import Renderer

    out_dir = Path(args.output)
    out_dir.mkdir(parents=True, exist_ok=True)
    results = []
    gts = dict(zip(args.runs, args.gt))
    for run_path in args.runs:
        run = RunDir(run_path)
        with tempfile.TemporaryDirectory() as tmp:
            tmp = Path(tmp)
            bakes = []
            for r in range(args.repeats):
                t0 = time.perf_counter()
                with quiet():
                    summary = export_run(run.dir, "mitsuba", tmp / "mitsuba", args.texture_size)
                bakes.append({"total": time.perf_counter() - t0, **summary["seconds"]})
            cams = run.cameras()
            views = (cams.get("test") or cams["train"])[:args.views]
            t0 = time.perf_counter()
            subprocess.run([sys.executable, "-c", PLAIN, str(tmp / "mitsuba" / "scene.xml"), str(args.spp), str(tmp),
                            *[c.name for c in views]], check=True)
            plain_s = time.perf_counter() - t0
            fitted = run.load()
            renderer = Renderer(fitted)
            per_view = []
            t0 = time.perf_counter()
            for cam in views:
                theirs = np.load(tmp / f"{cam.name}.npy")
                ours = renderer.render(cam, spp=args.spp, seed=0)
                again = renderer.render(cam, spp=args.spp, seed=1)
                mask = ours["alpha"] > 0
                exp = M.image_metrics(theirs[..., :3], ours["rgb"], mask)
                floor = M.image_metrics(again["rgb"], ours["rgb"], mask)
                per_view.append({"view": cam.name, "psnr": exp["psnr"], "ssim": exp["ssim"],
                                 "noise_floor_psnr": floor["psnr"], "noise_floor_ssim": floor["ssim"],
                                 "alpha_mae": float(np.abs(theirs[..., 3] - ours["alpha"]).mean())})
            ours_s = (time.perf_counter() - t0) / 2
            with quiet():
                gltf = export_run(run.dir, "gltf", tmp / "gltf", args.texture_size)
            report = json.loads(subprocess.run(["node", str(ROOT / "tools" / "validate_gltf.js"),
                                                str(tmp / "gltf" / gltf["files"][0])],
                                               check=True, capture_output=True, text=True).stdout)
        med = {k: statistics.median(b[k] for b in bakes) for k in bakes[0]}
        res = {"run": str(run.dir), "edits": len(fitted.edits), "faces": summary["faces"],
               "texture_size": args.texture_size, "bake_seconds_median": med, "bake_seconds_all": bakes,
               "spp": args.spp, "views": per_view,
               "psnr_median": statistics.median(v["psnr"] for v in per_view),
               "noise_floor_psnr_median": statistics.median(v["noise_floor_psnr"] for v in per_view),
               "render_seconds": {"plain_mitsuba_all_views_with_load": plain_s, "ours_all_views": ours_s},
               "gltf_validator": {"errors": report["issues"]["numErrors"],
                                  "warnings": report["issues"]["numWarnings"]}}
        if run_path in gts:
            res["edit_checks"] = edit_checks(run, Path(gts[run_path]), args.views, args.edit_spp)
            e = res["edit_checks"]
            print(f"  edits: changed pixels inside K, direct light: min {e['inside_share_direct_min']:.4f} "
                  f"(majority mask {e['inside_share_direct_majority_mask_min']:.4f}); "
                  f"with interreflections: min {e['inside_share_bounces_min']:.4f}; --pick right "
                  f"{e['pick_right']} of {e['pick_tried']}", flush=True)
        results.append(res)
        print(f"{run.dir}: bake {args.texture_size}^2 {med['total']:.1f} s (median of {args.repeats}; unwrap "
              f"{med['unwrap']:.1f}, rasterise {med['rasterise']:.1f}, evaluate {med['evaluate']:.1f}, pad "
              f"{med['pad']:.1f}); plain Mitsuba vs ours at {args.spp} spp: PSNR {res['psnr_median']:.2f} dB "
              f"(noise floor {res['noise_floor_psnr_median']:.2f} dB); glTF validator: "
              f"{res['gltf_validator']['errors']} errors, {res['gltf_validator']['warnings']} warnings", flush=True)
    name = f"export_{provenance()['commit']}"
    write_result(out_dir / f"{name}.json", {"results": results})
    lines = ["| run | faces | bake 1024² s (median) | PSNR export vs ours, dB | noise floor, dB | glTF errors |",
             "|---|---:|---:|---:|---:|---:|"]
    for r in results:
        lines.append(f"| {Path(r['run']).name} | {r['faces']} | {r['bake_seconds_median']['total']:.1f} | "
                     f"{r['psnr_median']:.2f} | {r['noise_floor_psnr_median']:.2f} | {r['gltf_validator']['errors']} |")
    (out_dir / f"{name}.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    print(f"written {out_dir / name}.json, .md")


if __name__ == "__main__":
    main()
