"""The per-texel baseline: principled textures on a UV-unwrapped mesh, fitted with Mitsuba's own
differentiable renderer.

This is what a Mitsuba user would set up today for the same problem: the known mesh is unwrapped
with xatlas, its `principled` BSDF reads base_color, metallic and roughness from `bitmap`
textures (one value per texel, no neural field, no codebook), the lighting is a learnable
lat-long `envmap` (log radiance, or the capture's known envmap, fixed), and `mi.ad.Adam` fits
them through the `prb` integrator (max_depth 3: direct light plus one bounce, as our renderer)
from an L2 loss on gamma-encoded colour (as `losses.reconstruction_l2`). Each step renders one
(or a few) random whole training views; references are premultiplied by coverage over black,
and so are the renders (emitters hidden).

`fit_texel` writes snapshots (`snapshot_XXXXs.npz`) at given fit seconds; `TexelPredictor`
reads one back and renders the maps `evaluate.evaluate_predictor` scores (rgb with Mitsuba's
`path` integrator, material maps from the textures at the primary hits).
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from vq_mitsuba import brdf
from vq_mitsuba.brdf import INPUTS, NAMES
from vq_mitsuba.data.cameras import Camera
from vq_mitsuba.config import setting
from vq_mitsuba.errors import InputError
from vq_mitsuba.geometry.uv import uv_unwrap
from vq_mitsuba.run.loop import Budget, Loop, Progress
from vq_mitsuba.run.run_dir import write_atomic, write_json

SNAPSHOT_FORMAT = 1
TEXEL_SUMMARY = "texel_fit.json"  # the baseline's summary, beside its snapshots


@dataclass
class TexelConfig:
    """The per-texel baseline: principled textures on a UV atlas (fit_texel's settings; not part of a run's Config)."""

    resolution: int = setting(256, "texels per side of each material texture", ">0")
    uv_padding: int = setting(2, "texels between charts in the UV atlas")
    envmap_height: int = setting(32, "rows of the learned lat-long envmap (width is twice this)", ">0")
    env_init_scale: float = setting(2.0, "initial radiance as a multiple of the mean foreground pixel value", ">0")
    spp: int = setting(16, "samples per pixel of each training render", ">0")
    max_depth: int = setting(3, "path length of the integrator (3: direct light plus one bounce)", ">0")
    views_per_step: int = setting(1, "random whole training views rendered per Adam step", ">0")
    lr_texture: float = setting(0.05, "Adam learning rate of the texels", ">0")
    lr_envmap: float = setting(0.03, "Adam learning rate of the envmap's log radiance", ">0")
    lr_end_exponential: float = setting(
        0.1, "learning-rate factor reached at the time limit or last step (exponential in the share done)", "(0,1]")
    gamma: float = setting(2.2, "the loss compares x^(1/gamma)", ">0")
    tv_weight: float = setting(1.0, "weight of the mean squared difference of neighbouring texels")
    env_tv_weight: float = setting(1e-4, "weight of the smoothness of the envmap's log radiance")
    init_basecolor: float = setting(0.5, "initial basecolor texels", "[0,1]")
    init_metallic: float = setting(0.1, "initial metallic texels", "[0,1]")
    init_roughness: float = setting(0.5, "initial roughness texels", "[0,1]")
    roughness_min: float = setting(0.02, "roughness texels are clamped to [roughness_min, 1]", "[0,1]")
    iterations: int = setting(0, "stop after this many steps (0: only the time limit)")
    seed: int = setting(0, "seed of the view order and the Monte Carlo samples")


TEXTURES = NAMES


def _floors(cfg: TexelConfig) -> dict[str, float]:
    """Each texture's lowest texel value: its input's range, roughness's raised to `roughness_min`."""
    return {**{i.name: i.low for i in brdf.INPUTS}, brdf.ROUGHNESS: cfg.roughness_min}
_CHANNELS = {i.name: i.channels for i in INPUTS}
_BSDF_KEY = {i.name: i.principled for i in INPUTS}


# --------------------------------------------------------------------------------------------
# Geometry and scene


def _texture_dict(values: np.ndarray) -> dict:
    import mitsuba as mi

    if values.ndim == 2:
        values = values[..., None]
    return {"type": "bitmap", "data": mi.TensorXf(np.ascontiguousarray(values, dtype=np.float32)), "raw": True,
            "filter_type": "bilinear", "wrap_mode": "clamp"}


