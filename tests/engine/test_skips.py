"""The rules that fit a fit to its scene (vq_mitsuba/engine/skips.py): the bounce, the envmap's last
rung, the pace of the schedule (early stop) and the error-driven pixel sampler, each deciding
both ways."""

import json
import math

import numpy as np
import pytest
import torch

from tiny_scene import write_sphere_capture
from vq_mitsuba.config import load_config
from vq_mitsuba.engine import skips
from vq_mitsuba.engine.pipeline import fit
from vq_mitsuba.engine.trainer import Trainer
from vq_mitsuba.models import losses

QUICK = ["train.batch_rays=64", "residual.iterations=0", "vq.enabled=false"]


@pytest.fixture(scope="module")
def small_sphere(tmp_path_factory):
    return write_sphere_capture(tmp_path_factory.mktemp("sphere"), size=16, n_views=4, spp=8)


# --- bounce ----------------------------------------------------------------------------------------
def _bounce_decision(mesh, setting="auto"):
    """The bounce rule on the hits of rays from 300 random cameras around `mesh`."""
    from vq_mitsuba.render.shading import ShadingScene

    scene = ShadingScene(mesh.vertices, mesh.faces, np.ones((8, 16, 3), np.float32), np.eye(4),
                         normals=mesh.vertex_normals)
    rng = np.random.default_rng(0)
    d = rng.normal(size=(3000, 3))
    origins = 4.0 * d / np.linalg.norm(d, axis=1, keepdims=True)
    dirs = rng.normal(scale=0.3, size=(3000, 3)) - origins
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    hits = scene.trace(origins.astype(np.float32), dirs.astype(np.float32))
    return skips.decide_bounce(setting, 1, scene, hits.position[hits.valid], hits.wi[hits.valid], seed=0)


def test_the_bounce_is_off_for_a_lone_sphere_and_on_where_surfaces_face_each_other():
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=2, radius=0.5)  # coarse: facets far from the normals
    on, info = _bounce_decision(sphere)
    assert not on and info["choice"] == "off" and info["reason"].startswith("0.0 % of ")
    floor = trimesh.creation.box(extents=[2.0, 0.02, 2.0])
    floor.apply_translation([0, -0.52, 0])
    on, info = _bounce_decision(trimesh.util.concatenate([sphere, floor]))
    assert on and info["choice"] == "on"
    near, far = (trimesh.creation.box(extents=[1.0, 1.0, 0.02]) for _ in range(2))
    near.apply_translation([0, 0, -0.3])
    far.apply_translation([0, 0, 0.3])
    on, info = _bounce_decision(trimesh.util.concatenate([near, far]))
    share = float(info["reason"].split(" %")[0])
    assert on and share > 5.0
    assert _bounce_decision(sphere, "on")[0] and not _bounce_decision(floor, "off")[0]  # forced


# --- envmap ----------------------------------------------------------------------------------------
def test_the_envmap_stops_lower_for_matte_materials_than_for_glossy_ones():
    ladder = [32, 64, 128]
    matte = torch.full((1000,), 0.8)
    glossy = torch.cat([torch.full((900,), 0.8), torch.full((100,), 0.12)])  # one glossy part, 10 % of the hits
    satin = torch.full((1000,), 0.2)
    assert skips.envmap_rung(ladder, matte)[0] == 32
    assert skips.envmap_rung(ladder, satin)[0] == 64
    rows, why = skips.envmap_rung(ladder, glossy)
    assert rows == 128 and "quantile 0.120" in why and "the 128-row rung" in why
    # the bundled scenes' sharpest materials: balls' polished silver needs the top rung, demo's metal the first
    assert skips.rows_for_roughness(0.15) > 64 and skips.rows_for_roughness(0.3) < 32


def _rung_reads(monkeypatch, roughness_at) -> None:
    """The envmap rule reads the material field's roughness as `roughness_at(step)` everywhere."""
    real = Trainer.envmap_height

    def reading(self, progress):
        field = self.model.field
        forward, rough = field.forward, roughness_at(self.step)
        field.forward = lambda x: {**forward(x), "roughness": torch.full((len(x),), rough)}
        try:
            return real(self, progress)
        finally:
            del field.forward

    monkeypatch.setattr(Trainer, "envmap_height", reading)


