"""The device check: one command that says what a machine's device is and what it buys.

    python benchmarks/gpu_check.py --device cuda --budget 540 --out benchmarks/out/gpu_check.json  # a GPU
    python benchmarks/gpu_check.py --device cpu --size 32 --quick                                   # a CPU

(a) prints the device the process chooses (`vq_mitsuba.backend.choose_device`), the versions and the
    memory; (b) renders tabletop at --size pixels into a work folder (`make-scene`); (c) times NeuS
    steps and material-fit steps on it at several ray batches (--neus-batches, --fit-batches; NeuS's
    default batch is sized to the device, `backend.sized`), in a child process; (d) fits it from its true mesh and
    from its images (NeuS, then the materials), each with `--device`, and scores both runs (`eval
    --gt`), timing each stage; (e) runs the suite's GPU-relevant tests (`pytest -q` on --tests, with
    --workers pytest-xdist workers); (f) writes one JSON (--out) with the stage times, the step rates
    (the sweep and the runs' fit.json and geometry.json), the devices the runs recorded (run.json) and
    the eval figures. The JSON is rewritten after every stage; with --budget, each stage gets what is
    left of it and the ones that no longer fit are skipped (recorded as such).
--quick shrinks everything (views, samples, steps) so that the whole script runs in about a minute
on two CPU cores: it checks the script, not the device. Each stage is a child process (`python -m
vq_mitsuba.cli ...`), as a user runs it; a failed stage is recorded and the script goes on.
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

from provenance import command_line, provenance, write_json

ROOT = Path(__file__).resolve().parent.parent
GPU_TESTS = ["tests/geometry/test_geometry.py", "tests/engine/test_fit.py", "tests/render/test_rendering.py"]
QUICK_TESTS = ["tests/geometry/test_device.py"]
# (make-scene options, fit settings, eval options) of a full check and of --quick
FULL = (["--n-train", "100", "--n-test", "8"], [], [])
QUICK = (["--n-train", "8", "--n-test", "2", "--spp", "8"],
         ["neus.iterations=40", "neus.batch_rays=256", "neus.mesh_resolution=48", "neus.hull_resolution=32",
          "train.iterations=60", "train.batch_rays=256", "vq.enabled=false"],
         ["--spp", "4", "--meanshift", "none"])
FIGURES = (("novel_view", "psnr"), ("basecolor", "psnr"), ("metallic", "psnr"), ("roughness", "psnr"),
           ("normal", "mae_deg"))


def device_report(name: str) -> dict:
    """The device this process chooses for `name`, the versions and the memory (host and device)."""
    import drjit
    import mitsuba
    import torch

    from vq_mitsuba.backend import choose_device, device_record
    from vq_mitsuba.errors import InputError

    try:
        choose_device(name)
        record = device_record()
    except InputError as exc:
        record = {"requested": name, "error": str(exc)}
    memory = None
    if torch.cuda.is_available():
        free, total = torch.cuda.mem_get_info()
        memory = {"device_free_gb": round(free / 2 ** 30, 2), "device_total_gb": round(total / 2 ** 30, 2)}
    return {**record, "memory": memory, "versions": {"mitsuba": mitsuba.__version__, "drjit": drjit.__version__,
                                                     "torch": torch.__version__, "torch_cuda": torch.version.cuda}}


class Deadline:
    """What is left of --budget seconds (no budget: each stage's --timeout)."""

    def __init__(self, budget: float, timeout: float):
        self.end = time.perf_counter() + budget if budget > 0 else None
        self.timeout = timeout

    def left(self) -> float:
        return self.timeout if self.end is None else min(self.timeout, self.end - time.perf_counter())


DEADLINE = Deadline(0, 1800)


def run_stage(name: str, argv: list[str], log: Path, timeout: float | None = None) -> dict:
    """One child process, its wall time and exit status; its output goes to `log`. It gets what is
    left of the budget (`DEADLINE`); with under 5 seconds left it is skipped."""
    timeout = DEADLINE.left() if timeout is None else timeout
    if timeout < 5:
        print(f"{name}: skipped (the budget is spent)", flush=True)
        return {"command": " ".join(argv[2:] if argv[1] == "-m" else argv[1:]), "exit": "skipped (budget)",
                "seconds": 0.0}
    start = time.perf_counter()
    with open(log, "a") as out:
        out.write(f"\n$ {' '.join(argv)}\n")
        out.flush()
        try:
            code = subprocess.run(argv, cwd=ROOT, stdout=out, stderr=subprocess.STDOUT, timeout=timeout).returncode
        except subprocess.TimeoutExpired:
            code = "timeout"
    seconds = round(time.perf_counter() - start, 2)
    print(f"{name}: {'ok' if code == 0 else f'FAILED ({code})'} in {seconds:.1f} s", flush=True)
    return {"command": " ".join(argv[2:] if argv[1] == "-m" else argv[1:]), "exit": code, "seconds": seconds}


def run_tests(tests: list[str], log: Path, workers: int) -> dict:
    """pytest -q on `tests` (with `workers` pytest-xdist workers when > 0), with its summary line."""
    parallel = ["-n", str(workers)] if workers > 0 else []
    stage = run_stage("tests", [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-rf", *parallel,
                                *tests], log)
    lines = [ln for ln in log.read_text().splitlines() if " passed" in ln or " failed" in ln or " error" in ln]
    return {**stage, "files": tests, "summary": lines[-1].strip("= ") if lines else None}


def _timed(step, sync, warmup: int, steps: int) -> float:
    """Median seconds of one call of `step` over `steps` calls after `warmup`, each closed by `sync`."""
    for _ in range(warmup):
        step()
    sync()
    times = []
    for _ in range(steps):
        t0 = time.perf_counter()
        step()
        sync()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def _profile(step, sync, steps: int = 5) -> dict:
    """`steps` calls of `step` under torch's profiler (CUDA kernels of torch and Dr.Jit alike, on a
    GPU): the wall time, the kernels' busy time and the ops that took most device and host time."""
    import torch
    from torch.profiler import ProfilerActivity, profile

    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if torch.cuda.is_available() else [])
    sync()
    t0 = time.perf_counter()
    with profile(activities=activities) as prof:
        for _ in range(steps):
            step()
        sync()
    wall = time.perf_counter() - t0
    events = prof.key_averages()
    device_us = sum(getattr(e, "self_device_time_total", 0) or 0 for e in events)
    return {"steps": steps, "wall_s": wall, "device_busy_share": device_us * 1e-6 / wall if wall > 0 else None,
            "top_device": events.table(sort_by="self_device_time_total", row_limit=12) if device_us else None,
            "top_host": events.table(sort_by="self_cpu_time_total", row_limit=12)}