def _textured_mesh(vertices, faces, normals, uvs, textures: dict[str, np.ndarray]):
    """A Mitsuba mesh with UVs whose principled BSDF reads the three textures: (mesh, {name: texture})."""
    import mitsuba as mi

    texs = {name: mi.load_dict(_texture_dict(textures[name])) for name in TEXTURES}
    bsdf = mi.load_dict({"type": "principled", "specular": 0.5,
                         **{_BSDF_KEY[name]: tex for name, tex in texs.items()}})
    props = mi.Properties()
    props["bsdf"] = bsdf
    mesh = mi.Mesh("texel_mesh", len(vertices), len(faces), props, has_vertex_normals=True,
                   has_vertex_texcoords=True)
    p = mi.traverse(mesh)
    p["vertex_positions"] = mi.Float(np.ascontiguousarray(vertices, dtype=np.float32).ravel())
    p["vertex_normals"] = mi.Float(np.ascontiguousarray(normals, dtype=np.float32).ravel())
    p["vertex_texcoords"] = mi.Float(np.ascontiguousarray(uvs, dtype=np.float32).ravel())
    p["faces"] = mi.UInt32(np.ascontiguousarray(faces, dtype=np.uint32).ravel())
    p.update()
    return mesh, texs


def _sensor_dict(camera: Camera, spp: int, pixel_format: str = "rgb") -> dict:
    d = camera.to_mitsuba_dict(spp)
    d["film"]["pixel_format"] = pixel_format
    return d


def _build_scene(mesh, envmap: np.ndarray, env_to_world: np.ndarray, integrator: str, max_depth: int,
                 camera: Camera, spp: int, hide_emitters: bool = True):
    import mitsuba as mi

    return mi.load_dict({
        "type": "scene",
        "integrator": {"type": integrator, "max_depth": int(max_depth), "hide_emitters": bool(hide_emitters)},
        "mesh": mesh,
        "sensor": _sensor_dict(camera, spp),
        "env": {"type": "envmap", "bitmap": mi.Bitmap(np.ascontiguousarray(envmap, dtype=np.float32)),
                "to_world": mi.ScalarTransform4f(np.asarray(env_to_world, dtype=np.float64).tolist())},
    })


def _set_camera(params, camera: Camera) -> None:
    """Point the scene's one sensor along `camera` (opaque parameters: no kernel recompiles)."""
    import mitsuba as mi

    params["sensor.to_world"] = mi.ScalarTransform4f(np.asarray(camera.to_world, dtype=np.float64).tolist())
    params["sensor.x_fov"] = float(camera.fov_x_deg)
    if abs(camera.focal_y_ratio - 1.0) > 1e-9:
        raise ValueError(f"camera {camera.name}: the per-texel baseline renders with Mitsuba's perspective sensor, "
                         "which has one focal length")
    ox, oy = camera.principal_offset()
    params["sensor.principal_point_offset_x"] = float(ox)
    params["sensor.principal_point_offset_y"] = float(oy)


def _padding_index(height: int, width: int):
    """Flat gather indices (H, W+2, 3) -> (H, W, 3): Mitsuba's envmap keeps wrap-around columns."""
    import mitsuba as mi

    rows = np.arange(height)[:, None]
    cols = (np.arange(width + 2) - 1) % width
    flat = ((rows * width + cols)[..., None] * 3 + np.arange(3)).ravel()
    return mi.UInt32(flat.astype(np.uint32))


def _neighbour_index(res: int, channels: int):
    """Flat index pairs of horizontally and vertically adjacent texels of a (res, res, C) tensor."""
    import mitsuba as mi

    idx = np.arange(res * res * channels).reshape(res, res, channels)
    a = np.concatenate([idx[:, :-1].ravel(), idx[:-1].ravel()])
    b = np.concatenate([idx[:, 1:].ravel(), idx[1:].ravel()])
    return mi.UInt32(a.astype(np.uint32)), mi.UInt32(b.astype(np.uint32))


def _encode_gamma(x, gamma: float):
    """losses.encode_gamma in Dr.Jit."""
    import drjit as dr

    eps = 1e-3
    return dr.power(dr.maximum(x, 0.0) + eps, 1.0 / gamma) - eps ** (1.0 / gamma)


def _mean(x) -> float:
    import drjit as dr

    return float(dr.mean(x, axis=None).array[0])


# --------------------------------------------------------------------------------------------
# Fitting


