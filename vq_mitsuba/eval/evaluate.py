"""`vq-mitsuba eval`: score a fitted run against a synthetic dataset's ground truth.

The dataset is one written by `vq_mitsuba.synthetic.make_scene` (layout: `DatasetDir`). The
run may have been fitted on its scene.xml (Mitsuba world) or its transforms_train.json (Blender
world); the test cameras come from transforms_test.json and are converted to the run's world.
Every test view is rendered with the fitted lighting (novel view, material maps) and under each
held-aside envmap (relighting), and compared inside the ground-truth foreground (gt alpha > 0.5):

- novel view: premultiplied linear RGB of `images/<id>.exr`, compared in sRGB (PSNR, SSIM), the
  physically based render; with the run's residual (`novel_view_residual`) when it has one;
- basecolor: `gt/<id>_basecolor.exr` after a per-channel scale alignment computed once over all
  test views jointly (method "lstsq" as NeRFactor or "median" as TensoIR), compared in sRGB;
- metallic, roughness: PSNR of the linear [0, 1] maps, no alignment;
- with a discrete branch: its basecolor (aligned on its own), metallic and roughness maps too,
  segmentation micro/macro F1 against `gt/<id>_material.png`, and the MeanShift baseline;
- normals: mean angular error in degrees (world normals, both in Blender world);
- relighting under `relit/<env>/<id>.exr`, compared in sRGB, in two labelled variants:
  `albedo_scale` (the relit render times the basecolor alignment scales, as NeRFactor) and
  `image_scale` (each relit render aligned to its reference by its own per-channel least-squares
  scale, which also absorbs an exposure mismatch of the fitted lighting);
- with the dataset's true mesh (mesh.ply) and a run on another mesh: the materials at the true
  surface points, each read at the nearest point of the run's mesh (`vq_mitsuba.eval.surface`).

Figures are means of per-view values (NeRF convention). Renders are Monte Carlo estimates
(`spp` samples per pixel): their noise lowers PSNR slightly, more at low spp.

The readable table is `eval/report.py`'s; a run fitted with held-out views of a capture without
ground truth is scored by `eval/heldout.py`. Both are re-exported here.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vq_mitsuba import brdf
from vq_mitsuba.data.dataset_dir import DatasetDir
from vq_mitsuba.data.envmaps import load_envmap
from vq_mitsuba.data.imageio import checked_kind, read_exr
from vq_mitsuba.errors import InputError
from vq_mitsuba.eval import input_scores, metrics as M
from vq_mitsuba.eval.baselines import MEANSHIFT_BANDWIDTHS
from vq_mitsuba.eval.heldout import evaluate_holdout, held_out_capture, straight_colours
from vq_mitsuba.eval.report import format_table, table_rows
from vq_mitsuba.eval.surface import evaluate_surface
from vq_mitsuba.run.outputs import EVAL_MARK
from vq_mitsuba.run.run_dir import RunDir, json_safe, write_json

__all__ = ["MASK_THRESHOLD", "MIN_SIDE", "DEFAULT_AA", "dataset_root", "read_scene_meta", "relight_envs",
           "load_ground_truth", "RunPredictor", "evaluate", "evaluate_predictor", "relit_views", "coverage_scores",
           "per_material_scores", "meanshift_segmentation",
           # re-exported: the table (eval/report.py) and held-out views (eval/heldout.py)
           "format_table", "table_rows", "evaluate_holdout", "held_out_capture", "straight_colours"]

MASK_THRESHOLD = 0.5  # a pixel is foreground when the ground-truth coverage exceeds this
MIN_SIDE = 3  # pixels per side of a test view: SSIM's smallest window (eval.metrics.ssim)
DEFAULT_AA = None  # primary rays per pixel: None takes the run's render.aa


# --------------------------------------------------------------------------------------------
# Ground truth


def dataset_root(path: str | Path) -> Path:
    """The dataset folder for a folder or any file inside it (scene.json, scene.xml, transforms json)."""
    return DatasetDir.find(path).dir


def read_scene_meta(root: Path) -> dict:
    """scene.json of a dataset, checked where evaluation reads it (`DatasetDir.info`)."""
    return DatasetDir(root).info()


def relight_envs(root: Path, meta: dict) -> list[tuple[str, Path]]:
    """(name, envmap path) of every relighting condition with its envmap and relit views on disk."""
    return DatasetDir(root).relight_envs(meta)


def _read_rgba(path: Path) -> tuple[np.ndarray, np.ndarray | None]:
    if not path.is_file():
        raise InputError(path, "ground-truth image missing")
    data = read_exr(path)
    finite = np.isfinite(data)
    if not finite.all():
        raise InputError(path, f"{int((~finite).sum())} of its {finite.size} values are not finite numbers (NaN or "
                               "infinite): not usable as ground truth")
    return data[..., :3].astype(np.float64), (data[..., 3].astype(np.float64) if data.shape[-1] > 3 else None)


def _read_map(path: Path) -> np.ndarray:
    """A scalar EXR map (stored as Y) as (H, W)."""
    rgb, _ = _read_rgba(path)
    return rgb[..., 0]


def _read_mask(root: Path, name: str, image_alpha: np.ndarray | None) -> np.ndarray:
    """Foreground mask: gt/<id>_alpha.png (coverage, stored linearly), else the image's alpha."""
    png = DatasetDir(root).gt(name, "alpha")
    if png.is_file():
        import imageio.v3 as iio

        checked_kind(png)  # a file known by its bytes, not its name
        a = np.asarray(iio.imread(png)).astype(np.float64)
        a = a[..., 0] if a.ndim == 3 else a
        return a / (65535.0 if a.max() > 255 else 255.0) > MASK_THRESHOLD
    if image_alpha is None:
        raise InputError(png, "no ground-truth alpha (neither this file nor an alpha channel in the image)")
    return image_alpha > MASK_THRESHOLD