def test_a_fit_records_its_envmap_rung_and_keeps_it_on_resume(tmp_path, monkeypatch):
    """A learned envmap on a matte sphere: the ladder (32, 64) would grow at step 4 of 8; the fitted
    roughness (here the field's, near 1) keeps it at 32 rows, recorded in fit.json and the checkpoint."""
    capture = write_sphere_capture(tmp_path / "cap", size=16, n_views=4, spp=8, known_envmap=False)
    cfg = load_config(None, QUICK + ["train.iterations=8", "envmap.height=64", "field.pe_anneal=1.0"])
    _rung_reads(monkeypatch, lambda step: 0.9)  # matte whatever the field has learned in 4 steps
    summary = fit(capture, tmp_path / "run", cfg)
    env = summary["decisions"]["envmap"]
    assert env["choice"] == 32 and env["ladder"] == [32, 64] and env["checks"][0]["step"] == 4
    state = torch.load(tmp_path / "run" / "checkpoint.pt", weights_only=False)
    assert state["envmap"]["log_radiance"].shape[0] == 32 and state["skips"]["envmap"]["cap"] == 32


def test_a_roughness_that_falls_after_the_first_decision_still_grows_the_envmap(tmp_path, monkeypatch):
    """The ladder (32, 64) reaches 64 at step 6 of 12 while the field reads as matte: 32 rows kept.
    From step 8 it reads as glossy; the next reading (every 2 steps here) grows the light to 64 rows,
    and fit.json records both decisions."""
    capture = write_sphere_capture(tmp_path / "cap", size=16, n_views=4, spp=8, known_envmap=False)
    cfg = load_config(None, QUICK + ["train.iterations=12", "envmap.height=64", "field.pe_anneal=1.0"])
    monkeypatch.setattr(skips, "ENVMAP_RECHECK_EVERY", 2)
    _rung_reads(monkeypatch, lambda step: 0.9 if step < 8 else 0.1)
    summary = fit(capture, tmp_path / "run", cfg)
    env = summary["decisions"]["envmap"]
    first, second = env["checks"]
    assert (first["step"], first["rows"], first["ladder_rows"]) == (6, 32, 64)
    assert (second["step"], second["rows"]) == (8, 64) and "quantile 0.100" in second["reason"]
    assert env["choice"] == 64
    state = torch.load(tmp_path / "run" / "checkpoint.pt", weights_only=False)
    assert state["envmap"]["log_radiance"].shape[0] == 64 and state["skips"]["envmap"]["cap"] == 64


# --- pace ------------------------------------------------------------------------------------------
def _run_pace(pace: skips.Pace, loss) -> int:
    """Advance `pace` step by step, measuring `loss(step)` when due; the step it finished at."""
    for step in range(1, pace.iterations + 1):
        pace.advance()
        if pace.due(step):
            pace.observe(step, loss(step))
        if pace.finished:
            return step
    return pace.iterations


def test_the_pace_doubles_on_plateaus_and_not_while_the_loss_improves():
    flat = skips.Pace(600, active=True)
    assert flat.every == 10
    end = _run_pace(flat, lambda step: 1.0)
    # six measurements (10..60), the last three no better than the three before: 2x at 60, 4x at
    # 120, 8x at 180, then 8x to the end
    assert flat.speedups == [[60, 2], [120, 4], [180, 8]] and flat.finished
    assert end == 180 + math.ceil((600 - 60 - 60 * 2 - 60 * 4) / 8)
    improving = skips.Pace(600, active=True)
    assert _run_pace(improving, lambda step: 0.98 ** step) == 600  # 18 % better at each measurement
    assert improving.speedups == [] and improving.position == 600
    noisy = skips.Pace(600, active=True)  # a slow trend under +-10 % noise: the window means see it
    _run_pace(noisy, lambda step: (0.995 ** step) * (1.1 if step % 20 else 0.9))
    assert noisy.speedups == []
    # not before every stage of the schedule has begun
    late = skips.Pace(600, active=True, start_share=0.5)
    _run_pace(late, lambda step: 1.0)
    assert late.speedups[0] == [350, 2] and len(late.evals) > 35
    # a new stage (the discrete branch) starts its plateau measurement again
    pace = skips.Pace(600, active=True)
    for step in range(10, 60, 10):
        pace.observe(step, 1.0)
    pace.new_phase()
    assert not pace.observe(60, 2.0) and pace.rate == 1 and pace.window == [2.0]


