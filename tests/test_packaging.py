"""The package as a user installs it: `python -m build` makes a wheel and an sdist, and the wheel,
installed into a fresh virtual environment, runs from a folder outside the checkout with its
bundled presets and scenes (a 5-step demo fit)."""

import json
import os
import subprocess
import sys
import sysconfig
import tarfile
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def dist(tmp_path_factory):
    out = tmp_path_factory.mktemp("dist")
    subprocess.run([sys.executable, "-m", "build", "--no-isolation", "--outdir", str(out), str(ROOT)],
                   check=True, capture_output=True, text=True)
    return out


@pytest.fixture(scope="module")
def venv(dist, tmp_path_factory):
    """A fresh environment holding the wheel; its dependencies (torch, Mitsuba, ...) are read from
    this environment's site-packages, whose editable install of the checkout is not loaded."""
    env = tmp_path_factory.mktemp("venv") / "env"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(env)], check=True)
    python = env / "bin" / "python"
    purelib = Path(subprocess.run([str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                                  check=True, capture_output=True, text=True).stdout.strip())
    (purelib / "dependencies.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    wheel = next(dist.glob("*.whl"))
    # --ignore-installed: the checkout's own install (editable, or its egg-info on a PYTHONPATH) is
    # not the package under test
    subprocess.run([sys.executable, "-m", "pip", "--python", str(python), "install", "-q", "--no-deps", "--no-index",
                    "--ignore-installed", str(wheel)], check=True, capture_output=True, text=True, env=_clean_env())
    return env


def _clean_env() -> dict:
    return {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}


def _run(env: Path, cwd: Path, *args: str) -> str:
    done = subprocess.run([str(env / "bin" / "vq-mitsuba"), *args], cwd=cwd, env=_clean_env(), capture_output=True,
                          text=True)
    assert done.returncode == 0, done.stderr[-3000:]
    return done.stdout


def test_wheel_and_sdist_hold_the_presets_and_scenes(dist):
    wheel = zipfile.ZipFile(next(dist.glob("*.whl"))).namelist()
    sdist = tarfile.open(next(dist.glob("*.tar.gz"))).getnames()
    for name in ("vq_mitsuba/presets/demo.yaml", "vq_mitsuba/synthetic/scenes/demo.yaml",
                 "vq_mitsuba/synthetic/scenes/tabletop.yaml", "vq_mitsuba/ui/static/index.html",
                 "vq_mitsuba/geometry/neus/grid_kernel.c", "vq_mitsuba/models/material_library.json"):
        assert name in wheel, name
        assert any(n.endswith("/" + name) for n in sdist), name
    assert not any(n.startswith(("tests/", "benchmarks/")) for n in wheel)


@pytest.mark.slow  # over 10 s: CI runs it after the default suite (.ci/run)
def test_the_installed_wheel_runs_outside_the_checkout(venv, tmp_path):
    code = "import vq_mitsuba; print(vq_mitsuba.__file__)"
    where = subprocess.run([str(venv / "bin" / "python"), "-c", code], cwd=tmp_path, capture_output=True, text=True,
                           env=_clean_env()).stdout
    assert Path(where).resolve().is_relative_to(venv.resolve()), where
    assert _run(venv, tmp_path, "--version").split() == ["vq-mitsuba", "0.1.0"]
    listed = _run(venv, tmp_path, "make-scene", "--list")
    assert all(name in listed for name in ("demo", "texture", "balls", "polished", "tabletop"))
    presets = _run(venv, tmp_path, "fit", "--help-config")
    assert "continuous" in presets and "ablation_separate" in presets
    _run(venv, tmp_path, "make-scene", "demo", "-o", "data", "--resolution", "16", "--n-train", "4", "--n-test", "1",
         "--spp", "4")
    settings = ["train.iterations=5", "train.batch_rays=64", "train.spp=2", "train.checkpoint_every=1000",
                "vq.rank_pixels=64", "residual.iterations=0", "render.spp=4"]
    _run(venv, tmp_path, "fit", "data/scene.xml", "-o", "run", "--preset", "demo", "--quiet",
         *[arg for item in settings for arg in ("--set", item)])
    fitted = json.loads((tmp_path / "run" / "fit.json").read_text())
    assert fitted["iterations"] == 5 and (tmp_path / "run" / "materials.json").is_file()
