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
    ("train.lr=nan", "finite"), ("train.lr=-0.01", "> 0"), ("envmap.lr=inf", "finite"),
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
        render_views(fitted, cams[:1], world, tmp_path, exposure_ev=ev, spp=4, progress=False)
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
            out = scene.shade(pos, normal, wi, bc, torch.full((n,), metal), torch.full((n,), rough),
                              torch.as_tensor(env * scale), 16, generator=torch.Generator().manual_seed(0))
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
    from vq_mitsuba.data.photo_formats import Lens, write_colmap

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
