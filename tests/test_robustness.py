"""Odd input and numerical extremes: every bad value is refused once with a message (exit 2) before
anything is written; no output or checkpoint holds NaN or Inf."""

import numpy as np
import pytest
import torch

from tiny_scene import write_sphere_capture
from vq_mitsuba import cli
from vq_mitsuba.config import load_config
from vq_mitsuba.data.imageio import read_image, write_exr
from vq_mitsuba.run.run_dir import RunDir
from vq_mitsuba.errors import InputError, NumericalError


@pytest.mark.parametrize("setting, message", [
    ("train.lr=nan", "finite"), ("train.lr=-0.01", "in \\(0, 1]"), ("envmap.lr=inf", "finite"),
    ("train.batch_rays=-5", "> 0"), ("train.pixel_jitter=3", "square"), ("render.spp=0", "> 0"),
    ("render.aa=5", "square"), ("vq.decay=1.5", "[0, 1]"), ("loss.w_lam=-1", ">= 0"), ("train.bounces=-1", ">= 0"),
])
def test_config_refuses_values_out_of_range(setting, message):
    with pytest.raises(InputError, match=message.replace("[", r"\[").replace("]", r"\]")):
        load_config(None, [setting])


def test_every_preset_is_in_range():
    from vq_mitsuba.config import presets

    for name in presets():
        load_config(preset=name)


def test_fit_with_a_bad_value_writes_nothing(tmp_path, capsys):
    capture = write_sphere_capture(tmp_path / "cap", size=16, n_views=4, spp=8)
    out = tmp_path / "run"
    assert cli.main(["fit", str(capture), "-o", str(out), "--set", "train.batch_rays=-5", "--quiet"]) == 2
    assert "train.batch_rays must be > 0" in capsys.readouterr().err and not out.exists()
    some_file = tmp_path / "a_file"
    some_file.write_text("mine")
    assert cli.main(["fit", str(capture), "-o", str(some_file), "--quiet"]) == 2
    assert "-o names an output folder" in capsys.readouterr().err and some_file.read_text() == "mine"


@pytest.fixture(scope="module")
def envmaps(tmp_path_factory):
    d = tmp_path_factory.mktemp("envs")
    write_exr(d / "zero.exr", np.zeros((8, 16, 3), np.float32))
    write_exr(d / "tiny.exr", np.ones((1, 2, 3), np.float32))
    write_exr(d / "square.exr", np.ones((8, 8, 3), np.float32))
    write_exr(d / "dim.exr", np.full((8, 16, 3), 1e-35, np.float32))
    from vq_mitsuba.data.imageio import write_png

    write_png(d / "ldr.png", np.ones((8, 16, 3), np.float32) * 0.5)
    return d


@pytest.mark.parametrize("args, message", [
    (["--envmap", "zero.exr"], "gives no light"),
    (["--envmap", "tiny.exr"], "at least 4 x 2"),
    (["--envmap", "square.exr"], "twice as wide"),
    (["--envmap", "ldr.png"], ".exr or .hdr"),
    (["--exposure", "200"], "within +-64"),
    (["--exposure", "-200"], "within +-64"),
    (["--exposure", "nan"], "within +-64"),
    (["--env-rotate", "inf"], "finite"),
    (["--spp", "0"], ">= 1"),
    (["--spp", "-4"], ">= 1"),
    (["--envmap", "dim.exr"], "not be finite"),  # a valid file, too dark for float32 sums
])
def test_render_refuses_bad_lighting_and_settings(three_materials, envmaps, tmp_path, capsys, args, message):
    capture, run = three_materials
    args = [str(envmaps / a) if a.endswith((".exr", ".png")) else a for a in args]
    out = tmp_path / "renders"
    try:
        code = cli.main(["render", str(run.dir), "--cameras", str(capture), "-o", str(out), "--quiet", *args])
    except SystemExit as exc:  # argparse: usage error, exit 2
        code = exc.code
    assert code == 2
    assert message in capsys.readouterr().err
    assert not out.exists() or not any(out.iterdir())


def test_render_at_exposure_extremes_is_finite(three_materials, tmp_path):
    capture, run = three_materials
    from vq_mitsuba.data.captures import load_cameras
    from vq_mitsuba.render.views import render_views

    fitted = run.load()
    cams, world, _ = load_cameras(capture)
    for ev in (-64.0, 64.0):
        render_views(fitted, cams[:1], world, tmp_path, exposure_ev=ev, spp=4)
        rgb = read_image(tmp_path / f"{cams[0].name}_rgb.exr")[0]
        assert np.isfinite(rgb).all() and rgb.max() > 0


