"""Residual baking (VQ-NeRF, Sec. 4): the view-dependent residual fitted after the material fit.

Materials and light are frozen, so the physically based radiance of each training hit is a
constant: it is rendered once (`PREDICTION_SPP` sample pairs, the continuous branch with the
render's bounce, as `render.views.Renderer` shades it) for up to `RESIDUAL_HITS` random hits of
the trainer's pixel pool (every hit of a capture of a few million pixels): first for the
kept-aside hits and `FIRST_SHARE` of the others, the rest once there is something to learn. The
residual field, a surface light field (`vq_mitsuba.models.residual`), is then fitted in torch
alone, without Mitsuba in the loop, to the gamma-encoded pixel colours:

    min_r  mean || enc(L_pbr(x, wi) + r(x, wi)) - enc(target) ||^2,   enc(c) = c^(1/loss.gamma)

Adam, the hash table at `LR` and the network at `LR_NET`, both decaying to `LR_END` of that over
residual.iterations steps of `BATCH` hits (fewer on a small pool: at most `MAX_EPOCHS` passes).
The finest cells of the hash encoding follow the hits (`models.residual.finest_for_hits`). The
hits of `CHECK_SHARE` of the views are kept aside (`split_check_hits`): a field that learns what
one view alone shows (its noise, its own exposure) scores well on other pixels of that view and
worse from new viewpoints, so it is scored on views it never saw. They are scored every
`steps / CHECKS` steps and the best field is kept, the untrained (zero) one included, so the
residual never makes the views it was not fitted on worse. A field kept for what it learned then
goes on for `FINISH_SHARE` of the steps over every hit, the kept-aside views' too, so that novel
views get every viewpoint the capture has (fit.json's `finish_steps`; its kept-aside scores are
those of the field it chose).
The fit stops after `PATIENCE` scores in a row below the best. Until `CONFIRM` scores in a row beat
the zero field by `MIN_GAIN_DB`, the scores come every `FIRST_GAP` steps, and when that has not
happened within the first `PATIENCE`, there is nothing to learn (a capture the physically based render already explains, such as a scene
rendered by a path tracer): the zero field is kept and the fit stops after a few seconds. A smaller
gain is not trusted: the targets' Monte Carlo noise, through the gamma encoding's curvature, pays
a brighter field a few tenths of a dB on the kept-aside hits that novel views do not confirm
(`benchmarks/results/fit_minutes/`), and a single early score above it, gone by the next, was such
noise too: a field kept there cost novel views of a lamp-lit scene 3.5 dB (`benchmarks/results/lamps/`). The step runs eagerly until then
and is compiled (`vq_mitsuba.compiled`) when `COMPILE_FROM` full batches are left, so a residual
with nothing to learn, or little to do, never waits for the compiler.

Approximate: each hit's L_pbr is one Monte Carlo estimate, not its mean, so the targets of the
residual carry that noise; neighbouring hits share the field's cells and it is fitted over many
hits, so it averages the noise out rather than learning it (fit.json's `residual` block shows
the PSNR of the kept-aside views' hits before and after, and at each score).
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
CHECK_SHARE = 0.1  # share of the views whose hits are kept aside to measure it
CHECK_MIN_VIEWS = 5  # with fewer views, CHECK_SHARE of the hits at random
CHECK_MAX_HITS = 1 << 16  # kept-aside hits scored at most (the others of their views are not fitted)
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
MIN_GAIN_DB = 0.5  # ... in CONFIRM scores in a row, which tells that there is something to learn
CONFIRM = 2
FIRST_SHARE = 0.15  # share of the fitted hits rendered (and drawn) until then, at least ...
FIRST_MIN_HITS = 1 << 17  # ... this many (all of a smaller pool)
FINISH_SHARE = 0.1  # of the planned steps: the kept field's last steps, over every hit (the kept-aside views' too)
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
                                 generator=generator, material_fn=field, views=scene.lamp_views(pool, sel)))
    return torch.cat(parts)


def split_check_hits(view: torch.Tensor, generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """(the hits fitted, the hits kept aside to score the field) of hits seen from `view` (P,),
    which come in random order: the hits of CHECK_SHARE of the views, drawn at random (at least
    one view), so that the score is that of views the field never saw; with fewer than
    CHECK_MIN_VIEWS views, CHECK_SHARE of the hits. At most CHECK_MAX_HITS are kept aside."""
    device, n = view.device, len(view)
    views = torch.unique(view)
    if len(views) >= CHECK_MIN_VIEWS:
        pick = torch.randperm(len(views), generator=generator, device=device)
        held = views[pick[:max(1, round(CHECK_SHARE * len(views)))]]
        check = torch.isin(view, held)
        fit_ids = torch.nonzero(~check).squeeze(1)
        check_ids = torch.nonzero(check).squeeze(1)  # the hits come in random order: the first CHECK_MAX_HITS
        return fit_ids, check_ids[:CHECK_MAX_HITS]
    k = min(max(1, int(CHECK_SHARE * n)), CHECK_MAX_HITS) if n > 1 else 0
    fit_ids, check_ids = torch.arange(k, n, device=device), torch.arange(k, device=device)
    return (check_ids if len(fit_ids) == 0 else fit_ids), check_ids


def fit_residual(scene, model, pool: PixelPool, env: torch.Tensor, bounds, cfg: Config) -> tuple[ResidualField, dict]:
    """The residual field fitted on the pool's hits (materials `model` and light `env` frozen),
    and its summary: hits, steps, the sRGB PSNR of the kept-aside hits before and after, and at each
    score (`checks`: steps, seconds of fitting, PSNR)."""
    device = pool.position.device
    gen = torch.Generator(device=device).manual_seed(cfg.train.seed)
    scale = device_scale()
    n = min(len(pool), RESIDUAL_HITS * scale)
    idx = torch.randperm(len(pool), generator=gen, device=device)[:n]
    target = pool.rgb[idx]
    fit_ids, check_ids = split_check_hits(pool.views_of(idx), gen)
    # the physically based radiance, rendered first for the kept-aside hits and FIRST_SHARE of the
    # fitted ones (the early steps draw from those), the rest once there is something to learn
    first = fit_ids[:max(FIRST_MIN_HITS, math.ceil(FIRST_SHARE * len(fit_ids)))]
    physical = torch.zeros(n, 3, device=device)
    head = torch.cat([check_ids, first])
    physical[head] = physical_radiance(scene, model, pool, idx[head], env, cfg, gen)
    drawn = {"ids": first}  # the fitted hits the steps draw from (all of them once there is something to learn)
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
    zero = copy.deepcopy(field.state_dict())
    best = {"psnr": before, "step": 0, "state": zero, "worse": 0}
    # learning: CONFIRM scores in a row have beaten the zero field by MIN_GAIN_DB (gains: how many in
    # a row so far); scores: how many were taken
    state = {"learning": False, "compiled": False, "scores": 0, "gains": 0}
    curve = [(0, 0.0, before)]  # (steps, seconds, kept-aside PSNR) at each score

    def step(p: Progress) -> None:
        for g in optim.param_groups:
            g["lr"] = g["base"] * LR_END ** p.step_share
        ids = drawn["ids"]
        b = ids[torch.randint(0, len(ids), (batch,), generator=gen, device=device)]
        (compiled if state["compiled"] else gradients)(b)
        optim.step()
        done = p.step + 1
        if done % (every if state["learning"] else min(every, FIRST_GAP)) and done != steps:
            return
        now = check_psnr()
        state["scores"] += 1
        curve.append((done, round(time.perf_counter() - t0, 2), now))
        if now > best["psnr"]:
            best.update(psnr=now, step=done, state=copy.deepcopy(field.state_dict()), worse=0)
        else:
            best["worse"] += 1
        state["gains"] = state["gains"] + 1 if now >= before + MIN_GAIN_DB else 0
        if not state["learning"] and state["gains"] >= CONFIRM:
            state["learning"] = True
            state["compiled"] = batch == BATCH * scale and steps - done >= COMPILE_FROM
            rest = fit_ids[len(first):]
            if len(rest):
                physical[rest] = physical_radiance(scene, model, pool, idx[rest], env, cfg, gen)
                drawn["ids"] = fit_ids

    def finished() -> bool:
        if not state["learning"]:  # nothing to learn
            return state["scores"] >= PATIENCE
        return best["worse"] >= PATIENCE

    t0 = time.perf_counter()
    with messages.quiet():  # no bar of its own, as before: `residual_stage`'s note reports the fit
        done = Loop("residual", Budget(steps), step, done=finished).run()
    if not state["learning"]:  # a gain under MIN_GAIN_DB is not trusted: the zero field is kept
        best.update(psnr=before, step=0, state=zero)
    field.load_state_dict(best["state"])
    finish_steps = 0
    if state["learning"]:
        # the kept field goes on over every hit, the kept-aside views' too: they served the choice,
        # and novel views gain from every viewpoint the field has learned
        aside = torch.ones(n, dtype=torch.bool, device=device)
        aside[fit_ids] = False
        aside[check_ids] = False  # rendered already
        rest = torch.nonzero(aside).squeeze(1)
        if len(rest):
            physical[rest] = physical_radiance(scene, model, pool, idx[rest], env, cfg, gen)
        start = best["step"] / steps  # the learning rate goes on from the kept step's to the end's
        finish_steps = max(1, round(FINISH_SHARE * steps))

        def finish(p: Progress) -> None:
            for g in optim.param_groups:
                g["lr"] = g["base"] * LR_END ** (start + (1 - start) * p.step_share)
            (compiled if state["compiled"] else gradients)(torch.randint(0, n, (batch,), generator=gen, device=device))
            optim.step()

        with messages.quiet():
            Loop("residual", Budget(finish_steps), finish).run()
    field.eval()
    info = {"iterations": done.steps, "planned_iterations": steps, "kept_step": best["step"], "hits": n, "batch": batch,
            "check_hits": len(check_ids), "rendered_hits": n if finish_steps else len(check_ids) + len(drawn["ids"]),
            "finish_steps": finish_steps,
            "finest_cells": int(field.finest), "prediction_spp": PREDICTION_SPP,
            "step": compiled.state if state["compiled"] else "eager", "learned": state["learning"],
            "seconds": time.perf_counter() - t0, "psnr_check_hits_before": before,
            "psnr_check_hits_after": best["psnr"], "checks": curve}
    return field, info


def residual_stage(run: RunDir, scene, model, pool: PixelPool, env: torch.Tensor, bounds, cfg: Config,
                   step: int) -> dict:
    """Fit the residual after the material fit's step `step`, write it (RunDir.RESIDUAL) and
    return its summary for fit.json."""
    t0 = time.perf_counter()
    field, info = fit_residual(scene, model, pool, env.detach(), bounds, cfg)
    run.save_residual(field.state_dict(), step)
    info["fit_s"], info["seconds"] = info["seconds"], time.perf_counter() - t0  # the whole stage: its render too
    if math.isfinite(info["psnr_check_hits_before"]) and math.isfinite(info["psnr_check_hits_after"]):
        messages.note(f"residual: kept-aside views {info['psnr_check_hits_before']:.2f} -> "
                      f"{info['psnr_check_hits_after']:.2f} dB PSNR (physically based -> with the residual), "
                      f"{info['seconds']:.1f} s")
    return info
