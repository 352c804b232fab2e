"""Fitting: CLI smoke run, resume, render, bad inputs, and recovery of a known material."""

import json
import warnings

import numpy as np
import pytest
import torch

from tiny_scene import write_lamp_capture, write_sphere_capture
from vq_mitsuba.cli import main
from vq_mitsuba.config import load_config
from vq_mitsuba.errors import InputError
from vq_mitsuba.engine.pipeline import fit


@pytest.fixture(scope="module")
def sphere_capture(tmp_path_factory):
    return write_sphere_capture(tmp_path_factory.mktemp("sphere"), size=24, n_views=8, spp=32)


@pytest.mark.slow  # over 10 s: CI runs it after the default suite (.ci/run)
def test_fit_resume_render_smoke(sphere_capture, tmp_path, capsys):
    run = tmp_path / "run"
    args = ["fit", str(sphere_capture), "-o", str(run), "--set", "vq.warmup_frac=0.3", "--set", "loss.w_sm=0.05",
            "--quiet", "--set", "train.iterations=6",
            "--set", "train.batch_rays=256", "--set", "train.log_every=2", "--set", "train.checkpoint_every=3"]
    assert main(args) == 0
    for name in ("config.yaml", "checkpoint.pt", "mesh.ply", "envmap.exr", "loss.png", "fit.json", "run.json",
                 "materials.json", "materials_err.png", "materials_sheet.png"):
        assert (run / name).is_file(), name
    materials = json.loads((run / "materials.json").read_text())
    assert len(materials["err_k"]) == 8 and 1 <= materials["num_materials"] <= 8
    assert len(materials["materials"]) == materials["num_materials"]
    assert json.loads((run / "fit.json").read_text())["iterations"] == 6
    # Fitting into an existing run without --resume is refused; nothing is overwritten.
    mtime = (run / "checkpoint.pt").stat().st_mtime
    assert main(args) == 2
    assert "--resume" in capsys.readouterr().err
    assert (run / "checkpoint.pt").stat().st_mtime == mtime
    # Resume continues from the checkpoint to the new iteration count.
    assert main(args[:-8] + ["--resume", "--set", "train.iterations=9"]) == 0
    state = torch.load(run / "checkpoint.pt", weights_only=False)
    assert state["step"] == 9
    assert [h["step"] for h in state["history"]][:3] == [2, 4, 6]
    # Render: every file of the interface, finite values, coverage where the sphere is.
    out = tmp_path / "views"
    assert main(["render", str(run), "--cameras", str(sphere_capture), "-o", str(out), "--quiet", "--spp", "8",
                 "--exposure", "1", "--env-rotate", "30"]) == 0
    from vq_mitsuba.data.imageio import read_image

    for kind in ("rgb.exr", "rgb.png", "basecolor.exr", "metallic.exr", "roughness.exr", "normal.exr", "alpha.png",
                 "material.png", "segmentation.png"):
        assert (out / f"view_00_{kind}").is_file(), kind
    rgb, alpha = read_image(out / "view_00_rgb.exr")
    assert np.isfinite(rgb).all() and alpha[12, 12] == 1.0 and alpha[0, 0] == 0.0
    import imageio.v3 as iio

    ids = iio.imread(out / "view_00_material.png")
    assert ids.dtype == np.uint8 and ids[0, 0] == 0 and 1 <= ids[12, 12] <= materials["num_materials"]


