"""Fitting the continuous branch on known geometry: how the networks are trained.

Primary hits of every training pixel are traced once (geometry is fixed); each step draws a
random batch of foreground pixels across all views, evaluates the material field once per hit,
and shades through Mitsuba (vq_mitsuba.rendering). Checkpoints are written atomically and a
run resumes from its last one.
"""

from __future__ import annotations

import json
import math
import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from . import losses
from .capture.dataset import Capture, load_capture
from .capture.imageio import write_exr
from .config import Config, save_config, to_dict
from .errors import InputError, NumericalError
from .materials.fields import ContinuousMaterial, EnvironmentMap
from .materials.vq import (DiscreteBranch, choose_num_materials, dropout_rates, duplicates_last, kmeans_codebook,
                           redundant_last, sample_drop_mask, scale_gradient)

CHECKPOINT = "checkpoint.pt"
MAX_NONFINITE_RUN = 20  # non-finite steps in a row that stop a fit


@dataclass
class PixelPool:
    """Foreground training pixels with their primary hits."""

    position: torch.Tensor  # (P, 3)
    normal: torch.Tensor  # (P, 3)
    wi: torch.Tensor  # (P, 3)
    rgb: torch.Tensor  # (P, 3) linear target
    view: torch.Tensor  # (P,) view index
    pixel: torch.Tensor  # (P,) pixel index in its view (row-major)
    copy: torch.Tensor  # (P,) which of the jittered hits of that pixel

    def __len__(self) -> int:
        return self.position.shape[0]


def _without_gradients(model):
    """model as a material function whose outputs carry no gradient back into it."""
    def material(points):
        with torch.no_grad():
            return model(points)
    return material


def build_scene(mesh, env_init: np.ndarray, env_to_world: np.ndarray):
    from .rendering import ShadingScene

    return ShadingScene(mesh.vertices, mesh.faces, env_init, env_to_world, normals=mesh.vertex_normals)


def trace_training_pixels(scene, capture: Capture, alpha_threshold: float, jitter: int = 0,
                          seed: int = 0) -> tuple[PixelPool, dict]:
    """Primary hits of all views' opaque pixels: the pixel centre, or `jitter` random positions
    inside each pixel (a pixel's value is an area average; centres alias thin highlights)."""
    from .rendering import camera_rays, pixel_jitter

    rng = np.random.default_rng(seed)
    parts, n_alpha, n_hit = [], 0, 0
    for v, cam in enumerate(capture.cameras):
        opaque_np = capture.alpha[v].reshape(-1) >= alpha_threshold
        rgb = torch.as_tensor(capture.images[v].reshape(-1, 3))
        n_alpha += int(opaque_np.sum())
        for k in range(max(jitter, 1)):
            offsets = pixel_jitter(cam.width * cam.height, k, jitter, rng) if jitter > 0 else None
            o, d = camera_rays(cam, offsets)
            hits = scene.trace(o, d)
            keep = hits.valid & torch.as_tensor(opaque_np, device=hits.valid.device)
            if k == 0:
                n_hit += int(keep.sum())
            n_keep = int(keep.sum())
            parts.append((hits.position[keep], hits.normal[keep], hits.wi[keep], rgb.to(keep.device)[keep],
                          torch.full((n_keep,), v, dtype=torch.int64),
                          torch.nonzero(keep)[:, 0].cpu(), torch.full((n_keep,), k, dtype=torch.int64)))
    cat = [torch.cat(x) for x in zip(*parts)]
    pool = PixelPool(*cat)
    stats = {"opaque_pixels": n_alpha, "used_pixels": n_hit,
             "geometry_coverage": n_hit / max(n_alpha, 1)}
    return pool, stats


