"""A Mitsuba 3 scene: the mesh (PLY with UVs and the renderer's shading normals), a two-sided
`principled` BSDF reading linear EXR textures, the envmap with its frame, and cameras as
sensors, in the capture's own coordinates. `path` with max_depth 2 + train.bounces renders what
`vq-mitsuba render` renders (direct light and the same number of interreflections)."""

from __future__ import annotations

from pathlib import Path
from typing import Sequence
from xml.sax.saxutils import quoteattr

import numpy as np

from vq_mitsuba.brdf import FIXED, INPUTS
from vq_mitsuba.data.cameras import Camera, principal_xml
from vq_mitsuba.data.imageio import write_exr, written
from vq_mitsuba.data.names import unique_names
from vq_mitsuba.export.bake import BakedMesh


def write_ply(path: Path, vertices: np.ndarray, normals: np.ndarray, uvs: np.ndarray, faces: np.ndarray) -> Path:
    """Binary little-endian PLY with x y z, nx ny nz, u v per vertex and triangle faces."""
    n = len(vertices)
    vert = np.zeros(n, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("nx", "<f4"), ("ny", "<f4"),
                              ("nz", "<f4"), ("u", "<f4"), ("v", "<f4")])
    for i, k in enumerate("xyz"):
        vert[k] = vertices[:, i]
        vert["n" + k] = normals[:, i]
    vert["u"], vert["v"] = uvs[:, 0], uvs[:, 1]
    face = np.zeros(len(faces), dtype=[("n", "u1"), ("idx", "<i4", (3,))])
    face["n"], face["idx"] = 3, faces
    header = (f"ply\nformat binary_little_endian 1.0\ncomment vq-mitsuba export\nelement vertex {n}\n"
              + "".join(f"property float {k}\n" for k in ("x", "y", "z", "nx", "ny", "nz", "u", "v"))
              + f"element face {len(faces)}\nproperty list uchar int vertex_indices\nend_header\n")
    written(path, lambda: Path(path).write_bytes(header.encode("ascii") + vert.tobytes() + face.tobytes()))
    return path


def _matrix(m: np.ndarray) -> str:
    return " ".join(f"{x:.9g}" for x in np.asarray(m, np.float64).ravel())


def sensor_xml(camera: Camera, spp: int, sensor_id: str | None = None) -> str:
    """One perspective sensor; its id (`sensor_id`, else the camera's name) escaped for XML."""
    return (f'  <sensor type="perspective" id={quoteattr(camera.name if sensor_id is None else sensor_id)}>\n'
            f'    <float name="fov" value="{camera.fov_x_deg:.9g}"/>\n'
            f'    <string name="fov_axis" value="x"/>\n'
            + principal_xml(camera, "    ") +
            f'    <transform name="to_world"><matrix value="{_matrix(camera.to_world)}"/></transform>\n'
            f'    <sampler type="independent"><integer name="sample_count" value="$spp"/></sampler>\n'
            f'    <film type="hdrfilm"><integer name="width" value="{camera.width}"/>'
            f'<integer name="height" value="{camera.height}"/><string name="pixel_format" value="rgba"/>'
            f'<rfilter type="box"/></film>\n  </sensor>')


def write_mitsuba(out: Path, baked: BakedMesh, envmap: np.ndarray, env_to_world: np.ndarray,
                  cameras: Sequence[Camera], spp: int, max_depth: int, name: str = "object",
                  lamps: np.ndarray | None = None) -> list[Path]:
    """OUT/scene.xml with OUT/NAME.ply, NAME_{basecolor,metallic,roughness}.exr and envmap.exr;
    `lamps` (K, 6: position, RGB intensity) become `point` emitters beside the envmap.

    Render a view with `mitsuba OUT/scene.xml` (first sensor) or
    `mi.render(mi.load_file(...), sensor=i)`; `-Dspp=N` sets the samples per pixel."""
    from vq_mitsuba.export.files import write_envmap

    files = [write_ply(out / f"{name}.ply", baked.vertices, baked.normals, baked.uvs, baked.faces)]
    for i in INPUTS:
        write_exr(out / f"{name}_{i.name}.exr", getattr(baked, i.name))
        files.append(out / f"{name}_{i.name}.exr")
    files += write_envmap(out / "envmap", envmap)

    def texture(i) -> str:
        return (f'<texture type="bitmap" name="{i.principled}">'
                f'<string name="filename" value={quoteattr(f"{name}_{i.name}.exr")}/><boolean name="raw" value="true"/>'
                f'<string name="filter_type" value="bilinear"/><string name="wrap_mode" value="clamp"/></texture>')

    xml = "\n".join([
        '<scene version="3.0.0">',
        f'  <default name="spp" value="{int(spp)}"/>',
        f'  <integrator type="path"><integer name="max_depth" value="{int(max_depth)}"/>'
        '<boolean name="hide_emitters" value="true"/></integrator>',
        # Mitsuba wants every id once: the train and test views of a capture may share names.
        *[sensor_xml(c, spp, sid) for c, sid in zip(cameras, unique_names([c.name for c in cameras]))],
        f'  <shape type="ply" id={quoteattr(name)}><string name="filename" value={quoteattr(f"{name}.ply")}/>',
        '    <bsdf type="twosided"><bsdf type="principled">',
        *[f"      {texture(i)}" for i in INPUTS],
        *[f'      <float name="{key}" value="{value:g}"/>' for key, value in FIXED.items()],
        "    </bsdf></bsdf>",
        "  </shape>",
        *[f'  <emitter type="point"><point name="position" x="{p[0]:.9g}" y="{p[1]:.9g}" z="{p[2]:.9g}"/>'
          f'<rgb name="intensity" value="{p[3]:.9g}, {p[4]:.9g}, {p[5]:.9g}"/></emitter>'
          for p in (() if lamps is None else np.asarray(lamps, dtype=np.float64))],
        '  <emitter type="envmap"><string name="filename" value="envmap.exr"/>',
        f'    <transform name="to_world"><matrix value="{_matrix(env_to_world)}"/></transform>',
        "  </emitter>",
        "</scene>",
    ]) + "\n"
    written(out / "scene.xml", lambda: (out / "scene.xml").write_text(xml, encoding="utf-8"))
    return [out / "scene.xml"] + files