class TexelScene:
    """A capture's mesh (unwrapped), its textured principled BSDF and the envmap in one Mitsuba
    scene with one sensor, set up for differentiable renders of the training views.

    The optimised values live outside the scene (a dict or an `mi.ad.Adam`): `basecolor` (R, R, 3),
    `metallic`, `roughness` (R, R, 1) and, when the lighting is learned, `log_env` (H, 2H, 3)."""

    def __init__(self, capture, cfg: TexelConfig):
        import mitsuba as mi

        from vq_mitsuba.backend import init_mitsuba

        if capture.mesh is None:
            raise InputError(capture.source, "the per-texel baseline needs known geometry (no mesh in the capture)")
        init_mitsuba()
        self.capture, self.cfg = capture, cfg
        mesh_tm = capture.mesh
        vmap, self.faces, self.uvs = uv_unwrap(mesh_tm.vertices, mesh_tm.faces, cfg.resolution, cfg.uv_padding)
        self.vertices = np.asarray(mesh_tm.vertices, dtype=np.float32)[vmap]
        self.normals = np.asarray(mesh_tm.vertex_normals, dtype=np.float32)[vmap]
        res = self.resolution = int(cfg.resolution)
        floors = _floors(cfg)
        init = {i.name: np.full((res, res, 3) if i.colour else (res, res),
                                max(getattr(cfg, f"init_{i.name}"), floors[i.name]), np.float32) for i in brdf.INPUTS}
        self._init = init
        mesh, _ = _textured_mesh(self.vertices, self.faces, self.normals, self.uvs, init)

        self.learn_env = capture.envmap is None
        fg = capture.alpha >= 0.99
        mean_fg = float(np.mean(capture.images[fg])) if capture.has_alpha and fg.any() \
            else float(np.mean(capture.images))
        self.env_h = h = int(cfg.envmap_height)
        self.env_init = np.full((h, 2 * h, 3), cfg.env_init_scale * max(mean_fg, 1e-3), np.float32) \
            if self.learn_env else np.asarray(capture.envmap, dtype=np.float32)
        self.scene = _build_scene(mesh, self.env_init, capture.envmap_to_world, "prb", cfg.max_depth,
                                  capture.cameras[0], cfg.spp, hide_emitters=capture.has_alpha)
        self.params = mi.traverse(self.scene)
        self.sensor = self.scene.sensors()[0]
        self.keys = {name: f"mesh.bsdf.{_BSDF_KEY[name]}.data" for name in TEXTURES}
        self._pad_idx = _padding_index(h, 2 * h) if self.learn_env else None
        self.refs = [mi.TensorXf(np.ascontiguousarray(img, dtype=np.float32)) for img in capture.images]

    def initial_values(self) -> dict:
        """The starting values (Dr.Jit tensors, not yet differentiable)."""
        import mitsuba as mi

        out = {name: mi.TensorXf(v if v.ndim == 3 else v[..., None]) for name, v in self._init.items()}
        if self.learn_env:
            out["log_env"] = mi.TensorXf(np.log(self.env_init))
        return out

    def apply(self, values) -> None:
        """Put the textures and the envmap of `values` into the scene (their AD graph kept)."""
        import drjit as dr
        import mitsuba as mi

        for name in TEXTURES:
            self.params[self.keys[name]] = values[name]
        if self.learn_env:
            env = dr.exp(values["log_env"])
            self.params["env.data"] = mi.TensorXf(dr.gather(mi.Float, env.array, self._pad_idx),
                                                  (self.env_h, 2 * self.env_h + 2, 3))

    def render(self, view: int, seed: int, seed_grad: int | None = None, spp: int | None = None):
        """Differentiable render of training view `view` with the values last applied: (H, W, 3)."""
        import mitsuba as mi

        _set_camera(self.params, self.capture.cameras[view])
        self.params.update()
        return mi.render(self.scene, self.params, sensor=self.sensor, spp=int(spp or self.cfg.spp), seed=seed,
                         seed_grad=seed + (1 << 30) if seed_grad is None else seed_grad)

    def image_loss(self, image, view: int):
        """L2 of gamma-encoded colour against the reference of `view` (mean over pixels and channels)."""
        import drjit as dr

        g = self.cfg.gamma
        return dr.mean(dr.square(_encode_gamma(image, g) - _encode_gamma(self.refs[view], g)), axis=None)

    def loss(self, values, views, seed: int, seed_grad: int | None = None):
        """Mean image loss over `views`, each rendered with its own seed (seed, seed + 1, ...)."""
        self.apply(values)
        total = 0.0
        for j, v in enumerate(views):
            s = seed + j
            img = self.render(int(v), s, None if seed_grad is None else seed_grad + j)
            total = total + self.image_loss(img, int(v)) / len(views)
        return total

    def arrays(self, values) -> dict[str, np.ndarray]:
        """The snapshot's arrays for `values` (numpy)."""
        out = {i.name: np.array(values[i.name], dtype=np.float32)[..., slice(None) if i.colour else 0]
               for i in INPUTS}
        out["envmap"] = np.exp(np.array(values["log_env"], dtype=np.float32)) if self.learn_env else self.env_init
        out.update(envmap_to_world=np.asarray(self.capture.envmap_to_world, dtype=np.float64),
                   vertices=self.vertices, faces=self.faces.astype(np.int32), uvs=self.uvs, normals=self.normals)
        return out