def test_fit_rejects_bad_inputs_before_training(sphere_capture, tmp_path):
    cfg = load_config(None, ["train.iterations=1"])
    with pytest.raises(InputError, match="transforms"):
        fit(tmp_path / "missing" / "transforms_train.json", tmp_path / "r1", cfg)
    with pytest.raises(InputError, match="unknown config key 'train.iteration'"):
        load_config(None, ["train.iteration=5"])
    with pytest.raises(InputError, match="expects int"):
        load_config(None, ["train.iterations=many"])
    bad = tmp_path / "bad.yaml"
    bad.write_text("train: [1, 2]\n")
    with pytest.raises(InputError, match="bad.yaml"):
        load_config(bad)
    # A capture without geometry stops before any run directory is written.
    no_geo = tmp_path / "nogeo"
    no_geo.mkdir()
    (no_geo / "images").symlink_to(sphere_capture.parent / "images")
    (no_geo / "env.exr").symlink_to(sphere_capture.parent / "env.exr")
    xml = sphere_capture.read_text()
    xml = xml.replace('  <shape type="ply"><string name="filename" value="sphere.ply"/></shape>\n', "")
    (no_geo / "scene.xml").write_text(xml)
    with pytest.raises(InputError, match="no known geometry"):
        fit(no_geo / "scene.xml", tmp_path / "r2", cfg)
    assert not (tmp_path / "r2").exists()
    with pytest.raises(InputError, match="no run to resume"):
        fit(sphere_capture, tmp_path / "r3", cfg, resume=True)


def test_resume_without_checkpoint_starts_the_fit(sphere_capture, tmp_path, capsys):
    """A run stopped before its first checkpoint (e.g. after the geometry stage) resumes from scratch."""
    run = tmp_path / "run"
    run.mkdir()
    cfg = load_config(None, ["train.iterations=2", "train.batch_rays=64"])
    summary = fit(sphere_capture, run, cfg, resume=True)
    assert summary["iterations"] == 2 and (run / "checkpoint.pt").is_file()
    assert "no checkpoint yet" in capsys.readouterr().out


def test_snapshots_keep_earlier_states(sphere_capture, tmp_path):
    """train.snapshot_s keeps the state at those fit seconds; RunDir.load reads a snapshot as the run."""
    from vq_mitsuba.run.run_dir import RunDir

    run = tmp_path / "run"
    cfg = load_config(None, ["train.iterations=4", "train.batch_rays=64", "train.snapshot_s=1e-6,1e-5"])
    fit(sphere_capture, run, cfg)
    snaps = sorted((run / "snapshots").glob("*.pt"))
    assert len(snaps) == 1  # both times had passed after the first step: one copy, not two
    state = torch.load(snaps[0], weights_only=False)
    assert state["step"] == 1 and "optim" not in state
    early, last = RunDir(run).load(snaps[0]), RunDir(run).load()
    x = torch.zeros(3, 3, device=last.model.center.device)
    assert not torch.allclose(early.model(x)["basecolor"], last.model(x)["basecolor"])  # three more steps
    with pytest.raises(InputError, match="snapshot_s"):
        fit(sphere_capture, tmp_path / "r2", load_config(None, ["train.snapshot_s=10,soon"]))
    assert not (tmp_path / "r2").exists()


def test_time_limit_drives_the_schedules(sphere_capture, tmp_path, monkeypatch):
    """A fit stopped by the clock long before its iteration count has run its schedules to the end
    (every encoding frequency open), while its learning rate decayed with the iterations only."""
    import itertools

    import vq_mitsuba.engine.pipeline as fit_module

    # The fit's clock advances 10 ms per reading, so the test does not depend on how fast (or how
    # evenly: a kernel compiled mid-fit makes one step long) this machine runs the steps.
    ticks = itertools.count()
    monkeypatch.setattr(fit_module.time, "perf_counter", lambda: 0.01 * next(ticks))
    run = tmp_path / "run"
    cfg = load_config(None, ["train.iterations=100000", "train.batch_rays=64", "train.time_limit_s=2",
                             "train.lr=0.002", "train.lr_end_exponential=0.01", "field.pe_anneal=0.5",
                             "vq.enabled=false"])
    summary = fit(sphere_capture, run, cfg)
    state = torch.load(run / "checkpoint.pt", weights_only=False)
    assert 10 < summary["iterations"] < 100000  # stopped by the clock
    assert float(state["model"]["encoder.pe.progress"]) == float(cfg.field.pe_freqs)
    # Set before each step: the last step ran at step - 1 steps done.
    factor = 0.01 ** ((state["step"] - 1) / 100000)
    assert state["optim"]["param_groups"][0]["lr"] == pytest.approx(0.002 * factor, rel=1e-9)
    # Without a time limit the schedule follows the iterations.
    cfg = load_config(None, ["train.iterations=4", "train.batch_rays=64", "train.lr=0.01",
                             "train.lr_end_exponential=0.1"])
    fit(sphere_capture, tmp_path / "r2", cfg)
    lr_end = torch.load(tmp_path / "r2" / "checkpoint.pt", weights_only=False)["optim"]["param_groups"][0]["lr"]
    assert lr_end == pytest.approx(0.01 * 0.1 ** 0.75)


