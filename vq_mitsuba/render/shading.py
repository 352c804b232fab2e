"""Deferred physically based shading with Mitsuba's `principled` BSDF and an envmap emitter.

This module drives Dr.Jit/Mitsuba's shading during fitting and rendering (ray casting for coverage
masks is `geometry/mesh.py`'s). Geometry is fixed, so primary hits are traced once (no gradients)
and reused; at each step the material fields are evaluated in torch once per hit point and
handed to Mitsuba through `dr.wrap`. A small texture plugin (`vqm_lanes`) returns those per-lane
values when `principled` asks for `base_color`, `metallic` or `roughness`, so the BSDF code is
Mitsuba's own, not a copy.

Each lane takes one emitter sample (`scene.sample_emitter_direction`, importance-sampled from
the envmap, shadow ray tested) and one BSDF sample, combined with the power heuristic. When the
BSDF sample hits the object itself, the radiance arriving along it can be supplied by the
caller (`shade(..., material_fn=...)` shades that second hit with the same fields, direct light
only, as incoming light that is not differentiated), so one interreflection is simulated; deeper
paths are not (biased dark in deep concavities).
Sampled directions carry no gradient (as in Mitsuba's `prb`: BSDF values are differentiated,
sampling is detached). So a call runs two kernels: the sampling kernel draws both samples and traces
every ray without gradients (the shadow ray, and the BSDF sample's ray, whose hit is also the
bounce's point), and the differentiable kernel evaluates the BSDF at the stored samples, lit by the
envmap's radiance along them, which torch looks up as Mitsuba's envmap does (`envmap_lookup`: its
gradient then adds up in the same order every run). The backward pass traces no ray again: it
differentiates the second kernel alone.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

import drjit as dr
import mitsuba as mi

from vq_mitsuba import brdf
from vq_mitsuba.backend import init_mitsuba, torch_device

_PLUGINS_READY = False
# Differentiable inputs per shading lane: the BRDF's channels and the bounce's RGB radiance; then,
# where the envmap is differentiated, its RGB radiance along the emitter sample and along the BSDF
# sample where it escapes (LIGHT_LANES).
LIGHT_LANES = 6


def lane_inputs() -> int:
    """Differentiable inputs per shading lane besides the light's: the BRDF's channels and RGB."""
    return brdf.CHANNELS + 3


def _register_plugins() -> None:
    # Mitsuba classes exist only once a variant is set, so the plugin is defined here.
    global _PLUGINS_READY
    if _PLUGINS_READY:
        return
    _PLUGINS_READY = True
    class LaneTexture(mi.Texture):
        """A texture that returns values set per lane by the caller (one lane = one shading sample).

        `principled` calls `eval` for `base_color` and `eval_1` for scalars; the values are whatever
        the fitted fields produced for the hit point behind each lane, with their AD graph.
        """

        def __init__(self, props):
            super().__init__(props)
            self.values: tuple | None = None  # (Float,) or (Float, Float, Float)

        def eval(self, si, active=True):
            v = self.values
            if v is None:  # traced by a vcall of another render: no lanes set
                return mi.Color3f(0.5)
            return mi.Color3f(v[0], v[1], v[2]) if len(v) == 3 else mi.Color3f(v[0])

        def eval_3(self, si, active=True):
            return self.eval(si, active)

        def eval_1(self, si, active=True):
            return mi.Float(0.5) if self.values is None else self.values[0]

        def mean(self):
            return 0.5

        def traverse(self, callback):
            pass

        def to_string(self):
            return "LaneTexture[]"

    mi.register_texture("vqm_lanes", lambda props: LaneTexture(props))


def _flat(t) -> "mi.Float":
    """A kernel input as a flat Dr.Jit array (keeps array sizes out of the kernels' shapes)."""
    return mi.Float(t.array) if isinstance(t, mi.TensorXf) else mi.Float(t)


def envmap_padded(env: torch.Tensor) -> torch.Tensor:
    """(H, W, 3) -> (H, W + 2, 3) as Mitsuba's envmap stores it (wrap-around columns 0 and W+1)."""
    return torch.cat([env[:, -1:], env, env[:, :1]], dim=1)


def envmap_lookup(padded: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
    """The radiance (N, 3) Mitsuba's `envmap` gives at its texture coordinates `uv` (N, 2) from the
    padded data (`envmap_padded`, (H, W + 2, 3)): bilinear between texel centres, u wrapping around
    (its centres at (i + 0.5) / W), v from the first row's centre at 0 to the last's at 1 (as
    Mitsuba 3.9 evaluates it; `tests/render/test_rendering.py` holds the two together). In torch,
    so the envmap's gradient is summed in one order: Dr.Jit's scatter of it from several threads
    adds in a different order each run."""
    h, w2 = padded.shape[:2]
    u = uv[:, 0] - torch.floor(uv[:, 0])
    x, y = u * (w2 - 2) + 0.5, uv[:, 1] * (h - 1)
    ix, iy = x.long().clamp(0, w2 - 2), y.long().clamp(0, h - 2)
    fx, fy = (x - ix)[:, None], (y - iy)[:, None]
    flat, i = padded.reshape(-1, 3), iy * w2 + ix
    # index_select: its gradient (index_add) adds in index order on a CPU; indexing's does not
    v00, v10, v01, v11 = (torch.index_select(flat, 0, j) for j in (i, i + 1, i + w2, i + w2 + 1))
    top = v00 + fx * (v10 - v00)
    bottom = v01 + fx * (v11 - v01)
    return top + fy * (bottom - top)


def direction_uv(d_world: torch.Tensor, world_to_env: torch.Tensor) -> torch.Tensor:
    """Mitsuba's envmap texture coordinates (N, 2) of world directions (N, 3) towards the light."""
    v = d_world @ world_to_env.T
    return torch.stack([torch.atan2(v[:, 0], -v[:, 2]) * (0.5 / math.pi),
                        torch.acos(v[:, 1].clamp(-1.0, 1.0)) * (1.0 / math.pi)], -1)


def _lattice_generator(m: int) -> int:
    """A rank-1 lattice generator for m points: close to m / golden ratio, coprime to m."""
    g = max(1, round(m / 1.6180339887))
    while math.gcd(g, m) != 1:
        g += 1
    return g


def stratified_samples(n_points: int, spp: int, groups: int, generator: torch.Generator | None,
                       device) -> torch.Tensor:
    """(5, n_points * spp) random numbers for `shade`, stratified per point and per group.

    Each point's spp samples form `groups` independent sets of spp // groups samples; within a
    set the emitter and BSDF 2-D samples are randomly shifted rank-1 lattices and the lobe choice
    is a shifted 1-D stratification, each in its own random order so the dimensions stay
    independent. Far less noise than independent samples at equal count; sets are independent
    of each other, so estimates from different sets are uncorrelated.
    """
    m = spp // groups
    if m <= 1 or m * groups != spp:
        return torch.rand(5, n_points * spp, generator=generator, device=device)
    i = torch.arange(m, device=device, dtype=torch.float32)
    g = _lattice_generator(m)
    base = torch.stack([i / m, torch.remainder(i * g, m) / m])  # (2, m)
    rows = n_points * groups
    shift = torch.rand(5, rows, 1, generator=generator, device=device)
    perm = torch.argsort(torch.rand(3, rows, m, generator=generator, device=device), dim=-1)
    em = base[:, perm[0]]  # (2, rows, m)
    lobe = (i / m)[perm[1]][None]
    bs = base[:, perm[2]]
    u = torch.cat([em, lobe, bs], 0)
    u = torch.remainder(u + shift, 1.0)
    return u.reshape(5, n_points * spp)


def mesh_to_mitsuba(vertices: np.ndarray, faces: np.ndarray, normals: np.ndarray | None = None) -> "mi.Mesh":
    """A Mitsuba triangle mesh from arrays (world space), with smooth vertex normals."""
    vertices = np.ascontiguousarray(vertices, dtype=np.float32)
    faces = np.ascontiguousarray(faces, dtype=np.uint32)
    # Mitsuba cannot add normals to a mesh built without them, so the buffer always exists.
    mesh = mi.Mesh("geometry", len(vertices), len(faces), has_vertex_normals=True)
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float(vertices.ravel())
    params["faces"] = mi.UInt32(faces.ravel())
    if normals is not None:
        params["vertex_normals"] = mi.Float(np.ascontiguousarray(normals, dtype=np.float32).ravel())
    params.update()
    if normals is None:
        mesh.recompute_vertex_normals()
    return mesh


@dataclass
class Hits:
    """Surface points seen by rays (torch tensors on the shading device)."""

    valid: torch.Tensor  # (N,) bool
    position: torch.Tensor  # (N, 3) world
    normal: torch.Tensor  # (N, 3) world, shading normal facing the viewer side
    wi: torch.Tensor  # (N, 3) world, unit vector from the point towards the ray origin


def _setup_kernel(textures: tuple):
    """setup(p, n, wi, the BRDF's channels (brdf.CHANNELS flat arrays, in the order of brdf.INPUTS))
    -> the SurfaceInteraction3f of the lanes, with the lanes' BRDF loaded into `textures` (the
    BSDF's lane textures)."""
    f = _flat

    def setup(px, py, pz, nx, ny, nz, wx, wy, wz, chans):
        # Flat 1-D inputs keep array sizes out of the kernels (no per-step recompiles).
        px, py, pz, nx, ny, nz, wx, wy, wz = map(f, (px, py, pz, nx, ny, nz, wx, wy, wz))
        si = dr.zeros(mi.SurfaceInteraction3f, dr.width(px))
        si.p = mi.Point3f(px, py, pz)
        normal = mi.Normal3f(nx, ny, nz)
        si.n = normal
        si.sh_frame = mi.Frame3f(normal)
        si.wi = si.sh_frame.to_local(mi.Vector3f(wx, wy, wz))
        si.t = mi.Float(1.0)
        at = 0
        for inp, tex in zip(brdf.INPUTS, textures):
            tex.values = tuple(f(c) for c in chans[at:at + inp.channels])
            at += inp.channels
        return si

    return setup

def _sample_kernel(scene, bsdf, ctx, textures: tuple, setup):
    """The sampling kernel: each lane's emitter sample with its shadow ray and its BSDF sample
    with the ray it casts, in one kernel without gradients (the light in the scene must be set).
    Returns the `SAMPLED` arrays (torch): what shading reads, and where the BSDF sample meets the
    object (the bounce's points: p2, n2 facing back, wi2)."""
    f = _flat

    @dr.wrap(source="torch", target="drjit")
    def sample(px, py, pz, nx, ny, nz, wx, wy, wz, chans, u):
        with dr.suspend_grad():
            si = setup(px, py, pz, nx, ny, nz, wx, wy, wz, chans)
            u = [f(x) for x in u]
            # Emitter sampling with a shadow ray (unbounded: anything on the way occludes the envmap).
            ds, _ = scene.sample_emitter_direction(si, mi.Point2f(u[0], u[1]), False)
            lit = (ds.pdf > 0) & ~scene.ray_test(si.spawn_ray(ds.d), ds.pdf > 0)
            # BSDF sampling; the sampled direction is detached, its value differentiated in shading.
            bs, _ = bsdf.sample(ctx, si, u[2], mi.Point2f(u[3], u[4]))
            ray = si.spawn_ray(si.to_world(bs.wo))
            si_next = scene.ray_intersect(ray)
            miss = ~si_next.is_valid() & (bs.pdf > 0)
            pdf_em = scene.pdf_emitter_direction(si, mi.DirectionSample3f(scene, si_next, si), miss)
            w_bs = dr.select(miss, dr.rcp(1.0 + dr.square(pdf_em / bs.pdf)), 0.0)
            inv_pdf = dr.select(bs.pdf > 0, dr.rcp(bs.pdf), 0.0)
            hit = si_next.is_valid() & (bs.pdf > 0)
            n2 = si_next.sh_frame.n
            n2 = dr.select(dr.dot(n2, -ray.d) < 0, -n2, n2)
            out = (ds.d.x, ds.d.y, ds.d.z, ds.uv.x, ds.uv.y, ds.pdf, dr.select(lit, 1.0, 0.0),
                   bs.wo.x, bs.wo.y, bs.wo.z,
                   w_bs, inv_pdf, dr.select(miss, 1.0, 0.0), dr.select(hit, 1.0, 0.0),
                   *(dr.select(hit, v, 0.0) for v in (si_next.p.x, si_next.p.y, si_next.p.z, n2.x, n2.y, n2.z)),
                   -ray.d.x, -ray.d.y, -ray.d.z)
            dr.eval(*out)  # one kernel for all outputs (converted one by one, each would trace again)
        for tex in textures:
            tex.values = None
        return out

    return sample

# The sampling kernel's outputs, in order: the emitter sample (direction, the envmap's texture
# coordinates that Mitsuba's envmap looks its radiance up at, pdf, unoccluded), the
# BSDF sample (local direction, MIS weight where it escapes, 1 / pdf, escapes, meets the object),
# the point it meets (p2, n2 facing back) and the world direction back along it (wi2).
SAMPLED = ("dx", "dy", "dz", "ds_u", "ds_v", "ds_pdf", "lit",
           "wo_x", "wo_y", "wo_z", "w_bs", "inv_pdf", "miss", "hit",
           "p2x", "p2y", "p2z", "n2x", "n2y", "n2z", "wi2x", "wi2y", "wi2z")

def _shade_kernel(bsdf, ctx, textures: tuple, emitter, setup, light_lanes: bool):
    """The shading kernel: the sampled emitter direction (MIS) plus the BSDF sample, lit by the
    envmap or by the caller's bounce radiance; the differentiable part of shading, reading the
    sampling kernel's results (so the backward pass traces no ray). The envmap's radiance comes
    as lanes with `light_lanes` (a differentiated envmap), else from the scene's emitter."""
    inputs = lane_inputs()
    width = inputs + (LIGHT_LANES if light_lanes else 0)
    f = _flat

    @dr.wrap(source="torch", target="drjit")
    def shade(px, py, pz, nx, ny, nz, wx, wy, wz, lanes, sampled):
        # `lanes` holds the differentiable per-lane inputs interleaved (the BRDF's channels,
        # then the bounce's, the emitter sample's and the escaping BSDF sample's radiance, r, g,
        # b each): one gradient array, so the backward pass is one kernel instead of one per
        # input, each tracing the shading again. A differentiated light's radiance comes in as
        # lanes (`envmap_lookup`), so no Dr.Jit scatter adds into the envmap.
        # Each lane reads its own entries, so the backward scatter has no conflicts (Permute);
        # the default mode's per-thread copies bake the array size in: a compile per size.
        lanes, idx = f(lanes), dr.arange(mi.UInt32, dr.width(px)) * width
        values = [dr.gather(mi.Float, lanes, idx + c, mode=dr.ReduceMode.Permute) for c in range(width)]
        chans, (lr, lg, lb), light = values[:brdf.CHANNELS], values[brdf.CHANNELS:inputs], values[inputs:]
        si = setup(px, py, pz, nx, ny, nz, wx, wy, wz, chans)
        sm = dict(zip(SAMPLED, (f(v) for v in sampled)))
        d_em, pdf_em = mi.Vector3f(sm["dx"], sm["dy"], sm["dz"]), sm["ds_pdf"]
        lit, miss, hit_obj = sm["lit"] > 0.5, sm["miss"] > 0.5, sm["hit"] > 0.5
        if light_lanes:
            le_em, le_bs = mi.Color3f(*light[:3]), mi.Color3f(*light[3:])
        else:
            ds = dr.zeros(mi.DirectionSample3f, dr.width(px))
            ds.d, ds.uv, ds.pdf = d_em, mi.Point2f(sm["ds_u"], sm["ds_v"]), pdf_em
            escaped = dr.zeros(mi.SurfaceInteraction3f, dr.width(px))
            escaped.wi = mi.Vector3f(sm["wi2x"], sm["wi2y"], sm["wi2z"])  # world, as for a missed ray
            le_em, le_bs = emitter.eval_direction(si, ds, lit), emitter.eval(escaped, miss)
        em_weight = dr.select(lit, le_em * dr.rcp(pdf_em), 0.0)
        f_em, pdf_bsdf = bsdf.eval_pdf(ctx, si, si.to_local(d_em))
        # Power-heuristic MIS weights as 1 / (1 + (p_other / p)^2): a near-specular lobe's huge
        # pdf cannot overflow a square into inf / inf.
        w_em = dr.detach(dr.select(pdf_em > 0, dr.rcp(1.0 + dr.square(pdf_bsdf / pdf_em)), 0.0))
        radiance = f_em * em_weight * w_em

        # The BSDF sample: its direction detached, its value differentiated.
        f_bs = bsdf.eval(ctx, si, mi.Vector3f(sm["wo_x"], sm["wo_y"], sm["wo_z"]))
        le = dr.select(miss, le_bs, 0.0)
        # Radiance arriving from the object itself (one bounce), supplied by the caller; the
        # emitter sample is occluded in that direction, so its MIS weight is 1.
        li_obj = mi.Color3f(lr, lg, lb)
        radiance += f_bs * dr.select(hit_obj, li_obj, le * sm["w_bs"]) * sm["inv_pdf"]
        dr.eval(radiance)  # one kernel for the three channels, not one each
        for tex in textures:
            tex.values = None
        return radiance.x, radiance.y, radiance.z

    return shade


def _lamp_kernels(scene, bsdf, ctx, textures: tuple, setup):
    """The kernels of point lamps: `visible` (whether the segment from each point to its lamp is
    free, without gradients) and `shade` (the BSDF at the lamp's direction times the radiance
    arriving from it, both given per lane, differentiable in both and in the lanes' BRDF)."""
    f = _flat
    width = brdf.CHANNELS + 6

    @dr.wrap(source="torch", target="drjit")
    def visible(px, py, pz, nx, ny, nz, lx, ly, lz):
        with dr.suspend_grad():
            si = dr.zeros(mi.SurfaceInteraction3f, dr.width(f(px)))
            si.p = mi.Point3f(f(px), f(py), f(pz))
            si.n = mi.Normal3f(f(nx), f(ny), f(nz))
            free = ~scene.ray_test(si.spawn_ray_to(mi.Point3f(f(lx), f(ly), f(lz))))
            out = dr.select(free, 1.0, 0.0)
            dr.eval(out)
        return out

    @dr.wrap(source="torch", target="drjit")
    def shade(px, py, pz, nx, ny, nz, wx, wy, wz, lanes):
        # `lanes`: the BRDF's channels, the world direction towards the lamp and the radiance
        # arriving from it (I / d^2, zero where occluded), interleaved as `_shade_kernel` reads them
        lanes, idx = f(lanes), dr.arange(mi.UInt32, dr.width(f(px))) * width
        values = [dr.gather(mi.Float, lanes, idx + c, mode=dr.ReduceMode.Permute) for c in range(width)]
        chans, d, li = values[:brdf.CHANNELS], values[brdf.CHANNELS:brdf.CHANNELS + 3], values[brdf.CHANNELS + 3:]
        si = setup(px, py, pz, nx, ny, nz, wx, wy, wz, chans)
        radiance = bsdf.eval(ctx, si, si.to_local(mi.Vector3f(*d))) * mi.Color3f(*li)
        dr.eval(radiance)
        for tex in textures:
            tex.values = None
        return radiance.x, radiance.y, radiance.z

    return visible, shade


@dataclass
class Lanes:
    """Shading lanes: the points' position, normal and direction towards the viewer, as nine flat
    arrays (x, y, z each), and their BRDF inputs' channels (N, brdf.CHANNELS)."""

    geometry: tuple
    chans: torch.Tensor


class ShadingScene:
    """Fixed geometry + an envmap emitter + a `principled` BSDF fed by lane textures."""

    SAMPLED = SAMPLED  # the sampling kernel's outputs, in order

    def __init__(self, vertices, faces, env_init: np.ndarray, env_to_world: np.ndarray, normals=None):
        init_mitsuba()
        _register_plugins()
        self.mesh = mesh_to_mitsuba(vertices, faces, normals)
        env_init = np.ascontiguousarray(env_init, dtype=np.float32)
        self.env_shape = env_init.shape
        # the linear part of the envmap's world-to-local transform (directions), as Mitsuba's envmap applies it
        self.world_to_env = torch.tensor(np.linalg.inv(np.asarray(env_to_world, np.float64))[:3, :3],
                                         dtype=torch.float32, device=torch_device())
        self.scene = mi.load_dict(
            {
                "type": "scene",
                "geometry": self.mesh,
                "env": {
                    "type": "envmap",
                    "bitmap": mi.Bitmap(env_init),
                    "to_world": mi.ScalarTransform4f(np.asarray(env_to_world, dtype=np.float64).tolist()),
                },
            }
        )
        self.emitter = self.scene.environment()
        self.params = mi.traverse(self.scene)
        self.env_key = [k for k in self.params.keys() if k.endswith(".data")][0]
        self.textures = tuple(mi.load_dict({"type": "vqm_lanes"}) for _ in brdf.INPUTS)  # one per input
        self.bsdf = mi.load_dict({"type": "principled", **brdf.FIXED,
                                  **{i.principled: t for i, t in zip(brdf.INPUTS, self.textures)}})
        self.ctx = mi.BSDFContext()
        self._light_set = None  # (the envmap tensor last set for sampling, its version)
        # the sampling kernel and the shading kernels (lit by the light given as lanes, and by the
        # envmap set in the scene), sharing one setup of the shading points
        setup = _setup_kernel(self.textures)
        self._sample = _sample_kernel(self.scene, self.bsdf, self.ctx, self.textures, setup)
        self._shade = _shade_kernel(self.bsdf, self.ctx, self.textures, self.emitter, setup, light_lanes=True)
        self._shade_lit = _shade_kernel(self.bsdf, self.ctx, self.textures, self.emitter, setup, light_lanes=False)
        self._lamp_visible, self._lamp_shade = _lamp_kernels(self.scene, self.bsdf, self.ctx, self.textures, setup)
        # Point lamps beside the envmap: None, or a callable of the points' view indices (or None)
        # giving the lamps' world positions, (K, 3) or per point (K, N, 3), and radiant intensities
        # (K, 3) as torch tensors (differentiable where they are fitted).
        self.lamps = None

    # -- primary visibility -------------------------------------------------------------
    def trace(self, origins: np.ndarray, directions: np.ndarray) -> Hits:
        """First hits of rays (no gradients). Normals are flipped to face the ray origin."""
        if len(origins) == 0:  # Dr.Jit aborts on a ray array of size 0 (e.g. a view with no opaque pixel)
            dev = torch_device()
            empty = torch.zeros((0, 3), device=dev)
            return Hits(torch.zeros(0, dtype=torch.bool, device=dev), empty, empty.clone(), empty.clone())
        with dr.suspend_grad():
            ray = mi.Ray3f(mi.Point3f(*[mi.Float(origins[:, i]) for i in range(3)]),
                           mi.Vector3f(*[mi.Float(directions[:, i]) for i in range(3)]))
            si = self.scene.ray_intersect(ray)
            valid = si.is_valid()
            n = si.sh_frame.n
            flip = dr.dot(n, -ray.d) < 0
            n = dr.select(flip, -n, n)
            out = [valid, si.p.x, si.p.y, si.p.z, n.x, n.y, n.z]
            dr.eval(*out)
        dev = torch_device()
        valid_t = torch.as_tensor(np.array(out[0]), dtype=torch.bool, device=dev)
        pos = torch.as_tensor(np.stack([np.array(a) for a in out[1:4]], -1), device=dev)
        nrm = torch.as_tensor(np.stack([np.array(a) for a in out[4:7]], -1), device=dev)
        pos = torch.where(valid_t[:, None], pos, torch.zeros_like(pos))
        nrm = torch.where(valid_t[:, None], nrm, torch.zeros_like(nrm))
        wi = -torch.as_tensor(directions, device=dev)
        return Hits(valid_t, pos.float(), nrm.float(), wi.float())

    def secondary_hits(self, position: np.ndarray, wi: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Whether cosine-distributed rays from surface points meet the object: (valid, hit), (N,)
        bools. `position` (N, 3) are hits seen along -`wi` (unit, towards the viewer); each is traced
        again along -wi for its geometric normal (not the interpolated one, whose hemisphere dips
        under the facets of a coarse mesh), and one ray leaves it in the hemisphere on the viewer's
        side with a cosine-weighted direction from `u` (2, N) in [0, 1). `valid`: the point was
        found again."""
        position = np.ascontiguousarray(position, dtype=np.float32)
        wi = np.ascontiguousarray(wi, dtype=np.float32)
        eps = 1e-4 * float(np.linalg.norm(np.ptp(position, axis=0)) + 1e-3)
        with dr.suspend_grad():
            p = mi.Point3f(*[mi.Float(position[:, i]) for i in range(3)])
            w = mi.Vector3f(*[mi.Float(wi[:, i]) for i in range(3)])
            si = self.scene.ray_intersect(mi.Ray3f(p + w * eps, -w))
            valid = si.is_valid()
            n = dr.select(dr.dot(si.n, w) < 0, -si.n, si.n)
            local = mi.warp.square_to_cosine_hemisphere(mi.Point2f(mi.Float(u[0]), mi.Float(u[1])))
            ray = si.spawn_ray(mi.Frame3f(n).to_world(local))
            hit = valid & self.scene.ray_test(ray, valid)
            dr.eval(valid, hit)
        return np.array(valid, dtype=bool), np.array(hit, dtype=bool)

    # -- shading ------------------------------------------------------------------------
    def _light_lanes(self, env_linear: torch.Tensor, sampled: list, fixed: torch.Tensor) -> tuple:
        """The envmap's radiance (lanes, 3) along each lane's emitter sample (at the texture
        coordinates it was drawn at) and along its BSDF sample (where that escapes: the direction
        back along it, reversed), differentiable in `env_linear` except on lanes whose light is
        `fixed` (> 0.5)."""
        at = {name: sampled[i] for i, name in enumerate(self.SAMPLED)}
        padded = envmap_padded(env_linear)
        le_em = envmap_lookup(padded, torch.stack([at["ds_u"], at["ds_v"]], -1))
        wi2 = torch.stack([at["wi2x"], at["wi2y"], at["wi2z"]], -1)
        le_bs = envmap_lookup(padded, direction_uv(-wi2, self.world_to_env.to(wi2.device)))
        keep = fixed[:, None] > 0.5
        return tuple(torch.where(keep, le.detach(), le) for le in (le_em, le_bs))

    # Shading in steps, as `shade` runs them: `lanes` (the points and their BRDF), `set_light`,
    # `sample` (where each lane's emitter and BSDF samples go, traced without gradients),
    # `bounce_light` (the radiance arriving along BSDF samples that meet the object) and `radiance`
    # (the differentiable estimate). Each can be called alone.
    def lanes(self, position: torch.Tensor, normal: torch.Tensor, wi: torch.Tensor, material: dict) -> "Lanes":
        """The shading lanes of points (N, 3) seen from `wi` with their BRDF inputs (`vq_mitsuba.brdf`)."""
        n = position.shape[0]
        chans = torch.cat([material[i.name].reshape(n, i.channels) for i in brdf.INPUTS], 1)
        geometry = tuple(t[:, k] for t in (position, normal, wi) for k in range(3))
        return Lanes(geometry, chans)

    def set_light(self, env_linear: torch.Tensor) -> None:
        """The envmap `sample` draws emitter samples from (its distribution rebuilt, unless these
        values are already set: the bounce's shading and the step's share one light)."""
        if self._light_set is not None and self._light_set[0] is env_linear \
                and self._light_set[1] == env_linear._version:
            return
        self.params[self.env_key] = mi.TensorXf(envmap_padded(env_linear.detach()).contiguous())
        self.params.update()
        self._light_set = (env_linear, env_linear._version)

    def sample(self, lanes: "Lanes", u: torch.Tensor) -> list[torch.Tensor]:
        """Each lane's emitter sample (with its shadow ray) and BSDF sample (with the ray it casts)
        from the uniform numbers `u` (5, N), without gradients, under the light `set_light` set:
        the arrays named by `SAMPLED`."""
        with torch.no_grad():
            return list(self._sample(*lanes.geometry, [lanes.chans[:, c].detach() for c in range(brdf.CHANNELS)],
                                     [u[i] for i in range(5)]))

    def bounce_light(self, sampled: list[torch.Tensor], material_fn, env_linear: torch.Tensor,
                     generator: torch.Generator | None = None, views: torch.Tensor | None = None) -> torch.Tensor:
        """Radiance (N, 3) arriving along each lane's BSDF sample where it meets the object: that
        point's direct light, shaded with `material_fn` (world points (M, 3) -> BRDF inputs); zero
        elsewhere. Incoming light for the step, without gradients. `views` (N,): each lane's view (for
        lamps that ride with the camera)."""
        hit = torch.nonzero(sampled[self.SAMPLED.index("hit")] > 0.5)[:, 0]
        li = torch.zeros(len(sampled[0]), 3, device=sampled[0].device)
        if len(hit) > 0:
            first = self.SAMPLED.index("p2x")
            p2, n2, wi2 = (torch.stack(sampled[a:a + 3], -1)[hit] for a in (first, first + 3, first + 6))
            # The bounce light is incoming light for this step, not trained through: its
            # gradients cost a second backward pass for little (benchmarks/results/fit_speed).
            with torch.no_grad():
                li = li.index_put((hit,), self.shade(p2, n2, wi2, material_fn(p2), env_linear, 1, generator,
                                                     views=None if views is None else views[hit]))
        return li

    def radiance(self, lanes: "Lanes", sampled: list[torch.Tensor], env_linear: torch.Tensor,
                 bounce: torch.Tensor | None = None, fixed: torch.Tensor | None = None) -> torch.Tensor:
        """Each lane's outgoing radiance (N, 3) from its samples: the emitter sample and the BSDF
        sample (lit by the envmap where it escapes, by `bounce` where it meets the object),
        differentiable in the lanes' BRDF and, where `fixed` (N,) is not set, in `env_linear`."""
        n = lanes.chans.shape[0]
        li = torch.zeros(n, 3, device=lanes.chans.device) if bounce is None else bounce
        if torch.is_grad_enabled() and env_linear.requires_grad:
            fixed = torch.zeros(n, device=lanes.chans.device) if fixed is None else fixed
            flat = torch.cat([lanes.chans, li, *self._light_lanes(env_linear, sampled, fixed)], 1).reshape(-1)
            rgb = self._shade(*lanes.geometry, flat, list(sampled))
        else:  # the light set for sampling lights the lanes in the kernel (no gradient to add up)
            rgb = self._shade_lit(*lanes.geometry, torch.cat([lanes.chans, li], 1).reshape(-1), list(sampled))
        return torch.stack(rgb, -1)

    def lamp_views(self, pool, idx: torch.Tensor) -> torch.Tensor | None:
        """The views of a pixel pool's hits `idx` (`data.pixels.PixelPool.views_of`) that `shade`
        takes for the lamps; None without lamps (nothing to look up)."""
        return None if self.lamps is None else pool.views_of(idx)

    def lamp_radiance(self, position: torch.Tensor, normal: torch.Tensor, wi: torch.Tensor, material: dict,
                      fixed_light: torch.Tensor | None = None, views: torch.Tensor | None = None) -> torch.Tensor:
        """Radiance (N, 3) towards `wi` from the point lamps (`self.lamps`), with their shadows:
        differentiable in the material and, except at points where `fixed_light` (N,) is set, in
        the lamps' positions and intensities. `views` (N,): the view each point is seen in (lamps
        that ride with the camera stand at that view's camera). Zero without lamps."""
        n = position.shape[0]
        total = torch.zeros(n, 3, device=position.device)
        if self.lamps is None or n == 0:
            return total
        lamp_pos, lamp_int = self.lamps(None if views is None else views.to(position.device))
        lanes = self.lanes(position, normal, wi, material)
        for k in range(lamp_pos.shape[0]):
            lp, li = lamp_pos[k].expand(n, 3), lamp_int[k].expand(n, 3)
            if fixed_light is not None:
                keep = fixed_light.bool()[:, None]
                lp, li = torch.where(keep, lp.detach(), lp), torch.where(keep, li.detach(), li)
            to_lamp = lp - position
            dist2 = (to_lamp * to_lamp).sum(-1, keepdim=True).clamp_min(1e-12)
            with torch.no_grad():
                free = self._lamp_visible(*(t[:, c].contiguous() for t in (position, normal, lp.detach())
                                            for c in range(3)))
            arriving = li / dist2 * free[:, None]
            flat = torch.cat([lanes.chans, to_lamp * torch.rsqrt(dist2), arriving], 1).reshape(-1)
            total = total + torch.stack(self._lamp_shade(*lanes.geometry, flat), -1)
        return total

    def shade(self, hits_position, hits_normal, hits_wi, material: dict,
              env_linear: torch.Tensor, spp: int, generator: torch.Generator | None = None,
              reduce: bool = True, material_fn=None, groups: int = 1,
              fixed_light: torch.Tensor | None = None, views: torch.Tensor | None = None) -> torch.Tensor:
        """Outgoing radiance (N, 3) towards `wi` at N points, averaged over `spp` sample pairs
        (or every sample, (N, spp, 3), when reduce=False).

        `material` holds the BRDF inputs of the N points (`vq_mitsuba.brdf`: basecolor (N, 3), metallic
        (N,), roughness (N,)). With `material_fn` (world points (M, 3) -> such a dict), BSDF
        samples that hit the object are lit by that point's direct radiance (one bounce): where
        they go is found by the same rays that shading traces.
        `groups` independent stratified sample sets per point (see `stratified_samples`).

        The material's inputs and env_linear (H, W, 3) may carry torch gradients; the result is
        differentiable with respect to all of them, except that points where `fixed_light` (N,) is
        true pass no gradient to the envmap (several materials are shaded in one call, some of them
        lit by a light they do not train). The bounce light
        carries no gradient: neither into `material_fn` nor into the envmap through it.
        `views` (N,): the view each point is seen in, for lamps that ride with the camera.
        """
        n = hits_position.shape[0]
        rep = lambda t: t.repeat_interleave(spp, dim=0).contiguous()  # noqa: E731
        lanes = self.lanes(rep(hits_position), rep(hits_normal), rep(hits_wi),
                           {i.name: rep(material[i.name]) for i in brdf.INPUTS})
        fixed = None if fixed_light is None else rep(fixed_light.float())
        self.set_light(env_linear)
        sampled = self.sample(lanes, stratified_samples(n, spp, groups, generator, lanes.geometry[0].device))
        bounce = None if material_fn is None else self.bounce_light(
            sampled, material_fn, env_linear, generator, None if views is None else rep(views))
        samples = self.radiance(lanes, sampled, env_linear, bounce, fixed).view(n, spp, 3)
        if self.lamps is not None:  # a point lamp's light is one direction: once per point, not per sample
            samples = samples + self.lamp_radiance(hits_position, hits_normal, hits_wi, material, fixed_light,
                                                   views)[:, None]
        return samples.mean(1) if reduce else samples


def scene_for_mesh(mesh, envmap: np.ndarray, env_to_world: np.ndarray) -> ShadingScene:
    """A shading scene of a trimesh mesh (its vertex normals as shading normals) under an envmap."""
    return ShadingScene(mesh.vertices, mesh.faces, envmap, env_to_world, normals=mesh.vertex_normals)