def load_ground_truth(root: Path, name: str) -> dict[str, np.ndarray]:
    """Ground truth of one test view: rgb (linear, premultiplied), mask, basecolor, metallic,
    roughness, normal (Blender world)."""
    dataset = DatasetDir(root)
    rgb, alpha = _read_rgba(dataset.image(name).with_suffix(".exr"))
    gt = {"rgb": rgb, "mask": _read_mask(root, name, alpha)}
    for i in brdf.INPUTS:
        gt[i.name] = _read_rgba(dataset.gt(name, i.name))[0] if i.colour else _read_map(dataset.gt(name, i.name))
    normal_path = dataset.gt(name, "normal")
    if normal_path.is_file():
        gt["normal"], _ = _read_rgba(normal_path)
    material_path = dataset.gt(name, "material")
    if material_path.is_file():
        import imageio.v3 as iio

        checked_kind(material_path)
        gt["material"] = np.asarray(iio.imread(material_path))
    return gt


# --------------------------------------------------------------------------------------------
# Evaluation


def _normal_error_deg(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray) -> float:
    p, g = pred[mask], gt[mask]
    p = p / np.maximum(np.linalg.norm(p, axis=-1, keepdims=True), 1e-12)
    g = g / np.maximum(np.linalg.norm(g, axis=-1, keepdims=True), 1e-12)
    cos = np.clip(np.sum(p * g, -1), -1.0, 1.0)
    return float(np.degrees(np.arccos(cos)).mean()) if len(cos) else math.nan


class RunPredictor:
    """What `evaluate_predictor` needs from a fitted run: its world convention, default spp, number
    of materials, and a renderer under its own lighting (envmap None) or another envmap."""

    def __init__(self, run_dir: str | Path, checkpoint: str | Path | None = None):
        self.run = RunDir(run_dir)
        self.fitted = self.run.load(checkpoint)
        self.world = self.fitted.world
        self.default_spp = int(self.fitted.cfg.render.spp)
        self.default_aa = int(self.fitted.cfg.render.aa)
        self.num_materials = self.fitted.num_materials

    def renderer(self, envmap: np.ndarray | None = None):
        from vq_mitsuba.render.views import Renderer

        return Renderer(self.fitted, envmap=envmap)

    def fit_summary(self) -> dict:
        return {k: v for k, v in self.run.fit_summary().items() if k in ("iterations", "seconds", "iterations_per_s")}