def test_fit_recovers_uniform_sphere_material(tmp_path):
    """Known lighting, known geometry: basecolor within 0.05 and roughness within 0.1."""
    xml = write_sphere_capture(tmp_path / "cap", base_color=(0.7, 0.35, 0.2), roughness=0.3, size=32,
                               n_views=12, spp=64)
    cfg = load_config(None, ["train.iterations=400", "train.batch_rays=1024", "train.spp=8"], preset="continuous")
    fit(xml, tmp_path / "run", cfg)
    from vq_mitsuba.run.run_dir import RunDir

    fitted = RunDir(tmp_path / "run").load()
    pts = torch.tensor(np.asarray(fitted.mesh.vertices), dtype=torch.float32, device=fitted.model.center.device)
    with torch.no_grad():
        out = fitted.model(pts)
    base = out["basecolor"].mean(0).cpu().numpy()
    np.testing.assert_allclose(base, [0.7, 0.35, 0.2], atol=0.05)
    assert abs(out["roughness"].mean().item() - 0.3) < 0.1
    assert out["metallic"].mean().item() < 0.1


def test_metallic_barrier_stops_at_its_progress(sphere_capture, tmp_path, monkeypatch):
    """loss.metallic_barrier_until = 0.5 over 4 steps (progress 0, 0.25, 0.5, 0.75): the prior gets
    the metallic logit (the barrier) on the first two steps and the linear term after."""
    from vq_mitsuba.models import losses

    real, seen = losses.lambertian_prior, []

    def spy(metallic, roughness, metallic_weight=1.0, metallic_logit=None, weight=None, metallic_scale=None):
        seen.append(metallic_logit is not None)
        return real(metallic, roughness, metallic_weight, metallic_logit, weight, metallic_scale)

    monkeypatch.setattr(losses, "lambertian_prior", spy)
    run = tmp_path / "run"
    assert main(["fit", str(sphere_capture), "-o", str(run), "--quiet", "--set", "train.iterations=4",
                 "--set", "train.batch_rays=64", "--set", "loss.metallic_barrier_until=0.5",
                 "--preset", "continuous"]) == 0
    assert seen == [True, True, False, False]


def _nan_on_calls(monkeypatch, calls):
    """Make the reconstruction loss NaN on the given (1-based) calls."""
    from vq_mitsuba.models import losses

    real, count = losses.reconstruction_l2_decorrelated, [0]

    def patched(*args, **kwargs):
        count[0] += 1
        out = real(*args, **kwargs)
        return out * float("nan") if count[0] in calls else out

    monkeypatch.setattr(losses, "reconstruction_l2_decorrelated", patched)


def test_a_non_finite_step_is_skipped(sphere_capture, tmp_path, monkeypatch):
    _nan_on_calls(monkeypatch, {3})
    run = tmp_path / "run"
    assert main(["fit", str(sphere_capture), "-o", str(run), "--quiet", "--set", "train.iterations=6",
                 "--set", "train.batch_rays=128", "--set", "train.log_every=1"]) == 0
    assert json.loads((run / "fit.json").read_text())["nonfinite_steps_skipped"] == 1
    state = torch.load(run / "checkpoint.pt", weights_only=False)
    assert state["step"] == 6 and len(state["history"]) == 5  # the skipped step logs nothing
    assert all(torch.isfinite(v).all() for v in state["model"].values())


