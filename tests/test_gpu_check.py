"""benchmarks/gpu_check.py, the device check, runs end to end on the CPU (--device cpu, tiny sizes),
so that the minutes on a GPU machine go to measuring."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


@pytest.mark.slow  # over 10 s: CI runs it after the default suite (.ci/run)
def test_the_device_check_runs_end_to_end_on_the_cpu(tmp_path):
    out = tmp_path / "gpu_check.json"
    done = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "gpu_check.py"), "--device", "cpu", "--size", "32",
                           "--quick", "--out", str(out), "--work", str(tmp_path / "work"), "--neus-batches", "64", "128",
                           "--fit-batches", "64", "--rate-steps", "2", "--budget", "600"],
                          cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
    result = json.loads(out.read_text())
    assert result["device"]["requested"] == "cpu" and result["device"]["used"] == "cpu"
    assert result["tests"]["exit"] == 0 and "passed" in result["tests"]["summary"]
    assert result["make_scene"]["exit"] == 0 and result["make_scene"]["seconds"] > 0
    recorded = {"requested": "cpu", "used": "cpu", "variant": "llvm_ad_rgb", "torch_device": "cpu"}
    for label in ("images", "true_mesh"):
        run = result[label]
        assert run["stages"]["fit"]["exit"] == 0 and run["stages"]["eval"]["exit"] == 0, label
        assert run["device"] == recorded, label  # run.json's record
        assert run["fit"]["iterations_per_s"] > 0 and run["figures"]["basecolor_psnr"] > 10, label
    assert result["images"]["neus"]["iterations_per_s"] > 0 and result["images"]["neus"]["device"] == recorded
    assert result["true_mesh"]["neus"] is None  # the true mesh: no NeuS stage
    rates = result["rates"]  # the step-rate sweep, with the fits' batches (--quick's)
    assert rates["exit"] == 0 and rates["device_scale"] == 1 and rates["default"] == {"neus": 256, "fit": 256}
    assert [r["batch_rays"] for r in rates["neus"]] == [64, 128] and [r["batch_rays"] for r in rates["fit"]] == [64]
    assert all(r["seconds_per_step"] > 0 and r["rays_per_s"] > 0 for r in rates["neus"] + rates["fit"])
    assert {"commit", "machine", "versions"} <= set(result)  # the provenance block