def test_a_converged_fit_stops_early_says_why_and_resumes(small_sphere, tmp_path, capsys, monkeypatch):
    """Learning rates so small that nothing changes: the held-aside loss never improves, the
    schedule speeds up and ends before train.iterations; fit.json says so; resuming with the same
    iterations has nothing to do, with more it goes on at the pace it had."""
    monkeypatch.setattr(skips, "STOP_MIN_EVERY", 5)  # a measurement every 5 steps: a short fit
    run = tmp_path / "run"
    settings = QUICK + ["train.stop=auto", "train.iterations=60", "train.lr=1e-9", "train.checkpoint_every=1000", "field.pe_anneal=0.1",
                        "loss.metallic_barrier_until=0.1"]
    summary = fit(small_sphere, run, load_config(None, settings))
    stop = json.loads((run / "fit.json").read_text())["decisions"]["stop"]
    # measured from step 10 (the stages begin at 10 % of the schedule): 2x at step 35, done at 48
    assert summary["iterations"] == 48 and stop["choice"] == "early"
    assert "schedule done at step 48 of 60" in stop["reason"] and "2x from step 35" in stop["reason"]
    assert "bounce off" in capsys.readouterr().out  # a lone sphere
    state = torch.load(run / "checkpoint.pt", weights_only=False)
    assert state["skips"]["pace"]["position"] >= 60 and state["step"] == summary["iterations"]
    # the schedule ran to its end: the last step's learning rate is the decayed one
    assert state["optim"]["param_groups"][0]["lr"] == pytest.approx(1e-9 * 0.1, rel=0.2)
    again = fit(small_sphere, run, load_config(None, settings), resume=True)
    assert again["iterations"] == summary["iterations"] and "nothing to do" in capsys.readouterr().out
    more = fit(small_sphere, run, load_config(None, settings + ["train.iterations=120"]), resume=True)
    # on at 2x with the two measurements it had since: 4x from step 65, done at 72
    assert more["iterations"] == 72 and more["decisions"]["stop"]["pace"]["speedups"] == [[35, 2], [65, 4]]


def test_a_fit_that_keeps_improving_runs_every_step(small_sphere, tmp_path, monkeypatch):
    losses = iter(0.9 ** k for k in range(1000))
    monkeypatch.setattr(Trainer, "held_loss", lambda self: next(losses))
    summary = fit(small_sphere, tmp_path / "run", load_config(None, QUICK + ["train.iterations=40", "train.stop=auto"]))
    stop = summary["decisions"]["stop"]
    assert summary["iterations"] == 40 and stop["choice"] == "iterations" and stop["pace"]["speedups"] == []
    assert len(stop["pace"]["evals"]) == 4
    off = fit(small_sphere, tmp_path / "off", load_config(None, QUICK + ["train.iterations=12", "train.stop=iterations",
                                                                        "train.sampling=uniform"]))
    assert off["decisions"]["stop"]["pace"]["evals"] == [] and off["decisions"]["sampling"]["choice"] == "uniform"


def test_held_aside_pixels_are_never_drawn(small_sphere, tmp_path):
    from vq_mitsuba.data.captures import load_capture
    from vq_mitsuba.run.run_dir import RunDir

    cfg = load_config(None, QUICK + ["train.iterations=10", "train.stop=auto"])
    capture = load_capture(small_sphere, split="train")
    trainer = Trainer(capture, RunDir(tmp_path / "run"), cfg)
    pool, data = trainer.data.pool, trainer.data
    key = pool.view * capture.width * capture.height + pool.pixel
    held = set(key[data.held.cpu()].tolist())
    assert len(held) == len(data.held) > 0
    drawn = torch.cat([data.draw(step, trainer.gen)[0] for step in range(50)])
    assert not held & set(key[drawn.cpu()].tolist())