def _snapshot_path(out_dir: Path, seconds: float) -> Path:
    return out_dir / f"snapshot_{int(round(seconds)):04d}s.npz"


def _write_snapshot(path: Path, arrays: dict, meta: dict) -> None:
    write_atomic(path, lambda tmp: np.savez(tmp, meta=np.array(json.dumps(meta)), **arrays))


def fit_texel(capture_path: str | Path, out_dir: str | Path, cfg: TexelConfig | None = None,
              time_limit_s: float = 60.0, snapshot_s=(), mesh_path: str | Path | None = None) -> dict:
    """Fit per-texel principled textures (and the envmap unless the capture knows it) for
    `time_limit_s` seconds of optimisation (unwrapping and scene setup not counted, nor snapshot
    writes; 0: no limit, cfg.iterations then stops the fit). Writes `out_dir/snapshot_XXXXs.npz`
    at each time in `snapshot_s` and at the end, and `out_dir/texel_fit.json`.

    Returns {"snapshots": [(seconds, iterations, path), ...], "iterations", "seconds",
    "setup_seconds", "iterations_per_s", "loss_first", "loss_last"}."""
    from vq_mitsuba.data.captures import load_capture

    cfg = cfg or TexelConfig()
    if time_limit_s <= 0 and cfg.iterations <= 0:
        raise InputError(None, "fit_texel needs a positive time limit or iteration count")
    t_setup = time.perf_counter()
    fit = _TexelFit(load_capture(capture_path, mesh=mesh_path), Path(out_dir), cfg)
    setup_seconds = time.perf_counter() - t_setup
    loop = Loop("texel fit", Budget(cfg.iterations, time_limit_s), fit.loop_step,
                snapshot=fit.snapshot_at,
                snapshot_times=snapshot_s)
    fit.clock = loop.clock
    result = loop.run()
    elapsed, step = result.seconds, result.steps
    if fit.last_snap_step != step:
        path = str(fit.snapshot(elapsed, elapsed, step))
        fit.snaps = [s for s in fit.snaps if s[2] != path] + [(elapsed, step, path)]
    summary = {"snapshots": fit.snaps, "iterations": step, "seconds": elapsed, "setup_seconds": setup_seconds,
               "iterations_per_s": step / elapsed if elapsed > 0 else math.nan,
               "loss_first": fit.loss_first, "loss_last": fit.loss_ema}
    write_json(fit.out_dir / TEXEL_SUMMARY, summary)
    return summary


