"""Training NeuS (its step, optimiser, checkpoint and schedule on the loop skeleton) and
`reconstruct`: a model for a loaded capture (`rays.neus_for`), trained, its mesh extracted and its
summary gathered; the geometry stage (`vq_mitsuba.geometry.stage`) writes them into the run."""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from vq_mitsuba.backend import device_record
from vq_mitsuba.compiled import Compiled
from vq_mitsuba.config import NeuSConfig
from vq_mitsuba.errors import InputError
from vq_mitsuba.geometry.neus import CHECKPOINT, grid_kernel
from vq_mitsuba.geometry.neus.mesh_export import extract_mesh
from vq_mitsuba.geometry.neus.rays import neus_for, render_view
from vq_mitsuba.geometry.neus.renderer import NeuS, _threads, encode_srgb
from vq_mitsuba.geometry.neus.sampling import RaySampler
from vq_mitsuba.run.loop import Budget, Loop, Progress
from vq_mitsuba.run.run_dir import RunDir, save_torch


# The SDF-is-zero term at sparse points is Cauchy-robust with scale POINTS_SCALE (box units): a point
# at distance d pulls with 1 / (1 + d / POINTS_SCALE) of the strength of one on the surface, so an
# outlier SfM left pulls little; POINTS_FAR (1 % of the box's side): a point the final SDF puts further
# from its zero set is reported as not taken by the surface.
POINTS_SCALE, POINTS_FAR = 0.05, 0.02
HISTORY_EVERY = 10  # steps between reads of the losses from the device (and progress-bar updates)
# The step runs compiled (`NeuS.training_step` under torch.compile) when at least COMPILE_FROM steps
# are left: compiling costs about 15 s the first time on 2 cores (3 s from the cache) and a compiled
# step saves about a tenth of a 25 ms step, so a shorter stage would not earn back a first compile
# (benchmarks/results/compiled/).
COMPILE_FROM = 6000
# Without a step limit, the step runs compiled when the time budget is at least COMPILE_FROM_S seconds.
COMPILE_FROM_S = 200.0
# The plateau check (neus.plateau_s): HELD_ASIDE training rays never drawn, rendered CHECKS times
# in every neus.plateau_s training seconds once the finer grid levels are all open; training ends
# when their PSNR gained under PLATEAU_DB over neus.plateau_s seconds, after ANNEAL of the seconds
# done more with the learning rate decaying to its end (a clock-stopped rate left high renders worse).
HELD_ASIDE, CHECKS, PLATEAU_DB, ANNEAL = 4096, 4, 0.05, 0.15


def lr_factor(cfg: NeuSConfig, step: int, prog: float) -> float:
    warm = min(1.0, (step + 1) / max(cfg.warmup, 1))
    cos = 0.5 * (1.0 + math.cos(math.pi * prog))
    return warm * (cfg.lr_end_cosine + (1.0 - cfg.lr_end_cosine) * cos)


# Keys that shape the networks: a checkpoint resumes only under the same values. A checkpoint
# written before a key existed was made with the value given here.
_ARCHITECTURE = {"levels": None, "base_res": None, "max_res": None, "features": None, "hidden": None,
                 "geo_features": None, "reflect": False, "hash_log2": None, "sdf_layers": 2}


def check_architecture(path: Path, saved: dict, cfg: NeuSConfig) -> None:
    diff = []
    for key, before in _ARCHITECTURE.items():
        now = getattr(cfg, key)
        then = saved.get(key, now if before is None else before)
        if then != now:
            diff.append(f"neus.{key}={then} (now {now})")
    if diff:
        raise InputError(path, "this NeuS checkpoint was made with " + ", ".join(diff) + "; resume with "
                         "the same values (--set neus.KEY=VALUE), or start over without --resume")


def train(neus: NeuS, run: RunDir | None = None, resume: bool = False,
          callback=None, callback_every_s: float = 0.0) -> dict:
    """Optimise the NeuS model; returns a summary. `callback(neus, step, train_seconds)` is called
    every `callback_every_s` seconds of training (its own time is not counted)."""

    with _threads(neus.cfg.threads):
        return NeuSTraining(neus, run).run(resume, callback, callback_every_s)