def test_non_finite_steps_in_a_row_stop_the_fit_keeping_the_last_finite_state(sphere_capture, tmp_path,
                                                                              monkeypatch, capsys):
    from vq_mitsuba.engine.trainer import MAX_NONFINITE_RUN

    _nan_on_calls(monkeypatch, set(range(3, 100)))
    run = tmp_path / "run"
    assert main(["fit", str(sphere_capture), "-o", str(run), "--quiet", "--set", "train.iterations=40",
                 "--set", "train.batch_rays=128"]) == 3  # a RunFailure: the fit stopped mid-way
    err = capsys.readouterr().err
    assert str(run) in err and "non-finite" in err
    last = 2 + MAX_NONFINITE_RUN  # steps 1 and 2 update, then MAX_NONFINITE_RUN are skipped
    assert f"steps 3 to {last}" in err and "parameters of step 2" in err
    state = torch.load(run / "checkpoint.pt", weights_only=False)
    assert state["step"] == last
    assert all(torch.isfinite(v).all() for v in state["model"].values())


def test_the_discrete_loss_leaves_the_light_to_the_continuous_branch(tmp_path):
    """Separate training (ablation.separate), light from the continuous branch: nothing but the discrete branch learns (the
    continuous loss and priors are off), so the continuous field and the envmap stay as they were
    after one step; with the discrete loss allowed to train the light, the envmap moves."""
    base = ["--quiet", "--set", "vq.enabled=true", "--set", "vq.warmup_frac=0", "--set", "ablation.separate=true",
            "--set", "loss.w_rec_c=0", "--set", "loss.w_chr=0", "--set", "loss.w_lam=0",
            "--set", "envmap.tv_weight=0", "--set", "envmap.height=32", "--set", "train.bounces=1",
            "--set", "train.bounce_after=0",
            "--set", "train.batch_rays=128"]

    capture = write_sphere_capture(tmp_path / "capture", size=16, n_views=4, spp=16, known_envmap=False)

    def state(name, iterations, frozen):
        run = tmp_path / name
        assert main(["fit", str(capture), "-o", str(run), *base, "--set", f"train.iterations={iterations}",
                     "--set", f"ablation.shared_light={str(not frozen).lower()}"]) == 0
        return torch.load(run / "checkpoint.pt", weights_only=False)

    def weights(sd):
        return {k: v for k, v in sd.items() if k.endswith(("weight", "bias"))}

    one, three = state("one", 1, True), state("three", 3, True)
    assert weights(one["model"]) and all(torch.equal(v, weights(three["model"])[k])
                                         for k, v in weights(one["model"]).items())
    assert all(torch.equal(v, three["envmap"][k]) for k, v in one["envmap"].items())
    assert not all(torch.equal(v, three["discrete"][k]) for k, v in weights(one["discrete"]).items())
    shared = state("shared", 3, False)
    assert not all(torch.equal(v, shared["envmap"][k]) for k, v in one["envmap"].items())


@pytest.mark.parametrize("bounce_after, with_bounce", [(0, 12), (5, 7), (12, 0)])
def test_bounce_starts_after_its_number_of_steps(sphere_capture, tmp_path, monkeypatch, bounce_after, with_bounce):
    """train.bounce_after: the first steps shade direct light only (no material lookup at the
    bounce's hits), the later ones simulate the bounce."""
    from vq_mitsuba.render.shading import ShadingScene

    calls = []
    original = ShadingScene.shade

    def spy(self, *args, material_fn=None, **kwargs):
        if args[-1] == 8:  # the training step's call (spp 8); the bounce's own shading uses spp 1
            calls.append(material_fn is not None)
        return original(self, *args, material_fn=material_fn, **kwargs)

    monkeypatch.setattr(ShadingScene, "shade", spy)
    cfg = load_config(None, ["train.iterations=12", "train.batch_rays=64", "train.spp=8", "train.bounces=1",
                             f"train.bounce_after={bounce_after}", "train.bounce=on", "train.stop=iterations"],
                      preset="continuous")
    fit(sphere_capture, tmp_path / "run", cfg)
    assert len(calls) == 12
    assert sum(calls) == with_bounce
    assert calls == sorted(calls)  # once on, it stays on


