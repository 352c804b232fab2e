"""The stress suite: kill -9 at random points of fits followed by --resume, lighting and exposure
extremes on a fitted run, and the capture-loader fuzz (tests/data/test_fuzz_captures.py: NeRF json,
Mitsuba XML, image layouts, COLMAP text and binary, NeuS/IDR) with many examples per loader.
Prints what was tried, NaN/Inf found, tracebacks, and how the resumes went; writes JSON.

    .venv/bin/python benchmarks/stress.py [--kills 8] [--fuzz-examples 1000] [--seed 0] [-o benchmarks/out/stress]
        [--parts kill,lighting,fuzz] [--fuzz-tests PYTEST_K_EXPRESSION]
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent

QUICK = ["--set", "train.batch_rays=256", "--set", "vq.enabled=false", "--quiet"]


def tiny_scene():
    """tests/tiny_scene.py, the test suite's small captures, loaded from its file (tests/ is no package)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("tiny_scene", ROOT / "tests" / "tiny_scene.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


def kill_and_resume(capture: Path, tmp: Path, rng: np.random.Generator, i: int) -> dict:
    from vq_mitsuba import cli
    from vq_mitsuba.run.run_dir import RunDir
    from vq_mitsuba.errors import InputError

    every = int(rng.choice([1, 5, 20]))
    delay = float(rng.uniform(0.2, 4.0))
    run = tmp / f"run{i}"
    settings = ["--set", f"train.checkpoint_every={every}", *QUICK]
    proc = subprocess.Popen([sys.executable, "-m", "vq_mitsuba.cli", "fit", str(capture), "-o", str(run),
                             "--set", "train.iterations=100000", *settings],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.time() + 120
    while not (run / "checkpoint.pt").is_file() and time.time() < deadline:
        time.sleep(0.05)
    time.sleep(delay)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    case = {"checkpoint_every": every, "kill_after_first_checkpoint_s": delay}
    try:
        step = RunDir(run).load_state()["step"]
        case["checkpoint_step"], case["torn"] = int(step), False
    except InputError as exc:
        case.update(torn=True, error=str(exc))
        return case
    target = step + 20
    code = cli.main(["fit", str(capture), "-o", str(run), "--resume", *settings, "--set", f"train.iterations={target}"])
    fit = json.loads((run / "fit.json").read_text()) if (run / "fit.json").is_file() else {}
    case["resumed"] = code == 0 and fit.get("iterations") == target
    return case


def lighting_extremes(capture: Path, tmp: Path) -> dict:
    from vq_mitsuba import cli
    from vq_mitsuba.data.captures import load_cameras
    from vq_mitsuba.run.run_dir import RunDir
    from vq_mitsuba.errors import InputError
    from vq_mitsuba.render.views import Renderer

    run = tmp / "numerics"
    cli.main(["fit", str(capture), "-o", str(run), "--set", "train.iterations=60", *QUICK])
    fitted = RunDir(run).load()
    cam = load_cameras(capture)[0][0]
    counts = {"tried": 0, "rendered": 0, "refused": 0, "nonfinite": 0, "tracebacks": 0}
    for scale_exp in range(-40, 41, 5):
        for ev in (-64.0, -20.0, 0.0, 20.0, 64.0):
            counts["tried"] += 1
            try:
                out = Renderer(fitted, envmap=fitted.envmap * 10.0 ** scale_exp, exposure_ev=ev).render(cam, spp=8)
            except InputError:
                counts["refused"] += 1
                continue
            except Exception:  # noqa: BLE001 - what the suite counts
                counts["tracebacks"] += 1
                continue
            counts["rendered"] += 1
            counts["nonfinite"] += int(any(not np.isfinite(v).all() for v in out.values()
                                           if isinstance(v, np.ndarray) and v.dtype.kind == "f"))
    return counts


def loader_fuzz(examples: int, select: str | None, tmp: Path) -> dict:
    """The fuzz tests with `examples` Hypothesis examples each; per test, how many examples loaded,
    were refused with an InputError, held NaN/Inf or ended in another exception (from the tests'
    $VQM_FUZZ_TALLY lines)."""
    tally = tmp / "fuzz_tally.txt"
    env = {**os.environ, "VQM_FUZZ_EXAMPLES": str(examples), "VQM_FUZZ_TALLY": str(tally)}
    proc = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider",
                           str(ROOT / "tests" / "data" / "test_fuzz_captures.py"), *(["-k", select] if select else [])],
                          env=env, capture_output=True, text=True)
    last = proc.stdout.strip().splitlines()[-1] if proc.stdout.strip() else proc.stderr[-500:]
    tests: dict[str, dict[str, int]] = {}
    for line in tally.read_text().splitlines() if tally.is_file() else []:
        test, outcome = line.split()
        counts = tests.setdefault(test, {"examples": 0, "loaded": 0, "refused": 0, "nonfinite": 0, "traceback": 0})
        counts["examples"] += 1
        counts[outcome] += 1
    return {"examples_per_test": examples, "select": select, "tests": tests, "pytest": last,
            "pytest_returncode": proc.returncode, "tracebacks": sum(c["traceback"] for c in tests.values()),
            "nonfinite": sum(c["nonfinite"] for c in tests.values())}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--kills", type=int, default=8)
    p.add_argument("--fuzz-examples", type=int, default=1000)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("-o", "--output", default=str(ROOT / "benchmarks" / "out" / "stress"))
    p.add_argument("--parts", default="kill,lighting,fuzz", help="which parts to run (comma-separated)")
    p.add_argument("--fuzz-tests", default=None, help="a pytest -k expression choosing the fuzz tests (default all)")
    args = p.parse_args()
    parts = set(args.parts.split(","))

    from provenance import provenance, write_result

    write_sphere_capture = tiny_scene().write_sphere_capture
    rng = np.random.default_rng(args.seed)
    report = {"parts": sorted(parts)}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        capture = write_sphere_capture(tmp / "cap", size=16, n_views=6, spp=8) if parts & {"kill", "lighting"} else None
        if "kill" in parts:
            kills = [kill_and_resume(capture, tmp, rng, i) for i in range(args.kills)]
            report["kill_resume"] = {"cases": kills, "tried": len(kills), "torn": sum(k["torn"] for k in kills),
                                     "resumed": sum(bool(k.get("resumed")) for k in kills)}
            print(f"kill -9 + resume: {len(kills)} tried, {report['kill_resume']['torn']} torn checkpoints, "
                  f"{report['kill_resume']['resumed']} resumed and finished", flush=True)
        if "lighting" in parts:
            report["lighting_extremes"] = lighting_extremes(capture, tmp)
            print(f"lighting extremes: {report['lighting_extremes']}", flush=True)
        if "fuzz" in parts:
            fuzz = report["fuzz"] = loader_fuzz(args.fuzz_examples, args.fuzz_tests, tmp)
            for test, counts in fuzz["tests"].items():
                print(f"loader fuzz {test}: {counts}")
            print(f"loader fuzz: {args.fuzz_examples} examples x {len(fuzz['tests'])} tests, "
                  f"{fuzz['tracebacks']} tracebacks, {fuzz['nonfinite']} with NaN/Inf: {fuzz['pytest']}")
    out = Path(args.output)
    out.mkdir(parents=True, exist_ok=True)
    path = write_result(out / f"stress_{provenance()['commit']}.json", report)
    print(f"written {path}")


if __name__ == "__main__":
    main()