def step_rates(scene: Path, device: str, neus_batches: list[int], fit_batches: list[int], settings: list[str],
               warmup: int, steps: int, profile: bool = False) -> dict:
    """NeuS's and the material fit's step time at each ray batch on `device` (a trained-looking state:
    NeuS's occupancy opened at half-way, the material fit past its warm-up with the bounce on): the
    median seconds a step, its rays a second, and the batch a fit takes by default (NeuS's sized to the
    device, `backend.sized`); `profile`: at that batch, 5 more steps under torch's profiler (`_profile`)."""
    import drjit as dr
    import torch

    from vq_mitsuba.backend import choose_device, device_scale, sized, torch_device
    from vq_mitsuba.config import CPU_NEUS_BATCH, load_config
    from vq_mitsuba.data.captures import load_capture
    from vq_mitsuba.engine.schedule import schedule_at
    from vq_mitsuba.engine.trainer import Trainer
    from vq_mitsuba.geometry.neus.training import NeuSTraining
    from vq_mitsuba.geometry.neus.rays import neus_for
    from vq_mitsuba.run.loop import Progress
    from vq_mitsuba.run.run_dir import RunDir

    choose_device(device)

    def sync():
        if torch_device().type == "cuda":
            torch.cuda.synchronize()
        dr.sync_thread()

    cfg = load_config(None, settings)
    out = {"device_scale": device_scale(), "default": {"neus": sized(cfg.neus.batch_rays, CPU_NEUS_BATCH), "fit": cfg.train.batch_rays},
           "warmup": warmup, "steps": steps, "neus": [], "fit": []}
    capture = load_capture(scene / "transforms_train.json", split="train")
    for batch in neus_batches:
        neus = neus_for(capture, replace(cfg.neus, batch_rays=batch))
        fit = NeuSTraining(neus, None)
        fit.loop = type("Clock", (), {"clock": staticmethod(time.perf_counter)})
        neus.refresh_occupancy(neus.level_weights(0.5))
        step = iter(range(10 ** 9))
        seconds = _timed(lambda: fit.loop_step(Progress(step=1000 + next(step), seconds=0.0, step_share=0.5,
                                                        time_share=0.5)), sync, warmup, steps)
        out["neus"].append({"batch_rays": batch, "seconds_per_step": seconds, "rays_per_s": batch / seconds})
        if batch == out["default"]["neus"] and profile:
            out["neus_profile"] = _profile(lambda: fit.loop_step(Progress(step=1000 + next(step), seconds=0.0,
                                                                          step_share=0.5, time_share=0.5)), sync)
        print(f"NeuS batch {batch}: {seconds * 1000:.1f} ms a step, {batch / seconds:,.0f} rays/s", flush=True)
        del neus, fit
    capture = load_capture(scene / "transforms_train.json", mesh=scene / "mesh.ply", split="train")
    with tempfile.TemporaryDirectory() as tmp:
        trainer = Trainer(capture, RunDir(Path(tmp) / "run"), cfg)
        trainer.step = 1000  # past train.bounce_after: the bounce is simulated, as in most steps
        for batch in fit_batches:
            trainer.data.batch = min(batch, len(trainer.data))
            seconds = _timed(lambda: trainer.train_step(schedule_at(cfg, Progress(
                step=trainer.step, seconds=0.0, step_share=0.5, time_share=0.5))), sync, warmup, steps)
            out["fit"].append({"batch_rays": trainer.data.batch, "seconds_per_step": seconds,
                               "rays_per_s": trainer.data.batch / seconds})
            if batch == out["default"]["fit"] and profile:
                out["fit_profile"] = _profile(lambda: trainer.train_step(schedule_at(cfg, Progress(
                    step=trainer.step, seconds=0.0, step_share=0.5, time_share=0.5))), sync)
            print(f"material fit batch {trainer.data.batch}: {seconds * 1000:.1f} ms a step, "
                  f"{trainer.data.batch / seconds:,.0f} rays/s", flush=True)
    return out


