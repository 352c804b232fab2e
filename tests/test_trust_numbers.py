"""Finite in, finite out; one message instead of an abort or a traceback; a fit that ends on a
signal keeps its checkpoint and releases its lock."""

import http.client
import json
import math
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from tiny_scene import write_sphere_capture
from vq_mitsuba import cli
from vq_mitsuba.config import load_config
from vq_mitsuba.errors import InputError, NumericalError
from vq_mitsuba.run.run_dir import RunDir

QUICK = ["--set", "train.iterations=6", "--set", "train.batch_rays=128", "--set", "vq.enabled=false", "--quiet"]


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    return write_sphere_capture(tmp_path_factory.mktemp("cap") / "cap", size=16, n_views=4, spp=8)


@pytest.fixture(scope="module")
def tiny_run(capture, tmp_path_factory):
    """A 6-step fit of the small sphere with both branches (M materials in materials.json)."""
    run = tmp_path_factory.mktemp("tiny") / "run"
    assert cli.main(["fit", str(capture), "-o", str(run), "--quiet", "--set", "train.iterations=6",
                     "--set", "train.batch_rays=128", "--set", "vq.warmup_frac=0.3", "--set",
                     "residual.iterations=0"]) == 0
    return run


def _copy(run: Path, tmp_path: Path) -> Path:
    out = tmp_path / "copy"
    shutil.copytree(run, out)
    return out


# --- values a user sets --------------------------------------------------------------------------
@pytest.mark.parametrize("item, phrase", [
    ("train.iterations=true", "'train.iterations' expects int, got true"),
    ("train.iterations=1.0e+30", "'train.iterations' must be a whole number within"),
    ("train.iterations=1e30", "'train.iterations' expects int"),
    ("train.lr=1e30", "train.lr must be in (0, 1]"),
    ("envmap.lr=2", "envmap.lr must be in (0, 1]"),
    ("envmap.height=1", "envmap.height must be >= 2"),
    ("neus.mesh_resolution=100000", "neus.mesh_resolution must be in [2, 1024]"),
    ("loss.w_vq=.nan", "must be a finite number"),
])
def test_config_values_outside_what_the_code_takes_are_refused(item, phrase):
    with pytest.raises(InputError) as exc:
        load_config(None, [item])
    assert phrase in str(exc.value) and str(exc.value).startswith("--set: ")


