"""RunDir: every file of a run written and read in one place, with a format version."""

import json

import numpy as np
import pytest
import torch
import trimesh

from vq_mitsuba.config import load_config
from vq_mitsuba.run.run_dir import FORMAT_VERSION, RunDir
from vq_mitsuba.errors import InputError
from vq_mitsuba.models.fields import ContinuousMaterial, EnvironmentMap
from vq_mitsuba.models.vq import DiscreteBranch


def _write_run(path, cfg):
    run = RunDir(path)
    run.create()
    mesh = trimesh.creation.icosphere(subdivisions=2, radius=0.5)
    run.write_config(cfg)
    run.write_mesh(mesh)
    run.write_info({"capture": "/nowhere/scene.xml", "world": "blender", "envmap_to_world": np.eye(4).tolist()})
    bbox = torch.tensor(np.asarray(mesh.bounds), dtype=torch.float32)
    torch.manual_seed(0)
    model = ContinuousMaterial(cfg.field, bbox[0], bbox[1])
    discrete = DiscreteBranch(cfg.field, cfg.vq.num_codes, cfg.vq.decay, cfg.vq.commitment)
    discrete.initialised.fill_(True)
    discrete.num_materials.fill_(3)
    env = EnvironmentMap(4, 1.5)
    run.save_state({"model": model.state_dict(), "discrete": discrete.state_dict(), "envmap": env.state_dict(),
                    "envmap_fixed": None, "step": 17})
    run.write_materials({"num_materials": 3, "err_k": [0.3, 0.2, 0.1]})
    run.write_fit_summary({"iterations": 17, "seconds": 2.0})
    return run, model, env


def test_round_trip(tmp_path):
    cfg = load_config(None, ["field.hidden=32", "field.latent=8", "vq.num_codes=5", "render.spp=12"])
    run, model, env = _write_run(tmp_path / "run", cfg)
    again = RunDir(tmp_path / "run")
    assert again.info()["format"] == FORMAT_VERSION
    assert again.config() == cfg
    fitted = again.load()
    assert fitted.step == 17 and fitted.world == "blender" and fitted.num_materials == 3
    np.testing.assert_allclose(fitted.envmap, np.full((4, 8, 3), 1.5), rtol=1e-6)
    np.testing.assert_array_equal(fitted.envmap_to_world, np.eye(4))
    x = torch.rand(10, 3) - 0.5
    with torch.no_grad():
        for key in ("basecolor", "metallic", "roughness"):
            torch.testing.assert_close(fitted.model(x)[key], model(x)[key])
    assert again.materials()["err_k"] == [0.3, 0.2, 0.1]
    assert again.fit_summary()["iterations"] == 17
    assert len(fitted.mesh.faces) == 320


def test_unknown_format_version_is_refused(tmp_path):
    run, _, _ = _write_run(tmp_path / "run", load_config(None, ["field.hidden=16", "field.latent=4"]))
    info = json.loads((run / RunDir.INFO).read_text())
    info["format"] = FORMAT_VERSION + 1
    (run / RunDir.INFO).write_text(json.dumps(info))
    with pytest.raises(InputError, match=f"format {FORMAT_VERSION + 1}"):
        RunDir(run.dir).load()
    del info["format"]
    (run / RunDir.INFO).write_text(json.dumps(info))
    with pytest.raises(InputError, match="run.json"):
        RunDir(run.dir).info()


def test_run_json_records_the_device_and_an_older_one_without_it_loads(tmp_path):
    from vq_mitsuba.backend import device_record

    run, _, _ = _write_run(tmp_path / "run", load_config(None, ["field.hidden=16", "field.latent=4"]))
    assert "device" not in RunDir(run.dir).info()  # a run.json written before --device
    info = json.loads((run / RunDir.INFO).read_text())
    record = device_record()
    assert record["used"] in ("cpu", "cuda") and record["variant"].endswith("_ad_rgb")
    (run / RunDir.INFO).write_text(json.dumps({**info, "device": record}))
    assert RunDir(run.dir).info()["device"] == record
    (run / RunDir.INFO).write_text(json.dumps({**info, "device": {**record, "used": "tpu"}}))
    with pytest.raises(InputError, match="'device'"):
        RunDir(run.dir).info()


