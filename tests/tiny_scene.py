"""Tiny synthetic captures rendered with Mitsuba's path tracer, for tests."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def smooth_env(height: int = 32, lobe_strength: float = 40.0, lobe_width: float = 1.0) -> np.ndarray:
    """A smooth positive lat-long envmap with one bright sun-like lobe (Mitsuba convention)."""
    h, w = height, 2 * height
    v, u = np.meshgrid((np.arange(h) + 0.5) / h, (np.arange(w) + 0.5) / w, indexing="ij")
    env = np.stack([0.6 + 0.3 * np.cos(2 * np.pi * u), 0.6 + 0.2 * (1 - v), 0.5 + 0.4 * v], -1)
    du, dv = (u - 0.3) * 2 * np.pi, (v - 0.35) * np.pi  # radians
    sun = np.exp(-(du**2 + dv**2) / (2 * (0.08 * lobe_width) ** 2))
    return (env + lobe_strength * sun[..., None]).astype(np.float32)


def _render_view(scene, cam, spp: int, seed: int, out: Path) -> str:
    """Render `cam` with Mitsuba into OUT/images/NAME.exr; returns the camera's <sensor> XML."""
    import mitsuba as mi

    from vq_mitsuba.data.cameras import principal_xml
    from vq_mitsuba.data.imageio import write_exr

    img = np.array(mi.render(scene, sensor=mi.load_dict(cam.to_mitsuba_dict(spp)), seed=seed))
    write_exr(out / "images" / f"{cam.name}.exr", img)
    m = " ".join(f"{x:.9g}" for x in cam.to_world.ravel())
    return (f'  <sensor type="perspective" id="{cam.name}">\n'
            f'    <float name="fov" value="{cam.fov_x_deg!r}"/>\n    <string name="fov_axis" value="x"/>\n'
            + principal_xml(cam, "    ") +
            f'    <transform name="to_world"><matrix value="{m}"/></transform>\n'
            f'    <film type="hdrfilm"><integer name="width" value="{cam.width}"/>'
            f'<integer name="height" value="{cam.height}"/></film>\n  </sensor>')


def write_sphere_capture(out: Path, base_color=(0.7, 0.35, 0.2), roughness: float = 0.3, metallic: float = 0.0,
                         size: int = 32, n_views: int = 12, spp: int = 64, known_envmap: bool = True,
                         env: np.ndarray | None = None) -> Path:
    """A uniform principled sphere (radius 0.5) seen from n_views cameras under `env` (default
    `smooth_env()`); returns the XML path."""
    import mitsuba as mi
    import trimesh

    from vq_mitsuba.data.cameras import Camera, look_at
    from vq_mitsuba.data.imageio import write_exr
    from vq_mitsuba.backend import init_mitsuba

    init_mitsuba()
    out = Path(out)
    (out / "images").mkdir(parents=True, exist_ok=True)
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.5)
    sphere.export(out / "sphere.ply")
    env = smooth_env() if env is None else env
    write_exr(out / "env.exr", env)
    bsdf = {"type": "principled", "base_color": {"type": "rgb", "value": list(base_color)},
            "metallic": metallic, "roughness": roughness}
    scene = mi.load_dict({
        "type": "scene",
        "integrator": {"type": "path", "max_depth": 3, "hide_emitters": True},
        "shape": {"type": "ply", "filename": str(out / "sphere.ply"), "bsdf": bsdf},
        "env": {"type": "envmap", "filename": str(out / "env.exr")},
    })
    golden = np.pi * (3 - np.sqrt(5))
    sensors = []
    for i in range(n_views):
        y = 1 - 2 * (i + 0.5) / n_views
        r = np.sqrt(1 - y * y)
        origin = 2.2 * np.array([r * np.cos(golden * i), y, r * np.sin(golden * i)])
        cam = Camera(f"view_{i:02d}", look_at(origin, [0, 0, 0], [0, 1, 0] if abs(y) < 0.95 else [1, 0, 0]),
                     40.0, size, size)
        sensors.append(_render_view(scene, cam, spp, i, out))
    emitter = '  <emitter type="envmap"><string name="filename" value="env.exr"/></emitter>\n' if known_envmap else ""
    xml = ('<scene version="3.0.0">\n' + "\n".join(sensors) + "\n"
           '  <shape type="ply"><string name="filename" value="sphere.ply"/></shape>\n' + emitter + "</scene>\n")
    (out / "scene.xml").write_text(xml)
    return out / "scene.xml"


THREE_MATERIALS = [  # (centre, basecolor, metallic, roughness): three spheres that differ in every way
    ((-0.62, 0.0, 0.0), (0.80, 0.15, 0.10), 0.0, 0.7),  # rough red dielectric
    ((0.62, 0.0, 0.0), (0.15, 0.45, 0.85), 0.0, 0.25),  # glossy blue dielectric
    ((0.0, 0.0, 0.62), (0.95, 0.75, 0.35), 1.0, 0.3),  # gold-like metal
]