class NeuSTraining:
    """NeuS's step, optimiser and checkpoint for the loop skeleton (`vq_mitsuba.run.loop`). The
    finer grid levels fade in with the share of whichever budget runs out first, so a clock-stopped
    run has opened them all; the learning rate follows the step share alone, so a run that the
    clock stops early keeps a large rate (benchmarks/results/neus_step_decay/)."""

    def __init__(self, neus: NeuS, run: RunDir | None):
        cfg = self.cfg = neus.cfg
        self.neus, self.model = neus, neus.model
        model = neus.model
        mlp = [p for name, p in model.sdf.named_parameters() if not name.startswith("encoding")]
        background = list(model.background.parameters()) if model.background is not None else []
        groups = [{"params": list(model.sdf.encoding.parameters()) + list(model.color.parameters()) + background,
                   "base_lr": cfg.lr},
                  {"params": mlp, "base_lr": cfg.lr_sdf_mlp},
                  {"params": [model.variance], "base_lr": cfg.lr_variance}]
        self.optim = torch.optim.Adam([dict(g, lr=g["base_lr"]) for g in groups], betas=(0.9, 0.99), eps=1e-15,
                                      fused=True)
        self.device = neus.device
        self.gen = torch.Generator(device=self.device).manual_seed(cfg.seed)  # the batches' rays
        torch.manual_seed(cfg.seed)  # the samples' jitter (every device's generator)
        self.step, self.elapsed, self.history = 0, 0.0, []
        # (step, seconds, the step's losses as one device tensor): read into history every
        # HISTORY_EVERY steps, so that a step never waits for the device
        self.pending: list[tuple[int, float, torch.Tensor]] = []
        self.ckpt = run / CHECKPOINT if run is not None else None
        self.sampler = RaySampler(len(neus.rays_o), HELD_ASIDE if cfg.plateau_s > 0 else 0, self.gen, self.device)
        # the plateau check: [(training seconds, held-aside PSNR)], the next check's time, and once
        # the plateau is reached (seconds, schedule share) where the final decay started
        self.checks: list[tuple[float, float]] = []
        self.next_check = cfg.plateau_s / CHECKS
        self.anneal: tuple[float, float] | None = None

    def resume(self) -> None:
        if self.ckpt is None or not self.ckpt.is_file():
            return
        state = RunDir(self.ckpt.parent).load_state(self.ckpt, "cpu")
        check_architecture(self.ckpt, state.get("config") or {}, self.cfg)
        if state.get("background_model", False) != self.neus.box.mask_free:
            made = "without masks (neus.background model)" if state.get("background_model") else "with masks"
            raise InputError(self.ckpt, f"this NeuS checkpoint was made {made}, this capture and neus.background "
                                        "ask for the other; resume with the same setting, or start over without "
                                        "--resume")
        self.model.load_state_dict(state["model"])  # copied onto the model's device
        self.optim.load_state_dict(state["optim"])
        self.step, self.elapsed, self.history = state["step"], state["elapsed"], state["history"]
        plateau = state.get("plateau") or {}
        self.checks = [tuple(c) for c in plateau.get("checks", [])]
        self.next_check = plateau.get("next_check", self.cfg.plateau_s / CHECKS)
        self.anneal = tuple(plateau["anneal"]) if plateau.get("anneal") else None
        try:
            self.gen.set_state(state["generator"].cpu())  # CPU bytes on any device
        except RuntimeError:  # the generator of the other device kind: a new stream, seeded by the step
            self.gen.manual_seed(self.cfg.seed + self.step)
        torch.set_rng_state(state["torch_rng"].cpu())
        if self.device.type == "cuda" and state.get("cuda_rng") is not None:
            torch.cuda.set_rng_state(state["cuda_rng"].cpu(), self.device)

    def plan_compile(self) -> None:
        """Run the steps compiled when COMPILE_FROM or more are left (without a step limit: when
        COMPILE_FROM_S seconds or more are)."""
        cfg = self.cfg
        left = (cfg.iterations - self.step >= COMPILE_FROM if cfg.iterations
                else cfg.time_limit_s - self.elapsed >= COMPILE_FROM_S)
        if left:
            self.neus.compiled_step = Compiled(self.neus.training_step, "NeuS's step", data_dependent_shapes=True)

    def save(self, p: Progress) -> None:
        self.read_history()
        if self.ckpt is not None:
            extra = {"cuda_rng": torch.cuda.get_rng_state(self.device)} if self.device.type == "cuda" else {}
            save_torch({"model": self.model.state_dict(), "optim": self.optim.state_dict(),
                        "generator": self.gen.get_state(), "torch_rng": torch.get_rng_state(), "step": p.step,
                        "elapsed": p.seconds, "history": self.history, "config": asdict(self.cfg),
                        "background_model": self.neus.box.mask_free,
                        "plateau": {"checks": self.checks, "next_check": self.next_check, "anneal": self.anneal},
                        **extra}, self.ckpt)

    def read_history(self) -> None:
        """The pending steps' losses, read from the device at once (one small tensor), into history."""
        if not self.pending:
            return
        values = torch.stack([v for _, _, v in self.pending]).cpu().tolist()
        for (step, seconds, _), (loss, color, eikonal, mask, mse, s, points) in zip(self.pending, values):
            self.history.append({"step": step, "seconds": seconds, "loss": loss, "color": color, "eikonal": eikonal,
                                 "mask": mask, "psnr": -10.0 * math.log10(max(mse, 1e-10)), "s": s,
                                 "points": points})
        self.pending = []

    def _points_loss(self, lw: list[float]) -> torch.Tensor:
        """The mean Cauchy-robust |SDF| (scale POINTS_SCALE) at a batch of the sparse surface points
        (`NeuS.surface_points`): a point the SDF puts far away (an outlier SfM left, or a part the
        colour disagrees with) pulls weakly; zero without points."""
        pts = self.neus.surface_points
        if pts is None:
            return torch.zeros((), device=self.device)
        pick = torch.randint(0, len(pts), (min(self.cfg.batch_rays, len(pts)),), generator=self.gen,
                             device=self.device)
        distance = self.model.sdf(pts[pick], lw)[0].abs()
        return (POINTS_SCALE * torch.log1p(distance / POINTS_SCALE)).mean()

    def schedule_share(self, p: Progress) -> float:
        """Where the learning rate stands in its decay: the share of the steps (with a step limit) or
        of the seconds; once the plateau is reached, from there to the end over the final decay."""
        share = p.step_share if self.cfg.iterations else p.time_share
        if self.anneal is not None:
            start_s, start_share = self.anneal
            span = max(ANNEAL * start_s, self.cfg.plateau_s / CHECKS)
            share = start_share + (1.0 - start_share) * (p.seconds - start_s) / span
        return min(max(share, 0.0), 1.0)

    def done(self) -> bool:
        """True once the final decay after the plateau has run its course."""
        return self.anneal is not None and self.schedule_share(self.loop.progress()) >= 1.0

    @torch.no_grad()
    def held_aside_psnr(self, lw: list[float], chunk: int = 4096) -> float:
        """NeuS's render of the held-aside rays against their colours: sRGB PSNR."""
        neus, err = self.neus, []
        for idx in self.sampler.held.split(chunk):
            o, d = neus.rays_o[idx], neus.rays_d[idx]
            out = neus.render(o, d, lw, self.cfg.n_samples, False, False)
            err.append(((out["rgb"] - neus.rays_rgb[idx]) ** 2).mean(-1))
        return -10.0 * math.log10(max(float(torch.cat(err).mean()), 1e-10))

    def check_plateau(self, p: Progress, lw: list[float]) -> None:
        """CHECKS times every neus.plateau_s seconds once every grid level is open: score the
        held-aside rays, and start the final decay when they gained under PLATEAU_DB over
        neus.plateau_s seconds."""
        cfg = self.cfg
        if cfg.plateau_s <= 0 or len(self.sampler.held) == 0 or p.seconds < self.next_check:
            return
        self.next_check = p.seconds + cfg.plateau_s / CHECKS
        if p.share < cfg.coarse_to_fine or self.anneal is not None:
            return
        psnr = self.held_aside_psnr(lw)
        self.checks.append((round(p.seconds, 2), psnr))
        before = [v for t, v in self.checks if t <= p.seconds - cfg.plateau_s]
        if before and max(v for _, v in self.checks) - max(before) < PLATEAU_DB:
            self.anneal = (p.seconds, self.schedule_share(p))

    def loop_step(self, p: Progress) -> dict | None:
        cfg, neus = self.cfg, self.neus
        lw = neus.level_weights(p.share)
        self.check_plateau(p, lw)
        for group in self.optim.param_groups:
            group["lr"] = group["base_lr"] * lr_factor(cfg, p.step, self.schedule_share(p))
        idx = self.sampler.draw(cfg.batch_rays)
        o, d = neus.rays_o[idx], neus.rays_d[idx]
        near, far = neus.intervals(o, d)
        out = neus.render(o, d, lw, cfg.n_samples, True, True, near=near, far=far)
        target = neus.rays_rgb[idx]
        color_loss = (out["rgb"] - target).abs().mean()
        if neus.rays_alpha is None:  # no masks: the colour of every pixel, fore- and background
            mask_loss = out["acc"].new_zeros(())
        else:
            acc = out["acc"].clamp(1e-3, 1.0 - 1e-3)
            mask_loss = F.binary_cross_entropy(acc, neus.rays_alpha[idx])
        loss = color_loss + cfg.w_eikonal * out["eikonal"] + cfg.w_mask * mask_loss
        points_loss = self._points_loss(lw)
        loss = loss + cfg.w_points * (1.0 - p.share) * points_loss
        self.optim.zero_grad(set_to_none=True)
        loss.backward()
        self.optim.step()
        step = p.step + 1
        mse = ((out["rgb"].detach() - target) ** 2).mean()
        losses = torch.stack([loss, color_loss, out["eikonal"], mask_loss, mse, self.model.inv_s(),
                              points_loss]).detach()
        self.pending.append((step, round(self.loop.clock(), 3), losses))
        if cfg.occupancy_every > 0 and step % cfg.occupancy_every == 0:
            neus.refresh_occupancy(lw)
        if step % HISTORY_EVERY == 0:  # with the progress bar
            self.read_history()
            h = self.history[-1]
            return {"loss": f"{h['loss']:.4f}", "psnr": f"{h['psnr']:.1f}", "s": f"{h['s']:.0f}"}
        return None

    def run(self, resume: bool, callback, callback_every_s: float) -> dict:
        cfg = self.cfg
        if resume:
            self.resume()
        self.plan_compile()
        budget = Budget(cfg.iterations, cfg.time_limit_s)
        periodic = callback is not None and callback_every_s > 0
        self.loop = Loop("neus", budget, self.loop_step, start_step=self.step, start_seconds=self.elapsed,
                         checkpoint=self.save, checkpoint_every=cfg.checkpoint_every,
                         snapshot=(lambda p, label: callback(self.neus, p.step, p.seconds)) if periodic else None,
                         snapshot_every_s=callback_every_s if periodic else 0.0, done=self.done)
        with self.loop.clock.paused():  # set-up work is not training time
            self.neus.refresh_occupancy(self.neus.level_weights(self.loop.progress().share))
            if periodic and self.step == 0:
                callback(self.neus, 0, 0.0)  # the starting point (visual-hull or sphere initialisation)
        try:
            result = self.loop.run()
        finally:
            self.read_history()
        return {"iterations": result.steps, "train_seconds": result.seconds, "history": self.history,
                "stopped_by_time": result.stopped_by_time, "stopped_by_plateau": result.stopped_early,
                "plateau": {"checks": self.checks, "anneal_from_s": self.anneal[0] if self.anneal else None,
                            "held_aside_rays": len(self.sampler.held)},
                "step": "eager" if self.neus.compiled_step is None else self.neus.compiled_step.state}


