"""Draws docs/edit.png, the editing figure of the README, from a fitted demo run:

    .venv/bin/python docs/edit_figure.py [runs/demo] [--envmap data/demo/envmaps/sunset.exr]

Panels: a test view of the fit, the same view after `edit --material 2 --preset gold` (the
torus), and the edited run relit under another envmap; with the segmentation overlay.
"""

import argparse
import sys
import tempfile
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))


def over_white(images) -> np.ndarray:
    from vq_mitsuba.data.imageio import linear_to_srgb

    a = images["alpha"][..., None]
    straight = images["rgb"] / np.maximum(a, 1e-6)
    return np.clip(linear_to_srgb(np.clip(straight, 0, 1)) * a + (1 - a), 0, 1)


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("run", nargs="?", default=str(ROOT / "runs" / "demo"))
    p.add_argument("--envmap", default=str(ROOT / "data" / "demo" / "envmaps" / "sunset.exr"))
    p.add_argument("--material", type=int, default=2)
    p.add_argument("--preset", default="gold")
    p.add_argument("--size", type=int, default=320)
    p.add_argument("-o", "--output", default=str(ROOT / "docs" / "edit.png"))
    args = p.parse_args()

    from vq_mitsuba.data.cameras import Camera
    from vq_mitsuba.data.imageio import read_image
    from vq_mitsuba.edit import build_edit, edit_run
    from vq_mitsuba.run.run_dir import RunDir
    from vq_mitsuba.render.views import Renderer, segmentation_overlay

    run = RunDir(args.run)
    fitted = run.load()
    with tempfile.TemporaryDirectory() as tmp:
        edited = edit_run(run, Path(tmp) / "edited",
                          build_edit(run, fitted, materials=[args.material], preset=args.preset)).load()
    cams = run.cameras()
    cam = (cams.get("test") or cams["train"])[0]
    cam = Camera(cam.name, cam.to_world, cam.fov_x_deg, args.size, args.size)
    before = Renderer(fitted).render(cam, spp=256)
    after = Renderer(edited).render(cam, spp=256)
    relit = Renderer(edited, envmap=read_image(args.envmap)[0]).render(cam, spp=256)
    panels = [(segmentation_overlay(before["rgb"], before["alpha"], before["material"]), "segmentation (M = "
               f"{fitted.num_materials})"),
              (over_white(before), "fitted"),
              (over_white(after), f"edit --material {args.material} --preset {args.preset}"),
              (over_white(relit), f"edited, relit ({Path(args.envmap).stem})")]
    ys, xs = np.nonzero(before["alpha"] > 0)
    m = args.size // 16
    y0, y1 = max(ys.min() - m, 0), min(ys.max() + m + 1, args.size)
    x0, x1 = max(xs.min() - m, 0), min(xs.max() + m + 1, args.size)
    fig, axes = plt.subplots(1, len(panels), figsize=(3.0 * len(panels), 3.3))
    for ax, (img, title) in zip(axes, panels):
        ax.imshow(img[y0:y1, x0:x1])
        ax.set_title(title, fontsize=9)
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(args.output, dpi=110, bbox_inches="tight")
    print(f"written {args.output}")


if __name__ == "__main__":
    main()