def evaluate(run_dir: str | Path, dataset_dir: str | Path, spp: int | None = None, scale_method: str = "lstsq",
             output: str | Path | None = None, aa: int = DEFAULT_AA,
             meanshift_bandwidths=MEANSHIFT_BANDWIDTHS, checkpoint: str | Path | None = None) -> dict:
    """Score the fitted run RUN_DIR on the test views of DATASET_DIR; writes RUN_DIR/metrics.json
    (or `output`) and returns the same nested dict. spp None: the run's render.spp (default 256).
    `checkpoint`: score this state of the run (e.g. a snapshot) instead of its last checkpoint."""
    if scale_method not in M.SCALE_METHODS:  # before loading anything
        raise InputError(None, f"unknown scale method '{scale_method}' (use {' or '.join(M.SCALE_METHODS)})")
    dataset_root(dataset_dir)
    predictor = RunPredictor(run_dir, checkpoint)
    return evaluate_predictor(predictor, dataset_dir, spp=spp, scale_method=scale_method,
                              output=Path(output) if output is not None else predictor.run / RunDir.METRICS,
                              aa=aa, meanshift_bandwidths=meanshift_bandwidths,
                              run_label=str(Path(run_dir).resolve()), fit_summary=predictor.fit_summary())


def evaluate_predictor(predictor, dataset_dir: str | Path, spp: int | None = None, scale_method: str = "lstsq",
                       output: str | Path | None = None, aa: int = DEFAULT_AA,
                       meanshift_bandwidths=MEANSHIFT_BANDWIDTHS, run_label: str = "",
                       fit_summary: dict | None = None) -> dict:
    """The scores of `evaluate` for any predictor: an object with `world` ("mitsuba" or "blender"),
    `default_spp`, `default_aa`, `num_materials` (None without a segmentation) and `renderer(envmap)` returning
    an object whose `render(camera, spp=, aa=, seed=)` gives the maps of `render.views.Renderer.render`
    (`render.views.Renderer`s of one run render all relighting envmaps of a view in one pass, see
    `relit_views`). Writes `output` when given."""
    from vq_mitsuba import messages

    if scale_method not in M.SCALE_METHODS:
        raise InputError(None, f"unknown scale method '{scale_method}' (use {' or '.join(M.SCALE_METHODS)})")
    t0 = time.perf_counter()
    data = _load_test_views(dataset_dir, predictor.world)
    spp = int(spp or predictor.default_spp)
    bar = messages.progress(total=len(data.views) * (1 + len(data.envs)), desc="eval", unit="view")
    preds = _render_fitted_lighting(predictor, data, spp, aa, bar)
    per_view, scales = _image_scores(data, preds, scale_method)
    bc_scales = scales[brdf.BASECOLOR]  # the albedo's: relighting and coverage are scored with it too
    discrete = _discrete_branch_scores(preds, data.gts, scale_method)
    segmentation = _segmentation_scores(preds, data.gts, predictor.num_materials, data.meta)
    surface = evaluate_surface(predictor, data, aa or predictor.default_aa, scale_method)
    per_material = per_material_scores(preds, data.gts, scales, data.meta)
    meanshift = None
    if meanshift_bandwidths and all("material" in g for g in data.gts):
        meanshift = meanshift_segmentation(preds, data.gts, meanshift_bandwidths, seed=0)
    del preds
    relighting = _relighting_scores(predictor, data, per_view, bc_scales, spp, aa, bar, scale_method)
    bar.close()
    result = _assemble_result(data, per_view, bc_scales, relighting, scale_method, run_label=run_label,
                              render={"spp": spp, "aa": aa or predictor.default_aa}, discrete=discrete,
                              segmentation=segmentation, meanshift=meanshift, per_material=per_material,
                              fit_summary=fit_summary, t0=t0)
    result["surface_material"] = surface  # the materials at the true surface (eval/surface.py), or None
    result = {**EVAL_MARK, **result}  # `eval -o` replaces only a file that holds this mark
    if output is not None:
        out_path = Path(output)
        out_path.parent.mkdir(parents=True, exist_ok=True)
        write_json(out_path, json_safe(result))
    return result