def write_three_material_capture(out: Path, size: int | tuple[int, int] = 32, n_views: int = 10, spp: int = 32,
                                 principal_shift: tuple[float, float] | None = None) -> Path:
    """Three spheres (radius 0.3) of three materials under a known envmap, rendered with Mitsuba's
    path tracer; returns the XML path. Ground-truth ids: `three_material_ids`. `size`: square, or
    (width, height); `principal_shift`: the principal point's offset from the centre in pixels."""
    import mitsuba as mi
    import trimesh

    from vq_mitsuba.backend import init_mitsuba
    from vq_mitsuba.data.cameras import Camera, look_at
    from vq_mitsuba.data.imageio import write_exr

    init_mitsuba()
    out = Path(out)
    (out / "images").mkdir(parents=True, exist_ok=True)
    write_exr(out / "env.exr", smooth_env())
    shapes, xml_shapes = {}, []
    for k, (centre, base, metal, rough) in enumerate(THREE_MATERIALS):
        mesh = trimesh.creation.icosphere(subdivisions=3, radius=0.3)
        mesh.apply_translation(centre)
        mesh.export(out / f"sphere{k}.ply")
        shapes[f"s{k}"] = {"type": "ply", "filename": str(out / f"sphere{k}.ply"),
                           "bsdf": {"type": "principled", "base_color": {"type": "rgb", "value": list(base)},
                                    "metallic": metal, "roughness": rough}}
        xml_shapes.append(f'  <shape type="ply"><string name="filename" value="sphere{k}.ply"/></shape>')
    scene = mi.load_dict({"type": "scene", "integrator": {"type": "path", "max_depth": 3, "hide_emitters": True},
                          "env": {"type": "envmap", "filename": str(out / "env.exr")}, **shapes})
    sensors = []
    for i in range(n_views):
        a = 2 * np.pi * i / n_views
        origin = 2.4 * np.array([np.sin(a), 0.55 + 0.25 * np.cos(3 * a), np.cos(a)])
        w, h = (size, size) if isinstance(size, int) else size
        principal = None if principal_shift is None else (w / 2 + principal_shift[0], h / 2 + principal_shift[1])
        cam = Camera(f"view_{i:02d}", look_at(origin, [0, 0, 0.2], [0, 1, 0]), 45.0, w, h, principal=principal)
        sensors.append(_render_view(scene, cam, spp, i, out))
    (out / "scene.xml").write_text('<scene version="3.0.0">\n' + "\n".join(sensors) + "\n" + "\n".join(xml_shapes)
                                   + '\n  <emitter type="envmap"><string name="filename" value="env.exr"/></emitter>\n'
                                   "</scene>\n")
    return out / "scene.xml"


def three_material_ids(positions: np.ndarray) -> np.ndarray:
    """Ground-truth material id (1..3) of surface points of `write_three_material_capture`."""
    centres = np.array([c for c, *_ in THREE_MATERIALS])
    return 1 + np.argmin(np.linalg.norm(positions[:, None, :] - centres[None], axis=-1), axis=1)


def write_lamp_capture(out: Path, lamp: tuple = (0.9, 1.1, 0.6), intensity: float = 3.0, flash: bool = False,
                       size: int = 32, n_views: int = 16, spp: int = 32, roughness: float = 0.6) -> Path:
    """A grey-white sphere (radius 0.5) and slab of `roughness`, Mitsuba world (Y up), lit by a dim uniform sky and
    a point lamp: at `lamp` in the world, or with `flash` at `lamp` in each view's camera frame.
    The envmap is not in the XML (the fit learns it); returns the XML path."""
    import mitsuba as mi
    import trimesh

    from vq_mitsuba.data.cameras import Camera, look_at
    from vq_mitsuba.backend import init_mitsuba

    init_mitsuba()
    out = Path(out)
    (out / "images").mkdir(parents=True, exist_ok=True)
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.5)
    slab = trimesh.creation.box(extents=[2.0, 0.1, 2.0])
    slab.apply_translation([0.0, -0.55, 0.0])
    trimesh.util.concatenate([sphere, slab]).export(out / "mesh.ply")
    bsdf = {"type": "principled", "base_color": {"type": "rgb", "value": [0.7, 0.6, 0.5]}, "roughness": roughness}
    scene = mi.load_dict({
        "type": "scene",
        "integrator": {"type": "path", "max_depth": 3, "hide_emitters": True},
        "shape": {"type": "ply", "filename": str(out / "mesh.ply"), "bsdf": bsdf, "face_normals": False},
        "env": {"type": "constant", "radiance": {"type": "rgb", "value": [0.15, 0.15, 0.17]}},
        "lamp": {"type": "point", "position": list(lamp), "intensity": {"type": "rgb", "value": [intensity] * 3}},
    })
    params = mi.traverse(scene)
    sensors = []
    for i in range(n_views):
        a = 2 * np.pi * i / n_views
        elevation = 0.35 + 0.5 * (i % 3) / 2
        origin = 2.6 * np.array([np.cos(a) * np.cos(elevation), np.sin(elevation), np.sin(a) * np.cos(elevation)])
        cam = Camera(f"view_{i:02d}", look_at(origin, [0, -0.1, 0], [0, 1, 0]), 45.0, size, size)
        if flash:
            params["lamp.position"] = type(params["lamp.position"])(*(cam.to_world[:3, :3] @ np.asarray(lamp)
                                                                      + cam.to_world[:3, 3]).tolist())
            params.update()
        sensors.append(_render_view(scene, cam, spp, i, out))
    xml = ('<scene version="3.0.0">\n' + "\n".join(sensors) + "\n"
           '  <shape type="ply"><string name="filename" value="mesh.ply"/></shape>\n</scene>\n')
    (out / "scene.xml").write_text(xml)
    return out / "scene.xml"