def test_the_held_aside_loss_scores_each_pixels_mean(small_sphere, tmp_path, monkeypatch):
    """The held-aside loss shades every jittered hit of each held pixel and scores the pixel's mean,
    as a step does: shading that varies inside a pixel around its colour costs nothing, a pixel's
    mean off its colour does."""
    from vq_mitsuba.data.captures import load_capture
    from vq_mitsuba.run.run_dir import RunDir

    capture = load_capture(small_sphere, split="train")
    trainer = Trainer(capture, RunDir(tmp_path / "run"), load_config(None, QUICK + ["train.iterations=10",
                                                                                   "train.stop=auto"]))
    pool, shaded = trainer.data.pool, []
    key = pool.view * capture.width * capture.height + pool.pixel

    def shade(position, normal, wi, material, env, spp, **kw):
        hit = torch.cat([torch.nonzero((pool.position == p).all(1))[:1, 0] for p in position])
        shaded.append(hit)
        return pool.rgb[hit] * scale.repeat(len(hit) // 4)[:, None]

    monkeypatch.setattr(trainer.model.scene, "shade", shade)
    scale = torch.tensor([1.2, 0.8, 1.1, 0.9])  # each pixel's mean is its colour
    assert trainer.held_loss() == pytest.approx(0.0, abs=1e-9)
    assert torch.equal(key[shaded[0]].reshape(-1, 4), key[trainer.data.held][:, None].expand(-1, 4))
    scale = torch.tensor([1.2, 1.2, 1.2, 1.2])
    assert trainer.held_loss() > 1e-4


def test_the_training_pool_keeps_to_its_hit_budget(small_sphere, tmp_path):
    """train.max_hits: first fewer jittered hits per pixel, then a share of the pixels; every
    opaque pixel keeps its hits under the budget."""
    from vq_mitsuba.data.captures import load_capture
    from vq_mitsuba.run.run_dir import RunDir

    capture = load_capture(small_sphere, split="train")

    def pool(max_hits):
        cfg = load_config(None, QUICK + ["train.iterations=10", f"train.max_hits={max_hits}"])
        trainer = Trainer(capture, RunDir(tmp_path / f"run{max_hits}"), cfg)
        return trainer.data.pool, trainer.data.stats

    full, stats = pool(0)
    n = stats["opaque_pixels"]
    assert stats["hits_per_pixel"] == 4 and stats["pixel_share"] == 1.0 and len(full) > 3 * stats["used_pixels"]
    fewer, stats = pool(2 * n)  # 4 per pixel would exceed it: one each
    assert stats["hits_per_pixel"] == 1 and stats["pixel_share"] == 1.0
    assert len(fewer) == stats["used_pixels"] and int(fewer.copy.max()) == 0
    part, stats = pool(n // 2)
    assert stats["hits_per_pixel"] == 1 and stats["pixel_share"] == pytest.approx(0.5, abs=1e-3)
    assert 0.4 * len(fewer) < len(part) < 0.6 * len(fewer)


# --- sampler ---------------------------------------------------------------------------------------
def _pool(width=8, height=8, views=2, copies=1):
    from vq_mitsuba.data.pixels import PixelPool

    pix = torch.arange(width * height).repeat(views * copies)
    view = torch.arange(views).repeat_interleave(width * height).repeat(copies)
    copy = torch.arange(copies).repeat_interleave(views * width * height)
    n = len(pix)
    return PixelPool(torch.randn(n, 3), torch.randn(n, 3), torch.randn(n, 3), torch.rand(n, 3), view, pix, copy)


def test_the_error_sampler_draws_where_the_error_is_with_a_floor_for_every_pixel():
    from vq_mitsuba.data.pixels import ErrorSampler, sampler_tile

    pool = _pool()
    sampler = ErrorSampler(pool, torch.arange(len(pool)), 8, 8, tile=1, floor=0.3)
    n = len(pool)
    bad = torch.arange(10)  # ten pixels 100x worse than the rest
    err = torch.full((n,), 0.001)
    err[bad] = 0.1
    for _ in range(30):
        sampler.update(torch.arange(n), err)
    sampler.refresh()
    p = sampler.probabilities()
    assert float(p.min()) >= 0.3 / n * (1 - 1e-9)  # the floor
    gen = torch.Generator().manual_seed(0)
    idx, weight = sampler.draw(20000, gen)
    share_bad = float(torch.isin(idx, bad).float().mean())
    expected = 0.3 * 10 / n + 0.7 * 10 * 10 / (10 * 10 + (n - 10) * 1)  # sqrt(100) = 10x the RMS error
    assert share_bad == pytest.approx(expected, abs=0.02) and share_bad > 3 * 10 / n
    assert torch.bincount(idx, minlength=n).min() > 0  # no pixel starved
    # importance weights: the weighted mean of any per-pixel value is the uniform mean
    value = torch.rand(n, dtype=torch.float64)
    assert float((weight.double() * value[idx]).mean()) == pytest.approx(float(value.mean()), rel=0.03)
    assert float(weight.max()) <= 1 / 0.3 + 1e-6
    # tiles: every hit of a tile shares its error; the tile grows when the fit's draws are few
    tiled = ErrorSampler(_pool(copies=4), torch.arange(4 * n), 8, 8, tile=4)
    assert tiled.num_tiles == 2 * 2 * 2 and int(tiled.counts.sum()) == 4 * n
    assert sampler_tile(100_000, 2048 * 3000) == 1 and sampler_tile(2_000_000, 2048 * 3000) == 4


def test_a_step_shades_whole_pixels_and_scores_their_means(small_sphere, tmp_path, monkeypatch):
    """A step draws train.batch_rays / 4 pixels and shades every jittered hit of each, pixel by
    pixel; the reconstruction scores each pixel's mean: shading that varies inside a pixel around
    its colour costs nothing, where scoring hit by hit would ask every hit for the pixel's colour."""
    from vq_mitsuba.data.captures import load_capture
    from vq_mitsuba.engine.material_model import MaterialModel
    from vq_mitsuba.engine.schedule import StepSchedule
    from vq_mitsuba.run.run_dir import RunDir

    capture = load_capture(small_sphere, split="train")
    trainer = Trainer(capture, RunDir(tmp_path / "run"), load_config(None, QUICK + ["train.iterations=10"]))
    pool = trainer.data.pool
    key = pool.view * capture.width * capture.height + pool.pixel
    table = trainer.data.pixel_hits.cpu()
    assert trainer.data.copies == 4 and table.shape == (len(torch.unique(key)), 4)
    for row in table[torch.randperm(len(table))[:200]]:  # a pixel's row: its own hits, each of them
        assert len(set(key[row].tolist())) == 1
        assert set(row.tolist()) == set(torch.nonzero(key == key[row[0]])[:, 0].tolist())
    spread = torch.tensor([1.2, 0.8, 1.1, 0.9])  # the mean of each pixel's four hits is its colour
    shaded = []

    def render(self, data, idx, material, env, gen, bounce_fn, fixed_light=None):
        shaded.append(idx)
        return (pool.rgb[idx] * spread.repeat(len(idx) // 4)[:, None])[:, None, :].expand(-1, 8, -1)

    monkeypatch.setattr(MaterialModel, "_render", render)
    schedule = StepSchedule(done=0.0, progress=0.0, lr_factor=1.0, metallic_barrier=False, discrete=False)
    idx, _ = trainer.data.draw(0, trainer.gen)
    terms, rgb, _ = trainer.loss_terms(idx, schedule, bounce=False)
    assert len(idx) == 16 and len(shaded[0]) == 64
    assert torch.equal(key[shaded[0]].reshape(16, 4), key[idx][:, None].expand(-1, 4))
    assert float(terms["rec_c"]) == pytest.approx(0.0, abs=1e-9) and torch.allclose(rgb, pool.rgb[idx])
    per_hit = losses.reconstruction_l2_decorrelated(render(None, None, shaded[0], None, None, None, None),
                                                    pool.rgb[shaded[0]],
                                                    trainer.cfg.loss.gamma)
    assert float(per_hit) > 1e-4
