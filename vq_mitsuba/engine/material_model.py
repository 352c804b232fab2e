"""The material model of a fit: the continuous field, the discrete branch, the light and the
shading scene; it maps a batch of training pixels to their rendered colours and a named dict of
unweighted loss terms (VQ-NeRF Eq. 10; each term's weight is read from the config by its name,
`vq_mitsuba.models.losses.TERMS`).
"""

from __future__ import annotations

import numpy as np
import torch

from vq_mitsuba import brdf
from vq_mitsuba.config import Config
from vq_mitsuba.data.captures import Capture
from vq_mitsuba.engine.ladder import envmap_height_at
from vq_mitsuba.engine.pixel_data import PixelData
from vq_mitsuba.engine.schedule import StepSchedule
from vq_mitsuba.errors import NumericalError
from vq_mitsuba.models import losses
from vq_mitsuba.models.fields import EnvironmentMap, PointLamps
from vq_mitsuba.models.fitted import material_networks
from vq_mitsuba.models.vq import dropout_rates, kmeans_codebook, sample_drop_mask, scale_gradient
from vq_mitsuba.render.shading import scene_for_mesh

KMEANS_LATENTS = 20000  # latents clustered to start the codebook


class MaterialModel:
    """The networks and the light of one fit, over the capture's mesh."""

    def __init__(self, capture: Capture, cfg: Config, device, mean_foreground: float):
        """`mean_foreground`: the mean linear value of the opaque pixels, the learned light's start."""
        self.cfg, self.device, self.capture = cfg, device, capture
        self.learn_env = capture.envmap is None
        if self.learn_env:
            self.env_module = EnvironmentMap(envmap_height_at(cfg, 0.0), cfg.envmap.init_scale * max(mean_foreground,
                                                                                                    1e-3))
            self.env_module.to(device)
            env_init = self.env_module().detach().cpu().numpy()
        else:
            self.fixed_env = torch.as_tensor(capture.envmap, device=device)
            env_init = capture.envmap
        self.scene = scene_for_mesh(capture.mesh, env_init, capture.envmap_to_world)
        self.lamps = start_lamps(capture, cfg, mean_foreground).to(device) if cfg.lamps.count > 0 else None
        self.scene.lamps = self.lamps
        self.field, self.discrete = material_networks(cfg, capture.mesh, device)
        self.rates = dropout_rates(cfg.vq.num_codes, cfg.vq.dropout_max, cfg.vq.protected).to(device)
        self.prior = None  # the metallic prior's reading over the object (`vq_mitsuba.engine.evidence.PriorReading`)
        self.pull = None  # a trial's pull: (flags per hit, glossy roughness) (`vq_mitsuba.engine.trials`)

    @property
    def prior_grid(self):
        """The metallic prior's weight over the object as its reading stands now (None: whole)."""
        return None if self.prior is None else self.prior.grid

    # --- parameters and state ---------------------------------------------------------------------
    def parameter_groups(self) -> list[dict]:
        """Adam's groups: the field, the discrete branch, the learned light (in this order)."""
        cfg = self.cfg
        groups = [{"params": self.field.parameters(), "lr": cfg.train.lr}]
        if self.discrete is not None:
            groups.append({"params": self.discrete.parameters(), "lr": cfg.train.lr})
        if self.learn_env:
            groups.append({"params": self.env_module.parameters(), "lr": cfg.envmap.lr})
        if self.lamps is not None:
            groups.append({"params": self.lamps.parameters(), "lr": cfg.lamps.lr})
        return groups

    def state_dict(self) -> dict:
        """The fitted networks and light (the checkpoint's keys that rendering reads)."""
        return {"model": self.field.state_dict(),
                "discrete": self.discrete.state_dict() if self.discrete is not None else None,
                "envmap": self.env_module.state_dict() if self.learn_env else None,
                "envmap_fixed": None if self.learn_env else torch.as_tensor(self.capture.envmap),
                "lamps": None if self.lamps is None else self.lamps.state_dict()}

    def load_state_dict(self, state: dict) -> None:
        """Networks and light from a checkpoint (the learned envmap already at the checkpoint's rows)."""
        self.field.load_state_dict(state["model"])
        if self.discrete is not None:
            self.discrete.load_state_dict(state["discrete"])
        if self.learn_env:
            self.env_module.load_state_dict(state["envmap"])
        if self.lamps is not None:
            self.lamps.load_state_dict(state["lamps"])

    @torch.no_grad()
    def lamps_decision(self) -> dict:
        """fit.json's `lamps`: what the light beside the envmap is and, with lamps, where they ended."""
        from vq_mitsuba.engine.skips import decision

        n = self.cfg.lamps.count
        if self.lamps is None:
            return decision(n, "none", "lamps.count = 0: the envmap alone lights the fit")
        where = "fixed in the world" if self.cfg.lamps.frame == "world" else "riding with the camera"
        out = decision(n, self.cfg.lamps.frame, f"lamps.count = {n}: {n} point lamp(s) {where}, fitted beside the "
                                                 "envmap")
        out["lamps"] = [{"position": p.tolist(), "intensity": i.tolist()} for p, i in zip(*self.lamps.placement())]
        if bool(self.lamps.in_camera):
            out["position_frame"] = "each view's camera (Mitsuba camera space: +Z forward, +Y up, +X left)"
        return out

    def envmap(self) -> torch.Tensor:
        return self.env_module() if self.learn_env else self.fixed_env

    @property
    def envmap_rows(self) -> int:
        return int(self.env_module.log_radiance.shape[0])

    def resize_envmap(self, height: int, resample: bool = True) -> tuple[torch.Tensor, torch.Tensor] | None:
        """Bring the learned envmap to `height` rows (resampled, or a blank parameter of that shape
        that a checkpoint fills): (the old parameter, the new one), None when unchanged; the
        optimiser's state of the old one is the caller's to drop."""
        env = self.env_module
        old = env.log_radiance
        if old.shape[0] == height:
            return None
        if resample and height < old.shape[0]:  # the mean radiance of each coarser texel
            radiance = torch.nn.functional.adaptive_avg_pool2d(torch.exp(old.detach()).permute(2, 0, 1),
                                                               (height, 2 * height))
            env.log_radiance = torch.nn.Parameter(torch.log(radiance).permute(1, 2, 0).contiguous())
        elif resample:
            env.resize(height)
        else:
            env.log_radiance = torch.nn.Parameter(torch.zeros(height, 2 * height, 3, device=old.device))
        return old, env.log_radiance

    # --- the discrete branch ----------------------------------------------------------------------
    @property
    def discrete_on(self) -> bool:
        """The discrete branch has started (after its warm-up)."""
        return self.discrete is not None and bool(self.discrete.initialised)

    @torch.no_grad()
    def start_discrete(self, positions: torch.Tensor, gen: torch.Generator, step: int, run_dir) -> None:
        """The codebook from k-means of the warmed-up latents of a random subset of `positions`; the
        discrete decoder as a copy of the continuous one."""
        sub = torch.randint(0, len(positions), (min(KMEANS_LATENTS, len(positions)),), generator=gen,
                            device=self.device)
        z_warm = self.field(positions[sub])["z"]
        if not bool(torch.isfinite(z_warm).all()):
            raise NumericalError(run_dir, f"step {step}: the material field's latents are not finite, so "
                                          "the codebook cannot start from them; try a lower train.lr, or "
                                          "--resume with another train.seed")
        self.discrete.vq.init_codebook(kmeans_codebook(z_warm, self.cfg.vq.num_codes, self.cfg.train.seed))
        self.discrete.warm_start(self.field.decoder, z_warm)
        self.discrete.initialised.fill_(True)

    # --- a batch ----------------------------------------------------------------------------------
    def _render(self, data: PixelData, idx: torch.Tensor, material: dict, env, gen: torch.Generator, bounce_fn,
                fixed_light=None) -> torch.Tensor:
        """Per-hit Monte Carlo samples (B, spp, 3) of the hits `idx` with `material`'s BRDF, in two
        independent halves for the decorrelated loss."""
        p = data.pool
        return self.scene.shade(p.position[idx], p.normal[idx], p.wi[idx], material, env, self.cfg.train.spp,
                                generator=gen, reduce=False, material_fn=bounce_fn, groups=2, fixed_light=fixed_light,
                                views=self.scene.lamp_views(p, idx))

    def lambertian(self, out: dict, s: StepSchedule, weight: torch.Tensor | None = None,
                   metallic_scale: torch.Tensor | None = None) -> torch.Tensor:
        """Eq. (9), L_lam, with the metallic barrier early in training; `weight` (N,): the hits'
        importance weights, `metallic_scale` (N,): their metallic term's weight."""
        logit = out["metallic_logit"] if s.metallic_barrier else None
        return losses.lambertian_prior(out[brdf.METALLIC], out[brdf.ROUGHNESS], self.cfg.loss.lam_metallic, logit,
                                       weight, metallic_scale)

    def loss_dict(self, data: PixelData, idx: torch.Tensor, s: StepSchedule, bounce: bool, gen: torch.Generator,
                  weight: torch.Tensor | None = None) -> tuple[dict, torch.Tensor, torch.Tensor | None]:
        """The unweighted loss terms of the pixels `idx` by name (`losses.TERMS`), the continuous
        branch's pixel colours and, when the sampler keeps an error map, its per-pixel squared
        errors. `weight`: importance weights of the pixels, applied to the reconstruction terms;
        the priors, chromaticity and VQ terms are means over the batch."""
        cfg, pool, ab = self.cfg, data.pool, self.cfg.ablation
        gamma = cfg.loss.gamma
        # shaded, priors and VQ per hit; the reconstruction per pixel of `idx`, with its weight
        target, hits = pool.rgb[idx], data.footprint(idx)
        hit_weight = None if weight is None else weight.repeat_interleave(data.copies)
        out = self.field(pool.position[hits])
        metal_w = None if self.prior_grid is None else self.prior_grid(pool.position[hits])
        env = self.envmap()
        bounce_fn = self.field if bounce else None
        discrete_on = self.discrete_on
        single = discrete_on and ab.single_branch  # ablation: the discrete branch trains alone
        if not discrete_on:
            samples = self._render(data, hits, out, env, gen, bounce_fn)
        else:
            z = out["z"].detach() if ab.separate else scale_gradient(out["z"], cfg.vq.joint_scale)
            drop = None if ab.no_ranking else sample_drop_mask(z.shape[0], self.rates, gen)
            od = self.discrete(z, drop, weight=hit_weight)
            # Both branches are shaded in one call. The discrete branch is lit by the envmap and
            # bounce that the continuous branch fits, without training them: a few materials
            # cannot explain a texture, and their residual would otherwise bend the shared light
            # (ablation.shared_light lets it).
            n = len(hits)
            both = {k: torch.cat([out[k], od[k]]) for k in brdf.NAMES}
            fixed = None if ab.shared_light else torch.arange(2 * n, device=self.device) >= n
            samples_both = self._render(data, torch.cat([hits, hits]), both, env, gen, bounce_fn, fixed)
            samples, samples_d = samples_both[:n], data.pixel_means(samples_both[n:], len(target))
        samples = data.pixel_means(samples, len(target))
        per_pixel = None
        if data.sampler is not None:
            with torch.no_grad():
                per_pixel = losses.decorrelated_error(samples, target, gamma)
        terms = {}
        if not single:
            terms["rec_c"] = losses.reconstruction_l2_decorrelated(samples, target, gamma, weight)
        terms["lam_c"] = self.lambertian(out, s, hit_weight, metal_w)
        if discrete_on:
            terms["rec_d"] = losses.reconstruction_l2_decorrelated(samples_d, target, gamma, weight)
            if not single:
                terms["chr"] = losses.chromaticity_loss(od[brdf.BASECOLOR], out[brdf.BASECOLOR], hit_weight)
                # each hit's codeword's metallic, through the decoder alone: no pull on the latents
                code_metallic = self.discrete.decode_codewords()[brdf.METALLIC][od["index"]]
                terms["met"] = losses.metallic_agreement(code_metallic, out[brdf.METALLIC], hit_weight)
            terms["vq"] = od["vq_loss"]
            terms["lam_d"] = self.lambertian(od, s, hit_weight, metal_w)
        pick = data.neighbours(gen)
        if pick is not None:
            oa, ob = self.field(pool.position[pick[:, 0]]), self.field(pool.position[pick[:, 1]])
            ia, ib = losses.encode_gamma(pool.rgb[pick[:, 0]], gamma), losses.encode_gamma(pool.rgb[pick[:, 1]], gamma)
            terms["sm"] = losses.colour_aware_smoothness(oa, ob, ia, ib, cfg.loss.sm_alpha, cfg.loss.sm_beta)
        if self.learn_env and cfg.envmap.tv_weight > 0:
            terms["env_tv"] = self.env_module.smoothness()
        if self.pull is not None:  # a trial's copy: the flagged surfaces pulled to their other explanation
            from vq_mitsuba.engine.trials import pull_term

            flags, glossy = self.pull
            terms["trial"] = sum(pull_term(o[brdf.ROUGHNESS], flags[hits], glossy)
                                 for o in [out] + ([od] if discrete_on else []))
        return terms, samples.mean(1), per_pixel

    @torch.no_grad()
    def held_loss(self, data: PixelData, seed: int, bounce: bool) -> float:
        """The reconstruction loss (gamma-encoded L2) of the held-aside pixels, each pixel's mean over
        its jittered hits against its colour as in a step, with the same light samples each time
        (`seed`): the continuous branch's, plus the discrete branch's once it trains."""
        cfg, pool = self.cfg, data.pool
        idx = hits = data.footprint(data.held)  # idx: the hits shaded, once per branch
        out = self.field(pool.position[hits])
        mats = brdf.select(out)
        if self.discrete_on:
            was_training = self.discrete.training
            self.discrete.eval()  # no codebook (EMA) update from a measurement
            od = self.discrete(out["z"])
            self.discrete.train(was_training)
            mats = {k: torch.cat([mats[k], od[k]]) for k in mats}
            idx = torch.cat([idx, idx])
        gen = torch.Generator(device=self.device).manual_seed(seed)
        rgb = self.scene.shade(pool.position[idx], pool.normal[idx], pool.wi[idx], mats, self.envmap().detach(),
                               cfg.train.spp, generator=gen, material_fn=self.field if bounce else None,
                               views=self.scene.lamp_views(pool, idx))
        target = pool.rgb[data.held]
        return sum(float(losses.reconstruction_l2(data.pixel_means(branch, len(target)), target, cfg.loss.gamma))
                   for branch in rgb.split(len(hits)))

    def rank_materials(self, data: PixelData) -> dict:
        """The discrete branch's codewords ranked and M chosen (`vq_mitsuba.engine.ranking`)."""
        from vq_mitsuba.engine.ranking import rank_materials

        return rank_materials(self.scene, self.field, self.discrete, data.pool, self.envmap().detach(), self.cfg)

    def fit_residual(self, run, data: PixelData, step: int) -> dict:
        """The residual of novel views on the frozen materials and light (VQ-NeRF Sec. 4;
        `vq_mitsuba.engine.residual_fit`): its summary for fit.json."""
        from vq_mitsuba.engine.residual_fit import residual_stage

        return residual_stage(run, self.scene, self.field, data.pool, self.envmap().detach(), self.capture.mesh.bounds,
                              self.cfg, step)

    @torch.no_grad()
    def roughness(self, positions: torch.Tensor) -> torch.Tensor:
        """The continuous field's roughness at `positions`."""
        return self.field(positions)[brdf.ROUGHNESS]


