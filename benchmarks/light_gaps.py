#!/usr/bin/env python
"""Study: where the physically based render of a real capture's held-out views falls short of the
photos, before any light model is built on it.

    python benchmarks/light_gaps.py RUN_DIR [--spp 64] [--figure-views 3] -o OUT_DIR

RUN_DIR is a run fitted with `--holdout K`. Each held-out view is rendered (physically based, and
with the run's residual) and compared with its photo inside the mask the run is scored in. The
log ratio photo / render of every such pixel is then explained by nested models, each fitted by
least squares over all held-out views' pixels (in log space, then refined to the least sRGB error;
so each is an upper bound of what that explanation
can recover on these views, not a prediction):

- scale: one gain per colour channel for the whole capture (the light's overall level and tint);
- exposure: one gain per channel and view (per-view exposure and white balance);
- falloff: exposure, times d^a (d: the distance from the camera to the surface point): a lamp
  riding with the camera lights near parts more than far ones;
- facing: falloff, times |n . v|^b (v: towards the camera): that lamp lights surfaces facing the
  camera more than grazing ones;
- smooth: exposure, times the exponential of a quadratic in the surface point's world position
  (what any smooth light left out, such as a lamp fixed in the room, would change slowly over the
  object);
- view_lamp: exposure, times the exponential of a linear function of the world normal and of the
  world position for each view (to first order, a lamp that moves with the camera, off its axis:
  which way a surface faces it and how far it is, per view).

Then, for the points two held-out views both see (the second view's depth agreeing), how much of
the log ratio's variance is the point's own (the same in both views: a wrong basecolor, a shadow
or shading fixed on the object) and how much the view's (a highlight, a shadow or a lamp that
moves with the view).

The render is also scored against the photo with both blurred alike by 4 px: what is left at a
coarse scale.

Prints and writes OUT_DIR/light_gaps.json: each model's PSNR (sRGB, inside the masks; per view and
mean), its fitted exponents and gains, the residual's PSNR for reference, and where the error
left after `exposure` lies (by |n . v|, by distance, brighter or darker than the render).
OUT_DIR/light_gaps.png shows, for a few views: the photo, the render, the render with the residual,
log2(photo / render) and that ratio left after `view_lamp`.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from provenance import command_line, describe, provenance, write_result

MODELS = ("render", "scale", "exposure", "falloff", "facing", "smooth", "view_lamp")
FLOOR = 1e-3  # pixels darker than this in the photo or the render do not fit the ratios


def design(views: np.ndarray, n_views: int, log_d: np.ndarray, log_cos: np.ndarray, pos: np.ndarray,
           normal: np.ndarray, model: str) -> np.ndarray:
    """Columns of the least-squares fit of one channel's log ratio for `model`; `pos`: the points'
    world positions, centred and scaled to unit spread."""
    if model == "scale":
        cols = [np.ones(len(views))]
    else:
        cols = [(views == k).astype(np.float64) for k in range(n_views)]
    if model in ("falloff", "facing"):
        cols.append(log_d)
    if model == "facing":
        cols.append(log_cos)
    if model == "smooth":
        cols += [pos[:, a] for a in range(3)] + [pos[:, a] * pos[:, b] for a in range(3) for b in range(a, 3)]
    if model == "view_lamp":
        cols += [(views == k) * x[:, a] for k in range(n_views) for x in (normal, pos) for a in range(3)]
    return np.stack(cols, 1)


def refine_in_srgb(X: np.ndarray, render: np.ndarray, target: np.ndarray, beta: np.ndarray,
                   iterations: int = 8) -> np.ndarray:
    """Gauss-Newton steps on beta towards the least sRGB squared error of render * exp(X beta)
    against `target` (sRGB), the error PSNR scores; from the log-ratio fit `beta`."""
    from vq_mitsuba.eval import metrics as M

    def error(b):
        return float(((M.srgb(render * np.exp(X @ b)) - target) ** 2).sum())

    best = error(beta)
    for _ in range(iterations):
        x = np.clip(render * np.exp(X @ beta), 1e-6, None)
        slope = np.where(x > 0.0031308, 1.055 / 2.4 * x ** (1 / 2.4 - 1), 12.92) * (x < 1)  # d srgb / dx
        jac = (slope * x)[:, None] * X
        step = np.linalg.lstsq(jac, target - M.srgb(x), rcond=None)[0]
        trial = beta + step
        if error(trial) >= best:
            break
        beta, best = trial, error(trial)
    return beta


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    ap.add_argument("run", type=Path, help="run directory fitted with --holdout K")
    ap.add_argument("--spp", type=int, default=64, help="samples per pixel of the renders")
    ap.add_argument("--figure-views", type=int, default=3, help="held-out views shown in the figure")
    ap.add_argument("-o", "--output", type=Path, required=True, help="folder for light_gaps.json and .png")
    args = ap.parse_args(argv)
    record = provenance(command_line(argv))

    from vq_mitsuba.data.cameras import camera_rays
    from vq_mitsuba.eval import metrics as M
    from vq_mitsuba.eval.heldout import held_out_capture, straight_colours
    from vq_mitsuba.render.shading import scene_for_mesh
    from vq_mitsuba.render.views import Renderer
    from vq_mitsuba.run.run_dir import RunDir

    run = RunDir(args.run)
    held = held_out_capture(run)
    fitted = run.load()
    renderer = Renderer(fitted)
    scene = scene_for_mesh(fitted.mesh, fitted.envmap, fitted.envmap_to_world)
    views = []
    for cam, photo, alpha in zip(held.cameras, held.images, held.alpha):
        out = renderer.render(cam, spp=args.spp)
        physical, residual = straight_colours(out)
        mask = (alpha > 0.5) & (out["alpha"] > 0.5)
        origins, dirs = camera_rays(cam)
        hits = scene.trace(origins, dirs)
        pos = hits.position.cpu().numpy().reshape(cam.height, cam.width, 3)
        valid = hits.valid.cpu().numpy().reshape(cam.height, cam.width)
        mask &= valid
        to_cam = cam.origin - pos
        dist = np.linalg.norm(to_cam, axis=-1)
        cos = np.abs((out["normal"] * to_cam).sum(-1)) / np.maximum(dist, 1e-9)
        views.append({"name": cam.name, "pos": pos, "normal": out["normal"], "camera": cam, "depth": np.where(valid, dist, np.inf), "photo": np.asarray(photo, np.float64), "render": physical.astype(np.float64),
                      "residual": residual, "mask": mask, "dist": dist, "cos": np.clip(cos, 1e-3, 1.0)})
        print(f"{cam.name}: {int(mask.sum())} pixels", flush=True)

    # every held-out pixel: its view, log distance, log cosine, and per channel the log ratio
    n = len(views)
    vid = np.concatenate([np.full(int(v["mask"].sum()), k) for k, v in enumerate(views)])
    dist = np.concatenate([v["dist"][v["mask"]] for v in views])
    log_d = np.log(dist / np.median(dist))
    log_cos = np.log(np.concatenate([v["cos"][v["mask"]] for v in views]))
    pos = np.concatenate([v["pos"][v["mask"]] for v in views])
    pos = (pos - pos.mean(0)) / pos.std()
    normal = np.concatenate([v["normal"][v["mask"]] for v in views])
    photo = np.concatenate([v["photo"][v["mask"]] for v in views])
    render = np.concatenate([v["render"][v["mask"]] for v in views])
    fits = {}
    for model in MODELS[1:]:
        X = design(vid, n, log_d, log_cos, pos, normal, model)
        coef, factor = [], np.ones_like(render)
        for c in range(3):
            ok = (photo[:, c] > FLOOR) & (render[:, c] > FLOOR)
            y = np.log(photo[ok, c]) - np.log(render[ok, c])
            beta = np.linalg.lstsq(X[ok], y, rcond=None)[0]
            beta = refine_in_srgb(X, render[:, c], M.srgb(photo[:, c]), beta)
            coef.append(beta)
            factor[:, c] = np.exp(X @ beta)
        coef = np.asarray(coef)
        extra = coef[:, (1 if model == "scale" else n):]
        fits[model] = {"factor": factor,
                       "exponent_distance": float(extra[:, 0].mean()) if model in ("falloff", "facing") else None,
                       "exponent_facing": float(extra[:, 1].mean()) if model == "facing" else None,
                       "gains": np.exp(coef[:, :(1 if model == "scale" else n)]).T.round(4).tolist()}

    def psnr_of(pred_all: np.ndarray) -> list[float]:
        """Per-view PSNR of the masked pixels `pred_all` (in the views' pixel order)."""
        scores, start = [], 0
        for v in views:
            k = int(v["mask"].sum())
            image = v["render"].copy()
            image[v["mask"]] = pred_all[start:start + k]
            scores.append(M.image_metrics(image, v["photo"], v["mask"])["psnr"])
            start += k
        return scores

    result = {"views": [v["name"] for v in views], "pixels": int(len(vid)), "spp": args.spp, "models": {}}
    for model in MODELS:
        pred = render if model == "render" else render * fits[model]["factor"]
        per_view = psnr_of(pred)
        result["models"][model] = {"psnr": float(np.mean(per_view)), "psnr_views": per_view,
                                   **{k: v for k, v in fits.get(model, {}).items() if k != "factor"}}
    # the same scores with photo and render blurred alike (4 px): what is left at coarse scale
    def blur_rgb(image, mask):
        return np.stack([np.nan_to_num(blurred(np.where(mask, image[..., c], np.nan), 4.0)) for c in range(3)], -1)

    coarse = [M.image_metrics(blur_rgb(v["render"], v["mask"]), blur_rgb(v["photo"], v["mask"]), v["mask"])["psnr"]
              for v in views]
    result["render_blurred_4px"] = {"psnr": float(np.mean(coarse)), "psnr_views": coarse}
    if all(v["residual"] is not None for v in views):
        per_view = [M.image_metrics(v["residual"], v["photo"], v["mask"])["psnr"] for v in views]
        result["with_residual"] = {"psnr": float(np.mean(per_view)), "psnr_views": per_view}

    ratios = [log_ratio(v) for v in views]
    result["shared_between_views"] = {
        "log_ratio": shared_share(views, ratios),
        "log_ratio_blurred_4px": shared_share(views, [blurred(r, 4.0) for r in ratios]),
        "log_photo": shared_share(views, [log_photo(v) for v in views]),  # the photos' own agreement
    }

    # where the error left after per-view exposure lies (squared sRGB error, shares of the total)
    err = ((M.srgb(render * fits["exposure"]["factor"]) - M.srgb(photo)) ** 2).sum(1)
    cos = np.exp(log_cos)
    brighter = M.srgb(photo).mean(1) > M.srgb(render * fits["exposure"]["factor"]).mean(1)
    d_edges = np.quantile(dist, [0, 0.25, 0.5, 0.75, 1.0])
    result["error_after_exposure"] = {
        "by_facing": {f"{lo:.2f}-{hi:.2f}": {"pixels": float(((cos >= lo) & (cos < hi)).mean()),
                                             "error": float(err[(cos >= lo) & (cos < hi)].sum() / err.sum())}
                      for lo, hi in ((0.0, 0.25), (0.25, 0.5), (0.5, 0.75), (0.75, 1.01))},
        "by_distance_quartile": [float(err[(dist >= lo) & (dist <= hi)].sum() / err.sum())
                                 for lo, hi in zip(d_edges[:-1], d_edges[1:])],
        "photo_brighter": {"pixels": float(brighter.mean()), "error": float(err[brighter].sum() / err.sum())},
    }
    args.output.mkdir(parents=True, exist_ok=True)
    figure(views, fits["view_lamp"]["factor"], args.figure_views, args.output / "light_gaps.png")
    write_result(args.output / "light_gaps.json", {**record, **result})
    print(describe(record))
    for model, r in result["models"].items():
        extra = "".join(f", {k} {r[k]:+.2f}" for k in ("exponent_distance", "exponent_facing") if r.get(k) is not None)
        print(f"{model:9s} {r['psnr']:6.2f} dB{extra}")
    print(f"blurred   {result['render_blurred_4px']['psnr']:6.2f} dB (render and photo blurred 4 px)")
    if "with_residual" in result:
        print(f"residual  {result['with_residual']['psnr']:6.2f} dB")
    print("error after exposure:", result["error_after_exposure"])
    print("shared between views:", result["shared_between_views"])
    return 0


def log_ratio(v: dict) -> np.ndarray:
    """log(photo / render) of a view's luminance, NaN outside its mask or where either is dark."""
    photo, render = v["photo"].mean(-1), v["render"].mean(-1)
    ok = v["mask"] & (photo > FLOOR) & (render > FLOOR)
    return np.where(ok, np.log(np.maximum(photo, FLOOR) / np.maximum(render, FLOOR)), np.nan)


def log_photo(v: dict) -> np.ndarray:
    """log of a view's photo luminance, NaN outside its mask or where it is dark."""
    photo = v["photo"].mean(-1)
    return np.where(v["mask"] & (photo > FLOOR), np.log(np.maximum(photo, FLOOR)), np.nan)


def blurred(image: np.ndarray, sigma: float) -> np.ndarray:
    """A Gaussian blur of the finite values of `image` (NaN stays NaN), normalised by coverage."""
    from scipy.ndimage import gaussian_filter

    ok = np.isfinite(image)
    num = gaussian_filter(np.where(ok, image, 0.0), sigma)
    den = gaussian_filter(ok.astype(np.float64), sigma)
    return np.where(ok, num / np.maximum(den, 1e-6), np.nan)


def shared_share(views: list, ratios: list) -> dict:
    """Over the points two views both see: the variance of a per-pixel quantity (`ratios`, one map
    a view), the half mean squared difference of the two views' values at the same point (the
    view's part), and the share of the variance the point keeps in both views."""
    pairs = []
    for i, a in enumerate(views):
        ys, xs = np.nonzero(np.isfinite(ratios[i]))
        for j, b in enumerate(views):
            if i == j:
                continue
            cam = b["camera"]
            xy = cam.project(a["pos"][ys, xs])
            col, row = np.floor(xy[:, 0]).astype(int), np.floor(xy[:, 1]).astype(int)
            inside = (col >= 0) & (col < cam.width) & (row >= 0) & (row < cam.height)
            k = np.nonzero(inside)[0]
            dist = np.linalg.norm(a["pos"][ys[k], xs[k]] - cam.origin, axis=-1)
            seen = np.abs(b["depth"][row[k], col[k]] - dist) < 0.01 * dist  # not hidden in view j
            k = k[seen]
            rb = ratios[j][row[k], col[k]]
            keep = np.isfinite(rb)
            pairs.append(np.stack([ratios[i][ys[k[keep]], xs[k[keep]]], rb[keep]], 1))
    pairs = np.concatenate(pairs) if pairs else np.zeros((0, 2))
    if len(pairs) < 100:
        return {"pairs": int(len(pairs))}
    variance = float(np.var(pairs))
    view_part = float(0.5 * np.mean((pairs[:, 0] - pairs[:, 1]) ** 2))
    return {"pairs": int(len(pairs)), "variance": variance, "view_part": view_part,
            "point_share": 1.0 - view_part / variance,
            "correlation": float(np.corrcoef(pairs[:, 0], pairs[:, 1])[0, 1])}


def figure(views: list, factor: np.ndarray, count: int, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from vq_mitsuba.eval import metrics as M

    picks = np.linspace(0, len(views) - 1, min(count, len(views))).round().astype(int)
    offsets = np.cumsum([0] + [int(v["mask"].sum()) for v in views])
    fig, axes = plt.subplots(len(picks), 5, figsize=(15, 2.6 * len(picks)), squeeze=False)
    for row, k in zip(axes, picks):
        v = views[k]
        ratio = np.full(v["mask"].shape, np.nan)
        left = np.full(v["mask"].shape, np.nan)
        lum = lambda x: x.mean(-1)
        ratio[v["mask"]] = np.log2(np.maximum(lum(v["photo"][v["mask"]]), 1e-4) /
                                   np.maximum(lum(v["render"][v["mask"]]), 1e-4))
        fitted = v["render"][v["mask"]] * factor[offsets[k]:offsets[k + 1]]
        left[v["mask"]] = np.log2(np.maximum(lum(v["photo"][v["mask"]]), 1e-4) / np.maximum(lum(fitted), 1e-4))
        panels = [(M.srgb(v["photo"]), "photo"), (M.srgb(v["render"]), "physically based"),
                  (M.srgb(v["residual"]) if v["residual"] is not None else None, "with residual")]
        for ax, (img, title) in zip(row[:3], panels):
            if img is not None:
                ax.imshow(np.clip(img, 0, 1))
            ax.set_title(f"{v['name']}: {title}", fontsize=8)
        for ax, img, title in ((row[3], ratio, "log2 photo / render"), (row[4], left, "left after view_lamp")):
            im = ax.imshow(img, cmap="RdBu_r", vmin=-1.5, vmax=1.5)
            ax.set_title(title, fontsize=8)
            fig.colorbar(im, ax=ax, fraction=0.046)
        for ax in row:
            ax.axis("off")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


if __name__ == "__main__":
    raise SystemExit(main())