@dataclass
class _TestViews:
    """A dataset's test views as `evaluate_predictor` scores them."""

    root: Path
    meta: dict  # scene.json
    cameras: list  # the test cameras in the dataset's world
    views: list  # the same cameras in the predictor's world
    envs: list[tuple[str, Path]]  # relighting conditions (name, envmap)
    gts: list[dict]  # load_ground_truth of each view
    cameras_world: str  # the world of the dataset's cameras (and of its mesh.ply)


def _load_test_views(dataset_dir: str | Path, run_world: str) -> _TestViews:
    """The test cameras, relighting envmaps and ground truth of a dataset, checked: every envmap
    (vq_mitsuba.data.envmaps.check_envmap), every relit view on disk, every image the size of its camera."""
    from vq_mitsuba.data.captures import load_cameras
    from vq_mitsuba.data.cameras import convert_world

    dataset = DatasetDir.find(dataset_dir)
    root = dataset.dir
    meta = dataset.info()
    cameras, cam_world, _ = load_cameras(dataset / DatasetDir.TRANSFORMS_TEST)
    envs = dataset.relight_envs(meta)
    for env_name, env_path in envs:
        load_envmap(env_path)  # checked before any work (and read again when the relit views are rendered)
        for cam in cameras:
            p = dataset.image(cam.name, env_name).with_suffix(".exr")
            if not p.is_file():
                raise InputError(p, f"relit view missing for '{env_name}'")
    gts = [load_ground_truth(root, cam.name) for cam in cameras]
    for cam, gt in zip(cameras, gts):
        if gt["rgb"].shape[:2] != (cam.height, cam.width):
            raise InputError(dataset.image(cam.name).with_suffix(".exr"),
                             f"size differs from {DatasetDir.TRANSFORMS_TEST}")
        if min(cam.width, cam.height) < MIN_SIDE:
            raise InputError(dataset / DatasetDir.TRANSFORMS_TEST, f"test view {cam.name} is {cam.width}x"
                                                                   f"{cam.height} pixels: SSIM needs at least "
                                                                   f"{MIN_SIDE} per side")
    views = [convert_world(cam, cam_world, run_world) for cam in cameras]
    return _TestViews(root, meta, cameras, views, envs, gts, cam_world)


def _render_fitted_lighting(predictor, data: _TestViews, spp: int, aa: int | None, bar) -> list[dict]:
    """The predictor's maps of every test view under its own lighting (novel views, material
    maps), normals in Blender world as the ground truth's."""
    from vq_mitsuba.data.cameras import MITSUBA_TO_BLENDER
    from vq_mitsuba.render.views import check_finite

    renderer = predictor.renderer(None)
    preds = []
    for i, cam in enumerate(data.views):
        out = renderer.render(cam, spp=spp, aa=aa, seed=i)
        check_finite(out, cam.name)  # no score of a NaN image is written
        if "rgb_physical" in out:  # every score but novel_view_residual sees the physically based render
            out["rgb_residual"], out["rgb"] = out["rgb"], out.pop("rgb_physical")
        if predictor.world == "mitsuba":  # GT normals are in Blender world = R @ Mitsuba world
            out["normal"] = out["normal"] @ MITSUBA_TO_BLENDER.T
        preds.append(out)
        bar.update(1)
    return preds