def test_resume_after_the_envmap_grew(tmp_path):
    """The learned envmap grows during the fit; a run checkpointed after that resumes at its size
    and keeps growing to envmap.height."""
    from vq_mitsuba.run.run_dir import RunDir

    base = ["--quiet", "--set", "envmap.height=64", "--set", "field.pe_anneal=0.5", "--set", "train.batch_rays=128",
            "--set", "vq.enabled=false", "--set", "train.checkpoint_every=2", "--set", "envmap.final_height=full"]
    capture = write_sphere_capture(tmp_path / "capture", size=16, n_views=4, spp=16, known_envmap=False)
    run = tmp_path / "run"
    assert main(["fit", str(capture), "-o", str(run), *base, "--set", "train.iterations=4"]) == 0
    grown = torch.load(run / "checkpoint.pt", weights_only=False)["envmap"]["log_radiance"]
    assert grown.shape == (64, 128, 3)  # 32 rows for the first half of the annealing share, then 64
    assert main(["fit", str(capture), "-o", str(run), *base, "--set", "train.iterations=6", "--resume"]) == 0
    state = torch.load(run / "checkpoint.pt", weights_only=False)
    assert state["step"] == 6 and state["envmap"]["log_radiance"].shape == (64, 128, 3)
    assert RunDir(run).load().envmap.shape == (64, 128, 3)


@pytest.fixture
def five_step_run(tmp_path):
    """(capture, run folder, settings) of a 5-step fit with a learned envmap grown to 128 rows."""
    capture = write_sphere_capture(tmp_path / "capture", size=16, n_views=4, spp=8, known_envmap=False)
    run = tmp_path / "run"
    base = ["--quiet", "--set", "train.batch_rays=128", "--set", "vq.warmup_frac=0.3", "--set", "envmap.final_height=full"]
    assert main(["fit", str(capture), "-o", str(run), *base, "--set", "train.iterations=5"]) == 0
    assert torch.load(run / "checkpoint.pt", weights_only=False)["envmap"]["log_radiance"].shape[0] == 128
    return capture, run, base


def _config_iterations(run) -> int:
    import yaml

    return yaml.safe_load((run / "config.yaml").read_text())["train"]["iterations"]


def test_resume_with_more_iterations_follows_the_resumed_schedule(five_step_run, monkeypatch):
    """Step 5 of 40 is early on the envmap's ladder: the 128-row envmap is averaged down to 32 rows
    and grows back to 128 by the end; config.yaml matches the checkpoint."""
    from vq_mitsuba.engine.trainer import Trainer

    capture, run, base = five_step_run
    heights = []
    step = Trainer.train_step
    monkeypatch.setattr(Trainer, "train_step", lambda self, s: (step(self, s), heights.append(
        self.model.envmap_rows))[0])
    before = torch.exp(torch.load(run / "checkpoint.pt", weights_only=False)["envmap"]["log_radiance"])
    assert main(["fit", str(capture), "-o", str(run), *base, "--set", "train.iterations=40", "--resume"]) == 0
    assert heights[0] == 32 and heights[-1] == 128 and heights == sorted(heights)
    state = torch.load(run / "checkpoint.pt", weights_only=False)
    assert state["step"] == 40 and state["envmap"]["log_radiance"].shape == (128, 256, 3)
    assert state["config"]["train"]["iterations"] == _config_iterations(run) == 40
    assert json.loads((run / "fit.json").read_text())["iterations"] == 40
    # The shrunk envmap keeps the light's mean radiance (an average, not a fresh start).
    shrunk = torch.nn.functional.adaptive_avg_pool2d(before.permute(2, 0, 1), (32, 64))
    assert torch.allclose(shrunk.mean((1, 2)), before.mean((0, 1)), rtol=1e-4)


