"""Residual baking (VQ-NeRF, Sec. 4): the view-dependent residual fitted after the material fit.

Materials and light are frozen, so the physically based radiance of each training hit is a
constant: it is rendered once (`PREDICTION_SPP` sample pairs, the continuous branch with the
render's bounce, as `render.views.Renderer` shades it) for up to `RESIDUAL_HITS` random hits of
the trainer's pixel pool (every hit of a capture of a few million pixels). The residual field, a
surface light field (`vq_mitsuba.models.residual`), is then fitted in torch alone, without
Mitsuba in the loop, to the gamma-encoded pixel colours:

    min_r  mean || enc(L_pbr(x, wi) + r(x, wi)) - enc(target) ||^2,   enc(c) = c^(1/loss.gamma)

Adam, the hash table at `LR` and the network at `LR_NET`, both decaying to `LR_END` of that over
residual.iterations steps of `BATCH` hits (fewer on a small pool: at most `MAX_EPOCHS` passes).
The finest cells of the hash encoding follow the hits (`models.residual.finest_for_hits`); the
kept-aside hits are scored every `steps / CHECKS` steps and the best field is kept, the untrained
(zero) one included, so the residual never makes the training pixels it was not fitted on worse.
The fit stops after `PATIENCE` scores in a row below the best. Until a score beats the zero field by
`MIN_GAIN_DB`, the scores come every `FIRST_GAP` steps, and when none of the first `PATIENCE` does,
there is nothing to learn (a capture the physically based render already explains, such as a scene
rendered by the model itself): the fit stops after a few seconds. The step runs eagerly until then
and is compiled (`vq_mitsuba.compiled`) when `COMPILE_FROM` full batches are left, so a residual
with nothing to learn, or little to do, never waits for the compiler.

Approximate: each hit's L_pbr is one Monte Carlo estimate, not its mean, so the targets of the
residual carry that noise; neighbouring hits share the field's cells and it is fitted over many
hits, so it averages the noise out rather than learning it (fit.json's `residual` block shows
the training-pixel PSNR before and after, on hits the field was not fitted on).
"""

from __future__ import annotations

import copy
import math
import time

import torch

from vq_mitsuba import messages
from vq_mitsuba.backend import device_scale, sized
from vq_mitsuba.compiled import Compiled
from vq_mitsuba.config import CPU_RENDER_CHUNK, Config
from vq_mitsuba.data.pixels import PixelPool
from vq_mitsuba.models import losses
from vq_mitsuba.models.residual import ResidualField, add_residual, finest_for_hits
from vq_mitsuba.run.loop import Budget, Loop, Progress
from vq_mitsuba.run.run_dir import RunDir

RESIDUAL_HITS = 1 << 21  # training hits the residual is fitted on (a random subset of larger pools), on a CPU
CHECK_SHARE = 0.1  # share of those hits kept aside to measure it
PREDICTION_SPP = 16  # sample pairs of each hit's physically based radiance
BATCH = 8192  # hits a step on a CPU; RESIDUAL_HITS and BATCH grow with a GPU (`backend.device_scale`)
LR = 1e-2  # the hash table's; the network's is LR_NET
LR_NET = 2e-3
LR_END = 0.1  # learning-rate factor at the last step (exponential decay)
MAX_EPOCHS = 200  # passes over the fitted hits at most: a small pool needs fewer steps than residual.iterations
MIN_STEPS = 50
CHECKS = 10  # times the kept-aside hits are scored during the fit: the best field is kept ...
PATIENCE = 3  # ... and the fit stops after this many scores in a row below the best
FIRST_GAP = 30  # steps between scores at most until a score beats the zero field by MIN_GAIN_DB ...
MIN_GAIN_DB = 0.1  # ... which tells that there is something to learn
COMPILE_FROM = 1000  # steps of BATCH hits left that pay for compiling the step (about 16 s the first time)


@torch.no_grad()
def physical_radiance(scene, model, pool: PixelPool, idx: torch.Tensor, env: torch.Tensor, cfg: Config,
                      generator: torch.Generator) -> torch.Tensor:
    """Linear radiance (len(idx), 3) of the pool's hits `idx` with the continuous branch's BRDF
    under `env`, with the bounce when the fit simulates one (what `render` shows without the residual)."""
    field = (lambda p: model(p)) if cfg.train.bounces > 0 else None
    parts = []
    chunk = sized(cfg.render.chunk, CPU_RENDER_CHUNK)
    for s in range(0, len(idx), chunk):
        sel = idx[s:s + chunk]
        out = model(pool.position[sel])
        parts.append(scene.shade(pool.position[sel], pool.normal[sel], pool.wi[sel], out, env, PREDICTION_SPP,
                                 generator=generator, material_fn=field))
    return torch.cat(parts)