def _image_scores(data: _TestViews, preds: list[dict],
                  scale_method: str) -> tuple[list[dict], dict[str, np.ndarray]]:
    """(per-view rows of the novel-view, every BRDF input's, normal and coverage scores, each
    colour input's alignment scales computed over all views jointly)."""
    gts = data.gts
    masks = np.stack([gt["mask"] for gt in gts])
    scales = input_scores.alignment_scales(preds, gts, masks, scale_method)
    bc_scales = scales[brdf.BASECOLOR]
    per_view = []
    for cam, pred, gt in zip(data.cameras, preds, gts):
        m = gt["mask"]
        nv = M.image_metrics(pred["rgb"], gt["rgb"], m)
        row = {"view": cam.name, "pixels": int(m.sum()),
               "novel_view_psnr": nv["psnr"], "novel_view_ssim": nv["ssim"],
               **({"novel_view_residual_" + k: v for k, v in M.image_metrics(pred["rgb_residual"], gt["rgb"], m).items()}
                  if "rgb_residual" in pred else {}),
               **input_scores.view_scores(pred, gt, m, scales, unaligned=True)}
        if "normal" in gt:
            row["normal_mae_deg"] = _normal_error_deg(pred["normal"], gt["normal"], m)
        row.update(coverage_scores(pred["alpha"], pred[brdf.BASECOLOR] * bc_scales, gt[brdf.BASECOLOR], m))
        per_view.append(row)
    return per_view, scales


def _discrete_branch_scores(preds: list[dict], gts: list[dict], scale_method: str) -> dict | None:
    """The discrete branch's scores of every BRDF input (a colour aligned on its own); None when
    the predictor has no discrete branch."""
    if not all("discrete" in p for p in preds):
        return None
    masks = np.stack([gt["mask"] for gt in gts])
    dmaps = [p["discrete"] for p in preds]
    scales = input_scores.alignment_scales(dmaps, gts, masks, scale_method)
    rows = [input_scores.view_scores(d, gt, gt["mask"], scales, mae=False) for d, gt in zip(dmaps, gts)]
    out = input_scores.mean_scores(rows, mae=False)
    for name, s in scales.items():
        out[name]["scales"] = [float(x) for x in s]
    return out


def _segmentation_scores(preds: list[dict], gts: list[dict], num_materials: int | None, meta: dict) -> dict | None:
    """Segmentation F1 of the predicted material ids against the true ones; None without either."""
    if not (all("material" in p for p in preds) and all("material" in g for g in gts)):
        return None
    # Pooled over all test views: a predicted id names the same material in every view.
    segmentation = M.segmentation_scores(np.concatenate([p["material"].ravel() for p in preds]),
                                         np.concatenate([g["material"].ravel() for g in gts]),
                                         np.concatenate([g["mask"].ravel() for g in gts]))
    segmentation["mapping"] = {str(k): v for k, v in segmentation["mapping"].items()}
    segmentation["num_materials_found"] = num_materials
    segmentation["num_materials_true"] = len(meta.get("materials", []))
    return segmentation


def _relighting_scores(predictor, data: _TestViews, per_view: list[dict], bc_scales: np.ndarray, spp: int,
                       aa: int | None, bar, scale_method: str) -> dict:
    """Relighting under each held-aside envmap, view by view (one pass per view renders all
    envmaps), in both alignment variants; adds each view's relit PSNRs to its per_view row."""
    envs = data.envs
    renderers = [predictor.renderer(load_envmap(env_path)) for _, env_path in envs]  # the one envmap check
    rows = {name: {"albedo_scale": [], "image_scale": []} for name, _ in envs}
    for i, (cam, view, gt) in enumerate(zip(data.cameras, data.views, data.gts)):
        m = gt["mask"]
        for (env_name, _), pred in zip(envs, relit_views(renderers, view, spp=spp, aa=aa, seed=i)):
            ref, _ = _read_rgba(DatasetDir(data.root).image(cam.name, env_name).with_suffix(".exr"))
            pred = pred.astype(np.float64)
            env_rows = rows[env_name]
            env_rows["albedo_scale"].append(M.image_metrics(pred * bc_scales, ref, m))
            aligned, _ = M.scale_align(pred, ref, m, method="lstsq")
            env_rows["image_scale"].append(M.image_metrics(aligned, ref, m))
            for variant in env_rows:
                per_view[i][f"relit_{env_name}_{variant}_psnr"] = env_rows[variant][-1]["psnr"]
            bar.update(1)
    del renderers
    relit: dict[str, dict] = {"albedo_scale": {}, "image_scale": {}}
    for env_name, env_rows in rows.items():
        for variant, r in env_rows.items():
            relit[variant][env_name] = {"psnr": M.mean_of(x["psnr"] for x in r), "ssim": M.mean_of(x["ssim"] for x in r)}
    relighting = {}
    notes = {"albedo_scale": "relit render x basecolor alignment scales (" + scale_method + ")",
             "image_scale": "relit render aligned per image and channel (lstsq)"}
    for variant, per_env in relit.items():
        relighting[variant] = {
            "alignment": notes[variant], "envs": per_env,
            "mean": {"psnr": M.mean_of(v["psnr"] for v in per_env.values()),
                     "ssim": M.mean_of(v["ssim"] for v in per_env.values())} if per_env else None,
        }
    return relighting


