"""Fit speed beside a busy neighbour process: steps per second of a time-limited demo fit, idle and
with one process spinning on a core, with OpenMP's threads waiting passively (the default) or as
torch leaves them when it is imported before vq_mitsuba (spinning a while at every wait).

    .venv/bin/python benchmarks/bench_load.py [--capture data/demo/scene.xml] [--seconds 15] [--repeats 3]
        [--modes passive torch_default] [--threads N] [-o benchmarks/out/load]

Each fit is `vq-mitsuba fit CAPTURE --preset demo --set train.time_limit_s=S` in a fresh process;
the rate is fit.json's iterations_per_s. Writes OUT/load_<commit>.json and prints the medians and
the busy / idle ratio per mode.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

# torch_default: torch (and its OpenMP runtime) is loaded before vq_mitsuba can set the wait policy.
LAUNCH = {
    "passive": "from vq_mitsuba.cli import main; import sys; sys.exit(main(sys.argv[1:]))",
    "torch_default": "import torch; from vq_mitsuba.cli import main; import sys; sys.exit(main(sys.argv[1:]))",
}


def one_fit(mode: str, capture: str, seconds: float, threads: int | None) -> float:
    with tempfile.TemporaryDirectory() as tmp:
        argv = ["fit", capture, "-o", f"{tmp}/run", "--preset", "demo", "--quiet",
                "--set", f"train.time_limit_s={seconds}"] + (["--threads", str(threads)] if threads else [])
        subprocess.run([sys.executable, "-c", LAUNCH[mode], *argv], check=True, capture_output=True, text=True)
        return json.loads(Path(f"{tmp}/run/fit.json").read_text())["iterations_per_s"]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--capture", default=str(ROOT / "data" / "demo" / "scene.xml"))
    p.add_argument("--seconds", type=float, default=15.0)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--modes", nargs="+", default=list(LAUNCH), choices=list(LAUNCH))
    p.add_argument("--threads", type=int)
    p.add_argument("-o", "--output", default=str(ROOT / "benchmarks" / "out" / "load"))
    args = p.parse_args()

    from provenance import provenance, write_result

    results = {}
    for mode in args.modes:
        for load in ("idle", "busy"):
            rates = []
            for _ in range(args.repeats):
                hog = subprocess.Popen([sys.executable, "-c", "while True: pass"]) if load == "busy" else None
                try:
                    rates.append(one_fit(mode, args.capture, args.seconds, args.threads))
                finally:
                    if hog is not None:
                        hog.kill()
                        hog.wait()
            results[f"{mode}/{load}"] = {"rates": rates, "median": statistics.median(rates)}
            print(f"{mode:14s} {load:5s} it/s {', '.join(f'{r:.2f}' for r in rates)} (median "
                  f"{statistics.median(rates):.2f})", flush=True)
        ratio = results[f"{mode}/busy"]["median"] / results[f"{mode}/idle"]["median"]
        results[f"{mode}/busy_over_idle"] = ratio
        print(f"{mode:14s} busy / idle = {ratio:.2f}", flush=True)
    out = Path(args.output)
    out.mkdir(parents=True, exist_ok=True)
    path = write_result(out / f"load_{provenance()['commit']}.json", {"seconds": args.seconds, "results": results})
    print(f"written {path}")


if __name__ == "__main__":
    main()
