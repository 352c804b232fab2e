#!/usr/bin/env python
"""Figure: the same scene's ground truth from Mitsuba and from Blender Cycles, side by side.

    python benchmarks/renderer_figure.py MITSUBA_DATASET CYCLES_DATASET [--view test_000]
        [--envs sunset studio] [-o docs/cycles_vs_mitsuba.png]

Both datasets are `vq-mitsuba make-scene` outputs of one scene with the same resolution and seed
(so the same cameras). Rows: Mitsuba, Cycles, and their absolute difference (x4). Columns: the
test view, the basecolor map, the material-id map, and the view relit under each envmap. Prints
the PSNR between the two renderers for every image, over the ground-truth foreground.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from vq_mitsuba.eval import metrics as M
from vq_mitsuba.data.imageio import read_image
from vq_mitsuba.errors import InputError
from vq_mitsuba.eval.evaluate import dataset_root, load_ground_truth

REPO = Path(__file__).resolve().parent.parent

PALETTE = np.array([[0, 0, 0], [0.90, 0.35, 0.20], [0.25, 0.50, 0.90], [0.30, 0.75, 0.35], [0.95, 0.80, 0.25],
                    [0.65, 0.40, 0.80], [0.40, 0.85, 0.85], [0.85, 0.45, 0.65], [0.6, 0.6, 0.6]])


def panels(root: Path, view: str, envs: list[str]) -> dict[str, np.ndarray]:
    """Display images (sRGB in [0, 1], HxWx3) and the linear images they come from."""
    gt = load_ground_truth(root, view)
    out = {"view": gt["rgb"], "basecolor": gt["basecolor"]}
    for env in envs:
        path = root / "relit" / env / f"{view}.exr"
        if not path.is_file():
            raise InputError(path, f"relit view missing (is '{env}' one of the dataset's envmaps?)")
        img, _ = read_image(path)
        out[f"relit {env}"] = img[..., :3]
    mat = gt.get("material")
    if mat is None:
        raise InputError(root / "gt" / f"{view}_material.png", "material map missing")
    return out, mat, gt["mask"]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    ap.add_argument("mitsuba", type=Path, help="dataset rendered by Mitsuba")
    ap.add_argument("cycles", type=Path, help="the same scene rendered by Cycles (--renderer cycles)")
    ap.add_argument("--view", default="test_000", help="test view name (default test_000)")
    ap.add_argument("--envs", nargs="+", default=["sunset", "studio"], help="relighting envmaps to show")
    ap.add_argument("-o", "--output", type=Path, default=REPO / "docs" / "cycles_vs_mitsuba.png")
    args = ap.parse_args(argv)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    roots = [dataset_root(args.mitsuba), dataset_root(args.cycles)]
    metas = [json.loads((r / "scene.json").read_text()) for r in roots]
    if metas[0]["resolution"] != metas[1]["resolution"] or metas[0].get("seed") != metas[1].get("seed"):
        raise InputError(roots[1] / "scene.json", "resolution or seed differs from the Mitsuba dataset's: "
                         "the cameras would not match")
    (pm, mat_m, mask_m), (pc, mat_c, mask_c) = (panels(r, args.view, args.envs) for r in roots)
    mask = mask_m & mask_c
    names = list(pm) + ["material ids"]
    fig, axes = plt.subplots(3, len(names), figsize=(2.3 * len(names), 7.2), squeeze=False)
    print(f"{metas[0]['name']} / {args.view}: PSNR between the renderers (sRGB, foreground); "
          f"material ids agree on {100 * np.mean(mat_m[mask] == mat_c[mask]):.1f}% of the foreground")
    for j, name in enumerate(names):
        if name == "material ids":
            imgs = [PALETTE[np.clip(mat_m, 0, len(PALETTE) - 1)], PALETTE[np.clip(mat_c, 0, len(PALETTE) - 1)]]
            diff = (mat_m != mat_c).astype(np.float64)[..., None].repeat(3, -1)
            label = f"{name}\nagree {100 * np.mean(mat_m[mask] == mat_c[mask]):.1f}%"
        else:
            imgs = [M.srgb(pm[name]), M.srgb(pc[name])]
            diff = np.clip(4 * np.abs(imgs[0] - imgs[1]), 0, 1)
            p = M.psnr(imgs[0], imgs[1], mask)
            print(f"  {name:16s} {p:6.2f} dB")
            label = f"{name}\n{p:.1f} dB apart"
        for i, img in enumerate(imgs + [diff]):
            ax = axes[i][j]
            ax.imshow(np.clip(img, 0, 1), interpolation="nearest")
            ax.set_xticks([])
            ax.set_yticks([])
            if i == 0:
                ax.set_title(label, fontsize=9)
            if j == 0:
                ax.set_ylabel(["Mitsuba", "Cycles", "|difference| x4"][i])
    fig.tight_layout()
    args.output.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.output, dpi=100)
    print(f"wrote {args.output}")
    return 0


if __name__ == "__main__":
    try:
        sys.exit(main())
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        sys.exit(2)