def _assemble_result(data: _TestViews, per_view: list[dict], bc_scales: np.ndarray, relighting: dict,
                     scale_method: str, run_label: str, render: dict, discrete: dict | None,
                     segmentation: dict | None, meanshift: dict | None, per_material: list | None,
                     fit_summary: dict | None, t0: float) -> dict:
    """metrics.json's dict: the per-view rows and their means, beside the scores over all views;
    `seconds` counts from t0."""
    def avg(key):
        return M.mean_of(row[key] for row in per_view if key in row)

    cameras = data.cameras
    return {
        "run": run_label,
        "dataset": str(data.root.resolve()),
        "scene": data.meta.get("name"),
        "n_views": len(cameras),
        "resolution": [cameras[0].width, cameras[0].height] if cameras else None,
        "render": render,
        "mask": f"ground-truth alpha > {MASK_THRESHOLD}",
        "color_space": "images and basecolor: sRGB of clipped linear values; metallic, roughness: linear [0, 1]",
        "novel_view": {"psnr": avg("novel_view_psnr"), "ssim": avg("novel_view_ssim")},
        "novel_view_residual": {"psnr": avg("novel_view_residual_psnr"), "ssim": avg("novel_view_residual_ssim")}
        if any("novel_view_residual_psnr" in row for row in per_view) else None,
        **{name: {**s, **({"aligned_with": scale_method} if brdf.get(name).colour else {})}
           for name, s in input_scores.mean_scores(per_view, unaligned=True).items()},
        "alignment": {"method": scale_method, "scales": [float(s) for s in bc_scales],
                      "computed_over": "all test views jointly, foreground pixels, linear basecolor"},
        "normal": {"mae_deg": avg("normal_mae_deg")},
        "coverage": {"iou": avg("coverage_iou"), "basecolor_psnr_covered": avg("basecolor_psnr_covered"),
                     "what": "predicted alpha >= 0.5 against the ground-truth mask; basecolor PSNR (aligned) on "
                             "the foreground pixels the prediction covers"},
        "relighting": relighting,
        "discrete_branch": discrete,
        "segmentation": segmentation,
        "meanshift": meanshift,
        "per_material": per_material,
        "fit": fit_summary or {},
        "per_view": per_view,
        "seconds": time.perf_counter() - t0,
    }


def relit_views(renderers: list, camera, spp: int, aa: int | None, seed: int) -> list[np.ndarray]:
    """The rgb image of one view under each renderer's lighting. Renderers of a fitted run
    (`render.views.Renderer`) share one pass: the rays and the material field are evaluated once."""
    from vq_mitsuba.render.views import Renderer, check_finite

    if not renderers:
        return []
    first, *rest = renderers
    if all(isinstance(r, Renderer) for r in renderers):  # `Renderer.render` checks they share one run
        out = first.render(camera, spp=spp, aa=aa, seed=seed, relight=rest)
        images = [out["rgb"], *out.get("relit", [])]
    else:
        images = [r.render(camera, spp=spp, aa=aa, seed=seed)["rgb"] for r in renderers]
    check_finite({f"relit {i}": im for i, im in enumerate(images)}, camera.name)
    return images


