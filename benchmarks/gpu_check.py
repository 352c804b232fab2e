"""The device check: one command that says what a machine's device is and what it buys.

    python benchmarks/gpu_check.py --device cuda --out benchmarks/out/gpu_check.json   # on a GPU machine
    python benchmarks/gpu_check.py --device cpu --size 32 --quick                      # end to end on a CPU

(a) prints the device the process chooses (`vq_mitsuba.backend.choose_device`), the versions and the
    memory; (b) runs the suite's GPU-relevant tests (`pytest -q` on --tests); (c) renders tabletop at
    --size pixels into a temporary folder (`make-scene`), fits it from its images (NeuS, then the
    materials) and from its true mesh, each with `--device`, and scores both runs (`eval --gt`),
    timing each stage; (d) writes one JSON (--out) with the stage times, the step rates (the runs'
    fit.json and geometry.json), the devices the runs recorded (run.json) and the eval figures.
--quick shrinks everything (views, samples, steps) so that the whole script runs in about a minute
on two CPU cores: it checks the script, not the device. Each stage is a child process (`python -m
vq_mitsuba.cli ...`), as a user runs it; a failed stage is recorded and the script goes on.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from provenance import command_line, provenance, write_result

ROOT = Path(__file__).resolve().parent.parent
GPU_TESTS = ["tests/test_geometry.py", "tests/test_fit.py", "tests/test_rendering.py"]
QUICK_TESTS = ["tests/test_device.py"]
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


def run_stage(name: str, argv: list[str], log: Path, timeout: float) -> dict:
    """One child process, its wall time and exit status; its output goes to `log`."""
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


def run_tests(tests: list[str], log: Path, timeout: float) -> dict:
    """pytest -q on `tests`, with its summary line."""
    stage = run_stage("tests", [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", *tests], log,
                      timeout)
    lines = [ln for ln in log.read_text().splitlines() if " passed" in ln or " failed" in ln or " error" in ln]
    return {**stage, "files": tests, "summary": lines[-1].strip("= ") if lines else None}


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
                    + [x for s in settings for x in ("--set", s)], log, args.timeout)
    score = run_stage(f"eval ({label})", cli + ["eval", str(run), "--gt", str(scene), "-o", str(metrics), "--quiet",
                                                "--device", args.device, *eval_options], log, args.timeout) \
        if fit["exit"] == 0 else {"exit": "skipped (the fit failed)"}
    return {"stages": {"fit": fit, "eval": score}, **run_summary(run, metrics)}


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--device", choices=["auto", "cpu", "cuda"], default="auto", help="the --device of every stage")
    p.add_argument("--size", type=int, default=200, help="tabletop's image size in pixels (make-scene --resolution)")
    p.add_argument("--quick", action="store_true", help="few views, samples and steps: checks the script itself")
    p.add_argument("--tests", nargs="*", help="test files to run (default: the GPU-relevant ones; none: skip)")
    p.add_argument("--out", default="benchmarks/out/gpu_check.json", help="the JSON to write")
    p.add_argument("--work", help="keep the scene, runs and log in this folder (default: a temporary one)")
    p.add_argument("--timeout", type=float, default=1800, help="seconds each stage may take")
    return p.parse_args(argv)


def main(argv=None) -> int:
    args = parse_args(argv)
    start = time.perf_counter()
    block = {**provenance(), "command": command_line(sys.argv[1:] if argv is None else argv, Path(__file__))}
    device = device_report(args.device)
    print(json.dumps(device, indent=1), flush=True)
    work = Path(args.work) if args.work else Path(tempfile.mkdtemp(prefix="gpu_check_"))
    work.mkdir(parents=True, exist_ok=True)
    log = work / "gpu_check.log"
    tests = QUICK_TESTS if (args.quick and args.tests is None) else GPU_TESTS if args.tests is None else args.tests
    result = {"device": device, "size": args.size, "quick": args.quick,
              "tests": run_tests(tests, log, args.timeout) if tests else None}
    scene = work / "tabletop"
    options = (QUICK if args.quick else FULL)[0]
    result["make_scene"] = run_stage("make-scene", [sys.executable, "-m", "vq_mitsuba.cli", "make-scene", "tabletop",
                                                    "-o", str(scene), "--resolution", str(args.size), *options],
                                     log, args.timeout)
    if result["make_scene"]["exit"] == 0:
        result["images"] = fit_and_score("images", scene, work, args, ["--geometry", "neus"], log)
        result["true_mesh"] = fit_and_score("true_mesh", scene, work, args, ["--mesh", str(scene / "mesh.ply")],
                                            log)
    result["seconds"] = round(time.perf_counter() - start, 1)
    path = write_result(Path(args.out), {**block, **result})
    print(f"wrote {path} in {result['seconds']:.0f} s (log: {log})")
    if not args.work:
        shutil.copy(log, Path(args.out).with_suffix(".log"))
        shutil.rmtree(work, ignore_errors=True)
    failed = [s for s in ("images", "true_mesh") if result.get(s, {}).get("stages", {}).get("eval", {}).get("exit") != 0]
    return 1 if failed or result["make_scene"]["exit"] != 0 or (result["tests"] or {}).get("exit", 0) != 0 else 0


if __name__ == "__main__":
    sys.exit(main())