def rate_spread(history: list[dict], window_s: float = 30.0) -> dict | None:
    """Training steps per second over consecutive windows of about window_s training seconds:
    min, median and max. A wide spread on a fixed-size step means that something else shared the
    CPU (the step's cost hardly depends on the training's progress: a fixed number of rays and
    samples per ray)."""
    rates, start = [], None
    for h in history:
        if start is None:
            start = h
            continue
        if h["seconds"] - start["seconds"] >= window_s:
            rates.append((h["step"] - start["step"]) / (h["seconds"] - start["seconds"]))
            start = h
    last = history[-1] if history else None
    if start is not None and last is not start and last["seconds"] - start["seconds"] >= 0.5 * window_s:
        rates.append((last["step"] - start["step"]) / (last["seconds"] - start["seconds"]))  # the tail
    if not rates:
        return None
    return {"window_s": window_s, "min": float(np.min(rates)), "median": float(np.median(rates)),
            "max": float(np.max(rates))}


@torch.no_grad()
def points_report(neus: NeuS) -> dict | None:
    """What the SDF-is-zero term had and what the trained SDF says of it: the sparse points given,
    those it used, and of those the median |SDF| (world units) and how many the final SDF puts
    POINTS_FAR box units or more from its zero set (points the surface did not take)."""
    if neus.points is None:
        return None
    out = {"given": int(len(neus.points)), "used": 0, "median_abs_sdf": None, "far": 0}
    pts = neus.surface_points
    if pts is None:
        return out
    levels = neus.level_weights(1.0)
    sdf = torch.cat([neus.model.sdf(chunk, levels)[0] for chunk in pts.split(65536)]).abs()
    out.update(used=int(len(pts)), median_abs_sdf=float(sdf.median()) * neus.box.half,
               far=int((sdf >= POINTS_FAR).sum()))
    return out