def test_a_folder_without_a_run_is_named(tmp_path):
    with pytest.raises(InputError, match="run.json missing"):
        RunDir(tmp_path).load()


def test_parsed_once_but_each_load_has_its_own_config(tmp_path, monkeypatch):
    """run.json and config.yaml are read once per RunDir; a caller that changes its FittedModel's
    config (a preview without the bounce) changes no later load of the same run."""
    cfg = load_config(None, ["field.hidden=16", "field.decoder_hidden=16", "vq.num_codes=4"])
    run = RunDir(_write_run(tmp_path / "run", cfg)[0].dir)
    first = run.load()
    first.cfg.train.bounces = 0
    reads = []
    monkeypatch.setattr(RunDir, "saved_config", lambda self: reads.append(1) or {})
    second = run.load()
    assert second.cfg.train.bounces == cfg.train.bounces == 1
    assert reads == []  # the cached parse, not the file again
    assert run.info() is run.info()
    written = {**run.info(), "n_views": 7}
    run.write_info({k: v for k, v in written.items() if k != "format"})
    assert RunDir(run.dir).info()["n_views"] == 7 and run.info()["n_views"] == 7


@pytest.mark.parametrize("bad, where", [(float("nan"), "materials[1].roughness"), (float("inf"), "materials[1].roughness"),
                                        (-float("inf"), "materials[1].roughness")])
def test_json_holds_finite_numbers_only(tmp_path, bad, where):
    """A NaN or Inf is never written into a run's JSON: NumericalError naming the file and the key,
    and the file already there is kept."""
    from vq_mitsuba.errors import NumericalError

    run = RunDir(tmp_path / "run")
    run.create()
    good = {"num_materials": 2, "materials": [{"roughness": 0.5}, {"roughness": 0.25}]}
    run.write_materials(good)
    bad_materials = {"num_materials": 2, "materials": [{"roughness": 0.5}, {"roughness": bad}]}
    with pytest.raises(NumericalError) as info:
        run.write_materials(bad_materials)
    assert str(run / RunDir.MATERIALS) in str(info.value) and where in str(info.value)
    assert json.loads((run / RunDir.MATERIALS).read_text()) == good
    assert sorted(p.name for p in run.dir.iterdir()) == [RunDir.MATERIALS]  # no temporary file left


