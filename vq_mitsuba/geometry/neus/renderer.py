"""A NeuS model bound to a capture: its box, training rays, occupancy, volume rendering and mesh
export."""

from __future__ import annotations

import math
import time
from dataclasses import replace

import numpy as np
import torch
import torch.nn.functional as F

from vq_mitsuba.backend import available_memory, sized, torch_device
from vq_mitsuba.config import CPU_NEUS_BATCH, NeuSConfig
from vq_mitsuba.config import check as validate
from vq_mitsuba.data.cameras import camera_rays
from vq_mitsuba.errors import InputError
from vq_mitsuba.geometry.neus.networks import NeuSModel, choose_grid, trilinear
from vq_mitsuba.geometry.neus.framing import bounding_sphere, uses_background_model
from vq_mitsuba.geometry.neus.hull import _hull_box, hull_sdf

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


# Training steps when neus.iterations is 0 (auto): enough for PASSES passes over the training rays,
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
    wanted = math.ceil(PASSES * training_rays / cfg.batch_rays)
    steps = int(min(max(wanted, MIN_STEPS), MAX_STEPS))
    return replace(cfg, iterations=steps), {
        "iterations": steps, "batch_rays": cfg.batch_rays, "training_rays": training_rays,
        "reason": f"{PASSES:g} passes over {training_rays} training rays of {cfg.batch_rays} a step: {wanted} steps, "
                  f"held within {MIN_STEPS}-{MAX_STEPS}"}


def encode_srgb(x: torch.Tensor) -> torch.Tensor:
    x = x.clamp(0.0, 1.0)
    return torch.where(x <= 0.0031308, 12.92 * x, 1.055 * x.clamp(min=1e-8) ** (1 / 2.4) - 0.055)


