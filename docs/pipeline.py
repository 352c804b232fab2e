"""Draws docs/pipeline.png, the pipeline figure of the README: `python docs/pipeline.py`."""

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from matplotlib.patches import FancyBboxPatch  # noqa: E402

BLUE, ORANGE, GREEN, RED, PURPLE, GREY = "#dce8f5", "#fde3c6", "#dcefd6", "#f6d8d8", "#ebe0f4", "#eeeeee"

# name: (x, y, w, h, colour, title, body)
BOXES = {
    "capture": (0.1, 5.0, 2.2, 1.5, BLUE, "Capture", "posed images, masks;\nMitsuba XML or NeRF json"),
    "geometry": (2.7, 5.0, 2.4, 1.5, BLUE, "Geometry", "the capture's mesh, or\nNeuS -> marching cubes"),
    "hits": (5.5, 5.0, 2.3, 1.5, BLUE, "Primary hits", "traced once by Mitsuba:\nposition, normal, view"),
    "encoder": (8.2, 5.0, 2.4, 1.5, ORANGE, "Encoder", "positional encoding\n(coarse-to-fine) + MLP -> z"),
    "cont": (8.2, 2.9, 2.4, 1.4, ORANGE, "Continuous decoder", "basecolor, metallic,\nroughness per point"),
    "vq": (11.0, 5.0, 2.6, 1.5, ORANGE, "Codebook (VQ-EMA)", "nearest codeword, straight-\nthrough; codeword dropout"),
    "disc": (11.0, 2.9, 2.6, 1.4, ORANGE, "Discrete decoder", "one BRDF per codeword"),
    "mitsuba": (5.0, 2.9, 2.8, 1.4, GREEN, "Mitsuba principled BSDF", "dr.wrap; envmap emitter\nsampling + BSDF, MIS, 1 bounce"),
    "envmap": (2.4, 2.9, 2.2, 1.4, PURPLE, "Envmap", "learned lat-long\nlog radiance (or given)"),
    "loss": (0.1, 0.5, 4.5, 1.5, RED, "Losses (both branches)", "L_rec,c  L_rec,d  L_chr  L_vq\nL_lam  L_sm  envmap smoothness"),
    "rank": (5.0, 0.5, 4.0, 1.5, GREY, "After training: dropout ranking", "err_k of the first k codewords ->\nM; materials.json, sheet, err_k plot"),
    "use": (9.4, 0.5, 4.2, 1.5, GREY, "render / eval", "novel views, maps, material ids,\nsegmentation, relighting"),
}
ARROWS = [("capture", "geometry"), ("geometry", "hits"), ("hits", "encoder"), ("encoder", "vq"), ("encoder", "cont"),
          ("vq", "disc"), ("cont", "mitsuba"), ("envmap", "mitsuba"), ("mitsuba", "loss"),
          ("hits", "mitsuba"), ("rank", "use")]


def centre(name, side):
    x, y, w, h = BOXES[name][:4]
    return {"l": (x, y + h / 2), "r": (x + w, y + h / 2), "t": (x + w / 2, y + h), "b": (x + w / 2, y)}[side]


def main() -> None:
    fig, ax = plt.subplots(figsize=(13.8, 6.8))
    ax.set_xlim(0, 13.7)
    ax.set_ylim(0.2, 7.2)
    ax.axis("off")
    for x, y, w, h, colour, title, body in BOXES.values():
        ax.add_patch(FancyBboxPatch((x, y), w, h, boxstyle="round,pad=0.02,rounding_size=0.12", fc=colour,
                                    ec="#333333", lw=1.3))
        ax.text(x + w / 2, y + h - 0.3, title, ha="center", va="center", fontsize=11, weight="bold")
        ax.text(x + w / 2, y + h / 2 - 0.2, body, ha="center", va="center", fontsize=9)
    for a, b in ARROWS:
        xa, ya, wa, ha = BOXES[a][:4]
        xb, yb, wb, hb = BOXES[b][:4]
        if abs(ya - yb) < 0.3:  # same row
            start, end = (centre(a, "r"), centre(b, "l")) if xa < xb else (centre(a, "l"), centre(b, "r"))
        else:
            start, end = (centre(a, "b"), centre(b, "t")) if ya > yb else (centre(a, "t"), centre(b, "b"))
        ax.annotate("", xy=end, xytext=start, arrowprops=dict(arrowstyle="-|>", color="#333333", lw=1.3))
    ax.annotate("", xy=centre("loss", "t"), xytext=centre("capture", "b"),
                arrowprops=dict(arrowstyle="-|>", color="#333333", lw=1.3, linestyle="--"))
    x, y, w, _ = BOXES["mitsuba"][:4]
    ax.annotate("", xy=(x + 0.8 * w, y), xytext=centre("disc", "b"),  # below the continuous decoder
                arrowprops=dict(arrowstyle="-|>", color="#333333", lw=1.3, connectionstyle="arc3,rad=-0.25"))
    ax.text(1.35, 3.2, "pixels", fontsize=9, style="italic", ha="right")
    ax.set_title("vq-mitsuba fit: geometry, both material branches, one Mitsuba renderer; then ranking",
                 fontsize=13)
    fig.tight_layout()
    fig.savefig(Path(__file__).with_name("pipeline.png"), dpi=90)


if __name__ == "__main__":
    main()