def test_shading_is_finite_at_material_and_angle_extremes():
    from vq_mitsuba.render.shading import ShadingScene
    from tiny_scene import smooth_env
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=2, radius=0.5)
    env = smooth_env(16)
    for scale in (1e-12, 1.0, 1e12):
        scene = ShadingScene(sphere.vertices, sphere.faces, env * scale, np.eye(4))
        n = 64
        normal = torch.tensor([[0.0, 0.0, 1.0]]).repeat(n, 1)
        pos = normal * 0.5
        # Views from head-on to grazing (the last ones nearly tangent to the surface).
        angle = torch.linspace(0.0, 89.99, n) * np.pi / 180
        wi = torch.stack([torch.sin(angle), torch.zeros(n), torch.cos(angle)], -1)
        combos = [(0.0, 0.0, 0.02), (1.0, 1.0, 0.02), (0.0, 1.0, 1.0), (1.0, 0.0, 1e-4), (0.5, 0.5, 1.0)]
        for base, metal, rough in combos:
            bc = torch.full((n, 3), base)
            material = {"basecolor": bc, "metallic": torch.full((n,), metal), "roughness": torch.full((n,), rough)}
            out = scene.shade(pos, normal, wi, material, torch.as_tensor(env * scale), 16, generator=torch.Generator().manual_seed(0))
            assert torch.isfinite(out).all(), (scale, base, metal, rough)
            assert (out >= 0).all()


def test_checkpoints_hold_only_finite_values(tmp_path):
    run = RunDir(tmp_path / "run")
    run.create()
    good = {"model": {"w": torch.ones(3)}, "step": 1}
    run.save_state(good)
    bad = {"model": {"w": torch.tensor([1.0, float("nan")])}, "step": 2}
    with pytest.raises(NumericalError, match="model.w"):
        run.save_state(bad)
    assert run.load_state()["step"] == 1  # the previous checkpoint is kept
    torch.save(bad, run.checkpoint_path)  # written by something else
    with pytest.raises(InputError, match="non-finite values in model.w"):
        run.load_state()
    run.checkpoint_path.write_bytes(b"torn")
    with pytest.raises(InputError, match="not a readable checkpoint"):
        run.load_state()


def test_16_bit_png_keeps_its_precision(tmp_path):
    import mitsuba as mi

    from vq_mitsuba.backend import init_mitsuba

    init_mitsuba()
    values = np.linspace(0, 65535, 8 * 8 * 3).reshape(8, 8, 3).astype(np.uint16)
    mi.Bitmap(values, pixel_format=mi.Bitmap.PixelFormat.RGB).write(str(tmp_path / "deep.png"))
    rgb, _ = read_image(tmp_path / "deep.png")
    from vq_mitsuba.data.imageio import srgb_to_linear

    assert np.allclose(rgb, srgb_to_linear(values / 65535.0), atol=1e-6)
    assert len(np.unique(rgb)) > 150  # 8 bits would merge neighbouring values


def test_a_file_that_is_not_an_image_is_named_as_such(tmp_path):
    (tmp_path / "x.png").write_text("not a picture")
    with pytest.raises(InputError, match="not a PNG image"):
        read_image(tmp_path / "x.png")


def test_all_broken_images_of_a_capture_are_reported_together(tmp_path):
    from vq_mitsuba.data.captures import load_capture

    capture = write_sphere_capture(tmp_path / "cap", size=16, n_views=4, spp=8)
    (tmp_path / "cap" / "images" / "view_01.exr").write_text("garbage")
    (tmp_path / "cap" / "images" / "view_03.exr").unlink()
    with pytest.raises(InputError) as info:
        load_capture(capture)
    text = str(info.value)
    assert "2 problems" in text and "view_01.exr" in text and "view_03" in text


def test_fit_never_writes_over_a_users_folder(tmp_path, capsys):
    capture = write_sphere_capture(tmp_path / "cap", size=16, n_views=4, spp=8)
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "loss.png").write_bytes(b"my own picture")
    assert cli.main(["fit", str(capture), "-o", str(mine), "--quiet"]) == 2
    assert "no vq-mitsuba run" in capsys.readouterr().err
    assert (mine / "loss.png").read_bytes() == b"my own picture" and len(list(mine.iterdir())) == 1