def _first_hits(pool: PixelPool, width: int, height: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(pool indices of the pixels' first hits, their pixel keys view * W * H + pixel, and a lookup
    from any pixel key to its first hit's pool index, -1 where the pixel has none)."""
    first = torch.nonzero(pool.copy == 0)[:, 0]
    key = pool.view[first] * (width * height) + pool.pixel[first]
    n_keys = int(pool.view.max()) + 1 if len(pool) else 0
    lookup = torch.full((n_keys * width * height,), -1, dtype=torch.int64)
    lookup[key] = first
    return first, key, lookup


def footprint_table(pool: PixelPool, width: int, height: int, jitter: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Pool indices of each training pixel's first hit (R,) and of all its jittered hits (R, K),
    K = max(jitter, 1); a jittered hit that missed the mesh is replaced by the first one."""
    first, _, lookup = _first_hits(pool, width, height)
    row_of = torch.full((len(pool),), -1, dtype=torch.int64)
    row_of[first] = torch.arange(len(first))
    fi = lookup[pool.view * (width * height) + pool.pixel]  # each hit's pixel's first hit
    ok = fi >= 0
    table = first[:, None].repeat(1, max(jitter, 1))
    table[row_of[fi[ok]], pool.copy[ok]] = torch.nonzero(ok)[:, 0]
    return first, table


def neighbour_pairs(pool: PixelPool, width: int, height: int) -> torch.Tensor:
    """(Q, 2) pool indices of horizontally or vertically adjacent training pixels (first hits)."""
    first, key, lookup = _first_hits(pool, width, height)
    x = pool.pixel[first] % width
    y = pool.pixel[first] // width
    pairs = []
    for ok, step in ((x < width - 1, 1), (y < height - 1, width)):
        a = first[ok]
        b = lookup[key[ok] + step]
        pairs.append(torch.stack([a[b >= 0], b[b >= 0]], -1))
    return torch.cat(pairs)


def parse_snapshot_times(text: str) -> list[float]:
    """`train.snapshot_s` ("30,60,120") as sorted seconds."""
    try:
        times = sorted(float(t) for t in str(text).replace(";", ",").split(",") if t.strip())
    except ValueError:
        raise InputError(None, f"train.snapshot_s expects comma-separated seconds, got '{text}'") from None
    if any(t <= 0 for t in times):
        raise InputError(None, f"train.snapshot_s expects positive seconds, got '{text}'")
    return times


def _atomic_save(obj, path: Path) -> None:
    tmp = path.with_suffix(path.suffix + ".tmp")
    torch.save(obj, tmp)
    os.replace(tmp, path)


def _write_json(path: Path, data: dict) -> None:
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(data, indent=2))
    os.replace(tmp, path)


class Run:
    """A run directory: config, capture info, checkpoint; what render/eval read back."""

    def __init__(self, run_dir: str | Path):
        self.dir = Path(run_dir)

    @property
    def checkpoint_path(self) -> Path:
        return self.dir / CHECKPOINT

    def info(self) -> dict:
        path = self.dir / "run.json"
        if not path.is_file():
            raise InputError(path, "not a fitted run directory (run.json missing); run `vq-mitsuba fit` first")
        return json.loads(path.read_text())


def fit(capture_path: str | Path, run_dir: str | Path, cfg: Config, mesh_path: str | Path | None = None,
        resume: bool = False, progress: bool = True) -> dict:
    """Fit materials and lighting; returns the summary written to RUN_DIR/fit.json."""
    from tqdm import tqdm

    from .rendering import init_mitsuba, torch_device

    run_dir = Path(run_dir)
    ckpt_path = run_dir / CHECKPOINT
    snap_times = parse_snapshot_times(cfg.train.snapshot_s)
    if ckpt_path.exists() and not resume:
        raise InputError(run_dir, "already holds a fitted run: pass --resume to continue it, or choose another -o")
    if resume and not ckpt_path.exists():
        if not run_dir.is_dir():
            raise InputError(run_dir, "no run to resume (the folder does not exist)")
        # Interrupted before the first checkpoint (e.g. right after the geometry stage): start the
        # material fit from the beginning, keeping what the folder already holds (mesh.ply).
        print(f"{ckpt_path}: no checkpoint yet; the material fit starts from the beginning")
        resume = False

    capture = load_capture(capture_path, mesh=mesh_path)  # every input check happens here, first
    if capture.mesh is None:
        raise InputError(capture.source, "no known geometry: the capture has no shapes and no mesh "
                         "(pass --mesh PATH, put mesh.ply beside the json, or reconstruct it from masked images "
                         "with `fit --geometry neus` or `vq-mitsuba geometry`)")
    torch.manual_seed(cfg.train.seed)
    np.random.seed(cfg.train.seed)
    init_mitsuba()
    device = torch_device()
    run_dir.mkdir(parents=True, exist_ok=True)
    save_config(cfg, run_dir / "config.yaml")
    capture.mesh.export(run_dir / "mesh.ply")

    mean_fg = float(np.mean(capture.images[capture.alpha >= cfg.train.alpha_threshold])) if capture.has_alpha \
        else float(np.mean(capture.images))
    learn_env = capture.envmap is None
    if learn_env:
        env_module = EnvironmentMap(cfg.envmap.height, cfg.envmap.init_scale * max(mean_fg, 1e-3)).to(device)
        env_init = env_module().detach().cpu().numpy()
    else:
        env_init = capture.envmap
    scene = build_scene(capture.mesh, env_init, capture.envmap_to_world)
    pool, stats = trace_training_pixels(scene, capture, cfg.train.alpha_threshold, cfg.train.pixel_jitter,
                                        cfg.train.seed)
    if len(pool) == 0:
        raise InputError(capture.source, "no training pixel hits the geometry: check the cameras, the mesh and the alpha masks")
    if stats["geometry_coverage"] < 0.9:
        print(f"warning: only {100 * stats['geometry_coverage']:.1f}% of opaque pixels hit the mesh; "
              "the geometry may not match the images (units, world axes?)")
    _write_json(run_dir / "run.json", {
        "capture": str(Path(capture.source).resolve()),
        "world": capture.world,
        "envmap_to_world": np.asarray(capture.envmap_to_world).tolist(),
        "learned_envmap": learn_env,
        "n_views": len(capture.cameras),
        **stats,
    })

    bbox = torch.tensor(np.asarray(capture.mesh.bounds), dtype=torch.float32)
    model = ContinuousMaterial(cfg.field, bbox[0], bbox[1]).to(device)
    discrete = DiscreteBranch(cfg.field, cfg.vq.num_codes, cfg.vq.decay, cfg.vq.commitment).to(device) \
        if cfg.vq.enabled else None
    groups = [{"params": model.parameters(), "lr": cfg.train.lr}]
    if discrete is not None:
        groups.append({"params": discrete.parameters(), "lr": cfg.train.lr})
    if learn_env:
        groups.append({"params": env_module.parameters(), "lr": cfg.envmap.lr})
    optim = torch.optim.Adam(groups)
    total = cfg.train.iterations
    base_lrs = [g["lr"] for g in optim.param_groups]  # decayed during training (below)
    gen = torch.Generator(device=device).manual_seed(cfg.train.seed)
    history: list[dict] = []
    step, elapsed_before = 0, 0.0

    if resume:
        state = torch.load(ckpt_path, map_location=device, weights_only=False)
        model.load_state_dict(state["model"])
        if discrete is not None:
            discrete.load_state_dict(state["discrete"])
        if learn_env:
            env_module.load_state_dict(state["envmap"])
        optim.load_state_dict(state["optim"])
        gen.set_state(state["generator"])
        history, step, elapsed_before = state["history"], state["step"], state["elapsed_s"]
        if step >= total:
            print(f"{run_dir}: already fitted ({step} of {total} iterations); nothing to do")

    def fitted_state(elapsed: float) -> dict:  # what rendering and scoring need
        return {
            "model": model.state_dict(),
            "discrete": discrete.state_dict() if discrete is not None else None,
            "envmap": env_module.state_dict() if learn_env else None,
            "envmap_fixed": None if learn_env else torch.as_tensor(capture.envmap),
            "step": step, "elapsed_s": elapsed, "config": to_dict(cfg),
        }

    def checkpoint(elapsed: float) -> None:  # plus what resuming needs
        _atomic_save({**fitted_state(elapsed), "optim": optim.state_dict(), "generator": gen.get_state(),
                      "history": history}, ckpt_path)

    def snapshot(elapsed: float) -> None:  # the state as it is now, for scoring later (no optimiser)
        (run_dir / "snapshots").mkdir(exist_ok=True)
        _atomic_save(fitted_state(elapsed), run_dir / "snapshots" / f"t{elapsed:07.1f}s_step{step:06d}.pt")

    snap_times = [t for t in snap_times if t > elapsed_before]
    fixed_env = None if learn_env else torch.as_tensor(capture.envmap, device=device)
    start_step = step
    t0 = time.perf_counter()
    bar = tqdm(total=total, initial=step, desc="fit", disable=not progress, dynamic_ncols=True)
    loss_acc, mse_acc, n_acc = 0.0, 0.0, 0
    nonfinite_steps, nonfinite_run = 0, 0
    B = min(cfg.train.batch_rays, len(pool))
    rates = dropout_rates(cfg.vq.num_codes, cfg.vq.dropout_max, cfg.vq.protected).to(device)
    t_limit = cfg.train.time_limit_s
    pairs = neighbour_pairs(pool, capture.width, capture.height).to(device) if cfg.loss.w_sm > 0 else None
    groups_mc = 2 if cfg.loss.decorrelated else 1
    if cfg.train.footprint:  # a pixel's samples spread over its jittered hits: the loss sees pixel averages
        first_hits, hit_table = (t.to(device) for t in footprint_table(pool, capture.width, capture.height,
                                                                      cfg.train.pixel_jitter))

    per_hit = cfg.train.footprint and cfg.train.footprint_per_hit

    def shading_material(o):  # (basecolor, metallic, roughness) per pixel, or (B, K, ...) per hit
        if not per_hit:
            return o["basecolor"], o["metallic"], o["roughness"]
        k = hit_table.shape[1]
        return o["basecolor"].view(-1, k, 3), o["metallic"].view(-1, k), o["roughness"].view(-1, k)

    def rec_loss(samples, target):
        if cfg.loss.decorrelated:
            return losses.reconstruction_l2_decorrelated(samples, target, cfg.loss.gamma)
        return losses.reconstruction_l2(samples.mean(1), target, cfg.loss.gamma)

    def lambertian(out, frac, gate=1.0):  # L_lam of a branch's output at training progress frac (gate: the metallic gate it was made with)
        barrier = cfg.loss.metallic_barrier and frac < cfg.loss.metallic_barrier_until
        logit = out.get("metallic_logit") if barrier else None
        return losses.lambertian_prior(out["metallic"], out["roughness"], cfg.loss.lam_metallic, logit, gate)

    while step < total:
        # Training progress in [0, 1] drives the schedules (encoding frequencies, metallic delay,
        # Lambertian prior, VQ warm-up): the share of iterations done or, under a time limit, of
        # the time used if larger, so that a fit stopped by the clock has run its whole schedule.
        # The learning rates follow the iterations alone (train.lr_decay_iterations): a short
        # budget's few steps need a large rate more than a finished schedule.
        done = step / max(total, 1)  # the share of iterations done
        frac = done
        if t_limit > 0:
            frac = min(max(done, (elapsed_before + time.perf_counter() - t0) / t_limit), 1.0)
        lr_frac = done if cfg.train.lr_decay_iterations else frac
        for g, lr in zip(optim.param_groups, base_lrs):
            g["lr"] = lr * cfg.train.lr_decay ** lr_frac
        w_lam = cfg.loss.w_lam * cfg.loss.lam_decay ** frac  # continuous branch's prior
        w_lam_d = cfg.loss.w_lam * cfg.vq.lam_decay ** frac  # discrete branch's prior
        if discrete is not None and frac >= cfg.vq.warmup_frac and not bool(discrete.initialised):
            with torch.no_grad():  # codebook from k-means of the warmed-up latents
                sub = torch.randint(0, len(pool), (min(20000, len(pool)),), generator=gen, device=device)
                z_warm = model(pool.position[sub])["z"]
                discrete.vq.init_codebook(kmeans_codebook(z_warm, cfg.vq.num_codes, cfg.train.seed))
                if cfg.vq.warm_start_decoder:
                    discrete.warm_start(model.decoder, z_warm)
                discrete.initialised.fill_(True)
        if cfg.train.footprint:
            rows = torch.randint(0, len(first_hits), (B,), generator=gen, device=device)
            idx, hit_idx = first_hits[rows], hit_table[rows]  # (B,), (B, K)
        else:
            idx = torch.randint(0, len(pool), (B,), generator=gen, device=device)
            hit_idx = idx
        model.set_progress(frac, cfg.field.pe_anneal, cfg.field.metallic_delay,
                           pe_fraction=done if cfg.field.pe_anneal_iterations else None)
        # The material at each hit of the footprint, or at the pixel's first hit for all of them.
        out = model(pool.position[hit_idx.reshape(-1) if per_hit else idx])
        env = env_module() if learn_env else fixed_env
        bounce = cfg.train.bounces > 0 and step >= cfg.train.bounce_after
        samples = scene.shade(pool.position[hit_idx], pool.normal[hit_idx], pool.wi[hit_idx], *shading_material(out),
                              env, cfg.train.spp, generator=gen, reduce=False,
                              material_fn=model if bounce else None, groups=groups_mc)
        rgb = samples.mean(1)
        target = pool.rgb[idx]
        l_rec = rec_loss(samples, target)
        l_lam = lambertian(out, frac, float(model.metallic_gate))
        discrete_on = discrete is not None and bool(discrete.initialised)
        w_rec_c = 0.0 if discrete_on and cfg.vq.single_branch else cfg.loss.w_rec_c
        loss = w_rec_c * l_rec + w_lam * l_lam
        if discrete_on:
            z = scale_gradient(out["z"], cfg.vq.joint_scale) if cfg.vq.joint else out["z"].detach()
            drop = sample_drop_mask(z.shape[0], rates, gen) if cfg.vq.ranking else None
            od = discrete(z, drop, forced_gradient=cfg.vq.forced_gradient)
            # The bounce is lit by the continuous field (cheaper; the codebook sees primary hits only).
            # With light_from_continuous the discrete loss leaves the light (envmap, bounce) to the
            # continuous branch: a few materials cannot explain a texture, and their 5x-weighted
            # residual would otherwise bend the shared light (and through it the continuous field).
            frozen = cfg.vq.light_from_continuous
            env_d = env.detach() if frozen else env
            bounce_fn = None
            if bounce:
                bounce_fn = _without_gradients(model) if frozen else model
            samples_d = scene.shade(pool.position[hit_idx], pool.normal[hit_idx], pool.wi[hit_idx],
                                    *shading_material(od), env_d, cfg.train.spp, generator=gen,
                                    reduce=False, material_fn=bounce_fn, groups=groups_mc)
            loss = loss + cfg.loss.w_rec_d * rec_loss(samples_d, target) \
                + (0.0 if cfg.vq.single_branch else cfg.loss.w_chr) * losses.chromaticity_loss(od["basecolor"], out["basecolor"]) \
                + cfg.loss.w_vq * od["vq_loss"] \
                + w_lam_d * lambertian(od, frac)
        if pairs is not None and len(pairs) > 0:
            pick = pairs[torch.randint(0, len(pairs), (max(B // 4, 1),), generator=gen, device=device)]
            oa, ob = model(pool.position[pick[:, 0]]), model(pool.position[pick[:, 1]])
            ia = losses.encode_gamma(pool.rgb[pick[:, 0]], cfg.loss.gamma)
            ib = losses.encode_gamma(pool.rgb[pick[:, 1]], cfg.loss.gamma)
            loss = loss + cfg.loss.w_sm * losses.colour_aware_smoothness(oa, ob, ia, ib, cfg.loss.sm_alpha,
                                                                         cfg.loss.sm_beta)
        if learn_env and cfg.envmap.tv_weight > 0:
            loss = loss + cfg.envmap.tv_weight * env_module.smoothness()
        optim.zero_grad(set_to_none=True)
        loss.backward()
        # A step whose loss or gradients are not finite (a rare Monte Carlo sample can overflow)
        # is dropped rather than written into every parameter; many in a row stop the fit.
        grads = [p.grad for g in optim.param_groups for p in g["params"] if p.grad is not None]
        finite = bool(torch.isfinite(loss)) and bool(torch.stack([torch.isfinite(g).all() for g in grads]).all())
        step += 1
        if not finite:
            nonfinite_steps += 1
            nonfinite_run += 1
            if nonfinite_steps == 1:
                print(f"warning: step {step}: loss or gradients not finite; the step is skipped")
            if nonfinite_run >= MAX_NONFINITE_RUN:
                bar.close()
                checkpoint(elapsed_before + time.perf_counter() - t0)
                raise NumericalError(run_dir, f"steps {step - nonfinite_run + 1} to {step} all gave a non-finite "
                                     f"loss or gradient; the checkpoint (step {step}) keeps the parameters of "
                                     f"step {step - nonfinite_run}, the last finite one; try a lower train.lr, "
                                     "or --resume with another train.seed")
            bar.update(1)
            continue
        nonfinite_run = 0
        optim.step()
        with torch.no_grad():
            mse = float(losses.srgb_mse(rgb.detach(), target))
        loss_acc, mse_acc, n_acc = loss_acc + float(loss.detach()), mse_acc + mse, n_acc + 1
        if step % cfg.train.log_every == 0 or step == total:
            elapsed = elapsed_before + time.perf_counter() - t0
            history.append({"step": step, "seconds": elapsed, "loss": loss_acc / n_acc,
                            "psnr": losses.psnr(mse_acc / n_acc)})
            bar.set_postfix(loss=f"{loss_acc / n_acc:.4g}", psnr=f"{history[-1]['psnr']:.2f}")
            loss_acc, mse_acc, n_acc = 0.0, 0.0, 0
        bar.update(1)
        elapsed = elapsed_before + time.perf_counter() - t0
        if step % cfg.train.checkpoint_every == 0:
            checkpoint(elapsed)
        if snap_times and elapsed >= snap_times[0]:
            while snap_times and elapsed >= snap_times[0]:
                snap_times.pop(0)
            t_write = time.perf_counter()
            snapshot(elapsed)
            t0 += time.perf_counter() - t_write  # the fit's clock does not count the copy
        if cfg.train.time_limit_s > 0 and elapsed >= cfg.train.time_limit_s:
            print(f"time limit of {cfg.train.time_limit_s:.0f} s reached at step {step}")
            break
    bar.close()
    elapsed = elapsed_before + time.perf_counter() - t0
    checkpoint(elapsed)

    env_final_t = (env_module() if learn_env else fixed_env).detach()
    if discrete is not None and bool(discrete.initialised):
        rank_materials(scene, model, discrete, pool, env_final_t, cfg, run_dir)
        checkpoint(elapsed)
    env_final = env_final_t.cpu().numpy()
    write_exr(run_dir / "envmap.exr", env_final)
    plot_history(history, run_dir / "loss.png")
    summary = {"iterations": step, "seconds": elapsed,
               "iterations_per_s": step / elapsed if elapsed > 0 else math.nan,
               "final_psnr_train_batch": history[-1]["psnr"] if history else None,
               "training_pixels": len(pool), "steps_this_call": step - start_step,
               "nonfinite_steps_skipped": nonfinite_steps}
    _write_json(run_dir / "fit.json", summary)
    return summary


@torch.no_grad()
def rank_materials(scene, model, discrete, pool: PixelPool, env: torch.Tensor, cfg: Config, run_dir: Path) -> dict:
    """Dropout-based ranking (Sec. III-D): err_k of the discrete branch restricted to the first k
    codewords, k = 1..M0, on a fixed set of training pixels; M = the first k within epsilon of
    every longer prefix. Writes materials.json and materials_err.png."""
    gen = torch.Generator(device=pool.position.device).manual_seed(cfg.train.seed + 1)
    n = min(cfg.vq.rank_pixels, len(pool))
    sel = torch.randperm(len(pool), generator=gen, device=pool.position.device)[:n]
    z = model(pool.position[sel])["z"]
    was_training = discrete.training
    discrete.eval()
    errs, usage = [], []
    K = cfg.vq.num_codes
    # Codewords that (almost) no pixel picks are not materials: move them behind the used ones,
    # keeping the dropout order otherwise, so that they do not sit inside the ranked prefix.
    share = torch.bincount(discrete(z)["index"], minlength=K).float() / max(n, 1)
    used = share >= cfg.vq.min_share
    order = torch.cat([torch.nonzero(used)[:, 0], torch.nonzero(~used)[:, 0]])
    # Codewords that decode to the same material as a higher-ranked one go behind the distinct ones.
    ranked, n_distinct = duplicates_last(discrete.codeword_brdfs(), order.tolist(), int(used.sum()), cfg.vq.merge_tol)
    current = list(range(K))  # training index of the codeword now at each position

    def measure(rank: list[int]) -> list[float]:  # err_k of the prefixes of `rank` (training indices)
        nonlocal usage, current
        discrete.vq.reorder(torch.as_tensor([current.index(i) for i in rank], device=z.device))
        current = list(rank)
        errs_k = []
        for k in range(1, K + 1):
            od = discrete(z, n_codes=k)
            g = torch.Generator(device=pool.position.device).manual_seed(cfg.train.seed + 2)  # same samples for every k
            rgb = scene.shade(pool.position[sel], pool.normal[sel], pool.wi[sel], od["basecolor"], od["metallic"],
                              od["roughness"], env, 16, generator=g, groups=1)
            errs_k.append(float(losses.reconstruction_l2(rgb, pool.rgb[sel], cfg.loss.gamma)))
            if k == K:
                usage = torch.bincount(od["index"], minlength=K).float() / n
        return errs_k

    redundant = []
    if cfg.vq.ranking and cfg.vq.redundant_last:
        ranked, errs, redundant = redundant_last(measure, ranked, cfg.vq.rank_eps, n_keep=n_distinct)
    else:
        errs = measure(ranked)
    order = torch.as_tensor(ranked, device=order.device)
    M = choose_num_materials(errs, cfg.vq.rank_eps) if cfg.vq.ranking else K
    M = max(1, min(M, n_distinct)) if cfg.vq.ranking else M
    discrete.num_materials.fill_(M)
    discrete.train(was_training)
    brdf = discrete.codeword_brdfs()
    final = discrete(z, n_codes=M)["index"]
    usage_m = torch.bincount(final, minlength=K).float() / n
    materials = [{"id": k + 1, "basecolor": brdf["basecolor"][k].tolist(), "metallic": float(brdf["metallic"][k]),
                  "roughness": float(brdf["roughness"][k]), "pixel_fraction": float(usage_m[k]),
                  "pixel_fraction_all_codewords": float(usage[k])} for k in range(K)]
    info = {"num_materials": M, "num_codewords": K, "epsilon": cfg.vq.rank_eps, "ranking": cfg.vq.ranking,
            "min_share": cfg.vq.min_share, "codewords_used": int(used.sum()),
            "merge_tol": cfg.vq.merge_tol, "codewords_distinct": n_distinct,
            "training_order": order.tolist(), "redundant_codewords": redundant,
            "err_k": errs, "materials": materials[:M], "dropped_codewords": materials[M:],
            "note": "materials are ranked codewords (id k = k-th); basecolor in linear RGB; err_k is the "
                    "discrete branch's gamma-space L2 on training pixels using the first k codewords"}
    _write_json(run_dir / "materials.json", info)
    plot_err_k(errs, M, cfg.vq.rank_eps, run_dir / "materials_err.png")
    return info


def plot_err_k(errs: list[float], chosen: int, eps: float, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ks = list(range(1, len(errs) + 1))
    fig, ax = plt.subplots(figsize=(4.5, 3.2))
    ax.plot(ks, errs, "o-")
    ax.axvline(chosen, color="tab:red", linestyle="--", label=f"M = {chosen}")
    ax.axhspan(min(errs), min(errs) + eps, color="tab:green", alpha=0.15, label=f"min + epsilon ({eps:g})")
    ax.set_xlabel("k (first k ranked codewords)")
    ax.set_ylabel("err_k")
    ax.set_title("material count by dropout ranking")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def plot_history(history: list[dict], path: Path) -> None:
    if not history:
        return
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    steps = [h["step"] for h in history]
    fig, ax = plt.subplots(1, 2, figsize=(9, 3.2))
    ax[0].semilogy(steps, [h["loss"] for h in history])
    ax[0].set_xlabel("iteration"); ax[0].set_ylabel("loss"); ax[0].set_title("training loss")
    ax[1].plot(steps, [h["psnr"] for h in history])
    ax[1].set_xlabel("iteration"); ax[1].set_ylabel("PSNR (dB, sRGB)"); ax[1].set_title("training-batch PSNR")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
