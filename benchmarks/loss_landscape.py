"""Loss landscape of one material of a bundled synthetic scene under its true lighting.

    .venv/bin/python benchmarks/loss_landscape.py benchmarks/out/data/balls green_plastic
        [--metallic 0,0.5,1] [--roughness 0.1,0.2,0.3,0.5,0.7,0.85,1] [--views 8] [--spp 64]

The scene's test cameras, its true envmap and all other materials are kept; the chosen material's
metallic and roughness run over a grid. For each grid point its basecolor is solved per channel by
least squares (the image is affine in basecolor: two renders, basecolor 0 and 1, give it), and
the gamma-2.2 MSE and linear PSNR against the dataset's test images on that material's pixels
(ground-truth material ids) are printed. Says whether a fit's wrong answer (e.g. a rough metal for
a glossy plastic) is a better explanation of the images or a local minimum of the optimisation.
Monte Carlo noise of both the renders (--spp) and the dataset adds to every MSE alike.
"""

from __future__ import annotations

import argparse
import json
import re
from pathlib import Path

import numpy as np


def floats(text: str) -> list[float]:
    return [float(x) for x in text.split(",")]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("dataset", type=Path, help="a dataset written by `vq-mitsuba make-scene`")
    ap.add_argument("material", help="material name in the dataset's scene.json")
    ap.add_argument("--metallic", type=floats, default=[0.0, 0.5, 1.0])
    ap.add_argument("--roughness", type=floats, default=[0.1, 0.2, 0.3, 0.5, 0.7, 0.85, 1.0])
    ap.add_argument("--views", type=int, default=8, help="test views used (evenly spread)")
    ap.add_argument("--spp", type=int, default=64)
    args = ap.parse_args()

    import mitsuba as mi

    mi.set_variant("llvm_ad_rgb")
    from PIL import Image

    from vq_mitsuba.data.imageio import read_image
    from vq_mitsuba.models.losses import encode_gamma

    data = args.dataset.resolve()
    meta = json.loads((data / "scene.json").read_text())
    mats = {m["name"]: m for m in meta["materials"]}
    if args.material not in mats:
        ap.error(f"{data / 'scene.json'}: no material '{args.material}' (there are: {', '.join(mats)})")
    mat = mats[args.material]
    xml = (data / "scene_test.xml").read_text()
    xml = re.sub(r"<integrator.*?</integrator>|<integrator[^>]*/>", "", xml, flags=re.S)
    xml = xml.replace("</scene>", f'<emitter type="envmap"><string name="filename" value="{meta["envmap"]["train"]}"/>'
                      f'</emitter><integrator type="path"><integer name="max_depth" value="{meta["max_depth"]}"/>'
                      "</integrator></scene>")
    mi.file_resolver().prepend(str(data))
    scene = mi.load_string(xml)
    params = mi.traverse(scene)
    key = f"mat_{args.material}"
    sensors = {s.id(): i for i, s in enumerate(scene.sensors())}
    names = sorted(sensors)
    names = [names[i] for i in np.linspace(0, len(names) - 1, min(args.views, len(names))).round().astype(int)]
    target, masks = [], []
    for n in names:
        img, _ = read_image(data / "images" / f"{n}.exr")
        m = np.asarray(Image.open(data / "gt" / f"{n}_material.png")) == mat["id"]
        target.append(img[m])
        masks.append(m)
    target = np.concatenate(target)
    if len(target) == 0:
        ap.error(f"material '{args.material}' covers no pixel of the chosen test views")

    def render(bc, metallic, roughness):
        params[key + ".base_color.value"] = mi.Color3f(*bc)
        params[key + ".metallic.value"] = metallic
        params[key + ".roughness.value"] = roughness
        params.update()
        out = [np.asarray(mi.render(scene, sensor=sensors[n], spp=args.spp, seed=i))[..., :3][masks[i]]
               for i, n in enumerate(names)]
        return np.concatenate(out)

    import torch

    g = lambda x: encode_gamma(torch.as_tensor(x), 2.2).numpy()
    print(f"{args.material} (true: basecolor {mat['mean_base_color']}, metallic {mat['metallic']}, roughness "
          f"{mat['roughness']}); {len(target)} pixels in {len(names)} test views, {args.spp} spp, true lighting")
    print("| metallic | roughness | basecolor (solved) | gamma MSE | linear PSNR |\n|---:|---:|---|---:|---:|")
    for m in args.metallic:
        for r in args.roughness:
            i0, i1 = render((0.0, 0.0, 0.0), m, r), render((1.0, 1.0, 1.0), m, r)
            a = i1 - i0
            bc = np.clip(((target - i0) * a).sum(0) / np.maximum((a * a).sum(0), 1e-12), 0.0, 1.0)
            pred = i0 + a * bc
            mse = float(np.mean((g(pred) - g(target)) ** 2))
            lin = float(np.mean((np.clip(pred, 0, 1) - np.clip(target, 0, 1)) ** 2))
            print(f"| {m:.2f} | {r:.2f} | ({bc[0]:.2f}, {bc[1]:.2f}, {bc[2]:.2f}) | {mse:.2e} | "
                  f"{-10 * np.log10(lin):.2f} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