def test_eval_names_a_missing_dataset_folder(three_materials, tmp_path, capsys):
    _, run = three_materials
    missing = tmp_path / "no_such_dataset"
    assert cli.main(["eval", str(run.dir), "--gt", str(missing), "--quiet"]) == 2
    assert f"{missing}: dataset folder not found" in capsys.readouterr().err


@pytest.mark.slow  # over 10 s: CI runs it after the default suite (.ci/run)
@pytest.mark.parametrize("checkpoint_every, kill_after_s", [(1, 7.0), (25, 9.0)])
def test_a_killed_fit_resumes_from_an_intact_checkpoint(tmp_path, checkpoint_every, kill_after_s):
    """kill -9 in the middle of a fit (with checkpoint_every=1, most likely during a checkpoint
    write); `fit --resume` then loads an intact checkpoint and finishes the run."""
    import json
    import signal
    import subprocess
    import sys
    import time

    capture = write_sphere_capture(tmp_path / "cap", size=16, n_views=4, spp=8)
    run = tmp_path / "run"
    settings = ["--set", "train.iterations=100000", "--set", f"train.checkpoint_every={checkpoint_every}",
                "--set", "train.batch_rays=256", "--set", "vq.enabled=false", "--quiet"]
    proc = subprocess.Popen([sys.executable, "-m", "vq_mitsuba.cli", "fit", str(capture), "-o", str(run), *settings],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.time() + 120
    while not (run / "checkpoint.pt").is_file() and time.time() < deadline:
        time.sleep(0.2)
    time.sleep(kill_after_s - 6.0)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert (run / "checkpoint.pt").is_file()
    step = RunDir(run).load_state()["step"]  # intact: loads, finite
    assert step >= 1
    done = step + 30
    code = cli.main(["fit", str(capture), "-o", str(run), "--resume", *settings[:-1],
                     "--set", f"train.iterations={done}", "--quiet"])
    assert code == 0
    assert json.loads((run / "fit.json").read_text())["iterations"] == done


def test_resume_refuses_another_capture(tmp_path, capsys):
    first = write_sphere_capture(tmp_path / "a", size=16, n_views=4, spp=8)
    other = write_sphere_capture(tmp_path / "b", size=16, n_views=4, spp=8, base_color=(0.2, 0.3, 0.8))
    run = tmp_path / "run"
    quick = ["--set", "train.iterations=20", "--set", "train.batch_rays=128", "--set", "vq.enabled=false", "--quiet"]
    assert cli.main(["fit", str(first), "-o", str(run), *quick]) == 0
    before = (run / "run.json").read_text()
    assert cli.main(["fit", str(other), "-o", str(run), "--resume", *quick]) == 2
    assert "was fitted to" in capsys.readouterr().err
    assert (run / "run.json").read_text() == before


def test_resume_refuses_another_mesh(tmp_path, capsys):
    import trimesh

    capture = write_sphere_capture(tmp_path / "a", size=16, n_views=4, spp=8)
    run = tmp_path / "run"
    quick = ["--set", "train.iterations=20", "--set", "train.batch_rays=128", "--set", "vq.enabled=false", "--quiet"]
    assert cli.main(["fit", str(capture), "-o", str(run), *quick]) == 0
    trimesh.creation.icosphere(subdivisions=2, radius=0.5).export(tmp_path / "a" / "sphere.ply")
    assert cli.main(["fit", str(capture), "-o", str(run), "--resume", *quick]) == 2
    assert "another mesh" in capsys.readouterr().err


@pytest.mark.parametrize("binary, model", [(False, "OPENCV"), (True, "PINHOLE")])
def test_fit_of_a_colmap_capture_with_a_nan_focal_length_writes_nothing(tmp_path, capsys, binary, model):
    """Once a Dr.Jit abort (exit 134) after an all-NaN undistorted/ cache, or a fit of NaN cameras."""
    from vq_mitsuba.data.captures import load_capture
    from vq_mitsuba.data.imageio import write_png
    from vq_mitsuba.data.formats.colmap import write_colmap
    from vq_mitsuba.data.lens import Lens

    capture = load_capture(write_sphere_capture(tmp_path / "cap", size=16, n_views=4, spp=8))
    folder = tmp_path / "colmap"
    lenses = iter([Lens(model, 16, 16, float("nan"), 20.0, 8.0, 8.0)]
                  + [Lens(model, 16, 16, 20.0, 20.0, 8.0, 8.0, *([-0.05] if model == "OPENCV" else []))] * 3)
    names = [f"{c.name}.png" for c in capture.cameras]
    write_colmap(folder / "sparse" / "0", capture.cameras, names, lens_of=lambda c: next(lenses), binary=binary)
    for name, rgb, alpha in zip(names, capture.images, capture.alpha):
        write_png(folder / "images" / name, rgb, alpha=alpha)
    out = tmp_path / "run"
    assert cli.main(["fit", str(folder), "-o", str(out), "--set", "train.iterations=5", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert f"cameras.{'bin' if binary else 'txt'}: camera 1 ({model}): fx = nan is not a finite number" in err
    assert "Traceback" not in err and not out.exists()


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    """(capture XML, run folder) of a 6-step fit of a small sphere, with both branches."""
    from vq_mitsuba.engine.pipeline import fit

    folder = tmp_path_factory.mktemp("tiny")
    capture = write_sphere_capture(folder / "cap", size=16, n_views=4, spp=8)
    fit(capture, folder / "run", load_config(None, ["train.iterations=6", "train.batch_rays=128",
                                                    "vq.warmup_frac=0.3"]))
    return capture, folder / "run"


def _wait_for(predicate, seconds: float = 300.0) -> None:
    import time

    deadline = time.time() + seconds
    while not predicate():
        assert time.time() < deadline, "timed out"
        time.sleep(0.2)


@pytest.mark.slow  # over 10 s: CI runs it after the default suite (.ci/run)
def test_two_concurrent_fits_on_one_folder(tmp_path, capsys):
    """The second `fit` into a folder that a running fit writes is refused (exit 2, naming the
    owner), with or without --resume; the first finishes with its results intact."""
    import json
    import subprocess
    import sys

    capture = write_sphere_capture(tmp_path / "cap", size=16, n_views=4, spp=8)
    run = tmp_path / "run"
    # The first fit runs for 6 training seconds (after its start-up), whatever this machine's speed.
    first_settings = ["--set", "train.iterations=100000", "--set", "train.time_limit_s=6", "--set",
                      "train.batch_rays=128", "--set", "vq.enabled=false", "--set", "train.checkpoint_every=10"]
    first = subprocess.Popen([sys.executable, "-m", "vq_mitsuba.cli", "fit", str(capture), "-o", str(run), "--quiet",
                              *first_settings], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        _wait_for(lambda: (run / "config.yaml").is_file() or first.poll() is not None)
        assert first.poll() is None and json.loads((run / RunDir.LOCK).read_text())["pid"] == first.pid
        second = ["fit", str(capture), "-o", str(run), "--quiet", "--set", "train.iterations=5"]
        for extra in ([], ["--resume"]):
            assert cli.main(second + extra) == 2
            err = capsys.readouterr().err
            assert f"{run}: is in use by `vq-mitsuba fit` (pid {first.pid} on " in err and "Traceback" not in err
        out, err = first.communicate(timeout=600)
    finally:
        first.kill()
        first.wait()
    assert first.returncode == 0, err
    summary = json.loads((run / "fit.json").read_text())
    state = RunDir(run).load_state()
    assert summary["iterations"] == state["step"] > 0 and state["config"]["train"]["time_limit_s"] == 6
    assert RunDir(run).config().train.iterations == 100000  # config.yaml is the first fit's
    assert not (run / RunDir.LOCK).exists()


def test_disk_full_during_a_fit_keeps_the_last_checkpoint(tmp_path, monkeypatch, capsys):
    """ENOSPC while the second checkpoint is written: one message naming the file (exit 3, mid-run); the
    first checkpoint stays whole and loadable, and no temporary file is left."""
    import errno
    from pathlib import Path

    capture = write_sphere_capture(tmp_path / "cap", size=16, n_views=4, spp=8)
    run = tmp_path / "run"
    real_save, saves = torch.save, []

    def save(obj, f, *args, **kwargs):
        saves.append(Path(f))
        if len(saves) >= 2:
            Path(f).write_bytes(b"half a checkpoint")
            raise OSError(errno.ENOSPC, "No space left on device", str(f))
        return real_save(obj, f, *args, **kwargs)

    monkeypatch.setattr(torch, "save", save)
    code = cli.main(["fit", str(capture), "-o", str(run), "--quiet", "--set", "train.iterations=6", "--set",
                     "train.checkpoint_every=2", "--set", "train.batch_rays=128", "--set", "vq.enabled=false"])
    monkeypatch.undo()
    err = capsys.readouterr().err
    assert code == 3 and len(saves) == 2  # no second try after the refused write
    assert [line for line in err.splitlines() if line.startswith("error")] == [
        f"error: {run / RunDir.CHECKPOINT}: cannot be written: no space left on the device (files written before "
        "are kept)"]
    assert "Traceback" not in err and "warning" not in err
    assert RunDir(run).load_state()["step"] == 2
    assert not [p.name for p in run.iterdir() if p.name.startswith(".")]


def _command(name: str, capture, run, out) -> list[str]:
    return {"fit": ["fit", str(capture), "-o", str(out / "run"), "--quiet"],
            "render": ["render", str(run), "--cameras", str(capture), "-o", str(out / "views"), "--quiet"],
            "edit": ["edit", str(run), "--material", "1", "--set", "roughness=0.5", "-o", str(out / "edited")],
            "eval": ["eval", str(run), "--gt", str(out.parent / "no_dataset"), "-o", str(out / "metrics.json")],
            "make-scene": ["make-scene", "demo", "-o", str(out / "demo"), "--resolution", "8"],
            "export": ["export", str(run), "-o", str(out / "export"), "--format", "obj", "--quiet"]}[name]


COMMANDS_WRITING = ("fit", "render", "edit", "eval", "make-scene", "export")


@pytest.mark.parametrize("command", COMMANDS_WRITING)
def test_an_output_folder_that_cannot_be_written_is_refused_before_any_work(tiny_run, tmp_path, monkeypatch, capsys,
                                                                           command):
    """The operating system says the folder is not writable (as for a read-only folder of a user
    without root): one message naming it, exit 2, before the run or the capture is read."""
    import os
    from pathlib import Path

    capture, run = tiny_run
    locked = tmp_path / "locked"
    locked.mkdir()
    real_access = os.access
    monkeypatch.setattr(os, "access", lambda p, mode, **kw: False if Path(p) == locked else real_access(p, mode, **kw))
    monkeypatch.setattr(RunDir, "load", lambda *a, **kw: pytest.fail("the run was loaded"))
    from vq_mitsuba.data.captures import CaptureSource

    monkeypatch.setattr(CaptureSource, "load", lambda *a, **kw: pytest.fail("the capture was loaded"))
    assert cli.main(_command(command, capture, run, locked)) == 2
    assert f"error: {locked}: cannot be written: permission denied" in capsys.readouterr().err
    assert list(locked.iterdir()) == []


@pytest.mark.skipif(not hasattr(__import__("os"), "geteuid") or __import__("os").geteuid() == 0,
                    reason="root writes into read-only folders")
@pytest.mark.parametrize("command", COMMANDS_WRITING)
def test_a_read_only_output_folder_is_one_message(tiny_run, tmp_path, capsys, command):
    capture, run = tiny_run
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o555)
    try:
        assert cli.main(_command(command, capture, run, locked)) == 2
        err = capsys.readouterr().err
        assert f"{locked}" in err and "cannot be written" in err and "Traceback" not in err
        assert list(locked.iterdir()) == []
    finally:
        locked.chmod(0o755)


def test_make_scene_never_writes_into_a_run(tmp_path, capsys):
    run = tmp_path / "run"
    run.mkdir()
    (run / RunDir.INFO).write_text("{}")
    (run / RunDir.MESH).write_bytes(b"the fitted geometry")
    assert cli.main(["make-scene", "demo", "-o", str(run), "--resolution", "8"]) == 2
    assert "holds a vq-mitsuba run" in capsys.readouterr().err
    assert (run / RunDir.MESH).read_bytes() == b"the fitted geometry" and len(list(run.iterdir())) == 2


@pytest.mark.parametrize("resolution", ["100000", "64x100000", "4"])
def test_make_scene_refuses_an_absurd_resolution_up_front(tmp_path, capsys, resolution):
    out = tmp_path / "demo"
    assert cli.main(["make-scene", "demo", "-o", str(out), "--resolution", resolution]) == 2
    assert "each side must be 8 to 4096 pixels" in capsys.readouterr().err and not out.exists()


def test_make_scene_leaves_no_half_written_dataset(tmp_path, monkeypatch):
    from vq_mitsuba.eval.evaluate import dataset_root
    from vq_mitsuba.synthetic import mitsuba_scenes as synthetic

    def fail(*args, **kwargs):
        raise RuntimeError("the renderer ran out of memory")

    monkeypatch.setattr(synthetic, "_render_views", fail)
    settings = dict(resolution=8, n_train=1, n_test=1, spp=1)
    with pytest.raises(RuntimeError, match="out of memory"):
        synthetic.make_scene("demo", tmp_path / "new", **settings)
    assert not (tmp_path / "new").exists()
    earlier = tmp_path / "earlier"  # an earlier dataset written over: no longer passes for a dataset
    (earlier / "images").mkdir(parents=True)
    (earlier / "images" / "r_0.exr").write_bytes(b"stale view")
    for name in ("scene.json", "transforms_test.json"):
        (earlier / name).write_text("{}")
    with pytest.raises(RuntimeError, match="out of memory"):
        synthetic.make_scene("demo", earlier, **settings)
    assert not (earlier / "scene.json").exists() and (earlier / synthetic.INCOMPLETE).is_file()
    assert not (earlier / "images" / "r_0.exr").exists()
    with pytest.raises(InputError, match="scene.json: not a dataset"):
        dataset_root(earlier)


@pytest.mark.parametrize("output", ["folder", "folder/", "new_folder/"])
def test_eval_refuses_a_folder_as_its_output_before_any_work(tiny_run, tmp_path, monkeypatch, capsys, output):
    _, run = tiny_run
    (tmp_path / "folder").mkdir()
    monkeypatch.setattr(RunDir, "load", lambda *a, **kw: pytest.fail("the run was loaded"))
    target = str(tmp_path / output.rstrip("/")) + ("/" if output.endswith("/") else "")
    assert cli.main(["eval", str(run), "-o", target, "--quiet"]) == 2
    assert f"{tmp_path / output.rstrip('/')}: is a folder; eval -o names the metrics JSON file" in capsys.readouterr().err
    assert not (tmp_path / "new_folder").exists()


def test_eval_of_a_1x1_dataset_is_refused_before_rendering(tiny_run, tmp_path, monkeypatch, capsys):
    from vq_mitsuba.render.views import Renderer
    from vq_mitsuba.synthetic import mitsuba_scenes as synthetic

    monkeypatch.setattr(synthetic, "RESOLUTION_RANGE", (1, 4096))  # make-scene refuses it now; others may not
    data = synthetic.make_scene("demo", tmp_path / "tiny", resolution=1, n_train=1, n_test=1, spp=1)
    monkeypatch.setattr(Renderer, "render", lambda *a, **kw: pytest.fail("rendered"))
    _, run = tiny_run
    assert cli.main(["eval", str(run), "--gt", str(data), "-o", str(tmp_path / "m.json"), "--quiet"]) == 2
    assert "is 1x1 pixels: SSIM needs at least 3 per side" in capsys.readouterr().err
    assert not (tmp_path / "m.json").exists()


def test_an_edit_box_that_selects_nothing_is_refused(tiny_run, tmp_path, capsys):
    """The sphere of radius 0.5 about the origin: a box beside it changes nothing and is refused,
    writing no folder; a box through it is an edit."""
    _, run = tiny_run
    for box in (["--box", "5,5,5,6,6,6"], ["--box", "0.55,-0.1,-0.1,0.7,0.1,0.1"], ["--material", "1", "--box=2,2,2,3,3,3"]):
        out = tmp_path / "nothing"
        assert cli.main(["edit", str(run), *box, "--set", "roughness=0.5", "-o", str(out)]) == 2
        assert "hold no surface point" in capsys.readouterr().err and not out.exists()
    out = tmp_path / "half"
    assert cli.main(["edit", str(run), "--box", "-1,-1,-1,0,1,1", "--set", "roughness=0.5", "-o", str(out)]) == 0
    assert (out / RunDir.EDITS).is_file() and not (out / RunDir.LOCK).exists()


def test_a_failed_render_leaves_no_empty_folder(tiny_run, tmp_path, monkeypatch, capsys):
    import shutil

    import vq_mitsuba.render.views as views

    capture, run = tiny_run
    out = tmp_path / "views"
    monkeypatch.setattr(views, "render_views", lambda *a, **kw: (_ for _ in ()).throw(
        InputError(None, "view_00: the render is not finite")))
    assert cli.main(["render", str(run), "--cameras", str(capture), "-o", str(out), "--quiet"]) == 2
    assert "not finite" in capsys.readouterr().err and not out.exists()
    broken = tmp_path / "broken"
    shutil.copytree(run, broken)
    (broken / RunDir.CHECKPOINT).write_bytes(b"torn")
    assert cli.main(["render", str(broken), "--cameras", str(capture), "--quiet"]) == 2
    assert "not a readable checkpoint" in capsys.readouterr().err and not (broken / RunDir.RENDERS).exists()
