"""`vq-mitsuba batch`: many runs as Ray tasks on a local Ray with 2 CPUs; a bad capture fails only
its own runs, a rerun skips finished runs, and a run whose worker is killed is retried and resumes."""

import csv
import json
import os
import signal
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from tiny_scene import write_sphere_capture
from vq_mitsuba import cli
from vq_mitsuba.batch import RunSpec, plan, run_batch
from vq_mitsuba.errors import InputError
from vq_mitsuba.run.run_dir import RunDir

QUICK = ["--set", "train.iterations=6", "--set", "train.batch_rays=128", "--set", "vq.enabled=false"]

ray = pytest.importorskip("ray")


@pytest.fixture(scope="module")
def local_ray():
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, object_store_memory=80 * 1024 ** 2)
    yield ray
    ray.shutdown()


@pytest.fixture(scope="module")
def captures(tmp_path_factory):
    root = tmp_path_factory.mktemp("captures")
    good = [write_sphere_capture(root / name, size=16, n_views=4, spp=8) for name in ("sphere_a", "sphere_b")]
    bad = root / "broken" / "scene.xml"
    bad.parent.mkdir()
    bad.write_text("<scene version='3.0.0'><sensor type='perspective'")  # truncated XML
    return [str(p) for p in good] + [str(bad)]


def _fits_started(out: Path, run: str) -> list[str]:
    return [line for line in (out / "logs" / f"{run}.log").read_text().splitlines() if line.startswith("$ vq-mitsuba fit")]


@pytest.mark.slow  # over 10 s: CI runs it after the default suite (.ci/run)
def test_a_batch_fits_every_capture_and_seed_and_a_rerun_skips_the_finished(local_ray, captures, tmp_path):
    out = tmp_path / "batch"
    rows = run_batch(captures, out, seeds=[0, 1], fit_args=QUICK)
    status = {r["run"]: r for r in rows}
    assert set(status) == {f"{c}-s{s}" for c in ("sphere_a", "sphere_b", "broken") for s in (0, 1)}
    for name, row in status.items():
        if name.startswith("broken"):
            assert row["status"] == "failed" and "scene.xml" in row["message"], row
            assert not (out / name / RunDir.CHECKPOINT).exists()
        else:
            assert row["status"] == "done", row
            assert RunDir(out / name).load_state()["step"] == 6
    # the seed reaches the fit: the two seeds' networks differ
    a0, a1 = (RunDir(out / f"sphere_a-s{s}").load_state()["model"] for s in (0, 1))
    assert any(not (a0[k] == a1[k]).all() for k in a0)
    with open(out / "summary.csv") as f:
        table = list(csv.DictReader(f))
    assert len(table) == 6 and {r["status"] for r in table} == {"done", "failed"}
    assert all(float(r["iterations"]) == 6 for r in table if r["status"] == "done")
    summary_md = (out / "summary.md").read_text()
    for name in status:  # a novel view of every finished run, shown in the summary
        view = out / "views" / f"{name}.png"
        assert view.is_file() == (not name.startswith("broken")), name
        if view.is_file():
            from vq_mitsuba.data.imageio import read_image

            rgb, alpha = read_image(view)
            assert rgb.shape[:2] == (16, 16) and np.isfinite(rgb).all() and alpha is not None and alpha.max() > 0.5
            assert f'src="views/{name}.png"' in summary_md

    again = run_batch(captures, out, seeds=[0, 1], fit_args=QUICK)
    assert [r["status"] for r in again] == [r["status"] for r in rows]
    for name in status:
        assert len(_fits_started(out, name)) == (2 if name.startswith("broken") else 1), name


@pytest.mark.slow  # over 10 s: CI runs it after the default suite (.ci/run)
def test_a_batch_evaluates_held_out_views_and_shows_one(local_ray, captures, tmp_path):
    """--eval on a capture fitted with held-out views: eval scores them, the summary holds the
    score, and the run's picture is its first held-out view."""
    from vq_mitsuba.batch import preview_camera

    out = tmp_path / "batch"
    rows = run_batch(captures[:1], out, seeds=[0], fit_args=[*QUICK, "--set", "capture.holdout=2"], evaluate=True)
    assert rows[0]["status"] == "done", rows
    with open(out / "summary.csv") as f:
        row = next(csv.DictReader(f))
    assert 5.0 < float(row["novel_view_psnr"]) < 60.0
    run = RunDir(out / "sphere_a-s0")
    held = [v["view"] for v in json.loads((run / RunDir.METRICS).read_text())["views"]]
    assert preview_camera(run).name == held[0]
    assert (out / "views" / "sphere_a-s0.png").is_file()


