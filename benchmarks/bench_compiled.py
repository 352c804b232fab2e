#!/usr/bin/env python
"""Benchmark: each hot loop's step eager against compiled with torch.compile, in one process.

    .venv/bin/python benchmarks/bench_compiled.py [--loops residual neus material threads] [--neus-capture DIR]
        [--downscale 4] [--material-capture DATA/scene.xml] [--rounds 5] [--steps 15]
        [--out benchmarks/out/compiled]

- residual: the residual's step (`vq_mitsuba.engine.residual_fit`: forward, gamma-space L2, backward,
  fused Adam) at its batch of 8192 hits, on random hits of a 2^17-hit pool, as `fit` compiles it
  (`vq_mitsuba.compiled.Compiled`), with the first call's compile time.
- neus: a NeuS training step (`geometry/neus/training.py: NeuSTraining.loop_step`) on --neus-capture (its auto
  grid, the occupancy opened at half-way): the eager step (the rays that meet the hull gathered, the
  colour network at the samples that count) against `NeuS.training_step` compiled (fixed shapes
  but the colour network's samples: every ray of the batch, the grid lookup's C kernel a torch
  operator inside the graph), with the process's CPU time over wall time (cores busy).
- material: a material step on --material-capture (`Trainer.train_step` in the discrete branch's
  phase) with the continuous material network compiled (static shapes: the step's batch), against
  the eager step.
- threads: the same material step (the bounce on, the continuous and the discrete branch's phase)
  with torch on every core beside Dr.Jit's pool of every core, against torch on half of them
  (`backend.shading_threads`, what `fit` does).

Rounds of --steps steps alternate between the two variants (so that a neighbour's load falls on
both alike); printed and written to OUT/compiled_<commit>.json with the machine and versions: the
median ms a step of each, their ratio, the first compiled call's seconds and the losses at the end
(the same arithmetic up to rounding). A variant that is not the default says so.
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

from provenance import describe, provenance, write_result


def alternate(variants: dict, rounds: int, steps: int) -> dict:
    """Median ms a step of each variant (name -> step function), rounds alternating."""
    times = {name: [] for name in variants}
    for _ in range(rounds):
        for name, step in variants.items():
            t0 = time.perf_counter()
            for i in range(steps):
                step(i)
            times[name].append((time.perf_counter() - t0) / steps * 1000)
    return {name: {"median_ms": statistics.median(t), "rounds_ms": t} for name, t in times.items()}


def residual_loop(args) -> dict:
    import torch

    from vq_mitsuba.compiled import Compiled
    from vq_mitsuba.engine.residual_fit import BATCH, LR, LR_NET
    from vq_mitsuba.models import losses
    from vq_mitsuba.models.residual import ResidualField, add_residual

    gen = torch.Generator().manual_seed(0)
    n = 1 << 17
    unit = lambda: torch.nn.functional.normalize(torch.randn(n, 3, generator=gen), dim=-1)  # noqa: E731
    pos, nrm, wi = torch.rand(n, 3, generator=gen), unit(), unit()
    physical, target = torch.rand(n, 3, generator=gen), torch.rand(n, 3, generator=gen)

    def make():
        torch.manual_seed(1)
        field = ResidualField([0, 0, 0], [1, 1, 1], scale=0.5, finest=128)
        optim = torch.optim.Adam([{"params": [field.encoding.table], "lr": LR},
                                  {"params": list(field.mlp.parameters()), "lr": LR_NET}], eps=1e-15, fused=True)

        def gradients(b):
            optim.zero_grad(set_to_none=True)
            loss = losses.reconstruction_l2(add_residual(physical[b], field(pos[b], nrm[b], wi[b])), target[b], 2.2)
            loss.backward()
            return loss
        return optim, gradients

    batches = [torch.randint(0, n, (BATCH,), generator=gen) for _ in range(args.steps)]
    eager_optim, eager_grad = make()
    comp_optim, comp_grad = make()
    compiled = Compiled(comp_grad, "the residual's step")
    t0 = time.perf_counter()
    compiled(batches[0])
    first = time.perf_counter() - t0
    last = {}

    def eager(i):
        last["eager"] = float(eager_grad(batches[i]))
        eager_optim.step()

    def comp(i):
        last["compiled"] = float(compiled(batches[i]))
        comp_optim.step()

    out = alternate({"eager": eager, "compiled": comp}, args.rounds, args.steps)
    return {"batch": BATCH, "first_compiled_call_s": first, "state": compiled.state, "last_loss": last,
            "kept": "compiled (the default once the residual learns with 1000 full batches left)", **out}


def neus_loop(args) -> dict:
    import resource

    import torch

    from vq_mitsuba.compiled import Compiled
    from vq_mitsuba.config import CaptureConfig, load_config
    from vq_mitsuba.data.captures import load_capture
    from vq_mitsuba.geometry import neus as module
    from vq_mitsuba.run.loop import Progress

    torch.set_num_threads(2)
    capture = load_capture(args.neus_capture, options=CaptureConfig(downscale=args.downscale))
    neus = module.neus_for(capture, load_config(None).neus)
    fit = module.NeuSTraining(neus, None)
    fit.loop = type("Clock", (), {"clock": staticmethod(time.perf_counter)})
    neus.refresh_occupancy(neus.level_weights(0.5))
    compiled = Compiled(neus.training_step, "NeuS's step", data_dependent_shapes=True)
    cores = {"eager": [], "compiled": []}

    def run(name, step_fn):
        def step(i):
            neus.compiled_step = step_fn
            r0, t0 = resource.getrusage(resource.RUSAGE_SELF), time.perf_counter()
            fit.loop_step(Progress(step=1000 + i, seconds=0.0, step_share=0.5, time_share=0.5))
            r1, t1 = resource.getrusage(resource.RUSAGE_SELF), time.perf_counter()
            cores[name].append((r1.ru_utime + r1.ru_stime - r0.ru_utime - r0.ru_stime) / (t1 - t0))
        return step

    t0 = time.perf_counter()
    run("compiled", compiled)(0)
    first = time.perf_counter() - t0
    out = alternate({"eager": run("eager", None), "compiled": run("compiled", compiled)}, args.rounds, args.steps)
    points = neus.cfg.batch_rays * neus.cfg.n_samples
    for name in out:
        out[name]["sample_points_per_s"] = points / (out[name]["median_ms"] / 1000)
        out[name]["cores_busy"] = statistics.median(cores[name])
    return {"capture": args.neus_capture, "downscale": args.downscale, "grid": neus.grid, "batch_rays": neus.cfg.batch_rays,
            "first_compiled_call_s": first, "state": compiled.state,
            "kept": f"compiled (the default with {module.training.COMPILE_FROM} steps or more to go)", **out}


def demo_trainer(capture: str):
    """A Trainer of the demo preset on `capture` in a temporary run folder (the bounce from the first
    step), and a function taking one step at a schedule progress; remove the folder when done."""
    import tempfile

    from vq_mitsuba.config import load_config
    from vq_mitsuba.data.captures import open_capture
    from vq_mitsuba.engine.pipeline import load_training_capture
    from vq_mitsuba.engine.schedule import schedule_at
    from vq_mitsuba.engine.trainer import Trainer
    from vq_mitsuba.run.loop import Progress
    from vq_mitsuba.run.run_dir import RunDir

    cfg = load_config(None, ["train.bounce_after=0"], preset="demo")
    folder = Path(tempfile.mkdtemp())
    run = RunDir(folder / "run")
    run.create()
    trainer = Trainer(load_training_capture(open_capture(capture, options=cfg.capture), run), run, cfg)

    def take_step(progress: float) -> None:
        trainer.train_step(schedule_at(cfg, Progress(trainer.step, 0.0, progress, 0.0)))
    return trainer, take_step, folder


def material_loop(args) -> dict:
    import shutil

    import torch

    trainer, take_step, folder = demo_trainer(args.material_capture)
    eager_model = trainer.model.field
    compiled_model = torch.compile(eager_model, dynamic=False)

    class StepModel:
        """The compiled network for the step's fixed-size batches, the eager one elsewhere (the bounce)."""

        def __getattr__(self, name):
            return getattr(eager_model, name)

        def __call__(self, x):
            sizes = (trainer.data.batch, max(trainer.data.batch // 4, 1))
            return compiled_model(x) if x.shape[0] in sizes else eager_model(x)

    def run_with(model):
        def step(i):
            trainer.model.field = model
            take_step(0.6)
            trainer.model.field = eager_model
        return step

    t0 = time.perf_counter()
    for i in range(3):
        run_with(StepModel())(i)
    first = time.perf_counter() - t0
    out = alternate({"eager": run_with(eager_model), "compiled": run_with(StepModel())}, args.rounds, args.steps)
    shutil.rmtree(folder, ignore_errors=True)
    return {"capture": args.material_capture, "batch_rays": trainer.data.batch, "first_compiled_calls_s": first,
            "kept": "eager (within the noise of the step)", **out}


def threads_loop(args) -> dict:
    import shutil

    import drjit as dr
    import torch

    from vq_mitsuba.backend import available_cores

    trainer, take_step, folder = demo_trainer(args.material_capture)
    cores = available_cores()
    out = {"cores": cores, "dr_jit_threads": dr.thread_count(),
           "kept": f"torch on {max(1, cores // 2)} thread(s) while Dr.Jit shades (the default)"}
    for phase, progress in (("continuous", 0.1), ("discrete", 0.6)):
        def run_with(threads):
            def step(i):
                torch.set_num_threads(threads)
                take_step(progress)
            return step
        for i in range(5):
            run_with(cores)(i)
        half = max(1, cores // 2)
        out[phase] = alternate({f"torch {cores}": run_with(cores), f"torch {half}": run_with(half)}, args.rounds,
                               args.steps)
    torch.set_num_threads(cores)
    shutil.rmtree(folder, ignore_errors=True)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--loops", nargs="+", default=["residual"], choices=["residual", "neus", "material", "threads"],
                    help="the loops to time (default residual)")
    ap.add_argument("--neus-capture", help="a capture NeuS trains on (for --loops neus)")
    ap.add_argument("--downscale", type=int, default=4, help="image downscale of --neus-capture (default 4)")
    ap.add_argument("--material-capture", help="a capture with geometry, e.g. DATA/scene.xml (for --loops material)")
    ap.add_argument("--rounds", type=int, default=5, help="alternating rounds a variant (default 5)")
    ap.add_argument("--steps", type=int, default=15, help="steps a round (default 15)")
    ap.add_argument("--out", type=Path, default=Path(__file__).resolve().parent / "out" / "compiled")
    args = ap.parse_args()
    loops = {"residual": residual_loop, "neus": neus_loop, "material": material_loop, "threads": threads_loop}
    results = {}
    for name in args.loops:
        results[name] = r = loops[name](args)
        if name == "threads":
            for phase in ("continuous", "discrete"):
                a, b = (r[phase][k]["median_ms"] for k in r[phase])
                names = list(r[phase])
                print(f"threads, {phase} phase: {names[0]} {a:.1f} ms, {names[1]} {b:.1f} ms a step ({a / b:.2f}x)")
            print(f"threads: kept: {r['kept']}")
            continue
        print(f"{name}: eager {r['eager']['median_ms']:.1f} ms, compiled {r['compiled']['median_ms']:.1f} ms a step "
              f"({r['eager']['median_ms'] / r['compiled']['median_ms']:.2f}x); kept: {r['kept']}")
    record = provenance()
    path = write_result(args.out / f"compiled_{record['commit']}.json", {**record, "results": results})
    print(describe(record))
    print(f"written {path}")


if __name__ == "__main__":
    main()
