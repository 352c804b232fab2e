"""Bundled synthetic scenes rendered with Mitsuba, written as both capture formats.

A scene is defined in `synthetic/scenes/<name>.yaml` in Blender world (Z up): principled materials
(base_color, metallic, roughness; base_color may be a procedural pattern baked into per-vertex
colours) and shapes made with trimesh. `make_scene` writes into `out_dir` the layout that
`vq_mitsuba.data.dataset_dir.DatasetDir` names and describes: both capture formats (transforms json
and mesh.ply in Blender world, scene.xml and meshes/ in Mitsuba world), the views (images/), the test
views' ground-truth maps (gt/) and relit views (relit/), the envmaps (envmaps/) and scene.json.

Worlds: Blender_world = R @ Mitsuba_world with R the 3x3 part of BLENDER_ENV_TO_WORLD. Every
vertex and camera of the XML is the Blender one mapped by R^-1, so an envmap with identity
to_world in the XML's scene lights it exactly as the same EXR with to_world = R lights the
Blender-world scene (see vq_mitsuba.data.envmaps for the lat-long convention).

Images: EXR is linear RGBA with premultiplied colour (OpenEXR's convention; background 0),
PNG is sRGB RGBA with straight (un-premultiplied) colour and alpha = pixel coverage.
"""

from __future__ import annotations

import math
import re
import shutil
import time
from contextlib import contextmanager
from dataclasses import dataclass, replace
from importlib import resources
from pathlib import Path

import numpy as np

from vq_mitsuba import brdf
from vq_mitsuba.data import envmaps
from vq_mitsuba.backend import init_mitsuba
from vq_mitsuba.config import read_yaml
from vq_mitsuba.data.cameras import BLENDER_ENV_TO_WORLD, Camera, look_at
from vq_mitsuba.data.dataset_dir import DatasetDir
from vq_mitsuba.data.formats import mitsuba_xml, nerf_synthetic
from vq_mitsuba.data.imageio import written
from vq_mitsuba.errors import InputError, WriteError, as_write_error

# A scene's material gives each BRDF input under its principled name; the base colour's may be a
# pattern (a dict), baked into per-vertex colours.
BASE_COLOR = brdf.get(brdf.BASECOLOR).principled

SCENES_DIR = Path(str(resources.files("vq_mitsuba.synthetic") / "scenes"))  # package data, installed with the wheel
R_BLENDER_FROM_MITSUBA = BLENDER_ENV_TO_WORLD[:3, :3].copy()  # Blender_world = R @ Mitsuba_world
FOV_X_DEG = 40.0
FILL = 0.7  # fraction of the half-frame the bounding sphere's silhouette covers
MAX_DEPTH = 4
MAX_SEED = 2 ** 32 - 1  # numpy and Mitsuba take seeds from 0 to this
# Stratified (multi-jittered) pixel samples: half the noise of `independent` at the same cost
# under smooth sky lighting (Mitsuba may round the count up, e.g. 512 -> 528).
SAMPLER = "multijitter"
GT_SAMPLES = 4  # GT maps average GT_SAMPLES x GT_SAMPLES stratified rays per pixel
_NAME_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")


def _scene_names() -> tuple[str, ...]:
    if not SCENES_DIR.is_dir():
        return ()
    return tuple(sorted(p.stem for p in SCENES_DIR.glob("*.yaml")))


SCENES: tuple[str, ...] = _scene_names()


# --------------------------------------------------------------------------------------------
# Scene definitions
# --------------------------------------------------------------------------------------------
def load_scene_spec(name: str) -> dict:
    """The parsed and checked `vq_mitsuba/synthetic/scenes/<name>.yaml`."""
    path = SCENES_DIR / f"{name}.yaml"
    if not path.is_file():
        raise InputError(None, f"unknown synthetic scene '{name}' (bundled: {', '.join(SCENES) or 'none'})")
    spec = read_yaml(path, "a scene definition")
    if not isinstance(spec, dict):
        raise InputError(path, "expected a mapping with materials and shapes")
    spec["name"] = name
    mats = spec.get("materials") or []
    shapes = spec.get("shapes") or []
    if not mats or not shapes:
        raise InputError(path, "a scene needs at least one material and one shape")
    names = set()
    for m in mats:
        if not _NAME_RE.match(str(m.get("name", ""))) or m["name"] in names:
            raise InputError(path, f"bad or duplicate material name {m.get('name')!r}")
        names.add(m["name"])
        for i in brdf.INPUTS:
            if i.default is not None:
                m.setdefault(i.principled, i.default)
    shape_names = set()
    for s in shapes:
        if not _NAME_RE.match(str(s.get("name", ""))) or s["name"] in shape_names or s["name"] in names:
            raise InputError(path, f"bad or duplicate shape name {s.get('name')!r}")
        shape_names.add(s["name"])
        if s.get("material") not in names:
            raise InputError(path, f"shape {s['name']} uses unknown material {s.get('material')!r}")
    spec["lamps"] = _checked_lamps(spec.get("lamps"), path)
    return spec


def is_textured(material: dict) -> bool:
    return isinstance(material[BASE_COLOR], dict)