def test_resume_with_fewer_iterations_leaves_the_run_unchanged(five_step_run, capsys):
    capture, run, base = five_step_run
    files = {p.name: p.read_bytes() for p in run.iterdir() if p.is_file()}
    loud = [a for a in base if a != "--quiet"]  # the note is what is checked
    assert main(["fit", str(capture), "-o", str(run), *loud, "--set", "train.iterations=3", "--resume"]) == 0
    out = capsys.readouterr().out
    assert "already fitted (5 iterations; train.iterations=3" in out and "nothing to do" in out
    assert main(["fit", str(capture), "-o", str(run), *base, "--set", "train.iterations=3", "--resume"]) == 0
    assert "already fitted" not in capsys.readouterr().out  # --quiet: no note (the command's result remains)
    assert {p.name: p.read_bytes() for p in run.iterdir() if p.is_file()} == files
    assert _config_iterations(run) == torch.load(run / "checkpoint.pt", weights_only=False)["config"]["train"][
        "iterations"] == 5


def test_resume_past_the_target_of_an_unfinished_run_finishes_it(five_step_run, capsys):
    """A run stopped after its last step but before its results (no fit.json): resuming with fewer
    iterations writes the results at the steps done, and config.yaml says that many."""
    capture, run, base = five_step_run
    (run / "fit.json").unlink()
    assert main(["fit", str(capture), "-o", str(run), *base, "--set", "train.iterations=3", "--resume"]) == 0
    assert json.loads((run / "fit.json").read_text())["iterations"] == 5
    assert _config_iterations(run) == 5 == torch.load(run / "checkpoint.pt", weights_only=False)["step"]


def test_a_mesh_far_too_large_for_the_cameras_is_warned_about(tmp_path, capsys):
    import trimesh

    capture = write_sphere_capture(tmp_path / "capture", size=16, n_views=4, spp=8)
    cfg = load_config(None, ["train.iterations=2", "train.batch_rays=64", "vq.enabled=false"])
    from vq_mitsuba.errors import Notice

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        fit(capture, tmp_path / "right", cfg)
    assert not [w for w in caught if "the mesh" in str(w.message)]
    trimesh.creation.icosphere(subdivisions=3, radius=500.0).export(capture.parent / "sphere.ply")  # mm, not m
    with pytest.warns(Notice, match=r"the mesh's bounding sphere \(radius 866\) encloses every camera"):  # 500 * sqrt(3)
        fit(capture, tmp_path / "huge", cfg)
    assert "the mesh" not in capsys.readouterr().out  # a warning, not a result on stdout



def _lamp_fit(tmp_path, frame: str, lamp: tuple, intensity: float, roughness: float = 0.6):
    """A short continuous fit of `write_lamp_capture` with one lamp of `frame`: (fitted run, fit.json)."""
    from vq_mitsuba.run.run_dir import RunDir

    xml = write_lamp_capture(tmp_path / "cap", lamp=lamp, intensity=intensity, flash=frame == "camera",
                             roughness=roughness)
    cfg = load_config(None, ["train.iterations=400", "train.batch_rays=1024", "train.spp=8", "lamps.count=1",
                             f"lamps.frame={frame}", "residual.iterations=0"], preset="continuous")
    fit(xml, tmp_path / "run", cfg)
    run = RunDir(tmp_path / "run")
    return run.load(), json.loads((tmp_path / "run" / "fit.json").read_text())