def run_summary(run: Path, metrics: Path) -> dict:
    """What a run recorded: its device, step rates and stage times, and its eval figures."""
    def read(path: Path) -> dict:
        return json.loads(path.read_text()) if path.is_file() else {}

    info, fit, geometry, scores = read(run / "run.json"), read(run / "fit.json"), read(run / "geometry.json"), \
        read(metrics)
    out = {"device": info.get("device"),
           "fit": {k: fit.get(k) for k in ("iterations", "seconds", "iterations_per_s", "startup_s")} if fit else None,
           "neus": {"iterations": geometry.get("iterations"), "iterations_per_s": geometry.get("iterations_per_s"),
                    "seconds": geometry.get("seconds"), "device": geometry.get("device")} if geometry else None}
    def at(*keys):  # None where a part is missing (or null: no discrete branch)
        value = scores
        for key in keys:
            value = value.get(key) if isinstance(value, dict) else None
        return value

    figures = {f"{part}_{key}": at(part, key) for part, key in FIGURES}
    figures["relighting_psnr"] = at("relighting", "albedo_scale", "mean", "psnr")
    figures["segmentation_micro_f1"] = at("segmentation", "micro_f1")
    return {**out, "figures": figures}


def fit_and_score(label: str, scene: Path, work: Path, args, extra: list[str], log: Path) -> dict:
    """`fit` the scene (NeuS from the images, or the true mesh), then `eval --gt`: stage times and figures."""
    _, settings, eval_options = QUICK if args.quick else FULL
    run, metrics = work / f"run_{label}", work / f"metrics_{label}.json"
    cli = [sys.executable, "-m", "vq_mitsuba.cli"]
    fit = run_stage(f"fit ({label})", cli + ["fit", str(scene / "transforms_train.json"), "-o", str(run), "--quiet",
                                             "--device", args.device, *extra]
                    + [x for s in settings + (args.set or []) for x in ("--set", s)], log)
    score = run_stage(f"eval ({label})", cli + ["eval", str(run), "--gt", str(scene), "-o", str(metrics), "--quiet",
                                                "--device", args.device, *eval_options], log) \
        if fit["exit"] == 0 else {"exit": "skipped (the fit failed)"}
    return {"stages": {"fit": fit, "eval": score}, **run_summary(run, metrics)}


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--device", choices=["auto", "cpu", "cuda"], default="auto", help="the --device of every stage")
    p.add_argument("--size", type=int, default=200, help="tabletop's image size in pixels (make-scene --resolution)")
    p.add_argument("--quick", action="store_true", help="few views, samples and steps: checks the script itself")
    p.add_argument("--tests", nargs="*", help="test files to run (default: the GPU-relevant ones; none: skip)")
    p.add_argument("--workers", type=int, default=0, help="pytest-xdist workers for the tests (0: one process)")
    p.add_argument("--neus-batches", type=int, nargs="*", default=[512, 2048, 4096, 8192],
                   help="NeuS ray batches to time a step at (none: skip)")
    p.add_argument("--fit-batches", type=int, nargs="*", default=[2048, 8192, 16384, 32768],
                   help="material-fit ray batches to time a step at (none: skip)")
    p.add_argument("--rate-steps", type=int, default=20, help="timed steps per batch (after as many warm-up steps)")
    p.add_argument("--set", action="append", metavar="KEY=VALUE", help="a setting of both fits (repeatable)")
    p.add_argument("--out", default="benchmarks/out/gpu_check.json", help="the JSON to write")
    p.add_argument("--work", help="keep the scene, runs and log in this folder (default: a temporary one)")
    p.add_argument("--timeout", type=float, default=1800, help="seconds each stage may take")
    p.add_argument("--budget", type=float, default=0, help="seconds the whole check may take (0: no limit)")
    p.add_argument("--profile", action="store_true", help="profile 5 steps of each at its default batch")
    p.add_argument("--rates-of", help=argparse.SUPPRESS)  # internal: the step-rate child, on this scene
    return p.parse_args(argv)


