"""A stop by signal during the geometry stage keeps its work: NeuS writes its checkpoint, the run's
lock is released, the command exits 128 + the signal without a stack dump (pycolmap's glog, which
the stage imports for its sparse points, must not take the signal), and `--resume` continues."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from tiny_scene import write_sphere_capture
from vq_mitsuba import cli
from vq_mitsuba.geometry.neus import CHECKPOINT as NEUS_CHECKPOINT
from vq_mitsuba.run.run_dir import RunDir

NEUS = ["--set", "neus.iterations=100000", "--set", "neus.time_limit_s=0", "--set", "neus.checkpoint_every=20",
        "--set", "neus.mesh_resolution=32", "--set", "neus.hull_resolution=32", "--set", "neus.normal_smoothing=0"]


@pytest.mark.slow  # over 10 s: CI runs it after the default suite (.ci/run)
@pytest.mark.parametrize("command", ["geometry", "fit"])
def test_a_signal_during_neus_keeps_its_checkpoint_and_the_run_resumes(tmp_path, command):
    capture = write_sphere_capture(tmp_path / "cap", size=16, n_views=6, spp=8)
    run = tmp_path / "run"
    extra = ["--geometry", "neus", "--set", "train.iterations=3", "--set", "train.batch_rays=64",
             "--set", "vq.enabled=false", "--set", "residual.iterations=0"] if command == "fit" else []
    env = {**os.environ, "PYTHONPATH": str(Path(cli.__file__).resolve().parents[2])}
    proc = subprocess.Popen([sys.executable, "-m", "vq_mitsuba.cli", command, str(capture), "-o", str(run), "--quiet",
                             *NEUS, *extra], env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 120
        while not (run / NEUS_CHECKPOINT).is_file():
            assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()
            time.sleep(0.1)
        time.sleep(0.5)
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=120)
    finally:
        proc.kill()
    assert proc.returncode == 143, err[-2000:]
    assert b"SIGTERM" not in err and b"stack trace" not in err and b"Traceback" not in err
    assert b"interrupted; the last checkpoint is kept" in err
    assert not (run / RunDir.LOCK).exists()
    step = torch.load(run / NEUS_CHECKPOINT, weights_only=False)["step"]
    assert step >= 20
    resumed = [a.replace("100000", str(step + 10)) for a in NEUS]
    assert cli.main([command, str(capture), "-o", str(run), "--resume", "--quiet", *resumed, *extra]) == 0
    assert torch.load(run / NEUS_CHECKPOINT, weights_only=False)["step"] == step + 10
    assert (run / RunDir.MESH).is_file() and (run / RunDir.GEOMETRY).is_file()


def _stop_when(proc: subprocess.Popen, ready, what: str, timeout: float = 180) -> bytes:
    """SIGTERM to `proc` once `ready()`; its stderr once it has ended."""
    try:
        deadline = time.monotonic() + timeout
        while not ready():
            if proc.poll() is not None or time.monotonic() > deadline:
                pytest.fail(f"{what} was not reached: {proc.communicate()}")
            time.sleep(0.05)
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=120)
    finally:
        proc.kill()
    return err


def _stopped_cleanly(proc: subprocess.Popen, err: bytes) -> None:
    assert proc.returncode == 143, err[-2000:]
    assert b"Traceback" not in err and b"stack trace" not in err and b"SIGTERM" not in err, err[-2000:]
    assert err.decode().strip().splitlines()[-1].startswith("interrupted"), err[-2000:]


@pytest.fixture(scope="module")
def photos(tmp_path_factory):
    """24 photos of a textured scene around it, without poses (the SfM tests' own)."""
    from orbit_photos import write_photos

    folder = tmp_path_factory.mktemp("orbit") / "photos"
    write_photos(folder, n=24)
    return folder


@pytest.mark.parametrize("command", ["pose", "fit"])
def test_a_signal_during_structure_from_motion_leaves_no_half_pose_and_says_how_to_go_on(photos, tmp_path,
                                                                                        monkeypatch, command):
    """SIGTERM while COLMAP poses the photos (`pose`, or `fit` of a photo folder): exit 143 without a
    stack dump, no half-written model or scratch folder, the run's lock released, and a last line
    that says what was kept and how to go on; `fit` run again as it says poses the photos and goes
    on to the next stages (stand-ins here: NeuS and the material fit have their own tests)."""
    import vq_mitsuba.engine.pipeline as pipeline
    from vq_mitsuba.config import load_config

    out = tmp_path / ("posed" if command == "pose" else "run")
    scratch = out.parent / ".posed.pose-tmp" if command == "pose" else out / f".{RunDir.POSE}.pose-tmp"
    env = {**os.environ, "PYTHONPATH": str(Path(cli.__file__).resolve().parents[2])}
    proc = subprocess.Popen([sys.executable, "-m", "vq_mitsuba.cli", command, str(photos), "-o", str(out), "--quiet"],
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    err = _stop_when(proc, lambda: (scratch / "database.db").is_file(), "structure from motion")
    _stopped_cleanly(proc, err)
    assert not scratch.exists() and not (out / "sparse").exists() and not (out / RunDir.POSE).exists()
    assert not out.exists()  # nothing was written yet, and the folder the command made is gone
    if command == "pose":
        assert b"nothing half-written is kept (run the same command again)" in err
        return
    assert b"nothing was kept yet (run the same command again, without --resume)" in err
    seen = []
    monkeypatch.setattr(pipeline, "ensure_geometry", lambda capture, run, *a, **k: seen.append(capture) or
                        run / RunDir.MESH)
    monkeypatch.setattr(pipeline, "fit_materials", lambda capture, *a, **k: seen.append(capture) or {"iterations": 1})
    pipeline.fit_capture(photos, out, load_config(None, []), log=lambda line: None)
    assert [c.source for c in seen] == [out / RunDir.POSE] * 2 and (out / RunDir.POSE_SUMMARY).is_file()


# the residual made to run until a signal ends it (no early stop, no bound by the pool's size); a file
# tells when its steps have begun
_LONG_RESIDUAL = """
import sys
from pathlib import Path
import vq_mitsuba.engine.residual_fit as residual_fit
residual_fit.PATIENCE = residual_fit.MAX_EPOCHS = 10 ** 9
radiance = residual_fit.physical_radiance
def physical_radiance(*args, **kwargs):
    out = radiance(*args, **kwargs)
    Path(sys.argv[1]).touch()
    return out
residual_fit.physical_radiance = physical_radiance
from vq_mitsuba import cli
sys.exit(cli.main(sys.argv[2:]))
"""


def test_a_signal_during_the_residual_keeps_the_material_fit_and_the_run_resumes(tmp_path):
    """SIGTERM while the residual is fitted, after the material fit's last step: exit 143 without a
    stack dump, the material fit's checkpoint kept at its last step and no residual written; `fit
    --resume` trains no step again and fits the residual."""
    capture = write_sphere_capture(tmp_path / "cap", size=16, n_views=4, spp=8)
    run = RunDir(tmp_path / "run")
    started = tmp_path / "residual-started"
    quick = ["--set", "train.iterations=8", "--set", "train.batch_rays=64", "--set", "vq.enabled=false"]
    env = {**os.environ, "PYTHONPATH": str(Path(cli.__file__).resolve().parents[2])}
    proc = subprocess.Popen([sys.executable, "-c", _LONG_RESIDUAL, str(started), "fit", str(capture), "-o",
                             str(run.dir), "--quiet", *quick, "--set", "residual.iterations=100000"],
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    err = _stop_when(proc, started.is_file, "the residual")
    _stopped_cleanly(proc, err)
    assert not (run / RunDir.LOCK).exists() and not (run / RunDir.RESIDUAL).exists() and not run.fit_summary()
    assert run.load_state()["step"] == 8
    assert cli.main(["fit", str(capture), "-o", str(run.dir), "--resume", "--quiet", *quick,
                     "--set", "residual.iterations=50"]) == 0
    summary = run.fit_summary()
    assert summary["steps_this_call"] == 0 and summary["iterations"] == 8 and summary["residual"]["iterations"] > 0
    assert run.residual_state(8) is not None


def _ray_processes() -> set[str]:
    found = subprocess.run(["pgrep", "-f", "raylet|gcs_server|ray::"], capture_output=True, text=True).stdout
    return set(found.split())


# a batch of one fit of a few seconds (about 70 steps a second on one core), checkpointed often
BATCH = ["--set", "train.iterations=400", "--set", "train.batch_rays=64", "--set", "train.checkpoint_every=5",
         "--set", "vq.enabled=false"]


def _batch_with_a_checkpoint(capture, out: Path) -> subprocess.Popen:
    """A batch of one fit, in its own process, once that fit has written its first checkpoint."""
    env = {**os.environ, "PYTHONPATH": str(Path(cli.__file__).resolve().parents[2])}
    proc = subprocess.Popen([sys.executable, "-m", "vq_mitsuba.cli", "batch", str(capture), "-o", str(out), "--quiet",
                             *BATCH], env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 180
    while not any(out.glob("*/checkpoint.pt")):
        if proc.poll() is not None or time.monotonic() > deadline:
            proc.kill()
            pytest.fail(f"the batch did not reach a checkpoint: {proc.communicate()}")
        time.sleep(0.2)
    return proc


@pytest.mark.slow  # over 10 s: CI runs it after the default suite (.ci/run)
def test_a_sigterm_to_a_batch_exits_143_leaves_no_ray_process_and_the_batch_resumes(tmp_path, capsys):
    capture = write_sphere_capture(tmp_path / "cap", size=16, n_views=4, spp=8)
    out = tmp_path / "batch"
    before = _ray_processes()
    proc = _batch_with_a_checkpoint(capture, out)
    try:
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=120)
    finally:
        proc.kill()
    assert proc.returncode == 143, err[-2000:]
    assert b"Traceback" not in err and b"stack trace" not in err and b"interrupted; finished runs" in err
    time.sleep(2)  # Ray's processes end with the batch
    assert _ray_processes() <= before
    assert (out / "batch.json").is_file()  # stopped before its first run finished, and still a batch
    run = RunDir(next(out.glob("*-s0")))
    stopped_at = run.load_state()["step"]
    assert 5 <= stopped_at < 400
    # a rerun asking for other settings leaves the run as it is and says so, naming the key
    other = [a.replace("=400", "=12") for a in BATCH]
    assert cli.main(["batch", str(capture), "-o", str(out), "--quiet", *other]) == 1
    err = capsys.readouterr().err
    assert "refused" in err and "train.iterations=400 (asked 12)" in err, err
    assert run.load_state()["step"] == stopped_at and not run.fit_summary()
    # with its own settings it resumes from its checkpoint and finishes
    assert cli.main(["batch", str(capture), "-o", str(out), "--quiet", *BATCH]) == 0
    assert run.fit_summary()["iterations"] == 400 and run.fit_summary()["steps_this_call"] == 400 - stopped_at


@pytest.mark.parametrize("args, message", [
    (["--threads-per-run", "4096"], "no run could ever start"),
    (["--address", "ray://127.0.0.1:1"], "Ray could not start or connect"),
    (["--address", "garbage!!"], "Ray could not start or connect"),
    (["--seeds", "0,99999999999999"], "seeds from 0 to"),
])
def test_a_batch_that_cannot_start_says_why_and_leaves_no_folder(tmp_path, capsys, args, message):
    capture = write_sphere_capture(tmp_path / "cap", size=16, n_views=4, spp=8)
    out = tmp_path / "batch"
    assert cli.main(["batch", str(capture), "-o", str(out), "--quiet", *args]) == 2
    assert message in capsys.readouterr().err and not out.exists()


def test_geometry_resume_of_a_missing_folder_is_refused(tmp_path, capsys):
    capture = write_sphere_capture(tmp_path / "cap", size=16, n_views=4, spp=8)
    assert cli.main(["geometry", str(capture), "-o", str(tmp_path / "nothing"), "--resume", "--quiet"]) == 2
    assert "no run to resume" in capsys.readouterr().err and not (tmp_path / "nothing").exists()


@pytest.mark.slow  # over 10 s: CI runs it after the default suite (.ci/run)
def test_a_killed_batch_leaves_no_ray_process(tmp_path):
    """kill -9 gives the batch no time to stop Ray: a watchdog ends the Ray processes it started."""
    capture = write_sphere_capture(tmp_path / "cap", size=16, n_views=4, spp=8)
    out = tmp_path / "batch"
    before = _ray_processes()
    proc = _batch_with_a_checkpoint(capture, out)
    try:
        assert _ray_processes() - before  # Ray runs
    finally:
        proc.kill()
        proc.wait()
    deadline = time.monotonic() + 30
    while _ray_processes() - before and time.monotonic() < deadline:
        time.sleep(0.5)
    assert not _ray_processes() - before