class _TexelFit:
    """The per-texel baseline's optimiser and step for the loop skeleton (`vq_mitsuba.run.loop`).
    Its learning rate decays with the share of whichever budget runs out first (it is compared
    with the material fit at equal time)."""

    def __init__(self, capture, out_dir: Path, cfg: TexelConfig):
        import mitsuba as mi

        self.cfg, self.out_dir = cfg, out_dir
        ts = self.ts = TexelScene(capture, cfg)
        out_dir.mkdir(parents=True, exist_ok=True)
        self.rng = np.random.default_rng(cfg.seed)
        self.opt = mi.ad.Adam(lr=cfg.lr_texture, mask_updates=True)
        for name, value in ts.initial_values().items():
            self.opt[name] = value
        self.lrs = {name: cfg.lr_texture for name in TEXTURES}
        if ts.learn_env:
            self.lrs["log_env"] = cfg.lr_envmap
        self.tv_idx = {name: _neighbour_index(ts.resolution, _CHANNELS[name]) for name in TEXTURES} \
            if cfg.tv_weight > 0 else None
        self.env_tv_idx = _neighbour_index_wrapped(ts.env_h) if ts.learn_env and cfg.env_tv_weight > 0 else None
        self.lo = _floors(cfg)
        self.n_views = len(capture.cameras)
        self.per_step = max(1, min(int(cfg.views_per_step), self.n_views))
        self.meta = {"format": SNAPSHOT_FORMAT, "world": capture.world,
                     "capture": str(Path(capture.source).resolve()), "learned_envmap": ts.learn_env,
                     "max_depth": int(cfg.max_depth), "config": asdict(cfg)}
        self.snaps: list[tuple[float, int, str]] = []
        self.last_snap_step = -1
        self.loss_ema, self.loss_first = None, None

    def snapshot(self, label_s: float, elapsed: float, step: int) -> Path:
        path = _snapshot_path(self.out_dir, label_s)
        _write_snapshot(path, self.ts.arrays(self.opt), {**self.meta, "seconds": elapsed, "iterations": step})
        return path

    def snapshot_at(self, p: Progress, label_s: float) -> None:
        """The loop's snapshot at the requested training time `label_s`."""
        self.snaps.append((p.seconds, p.step, str(self.snapshot(label_s, p.seconds, p.step))))
        self.last_snap_step = p.step

    @staticmethod
    def _tv(x, idx):
        import drjit as dr
        import mitsuba as mi

        a, b = idx
        return dr.mean(dr.square(dr.gather(mi.Float, x.array, a) - dr.gather(mi.Float, x.array, b)))

    def loop_step(self, p: Progress) -> dict | None:
        import drjit as dr

        cfg, opt = self.cfg, self.opt
        decay = cfg.lr_end_exponential ** p.share
        opt.set_learning_rate({k: v * decay for k, v in self.lrs.items()})
        views = self.rng.choice(self.n_views, size=self.per_step, replace=False)
        rec = self.ts.loss(opt, views, seed=p.step * self.per_step)
        loss = rec
        if self.tv_idx is not None:
            for name in TEXTURES:
                loss = loss + cfg.tv_weight * self._tv(opt[name], self.tv_idx[name])
        if self.env_tv_idx is not None:
            loss = loss + cfg.env_tv_weight * self._tv(opt["log_env"], self.env_tv_idx)
        dr.backward(loss)
        opt.step()
        for name in TEXTURES:
            opt[name] = dr.clip(opt[name], self.lo[name], brdf.get(name).high)
        rec_value = _mean(rec)
        self.loss_first = rec_value if self.loss_first is None else self.loss_first
        self.loss_ema = rec_value if self.loss_ema is None else 0.95 * self.loss_ema + 0.05 * rec_value
        if (p.step + 1) % 10 == 0:
            return {"loss": f"{self.loss_ema:.4g}", "s": f"{self.clock():.0f}"}
        return None


def _neighbour_index_wrapped(height: int):
    """Neighbour pairs of an (H, 2H, 3) lat-long map; longitude wraps around."""
    import mitsuba as mi

    w = 2 * height
    idx = np.arange(height * w * 3).reshape(height, w, 3)
    a = np.concatenate([idx.ravel(), idx[:-1].ravel()])
    b = np.concatenate([np.roll(idx, -1, axis=1).ravel(), idx[1:].ravel()])
    return mi.UInt32(a.astype(np.uint32)), mi.UInt32(b.astype(np.uint32))


# --------------------------------------------------------------------------------------------
# Prediction