def test_yaml_booleans_are_not_step_counts(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_text("train:\n  iterations: true\n")
    with pytest.raises(InputError, match="'train.iterations' expects int, got true") as exc:
        load_config(path)
    assert exc.value.path == path
    assert load_config(None, ["envmap.height=2", "train.lr=1"]).envmap.height == 2


def test_threads_beyond_four_per_core_are_one_message(capture, tmp_path, capsys):
    assert cli.main(["fit", str(capture), "-o", str(tmp_path / "run"), "--threads", "100000", "--quiet"]) == 2
    assert "--threads 100000: expected 1 to" in capsys.readouterr().err
    assert not (tmp_path / "run").exists()


def test_a_negative_scene_seed_is_refused(tmp_path, capsys):
    assert cli.main(["make-scene", "balls", "--seed", "-5", "-o", str(tmp_path / "scene")]) == 2
    assert "--seed -5: a seed is a whole number from 0" in capsys.readouterr().err
    assert not (tmp_path / "scene").exists()
    from vq_mitsuba.synthetic.cycles import make_scene_cycles  # the same check, before Blender is looked for

    with pytest.raises(InputError, match="--seed -5"):
        make_scene_cycles("balls", tmp_path / "cycles", seed=-5)
    assert not (tmp_path / "cycles").exists()


# --- fits that stop before Dr.Jit, or end cleanly ------------------------------------------------------
def test_a_capture_without_an_opaque_pixel_is_refused_before_tracing(capture, tmp_path, capsys):
    from vq_mitsuba.data.imageio import read_exr, write_exr

    folder = tmp_path / "clear"
    shutil.copytree(capture.parent, folder)
    for exr in (folder / "images").glob("*.exr"):
        image = read_exr(exr)
        image[..., 3] = 0.0
        write_exr(exr, image)
    run = tmp_path / "run"
    assert cli.main(["fit", str(folder / capture.name), "-o", str(run), *QUICK]) == 2
    err = capsys.readouterr().err
    assert f"{folder / capture.name}: no pixel of the 4 training views is opaque" in err
    assert not (run / RunDir.LOCK).exists()


@pytest.mark.parametrize("setting", ["train.max_hits=1", "train.time_limit_s=0.001"])
def test_tiny_budgets_end_in_a_finished_run(capture, tmp_path, setting):
    """One training hit (most views trace no ray), or a time limit spent before the first step."""
    run = tmp_path / "run"
    assert cli.main(["fit", str(capture), "-o", str(run), *QUICK, "--set", setting, "--set",
                     "residual.iterations=0"]) == 0
    assert (run / "fit.json").is_file() and (run / "loss.png").is_file() and not (run / RunDir.LOCK).exists()


def test_latents_that_are_not_finite_stop_the_codebook_with_a_numerical_error(capture, tmp_path):
    from vq_mitsuba.data.captures import load_capture
    from vq_mitsuba.engine.trainer import Trainer

    cfg = load_config(None, ["train.iterations=6", "train.batch_rays=128"])
    trainer = Trainer(load_capture(capture, split="train"), RunDir(tmp_path / "run"), cfg)
    with torch.no_grad():
        for p in trainer.model.field.parameters():
            p.fill_(1e30)
    with pytest.raises(NumericalError, match="latents are not finite"):
        trainer.model.start_discrete(trainer.data.pool.position, trainer.gen, trainer.step, trainer.run.dir)


# --- files read back -----------------------------------------------------------------------------------
@pytest.mark.parametrize("change, key", [
    (lambda info: info["envmap_to_world"][1].__setitem__(2, math.nan), "'envmap_to_world[1][2]' is not a finite"),
    (lambda info: info.pop("world"), "'world' must be 'mitsuba' or 'blender' (missing)"),
    (lambda info: info.__setitem__("envmap_to_world", [[1, 0], [0, 1]]), "'envmap_to_world' must be a 4 x 4"),
    (lambda info: info.__setitem__("capture", 3), "'capture' must be the capture's path"),
])
def test_run_json_with_a_bad_value_is_refused_naming_the_key(tiny_run, tmp_path, change, key):
    run = _copy(tiny_run, tmp_path)
    info = json.loads((run / "run.json").read_text())
    change(info)
    (run / "run.json").write_text(json.dumps(info))
    with pytest.raises(InputError) as exc:
        RunDir(run).load()
    assert exc.value.path == run / "run.json" and key in exc.value.message


def test_export_of_a_run_json_with_nan_is_one_message(tiny_run, tmp_path, capsys):
    run = _copy(tiny_run, tmp_path)
    info = json.loads((run / "run.json").read_text())
    info["envmap_to_world"][0][0] = math.nan
    (run / "run.json").write_text(json.dumps(info))
    out = tmp_path / "exported"
    assert cli.main(["export", str(run), "-o", str(out), "--format", "obj", "--texture-size", "16"]) == 2
    assert f"{run / 'run.json'}: 'envmap_to_world[0][0]' is not a finite number" in capsys.readouterr().err
    assert not (out / "envmap.exr").exists()


@pytest.mark.parametrize("state, phrase", [
    (torch.zeros(3), "not a vq-mitsuba state file (a torch file holding a Tensor"),
    ({"model": {"encoder.mlp.layers.0.weight": torch.zeros(2, 2)}}, "'model' does not fit the networks"),
    ({"step": 3}, "'model' is not a state of networks"),
])
def test_a_checkpoint_of_another_kind_is_refused_naming_it(tiny_run, tmp_path, state, phrase):
    run = _copy(tiny_run, tmp_path)
    torch.save(state, run / "checkpoint.pt")
    with pytest.raises(InputError) as exc:
        RunDir(run).load()
    assert exc.value.path == run / "checkpoint.pt" and phrase in exc.value.message


def test_a_checkpoint_with_a_broken_envmap_is_refused(tiny_run, tmp_path):
    run = _copy(tiny_run, tmp_path)
    state = torch.load(run / "checkpoint.pt", weights_only=False)
    state["envmap"], state["envmap_fixed"] = None, torch.zeros(7)
    torch.save(state, run / "checkpoint.pt")
    with pytest.raises(InputError, match="the envmap is of shape \\(7,\\)"):
        RunDir(run).load()


@pytest.mark.parametrize("setting, phrase", [
    ("field.hidden=32", "'model' does not fit the networks"),
    ("vq.num_codes=4", "'discrete' does not fit the networks"),
    ("vq.enabled=false", "was fitted with vq.enabled=true, not false"),
])
def test_resume_with_another_architecture_is_refused_and_changes_nothing(capture, tiny_run, tmp_path, capsys,
                                                                         setting, phrase):
    run = _copy(tiny_run, tmp_path)
    before = {p.name: p.read_bytes() for p in run.iterdir() if p.is_file()}
    assert cli.main(["fit", str(capture), "-o", str(run), "--resume", "--quiet", "--set", "train.iterations=8",
                     "--set", setting]) == 2
    err = capsys.readouterr().err
    assert f"{run / 'checkpoint.pt'}: {phrase}" in err and "Traceback" not in err
    assert {p.name: p.read_bytes() for p in run.iterdir() if p.is_file()} == before


def test_resuming_with_fewer_steps_before_the_discrete_branch_is_refused(capture, tiny_run, tmp_path, capsys):
    """A run stopped before its codebook started, resumed with no more steps: it would end without
    materials; refused, naming the steps it has."""
    run = _copy(tiny_run, tmp_path)
    state = torch.load(run / "checkpoint.pt", weights_only=False)
    state["discrete"]["initialised"] = torch.tensor(False)
    torch.save(state, run / "checkpoint.pt")
    (run / "fit.json").unlink()
    assert cli.main(["fit", str(capture), "-o", str(run), "--resume", "--quiet", "--set", "train.iterations=3",
                     "--set", "vq.warmup_frac=0.3", "--set", "train.batch_rays=128"]) == 2
    assert "already has 6 steps, and its discrete branch has not started yet" in capsys.readouterr().err


def test_edits_selecting_a_material_the_run_lacks_are_refused(tiny_run, tmp_path):
    from vq_mitsuba.models.material_edits import Change, Edit, Selection

    fitted = RunDir(tiny_run)
    m = fitted.load().num_materials
    edited = RunDir(tmp_path / "edited")
    edited.write_edit(fitted, [Edit(Selection((1,)), [Change("set", "roughness", 0.5)])])
    assert edited.load().edits  # a material the run has
    data = json.loads((edited.dir / "edits.json").read_text())
    data["edits"][0]["select"]["materials"] = [99]
    (edited.dir / "edits.json").write_text(json.dumps(data))
    with pytest.raises(InputError) as exc:
        RunDir(edited.dir).load()
    assert exc.value.path == edited.dir / "edits.json"
    assert f"edit 1 selects material 99, but the fitted run has materials 1..{m}" in exc.value.message


def test_ground_truth_with_nan_and_a_garbage_scene_json_are_refused(tmp_path):
    from vq_mitsuba.data.imageio import write_exr
    from vq_mitsuba.eval.evaluate import _load_test_views, load_ground_truth

    root = tmp_path / "dataset"
    (root / "images").mkdir(parents=True)
    (root / "transforms_test.json").write_text("{}")
    for text, phrase in [("[1, 2]", "expected a JSON object"), ("{not json", "not valid JSON"),
                         ('{"relight": [{"name": "../up"}]}', "relight[0] must be"),
                         ('{"materials": [{"id": "x"}]}', "materials[0] must be")]:
        (root / "scene.json").write_text(text)
        with pytest.raises(InputError) as exc:
            _load_test_views(root, "mitsuba")
        assert exc.value.path == root / "scene.json" and phrase in exc.value.message, text
    image = np.full((8, 8, 4), np.nan, np.float32)
    write_exr(root / "images" / "v0.exr", image)
    with pytest.raises(InputError) as exc:
        load_ground_truth(root, "v0")
    assert exc.value.path == root / "images" / "v0.exr" and "256 of its 256 values are not finite" in exc.value.message


def test_a_torn_undistortion_cache_is_made_again_and_written_whole(tmp_path):
    from vq_mitsuba.data.lens import Lens, undistort_photo
    from vq_mitsuba.data.resize import Shrink

    photo = tmp_path / "p.png"
    photo.write_bytes(b"x")  # only its name and time key the cache
    rgb, alpha = np.random.default_rng(0).random((12, 16, 3)).astype(np.float32), np.ones((12, 16), np.float32)
    lens = Lens("OPENCV", 16, 12, 14.0, 14.0, 8.0, 6.0, k1=-0.05)
    cache = tmp_path / "undistorted"
    first = undistort_photo(photo, rgb, alpha, lens, cache, Shrink())
    (cached,) = cache.glob("*.npz")
    assert [p.name for p in cache.iterdir()] == [cached.name]  # no temporary file left
    cached.write_bytes(cached.read_bytes()[:40])  # torn
    again = undistort_photo(photo, rgb, alpha, lens, cache, Shrink())
    assert np.allclose(again[0], first[0], atol=1e-3) and np.allclose(again[1], first[1], atol=1e-3)
    with np.load(cached) as data:
        assert data["rgb"].shape == (12, 16, 3)


# --- the editor's requests -----------------------------------------------------------------------------
@pytest.fixture
def fake_editor(tmp_path):
    """The editor's server over a stand-in session whose state holds NaN and infinity."""
    from vq_mitsuba.ui.server import make_server

    calls = []
    session = SimpleNamespace(
        run=SimpleNamespace(dir=tmp_path, is_edit=lambda: False),
        state=lambda: {"bounds": [[math.nan, 0.0, 1.0]], "lighting": {"exposure": math.inf}, "view": "v"},
        orbit_view=lambda *a: calls.append(a))
    server = make_server(session, "127.0.0.1", 0)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    yield server, calls
    server.shutdown()
    server.server_close()


def _request(server, method, path, body=b"", headers=None):
    conn = http.client.HTTPConnection(*server.server_address[:2], timeout=10)
    conn.putrequest(method, path)
    sent = {"Content-Type": "application/json", "X-VQM-Token": server.token, "Content-Length": str(len(body)),
            **(headers or {})}
    for k, v in sent.items():
        conn.putheader(k, v)
    conn.endheaders(body)
    r = conn.getresponse()
    return r.status, r.read()


def test_the_editor_state_is_strict_json(fake_editor):
    server, _ = fake_editor
    status, body = _request(server, "GET", "/api/state")
    assert status == 200
    state = json.loads(body, parse_constant=lambda name: pytest.fail(f"{name} in the state"))
    assert state["bounds"] == [[None, 0.0, 1.0]] and state["lighting"]["exposure"] is None


@pytest.mark.parametrize("body, phrase", [
    (b'{"yaw": Infinity}', "Infinity, which is not a JSON number"),
    (b'{"yaw": NaN}', "NaN, which is not a JSON number"),
    (b'{"yaw": 1e400}', "1e400, which is beyond the range"),
])
def test_editor_requests_with_numbers_json_lacks_are_refused(fake_editor, body, phrase):
    server, calls = fake_editor
    status, reply = _request(server, "POST", "/api/orbit", body)
    assert status == 400 and phrase in json.loads(reply)["error"]
    assert calls == []
    assert _request(server, "POST", "/api/orbit", b'{"yaw": 10}')[0] == 200 and calls == [(10.0, 0.0, 1.0)]


def test_a_negative_content_length_is_refused(fake_editor):
    server, calls = fake_editor
    status, reply = _request(server, "POST", "/api/orbit", b"", {"Content-Length": "-1"})
    assert status == 400 and "Content-Length -1 is negative" in json.loads(reply)["error"] and calls == []


# --- signals ----------------------------------------------------------------------------------------
@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_a_signal_ends_a_fit_with_a_checkpoint_and_no_lock(capture, tmp_path, sig):
    """Started as a script's background job does (SIGINT inherited ignored), the fit still stops on
    SIGINT as on SIGTERM: a checkpoint past the first one, no run.lock, exit 128 + the signal."""
    run = tmp_path / "run"
    env = {**os.environ, "PYTHONPATH": str(Path(cli.__file__).resolve().parents[2])}
    proc = subprocess.Popen(
        [sys.executable, "-m", "vq_mitsuba.cli", "fit", str(capture), "-o", str(run), "--quiet",
         "--set", "train.iterations=100000", "--set", "train.batch_rays=128", "--set", "vq.enabled=false",
         "--set", "train.checkpoint_every=2"],
        env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN))
    try:
        deadline = time.monotonic() + 120
        while not (run / "checkpoint.pt").is_file():
            assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()
            time.sleep(0.1)
        first = torch.load(run / "checkpoint.pt", weights_only=False)["step"]
        time.sleep(1.0)
        proc.send_signal(sig)
        _, err = proc.communicate(timeout=120)
    finally:
        proc.kill()
    assert proc.returncode == 128 + sig, err
    assert b"interrupted; the last checkpoint is kept" in err and b"Traceback" not in err
    assert not (run / RunDir.LOCK).exists()
    assert torch.load(run / "checkpoint.pt", weights_only=False)["step"] > first


def test_a_fit_on_one_thread_finishes(tmp_path):
    """`--threads 1` (what each run of a batch uses): Mitsuba's EXR reads wait on Dr.Jit's pool,
    which deadlocked with a single worker."""
    import subprocess
    import sys

    capture = write_sphere_capture(tmp_path / "cap", size=16, n_views=4, spp=8)
    proc = subprocess.run([sys.executable, "-m", "vq_mitsuba.cli", "fit", str(capture), "-o", str(tmp_path / "run"),
                           "--threads", "1", "--quiet", "--set", "train.iterations=4", "--set", "train.batch_rays=128",
                           "--set", "vq.enabled=false"], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert RunDir(tmp_path / "run").load_state()["step"] == 4