def _hold_lock_in_subprocess(folder, command="fit"):
    """A process holding the run's lock until it is killed; returns (process, its pid)."""
    import subprocess
    import sys

    code = ("import sys, time\nfrom vq_mitsuba.run.run_dir import RunDir\n"
            f"with RunDir(sys.argv[1]).lock({command!r}):\n    print('held', flush=True)\n    time.sleep(600)\n")
    proc = subprocess.Popen([sys.executable, "-c", code, str(folder)], stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "held"
    return proc


def test_lock_refuses_a_second_process_and_is_taken_over_once_its_owner_died(tmp_path):
    import os
    import signal

    folder = tmp_path / "run"
    proc = _hold_lock_in_subprocess(folder)
    try:
        owner = json.loads((folder / RunDir.LOCK).read_text())
        assert owner["pid"] == proc.pid and owner["command"] == "fit" and owner["host"]
        with pytest.raises(InputError, match=rf"in use by `vq-mitsuba fit` \(pid {proc.pid} on "):
            with RunDir(folder).lock("edit"):
                pass
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    assert (folder / RunDir.LOCK).is_file()  # left behind by the killed process: stale
    notes = []
    with RunDir(folder).lock("fit", log=notes.append):
        assert json.loads((folder / RunDir.LOCK).read_text())["pid"] == os.getpid()
        with RunDir(folder).lock("geometry", log=notes.append):  # the same process again: no-op
            pass
        assert (folder / RunDir.LOCK).is_file()  # still held by the outer one
    assert len(notes) == 1 and f"pid {proc.pid}" in notes[0] and "no longer running" in notes[0]
    assert not (folder / RunDir.LOCK).exists()


def test_lock_leaves_no_empty_folder_behind(tmp_path):
    folder = tmp_path / "new" / "run"
    with pytest.raises(InputError, match="refused"):
        with RunDir(folder).lock("fit"):
            raise InputError(None, "refused")
    assert not folder.exists()
    with RunDir(folder).lock("fit"):
        (folder / "result.txt").write_text("kept")
    assert sorted(p.name for p in folder.iterdir()) == ["result.txt"]


def test_a_refused_write_names_the_file_and_keeps_the_old_one(tmp_path, monkeypatch):
    """Disk full (ENOSPC) or no permission while a file is written: one WriteError naming the
    file; the file written before stays whole and no temporary file is left."""
    import errno

    from vq_mitsuba.run.run_dir import WriteError, write_atomic

    target = tmp_path / "fit.json"
    target.write_text("before")

    def full_disk(tmp):
        tmp.write_text("half of")
        raise OSError(errno.ENOSPC, "No space left on device", str(tmp))

    with pytest.raises(WriteError, match="no space left on the device") as info:
        write_atomic(target, full_disk)
    assert info.value.path == target
    assert target.read_text() == "before" and sorted(p.name for p in tmp_path.iterdir()) == ["fit.json"]

    def denied(tmp):
        raise PermissionError(errno.EACCES, "Permission denied", str(tmp))

    with pytest.raises(WriteError, match="permission denied"):
        write_atomic(target, denied)
    with pytest.raises(OSError, match="something else"):  # other errors are not disguised as write errors
        write_atomic(target, lambda tmp: (_ for _ in ()).throw(OSError(errno.EIO, "something else")))


def test_metrics_keep_undefined_scores_as_text(tmp_path):
    """eval's scores may be undefined (PSNR of identical images, SSIM of an empty mask): metrics.json
    keeps them as "inf" / "nan", as `eval` writes them, instead of losing the scoring work."""
    run = RunDir(tmp_path / "run")
    run.create()
    run.write_metrics({"views": [{"psnr": float("inf"), "ssim": float("nan")}], "coverage_iou": 0.5})
    assert json.loads((run / RunDir.METRICS).read_text()) == {"views": [{"psnr": "inf", "ssim": "nan"}],
                                                              "coverage_iou": 0.5}


def test_views_of_every_split_have_names_of_their_own(tmp_path):
    """NeRF-synthetic captures name train/r_0 and test/r_0 both r_0: a run's cameras keep every
    name unique over the splits (the test view is test_r_0), so the editor and `edit --pick` can
    tell them apart."""
    import shutil

    from test_capture import make_json_capture
    from vq_mitsuba.edit import find_view

    capture = make_json_capture(tmp_path / "cap")
    root = capture.parent
    shutil.copytree(root / "train", root / "test")
    test = json.loads(capture.read_text())
    test["frames"] = [{**f, "file_path": f["file_path"].replace("train", "test")} for f in test["frames"]]
    test["frames"][1]["transform_matrix"] = np.diag([1.0, 1.0, 1.0, 1.0]).tolist()
    (root / "transforms_test.json").write_text(json.dumps(test))
    run = RunDir(tmp_path / "run")
    run.create()
    run.write_config(load_config(None, []))
    run.write_info({"capture": str(capture), "world": "blender", "envmap_to_world": np.eye(4).tolist()})
    views = run.cameras()
    assert [c.name for c in views["train"]] == ["r_0", "r_1", "r_2"]
    assert [c.name for c in views["test"]] == ["test_r_0", "test_r_1", "test_r_2"]
    assert np.allclose(find_view(run, "test_r_1").to_world, views["test"][1].to_world)
    assert not np.allclose(find_view(run, "r_1").to_world, views["test"][1].to_world)


class _RunsCode:
    """A pickle that would create a file when loaded."""

    def __init__(self, path):
        self.path = str(path)

    def __reduce__(self):
        return (open, (self.path, "w"))


def test_a_checkpoint_that_would_run_code_is_refused_without_running_it(tmp_path):
    run = RunDir(tmp_path / "run")
    run.create()
    marker = tmp_path / "code_ran"
    torch.save({"model": {}, "step": 1, "payload": _RunsCode(marker)}, run.checkpoint_path)
    with pytest.raises(InputError, match="not a readable checkpoint") as info:
        run.load_state()
    assert str(run.checkpoint_path) in str(info.value)
    assert not marker.exists()
