"""Views of a fitted scene: novel views, material maps, segmentation and relighting.

Works on a `FittedModel` (`vq_mitsuba.run.run_dir.RunDir.load`); nothing here trains.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from vq_mitsuba.backend import sized
from vq_mitsuba.brdf import INPUTS
from vq_mitsuba.config import CPU_RENDER_CHUNK
from vq_mitsuba.data.cameras import Camera, camera_rays, convert_world, pixel_jitter, world_rotation
from vq_mitsuba.data.envmaps import ENV_PEAK_RANGE
from vq_mitsuba.data.imageio import linear_to_srgb, write_exr, write_png
from vq_mitsuba.data.names import view_names
from vq_mitsuba.errors import InputError, NumericalError
from vq_mitsuba.models.fitted import FittedModel
from vq_mitsuba.models.residual import add_residual
from vq_mitsuba.render.shading import scene_for_mesh

MAX_RAYS = 1 << 20  # primary rays traced at once by Renderer.render (bounds its memory)


def rotate_about_up(env_to_world: np.ndarray, degrees: float) -> np.ndarray:
    """Rotate an envmap about its own up axis (local +Y of Mitsuba's lat-long frame)."""
    a = math.radians(degrees)
    rot = np.eye(4)
    rot[0, 0], rot[0, 2], rot[2, 0], rot[2, 2] = math.cos(a), math.sin(a), -math.sin(a), math.cos(a)
    return np.asarray(env_to_world) @ rot


def own_lighting(envmap: np.ndarray | None, env_rotate_deg: float, exposure_ev: float) -> bool:
    """A render under the run's own light (its envmap as fitted): its residual and its lamps light it."""
    return envmap is None and env_rotate_deg == 0 and exposure_ev == 0


class Renderer:
    """Renders views of a fitted run under its own lighting or another envmap.

    Under the run's own lighting (no envmap, rotation or exposure given), the run's residual
    (`FittedModel.residual`, VQ-NeRF Sec. 4) is added to the radiance of each hit that no edit
    selects; the render then also returns `rgb_physical`, the same image without it. Any other
    lighting gives the physically based render alone, and so do edited parts: an edit changes its
    own material only."""

    def __init__(self, fitted: FittedModel, envmap: np.ndarray | None = None, env_rotate_deg: float = 0.0,
                 exposure_ev: float = 0.0, keep_lamps: bool = False):
        self.fitted = fitted
        env = fitted.envmap if envmap is None else envmap
        peak = float(np.max(env)) * 2.0 ** exposure_ev
        if not ENV_PEAK_RANGE[0] <= peak <= ENV_PEAK_RANGE[1]:
            raise InputError(None, f"the lighting's brightest texel would be {peak:.3g} at exposure {exposure_ev:+g} EV: "
                                   f"outside {ENV_PEAK_RANGE[0]:g}..{ENV_PEAK_RANGE[1]:g}, where the renders could "
                                   "not be finite; choose another --exposure or envmap")
        self.envmap = np.ascontiguousarray(env * (2.0 ** exposure_ev), dtype=np.float32)
        to_world = rotate_about_up(fitted.envmap_to_world, env_rotate_deg)
        self.scene = scene_for_mesh(fitted.mesh, self.envmap, to_world)
        self.env_t = torch.as_tensor(self.envmap, device=fitted.model.center.device)
        own_light = own_lighting(envmap, env_rotate_deg, exposure_ev)
        # the fitted lamps (at this exposure), placed for each view's camera in `render`
        self.lamps = fitted.lamps if own_light or keep_lamps else None
        self.lamp_scale = 2.0 ** exposure_ev
        self.residual = fitted.residual if own_light else None

    @torch.no_grad()
    def render(self, camera: Camera, spp: int | None = None, aa: int | None = None, seed: int = 0,
               relight: Sequence[Renderer] = ()) -> dict[str, np.ndarray]:
        """Images of one view: rgb (linear, HxWx3), alpha, basecolor, metallic, roughness, normal;
        with a discrete branch also material (majority id per pixel), material_share (H, W, M+1)
        and discrete (the discrete branch's maps).

        Each pixel averages `aa` primary rays (stratified over the pixel); each hit is shaded with
        spp/aa light samples. Pixel coverage, not light sampling, dominates the error at edges
        and on small highlights, so aa is high by default.

        `relight`: renderers of the same fitted run under other lighting. Their rgb images come
        back as the list `relit`, each the same image as their own `render` with this seed, but
        the rays are traced and the material field evaluated once for all of them.
        """
        cfg = self.fitted.cfg.render
        spp = spp or cfg.spp
        aa = aa or cfg.aa
        sums = _PixelSums(camera.height * camera.width, self.fitted.discrete, len(relight), self.env_t.device,
                          physical=self._residual() is not None)
        lights = [self, *relight]
        if any(r.fitted is not self.fitted for r in relight):
            raise ValueError("relight renderers must render the same fitted run")
        for light in lights:
            light.scene.lamps = None if light.lamps is None else \
                light.lamps.light(camera.to_world, light.lamp_scale, self.env_t.device)
        self._trace_passes(camera, sums, lights, aa, max(2, spp // aa), seed)
        return sums.images(camera.height, camera.width, aa)

    def _residual(self):
        """The residual this render adds: the run's under its own light (None otherwise)."""
        return self.residual

    def _trace_passes(self, camera: Camera, sums: _PixelSums, lights: list[Renderer], aa: int, light_spp: int,
                      seed: int) -> None:
        """Trace the `aa` stratified primary-ray passes of the view and add their shaded hits to sums."""
        n_pix = sums.n_pix
        rng = np.random.default_rng(seed)
        # One generator per lighting, all seeded alike: each draws the samples its own render would.
        gens = [torch.Generator(device=self.env_t.device).manual_seed(seed) for _ in lights]
        # Several primary-ray passes per trace (up to MAX_RAYS rays), their hits shaded in chunks:
        # few large Mitsuba calls rather than one per pass, since each call has a fixed cost.
        per_trace = max(1, MAX_RAYS // n_pix)
        chunk = sized(self.fitted.cfg.render.chunk, CPU_RENDER_CHUNK)
        for first in range(0, aa, per_trace):
            # Each pass's offsets are drawn here, in pass order, so only this trace's are held.
            rays = [camera_rays(camera, np.full((n_pix, 2), 0.5) if aa == 1 else pixel_jitter(n_pix, a, aa, rng))
                    for a in range(first, min(first + per_trace, aa))]
            hits = self.scene.trace(np.concatenate([r[0] for r in rays]), np.concatenate([r[1] for r in rays]))
            idx = torch.nonzero(hits.valid)[:, 0]
            pixel = idx % n_pix  # the pixel of each hit
            sums.hits_count += torch.bincount(pixel, minlength=n_pix)
            for s in range(0, len(idx), chunk):
                self._shade_chunk(hits, idx[s:s + chunk], pixel[s:s + chunk], sums, lights, gens, light_spp)

    def _shade_chunk(self, hits, sel: torch.Tensor, pix: torch.Tensor, sums: _PixelSums, lights: list[Renderer],
                     gens: list[torch.Generator], light_spp: int) -> None:
        """Shade the hits `sel` (of pixels `pix`) under every lighting and add them to sums."""
        discrete = self.fitted.discrete
        out = self.fitted.materials_at(hits.position[sel], discrete=discrete is not None)
        # Every lighting's bounce samples land on the same points: the field runs once for them.
        bounce_field = _LastAnswer(lambda p: self.fitted.materials_at(p, ids=False)) \
            if self.fitted.cfg.train.bounces > 0 else None
        rgb, *rgb_relit = (light.scene.shade(hits.position[sel], hits.normal[sel], hits.wi[sel], out,
                                             light.env_t, light_spp, generator=g, material_fn=bounce_field)
                           for light, g in zip(lights, gens))
        values = {**{i.name: out[i.name].reshape(-1, i.channels) for i in INPUTS}, "normal": hits.normal[sel],
                  **dict(zip(sums.relit_keys, rgb_relit))}
        residual = self._residual()
        if residual is not None:
            values["rgb_physical"] = rgb
            r = residual(hits.position[sel], hits.normal[sel], hits.wi[sel])
            for edit in self.fitted.edits:  # edited points are physically based
                r = r * (~edit.selection.mask(hits.position[sel], out.get("material")))[:, None]
            rgb = add_residual(rgb, r)
        values["rgb"] = rgb
        if discrete is not None:  # material id of the hit (its nearest ranked codeword, 1..M) and its BRDF
            od = out["discrete"]
            sums.votes.index_put_((pix, out["material"]), torch.ones_like(pix, dtype=torch.int32),
                                  accumulate=True)
            values.update({f"{i.name}_d": od[i.name].reshape(-1, i.channels) for i in INPUTS})
        for k, v in values.items():  # hits of one chunk may share a pixel: index_add sums them
            sums.acc[k].index_add_(0, pix, v.double())


class _PixelSums:
    """Per-pixel sums of a render's shaded hits (float64): hit counts, every map, the rgb under
    each other lighting and, with a discrete branch, its maps and the material votes."""

    def __init__(self, n_pix: int, discrete, n_relight: int, dev, physical: bool = False):
        self.n_pix = n_pix
        self.hits_count = torch.zeros(n_pix, dtype=torch.float64, device=dev)
        channels = {"rgb": 3, **{i.name: i.channels for i in INPUTS}, "normal": 3}
        self.discrete = discrete is not None
        n_mat = int(discrete.num_materials) if discrete is not None else 0
        self.votes = torch.zeros(n_pix, n_mat + 1, dtype=torch.int32, device=dev) if discrete is not None else None
        if discrete is not None:  # the discrete branch's maps: each hit's material, decoded
            channels.update({f"{i.name}_d": i.channels for i in INPUTS})
        self.relit_keys = [f"relit_{j}" for j in range(n_relight)]  # rgb under each other lighting
        if physical:  # the rgb without the residual
            channels["rgb_physical"] = 3
        channels.update({k: 3 for k in self.relit_keys})
        self.acc = {k: torch.zeros(n_pix, c, dtype=torch.float64, device=dev) for k, c in channels.items()}

    def images(self, h: int, w: int, aa: int) -> dict[str, np.ndarray]:
        """`Renderer.render`'s images from the sums of `aa` primary rays per pixel."""
        acc = {k: v.cpu().numpy() for k, v in self.acc.items()}
        hits_count = self.hits_count.cpu().numpy()
        votes = self.votes.cpu().numpy() if self.votes is not None else None
        alpha = hits_count / aa
        out = {"alpha": alpha.reshape(h, w).astype(np.float32)}
        # Colour is premultiplied by coverage (background is black); maps are averaged over hits.
        out["rgb"] = (acc["rgb"] / aa).reshape(h, w, 3).astype(np.float32)
        if "rgb_physical" in acc:
            out["rgb_physical"] = (acc["rgb_physical"] / aa).reshape(h, w, 3).astype(np.float32)
        if self.relit_keys:
            out["relit"] = [(acc[k] / aa).reshape(h, w, 3).astype(np.float32) for k in self.relit_keys]
        safe = np.maximum(hits_count, 1)[:, None]
        def maps(suffix: str) -> dict:  # each BRDF input's map, (h, w, 3) or (h, w)
            return {i.name: (acc[i.name + suffix] / safe).reshape((h, w, 3) if i.colour else (h, w))
                    .astype(np.float32) for i in INPUTS}

        out.update(maps(""))
        nrm = acc["normal"] / safe
        nrm /= np.maximum(np.linalg.norm(nrm, axis=-1, keepdims=True), 1e-8)
        out["normal"] = nrm.reshape(h, w, 3).astype(np.float32)
        if self.discrete:
            out["discrete"] = maps("_d")
        if votes is not None:  # majority over the pixel's primary rays; background (alpha < 0.5) is 0
            ids = np.argmax(votes[:, 1:], axis=1) + 1
            out["material"] = np.where(alpha >= 0.5, ids, 0).reshape(h, w).astype(np.uint8)
            # Share of each pixel's primary rays that hit material k (index k = 1..M; index 0 stays 0).
            out["material_share"] = (votes / aa).reshape(h, w, -1).astype(np.float32)
        return out

class _LastAnswer:
    """A material field that keeps its last answer and gives it again for the same points."""

    def __init__(self, field):
        self.field, self.points, self.answer = field, None, None

    def __call__(self, points: torch.Tensor) -> dict[str, torch.Tensor]:
        if self.points is None or self.points.shape != points.shape or not torch.equal(self.points, points):
            self.points, self.answer = points, self.field(points)
        return self.answer


# Distinct colours for material ids 1..20 (id 0, the background, is not drawn).
PALETTE = np.array([
    [0.90, 0.10, 0.10], [0.10, 0.60, 0.90], [0.20, 0.75, 0.20], [0.95, 0.75, 0.10], [0.60, 0.25, 0.80],
    [0.95, 0.45, 0.10], [0.10, 0.80, 0.75], [0.90, 0.30, 0.60], [0.55, 0.55, 0.15], [0.35, 0.35, 0.85],
    [0.65, 0.35, 0.20], [0.50, 0.85, 0.50], [0.85, 0.85, 0.85], [0.20, 0.40, 0.30], [0.80, 0.55, 0.55],
    [0.30, 0.20, 0.50], [0.70, 0.90, 0.20], [0.15, 0.55, 0.55], [0.95, 0.60, 0.75], [0.45, 0.45, 0.45],
], dtype=np.float32)


def material_colours(ids: np.ndarray) -> np.ndarray:
    """(H, W, 3) colour of each material id (palette; black for 0, the background)."""
    colours = np.concatenate([np.zeros((1, 3), np.float32), PALETTE])
    ids = np.asarray(ids, dtype=np.int64)
    return colours[np.where(ids > 0, (ids - 1) % len(PALETTE) + 1, 0)]


def segmentation_overlay(rgb_linear: np.ndarray, alpha: np.ndarray, material: np.ndarray,
                         opacity: float = 0.5) -> np.ndarray:
    """sRGB image (H, W, 3) in [0, 1]: the view over white, each material's pixels tinted with its
    palette colour."""
    a = alpha[..., None]
    straight = rgb_linear / np.maximum(a, 1e-6)
    over_white = linear_to_srgb(np.clip(straight, 0, None)) * a + (1 - a)
    tint = material_colours(material)
    on = (material > 0)[..., None]
    return np.clip(np.where(on, (1 - opacity) * over_white + opacity * tint, over_white), 0, 1)


def check_finite(images: dict, view: str) -> None:
    """Raise NumericalError when a rendered image holds NaN or Inf (nothing of the view is written)."""
    bad = [k for k, v in images.items() if isinstance(v, np.ndarray) and v.dtype.kind == "f" and not np.isfinite(v).all()]
    if bad:
        raise NumericalError(None, f"view {view}: the render holds non-finite values in {', '.join(bad)}; "
                                   "nothing of this view was written")


def write_rgb_png(path: Path, images: dict[str, np.ndarray]) -> None:
    """A render's colour as an sRGB PNG: straight (not premultiplied) colour with alpha, as image
    viewers expect."""
    a = images["alpha"]
    write_png(path, images["rgb"] / np.maximum(a, 1e-6)[..., None], alpha=a)


def write_view(out_dir: Path, name: str, images: dict[str, np.ndarray]) -> None:
    """The per-view files of INTERFACE.md."""
    a = images["alpha"]
    write_exr(out_dir / f"{name}_rgb.exr", np.concatenate([images["rgb"], a[..., None]], -1))
    write_rgb_png(out_dir / f"{name}_rgb.png", images)
    for i in INPUTS:
        write_exr(out_dir / f"{name}_{i.name}.exr", images[i.name])
    write_exr(out_dir / f"{name}_normal.exr", images["normal"])
    write_png(out_dir / f"{name}_alpha.png", a, srgb=False)
    if "material" in images:
        write_png(out_dir / f"{name}_material.png", images["material"])
        overlay = segmentation_overlay(images["rgb"], a, images["material"])
        write_png(out_dir / f"{name}_segmentation.png", overlay, srgb=False)


def render_views(fitted: FittedModel, cameras: Sequence[Camera], cameras_world: str, out_dir: Path,
                 envmap: np.ndarray | None = None, env_rotate_deg: float = 0.0, exposure_ev: float = 0.0,
                 spp: int | None = None,
                 more_envmaps: Sequence[tuple[str, np.ndarray]] = (), keep_lamps: bool = False) -> None:
    """Render every camera (given in world `cameras_world`) and write the per-view files.

    `more_envmaps`: (name, envmap) pairs of further lightings. Then the views under `envmap` go to
    OUT_DIR and those under each further lighting to OUT_DIR/NAME, the same files; one pass per
    view traces the rays and evaluates the material field for all of them, and each lighting's
    images are those a render under it alone gives (same seed)."""
    from vq_mitsuba import messages

    for name, _ in more_envmaps:  # each lighting's folder lies inside OUT_DIR
        if name in ("", ".", "..") or "/" in name or "\\" in name:
            raise InputError(None, f"the lighting name {name!r} cannot name a folder inside {out_dir}")
    # The loaders' names are file names already (vq_mitsuba.data.names); this keeps any other
    # caller's inside OUT_DIR and apart.
    files = view_names([cam.name for cam in cameras])
    renderer = Renderer(fitted, envmap, env_rotate_deg, exposure_ev, keep_lamps)
    others = [Renderer(fitted, env, env_rotate_deg, exposure_ev, keep_lamps) for _, env in more_envmaps]
    for cam, file_name in zip(messages.progress(cameras, desc="render"), files):
        images = renderer.render(convert_world(cam, cameras_world, fitted.world), spp=spp, relight=others)
        relit = images.pop("relit", [])
        check_finite(images, cam.name)
        check_finite({f"{name} rgb": im for (name, _), im in zip(more_envmaps, relit)}, cam.name)
        if cameras_world != fitted.world:  # normals in the cameras' world
            images["normal"] = images["normal"] @ world_rotation(fitted.world, cameras_world).T
        write_view(out_dir, file_name, images)
        for (name, _), rgb in zip(more_envmaps, relit):
            write_view(out_dir / name, file_name, dict(images, rgb=rgb))