def start_lamps(capture: Capture, cfg: Config, mean_foreground: float) -> PointLamps:
    """`cfg.lamps.count` point lamps. Fixed in the world: at `cfg.lamps.distance` object radii from
    the centre of the mesh's bounding box, the first towards the cameras' mean position (where a
    capture's lamps mostly stand), the others on a cone of 60 deg about it. Riding with the camera:
    at the camera, the others a radius to its sides. Each as bright as lights a white facing
    surface at the lamps' distance to the capture's mean value."""
    lo, hi = np.asarray(capture.mesh.bounds, dtype=np.float64)
    center, radius = (lo + hi) / 2, float(np.linalg.norm(hi - lo) / 2)
    eyes = np.array([c.to_world[:3, 3] for c in capture.cameras])
    n = cfg.lamps.count
    if cfg.lamps.frame == "camera":
        offsets = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])[:n]
        distance = max(float(np.median(np.linalg.norm(eyes - center, axis=1))) - radius, 0.5 * radius)
        return PointLamps(center, radius, torch.tensor(offsets, dtype=torch.float32),
                          np.pi * max(mean_foreground, 1e-3) * distance ** 2,
                          camera_to_world=np.array([c.to_world for c in capture.cameras]))
    toward = eyes.mean(0) - center
    toward = toward / np.linalg.norm(toward) if np.linalg.norm(toward) > 1e-6 * radius else np.array([0.0, 0.0, 1.0])
    side = np.cross(toward, [1.0, 0.0, 0.0] if abs(toward[0]) < 0.9 else [0.0, 1.0, 0.0])
    side /= np.linalg.norm(side)
    dirs = []
    for k in range(n):
        a = 2 * np.pi * k / max(n - 1, 1)
        other = np.cos(a) * side + np.sin(a) * np.cross(toward, side)
        dirs.append(toward if k == 0 else np.cos(np.pi / 3) * toward + np.sin(np.pi / 3) * other)
    offsets = torch.tensor(np.array(dirs) * cfg.lamps.distance, dtype=torch.float32)
    return PointLamps(center, radius, offsets, np.pi * max(mean_foreground, 1e-3) * radius ** 2)


def mean_foreground(capture: Capture, alpha_threshold: float) -> float:
    """The mean linear value of the capture's opaque pixels (of all, without alpha)."""
    if capture.has_alpha:
        return float(np.mean(capture.images[capture.alpha >= alpha_threshold]))
    return float(np.mean(capture.images))