def load_snapshot(path: str | Path) -> tuple[dict[str, np.ndarray], dict]:
    """(arrays, meta) of a snapshot written by fit_texel."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "texel snapshot not found")
    with np.load(path) as data:
        arrays = {k: data[k] for k in data.files if k != "meta"}
        meta = json.loads(str(data["meta"]))
    return arrays, meta


class TexelPredictor:
    """A texel snapshot as `evaluate.evaluate_predictor` expects it (see RunPredictor)."""

    def __init__(self, snapshot_path: str | Path, world: str | None = None, default_spp: int = 256,
                 default_aa: int = 16):
        self.path = Path(snapshot_path)
        self.arrays, self.meta = load_snapshot(self.path)
        self.world = world or self.meta["world"]
        if world is not None and world != self.meta["world"]:
            raise InputError(self.path, f"snapshot was fitted in the {self.meta['world']} world, not {world}")
        self.default_spp = int(default_spp)
        self.default_aa = int(default_aa)
        self.num_materials = None

    def renderer(self, envmap: np.ndarray | None = None) -> "TexelRenderer":
        return TexelRenderer(self.arrays, envmap if envmap is not None else self.arrays["envmap"],
                             int(self.meta.get("max_depth", 3)))

    def fit_summary(self) -> dict:
        return {"iterations": self.meta["iterations"], "seconds": self.meta["seconds"],
                "iterations_per_s": self.meta["iterations"] / max(self.meta["seconds"], 1e-9)}


class TexelRenderer:
    """Renders views of a texel snapshot under its envmap (or another): the dict of
    render.views.Renderer.render."""

    def __init__(self, arrays: dict[str, np.ndarray], envmap: np.ndarray, max_depth: int = 3):
        import mitsuba as mi

        from vq_mitsuba.backend import init_mitsuba

        init_mitsuba()
        self.max_depth = int(max_depth)
        mesh, self.textures = _textured_mesh(arrays["vertices"], arrays["faces"], arrays["normals"], arrays["uvs"],
                                             {name: arrays[name] for name in TEXTURES})
        self._mesh = mesh
        self._env = np.ascontiguousarray(envmap, dtype=np.float32)
        self._env_to_world = arrays["envmap_to_world"]
        self._scenes: dict[tuple[int, int], tuple] = {}  # (width, height) -> (scene, params, sensor)
        self._mi = mi

    def _scene_for(self, camera: Camera):
        key = (camera.width, camera.height)
        if key not in self._scenes:
            scene = _build_scene(self._mesh, self._env, self._env_to_world, "path", self.max_depth, camera, 1)
            self._scenes[key] = (scene, self._mi.traverse(scene), scene.sensors()[0])
        return self._scenes[key]

    def render(self, camera: Camera, spp: int | None = None, aa: int | None = None, seed: int = 0) -> dict:
        """rgb (linear, premultiplied by coverage), alpha, basecolor, metallic, roughness, normal
        (world, facing the camera). Maps average `aa` stratified primary rays per pixel."""
        import drjit as dr
        import mitsuba as mi

        from vq_mitsuba.data.cameras import camera_rays, pixel_jitter

        spp = int(spp or 256)
        aa = int(aa or 16)
        scene, params, sensor = self._scene_for(camera)
        _set_camera(params, camera)
        params.update()
        img = np.array(mi.render(scene, sensor=sensor, spp=spp, seed=seed), dtype=np.float32)
        h, w = camera.height, camera.width
        n = h * w
        rng = np.random.default_rng(seed)
        acc = np.zeros((n, brdf.CHANNELS + 3), np.float64)  # the inputs' channels, then the normal's 3
        hits = np.zeros(n, np.float64)
        for a in range(aa):
            jitter = np.full((n, 2), 0.5) if aa == 1 else pixel_jitter(n, a, aa, rng)
            o, d = camera_rays(camera, jitter)
            with dr.suspend_grad():
                ray = mi.Ray3f(mi.Point3f(*[mi.Float(o[:, i]) for i in range(3)]),
                               mi.Vector3f(*[mi.Float(d[:, i]) for i in range(3)]))
                si = scene.ray_intersect(ray)
                valid = si.is_valid()
                cols = []
                for i in brdf.INPUTS:
                    if i.colour:
                        c = self.textures[i.name].eval(si, valid)
                        cols += [c.x, c.y, c.z]
                    else:
                        cols.append(self.textures[i.name].eval_1(si, valid))
                nrm = si.sh_frame.n
                nrm = dr.select(dr.dot(nrm, -ray.d) < 0, -nrm, nrm)
                cols += [nrm.x, nrm.y, nrm.z]
                cols = [dr.select(valid, c, 0.0) for c in cols]
                dr.eval(valid, *cols)
            acc += np.stack([np.array(c, dtype=np.float64) for c in cols], -1)
            hits += np.array(valid, dtype=np.float64)
        safe = np.maximum(hits, 1.0)[:, None]
        maps = acc / safe
        out, at = {"rgb": img[..., :3], "alpha": (hits / aa).reshape(h, w).astype(np.float32)}, 0
        for i in brdf.INPUTS:
            out[i.name] = maps[:, at:at + i.channels].reshape((h, w, 3) if i.colour else (h, w)).astype(np.float32)
            at += i.channels
        nrm = maps[:, at:at + 3]
        nrm = nrm / np.maximum(np.linalg.norm(nrm, axis=-1, keepdims=True), 1e-8)
        return {**out, "normal": nrm.reshape(h, w, 3).astype(np.float32)}
