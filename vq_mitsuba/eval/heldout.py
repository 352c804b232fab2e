"""`vq-mitsuba eval` of a run fitted with capture.holdout K: novel views of a capture without ground-truth
maps, scored against the views the fit kept out of training."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from vq_mitsuba.errors import InputError
from vq_mitsuba.eval import metrics as M
from vq_mitsuba.run.outputs import EVAL_MARK
from vq_mitsuba.run.run_dir import RunDir

def held_out_capture(run: RunDir, downscale: int | None = None, max_size: int | None = None):
    """The views a run fitted with capture.holdout K kept out of training, at the fit's size (or
    the `downscale` / `max_size` given), masked as the fit was: by their masks, or by the mesh's
    coverage for a run whose mesh NeuS made without masks."""
    from vq_mitsuba.data.captures import load_capture

    cfg = run.source().config()
    if cfg.capture.holdout <= 0:
        raise InputError(run.dir, "was fitted without held-out views: fit with --holdout K to score novel views "
                                  "of a real capture, or give --gt DATASET for a synthetic one")
    sizes = {k: v for k, v in (("downscale", downscale), ("max_size", max_size)) if v is not None}
    held = load_capture(run.source().info()["capture"], options=replace(cfg.capture, **sizes), split="holdout",
                        cache_dir=run.undistorted_dir)
    if not held.has_alpha and run.source().masks_from_mesh():
        from vq_mitsuba.geometry.stage import masked_by_mesh

        held = masked_by_mesh(held, run.mesh())
    return held


def straight_colours(out: dict) -> tuple[np.ndarray, np.ndarray | None]:
    """(physically based colour, colour with the run's residual or None) of a render, divided by
    its coverage as a photo's straight colours are."""
    cover = np.maximum(out["alpha"], 1e-6)[..., None]
    if "rgb_physical" in out:  # the run's residual: rgb has it, rgb_physical not
        return out["rgb_physical"] / cover, out["rgb"] / cover
    return out["rgb"] / cover, None


def evaluate_holdout(run_dir: str | Path, spp: int | None = None,
                     output: str | Path | None = None, downscale: int | None = None,
                     max_size: int | None = None) -> dict:
    """Score a run fitted with capture.holdout K on the views it kept out of training: novel-view
    PSNR / SSIM (sRGB) inside each view's mask, its own images being the reference. For captures
    without ground-truth maps; writes RUN_DIR/metrics.json (or `output`). A run whose mesh NeuS
    made without masks is scored inside the mesh's coverage, as it was fitted (its coverage_iou is
    then 1 by construction)."""
    from vq_mitsuba import messages

    from vq_mitsuba.render.views import Renderer, check_finite

    run = RunDir(run_dir)
    cfg = run.source().config()
    held = held_out_capture(run, downscale, max_size)
    fitted = run.load()
    renderer = Renderer(fitted)
    spp = spp or cfg.render.spp
    rows = []
    for cam, image, alpha in messages.progress(list(zip(held.cameras, held.images, held.alpha)), desc="eval holdout"):
        out = renderer.render(cam, spp=spp)
        check_finite(out, cam.name)
        mask = alpha > 0.5
        physical, with_residual = straight_colours(out)
        row = {"view": cam.name, **M.image_metrics(physical, image, mask),
               "coverage_iou": float((mask & (out["alpha"] > 0.5)).sum() / max((mask | (out["alpha"] > 0.5)).sum(), 1))}
        if with_residual is not None:
            row.update({"residual_" + k: v for k, v in M.image_metrics(with_residual, image, mask).items()})
        rows.append(row)
    metrics = {**EVAL_MARK, "run": str(run.dir.resolve()), "holdout": cfg.capture.holdout, "spp": spp,
               "novel_view": {"psnr": M.mean_of(r["psnr"] for r in rows), "ssim": M.mean_of(r["ssim"] for r in rows)},
               "novel_view_residual": {"psnr": M.mean_of(r["residual_psnr"] for r in rows),
                                       "ssim": M.mean_of(r["residual_ssim"] for r in rows)}
               if any("residual_psnr" in r for r in rows) else None,
               "coverage_iou": M.mean_of(r["coverage_iou"] for r in rows), "views": rows}
    if output is not None:
        Path(output).parent.mkdir(parents=True, exist_ok=True)
    run.write_metrics(metrics, output)
    return metrics
