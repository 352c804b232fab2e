#!/usr/bin/env python
"""Figure: a real capture's held-out photos beside the fitted run's renders of the same views.

    python benchmarks/holdout_figure.py RUN_DIR [--views 4] [--spp 64] [--size 400] -o FIGURE.png

RUN_DIR is a run fitted with `--holdout K`. Rows: the held-out photo (its background greyed
outside the mask the run is scored in), the physically based render, the render with the
residual (when the run has one), and its basecolor. Prints each view's PSNR inside that mask and
writes FIGURE.json beside the figure.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from provenance import command_line, describe, write_result


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    ap.add_argument("run", type=Path, help="run directory fitted with --holdout K")
    ap.add_argument("--views", type=int, default=4, help="held-out views shown, spread over all of them")
    ap.add_argument("--spp", type=int, default=64, help="samples per pixel of the renders")
    ap.add_argument("--size", type=int, default=400, help="longest side of each panel in pixels")
    ap.add_argument("-o", "--output", type=Path, required=True, help="figure (PNG) written")
    args = ap.parse_args(argv)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from vq_mitsuba.data.resize import Shrink
    from vq_mitsuba.eval import metrics as M
    from vq_mitsuba.eval.evaluate import held_out_capture, straight_colours
    from vq_mitsuba.render.views import Renderer
    from vq_mitsuba.run.run_dir import RunDir

    run = RunDir(args.run)
    held = held_out_capture(run)
    picks = np.unique(np.linspace(0, len(held.cameras) - 1, min(args.views, len(held.cameras))).round().astype(int))
    renderer = Renderer(run.load())
    shrink = Shrink(1, args.size)
    rows, columns = [], None
    for i in picks:
        cam, photo, alpha = held.cameras[i], held.images[i], held.alpha[i]
        out = renderer.render(cam, spp=args.spp)
        mask = alpha > 0.5
        physical, with_residual = straight_colours(out)
        panels = {"photo": np.where(mask[..., None], photo, 0.5 * photo + 0.1), "render": physical}
        row = {"view": cam.name, "psnr": M.image_metrics(physical, photo, mask)["psnr"]}
        if with_residual is not None:
            panels["with residual"] = with_residual
            row["residual_psnr"] = M.image_metrics(with_residual, photo, mask)["psnr"]
        if "basecolor" in out:
            panels["basecolor"] = out["basecolor"]
        columns = list(panels)
        rows.append((row, {k: M.srgb(shrink.image(np.asarray(v, np.float32))) for k, v in panels.items()}))
        print(f"{cam.name}: {row['psnr']:.2f} dB" + (f", {row['residual_psnr']:.2f} dB with the residual"
                                                      if "residual_psnr" in row else ""))
    fig, axes = plt.subplots(len(rows), len(columns), figsize=(3.2 * len(columns), 3.2 * len(rows) * 0.9),
                             squeeze=False)
    for r, (row, panels) in enumerate(rows):
        for c, name in enumerate(columns):
            ax = axes[r, c]
            ax.imshow(np.clip(panels[name], 0, 1))
            ax.set_xticks([])
            ax.set_yticks([])
            if r == 0:
                ax.set_title(name)
            if c == 0:
                ax.set_ylabel(row["view"])
            if name == "render":
                ax.set_xlabel(f"{row['psnr']:.2f} dB")
            if name == "with residual":
                ax.set_xlabel(f"{row['residual_psnr']:.2f} dB")
    fig.tight_layout()
    args.output.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.output, dpi=100)
    write_result(args.output.with_suffix(".json"), {"command": command_line(argv, __file__), "run": str(args.run),
                                                    "spp": args.spp, "views": [row for row, _ in rows]})
    print(describe())
    print(f"figure written to {args.output}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
