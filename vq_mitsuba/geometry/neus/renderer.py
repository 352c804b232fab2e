"""The NeuS model: its networks in the normalised box, the occupancy that bounds each ray's samples,
and volume rendering of rays given in box units. It takes rays, not a capture: `rays.neus_for`
frames a capture's views into a `Box` and its `TrainingRays`, and `mesh_export` extracts the surface."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import torch
import torch.nn.functional as F

from vq_mitsuba.backend import available_memory, sized, torch_device
from vq_mitsuba.config import CPU_NEUS_BATCH, NeuSConfig
from vq_mitsuba.errors import InputError
from vq_mitsuba.geometry.neus.networks import NeuSModel

BACKGROUND_SAMPLES = 16  # samples per ray of the background model (without masks)
COLOR_MIN_WEIGHT = 1e-3  # samples of smaller compositing weight are shaded black (the colour network skips them)


class _threads:
    """Use n torch CPU threads inside the block (n <= 0: unchanged), then restore the previous count.
    On cores shared with other work one thread can be faster than several (`neus.threads` 1)."""

    def __init__(self, n: int):
        self.n = n

    def __enter__(self):
        self.old = torch.get_num_threads()
        if self.n > 0:
            torch.set_num_threads(self.n)

    def __exit__(self, *exc):
        torch.set_num_threads(self.old)
        return False


# Training steps when neus.iterations and neus.time_limit_s are 0: enough for PASSES passes over the training rays,
# at least MIN_STEPS and at most MAX_STEPS. On DTU's photos (2-3.4 M rays at --downscale 4) 8000 steps
# raised NeuS's own held-out renders 0.6-0.7 dB over 4000, and 11000 another 0.5-0.6 dB, each in
# about the time the fewer steps took before the step got faster; on tabletop (0.57 M rays, 3.6
# passes at 4000) 8000 steps did not improve the mesh (benchmarks/results/neus_step/).
PASSES, MIN_STEPS, MAX_STEPS = 2.0, 4000, 11000


# Memory a NeuS step holds per sample point (grid features, both MLPs' activations and the eikonal
# term's second pass), measured on the CPU at the default widths: peak RSS 3.4 GB at 512 x 2000
# samples, 10.5 GB at 512 x 8000, against 0.64 GB at 512 x 24.
STEP_BYTES_PER_SAMPLE = 2700


def check_step_memory(cfg: NeuSConfig, available: int) -> None:
    """Refuse, before training, settings whose step would not fit in `available` bytes."""
    need = cfg.batch_rays * cfg.n_samples * STEP_BYTES_PER_SAMPLE * max(1.0, cfg.hidden / 64)
    if available and need > available:
        raise InputError(None, f"neus.batch_rays {cfg.batch_rays} x neus.n_samples {cfg.n_samples} samples a step "
                               f"need about {need / 2 ** 30:.1f} GiB, and {available / 2 ** 30:.1f} GiB are available: "
                               "lower neus.n_samples or neus.batch_rays")


def choose_iterations(cfg: NeuSConfig, training_rays: int) -> tuple[NeuSConfig, dict]:
    """The config with neus.batch_rays (`backend.sized`) and neus.iterations decided (when 0), and
    what decided the steps; settings whose step would not fit in memory are refused."""
    cfg = replace(cfg, batch_rays=sized(cfg.batch_rays, CPU_NEUS_BATCH))
    check_step_memory(cfg, available_memory())
    if cfg.iterations:
        return cfg, {"iterations": cfg.iterations, "batch_rays": cfg.batch_rays, "reason": "neus.iterations given"}
    if cfg.time_limit_s > 0:
        return cfg, {"iterations": 0, "batch_rays": cfg.batch_rays, "training_rays": training_rays,
                     "reason": f"no step limit: {cfg.time_limit_s:g} s of training or the plateau of the held-aside "
                               "rays, whichever first"}
    wanted = math.ceil(PASSES * training_rays / cfg.batch_rays)
    steps = int(min(max(wanted, MIN_STEPS), MAX_STEPS))
    return replace(cfg, iterations=steps), {
        "iterations": steps, "batch_rays": cfg.batch_rays, "training_rays": training_rays,
        "reason": f"{PASSES:g} passes over {training_rays} training rays of {cfg.batch_rays} a step: {wanted} steps, "
                  f"held within {MIN_STEPS}-{MAX_STEPS}"}


def encode_srgb(x: torch.Tensor) -> torch.Tensor:
    x = x.clamp(0.0, 1.0)
    return torch.where(x <= 0.0031308, 12.92 * x, 1.055 * x.clamp(min=1e-8) ** (1 / 2.4) - 0.055)


@dataclass
class Box:
    """Where NeuS works: the normalised box [-1, 1]^3 around the visual hull (with masks) or around the
    bounding sphere, its unit sphere (without masks: `mask_free`), and its occupancy grids at
    neus.hull_resolution on the model's device."""

    center: np.ndarray  # the box's centre in the world
    half: float  # its half-size in world units
    hull: torch.Tensor  # (R, R, R) bool: the visual hull (without masks the sphere above the support)
    hull_sdf: torch.Tensor  # (R, R, R) its smoothed signed distance, box units
    hull_dilated: torch.Tensor  # (R, R, R) bool: the hull dilated by two cells
    mask_free: bool  # trained without masks: a background model takes what lies outside the sphere
    plane: tuple | None = None  # a known supporting plane in box units: (unit normal tensor, offset)
    sphere_source: str | None = None  # what framed the bounding sphere (without masks)
    seconds: float = 0.0  # the time its hull took

    def to_box(self, x_world: torch.Tensor) -> torch.Tensor:
        center = torch.from_numpy(self.center).to(x_world.device)
        return ((x_world.double() - center) / self.half).float()

    def to_world(self, p_box: np.ndarray) -> np.ndarray:
        return np.asarray(p_box, dtype=np.float64) * self.half + self.center