@pytest.mark.slow  # over 10 s: CI runs it after the default suite (.ci/run)
def test_a_rerun_with_other_settings_refuses_the_runs_it_would_change_and_the_summary_shows_each_runs_own(
        local_ray, captures, tmp_path):
    """A rerun asking for other settings than a run's own (here train.iterations) leaves that run as
    it is and says so, naming the key; a new run takes the new settings; the summary shows each
    run's own iterations and a digest of its settings."""
    out = tmp_path / "batch"
    assert run_batch(captures[:1], out, seeds=[0], fit_args=QUICK)[0]["status"] == "done"
    fewer = [*QUICK, "--set", "train.iterations=4"]
    rows = {r["run"]: r for r in run_batch(captures[:2], out, seeds=[0], fit_args=fewer)}
    kept = rows["sphere_a-s0"]
    assert kept["status"] == "refused", kept
    assert "train.iterations=6 (asked 4)" in kept["message"] and "batch_rays" not in kept["message"]
    assert rows["sphere_b-s0"]["status"] == "done", rows
    assert RunDir(out / "sphere_a-s0").load_state()["step"] == 6 and len(_fits_started(out, "sphere_a-s0")) == 1
    assert RunDir(out / "sphere_b-s0").load_state()["step"] == 4
    assert json.loads((out / "batch.json").read_text())["runs"]["sphere_a-s0"]["status"] == "refused"
    with open(out / "summary.csv") as f:
        table = {r["run"]: r for r in csv.DictReader(f)}
    assert (table["sphere_a-s0"]["train_iterations"], table["sphere_a-s0"]["iterations"]) == ("6", "6")
    assert (table["sphere_b-s0"]["train_iterations"], table["sphere_b-s0"]["iterations"]) == ("4", "4")
    digests = {name: row["settings"] for name, row in table.items()}
    assert all(len(d) == 8 for d in digests.values()) and digests["sphere_a-s0"] != digests["sphere_b-s0"]
    summary_md = (out / "summary.md").read_text()
    assert "| sphere_a-s0 | refused: its settings differ" in summary_md and "| 6 of 6 |" in summary_md
    assert "| 4 of 4 |" in summary_md
    # asked again with its own settings, the run is done again, as it was
    again = {r["run"]: r for r in run_batch(captures[:1], out, seeds=[0], fit_args=QUICK)}
    assert again["sphere_a-s0"]["status"] == "done" and RunDir(out / "sphere_a-s0").load_state()["step"] == 6


def test_a_try_waits_for_the_process_still_holding_its_run(captures, tmp_path):
    """The fit of a try whose worker or node was lost may still be writing its checkpoint when the
    retry starts: the retry waits for it to let go of the run rather than fail on its lock."""
    from vq_mitsuba.batch import run_one
    from vq_mitsuba.run.lock import RunLock

    out = tmp_path / "batch"
    spec = plan(captures[:1], [0], [None])[0]
    log = out / "logs" / f"{spec.name}.log"
    held = threading.Event()

    def earlier_try():  # ends once the try has seen it (or after 60 s)
        with RunLock(out / spec.name / RunDir.LOCK, "fit"):
            held.set()
            deadline = time.monotonic() + 60
            while time.monotonic() < deadline and not (log.is_file() and "held by another" in log.read_text()):
                time.sleep(0.05)

    holder = threading.Thread(target=earlier_try)
    holder.start()
    held.wait(10)
    record = run_one(spec, str(out), QUICK, 1, False, call="c")
    holder.join()
    assert record["status"] == "done", record
    assert RunDir(out / spec.name).load_state()["step"] == 6


def _parent_pid(pid: int) -> int:
    return int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[1])


@pytest.mark.slow  # over 10 s: CI runs it after the default suite (.ci/run)
@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="finds the worker through /proc")
@pytest.mark.parametrize("target, sig", [("worker", signal.SIGKILL), ("fit", signal.SIGTERM)])
def test_a_run_whose_worker_is_killed_is_retried_and_resumes(local_ray, captures, tmp_path, target, sig):
    """SIGKILL of the Ray worker running a fit (a lost machine), or SIGTERM of the fit itself (a
    pre-empted job): the task is retried and the retry resumes from the checkpoint."""
    out = tmp_path / "batch"
    run = out / "sphere_a-s0"
    killed = {}

    def kill_the_worker():
        deadline = time.time() + 120
        while not (run / RunDir.CHECKPOINT).is_file() and time.time() < deadline:
            time.sleep(0.05)
        import json
        fit_pid = json.loads((run / RunDir.LOCK).read_text())["pid"]
        killed[target] = _parent_pid(fit_pid) if target == "worker" else fit_pid
        os.kill(killed[target], sig)

    watcher = threading.Thread(target=kill_the_worker)
    watcher.start()
    settings = ["--set", "train.iterations=400", "--set", "train.checkpoint_every=5", "--set", "train.batch_rays=128",
                "--set", "vq.enabled=false"]
    rows = run_batch(captures[:1], out, seeds=[0], fit_args=settings)
    watcher.join()
    assert killed and rows[0]["status"] == "done", rows
    starts = _fits_started(out, "sphere_a-s0")
    assert len(starts) == 2 and "--resume" in starts[1]
    summary = RunDir(run).fit_summary()
    assert RunDir(run).load_state()["step"] == 400
    assert 0 < summary["steps_this_call"] < 400  # the retry went on from the checkpoint


def test_batch_refuses_bad_plans_before_any_run(tmp_path, capsys):
    a, b = tmp_path / "x" / "cap", tmp_path / "y" / "cap"
    for folder in (a, b):
        folder.mkdir(parents=True)
    with pytest.raises(InputError, match="shares the name 'cap'"):
        plan([str(a), str(b)], [0], [None])
    assert plan([str(a)], [0, 3], ["demo"]) == [RunSpec("cap-demo-s0", str(a.resolve()), 0, "demo"),
                                                 RunSpec("cap-demo-s3", str(a.resolve()), 3, "demo")]
    other = tmp_path / "other"
    other.mkdir()
    (other / "notes.txt").write_text("mine")
    assert cli.main(["batch", str(a), "-o", str(other), "--quiet"]) == 2
    assert "holds other files" in capsys.readouterr().err and (other / "notes.txt").read_text() == "mine"
    assert cli.main(["batch", str(a), "-o", str(tmp_path / "new"), "--seeds", "1,x"]) == 2
    assert cli.main(["batch", str(a), "-o", str(tmp_path / "new"), "--set", "train.lr=-1"]) == 2
    assert not (tmp_path / "new").exists()
