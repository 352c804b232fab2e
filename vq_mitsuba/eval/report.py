"""The readable table of `vq-mitsuba eval`'s scores (metrics.json of a synthetic dataset), as the
CLI prints it."""

from __future__ import annotations

import math

from vq_mitsuba import brdf
from vq_mitsuba.eval import input_scores

def _fmt(x, digits: int) -> str:
    if x is None:
        return "-"
    if isinstance(x, str):
        return x
    if math.isnan(x):
        return "nan"
    if math.isinf(x):
        return "inf" if x > 0 else "-inf"
    return f"{x:.{digits}f}"


def table_rows(metrics: dict) -> list[tuple[str, object, object]]:
    """(label, PSNR, SSIM) rows of the readable table; SSIM None where not computed."""
    method = metrics["alignment"]["method"]
    rows = [("novel view", metrics["novel_view"]["psnr"], metrics["novel_view"]["ssim"])]
    if metrics.get("novel_view_residual"):
        rows.append(("novel view + residual", metrics["novel_view_residual"]["psnr"],
                     metrics["novel_view_residual"]["ssim"]))
    rows += input_scores.table_rows(metrics, method)
    d = metrics.get("discrete_branch")
    if d:
        rows += input_scores.table_rows(d, method, prefix="discrete: ")
    for variant in ("albedo_scale", "image_scale"):
        block = metrics["relighting"][variant]
        for env, v in block["envs"].items():
            rows.append((f"relit {env} ({variant})", v["psnr"], v["ssim"]))
        if block["mean"] is not None and len(block["envs"]) > 1:
            rows.append((f"relit mean ({variant})", block["mean"]["psnr"], block["mean"]["ssim"]))
    return rows


def format_table(metrics: dict) -> str:
    """A plain-text table of the headline figures."""
    rows = table_rows(metrics)
    width = max(len(r[0]) for r in rows)
    lines = [f"{metrics.get('scene') or 'run'}: {metrics['n_views']} test views, {metrics['render']['spp']} spp, "
             f"mask {metrics['mask']}",
             f"{'':{width}}  {'PSNR':>7}  {'SSIM':>6}"]
    lines += [f"{label:{width}}  {_fmt(p, 2):>7}  {_fmt(s, 4):>6}" for label, p, s in rows]
    scales = ", ".join(f"{s:.3f}" for s in metrics["alignment"]["scales"])
    lines.append(f"basecolor scales ({metrics['alignment']['method']}): {scales}")
    cov = metrics.get("coverage")
    if cov and cov["iou"] is not None:
        lines.append(f"silhouette IoU {cov['iou']:.4f}; basecolor PSNR on the covered foreground "
                     f"{_fmt(cov['basecolor_psnr_covered'], 2)} dB")
    if metrics["normal"]["mae_deg"] is not None and not math.isnan(metrics["normal"]["mae_deg"]):
        lines.append(f"normal mean angular error: {metrics['normal']['mae_deg']:.2f} deg")
    surf = metrics.get("surface_material")
    if surf:
        each = ", ".join(f"{i.name} {_fmt(surf[i.name]['psnr'], 2)} dB" for i in brdf.INPUTS if i.name in surf)
        lines.append(f"materials at the true surface (nearest point of the run's mesh): {each}; true points "
                     f"{_fmt(surf['distance']['median'], 4)} (median) from the run's mesh")
    seg = metrics.get("segmentation")
    if seg:
        lines.append(f"segmentation: micro-F1 {seg['micro_f1']:.3f}, macro-F1 {seg['macro_f1']:.3f}, "
                     f"precision {seg['macro_precision']:.3f}, recall {seg['macro_recall']:.3f}; "
                     f"materials found {seg['num_materials_found']} (true {seg['num_materials_true']})")
    mats = metrics.get("per_material")
    if mats:
        lines.append("per material (fitted / true; basecolor linear, aligned):")
        w = max(len(m["name"]) for m in mats)
        value = lambda v: "(" + ", ".join(f"{x:.2f}" for x in v) + ")" if isinstance(v, list) else f"{v:.2f}"
        for m in mats:
            each = "".join(f"{i.name} {value(m[i.name])} / {value(m[i.name + '_true'])}  "
                           for i in brdf.INPUTS if i.name in m)
            lines.append(f"  {m['name']:{w}}  {each}view {_fmt(m['novel_view_psnr'], 2)} dB")
    ms = metrics.get("meanshift")
    if ms:
        for bw, v in ms.items():
            if isinstance(v, dict):
                lines.append(f"MeanShift baseline (bandwidth {bw}): micro-F1 {v['micro_f1']:.3f}, "
                             f"macro-F1 {v['macro_f1']:.3f}; clusters {v['num_materials_found']}")
    return "\n".join(lines)