@dataclass
class TrainingRays:
    """The rays a step draws from, on the model's device: origins in box units, unit directions,
    sRGB target colours and, with masks, each ray's alpha (None without masks)."""

    origins: torch.Tensor  # (N, 3)
    dirs: torch.Tensor  # (N, 3)
    rgb: torch.Tensor  # (N, 3)
    alpha: torch.Tensor | None  # (N,)


class NeuS:
    """The NeuS model in a `Box` (`rays.neus_for` builds one from a capture's views): its networks
    (with a background model when the box is `mask_free`), trained on `rays`. `grid`: how its feature
    grid was sized (for geometry.json); `views`: the cameras' centres (N, 3) in the world, which the
    mesh export's search for a support looks from; `points`: sparse points (N, 3) in the world, for
    the SDF-is-zero term and that search; `source`: the capture file, for messages."""

    def __init__(self, cfg: NeuSConfig, box: Box, rays: TrainingRays, grid: dict | None = None,
                 views: np.ndarray | None = None, points: np.ndarray | None = None, source=None):
        self.cfg, self.grid, self.box, self.source = cfg, grid, box, source
        self.device = torch_device()  # the model, its training rays and its grids live there
        self.points = None if points is None else np.asarray(points, np.float64).reshape(-1, 3)
        self.views = np.zeros((0, 3)) if views is None else np.asarray(views, np.float64).reshape(-1, 3)
        torch.manual_seed(cfg.seed)
        # built on the CPU (the same initial weights on every device), then moved
        init = self.box.hull_sdf.cpu() if not self.box.mask_free and cfg.init == "hull" else None
        self.model = NeuSModel(cfg, init, background=self.box.mask_free).to(self.device)
        self.deep = torch.zeros_like(self.box.hull)  # cells the current SDF marks as well inside the object
        self.rays_o, self.rays_d, self.rays_rgb, self.rays_alpha = rays.origins, rays.dirs, rays.rgb, rays.alpha
        self.cfg, self.steps = choose_iterations(cfg, len(self.rays_o))
        self.surface_points = self._surface_points(self.cfg)
        # the training step's fixed-shape form compiled (`training_step` under `vq_mitsuba.compiled`),
        # or None: every step runs `_foreground` eagerly (NeuSTraining decides)
        self.compiled_step = None

    def _surface_points(self, cfg: NeuSConfig) -> torch.Tensor | None:
        """The sparse points the SDF-is-zero term uses (neus.w_points), in box units on the device:
        those inside the box and, with masks, inside the dilated visual hull; without masks those
        inside the unit sphere and above a known support. None without points or with the term off."""
        if self.points is None or len(self.points) == 0 or cfg.w_points <= 0:
            return None
        p = self.to_box(torch.from_numpy(self.points)).to(self.device)
        if self.box.mask_free:
            inside = p.norm(dim=1) < 1.0
            if self.box.plane is not None:
                inside &= p @ self.box.plane[0] > self.box.plane[1]
        else:
            res = self.box.hull_dilated.shape[0]
            inside = (p.abs() < 1.0).all(1)
            cell = ((p + 1.0) * 0.5 * res).long().clamp(0, res - 1)
            inside &= self.box.hull_dilated[cell[:, 0], cell[:, 1], cell[:, 2]]
        p = p[inside]
        return p if len(p) else None

    # ---- coordinates
    def to_box(self, x_world: torch.Tensor) -> torch.Tensor:
        return self.box.to_box(x_world)

    def to_world(self, p_box: np.ndarray) -> np.ndarray:
        return self.box.to_world(p_box)

    # ---- schedule
    def level_weights(self, frac: float) -> list[float]:
        """Grid level weights at training progress frac in [0, 1] (coarse-to-fine fade-in)."""
        levels = self.cfg.levels
        span = self.cfg.coarse_to_fine
        if span <= 0 or levels == 1:
            return [1.0] * levels
        progress = frac / span * (levels - 1)  # level l fully on once progress >= l
        return [float(np.clip(progress - (l - 1), 0.0, 1.0)) if l > 0 else 1.0 for l in range(levels)]

    # ---- occupancy
    @torch.no_grad()
    def refresh_occupancy(self, level_weights, chunk: int = 65536) -> None:
        """Mark hull cells whose SDF is below -margin as deep inside (ray intervals end there)."""
        res = self.cfg.hull_resolution
        cells = self.box.hull.nonzero()
        p = (cells.float() + 0.5) / res * 2.0 - 1.0
        sdf = torch.cat([self.model.sdf(p[i:i + chunk], level_weights)[0] for i in range(0, len(p), chunk)])
        margin = 3.0 * 2.0 / res
        deep = torch.zeros(res ** 3, dtype=torch.bool, device=self.box.hull.device)
        flat = (cells[:, 0] * res + cells[:, 1]) * res + cells[:, 2]
        deep[flat] = sdf < -margin
        self.deep = deep.reshape(res, res, res)
        self.codes = self.box.hull_dilated.to(torch.uint8) + (self.deep & self.box.hull_dilated).to(torch.uint8)
        # Each batch's ray intervals are marched when drawn: caching them for every training ray
        # costs minutes and gigabytes per refresh on a capture of many large photos.

    def _lookup(self, grid: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
        res = grid.shape[0]
        i = ((p + 1.0) * 0.5 * res).floor().long()
        ok = ((i >= 0) & (i < res)).all(-1)
        i = i.clamp(0, res - 1)
        return grid[i[..., 0], i[..., 1], i[..., 2]] & ok

    def _codes(self, p: torch.Tensor) -> torch.Tensor:
        """Occupancy code of the cell holding each point (inside the box): 0 empty, 1 hull, 2 deep inside."""
        res = self.codes.shape[0]
        i = ((p + 1.0) * (0.5 * res)).to(torch.int32).clamp_(0, res - 1)
        flat = (i[..., 0] * res + i[..., 1]) * res + i[..., 2]
        return self.codes.view(-1)[flat.long()]

    def intervals(self, o: torch.Tensor, d: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Per ray (t_near, t_far) in box units: entry into the dilated hull to just past the first
        deep-inside cell (or the hull exit); t_near == t_far for rays that miss the hull."""
        inv = 1.0 / torch.where(d.abs() < 1e-9, torch.full_like(d, 1e-9), d)
        t1, t2 = (-1.0 - o) * inv, (1.0 - o) * inv
        t_in = torch.minimum(t1, t2).amax(-1).clamp(min=0.0)
        t_out = torch.maximum(t1, t2).amin(-1)
        hit = t_out > t_in
        if not bool(hit.all()):  # march only the rays that cross the box (without masks: often half)
            near, far = t_in.clone(), t_in.clone()
            if bool(hit.any()):
                near[hit], far[hit] = self.intervals(o[hit], d[hit])
            return near, far
        k = self.cfg.march_steps
        steps = (torch.arange(k, dtype=torch.float32, device=o.device) + 0.5) / k
        t = t_in[:, None] + (t_out - t_in).clamp(min=0)[:, None] * steps
        pts = o[:, None] + d[:, None] * t[..., None]
        code = self._codes(pts) * hit[:, None]
        occ = code > 0
        deep = code > 1
        any_occ = occ.any(-1)
        idx = torch.arange(k, device=o.device).expand_as(occ)
        first = torch.where(occ, idx, k).amin(-1).clamp(max=k - 1)
        last = torch.where(occ, idx, -1).amax(-1).clamp(min=0)
        first_deep = torch.where(deep, idx, k).amin(-1)
        end = torch.where(first_deep < k, first_deep, last)
        dt = (t_out - t_in).clamp(min=0) / k
        near = t_in + first * dt - dt
        far = t_in + (end + 1) * dt + dt
        near = torch.where(any_occ, near.clamp(min=0), t_in)
        far = torch.where(any_occ, far, near)
        if self.box.plane is not None:  # the foreground ends where the ray meets the support
            far = torch.maximum(torch.minimum(far, self._foreground_end(o, d)), near)
        return near, far

    def _foreground_end(self, o: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
        """Where each ray leaves the foreground region (box units): the unit sphere's exit (the
        closest approach for a ray that misses it), or, sooner, a known support's plane."""
        b = (o * d).sum(-1)
        disc = b * b - ((o * o).sum(-1) - 1.0)
        t = torch.where(disc > 0, -b + disc.clamp(min=0.0).sqrt(), (-b).clamp(min=0.0))
        if self.box.plane is not None:
            n, c = self.box.plane
            nd = d @ n
            t_plane = (c - o @ n) / torch.where(nd.abs() < 1e-9, torch.full_like(nd, -1e-9), nd)
            t = torch.where((nd < 0) & (t_plane > 0) & (t_plane < t), t_plane, t)
        return t.clamp(min=1e-3)

    # ---- rendering
    def render(self, o, d, level_weights, n_samples: int, perturb: bool, create_graph: bool,
               cos_anneal: float = 1.0, near=None, far=None) -> dict:
        """Rays (box units) through the SDF: colour `rgb`, foreground opacity `acc`, the eikonal
        term and (without create_graph) depth and normal. With a background model, `rgb` is the
        foreground composited over the background and `rgb_fg` the foreground alone."""
        out = self._foreground(o, d, level_weights, n_samples, perturb, create_graph, cos_anneal, near, far)
        if self.model.background is not None:
            out["rgb_fg"] = out["rgb"]
            out["rgb"] = out["rgb"] + (1.0 - out["acc"])[:, None] * self._background(o, d, perturb)
        return out

    def _background(self, o: torch.Tensor, d: torch.Tensor, perturb: bool) -> torch.Tensor:
        """Colour behind the unit sphere along each ray (NeRF++): samples from the sphere's exit (the
        closest approach for a ray that misses it, or a known support's plane) to far away, uniform
        in inverse distance. A point inside the sphere (on the support) is encoded as (x, 1)."""
        n = BACKGROUND_SAMPLES
        t0 = self._foreground_end(o, d)
        u = torch.rand(len(o), n, device=o.device) if perturb else torch.full((len(o), n), 0.5, device=o.device)
        # 1 (the exit) .. 1e-3
        inv = 1.0 - (torch.arange(n, dtype=torch.float32, device=o.device) + u) / n * (1.0 - 1e-3)
        t = t0[:, None] / inv  # increasing
        pts = o[:, None] + d[:, None] * t[..., None]
        r = pts.norm(dim=-1, keepdim=True).clamp(min=1.0)
        x4 = torch.cat([pts / r, 1.0 / r], -1).reshape(-1, 4)
        sigma, color = self.model.background(x4, d[:, None].expand(-1, n, 3).reshape(-1, 3))
        dists = torch.cat([t[:, 1:] - t[:, :-1], t.new_full((len(o), 1), 1e10)], 1)
        alpha = 1.0 - torch.exp(-sigma.view(-1, n) * dists)
        trans = torch.cumprod(torch.cat([alpha.new_ones(len(o), 1), 1.0 - alpha + 1e-7], 1), 1)[:, :-1]
        return ((alpha * trans)[..., None] * color.view(-1, n, 3)).sum(1)

    def _foreground(self, o, d, level_weights, n_samples: int, perturb: bool, create_graph: bool,
                    cos_anneal: float = 1.0, near=None, far=None) -> dict:
        if near is None or far is None:
            near, far = self.intervals(o, d)
        b = len(o)
        jitter = (torch.rand(b, n_samples, device=o.device) if perturb
                  else torch.full((b, n_samples), 0.5, device=o.device))
        lw = torch.as_tensor(level_weights, dtype=torch.float32, device=o.device)
        if create_graph and self.compiled_step is not None:  # a training step of fixed shapes
            rgb, acc, eikonal = self.compiled_step(o, d, near, far, jitter, lw, cos_anneal)
            return {"rgb": rgb, "acc": acc, "eikonal": eikonal}
        valid = far > near + 1e-6
        out = {"rgb": o.new_zeros(b, 3), "acc": o.new_zeros(b), "eikonal": o.new_zeros(()),
               "depth": o.new_zeros(b), "normal": o.new_zeros(b, 3)}
        if not bool(valid.any()):
            return out
        r = self._samples(o[valid], d[valid], near[valid], far[valid], jitter[valid], lw, cos_anneal, create_graph)
        out["eikonal"] = r["eikonal"]
        for key in ("rgb", "acc") if create_graph else ("rgb", "acc", "depth", "normal"):
            full = torch.zeros_like(out[key])
            full[valid] = r[key]
            out[key] = full
        return out

    def training_step(self, o, d, near, far, jitter, lw, cos_anneal: float = 1.0):
        """(colour, opacity, eikonal term) of a training batch, every ray kept (fixed shapes but
        the colour network's samples, no host reads: the form `torch.compile` fuses): a ray that
        misses the hull weighs nothing and its samples stay out of the eikonal mean; the same
        values as `_foreground`'s."""
        valid = (far > near + 1e-6).to(o.dtype)
        r = self._samples(o, d, near, far, jitter, lw, cos_anneal, True, valid)
        return r["rgb"], r["acc"], r["eikonal"]

    def _samples(self, o, d, near, far, jitter, lw, cos_anneal, create_graph: bool, valid=None) -> dict:
        """Stratified samples (jitter (m, n) in [0, 1)) of each ray's interval through the SDF and
        colour networks, composited: rgb, acc, eikonal and, without create_graph, depth and normal.
        `valid` (m,) 0 / 1: rays of weight 0 and out of the eikonal mean (fixed shapes); None: every
        ray counts."""
        m, n_samples = jitter.shape
        steps = (torch.arange(n_samples, dtype=torch.float32, device=o.device) + jitter) / n_samples
        z = near[:, None] + (far - near)[:, None] * steps
        dists = ((far - near) / n_samples)[:, None].expand(m, n_samples)
        pts = (o[:, None] + d[:, None] * z[..., None]).reshape(-1, 3)
        sdf, feat, grad = self.model.sdf_grad(pts, lw, create_graph)
        sdf = sdf.view(m, n_samples)
        g = grad.view(m, n_samples, 3)
        true_cos = (d[:, None] * g).sum(-1)
        iter_cos = -(F.relu(-true_cos * 0.5 + 0.5) * (1.0 - cos_anneal) + F.relu(-true_cos) * cos_anneal)
        inv_s = self.model.inv_s()
        prev_cdf = torch.sigmoid((sdf - iter_cos * dists * 0.5) * inv_s)
        next_cdf = torch.sigmoid((sdf + iter_cos * dists * 0.5) * inv_s)
        alpha = ((prev_cdf - next_cdf + 1e-5) / (prev_cdf + 1e-5)).clamp(0.0, 1.0)
        trans = torch.cumprod(torch.cat([alpha.new_ones(m, 1), 1.0 - alpha + 1e-7], 1), 1)[:, :-1]
        w = alpha * trans
        if valid is not None:
            w = w * valid[:, None]
        normal = F.normalize(g, dim=-1)
        view = d[:, None].expand(m, n_samples, 3).reshape(-1, 3)
        color = self._sample_colors(w, feat, normal.reshape(-1, 3), view)
        eik = (grad.norm(dim=-1) - 1.0) ** 2
        if valid is None:
            eikonal = eik.mean()
        else:
            eikonal = (eik.view(m, n_samples) * valid[:, None]).sum() / (valid.sum() * n_samples).clamp(min=1.0)
        out = {"rgb": (w[..., None] * color).sum(1), "acc": w.sum(1), "eikonal": eikonal}
        if not create_graph:
            out["depth"] = (w * z).sum(1)
            out["normal"] = (w[..., None] * normal).sum(1)
        return out

    def _sample_colors(self, w: torch.Tensor, feat: torch.Tensor, normal: torch.Tensor,
                       view: torch.Tensor) -> torch.Tensor:
        """The colour network at the samples (m, n) whose compositing weight exceeds COLOR_MIN_WEIGHT
        (black elsewhere): (m, n, 3)."""
        keep = (w.detach() > COLOR_MIN_WEIGHT).reshape(-1).nonzero()[:, 0]
        color = self.model.color(feat[keep], normal[keep], view[keep])
        return w.new_zeros(w.numel(), 3).index_copy(0, keep, color).view(*w.shape, 3)