class NeuS:
    """A NeuS model bound to a capture's cameras, in the normalised box around the visual hull, or
    without masks (`uses_background_model`) in the box around the bounding sphere (`sphere`:
    (centre, radius, what framed it); default `bounding_sphere` of the cameras). `support`: a
    known supporting plane without masks ((unit normal towards the cameras, offset) in the world,
    e.g. `support_from_points`): the foreground is what lies inside the sphere above it, and the
    background model takes the plane and what lies below. `points`: the capture's sparse points
    (N, 3) in the world, which the mesh export's search for a support checks its planes against."""

    def __init__(self, capture, cfg: NeuSConfig, sphere: tuple | None = None, support: tuple | None = None,
                 points: np.ndarray | None = None):
        validate(cfg)
        self.cfg = cfg
        self.device = torch_device()  # the model, its training rays and its grids live there
        self.points = None if points is None else np.asarray(points, np.float64).reshape(-1, 3)
        self.capture = capture
        self.source = capture.source
        self.mask_free = uses_background_model(capture, cfg)
        self.support = None  # the supporting plane the mesh export cut away (without masks)
        self.plane = None  # a known supporting plane in box units: (normal, offset)
        if len(capture.cameras) == 0:
            raise InputError(capture.source, "the capture has no images")
        if not capture.has_alpha and not self.mask_free:
            raise InputError(capture.source, "neus.background is masks, but the images have no alpha channel and "
                                             "there is no mask folder (give RGBA PNG/EXR images, masks/ for COLMAP or "
                                             "mask/ for NeuS/IDR, --background-color R,G,B for a plain backdrop, or "
                                             "leave neus.background at auto to reconstruct without masks)")
        alpha = torch.from_numpy(np.ascontiguousarray(capture.alpha))
        if not self.mask_free and float(alpha.max()) <= cfg.hull_threshold:
            raise InputError(capture.source, "the alpha masks are empty: no foreground pixel in any image")
        torch.manual_seed(cfg.seed)
        with _threads(cfg.threads):
            if self.mask_free:
                self._setup_sphere(capture, cfg, sphere or bounding_sphere(capture.cameras), support)
            else:
                self.sphere_source = None
                self._setup(capture, cfg, alpha)
        self.surface_points = self._surface_points(cfg)
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
        if self.mask_free:
            inside = p.norm(dim=1) < 1.0
            if self.plane is not None:
                inside &= p @ self.plane[0] > self.plane[1]
        else:
            res = self.hull_dilated.shape[0]
            inside = (p.abs() < 1.0).all(1)
            cell = ((p + 1.0) * 0.5 * res).long().clamp(0, res - 1)
            inside &= self.hull_dilated[cell[:, 0], cell[:, 1], cell[:, 2]]
        p = p[inside]
        return p if len(p) else None

    def _setup_sphere(self, capture, cfg: NeuSConfig, sphere: tuple, support: tuple | None) -> None:
        """Without masks: the bounding sphere (above a known support) is the unit sphere of the box
        and stands in for the visual hull; the SDF starts as a sphere; every pixel of every view is
        a training ray."""
        t0 = time.perf_counter()
        center, radius, self.sphere_source = sphere
        if not (np.all(np.isfinite(center)) and math.isfinite(radius) and radius > 0):
            raise InputError(capture.source, f"the bounding sphere (centre {center}, radius {radius}, from "
                                             f"{self.sphere_source}) is degenerate: check the camera poses")
        self.center, self.half = np.asarray(center, dtype=np.float64), float(radius)
        res = cfg.hull_resolution
        axis = (torch.arange(res, dtype=torch.float32, device=self.device) + 0.5) / res * 2.0 - 1.0
        grid = torch.stack(torch.meshgrid(axis, axis, axis, indexing="ij"), -1)
        self.hull_sdf = grid.norm(dim=-1) - 1.0
        if support is not None:
            length = float(np.linalg.norm(support[0]))
            n = np.asarray(support[0], np.float64) / length
            c = (float(support[1]) / length - float(n @ self.center)) / self.half
            if c > 0.9:
                raise InputError(capture.source, "the supporting plane passes above the bounding sphere")
            self.plane = (torch.tensor(n, dtype=torch.float32, device=self.device), c)
            self.hull_sdf = torch.maximum(self.hull_sdf, c - grid @ self.plane[0])
        self.hull = self.hull_sdf < 0
        self.hull_dilated = self._dilated(self.hull)
        self.hull_seconds = time.perf_counter() - t0
        self.cfg, self.grid = choose_grid(cfg, capture.cameras, self.center, self.half, masks=False)
        self.model = NeuSModel(self.cfg, None, background=True).to(self.device)
        self.deep = torch.zeros_like(self.hull)
        origins, dirs = zip(*(camera_rays(c) for c in capture.cameras))
        self.rays_o = self.to_box(torch.from_numpy(np.concatenate(origins)).to(self.device))
        self.rays_d = torch.from_numpy(np.concatenate(dirs)).to(self.device)
        images = torch.from_numpy(np.ascontiguousarray(capture.images)).to(self.device)
        self.rays_rgb = encode_srgb(images.reshape(-1, 3))
        self.rays_alpha = None
        self.cfg, self.steps = choose_iterations(self.cfg, len(self.rays_o))

    def _dilated(self, occ: torch.Tensor) -> torch.Tensor:
        """The occupancy grid dilated by two cells (scipy's, on the CPU), on the model's device."""
        from scipy import ndimage

        return torch.from_numpy(ndimage.binary_dilation(occ.cpu().numpy(), iterations=2)).to(self.device)

    def _setup(self, capture, cfg: NeuSConfig, alpha: torch.Tensor) -> None:
        alpha = alpha.to(self.device)
        masks = alpha > cfg.hull_threshold
        # Carve with masks dilated by one pixel, so the hull stays conservative at silhouettes.
        dil = F.max_pool2d(masks.float()[:, None], 3, stride=1, padding=1)[:, 0] > 0.5
        t0 = time.perf_counter()
        center, half, occ = _hull_box(capture.cameras, dil, cfg, capture.source)
        self.center, self.half = np.asarray(center, dtype=np.float64), float(half)
        self.hull = occ
        self.hull_sdf = hull_sdf(occ).to(self.device)
        self.hull_dilated = self._dilated(occ)
        self.hull_seconds = time.perf_counter() - t0
        self.cfg, self.grid = choose_grid(cfg, capture.cameras, self.center, self.half)
        # built on the CPU (the same initial weights on every device), then moved
        self.model = NeuSModel(self.cfg, self.hull_sdf.cpu() if cfg.init == "hull" else None).to(self.device)
        self.deep = torch.zeros_like(occ)  # cells the current SDF marks as well inside the object

        # Training rays: pixels within a few pixels of the foreground, from every view.
        near_fg = F.max_pool2d(masks.float()[:, None], 7, stride=1, padding=3)[:, 0] > 0.5
        origins, dirs = zip(*(camera_rays(c) for c in capture.cameras))
        origins = torch.from_numpy(np.concatenate(origins)).to(self.device)
        dirs = torch.from_numpy(np.concatenate(dirs)).to(self.device)
        sel = near_fg.reshape(-1)
        self.rays_o = self.to_box(origins[sel])
        self.rays_d = dirs[sel]
        rgb = torch.from_numpy(np.ascontiguousarray(capture.images)).to(self.device).reshape(-1, 3)
        self.rays_rgb = encode_srgb(rgb[sel])
        self.rays_alpha = alpha.reshape(-1)[sel].clamp(0, 1)
        self.cfg, self.steps = choose_iterations(self.cfg, len(self.rays_o))

    # ---- coordinates
    def to_box(self, x_world: torch.Tensor) -> torch.Tensor:
        center = torch.from_numpy(self.center).to(x_world.device)
        return ((x_world.double() - center) / self.half).float()

    def to_world(self, p_box: np.ndarray) -> np.ndarray:
        return np.asarray(p_box, dtype=np.float64) * self.half + self.center

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
        cells = self.hull.nonzero()
        p = (cells.float() + 0.5) / res * 2.0 - 1.0
        sdf = torch.cat([self.model.sdf(p[i:i + chunk], level_weights)[0] for i in range(0, len(p), chunk)])
        margin = 3.0 * 2.0 / res
        deep = torch.zeros(res ** 3, dtype=torch.bool, device=self.hull.device)
        flat = (cells[:, 0] * res + cells[:, 1]) * res + cells[:, 2]
        deep[flat] = sdf < -margin
        self.deep = deep.reshape(res, res, res)
        self.codes = self.hull_dilated.to(torch.uint8) + (self.deep & self.hull_dilated).to(torch.uint8)
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
        if self.plane is not None:  # the foreground ends where the ray meets the support
            far = torch.maximum(torch.minimum(far, self._foreground_end(o, d)), near)
        return near, far

    def _foreground_end(self, o: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
        """Where each ray leaves the foreground region (box units): the unit sphere's exit (the
        closest approach for a ray that misses it), or, sooner, a known support's plane."""
        b = (o * d).sum(-1)
        disc = b * b - ((o * o).sum(-1) - 1.0)
        t = torch.where(disc > 0, -b + disc.clamp(min=0.0).sqrt(), (-b).clamp(min=0.0))
        if self.plane is not None:
            n, c = self.plane
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

    @torch.no_grad()
    def render_camera(self, cam, chunk: int = 4096, composite: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """(sRGB colour (H, W, 3) on black, or with `composite` over the background model where there
        is one; opacity (H, W)) of a camera, for novel-view PSNR."""
        o, d = camera_rays(cam)
        o = self.to_box(torch.from_numpy(o).to(self.device))
        d = torch.from_numpy(d).to(self.device)
        lw = [1.0] * self.cfg.levels
        rgb, acc = [], []
        for i in range(0, len(o), chunk):
            r = self.render(o[i:i + chunk], d[i:i + chunk], lw, self.cfg.n_samples, False, False)
            rgb.append(r["rgb"] if composite else r.get("rgb_fg", r["rgb"]))
            acc.append(r["acc"].detach())
        return (torch.cat(rgb).reshape(cam.height, cam.width, 3).cpu().numpy(),
                torch.cat(acc).reshape(cam.height, cam.width).cpu().numpy())

    # ---- mesh
    @torch.no_grad()
    def sdf_volume(self, res: int, chunk: int = 131072) -> np.ndarray:
        """SDF on a res^3 grid spanning [-1, 1]^3 (box units), limited to the visual hull."""
        axis = torch.linspace(-1.0, 1.0, res, device=self.device)
        hull_res = self.cfg.hull_resolution
        lw = [1.0] * self.cfg.levels
        vol = torch.empty(res, res, res, device=self.device)
        # Outside the (dilated) hull the SDF is the hull's own distance; inside, the network's,
        # never below the hull distance minus a tolerance (the visual-hull constraint).
        tol = 2.0 * 2.0 / hull_res
        for i in range(res):
            p = torch.stack(torch.meshgrid(axis[i:i + 1], axis, axis, indexing="ij"), -1).reshape(-1, 3)
            hs = trilinear(self.hull_sdf.reshape(-1, 1), hull_res, p)[:, 0]
            inside = self._lookup(self.hull_dilated, p)
            s = hs.clone()
            if bool(inside.any()):
                q = p[inside]
                s[inside] = torch.cat([self.model.sdf(q[j:j + chunk], lw)[0] for j in range(0, len(q), chunk)])
                s = torch.maximum(s, hs - tol)
            vol[i] = s.view(res, res)
        return vol.cpu().numpy()

    def _without_support(self, vol: np.ndarray, mesh):
        """The mesh (box units) cut above a supporting plane, the known one or the one the mesh
        shows (`support_plane`): the volume below the plane plus two grid cells is made empty and
        the surface extracted again. Sets self.support to the plane in world units ({normal,
        point, from}) or None."""
        from vq_mitsuba.geometry.mesh import marching_cubes, support_plane

        res = vol.shape[0]
        cell = 2.0 / (res - 1)
        if self.plane is not None:
            plane = (self.plane[0].cpu().numpy().astype(np.float64), self.plane[1])
        else:
            views = self.to_box(torch.from_numpy(np.array([c.origin for c in self.capture.cameras]))).numpy()
            points = None if self.points is None else self.to_box(torch.from_numpy(self.points)).numpy()
            plane = support_plane(mesh, views, radius=1.0, tol=1.5 * cell, seed=self.cfg.seed, points=points)
        if plane is None:
            return mesh
        n, c = plane
        axis = np.linspace(-1.0, 1.0, res)
        x, y, z = np.meshgrid(axis, axis, axis, indexing="ij")
        above = (c + 2.0 * cell) - (n[0] * x + n[1] * y + n[2] * z)  # positive (empty) below the cut
        try:
            cut = marching_cubes(np.maximum(vol, above.astype(np.float32)), (-1.0, -1.0, -1.0), (1.0, 1.0, 1.0))
        except ValueError:  # nothing stands on the plane: keep the surface as it is
            return mesh
        self.support = {"normal": [float(v) for v in n], "point": self.to_world(n * c).tolist(),
                        "from": "sparse points" if self.plane is not None else "mesh"}
        return cut

    def extract_mesh(self, res: int | None = None, clean: bool = True):
        from vq_mitsuba.geometry.mesh import clean_mesh, marching_cubes, smooth_vertex_normals

        res = res or self.cfg.mesh_resolution
        vol = self.sdf_volume(res)
        try:
            mesh = marching_cubes(vol, (-1.0, -1.0, -1.0), (1.0, 1.0, 1.0))
            self.support = None
            if self.mask_free and clean:
                mesh = self._without_support(vol, mesh)
        except ValueError as exc:
            raise InputError(self.source, f"NeuS produced no surface ({exc}); check the masks and cameras") from exc
        mesh.vertices = self.to_world(mesh.vertices)
        if clean:
            c = self.cfg
            # without masks only the largest piece is the object (the rest: background the SDF took)
            mesh = clean_mesh(mesh, c.min_component, c.keep_largest or self.mask_free, c.smooth_iterations,
                              c.max_faces)
            if c.normal_smoothing > 0:
                mesh = smooth_vertex_normals(mesh, c.normal_smoothing, c.normal_smoothing_angle)
        return mesh
