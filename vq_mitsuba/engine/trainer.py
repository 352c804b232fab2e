"""The training loop: both branches of VQ-NeRF on known geometry, their losses, checkpoints,
time limit.

Primary hits of every training pixel are traced once (`vq_mitsuba.data.pixels`); each step
draws a random batch of foreground pixels across all views, evaluates the material field once
per hit and shades through Mitsuba (`vq_mitsuba.render.shading`). After `vq.warmup_frac` of
training the discrete branch starts from k-means of the latents and trains beside the
continuous one. The fit around the loop (checks, loading, resuming) is `vq_mitsuba.engine.pipeline`;
what is written at its end (ranked materials, residual, plots) is `vq_mitsuba.engine.products`.
Every file is written through `RunDir`; a run resumes from its last checkpoint.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from vq_mitsuba import messages
from vq_mitsuba import brdf
from vq_mitsuba.backend import init_mitsuba, shading_threads, torch_device
from vq_mitsuba.config import Config, to_dict
from vq_mitsuba.data.captures import Capture
from vq_mitsuba.data.pixels import (ErrorSampler, hold_aside, neighbour_pairs, pixel_hit_table, sampler_tile,
                                    trace_training_pixels)
from vq_mitsuba.run.run_dir import RunDir
from vq_mitsuba.engine import evidence, skips, trials
from vq_mitsuba.engine.schedule import StepSchedule, schedule_at
from vq_mitsuba.run.loop import Budget, Loop, Progress
from vq_mitsuba.errors import InputError, NumericalError, warn
from vq_mitsuba.models import losses
from vq_mitsuba.models.fields import EnvironmentMap
from vq_mitsuba.models.fitted import material_networks
from vq_mitsuba.models.vq import dropout_rates, kmeans_codebook, sample_drop_mask, scale_gradient
from vq_mitsuba.render.shading import scene_for_mesh

MAX_NONFINITE_RUN = 20  # non-finite steps in a row that stop a fit
KMEANS_LATENTS = 20000  # latents clustered to start the codebook
ENVMAP_START_HEIGHT = 32  # rows of the learned envmap at the start of a fit


def parse_snapshot_times(text: str) -> list[float]:
    """`train.snapshot_s` ("30,60,120") as sorted seconds."""
    try:
        times = sorted(float(t) for t in str(text).replace(";", ",").split(",") if t.strip())
    except ValueError:
        raise InputError(None, f"train.snapshot_s expects comma-separated seconds, got '{text}'") from None
    if any(t <= 0 for t in times):
        raise InputError(None, f"train.snapshot_s expects positive seconds, got '{text}'")
    return times


def check_opaque_pixels(capture: Capture, alpha_threshold: float) -> None:
    """Refuse a capture without a pixel to fit (every alpha below train.alpha_threshold) before
    anything is traced."""
    if capture.has_alpha and not bool((capture.alpha >= alpha_threshold).any()):
        raise InputError(capture.source, f"no pixel of the {len(capture.cameras)} training views is opaque (alpha "
                                         f">= train.alpha_threshold = {alpha_threshold:g}): nothing to fit; check the "
                                         "alpha masks, or lower train.alpha_threshold")


def envmap_ladder(cfg: Config) -> list[int]:
    """The learned envmap's rungs: envmap.height halved while it stays at least 32 rows."""
    ladder = [cfg.envmap.height]
    while ladder[0] % 2 == 0 and ladder[0] // 2 >= ENVMAP_START_HEIGHT:
        ladder.insert(0, ladder[0] // 2)
    return ladder


def envmap_height_at(cfg: Config, progress: float) -> int:
    """Rows of the learned envmap at this training progress: the ladder (`envmap_ladder`) climbed
    at even steps over the first field.pe_anneal share of training (the sharp light is fitted
    after the coarse light and materials, as the encoding's frequencies open)."""
    ladder = envmap_ladder(cfg)
    anneal = cfg.field.pe_anneal
    if anneal <= 0:
        return ladder[-1]
    return ladder[min(len(ladder) - 1, int(progress / anneal * len(ladder)))]


class Trainer:
    """The networks, the optimiser and the pixel pool of one fit, and one training step."""

    def __init__(self, capture: Capture, run: RunDir, cfg: Config):
        self.cfg, self.run, self.capture = cfg, run, capture
        check_opaque_pixels(capture, cfg.train.alpha_threshold)
        torch.manual_seed(cfg.train.seed)
        np.random.seed(cfg.train.seed)
        init_mitsuba()
        self.device = device = torch_device()
        mean_fg = float(np.mean(capture.images[capture.alpha >= cfg.train.alpha_threshold])) if capture.has_alpha \
            else float(np.mean(capture.images))
        self.learn_env = capture.envmap is None
        if self.learn_env:
            self.env_module = EnvironmentMap(envmap_height_at(cfg, 0.0), cfg.envmap.init_scale * max(mean_fg, 1e-3))
            self.env_module.to(device)
            env_init = self.env_module().detach().cpu().numpy()
        else:
            self.fixed_env = torch.as_tensor(capture.envmap, device=device)
            env_init = capture.envmap
        self.scene = scene_for_mesh(capture.mesh, env_init, capture.envmap_to_world)
        self.pool, self.pool_stats = trace_training_pixels(self.scene, capture, cfg.train.alpha_threshold,
                                                           cfg.train.pixel_jitter, cfg.train.seed, cfg.train.max_hits)
        stats = self.pool_stats
        if stats["hits_per_pixel"] < max(cfg.train.pixel_jitter, 1) or stats["pixel_share"] < 1.0:
            messages.note(f"training pixels: {stats['opaque_pixels']:,} opaque pixels, {stats['hits_per_pixel']} "
                          f"hit(s) each instead of {max(cfg.train.pixel_jitter, 1)}"
                          + (f", {100 * stats['pixel_share']:.0f} % of them" if stats["pixel_share"] < 1.0 else "")
                          + f" (train.max_hits {cfg.train.max_hits:,})")
        if len(self.pool) == 0:
            raise InputError(capture.source, "no training pixel hits the geometry: check the cameras, the mesh "
                                             "and the alpha masks")
        self.model, self.discrete = material_networks(cfg, capture.mesh, device)
        groups = [{"params": self.model.parameters(), "lr": cfg.train.lr}]
        if self.discrete is not None:
            groups.append({"params": self.discrete.parameters(), "lr": cfg.train.lr})
        if self.learn_env:
            groups.append({"params": self.env_module.parameters(), "lr": cfg.envmap.lr})
        self.optim = torch.optim.Adam(groups, fused=True)
        self.base_lrs = [g["lr"] for g in self.optim.param_groups]
        self.gen = torch.Generator(device=device).manual_seed(cfg.train.seed)
        self.rates = dropout_rates(cfg.vq.num_codes, cfg.vq.dropout_max, cfg.vq.protected).to(device)
        self.pairs = neighbour_pairs(self.pool, capture.width, capture.height).to(device) \
            if cfg.loss.w_sm > 0 else None
        self.batch = min(cfg.train.batch_rays, len(self.pool))
        # a pixel's colour is the mean over its footprint: its jittered hits are shaded together and
        # their mean is scored, so the loss does not also ask each hit for the pixel's mean colour
        self.copies = int(self.pool_stats["hits_per_pixel"])  # 1 without jitter
        self.hit_row = self.pixel_hits = None
        if self.copies > 1:
            self.hit_row, self.pixel_hits = pixel_hit_table(self.pool, capture.width, capture.height, self.copies)
        self.history: list[dict] = []
        self.step, self.elapsed_before = 0, 0.0
        self._decide_at_start()

    def _decide_at_start(self) -> None:
        """The rules of `vq_mitsuba.engine.skips` that the scene decides before the first step: the
        bounce, the held-aside pixels of the pace, the pixel sampler; the envmap's rung is decided
        as the ladder would grow."""
        cfg, pool, t = self.cfg, self.pool, self.cfg.train
        seed = t.seed
        self.bounce_on, bounce = skips.decide_bounce(t.bounce, t.bounces, self.scene, pool.position, pool.wi,
                                                     skips.np_seed(seed, 1))
        self.decisions = {"bounce": bounce}
        w, h = self.capture.width, self.capture.height
        n_pixels = int((pool.copy == 0).sum())
        # no speed-up before every stage of the schedule has begun
        stages = [cfg.field.pe_anneal, cfg.loss.metallic_barrier_until] + ([cfg.vq.warmup_frac] if cfg.vq.enabled else [])
        self.pace = skips.Pace(t.iterations, t.stop == "auto", start_share=max(stages))
        self.held = self.train_idx = None
        self.trials_on = self.learn_env and t.trials == "auto"
        if self.pace.active or self.trials_on:
            self.held, self.train_idx = hold_aside(pool, w, h, skips.stop_pixels(n_pixels), skips.np_seed(seed, 2))
        self.sampler = None
        if t.sampling == "auto":
            candidates = self.train_idx if self.train_idx is not None else torch.arange(len(pool))
            drawable = n_pixels - (0 if self.held is None else len(self.held))
            tile = sampler_tile(drawable, self.pixels_per_step * t.iterations, skips.SAMPLER_VISITS)
            self.sampler = ErrorSampler(pool, candidates, w, h, tile, skips.SAMPLER_FLOOR)
        self.env_auto = self.learn_env and cfg.envmap.final_height == "auto"
        ladder = envmap_ladder(cfg)
        self.env_cap, self.env_decided, self.env_choices = ladder[0], 0, []
        gen = torch.Generator().manual_seed(skips.np_seed(seed, 3))
        self.rough_idx = torch.randperm(len(pool), generator=gen)[:skips.ROUGHNESS_HITS].to(self.device)
        self.trial_checked, self.trial, self.pull = False, None, None
        self.decisions["trials"] = skips.decision(
            t.trials, "none", "no learned light: nothing to trade a surface's roughness against" if not self.learn_env
            else f"train.trials = {t.trials}" if not self.trials_on else "the fit ended before the trial's check")
        self.prior_grid = None
        self.decisions["prior"] = self._weigh_prior()

    def _weigh_prior(self) -> dict:
        """The metallic term's weight over the object from the highlights of the images
        (`vq_mitsuba.engine.evidence`), before the first step; its decision."""
        cfg, pool, t = self.cfg, self.pool, self.cfg.train
        setting = cfg.loss.prior_evidence
        if setting != "auto" or cfg.loss.w_lam <= 0 or cfg.loss.lam_metallic <= 0:
            return skips.decision(setting, "whole", f"loss.prior_evidence = {setting}" if setting != "auto"
                                  else "no metallic prior to weigh (loss.w_lam or loss.lam_metallic is 0)")
        gen = torch.Generator().manual_seed(skips.np_seed(t.seed, 5))
        pick = torch.randperm(len(pool), generator=gen)[:evidence.HITS].to(self.device)
        pos = pool.position[pick]
        views = evidence.sample_views(self.scene, self.capture, pos, pool.normal[pick], t.alpha_threshold,
                                      skips.np_seed(t.seed, 6))
        tint = evidence.highlight_tint(views)
        bounds = torch.tensor(np.array(self.capture.mesh.bounds), dtype=torch.float32)
        grid = evidence.WeightGrid.of_tints(pos, tint, bounds)
        shown = ~torch.isnan(tint)
        weight = grid(pos).cpu()
        record = {"hits": len(pick), "hits_with_highlight": int(shown.sum()),
                  "tint_median": float(tint[shown].median()) if bool(shown.any()) else None,
                  "share_weakened": float((weight < 1).float().mean()), "share_off": float((weight == 0).float().mean()),
                  "mean_weight": float(weight.mean())}
        seen = (f"{record['hits_with_highlight']} of {len(pick)} training hits show a highlight (in {evidence.RANK + 1} "
                f"views at least {evidence.HIGHLIGHT:g} x their median view's luminance) on a coloured surface")
        if grid.full:
            return {**skips.decision(setting, "whole", f"{seen}; no voxel's highlights keep more than "
                                     f"{evidence.DIELECTRIC:g} of its colour (median "
                                     + ("none" if record["tint_median"] is None else f"{record['tint_median']:.2f}")
                                     + "): the metallic prior is whole"), **record}
        self.prior_grid = grid
        reason = (f"{seen}, their highlights keeping a median {record['tint_median']:.2f} of the surface's colour "
                  f"saturation; the metallic prior is weakened on {100 * record['share_weakened']:.0f} % of the hits "
                  f"(off on {100 * record['share_off']:.0f} %, from a tint of {evidence.METAL:g}), mean weight "
                  f"{record['mean_weight']:.2f}")
        messages.note(f"prior: {reason}")
        return {**skips.decision(setting, "weighed", reason), **record}

    # --- state ----------------------------------------------------------------------------------
    def envmap(self) -> torch.Tensor:
        return self.env_module() if self.learn_env else self.fixed_env

    def set_envmap_height(self, height: int, resample: bool = True) -> None:
        """Bring the learned envmap to `height` rows (resampled, or a blank parameter of that shape
        that a checkpoint fills); its Adam state restarts. It grows as the schedule goes on, and
        shrinks only when a run resumes with more iterations, at an earlier point of the ladder."""
        env = self.env_module
        old = env.log_radiance
        if old.shape[0] == height:
            return
        if resample and height < old.shape[0]:  # the mean radiance of each coarser texel
            radiance = torch.nn.functional.adaptive_avg_pool2d(torch.exp(old.detach()).permute(2, 0, 1),
                                                               (height, 2 * height))
            env.log_radiance = torch.nn.Parameter(torch.log(radiance).permute(1, 2, 0).contiguous())
        elif resample:
            env.resize(height)
        else:
            env.log_radiance = torch.nn.Parameter(torch.zeros(height, 2 * height, 3, device=old.device))
        group = next(g for g in self.optim.param_groups if any(q is old for q in g["params"]))
        group["params"] = [env.log_radiance]
        self.optim.state.pop(old, None)

    def fitted_state(self, elapsed: float) -> dict:
        """What rendering and scoring need."""
        return {"model": self.model.state_dict(),
                "discrete": self.discrete.state_dict() if self.discrete is not None else None,
                "envmap": self.env_module.state_dict() if self.learn_env else None,
                "envmap_fixed": None if self.learn_env else torch.as_tensor(self.capture.envmap),
                "step": self.step, "elapsed_s": elapsed, "config": to_dict(self.cfg)}

    def training_state(self, elapsed: float) -> dict:
        """The fitted state plus what resuming needs (`resume` reads it back)."""
        return {**self.fitted_state(elapsed), "optim": self.optim.state_dict(), "generator": self.gen.get_state(),
                "history": self.history, "skips": self.skips_state()}

    def checkpoint(self, elapsed: float) -> None:
        """`training_state` as the run's checkpoint, and config.yaml with the same configuration."""
        self.run.save_state(self.training_state(elapsed))
        self.run.write_config(self.cfg)

    def snapshot(self, elapsed: float) -> None:
        self.run.save_state(self.fitted_state(elapsed), self.run.snapshot_path(elapsed, self.step))

    def resume(self, state: dict | None = None) -> None:
        """Continue from the run's checkpoint (`state`: that checkpoint, when already loaded)."""
        state = self.run.load_state(device=self.device) if state is None else state
        self.model.load_state_dict(state["model"])
        if self.discrete is not None:
            self.discrete.load_state_dict(state["discrete"])
        if self.learn_env:
            self.set_envmap_height(state["envmap"]["log_radiance"].shape[0], resample=False)
            self.env_module.load_state_dict(state["envmap"])
        self.optim.load_state_dict(state["optim"])
        self.gen.set_state(state["generator"].cpu())  # CPU bytes on any device
        self.history, self.step, self.elapsed_before = state["history"], state["step"], state["elapsed_s"]
        self.load_skips_state(state.get("skips"))

    def skips_state(self) -> dict:
        """What the rules decided and measured so far (`vq_mitsuba.engine.skips`), for resuming."""
        return {"bounce_on": self.bounce_on, "decisions": self.decisions, "pace": self.pace.state_dict(),
                "sampler": self.sampler.state_dict() if self.sampler is not None else None,
                "envmap": {"cap": self.env_cap, "decided": self.env_decided, "choices": self.env_choices},
                "trial": {"checked": self.trial_checked, "pending": self.trial}}

    def load_skips_state(self, state: dict | None) -> None:
        """Resume the rules: a run keeps the bounce decided at its start, the pace, the envmap's
        rung and the sampler's errors. A checkpoint without them (older, or fitted before the
        rules) ran every step at pace 1: its schedule position is its step."""
        if state is None:
            self.pace.position = float(self.step)
            return
        self.bounce_on = bool(state["bounce_on"])
        if self.cfg.train.bounces > 0 and self.cfg.train.bounce == state["decisions"]["bounce"]["setting"]:
            self.decisions["bounce"] = state["decisions"]["bounce"]
        else:  # the setting changed on resume: the new one holds
            self.bounce_on = self.decisions["bounce"]["choice"] == "on"
        self.pace.load_state_dict(state["pace"])
        if not self.pace.active:
            self.pace.rate = 1
        if self.sampler is not None and state["sampler"] is not None:
            self.sampler.load_state_dict(state["sampler"])
        env = state["envmap"]
        self.env_cap, self.env_decided, self.env_choices = int(env["cap"]), int(env["decided"]), list(env["choices"])
        trial = state.get("trial") or {"checked": False, "pending": None}
        self.trial_checked, self.trial = bool(trial["checked"]), trial["pending"]
        if "trials" in state["decisions"]:
            self.decisions["trials"] = state["decisions"]["trials"]

    # --- one step -------------------------------------------------------------------------------
    @torch.no_grad()
    def start_discrete(self) -> None:
        """The codebook from k-means of the warmed-up latents; the discrete decoder as a copy of
        the continuous one."""
        pool = self.pool
        sub = torch.randint(0, len(pool), (min(KMEANS_LATENTS, len(pool)),), generator=self.gen, device=self.device)
        z_warm = self.model(pool.position[sub])["z"]
        if not bool(torch.isfinite(z_warm).all()):
            raise NumericalError(self.run.dir, f"step {self.step}: the material field's latents are not finite, so "
                                               "the codebook cannot start from them; try a lower train.lr, or "
                                               "--resume with another train.seed")
        self.discrete.vq.init_codebook(kmeans_codebook(z_warm, self.cfg.vq.num_codes, self.cfg.train.seed))
        self.discrete.warm_start(self.model.decoder, z_warm)
        self.discrete.initialised.fill_(True)

    def _render(self, idx, material: dict, env, bounce_fn, fixed_light=None):
        """Per-pixel Monte Carlo samples (B, spp, 3) of the pixels `idx` with `material`'s BRDF,
        in two independent halves for the decorrelated loss."""
        p = self.pool
        return self.scene.shade(p.position[idx], p.normal[idx], p.wi[idx], material, env, self.cfg.train.spp,
                                generator=self.gen, reduce=False, material_fn=bounce_fn, groups=2,
                                fixed_light=fixed_light)

    def _lambertian(self, out: dict, s: StepSchedule, weight: torch.Tensor | None = None,
                    metallic_scale: torch.Tensor | None = None) -> torch.Tensor:
        """Eq. (9), L_lam, with the metallic barrier early in training; `weight` (N,): the hits'
        importance weights, `metallic_scale` (N,): their metallic term's weight."""
        logit = out["metallic_logit"] if s.metallic_barrier else None
        return losses.lambertian_prior(out["metallic"], out["roughness"], self.cfg.loss.lam_metallic, logit, weight,
                                       metallic_scale)

    def loss_terms(self, idx: torch.Tensor, s: StepSchedule, bounce: bool,
                   weight: torch.Tensor | None = None) -> tuple[dict, torch.Tensor, torch.Tensor | None]:
        """The weighted loss terms of one batch (Eq. 10: their sum is the loss), the continuous
        branch's pixel colours and, when the sampler needs them, its per-pixel squared errors.
        `weight`: importance weights of the pixels (the error-driven sampler's), applied to the
        reconstruction terms; the priors, chromaticity and VQ terms are means over the batch."""
        cfg, pool, ab = self.cfg, self.pool, self.cfg.ablation
        gamma = cfg.loss.gamma
        # shaded, priors and VQ per hit; the reconstruction per pixel of `idx`, with its weight
        target, hits = pool.rgb[idx], self.footprint(idx)
        hit_weight = None if weight is None else weight.repeat_interleave(self.copies)
        out = self.model(pool.position[hits])
        # the metallic term of the prior weighed by the images' highlights (`evidence`)
        metal_w = None if self.prior_grid is None else self.prior_grid(pool.position[hits])
        env = self.envmap()
        bounce_fn = self.model if bounce else None
        discrete_on = self.discrete is not None and bool(self.discrete.initialised)
        single = discrete_on and ab.single_branch
        if not discrete_on:
            samples = self._render(hits, out, env, bounce_fn)
        else:
            z = out["z"].detach() if ab.separate else scale_gradient(out["z"], cfg.vq.joint_scale)
            drop = None if ab.no_ranking else sample_drop_mask(z.shape[0], self.rates, self.gen)
            od = self.discrete(z, drop, weight=hit_weight)
            # Both branches are shaded in one call. The discrete branch is lit by the envmap and
            # bounce that the continuous branch fits, without training them: a few materials
            # cannot explain a texture, and their residual would otherwise bend the shared light
            # (ablation.shared_light lets it).
            n = len(hits)
            both = {k: torch.cat([out[k], od[k]]) for k in brdf.NAMES}
            fixed = None if ab.shared_light else torch.arange(2 * n, device=self.device) >= n
            samples_both = self._render(torch.cat([hits, hits]), both, env, bounce_fn, fixed)
            samples, samples_d = samples_both[:n], samples_both[n:]
            samples_d = self._pixel_means(samples_d, len(target))
        samples = self._pixel_means(samples, len(target))
        per_pixel = None
        if self.sampler is not None:
            with torch.no_grad():
                per_pixel = losses.decorrelated_error(samples, target, gamma)
        terms = {
            "rec_c": (0.0 if single else cfg.loss.w_rec_c) * losses.reconstruction_l2_decorrelated(samples, target,
                                                                                                     gamma, weight),
            "lam_c": s.w_lam * self._lambertian(out, s, hit_weight, metal_w),
        }
        if discrete_on:
            terms["rec_d"] = cfg.loss.w_rec_d * losses.reconstruction_l2_decorrelated(samples_d, target, gamma, weight)
            terms["chr"] = (0.0 if single else cfg.loss.w_chr) * losses.chromaticity_loss(od["basecolor"],
                                                                                           out["basecolor"], hit_weight)
            terms["vq"] = cfg.loss.w_vq * od["vq_loss"]
            terms["lam_d"] = s.w_lam_d * self._lambertian(od, s, hit_weight, metal_w)
        if self.pairs is not None and len(self.pairs) > 0:
            pick = self.pairs[torch.randint(0, len(self.pairs), (max(self.batch // 4, 1),), generator=self.gen,
                                            device=self.device)]
            oa, ob = self.model(pool.position[pick[:, 0]]), self.model(pool.position[pick[:, 1]])
            ia = losses.encode_gamma(pool.rgb[pick[:, 0]], gamma)
            ib = losses.encode_gamma(pool.rgb[pick[:, 1]], gamma)
            terms["sm"] = cfg.loss.w_sm * losses.colour_aware_smoothness(oa, ob, ia, ib, cfg.loss.sm_alpha,
                                                                         cfg.loss.sm_beta)
        if self.learn_env and cfg.envmap.tv_weight > 0:
            terms["env_tv"] = cfg.envmap.tv_weight * self.env_module.smoothness()
        if self.pull is not None:  # a trial's copy: the flagged surfaces pulled to their other explanation
            flags, glossy = self.pull
            branches = [out] + ([od] if discrete_on else [])
            terms["trial"] = trials.PULL_WEIGHT * sum(trials.pull_term(o["roughness"], flags[hits], glossy)
                                                      for o in branches)
        return terms, samples.mean(1), per_pixel

    @staticmethod
    def _pixel_means(samples: torch.Tensor, n_pixels: int) -> torch.Tensor:
        """(n_pixels, spp, 3): the mean of each pixel's hits' samples (hits in pixel order)."""
        return samples.reshape(n_pixels, -1, *samples.shape[1:]).mean(1)

    def draw(self) -> tuple[torch.Tensor, torch.Tensor | None]:
        """The step's pixels (pool indices) and their importance weights (None: drawn uniformly)."""
        if self.sampler is not None:
            if self.step % skips.SAMPLER_REFRESH == 0:
                self.sampler.refresh()
            return self.sampler.draw(self.pixels_per_step, self.gen)
        if self.train_idx is not None:  # all but the held-aside pixels
            pick = torch.randint(0, len(self.train_idx), (self.pixels_per_step,), generator=self.gen,
                                 device=self.device)
            return self.train_idx[pick], None
        return torch.randint(0, len(self.pool), (self.pixels_per_step,), generator=self.gen, device=self.device), None

    @property
    def pixels_per_step(self) -> int:
        """Pixels a step draws: train.batch_rays hits, all the jittered hits of each pixel."""
        return max(1, self.batch // self.copies)

    def footprint(self, idx: torch.Tensor) -> torch.Tensor:
        """(len(idx) * copies,) the jittered hits of the pixels of the hits `idx`, pixel by pixel."""
        if self.pixel_hits is None:
            return idx
        return self.pixel_hits[self.hit_row[idx]].reshape(-1)

    def envmap_height(self, progress: float) -> int:
        """The ladder's rows at `progress` (`envmap_height_at`), no higher than the rung the fitted
        roughness asks for when envmap.final_height is auto: decided each time the ladder reaches
        a rung it has not reached before, and read again every `skips.ENVMAP_RECHECK_EVERY` steps
        while the ladder is above it, so a roughness that falls later still grows the light (the
        rung kept never goes down). A decision is recorded when the ladder reaches a rung or the
        rung grows."""
        want = envmap_height_at(self.cfg, progress)
        if not self.env_auto:
            return want
        ladder = envmap_ladder(self.cfg)
        k = ladder.index(want)
        reached = k > self.env_decided
        if reached or (want > self.env_cap and self.step % skips.ENVMAP_RECHECK_EVERY == 0):
            self.env_decided = max(self.env_decided, k)
            with torch.no_grad():
                roughness = self.model(self.pool.position[self.rough_idx])["roughness"]
            rows, why = skips.envmap_rung(ladder, roughness)
            grows = rows > self.env_cap
            if rows < self.env_cap:
                why += f"; kept at {self.env_cap} rows (a rung reached is kept)"
            self.env_cap = max(self.env_cap, rows)
            if reached or grows:
                self.env_choices.append({"step": self.step, "ladder_rows": want, "rows": min(want, self.env_cap),
                                         "reason": why})
                messages.note(f"envmap: {min(want, self.env_cap)} rows at step {self.step} (the ladder's {want}): {why}")
        return min(want, self.env_cap)

    def train_step(self, s: StepSchedule) -> tuple[bool, float, float]:
        """One optimisation step; (finite, loss, sRGB MSE of the continuous branch). A step whose
        loss or gradients are not finite is not applied."""
        for g, lr in zip(self.optim.param_groups, self.base_lrs):
            g["lr"] = lr * s.lr_factor
        if s.discrete and not bool(self.discrete.initialised):
            self.start_discrete()
        self.model.set_progress(s.progress, self.cfg.field.pe_anneal)
        if self.learn_env:
            self.set_envmap_height(self.envmap_height(s.progress))
        idx, weight = self.draw()
        terms, rgb, per_pixel = self.loss_terms(idx, s, self.bounce_active(), weight)
        loss = sum(terms.values())
        self.optim.zero_grad(set_to_none=True)
        loss.backward()
        grads = [p.grad for g in self.optim.param_groups for p in g["params"] if p.grad is not None]
        finite = bool(torch.isfinite(loss)) and bool(torch.stack([torch.isfinite(g).all() for g in grads]).all())
        self.step += 1
        if not finite:
            return False, math.nan, math.nan
        self.optim.step()
        if self.sampler is not None:
            self.sampler.update(idx, per_pixel)
        with torch.no_grad():
            mse = float(losses.srgb_mse(rgb.detach(), self.pool.rgb[idx], weight))  # of all pixels, by weight
        return True, float(loss.detach()), mse

    def bounce_active(self) -> bool:
        """The bounce is simulated at this step: decided on (`skips.decide_bounce`) and past
        train.bounce_after."""
        return self.bounce_on and self.step >= self.cfg.train.bounce_after

    @torch.no_grad()
    def held_loss(self) -> float:
        """The reconstruction loss (gamma-encoded L2) of the held-aside pixels, each pixel's mean over
        its jittered hits against its colour as in a step, with the same light samples each time: the
        continuous branch's, plus the discrete branch's once it trains."""
        cfg, pool = self.cfg, self.pool
        idx = hits = self.footprint(self.held)  # idx: the hits shaded, once per branch
        out = self.model(pool.position[hits])
        mats = brdf.select(out)
        discrete_on = self.discrete is not None and bool(self.discrete.initialised)
        if discrete_on:
            was_training = self.discrete.training
            self.discrete.eval()  # no codebook (EMA) update from a measurement
            od = self.discrete(out["z"])
            self.discrete.train(was_training)
            mats = {k: torch.cat([mats[k], od[k]]) for k in mats}
            idx = torch.cat([idx, idx])
        gen = torch.Generator(device=self.device).manual_seed(skips.np_seed(cfg.train.seed, 4))
        rgb = self.scene.shade(pool.position[idx], pool.normal[idx], pool.wi[idx], mats, self.envmap().detach(),
                               cfg.train.spp,
                               generator=gen, material_fn=self.model if self.bounce_active() else None)
        target = pool.rgb[self.held]
        return sum(float(losses.reconstruction_l2(self._pixel_means(branch, len(target)), target, cfg.loss.gamma))
                   for branch in rgb.split(len(hits)))

    # --- the trial (`vq_mitsuba.engine.trials`) ---------------------------------------------------
    def trial_after_step(self, p: Progress) -> None:
        """After a step: the trial's choice when its steps are done, or its check once every stage of
        the schedule has begun."""
        if self.trial is not None:
            if self.step >= self.trial["until"]:
                self.finish_trial()
        elif not self.trial_checked and self.pace.share() >= self.pace.start_share:
            self.trial_checked = True
            self.start_trial(p)

    def start_trial(self, p: Progress) -> None:
        """Flag the metals at the roughness floor on the fixed hits; where enough are flagged, train
        a copy of the fit with them pulled glossier, measure it on the held-aside pixels and keep it
        aside while the fit itself trains as many steps."""
        cfg, pool = self.cfg, self.pool
        floor, glossy = cfg.field.roughness_min, trials.glossy_roughness(ENVMAP_START_HEIGHT)
        with torch.no_grad():
            fixed = trials.flag(self.model(pool.position[self.rough_idx]), floor)
        share = float(fixed.float().mean())
        seen = (f"{100 * share:.1f} % of {len(self.rough_idx)} fixed training hits at step {self.step} metal (metallic "
                f"> {trials.METAL:g}) within {trials.FLOOR_BAND:g} of the roughness floor {floor:g}")
        if share < trials.MIN_SHARE:
            self.decisions["trials"] = skips.decision(cfg.train.trials, "none",
                                                      f"{seen} (a trial from {100 * trials.MIN_SHARE:g} %)")
            return
        flags = trials.flag_hits(self.model, pool.position, floor)
        probe = self.rough_idx[fixed]  # the fixed hits flagged, read again at the choice
        steps = max(2, round(trials.TRIAL_SHARE * cfg.train.iterations))
        messages.note(f"trial: {seen}; a copy of the fit tries them at roughness >= {glossy:.2f} for {steps} steps")
        start = trials.copy_fit(self)
        self.pull = (flags.to(self.device), glossy)
        for i in range(steps):
            if i == steps // 2:
                self.pull = None  # the second half free: the copy settles where the images want it
            self.train_step(schedule_at(cfg, Progress(self.step, p.seconds, self.pace.share(), p.time_share)))
            self.pace.advance()
        self.pull = None
        record = {"step": int(start["step"]), "steps": steps, "share_at_floor": share, "glossy": glossy,
                  "hits_flagged": int(flags.sum()), "held_loss_copy": self.held_loss(),
                  "roughness_copy": self._median_roughness(probe)}
        until, copied = self.step, trials.copy_fit(self)
        trials.restore_fit(self, start)
        self.trial = {"until": until, "copy": copied, "record": record, "probe": probe}

    def finish_trial(self) -> None:
        """Keep whichever of the fit and its copy has the lower held-aside loss."""
        cfg, trial = self.cfg, self.trial
        record = trial["record"]
        record["held_loss_fit"] = self.held_loss()
        record["roughness_fit"] = self._median_roughness(trial["probe"])
        keep_copy = record["held_loss_copy"] < record["held_loss_fit"]
        if keep_copy:
            trials.restore_fit(self, trial["copy"])
        fmt = lambda r: "none" if r is None else f"{r:.3f}"  # noqa: E731
        reason = (f"at step {record['step']}, {100 * record['share_at_floor']:.1f} % of the fixed hits metal at the "
                  f"roughness floor; after {record['steps']} steps the held-aside loss is "
                  f"{record['held_loss_copy']:.5g} for the copy pulled to >= {record['glossy']:.2f} (median roughness "
                  f"{fmt(record['roughness_copy'])}) against {record['held_loss_fit']:.5g} for the fit "
                  f"({fmt(record['roughness_fit'])}): " + ("the copy goes on" if keep_copy else "the fit goes on"))
        self.decisions["trials"] = {**skips.decision(cfg.train.trials, "swapped" if keep_copy else "kept", reason),
                                    "trials": [record]}
        messages.note(f"trial: {reason}")
        self.trial = None

    @torch.no_grad()
    def _median_roughness(self, idx: torch.Tensor) -> float | None:
        """Median fitted roughness of the training hits `idx` (None without any)."""
        if len(idx) == 0:
            return None
        return float(self.model(self.pool.position[idx.to(self.device)])["roughness"].median())

    # --- the loop -------------------------------------------------------------------------------
    def train(self, progress: bool = True) -> dict:
        """Run the remaining steps under train.iterations and train.time_limit_s (the loop skeleton,
        `vq_mitsuba.run.loop`); the learning rate follows the step share, the rest of the schedule
        the larger of the step and time shares (`schedule_at`)."""
        cfg = self.cfg
        self._acc = {"loss": 0.0, "mse": 0.0, "n": 0, "nonfinite": 0, "run": 0}
        loop = Loop("fit", Budget(cfg.train.iterations, cfg.train.time_limit_s), self._loop_step,
                    start_step=self.step, start_seconds=self.elapsed_before,
                    checkpoint=lambda p: self.checkpoint(p.seconds), checkpoint_every=cfg.train.checkpoint_every,
                    snapshot=lambda p, label: self.snapshot(p.seconds),
                    snapshot_times=parse_snapshot_times(cfg.train.snapshot_s), progress_bar=progress,
                    done=lambda: self.pace.finished)
        self._clock = loop.clock
        self._phase = self._stage()
        for name in ("bounce",):
            messages.note(f"{name} {self.decisions[name]['choice']}: {self.decisions[name]['reason']}")
        with shading_threads():
            result = loop.run()
        if result.stopped_by_time:
            messages.note(f"time limit of {cfg.train.time_limit_s:.0f} s reached at step {self.step}")
        elif result.stopped_early:
            messages.note(f"schedule done at step {self.step} of {cfg.train.iterations} (train.stop = {cfg.train.stop})")
        return {"iterations": self.step, "seconds": result.seconds,
                "iterations_per_s": self.step / result.seconds if result.seconds > 0 else math.nan,
                "final_psnr_train_batch": self.history[-1]["psnr"] if self.history else None,
                "batch_rays": self.batch, "training_pixels": len(self.pool), "steps_this_call": result.steps_this_call,
                "nonfinite_steps_skipped": self._acc["nonfinite"], "decisions": self.final_decisions()}

    def _stage(self) -> tuple[bool, bool]:
        """(the discrete branch trains, the bounce is on): a change starts a new phase of the pace."""
        return self.discrete is not None and bool(self.discrete.initialised), self.bounce_active()

    def final_decisions(self) -> dict:
        """fit.json's `decisions`: each rule's setting, choice and reason."""
        cfg = self.cfg
        out = dict(self.decisions)
        held = 0 if self.held is None else len(self.held)
        out["stop"] = self.pace.decision(cfg.train.stop, self.step, held)
        out["stop"]["pace"] = self.pace.state_dict()
        setting = cfg.envmap.final_height
        if not self.learn_env:
            out["envmap"] = skips.decision(setting, "known", "the capture's envmap lights the fit")
        else:
            rows, top = int(self.env_module.log_radiance.shape[0]), envmap_ladder(cfg)[-1]
            if not self.env_auto:
                reason = f"envmap.final_height = {setting}: the ladder's {top} rows"
            elif self.env_choices:
                last = self.env_choices[-1]
                reason = f"decided at step {last['step']}: {last['reason']}"
            else:
                reason = "the fit ended before the ladder grew"
            out["envmap"] = skips.decision(setting, rows, reason)
            out["envmap"]["ladder"] = envmap_ladder(cfg)
            out["envmap"]["checks"] = list(self.env_choices)
        if self.sampler is None:
            out["sampling"] = skips.decision(cfg.train.sampling, "uniform", f"train.sampling = {cfg.train.sampling}")
        else:
            info = self.sampler.summary()
            share = info["top10_tiles_draw_share"]
            out["sampling"] = skips.decision(
                cfg.train.sampling, "error",
                f"by the running error of {info['tiles']} tiles of {info['tile_px']} x {info['tile_px']} px, "
                f"{100 * skips.SAMPLER_FLOOR:g} % uniform, importance-weighted"
                + ("" if share is None else f"; the 10 % of tiles with the largest error drew {100 * share:.0f} % "
                                             "of the rays"))
            out["sampling"].update(info)
        return out

    def _loop_step(self, p: Progress) -> dict | None:
        """One step of the loop: the optimisation step, the non-finite guard and the loss curve."""
        acc = self._acc
        # The schedule follows the pace's schedule steps (the time share under a time limit, if larger).
        p = Progress(p.step, p.seconds, self.pace.share(), p.time_share)
        finite, loss, mse = self.train_step(schedule_at(self.cfg, p))
        self.pace.advance()
        if self.trials_on:
            self.trial_after_step(p)
        stage = self._stage()
        if stage != self._phase:
            self._phase = stage
            self.pace.new_phase()
        if finite and self.pace.due(self.step):
            if self.pace.observe(self.step, self.held_loss()):
                messages.note(f"step {self.step}: the held-aside loss of the last {skips.STOP_WINDOW} measurements is "
                          f"not {100 * skips.STOP_TOLERANCE:g} % below the {skips.STOP_WINDOW} before; the schedule "
                          f"runs {self.pace.rate}x from here")
        if not finite:
            acc["nonfinite"] += 1
            acc["run"] += 1
            if acc["nonfinite"] == 1:
                warn(f"step {self.step}: loss or gradients not finite; the step is skipped")
            if acc["run"] >= MAX_NONFINITE_RUN:
                raise NumericalError(self.run.dir, f"steps {self.step - acc['run'] + 1} to {self.step} all "
                                     f"gave a non-finite loss or gradient; the checkpoint (step {self.step}) "
                                     f"keeps the parameters of step {self.step - acc['run']}, the last finite "
                                     "one; try a lower train.lr, or --resume with another train.seed")
            return None
        acc["run"] = 0
        acc["loss"], acc["mse"], acc["n"] = acc["loss"] + loss, acc["mse"] + mse, acc["n"] + 1
        if self.step % self.cfg.train.log_every == 0 or self.step == self.cfg.train.iterations or self.pace.finished:
            self.history.append({"step": self.step, "seconds": self._clock(), "loss": acc["loss"] / acc["n"],
                                 "psnr": losses.psnr(acc["mse"] / acc["n"])})
            acc["loss"], acc["mse"], acc["n"] = 0.0, 0.0, 0
            return {"loss": f"{self.history[-1]['loss']:.4g}", "psnr": f"{self.history[-1]['psnr']:.2f}",
                    **self.progress_notes()}
        return None

    def progress_notes(self) -> dict:
        """The rules' state for the progress line: bounce, envmap rows, sampling, pace."""
        notes = {"bounce": "on" if self.bounce_on else "off"}
        if self.learn_env:
            notes["env"] = f"{self.env_module.log_radiance.shape[0]}/{envmap_ladder(self.cfg)[-1]}"
        notes["rays"] = "error" if self.sampler is not None else "uniform"
        if self.pace.active:
            notes["pace"] = f"{self.pace.rate}x"
        return notes