def coverage_scores(alpha: np.ndarray, basecolor: np.ndarray, gt_basecolor: np.ndarray, mask: np.ndarray) -> dict:
    """How well a view's silhouette matches the truth, and the basecolor PSNR (sRGB; `basecolor`
    already aligned) on the foreground pixels it covers. A reconstructed mesh misses some
    foreground pixels, where the maps are empty: this separates that from the material error."""
    covered = np.asarray(alpha) >= 0.5
    return {"coverage_iou": float((covered & mask).sum() / max((covered | mask).sum(), 1)),
            "basecolor_psnr_covered": M.psnr(M.srgb(basecolor), M.srgb(gt_basecolor), mask & covered)}


def per_material_scores(preds: list[dict], gts: list[dict], scales: dict[str, np.ndarray] | np.ndarray,
                        meta: dict) -> list[dict] | None:
    """Each ground-truth material's pixels pooled over the test views: the mean fitted value of
    every BRDF input (a colour linear, after its alignment `scales`, {input: (3,)}, or an array:
    the basecolor's) beside the true mean, a scalar's mean absolute error, and the novel-view PSNR
    there. Shows which material a fit got wrong. None when the dataset has no material ids."""
    if not isinstance(scales, dict):
        scales = {brdf.BASECOLOR: scales}
    if not all("material" in g for g in gts):
        return None
    names = {int(m["id"]): str(m.get("name", m["id"])) for m in meta.get("materials", []) if "id" in m}
    ids = np.concatenate([g["material"][g["mask"]].ravel() for g in gts])
    rows = []
    for k in sorted(int(v) for v in np.unique(ids) if v > 0):
        sel = [(g["material"] == k) & g["mask"] for g in gts]
        def pick(maps, key):  # (pixels, channels) of this material in every view (some views have none)
            return np.concatenate([m[key][s] if m[key].ndim == 3 else m[key][s][:, None] for m, s in zip(maps, sel)])
        row = {"id": k, "name": names.get(k, str(k)), "pixels": int(sum(s.sum() for s in sel))}
        errors = {}
        for i in brdf.INPUTS:
            p, g = pick(preds, i.name)[:, :i.channels], pick(gts, i.name)[:, :i.channels]
            if i.colour:
                p = p * scales[i.name]
                row[i.name], row[f"{i.name}_true"] = [float(x) for x in p.mean(0)], [float(x) for x in g.mean(0)]
            else:
                row[i.name], row[f"{i.name}_true"] = float(p.mean()), float(g.mean())
                errors[f"{i.name}_mae"] = float(np.abs(p - g).mean())
        rgb_p, rgb_g = pick(preds, "rgb"), pick(gts, "rgb")[:, :3]
        rows.append({**row, **errors, "novel_view_psnr": M.psnr(M.srgb(rgb_p), M.srgb(rgb_g))})
    return rows


def meanshift_segmentation(preds: list[dict], gts: list[dict], bandwidths, seed: int = 0) -> dict:
    """The MeanShift baseline on the continuous branch's BRDF maps of the test views, pooled
    over views like the discrete branch's scores: one entry per bandwidth."""
    from vq_mitsuba.eval.baselines import brdf_features, meanshift_labels

    fg = [g["mask"] & (g["material"] > 0) for g in gts]
    feats = np.concatenate([brdf_features(*(p[name][m] for name in brdf.NAMES)) for p, m in zip(preds, fg)])
    truth = np.concatenate([g["material"][m] for g, m in zip(gts, fg)])
    out = {"features": "sRGB basecolor, metallic, roughness (continuous branch, test views)"}
    for bw in bandwidths:
        t0 = time.perf_counter()
        labels = meanshift_labels(feats, float(bw), seed=seed)
        scores = M.segmentation_scores(labels, truth)
        scores.pop("mapping")
        scores["num_materials_found"] = int(labels.max())
        scores["seconds"] = time.perf_counter() - t0
        out[f"{float(bw):g}"] = scores
    return out
