"""Wavefront OBJ + MTL with the PBR extension keys (`Pr`/`map_Pr` roughness, `Pm`/`map_Pm`
metallic) that Blender's importer and many engines read; textures as PNG beside it. Y up, in
the capture's own world (`files.export_axes`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from vq_mitsuba.brdf import NAMES
from vq_mitsuba.data.imageio import write_png, written
from vq_mitsuba.export.bake import BakedMesh
from vq_mitsuba.export.files import texture_images


def write_obj(path: Path, baked: BakedMesh, axes: np.ndarray, name: str = "object") -> list[Path]:
    """`path`, its .mtl and textures: the baked mesh turned by `axes` (3, 3), run world -> the file's axes."""
    out = path.parent
    rot = np.asarray(axes, np.float64)
    v = baked.vertices.astype(np.float64) @ rot.T
    n = baked.normals.astype(np.float64) @ rot.T
    images = texture_images(baked)
    textures = []
    for key in NAMES:
        write_png(out / f"{name}_{key}.png", images[key])
        textures.append(out / f"{name}_{key}.png")
    mtl = path.with_suffix(".mtl")
    text = (
        f"# vq-mitsuba: PBR material (basecolor sRGB; roughness and metallic linear)\n"
        f"newmtl {name}_material\nKa 0 0 0\nKd 1 1 1\nKs 0 0 0\nd 1\nillum 2\n"
        f"map_Kd {name}_basecolor.png\nPr 1\nmap_Pr {name}_roughness.png\nPm 1\nmap_Pm {name}_metallic.png\n")
    written(mtl, lambda: mtl.write_text(text))
    # OBJ's v runs up the image (OpenGL); our texture row 0 is v = 0 of glTF / Mitsuba.
    lines = [f"# vq-mitsuba export: {len(v)} vertices, {len(baked.faces)} faces", f"mtllib {mtl.name}",
             f"o {name}"]
    lines += [f"v {x:.7g} {y:.7g} {z:.7g}" for x, y, z in v]
    lines += [f"vt {a:.7g} {1.0 - b:.7g}" for a, b in baked.uvs]
    lines += [f"vn {x:.6g} {y:.6g} {z:.6g}" for x, y, z in n]
    lines += [f"usemtl {name}_material", "s 1"]
    f1 = baked.faces + 1
    lines += [f"f {a}/{a}/{a} {b}/{b}/{b} {c}/{c}/{c}" for a, b, c in f1]
    written(path, lambda: path.write_text("\n".join(lines) + "\n"))
    return [path, mtl] + textures