def _plot_history(history: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if not history:
        return
    steps = [h["step"] for h in history]
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.5))
    for key in ("loss", "color", "mask", "eikonal", "points"):
        if any(h.get(key) for h in history):  # the points term: only where the capture has points
            axes[0].semilogy(steps, [max(h.get(key, 0.0), 1e-8) for h in history], label=key, lw=0.8)
    axes[0].legend()
    axes[0].set_xlabel("step")
    axes[0].set_title("NeuS losses")
    k = max(1, len(history) // 200)
    psnr = np.convolve([h["psnr"] for h in history], np.ones(k) / k, mode="valid")
    axes[1].plot(steps[k - 1:], psnr)
    axes[1].set_xlabel("step")
    axes[1].set_title("training-batch PSNR (dB, sRGB)")
    axes[2].semilogy(steps, [h["s"] for h in history])
    axes[2].set_xlabel("step")
    axes[2].set_title("sharpness s")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


@torch.no_grad()
def view_psnr(neus: NeuS, capture, views: list[int], chunk: int = 8192) -> dict[str, float]:
    """NeuS's own render of each of the capture's `views` (indices; the capture may be another split
    than the one NeuS trained on, in the same world) against its image: sRGB PSNR inside the masks
    when the capture has them, else over the whole image (composited over the background model).
    {view name: dB}."""
    out = {}
    with _threads(neus.cfg.threads):
        for v in views:
            cam = capture.cameras[v]
            rgb, _ = render_view(neus, cam, chunk, composite=True)
            photo = encode_srgb(torch.from_numpy(np.ascontiguousarray(capture.images[v]))).numpy()
            err = (rgb - photo) ** 2
            if capture.has_alpha:
                inside = capture.alpha[v] > 0.5
                if not inside.any():
                    continue  # no foreground in this view: nothing to score
                err = err[inside]
            out[cam.name] = -10.0 * math.log10(max(float(err.mean()), 1e-10))
    return out


def sample_views(count: int, at_most: int) -> list[int]:
    """Up to `at_most` view indices spread evenly over `count` views."""
    return sorted({int(round(x)) for x in np.linspace(0, count - 1, min(at_most, count))}) if count else []


@dataclass
class NeuSResult:
    """What `reconstruct` made: the extracted mesh, the trained model and its summary (NeuS's
    geometry method, `method.py`, makes them a `Reconstruction` for the geometry stage)."""

    mesh: object  # trimesh.Trimesh, in the capture's world
    neus: NeuS
    summary: dict


def reconstruct(capture, run: RunDir | str | Path, cfg: NeuSConfig | None = None, resume: bool = False,
                callback=None, callback_every_s: float = 0.0,
                sphere: tuple | None = None, support: tuple | None = None,
                points: np.ndarray | None = None) -> NeuSResult:
    """NeuS on a loaded capture, then mesh extraction: writes the run's NeuS checkpoint neus.pt and
    geometry_loss.png, and returns the mesh and the summary. `sphere`, `support`, `points`: the
    bounding sphere, a known supporting plane and the sparse points when NeuS runs without masks
    (`NeuS`)."""
    cfg = cfg or NeuSConfig()
    run = run if isinstance(run, RunDir) else RunDir(run)
    with _threads(cfg.threads):
        return _reconstruct(capture, run, cfg, resume, callback, callback_every_s, sphere, support, points)


def _reconstruct(capture, run: RunDir, cfg: NeuSConfig, resume, callback, callback_every_s,
                 sphere=None, support=None, points=None) -> NeuSResult:
    t0 = time.perf_counter()
    neus = neus_for(capture, cfg, sphere, support, points)
    run.create()
    setup_s = time.perf_counter() - t0
    summary = train(neus, run, resume=resume, callback=callback,
                    callback_every_s=callback_every_s)
    t1 = time.perf_counter()
    mesh, support_plane = extract_mesh(neus)
    export_s = time.perf_counter() - t1
    if summary["history"]:
        run.write_file(run.GEOMETRY_PLOT, lambda path: _plot_history(summary["history"], path))
    last = summary["history"][-1] if summary["history"] else {}
    box = neus.box
    info = {
        "capture": str(Path(capture.source).resolve()),
        "world": capture.world,
        "iterations": summary["iterations"],
        "stopped_by_time_limit": summary["stopped_by_time"],
        "stopped_by_plateau": summary["stopped_by_plateau"],
        "plateau": summary["plateau"],
        "seconds": {"setup_and_hull": round(setup_s, 2), "hull": round(box.seconds, 2),
                    "train": round(summary["train_seconds"], 2), "mesh_export": round(export_s, 2),
                    "total": round(time.perf_counter() - t0, 2)},
        "iterations_per_s": summary["iterations"] / max(summary["train_seconds"], 1e-9),
        "iterations_per_s_spread": rate_spread(summary["history"]),
        "final_train_psnr": last.get("psnr"),
        "final_sharpness_s": last.get("s"),
        "box_center": box.center.tolist(),
        "box_half_size": box.half,
        "background": "model" if box.mask_free else "masks",
        "bounding_sphere": {"center": box.center.tolist(), "radius": box.half, "from": box.sphere_source}
        if box.mask_free else None,
        "support_plane": support_plane,
        "training_rays": len(neus.rays_o),
        "mesh": {"vertices": int(len(mesh.vertices)), "faces": int(len(mesh.faces)),
                 "watertight": bool(mesh.is_watertight)},
        "grid": neus.grid,
        "steps": neus.steps,
        "sparse_points": points_report(neus),
        "config": asdict(neus.cfg),
        "torch_threads": torch.get_num_threads(),
        "grid_lookup": grid_kernel.status(),
        "training_step": summary["step"],
        "device": device_record(),
    }
    return NeuSResult(mesh, neus, info)
