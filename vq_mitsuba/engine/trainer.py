"""The training loop of a fit: the material model (`vq_mitsuba.engine.material_model`) trained on
the pixel data (`vq_mitsuba.engine.pixel_data`) by Adam, with the rules that decide as the fit
goes (`vq_mitsuba.engine.skips`, `ladder`, `trials`, `evidence`), its checkpoints and time limit.

Each step draws a batch of foreground pixels across all views, asks the model for its named loss
terms, weighs them by their config keys (`vq_mitsuba.models.losses.weighted`) and steps. After
`vq.warmup_frac` of training the discrete branch starts from k-means of the latents and trains
beside the continuous one. The fit around the loop (checks, loading, resuming) is
`vq_mitsuba.engine.pipeline`; what is written at its end is `vq_mitsuba.engine.products`. Every
file is written through `RunDir`; a run resumes from its last checkpoint.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from vq_mitsuba import messages
from vq_mitsuba.backend import init_mitsuba, shading_threads, torch_device
from vq_mitsuba.config import Config, to_dict
from vq_mitsuba.data.captures import Capture
from vq_mitsuba.engine import evidence, skips
from vq_mitsuba.engine.ladder import EnvmapLadder, envmap_height_at, envmap_ladder  # noqa: F401 (re-exported)
from vq_mitsuba.engine.material_model import MaterialModel, mean_foreground
from vq_mitsuba.engine.pixel_data import PixelData
from vq_mitsuba.engine.schedule import StepSchedule, schedule_at
from vq_mitsuba.engine.trials import Trials
from vq_mitsuba.errors import InputError, NumericalError, warn
from vq_mitsuba.models import losses
from vq_mitsuba.run.loop import Budget, Loop, Progress
from vq_mitsuba.run.run_dir import RunDir

MAX_NONFINITE_RUN = 20  # non-finite steps in a row that stop a fit


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


class Trainer:
    """One fit: the model, the pixel data, the optimiser, the rules, the step and the loop."""

    def __init__(self, capture: Capture, run: RunDir, cfg: Config):
        self.cfg, self.run, self.capture = cfg, run, capture
        t = cfg.train
        check_opaque_pixels(capture, t.alpha_threshold)
        torch.manual_seed(t.seed)
        np.random.seed(t.seed)
        init_mitsuba()
        self.device = torch_device()
        self.model = MaterialModel(capture, cfg, self.device, mean_foreground(capture, t.alpha_threshold))
        # no speed-up before every stage of the schedule has begun
        stages = [cfg.field.pe_anneal, cfg.loss.metallic_barrier_until] + ([cfg.vq.warmup_frac] if cfg.vq.enabled
                                                                           else [])
        self.pace = skips.Pace(t.iterations, t.stop == "auto", start_share=max(stages))
        trials_on = self.model.learn_env and t.trials == "auto"
        self.data = PixelData(self.model.scene, capture, cfg, self.device, hold=self.pace.active or trials_on)
        stats = self.data.stats
        if stats["hits_per_pixel"] < max(t.pixel_jitter, 1) or stats["pixel_share"] < 1.0:
            messages.note(f"training pixels: {stats['opaque_pixels']:,} opaque pixels, {stats['hits_per_pixel']} "
                          f"hit(s) each instead of {max(t.pixel_jitter, 1)}"
                          + (f", {100 * stats['pixel_share']:.0f} % of them" if stats["pixel_share"] < 1.0 else "")
                          + f" (train.max_hits {t.max_hits:,})")
        self.optim = torch.optim.Adam(self.model.parameter_groups(), fused=True)
        self.base_lrs = [g["lr"] for g in self.optim.param_groups]
        self.gen = torch.Generator(device=self.device).manual_seed(t.seed)
        self.history: list[dict] = []
        self.step, self.elapsed_before = 0, 0.0
        pool = self.data.pool
        self.bounce_on, bounce = skips.decide_bounce(t.bounce, t.bounces, self.model.scene, pool.position, pool.wi,
                                                     skips.np_seed(t.seed, 1))
        self.decisions = {"bounce": bounce}
        self.ladder = EnvmapLadder(cfg, self.model.learn_env and cfg.envmap.final_height == "auto")
        gen = torch.Generator().manual_seed(skips.np_seed(t.seed, 3))
        # fixed hits whose roughness the ladder and the trials read
        self.fixed_hits = torch.randperm(len(pool), generator=gen)[:skips.ROUGHNESS_HITS].to(self.device)
        self.trials = None if not trials_on else Trials(self, t.trials, skips.decision(
            t.trials, "none", "the fit ended before the trial's check"))
        self.decisions["trials"] = self.trials.decision if self.trials is not None else skips.decision(
            t.trials, "none", "no learned light: nothing to trade a surface's roughness against"
            if not self.model.learn_env else f"train.trials = {t.trials}")
        self.prior = evidence.PriorReading(self.model.scene, capture, pool, cfg,
                                           None if self.model.learn_env else self.model.envmap())
        self.model.prior = self.prior

    # --- state ----------------------------------------------------------------------------------
    def envmap(self) -> torch.Tensor:
        return self.model.envmap()

    @property
    def finished(self) -> bool:
        """The schedule is done (train.iterations, or sooner at the pace of train.stop = auto)."""
        return self.step >= self.cfg.train.iterations or self.pace.finished

    def set_envmap_height(self, height: int, resample: bool = True) -> None:
        """Bring the learned envmap to `height` rows; its Adam state restarts. It grows as the
        schedule goes on, and shrinks only when a run resumes with more iterations, at an earlier
        point of the ladder."""
        swapped = self.model.resize_envmap(height, resample)
        if swapped is None:
            return
        old, new = swapped
        group = next(g for g in self.optim.param_groups if any(q is old for q in g["params"]))
        group["params"] = [new]
        self.optim.state.pop(old, None)

    def fitted_state(self, elapsed: float) -> dict:
        """What rendering and scoring need."""
        return {**self.model.state_dict(), "step": self.step, "elapsed_s": elapsed, "config": to_dict(self.cfg)}

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
        if self.model.learn_env:
            self.set_envmap_height(state["envmap"]["log_radiance"].shape[0], resample=False)
        self.model.load_state_dict(state)
        self.optim.load_state_dict(state["optim"])
        self.gen.set_state(state["generator"].cpu())  # CPU bytes on any device
        self.history, self.step, self.elapsed_before = state["history"], state["step"], state["elapsed_s"]
        self.load_skips_state(state.get("skips"))

    def skips_state(self) -> dict:
        """What the rules decided and measured so far (`vq_mitsuba.engine.skips`), for resuming."""
        return {"bounce_on": self.bounce_on, "decisions": self.decisions_so_far(), "pace": self.pace.state_dict(),
                "sampler": self.data.state_dict(), "envmap": self.ladder.state_dict(), "prior": self.prior.state_dict(),
                "trial": self.trials.state_dict() if self.trials is not None else {"checked": False, "pending": None}}

    def decisions_so_far(self) -> dict:
        """Each rule's decision (setting, choice, reason) made so far; the trial's is the trial's own."""
        out = {**self.decisions, "prior": self.prior.decision}
        if self.trials is not None:
            out["trials"] = self.trials.decision
        return out

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
        self.data.load_state_dict(state["sampler"])
        self.ladder.load_state_dict(state["envmap"])
        self.prior.load_state_dict(state.get("prior"))
        if self.trials is not None:
            self.trials.load_state_dict(state.get("trial"), state["decisions"].get("trials"))

    # --- one step -------------------------------------------------------------------------------
    def loss_terms(self, idx: torch.Tensor, s: StepSchedule, bounce: bool,
                   weight: torch.Tensor | None = None) -> tuple[dict, torch.Tensor, torch.Tensor | None]:
        """The weighted loss terms of the pixels `idx` (Eq. 10: their sum is the loss), the
        continuous branch's pixel colours and the per-pixel squared errors (`MaterialModel.loss_dict`)."""
        terms, rgb, per_pixel = self.model.loss_dict(self.data, idx, s, bounce, self.gen, weight)
        return losses.weighted(terms, self.cfg, s.progress), rgb, per_pixel

    def train_step(self, s: StepSchedule) -> tuple[bool, float, float]:
        """One optimisation step; (finite, loss, sRGB MSE of the continuous branch). A step whose
        loss or gradients are not finite is not applied."""
        model, data = self.model, self.data
        for g, lr in zip(self.optim.param_groups, self.base_lrs):
            g["lr"] = lr * s.lr_factor
        if s.discrete and not model.discrete_on:
            model.start_discrete(data.pool.position, self.gen, self.step, self.run.dir)
        model.field.set_progress(s.progress, self.cfg.field.pe_anneal)
        if model.learn_env:
            self.set_envmap_height(self.envmap_height(s.progress))
        if self.prior.due(s.progress):
            self.prior.read(model.envmap(), self.step)
        idx, weight = data.draw(self.step, self.gen)
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
        data.observe(idx, per_pixel)
        with torch.no_grad():
            mse = float(losses.srgb_mse(rgb.detach(), data.pool.rgb[idx], weight))  # of all pixels, by weight
        return True, float(loss.detach()), mse

    def envmap_height(self, progress: float) -> int:
        """The learned envmap's rows at `progress` (`EnvmapLadder.height`)."""
        return self.ladder.height(progress, self.step, lambda: self.model.roughness(
            self.data.pool.position[self.fixed_hits]))

    def bounce_active(self) -> bool:
        """The bounce is simulated at this step: decided on (`skips.decide_bounce`) and past
        train.bounce_after."""
        return self.bounce_on and self.step >= self.cfg.train.bounce_after

    def held_loss(self) -> float:
        """The reconstruction loss of the held-aside pixels (`MaterialModel.held_loss`)."""
        return self.model.held_loss(self.data, skips.np_seed(self.cfg.train.seed, 4), self.bounce_active())

    # --- the loop -------------------------------------------------------------------------------
    def train(self) -> dict:
        """Run the remaining steps under train.iterations and train.time_limit_s (the loop skeleton,
        `vq_mitsuba.run.loop`); the learning rate follows the step share, the rest of the schedule
        the larger of the step and time shares (`schedule_at`)."""
        cfg = self.cfg
        self._acc = {"loss": 0.0, "mse": 0.0, "n": 0, "nonfinite": 0, "run": 0}
        loop = Loop("fit", Budget(cfg.train.iterations, cfg.train.time_limit_s), self._loop_step,
                    start_step=self.step, start_seconds=self.elapsed_before,
                    checkpoint=lambda p: self.checkpoint(p.seconds), checkpoint_every=cfg.train.checkpoint_every,
                    snapshot=lambda p, label: self.snapshot(p.seconds),
                    snapshot_times=parse_snapshot_times(cfg.train.snapshot_s),
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
                "batch_rays": self.data.batch, "training_pixels": len(self.data), "steps_this_call": result.steps_this_call,
                "nonfinite_steps_skipped": self._acc["nonfinite"], "decisions": self.final_decisions()}

    def _stage(self) -> tuple[bool, bool]:
        """(the discrete branch trains, the bounce is on): a change starts a new phase of the pace."""
        return self.model.discrete_on, self.bounce_active()

    def final_decisions(self) -> dict:
        """fit.json's `decisions`: each rule's setting, choice and reason."""
        cfg = self.cfg
        out = self.decisions_so_far()
        held = 0 if self.data.held is None else len(self.data.held)
        out["stop"] = self.pace.decision(cfg.train.stop, self.step, held)
        out["stop"]["pace"] = self.pace.state_dict()
        if not self.model.learn_env:
            out["envmap"] = skips.decision(cfg.envmap.final_height, "known", "the capture's envmap lights the fit")
        else:
            out["envmap"] = self.ladder.decision(self.model.envmap_rows)
        out["sampling"] = self.data.sampling_decision(cfg.train.sampling)
        out["lamps"] = self.model.lamps_decision()
        return out

    def _loop_step(self, p: Progress) -> dict | None:
        """One step of the loop: the optimisation step, the non-finite guard and the loss curve."""
        acc = self._acc
        # The schedule follows the pace's schedule steps (the time share under a time limit, if larger).
        p = Progress(p.step, p.seconds, self.pace.share(), p.time_share)
        finite, loss, mse = self.train_step(schedule_at(self.cfg, p))
        self.pace.advance()
        if self.trials is not None:
            self.trials.after_step(p)
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
        if self.model.learn_env:
            notes["env"] = f"{self.model.envmap_rows}/{self.ladder.rungs[-1]}"
        notes["rays"] = "error" if self.data.sampler is not None else "uniform"
        if self.pace.active:
            notes["pace"] = f"{self.pace.rate}x"
        return notes