def fit_residual(scene, model, pool: PixelPool, env: torch.Tensor, bounds, cfg: Config) -> tuple[ResidualField, dict]:
    """The residual field fitted on the pool's hits (materials `model` and light `env` frozen),
    and its summary: hits, steps, and the sRGB PSNR of the kept-aside hits before and after."""
    device = pool.position.device
    gen = torch.Generator(device=device).manual_seed(cfg.train.seed)
    scale = device_scale()
    n = min(len(pool), RESIDUAL_HITS * scale)
    idx = torch.randperm(len(pool), generator=gen, device=device)[:n]
    target = pool.rgb[idx]
    physical = physical_radiance(scene, model, pool, idx, env, cfg, gen)
    n_check = max(1, int(CHECK_SHARE * n)) if n > 1 else 0
    fit_ids, check_ids = torch.arange(n_check, n, device=device), torch.arange(n_check, device=device)
    if len(fit_ids) == 0:
        fit_ids = check_ids
    field = ResidualField(*bounds, scale=float(target.mean().clamp_min(1e-4)),
                          finest=finest_for_hits(len(fit_ids))).to(device)
    optim = torch.optim.Adam([{"params": [field.encoding.table], "lr": LR, "base": LR},
                              {"params": list(field.mlp.parameters()), "lr": LR_NET, "base": LR_NET}], eps=1e-15,
                             fused=True)
    gamma = cfg.loss.gamma
    position, normal, wi = pool.position[idx], pool.normal[idx], pool.wi[idx]
    batch = min(BATCH * scale, len(fit_ids))
    steps = min(cfg.residual.iterations, max(MIN_STEPS, math.ceil(MAX_EPOCHS * len(fit_ids) / batch)))
    every = max(1, steps // CHECKS)

    @torch.no_grad()
    def check_psnr() -> float:
        c = check_ids
        return losses.psnr(float(losses.srgb_mse(add_residual(physical[c], field(position[c], normal[c], wi[c])),
                                                 target[c])))

    def gradients(b: torch.Tensor) -> torch.Tensor:
        """The loss of the hits `b`, its gradients left in the parameters."""
        optim.zero_grad(set_to_none=True)
        loss = losses.reconstruction_l2(add_residual(physical[b], field(position[b], normal[b], wi[b])), target[b],
                                        gamma)
        loss.backward()
        return loss

    compiled = Compiled(gradients, "the residual's step")
    before = check_psnr()  # the untrained field adds nothing
    best = {"psnr": before, "step": 0, "state": copy.deepcopy(field.state_dict()), "worse": 0}
    # learning: a score has beaten the zero field by MIN_GAIN_DB; scores: how many were taken
    state = {"learning": False, "compiled": False, "scores": 0}

    def step(p: Progress) -> None:
        for g in optim.param_groups:
            g["lr"] = g["base"] * LR_END ** p.step_share
        b = fit_ids[torch.randint(0, len(fit_ids), (batch,), generator=gen, device=device)]
        (compiled if state["compiled"] else gradients)(b)
        optim.step()
        done = p.step + 1
        if done % (every if state["learning"] else min(every, FIRST_GAP)) and done != steps:
            return
        now = check_psnr()
        state["scores"] += 1
        if now > best["psnr"]:
            best.update(psnr=now, step=done, state=copy.deepcopy(field.state_dict()), worse=0)
        else:
            best["worse"] += 1
        if not state["learning"] and best["step"] > 0 and best["psnr"] >= before + MIN_GAIN_DB:
            state["learning"] = True
            state["compiled"] = batch == BATCH * scale and steps - done >= COMPILE_FROM

    def finished() -> bool:
        if not state["learning"]:  # nothing to learn
            return state["scores"] >= PATIENCE
        return best["worse"] >= PATIENCE

    t0 = time.perf_counter()
    with messages.quiet():  # no bar of its own, as before: `residual_stage`'s note reports the fit
        done = Loop("residual", Budget(steps), step, done=finished).run()
    field.load_state_dict(best["state"])
    field.eval()
    info = {"iterations": done.steps, "planned_iterations": steps, "kept_step": best["step"], "hits": n, "batch": batch,
            "check_hits": len(check_ids), "finest_cells": int(field.finest), "prediction_spp": PREDICTION_SPP,
            "step": compiled.state if state["compiled"] else "eager", "learned": state["learning"],
            "seconds": time.perf_counter() - t0, "psnr_check_hits_before": before,
            "psnr_check_hits_after": best["psnr"]}
    return field, info


def residual_stage(run: RunDir, scene, model, pool: PixelPool, env: torch.Tensor, bounds, cfg: Config,
                   step: int) -> dict:
    """Fit the residual after the material fit's step `step`, write it (RunDir.RESIDUAL) and
    return its summary for fit.json."""
    t0 = time.perf_counter()
    field, info = fit_residual(scene, model, pool, env.detach(), bounds, cfg)
    run.save_residual(field.state_dict(), step)
    info["seconds"] = time.perf_counter() - t0  # the prediction's render included
    if math.isfinite(info["psnr_check_hits_before"]) and math.isfinite(info["psnr_check_hits_after"]):
        messages.note(f"residual: training hits {info['psnr_check_hits_before']:.2f} -> "
                      f"{info['psnr_check_hits_after']:.2f} dB PSNR (physically based -> with the residual), "
                      f"{info['seconds']:.1f} s")
    return info