def _smoothstep(e0, e1, x):
    t = np.clip((x - e0) / (e1 - e0), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def eval_base_color(base_color, points) -> np.ndarray:
    """Base colour (N, 3) of a material at Blender-world points (N, 3): constant or pattern."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if not isinstance(base_color, dict):
        return np.tile(np.asarray(base_color, dtype=np.float64), (len(points), 1))
    colors = np.asarray(base_color["colors"], dtype=np.float64)
    pattern = base_color.get("pattern", "stripes")
    freq = float(base_color.get("frequency", 2.0))
    soft = float(base_color.get("softness", 0.1))
    if pattern == "stripes":
        axis = np.asarray(base_color.get("axis", [0.0, 0.0, 1.0]), dtype=np.float64)
        t = freq * (points @ (axis / np.linalg.norm(axis)))
        band = np.floor(t)
        frac = t - band
        i0 = np.mod(band, len(colors)).astype(int)
        i1 = np.mod(i0 + 1, len(colors))
        w = _smoothstep(1.0 - soft, 1.0, frac)[:, None]
        return (1.0 - w) * colors[i0] + w * colors[i1]
    if pattern == "checker":
        s = np.prod(np.sin(math.pi * freq * points), axis=1)
        return _blend(colors, _smoothstep(-soft, soft, s))
    if pattern == "waves":  # wood-like grain: bands along `axis`, bent by a sine along `bend_axis`
        axis = np.asarray(base_color.get("axis", [1.0, 0.0, 0.0]), dtype=np.float64)
        bend = np.asarray(base_color.get("bend_axis", [0.0, 1.0, 0.0]), dtype=np.float64)
        amp, bend_freq = float(base_color.get("bend", 0.6)), float(base_color.get("bend_frequency", 1.5))
        t = freq * (points @ (axis / np.linalg.norm(axis)))
        t = t + amp * np.sin(2 * math.pi * bend_freq * (points @ (bend / np.linalg.norm(bend))))
        return _blend(colors, (0.5 + 0.5 * np.sin(2 * math.pi * t)) ** (1.0 / max(soft, 1e-3)))
    if pattern == "noise":  # value noise on a lattice of `frequency` cells per unit, two octaves
        seed = int(base_color.get("seed", 0))
        w = 0.65 * _value_noise(points * freq, seed) + 0.35 * _value_noise(points * 2.7 * freq, seed + 1)
        return _blend(colors, _smoothstep(0.5 - soft, 0.5 + soft, w))
    raise InputError(None, f"unknown base_color pattern '{pattern}' (use stripes, checker, waves or noise)")


def _blend(colors: np.ndarray, w: np.ndarray) -> np.ndarray:
    """The first colour where w = 0, the second (the first again if there is one) where w = 1."""
    return (1.0 - w[:, None]) * colors[0] + w[:, None] * colors[1 % len(colors)]


def _value_noise(p: np.ndarray, seed: int) -> np.ndarray:
    """Trilinearly interpolated random values in [0, 1] on the integer lattice (smoothstep weights)."""
    cell = np.floor(p)
    f = p - cell
    f = f * f * (3.0 - 2.0 * f)
    cell = cell.astype(np.int64)

    def rand(c):
        h = (c[:, 0] * 73856093) ^ (c[:, 1] * 19349663) ^ (c[:, 2] * 83492791) ^ (seed * 2654435761)
        h = (h ^ (h >> 13)) * 1274126177
        return ((h ^ (h >> 16)) & 0xFFFF) / 65535.0

    out = np.zeros(len(p))
    for corner in range(8):
        d = np.array([(corner >> a) & 1 for a in range(3)])
        weight = np.prod(np.where(d == 1, f, 1.0 - f), axis=1)
        out += weight * rand(cell + d)
    return out


def _box(extents: np.ndarray, max_edge: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A box centred at the origin, each face a regular grid of cells at most `max_edge` wide
    (dense enough for a per-vertex colour pattern), vertices not shared across faces: flat normals."""
    verts, faces, normals = [], [], []
    for axis in range(3):
        u_ax, v_ax = [a for a in range(3) if a != axis]
        for sign in (-1.0, 1.0):
            nu = max(2, int(np.ceil(extents[u_ax] / max_edge)) + 1)
            nv = max(2, int(np.ceil(extents[v_ax] / max_edge)) + 1)
            uu, vv = np.meshgrid(np.linspace(-0.5, 0.5, nu), np.linspace(-0.5, 0.5, nv), indexing="ij")
            p = np.zeros((nu * nv, 3))
            p[:, u_ax], p[:, v_ax] = uu.ravel() * extents[u_ax], vv.ravel() * extents[v_ax]
            p[:, axis] = 0.5 * sign * extents[axis]
            idx = np.arange(nu * nv).reshape(nu, nv)
            a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
            tri = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
            normal = np.zeros(3)
            normal[axis] = sign
            # counter-clockwise seen from outside: flip where the grid's winding points inwards
            e = np.cross(p[tri[0, 1]] - p[tri[0, 0]], p[tri[0, 2]] - p[tri[0, 0]])
            if e @ normal < 0:
                tri = tri[:, ::-1]
            faces.append(tri + sum(len(x) for x in verts))
            verts.append(p)
            normals.append(np.tile(normal, (len(p), 1)))
    return np.concatenate(verts), np.concatenate(faces), np.concatenate(normals)


def _euler_xyz(deg) -> np.ndarray:
    ax, ay, az = np.radians(np.asarray(deg, dtype=np.float64))
    rx = np.array([[1, 0, 0], [0, math.cos(ax), -math.sin(ax)], [0, math.sin(ax), math.cos(ax)]])
    ry = np.array([[math.cos(ay), 0, math.sin(ay)], [0, 1, 0], [-math.sin(ay), 0, math.cos(ay)]])
    rz = np.array([[math.cos(az), -math.sin(az), 0], [math.sin(az), math.cos(az), 0], [0, 0, 1]])
    return rz @ ry @ rx  # rotate about X, then Y, then Z (Blender's default XYZ Euler)


def _mesh_arrays(mesh) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(vertices, faces, vertex normals) of a trimesh mesh."""
    return (np.asarray(mesh.vertices, dtype=np.float64), mesh.faces,
            np.asarray(mesh.vertex_normals, dtype=np.float64))


def build_shape(shape: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(vertices, faces, vertex normals) of a shape in Blender world."""
    import trimesh

    kind = shape.get("type", "icosphere")
    if kind == "icosphere":
        r = float(shape.get("radius", 0.5))
        mesh = trimesh.creation.icosphere(subdivisions=int(shape.get("subdivisions", 4)), radius=r)
        v, f = np.asarray(mesh.vertices, dtype=np.float64), mesh.faces
        n = v / np.linalg.norm(v, axis=1, keepdims=True)  # exact sphere normals
        v = n * r
    elif kind == "torus":
        mesh = trimesh.creation.torus(float(shape.get("major_radius", 0.3)), float(shape.get("minor_radius", 0.1)),
                                      major_sections=int(shape.get("major_sections", 128)),
                                      minor_sections=int(shape.get("minor_sections", 48)))
        v, f, n = _mesh_arrays(mesh)
    elif kind == "capsule":
        mesh = trimesh.creation.capsule(height=float(shape.get("height", 0.5)), radius=float(shape.get("radius", 0.15)),
                                        count=[64, 64])
        mesh.merge_vertices()
        v, f, n = _mesh_arrays(mesh)
    elif kind == "box":
        v, f, n = _box(np.asarray(shape.get("extents", [1.0, 1.0, 1.0]), dtype=np.float64),
                       float(shape.get("max_edge", 0.02)))
    else:
        raise InputError(None, f"shape {shape.get('name')}: unknown type '{kind}' (icosphere, torus, capsule, box)")
    f = np.asarray(f, dtype=np.int64)
    v = v * float(shape.get("scale", 1.0))
    rot = _euler_xyz(shape.get("rotation_deg", [0.0, 0.0, 0.0]))
    v = v @ rot.T + np.asarray(shape.get("center", [0.0, 0.0, 0.0]), dtype=np.float64)
    n = n @ rot.T
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    return v, f, n


def _mi_mesh(name: str, v: np.ndarray, f: np.ndarray, n: np.ndarray, colors: np.ndarray | None = None):
    import mitsuba as mi

    mesh = mi.Mesh(name, len(v), len(f), has_vertex_normals=True)
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float(np.ascontiguousarray(v, dtype=np.float32).ravel())
    params["faces"] = mi.UInt32(np.ascontiguousarray(f, dtype=np.uint32).ravel())
    params["vertex_normals"] = mi.Float(np.ascontiguousarray(n, dtype=np.float32).ravel())
    params.update()
    if colors is not None:
        mesh.add_attribute("vertex_color", 3, mi.Float(np.ascontiguousarray(colors, dtype=np.float32).ravel()))
    return mesh


# --------------------------------------------------------------------------------------------
# Cameras
# --------------------------------------------------------------------------------------------
def make_cameras(center, radius: float, n_train: int, n_test: int, resolution: int | tuple[int, int],
                 fov_x_deg: float = FOV_X_DEG, seed: int = 0) -> tuple[list[Camera], list[Camera], float]:
    """Blender-world cameras: train on a Fibonacci sphere band (elevation about -20..67 deg),
    test on a ring at 25 deg elevation at azimuths between the train ones. Returns (train, test, distance)."""
    center = np.asarray(center, dtype=np.float64)
    width, height = (resolution, resolution) if isinstance(resolution, int) else resolution
    half = math.atan(math.tan(math.radians(fov_x_deg) / 2.0) * min(1.0, height / width))  # the narrower side
    dist = radius / math.sin(math.atan(FILL * math.tan(half)))
    rng = np.random.default_rng(seed)
    phase = rng.uniform(0.0, 2.0 * math.pi)
    golden = math.pi * (3.0 - math.sqrt(5.0))
    z_hi, z_lo = 0.92, -0.35
    up = np.array([0.0, 0.0, 1.0])

    def cam(name, d):
        return Camera(name, look_at(center + dist * d, center, up), fov_x_deg, width, height)

    train = []
    for i in range(n_train):
        z = z_hi - (z_hi - z_lo) * (i + 0.5) / max(n_train, 1)
        phi = phase + i * golden
        s = math.sqrt(1.0 - z * z)
        train.append(cam(f"train_{i:03d}", np.array([s * math.cos(phi), s * math.sin(phi), z])))
    test = []
    elev = math.radians(25.0)
    for i in range(n_test):
        phi = phase + 2.0 * math.pi * (i + 0.37) / max(n_test, 1)
        test.append(cam(f"test_{i:03d}", np.array([math.cos(elev) * math.cos(phi),
                                                    math.cos(elev) * math.sin(phi), math.sin(elev)])))
    return train, test, dist


def to_mitsuba_world(camera: Camera) -> Camera:
    """The same camera in Mitsuba world (Y up): to_world left-multiplied by R^-1."""
    m = np.eye(4)
    m[:3, :3] = R_BLENDER_FROM_MITSUBA.T
    return replace(camera, to_world=m @ camera.to_world)


# --------------------------------------------------------------------------------------------
# Writers: the capture formats' own (vq_mitsuba.data.formats)
# --------------------------------------------------------------------------------------------
def write_scene_xml(path: Path, spec: dict, cameras_mi: list[Camera], spp: int, split: str) -> None:
    """The scene in Mitsuba world, its `split` cameras as sensors, no emitter."""
    r = R_BLENDER_FROM_MITSUBA
    note = "\n".join([
        f'vq-mitsuba synthetic scene "{spec["name"]}", {split} cameras. Mitsuba world (Y up):',
        f'     Blender world = R @ this world, R = {r.astype(int).tolist()}. No emitter: the lighting',
        '     is unknown to a fit. A lat-long map in Blender\'s convention lights this scene through an',
        '     envmap with identity to_world, exactly as it lights the Blender-world capture.'])
    materials = [{**m, BASE_COLOR: None if is_textured(m) else m[BASE_COLOR]} for m in spec["materials"]]
    shapes = [{"name": s["name"], "material": s["material"], "file": DatasetDir.shape_file(s["name"])}
              for s in spec["shapes"]]
    mitsuba_xml.write_capture(path, cameras_mi, materials, shapes, spp, SAMPLER, note)


# --------------------------------------------------------------------------------------------
# Ground-truth maps
# --------------------------------------------------------------------------------------------
def _camera_rays(cam: Camera, n_sub: int, rng: np.random.Generator):
    """Stratified jittered rays: origins (3,), directions (N, 3) ordered (sub, y, x)."""
    w, h, f = cam.width, cam.height, cam.focal_px()
    ys, xs = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
    dirs = []
    for sy in range(n_sub):
        for sx in range(n_sub):
            jx = (sx + rng.uniform(size=(h, w))) / n_sub
            jy = (sy + rng.uniform(size=(h, w))) / n_sub
            px, py = xs + jx, ys + jy
            local = np.stack([(0.5 * w - px) / f, (0.5 * h - py) / f, np.ones_like(px, dtype=np.float64)], -1)
            dirs.append(local.reshape(-1, 3))
    local = np.concatenate(dirs, 0)
    local /= np.linalg.norm(local, axis=1, keepdims=True)
    return cam.to_world[:3, 3], local @ cam.to_world[:3, :3].T


def render_gt(scene, cam_mi: Camera, spec: dict, shape_info: dict, rng: np.random.Generator,
              n_sub: int = GT_SAMPLES) -> dict:
    """GT maps of one view by tracing primary rays in the Mitsuba-world scene.

    Returns basecolor (H,W,3), metallic (H,W), roughness (H,W), normal (H,W,3, Blender world),
    material (H,W uint8; 0 = background, k = spec material k-1), alpha (H,W coverage).
    """
    import mitsuba as mi

    h, w = cam_mi.height, cam_mi.width
    origin, d = _camera_rays(cam_mi, n_sub, rng)
    n = len(d)
    ray = mi.Ray3f(mi.Point3f(*[mi.Float(np.full(n, origin[i], dtype=np.float32)) for i in range(3)]),
                   mi.Vector3f(*[mi.Float(np.ascontiguousarray(d[:, i], dtype=np.float32)) for i in range(3)]))
    si = scene.ray_intersect(ray)
    valid = np.array(si.is_valid(), dtype=bool)
    p_mi = np.stack([np.array(si.p.x), np.array(si.p.y), np.array(si.p.z)], -1).astype(np.float64)
    n_mi = np.stack([np.array(si.sh_frame.n.x), np.array(si.sh_frame.n.y), np.array(si.sh_frame.n.z)], -1)
    prim = np.array(si.prim_index, dtype=np.int64)
    r = R_BLENDER_FROM_MITSUBA
    n_bl = n_mi.astype(np.float64) @ r.T

    mat_index = {m["name"]: k for k, m in enumerate(spec["materials"])}
    mat_id = np.zeros(n, dtype=np.int64)  # per sample, 0 = miss
    values = {i.name: np.zeros((n, 3) if i.colour else n) for i in brdf.INPUTS}  # per sample
    for shape in scene.shapes():
        info = shape_info[shape.id()]
        mask = valid & np.array(si.shape == mi.ShapePtr(shape), dtype=bool)
        if not mask.any():
            continue
        mat = spec["materials"][mat_index[info["material"]]]
        mat_id[mask] = mat_index[info["material"]] + 1
        for i in brdf.INPUTS:
            if not (i.principled == BASE_COLOR and is_textured(mat)):
                values[i.name][mask] = np.asarray(mat[i.principled], dtype=np.float64)
        if is_textured(mat):
            # Interpolate the vertex colours Mitsuba renders with (barycentric, from the hit point).
            params = mi.traverse(shape)
            verts = np.array(params["vertex_positions"], dtype=np.float64).reshape(-1, 3)
            faces = np.array(params["faces"], dtype=np.int64).reshape(-1, 3)
            cols = np.array(params["vertex_color"], dtype=np.float64).reshape(-1, 3)
            tri = faces[prim[mask]]
            a, b, c = verts[tri[:, 0]], verts[tri[:, 1]], verts[tri[:, 2]]
            bary = _barycentric(p_mi[mask], a, b, c)
            values[brdf.BASECOLOR][mask] = np.einsum("nk,nkc->nc", bary, cols[tri])

    def per_pixel(x):  # (n_sub^2 * H * W, ...) -> (n_sub^2, H, W, ...)
        return x.reshape((n_sub * n_sub, h, w) + x.shape[1:])

    hits = per_pixel(valid.astype(np.float64))
    cnt = hits.sum(0)
    alpha = cnt / (n_sub * n_sub)
    denom = np.maximum(cnt, 1.0)
    maps = {i.name: ((per_pixel(values[i.name]) * hits[..., None]).sum(0) / denom[..., None] if i.colour
                     else (per_pixel(values[i.name]) * hits).sum(0) / denom).astype(np.float32) for i in brdf.INPUTS}
    normal = (per_pixel(n_bl) * hits[..., None]).sum(0)
    normal /= np.maximum(np.linalg.norm(normal, axis=-1, keepdims=True), 1e-12)
    ids = per_pixel(mat_id)
    k = len(spec["materials"])
    votes = np.stack([(ids == j).sum(0) for j in range(k + 1)], -1)
    material = np.argmax(votes, -1).astype(np.uint8)
    return {**maps, "normal": normal.astype(np.float32), "material": material, "alpha": alpha.astype(np.float32)}


def _barycentric(p, a, b, c) -> np.ndarray:
    v0, v1, v2 = b - a, c - a, p - a
    d00 = np.einsum("ij,ij->i", v0, v0)
    d01 = np.einsum("ij,ij->i", v0, v1)
    d11 = np.einsum("ij,ij->i", v1, v1)
    d20 = np.einsum("ij,ij->i", v2, v0)
    d21 = np.einsum("ij,ij->i", v2, v1)
    den = d00 * d11 - d01 * d01
    den = np.where(np.abs(den) > 1e-30, den, 1e-30)
    bv = (d11 * d20 - d01 * d21) / den
    bw = (d00 * d21 - d01 * d20) / den
    bary = np.clip(np.stack([1.0 - bv - bw, bv, bw], -1), 0.0, 1.0)
    return bary / np.maximum(bary.sum(-1, keepdims=True), 1e-12)


# --------------------------------------------------------------------------------------------
# The whole scene
# --------------------------------------------------------------------------------------------
def _material_values(m: dict, verts: np.ndarray) -> dict:
    """A scene.json material's BRDF inputs under their principled names; the base colour also as
    its pattern (None when plain) and its mean over `verts`."""
    out = {}
    for i in brdf.INPUTS:
        key = i.principled
        if key == BASE_COLOR:
            out[key] = m[key] if not is_textured(m) else None
            out[f"{key}_pattern"] = m[key] if is_textured(m) else None
            out[f"mean_{key}"] = eval_base_color(m[key], verts).mean(0).tolist() if is_textured(m) \
                else list(map(float, m[key]))
        else:
            out[key] = [float(c) for c in m[key]] if i.colour else float(m[key])
    return out


def scene_description(spec: dict, verts: np.ndarray, shape_info: dict, env_train_name: str, relights: list,
                      r: np.ndarray, center: np.ndarray, radius: float, dist: float, envmap_convention: str) -> dict:
    """The scene.json entries every generator (Mitsuba, Cycles) writes alike: cameras' frame,
    materials, shapes, lighting, world conventions and image encodings."""
    return {
        "fov_x_deg": FOV_X_DEG,
        "camera_distance": dist,
        "bounding_sphere": {"center": center.tolist(), "radius": radius},
        "materials": [{"id": k + 1, "name": m["name"], **_material_values(m, verts), "textured": is_textured(m)}
                      for k, m in enumerate(spec["materials"])],
        "shapes": [dict(name=k, **v) for k, v in shape_info.items()],
        "envmap": {"train": DatasetDir.envmap_file(DatasetDir.TRAIN_ENVMAP), "preset": env_train_name,
                   "sun_elevation_deg": envmaps.SKY_SUN_ELEVATION_DEG if env_train_name == "sky" else None,
                   "sun_azimuth_deg": envmaps.SKY_SUN_AZIMUTH_DEG if env_train_name == "sky" else None},
        "relight": relights,
        **({"lamps": spec["lamps"]} if spec.get("lamps") else {}),
        "worlds": {"json_and_mesh_ply": "Blender (Z up)", "xml_and_meshes_dir": "Mitsuba (Y up)",
                   "blender_from_mitsuba": r.tolist(),
                   "envmap_convention": "Blender lat-long; " + envmap_convention},
        "images": {"exr": "linear RGBA, premultiplied", "png": "sRGB RGBA, straight alpha = coverage"},
    }


def _versions() -> dict:
    import drjit as dr
    import mitsuba as mi

    from vq_mitsuba import __version__

    return {"vq_mitsuba": __version__, "mitsuba": mi.__version__, "drjit": dr.__version__,
            "numpy": np.__version__, "variant": mi.variant()}


OUT_SUBDIRS = DatasetDir.SUBDIRS  # a dataset's folders, emptied by each make-scene


def prepare_out_dir(out_dir, subdirs=OUT_SUBDIRS) -> Path:
    """out_dir with its `subdirs` made; where out_dir holds an earlier make-scene output
    (scene.json), it is removed first, whole, so no stale view or capture survives."""
    return DatasetDir(out_dir).prepare(subdirs)


@dataclass
class SceneGeometry:
    """The shapes of a scene spec, Blender world, as `write_geometry` wrote them."""

    shapes: list[dict]  # per shape: name, material, vertices (V,3), faces (F,3), normals (V,3)
    shape_info: dict  # scene.json's entry per shape name: material, file, vertices, faces
    verts: np.ndarray  # all vertices, merged (V,3)
    center: np.ndarray  # centre of the bounding box
    radius: float  # bounding sphere about center


def write_geometry(spec: dict, out: Path) -> SceneGeometry:
    """meshes/<shape>.ply in Mitsuba world (R^-1; vertex colours where the base colour is a
    pattern) and mesh.ply, all shapes merged in Blender world."""
    r = R_BLENDER_FROM_MITSUBA
    dataset = DatasetDir(out)
    mats = {m["name"]: m for m in spec["materials"]}
    shapes, all_v, all_f, all_n, shape_info = [], [], [], [], {}
    offset = 0
    for s in spec["shapes"]:
        v, f, nrm = build_shape(s)
        mat = mats[s["material"]]
        colors = eval_base_color(mat[BASE_COLOR], v) if is_textured(mat) else None
        shape_mesh = _mi_mesh(s["name"], v @ r, f, nrm @ r, colors)
        written(dataset.shape_mesh(s["name"]), lambda: shape_mesh.write_ply(str(dataset.shape_mesh(s["name"]))))
        shapes.append({"name": s["name"], "material": s["material"], "vertices": v, "faces": f, "normals": nrm})
        all_v.append(v), all_f.append(f + offset), all_n.append(nrm)
        offset += len(v)
        shape_info[s["name"]] = {"material": s["material"], "file": DatasetDir.shape_file(s["name"]),
                                 "vertices": int(len(v)), "faces": int(len(f))}
    verts = np.concatenate(all_v)
    merged = _mi_mesh("mesh", verts, np.concatenate(all_f), np.concatenate(all_n))
    written(dataset / DatasetDir.MESH, lambda: merged.write_ply(str(dataset / DatasetDir.MESH)))
    lo, hi = verts.min(0), verts.max(0)
    center = 0.5 * (lo + hi)
    radius = float(np.linalg.norm(verts - center, axis=1).max())
    return SceneGeometry(shapes, shape_info, verts, center, radius)


@dataclass
class SceneCameras:
    """The cameras `write_cameras` wrote: Blender world and the same in Mitsuba world."""

    train: list[Camera]
    test: list[Camera]
    dist: float  # camera distance from the bounding sphere's centre
    train_mi: list[Camera]
    test_mi: list[Camera]


def write_cameras(out: Path, spec: dict, geometry: SceneGeometry, n_train: int, n_test: int,
                  resolution: int | tuple[int, int], spp: int, seed: int) -> SceneCameras:
    """transforms_train.json, transforms_test.json (Blender world) and scene.xml, scene_test.xml
    (Mitsuba world) of the cameras `make_cameras` places about the geometry."""
    train, test, dist = make_cameras(geometry.center, geometry.radius, n_train, n_test, resolution, seed=seed)
    train_mi, test_mi = [to_mitsuba_world(c) for c in train], [to_mitsuba_world(c) for c in test]
    for path, cameras in ((DatasetDir.TRANSFORMS_TRAIN, train), (DatasetDir.TRANSFORMS_TEST, test)):
        nerf_synthetic.write_capture(out / path, cameras, [DatasetDir.frame_file(c.name) for c in cameras], FOV_X_DEG)
    write_scene_xml(out / DatasetDir.SCENE_XML, spec, train_mi, spp, "train")
    write_scene_xml(out / DatasetDir.SCENE_TEST_XML, spec, test_mi, spp, "test")
    return SceneCameras(train, test, dist, train_mi, test_mi)


def write_envmaps(out: Path, spec: dict, probes: dict[str, Path], keep_arrays: bool = False,
                  probe_note: str | None = None) -> tuple[str, np.ndarray, list[dict]]:
    """envmaps/train.exr, the spec's held-aside envmaps and the Blender studio-light `probes`
    (name -> path; saved as envmaps/blender_<name>.exr). Returns (training envmap's name, its
    array, relights): one scene.json entry per held-aside envmap (name, file, source, with
    `probe_note` as note on the probes' entries), holding its array under "array" if keep_arrays."""
    dataset = DatasetDir(out)

    def relight(env_name: str, arr: np.ndarray, source: str, note: str | None = None) -> dict:
        envmaps.save_envmap(dataset.envmap(env_name), arr)
        entry = {"name": env_name, "file": DatasetDir.envmap_file(env_name), "source": source}
        if note is not None:
            entry["note"] = note
        if keep_arrays:
            entry["array"] = arr
        return entry

    env_train_name = spec.get("envmap", "sky")
    env_train = envmaps.named_envmap(env_train_name)
    envmaps.save_envmap(dataset.envmap(DatasetDir.TRAIN_ENVMAP), env_train)
    relights = [relight(env_name, envmaps.named_envmap(env_name), "preset")
                for env_name in spec.get("relight", ["sunset", "studio"])]
    relights += [relight(f"blender_{probe}", envmaps.load_envmap(path), str(path), probe_note)
                 for probe, path in probes.items()]
    return env_train_name, env_train, relights


def _scene_settings(spec: dict, resolution, n_train, n_test, spp) -> tuple[tuple[int, int], int, int, int]:
    """make_scene's (width, height), n_train, n_test and spp: the arguments, or the spec's defaults."""
    res = resolution or spec.get("resolution", 128)
    res = (int(res), int(res)) if isinstance(res, (int, float)) else (int(res[0]), int(res[1]))
    n_train = int(spec.get("n_train", 64) if n_train is None else n_train)
    n_test = int(spec.get("n_test", 16) if n_test is None else n_test)
    spp = int(spp or spec.get("spp", 256))
    if min(res) < 1 or n_train < 1 or n_test < 1 or spp < 1:
        raise InputError(None, "resolution, view counts and spp must be positive")
    check_resolution(res)
    return res, n_train, n_test, spp


RESOLUTION_RANGE = (8, 4096)  # pixels per side: SSIM needs a few pixels; beyond 4096 a dataset outgrows memory


def check_resolution(res: tuple[int, int]) -> None:
    """Refuse, before any work, an image side outside RESOLUTION_RANGE."""
    lo, hi = RESOLUTION_RANGE
    if not all(lo <= int(side) <= hi for side in res):
        raise InputError(None, f"--resolution {'x'.join(map(str, res))}: each side must be {lo} to {hi} pixels")


def _mitsuba_scene_dict(spec: dict, out: Path) -> dict:
    """The Mitsuba scene (path tracer, materials, the meshes of out/meshes/) without its envmap."""
    base = {"type": "scene", "integrator": {"type": "path", "max_depth": MAX_DEPTH, "hide_emitters": True}}
    for m in spec["materials"]:
        bsdf = {"type": "principled", **brdf.FIXED}
        for i in brdf.INPUTS:
            if i.principled == BASE_COLOR and is_textured(m):
                bsdf[i.principled] = {"type": "mesh_attribute", "name": "vertex_color"}
            elif i.colour:
                bsdf[i.principled] = {"type": "rgb", "value": [float(c) for c in m[i.principled]]}
            else:
                bsdf[i.principled] = float(m[i.principled])
        base["mat_" + m["name"]] = bsdf
    for s in spec["shapes"]:
        base[s["name"]] = {"type": "ply", "filename": str(DatasetDir(out).shape_mesh(s["name"]).resolve()),
                           "bsdf": {"type": "ref", "id": "mat_" + s["material"]}}
    return base


def _checked_lamps(lamps, path: Path) -> list[dict]:
    """A spec's point lamps, `lamps: [{position: [x, y, z], intensity: [r, g, b] or a number,
    frame: world or camera}]` (radiant intensity, W/sr), checked: [] when it has none. A lamp's
    position is in Blender world, or with `frame: camera` in the frame of the camera of each view
    (Mitsuba camera space: +X left, +Y up, +Z forward): a flash that rides with the camera."""
    out = []
    for k, lamp in enumerate(lamps or []):
        pos, inten = (lamp.get("position"), lamp.get("intensity")) if isinstance(lamp, dict) else (None, None)
        inten = [inten] * 3 if isinstance(inten, (int, float)) else inten
        ok = all(isinstance(v, list) and len(v) == 3 and all(isinstance(x, (int, float)) and np.isfinite(x)
                                                                 for x in v) for v in (pos, inten))
        frame = lamp.get("frame", "world") if isinstance(lamp, dict) else None
        if not ok or min(inten) < 0 or frame not in ("world", "camera"):
            raise InputError(path, f"lamp {k + 1} needs a position [x, y, z], an intensity [r, g, b] >= 0 (or one "
                                   "number) and a frame world or camera")
        out.append({"position": [float(x) for x in pos], "intensity": [float(x) for x in inten], "frame": frame})
    return out


def _lamp_emitters(spec: dict) -> dict:
    """Mitsuba `point` emitters of the spec's lamps (Mitsuba world; those that ride with the camera
    are placed for each view by `_place_camera_lamps`)."""
    r = R_BLENDER_FROM_MITSUBA
    return {f"lamp_{k}": {"type": "point", "position": (np.asarray(lamp["position"]) @ r).tolist()
                          if lamp["frame"] == "world" else [0.0, 0.0, 0.0],
                          "intensity": {"type": "rgb", "value": lamp["intensity"]}}
            for k, lamp in enumerate(spec.get("lamps", []))}


def _place_camera_lamps(params, spec: dict, cam: Camera) -> None:
    """Move the spec's lamps that ride with the camera to `cam` (Mitsuba world) in the scene's
    parameters `params` (`mi.traverse` of the scene)."""
    for k, lamp in enumerate(spec.get("lamps", [])):
        if lamp["frame"] == "camera":
            key = f"lamp_{k}.position"
            params[key] = type(params[key])(*(np.asarray(cam.to_world)[:3, :3] @ lamp["position"]
                                              + np.asarray(cam.to_world)[:3, 3]).tolist())
    params.update()


def _scene_with(base: dict, env: np.ndarray):
    """The scene `base` lit by the lat-long map `env` (Mitsuba world, identity to_world)."""
    import mitsuba as mi

    # optimize=False: Mitsuba would merge the meshes that share a BSDF into one shape without
    # an id, and the ground-truth maps look shapes up by id.
    return mi.load_dict(dict(base, envmap=envmaps.to_mitsuba_dict(env, blender_world=False)), optimize=False)


def _make_sensors(cameras: list[Camera], spp: int) -> dict:
    """Camera name -> Mitsuba sensor with a SAMPLER sampler of spp samples (built once per view)."""
    import mitsuba as mi

    def make_sensor(cam: Camera):
        d = cam.to_mitsuba_dict(spp)
        d["sampler"] = {"type": SAMPLER, "sample_count": spp}
        return mi.load_dict(d)

    log_level = mi.logger().log_level()
    mi.logger().set_log_level(mi.LogLevel.Error)  # no "sample count rounded" warnings
    try:
        return {c.name: make_sensor(c) for c in cameras}
    finally:
        mi.logger().set_log_level(log_level)


def _render_views(name: str, spec: dict, out: Path, base: dict, sensors: dict, cams: SceneCameras,
                  env_train: np.ndarray, relights: list[dict], shape_info: dict, seed: int) -> None:
    """images/ (train and test views under the training envmap), gt/ (test views) and relit/
    (test views under each held-aside envmap, whose "array" is taken from its relights entry)."""
    import mitsuba as mi
    from vq_mitsuba import messages

    train_mi, test_mi = cams.train_mi, cams.test_mi
    total = len(train_mi) + len(test_mi) + len(test_mi) * len(relights)
    bar = messages.progress(total=total, desc=f"make-scene {name}", unit="view")
    counter = [seed * 1_000_003]

    dataset = DatasetDir(out)

    flash = any(lamp["frame"] == "camera" for lamp in spec.get("lamps", []))

    def render(scene, cam: Camera, env: str | None = None):
        if env is None and flash:  # the training light: the flash at this view's camera
            _place_camera_lamps(mi.traverse(scene), spec, cam)
        img = mi.render(scene, sensor=sensors[cam.name], seed=counter[0] % (2**32))
        counter[0] += 1
        dataset.write_view(cam.name, np.array(img), env)
        bar.update(1)

    scene = _scene_with(dict(base, **_lamp_emitters(spec)), env_train)  # relit views: the envmap alone
    for cam in train_mi + test_mi:
        render(scene, cam)
    rng = np.random.default_rng(seed + 1)
    for cam in test_mi:
        gt = render_gt(scene, cam, spec, shape_info, rng)
        dataset.write_gt(cam.name, gt)
    del scene
    for rl in relights:
        scene = _scene_with(base, rl.pop("array"))
        dataset.relit_dir(rl["name"]).mkdir(parents=True, exist_ok=True)
        for cam in test_mi:
            render(scene, cam, rl["name"])
        del scene
    bar.close()


def check_seed(seed) -> None:
    """A dataset's seed is a whole number from 0 to MAX_SEED (both renderers)."""
    if isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed <= MAX_SEED:
        raise InputError(None, f"--seed {seed}: a seed is a whole number from 0 to {MAX_SEED}")


def make_scene(name: str, out_dir, resolution: int | tuple[int, int] | None = None, n_train: int | None = None,
               n_test: int | None = None, spp: int | None = None, seed: int = 0,
               photo_formats: bool = False) -> Path:
    """Render the bundled synthetic scene `name` into out_dir (both capture formats, GT maps,
    relit test views). None for resolution / n_train / n_test / spp takes the scene's default
    (synthetic/scenes/<name>.yaml); resolution is a side or (width, height). `photo_formats` also writes the
    training views as NeuS/IDR (neus/), COLMAP (colmap/, colmap_opencv/), nerfstudio (nerfstudio/) and
    LLFF (llff/) captures. Returns out_dir."""
    check_seed(seed)
    init_mitsuba()
    t_start = time.time()
    spec = load_scene_spec(name)
    res, n_train, n_test, spp = _scene_settings(spec, resolution, n_train, n_test, spp)
    with _complete_or_removed(out_dir) as out:
        _render_dataset(name, spec, out, res, n_train, n_test, spp, seed, t_start)
        if photo_formats:
            from vq_mitsuba.data.captures import load_capture
            from vq_mitsuba.data.formats.copies import write_photo_formats

            write_photo_formats(load_capture(out / DatasetDir.SCENE_XML), out)
    return out


INCOMPLETE = DatasetDir.INCOMPLETE  # in a dataset folder while make-scene writes it


@contextmanager
def _complete_or_removed(out_dir):
    """The dataset folder, prepared (`prepare_out_dir`) and marked incomplete while the body runs;
    if the body fails, what it wrote into a new or empty folder is removed, and an earlier dataset's
    folder keeps the mark and no scene.json (the next make-scene into it empties it first): no
    half-written dataset passes for a whole one."""
    out = Path(out_dir)
    made = not out.exists()
    empty = made or not any(out.iterdir())
    out = prepare_out_dir(out)
    DatasetDir(out).mark_incomplete()  # and an earlier dataset's scene.json removed, written again last
    try:
        yield out
    except BaseException as exc:
        if empty:
            shutil.rmtree(out, ignore_errors=True)
            if not made:
                out.mkdir()
        error = _refused_write(exc, out, removed=empty)
        if error is not None:
            raise error from None
        raise
    DatasetDir(out).mark_complete()


def _refused_write(exc: BaseException, out: Path, removed: bool) -> WriteError | None:
    """A write the disk refused (full, read-only, no permission) as a WriteError naming the file, or
    the dataset folder where the error names none, and saying what became of the dataset; None for
    any other exception."""
    error = exc if isinstance(exc, WriteError) else as_write_error(exc)
    if error is None:
        return None
    reason = error.message.removesuffix(" (files written before are kept)")
    became = "the unfinished dataset is removed" if removed else \
        f"the folder keeps its {INCOMPLETE} mark until make-scene finishes writing it"
    return WriteError(error.path or out, f"{reason} ({became})")


def _render_dataset(name: str, spec: dict, out: Path, res, n_train: int, n_test: int, spp: int, seed: int,
                    t_start: float) -> None:
    """make_scene's views, ground truth and scene.json into the prepared folder `out`."""
    # Geometry and cameras: Blender world for mesh.ply and the json, Mitsuba world (R^-1) for the XML.
    geometry = write_geometry(spec, out)
    cams = write_cameras(out, spec, geometry, n_train, n_test, res, spp, seed)
    env_train_name, env_train, relights = write_envmaps(out, spec, envmaps.blender_probes(), keep_arrays=True)

    # One Mitsuba scene per envmap (Mitsuba world, identity to_world), sensors built once.
    base = _mitsuba_scene_dict(spec, out)
    sensors = _make_sensors(cams.train_mi + cams.test_mi, spp)
    spp_used = int(next(iter(sensors.values())).sampler().sample_count())
    t_render = time.time()
    _render_views(name, spec, out, base, sensors, cams, env_train, relights, geometry.shape_info, seed)
    t_end = time.time()

    meta = {
        "name": name,
        "description": spec.get("description", ""),
        "resolution": list(res),
        "n_train": n_train,
        "n_test": n_test,
        "spp": spp_used,
        "sampler": SAMPLER,
        "seed": seed,
        "max_depth": MAX_DEPTH,
        "integrator": "path",
        **scene_description(spec, geometry.verts, geometry.shape_info, env_train_name, relights,
                            R_BLENDER_FROM_MITSUBA, geometry.center, geometry.radius, cams.dist,
                            envmap_convention="to_world = BLENDER_ENV_TO_WORLD in Blender world, identity in "
                                              "the XML's Mitsuba world"),
        "render_seconds": round(t_end - t_render, 2),
        "total_seconds": round(t_end - t_start, 2),
        "versions": _versions(),
    }
    DatasetDir(out).write_info(meta)