@pytest.mark.slow  # about 10 s: CI runs it after the default suite (.ci/run)
def test_fit_recovers_a_lamp_in_the_world(tmp_path):
    """A sphere on a slab under a dim sky and a point lamp (Mitsuba's path tracer): the fit places
    the lamp within 10 % of the object's size and its power within 20 %, and fit.json says so."""
    lamp = np.array([0.9, 1.1, 0.6])
    fitted, summary = _lamp_fit(tmp_path, "world", tuple(lamp), 3.0)
    size = float(np.linalg.norm(np.ptp(np.asarray(fitted.mesh.bounds), axis=0)))
    assert not fitted.lamps.in_camera
    assert np.linalg.norm(fitted.lamps.position[0] - lamp) < 0.1 * size
    assert abs(fitted.lamps.intensity[0].mean() / 3.0 - 1) < 0.2
    decision = summary["decisions"]["lamps"]
    assert decision["choice"] == "world"
    np.testing.assert_allclose(decision["lamps"][0]["position"], fitted.lamps.position[0], atol=1e-5)
    # render under the fitted light records the lamp that lit it; another envmap, none unless kept
    from vq_mitsuba.data.imageio import write_exr
    from vq_mitsuba.render.render_run import render_run

    write_exr(tmp_path / "env.exr", np.full((8, 16, 3), 0.5, np.float32))
    for name, envmaps, keep, lit in (("own", (), False, 1), ("relit", (tmp_path / "env.exr",), False, 0),
                                     ("kept", (tmp_path / "env.exr",), True, 1)):
        out = render_run(tmp_path / "run", tmp_path / "cap" / "scene.xml", tmp_path / name, envmaps, spp=2,
                         keep_lamps=keep)
        assert json.loads((out / "render.json").read_text())["lamps"] == lit, name


@pytest.mark.slow  # about 10 s: CI runs it after the default suite (.ci/run)
def test_fit_recovers_a_flash(tmp_path):
    """The same scene, glossier, lit by a flash 0.3 above each camera's lens: the fitted lamp rides
    with the camera, found above its lens (it starts at the lens) within 10 % of the object's size,
    its power within 20 %."""
    flash = np.array([0.0, 0.3, 0.0])
    fitted, summary = _lamp_fit(tmp_path, "camera", tuple(flash), 8.0, roughness=0.3)
    size = float(np.linalg.norm(np.ptp(np.asarray(fitted.mesh.bounds), axis=0)))
    assert fitted.lamps.in_camera and summary["decisions"]["lamps"]["choice"] == "camera"
    assert fitted.lamps.position[0][1] > 0.1 and fitted.lamps.position[0][2] == 0.0
    assert np.linalg.norm(fitted.lamps.position[0] - flash) < 0.1 * size
    assert abs(fitted.lamps.intensity[0].mean() / 8.0 - 1) < 0.2


def test_resume_refuses_another_lamp_count(tmp_path):
    """A checkpoint fitted without lamps is not resumed with lamps.count=1, nor one fitted with a
    lamp in the world with a flash: the message names the checkpoint and the key."""
    xml = write_sphere_capture(tmp_path / "cap", size=12, n_views=3, spp=4, known_envmap=False)
    run = tmp_path / "run"
    assert main(["fit", str(xml), "-o", str(run), "--quiet", "--set", "train.iterations=2",
                 "--set", "train.batch_rays=64", "--set", "residual.iterations=0", "--preset", "continuous"]) == 0
    with pytest.raises(InputError, match="lamps.count=0, not 1") as err:
        fit(xml, run, load_config(None, ["train.iterations=4", "train.batch_rays=64", "lamps.count=1"],
                                  preset="continuous"), resume=True)
    assert err.value.path.name == "checkpoint.pt"
    lamp_run = tmp_path / "lamp_run"
    assert main(["fit", str(xml), "-o", str(lamp_run), "--quiet", "--set", "train.iterations=2", "--set", "lamps.count=1",
                 "--set", "train.batch_rays=64", "--set", "residual.iterations=0", "--preset", "continuous"]) == 0
    with pytest.raises(InputError, match="lamps.frame=world, not camera"):
        fit(xml, lamp_run, load_config(None, ["train.iterations=4", "train.batch_rays=64", "lamps.count=1",
                                              "lamps.frame=camera"], preset="continuous"), resume=True)