def main(argv=None) -> int:
    global DEADLINE
    args = parse_args(argv)
    if args.rates_of:  # the child that times the steps
        settings = (QUICK[1] if args.quick else FULL[1]) + (args.set or [])
        rates = step_rates(Path(args.rates_of), args.device, args.neus_batches, args.fit_batches, settings,
                           max(1, args.rate_steps // 2), args.rate_steps, args.profile)
        Path(args.out).write_text(json.dumps(rates, indent=1))
        return 0
    DEADLINE = Deadline(args.budget, args.timeout)
    start = time.perf_counter()
    block = {**provenance(), "command": command_line(sys.argv[1:] if argv is None else argv, Path(__file__))}
    device = device_report(args.device)
    print(json.dumps(device, indent=1), flush=True)
    work = Path(args.work) if args.work else Path(tempfile.mkdtemp(prefix="gpu_check_"))
    work.mkdir(parents=True, exist_ok=True)
    log = work / "gpu_check.log"
    result = {"device": device, "size": args.size, "quick": args.quick, "budget_s": args.budget}

    def save() -> Path:
        result["seconds"] = round(time.perf_counter() - start, 1)
        return write_json(Path(args.out), {**block, **result})

    scene = work / "tabletop"
    options = (QUICK if args.quick else FULL)[0]
    result["make_scene"] = run_stage("make-scene", [sys.executable, "-m", "vq_mitsuba.cli", "make-scene", "tabletop",
                                                    "-o", str(scene), "--resolution", str(args.size), *options], log)
    save()
    if result["make_scene"]["exit"] == 0:
        if args.neus_batches or args.fit_batches:
            rates = work / "rates.json"
            stage = run_stage("step rates", [sys.executable, str(Path(__file__).resolve()), "--rates-of", str(scene),
                                             "--device", args.device, "--out", str(rates), "--rate-steps",
                                             str(args.rate_steps), *(["--quick"] if args.quick else []),
                                             *(["--profile"] if args.profile else []),
                                             "--neus-batches", *map(str, args.neus_batches),
                                             "--fit-batches", *map(str, args.fit_batches),
                                             *[x for s in args.set or [] for x in ("--set", s)]], log)
            result["rates"] = {**stage, **(json.loads(rates.read_text()) if rates.is_file() else {})}
            save()
        result["true_mesh"] = fit_and_score("true_mesh", scene, work, args, ["--mesh", str(scene / "mesh.ply")],
                                            log)
        save()
        result["images"] = fit_and_score("images", scene, work, args, ["--geometry", "neus"], log)
        save()
    tests = QUICK_TESTS if (args.quick and args.tests is None) else GPU_TESTS if args.tests is None else args.tests
    result["tests"] = run_tests(tests, log, args.workers) if tests else None
    path = save()
    print(f"wrote {path} in {result['seconds']:.0f} s (log: {log})")
    if not args.work:
        shutil.copy(log, Path(args.out).with_suffix(".log"))
        shutil.rmtree(work, ignore_errors=True)
    failed = [s for s in ("images", "true_mesh") if result.get(s, {}).get("stages", {}).get("eval", {}).get("exit") != 0]
    return 1 if failed or result["make_scene"]["exit"] != 0 or (result["tests"] or {}).get("exit", 0) != 0 else 0


if __name__ == "__main__":
    sys.exit(main())
