"""The Lambertian prior weighed by the view-dependent light the fit leaves unexplained
(vq_mitsuba/engine/evidence.py): the measure on Mitsuba renders of known materials, the weights,
their grid, and the trainer's use of them."""

import json
import math

import numpy as np
import pytest
import torch

from tiny_scene import smooth_env, write_sphere_capture
from vq_mitsuba.config import load_config
from vq_mitsuba.data.captures import load_capture
from vq_mitsuba.data.pixels import trace_training_pixels
from vq_mitsuba.engine import evidence
from vq_mitsuba.engine.pipeline import fit
from vq_mitsuba.engine.schedule import schedule_at
from vq_mitsuba.engine.trainer import Trainer
from vq_mitsuba.run.loop import Progress
from vq_mitsuba.render.shading import scene_for_mesh
from vq_mitsuba.run.run_dir import RunDir

QUICK = ["train.batch_rays=64", "residual.iterations=0", "train.iterations=40", "vq.warmup_frac=0.1"]
GOLD = dict(base_color=(0.9, 0.6, 0.15), roughness=0.3, metallic=1.0)
PLASTIC = dict(base_color=(0.3, 0.2, 0.05), roughness=0.3, metallic=0.0)


@pytest.fixture(scope="module")
def spheres(tmp_path_factory):
    """A glossy gold sphere and a glossy plastic one of the same hue under the same light, a broad sun."""
    return {name: write_sphere_capture(tmp_path_factory.mktemp(name), size=48, n_views=16, spp=32,
                                       env=smooth_env(lobe_strength=40.0, lobe_width=5.0), **material)
            for name, material in (("gold", GOLD), ("plastic", PLASTIC))}


def _views(capture_path, n=512):
    capture = load_capture(capture_path)
    scene = scene_for_mesh(capture.mesh, capture.envmap, capture.envmap_to_world)
    pool, _ = trace_training_pixels(scene, capture, 0.5)
    idx = torch.randperm(len(pool), generator=torch.Generator().manual_seed(0))[:n]
    pos, nrm = pool.position[idx], pool.normal[idx]
    return capture, scene, pos, nrm, evidence.sample_views(scene, capture, pos, nrm, 0.5, seed=1)


def test_saturation_is_the_chromaticity_s_distance_from_grey():
    sat = evidence.saturation(torch.tensor([[0.5, 0.5, 0.5], [2.0, 2.0, 2.0], [1.0, 0.0, 0.0], [0.2, 0.1, 0.1]]))
    assert sat.tolist() == pytest.approx([0.0, 0.0, math.sqrt(2 / 3), math.sqrt(6) / 12], abs=1e-6)


def _samples(rows):
    """ViewSamples of hits whose colours in their views are `rows` (lists of RGB, None: not seen)."""
    k = max(len(r) for r in rows)
    rgb = torch.full((len(rows), k, 3), float("nan"))
    view = torch.full((len(rows), k), -1)
    for i, r in enumerate(rows):
        for j, c in enumerate(r):
            if c is not None:
                rgb[i, j], view[i, j] = torch.tensor(c), j
    return evidence.ViewSamples(view, rgb)


def test_a_highlight_keeps_the_colour_of_a_metal_and_pales_on_a_dielectric():
    red, grey = [0.4, 0.1, 0.1], [0.3, 0.3, 0.3]
    tint = evidence.highlight_tint(_samples([
        [red] * 6 + [[1.6, 0.4, 0.4]] * 2,  # a metal: the highlight is the surface's colour, brighter
        [red] * 6 + [[1.6, 1.3, 1.3]] * 2,  # a dielectric: the light's white added
        [red] * 6 + [[0.55, 0.25, 0.25]] * 2,  # a dielectric's faint highlight (1.7 x): white added all the same
        [red] * 8,  # no highlight: no evidence
        [grey] * 6 + [[1.2, 1.2, 1.2]] * 2,  # a grey surface: no colour to keep
        [red] * 7 + [[1.6, 0.4, 0.4]],  # a highlight in one view only: a misregistered edge as likely
        [red, red, [1.6, 0.4, 0.4], None, None, None, None, None],  # seen in too few views
    ]))
    assert float(tint[0]) == pytest.approx(1.0, abs=1e-5)
    assert tint[1:3].tolist() == pytest.approx([0.0, 0.0], abs=1e-5)  # nothing of the colour kept
    assert float(evidence.saturation(torch.tensor([0.55, 0.25, 0.25])) / evidence.saturation(torch.tensor(red))) > 0.55
    assert bool(torch.isnan(tint[3:]).all())
    assert evidence.metallic_weight(tint).tolist()[:4] == [0.0, 1.0, 1.0, 1.0]


def test_a_hit_is_read_in_the_views_that_face_it_at_its_pixel(spheres):
    capture, scene, pos, nrm, views = _views(spheres["plastic"])
    assert float(views.seen().float().mean()) > 0.5  # 16 views around a sphere: most hits face MIN_VIEWS of them
    p, k = torch.nonzero(views.valid, as_tuple=True)
    v = views.view[p, k]
    cams = capture.cameras
    # the camera of each view a hit is read in lies within FACING of the hit's normal
    to_cam = torch.stack([torch.as_tensor(cams[int(i)].origin, dtype=torch.float32) for i in v]) - pos[p]
    to_cam = to_cam / to_cam.norm(dim=1, keepdim=True)
    assert bool(((to_cam * nrm[p]).sum(1) > evidence.FACING).all())
    # and the colour is that of the image at the hit's projection in that view, an opaque pixel
    for j in range(0, len(p), 97):
        cam, point = cams[int(v[j])], pos[int(p[j])].double().numpy()[None]
        x, y = np.floor(cam.project(point)[0]).astype(int)
        assert views.rgb[p[j], k[j]].tolist() == pytest.approx(capture.images[int(v[j]), y, x].tolist(), rel=1e-6)
        assert capture.alpha[int(v[j]), y, x] >= evidence.OPAQUE
    assert bool(torch.isnan(views.rgb[~views.valid]).all())
    # a hit on the far side of the sphere (centred at the origin) from a camera is never read in it
    for i in range(len(cams)):
        away = (nrm * torch.as_tensor(cams[i].origin, dtype=torch.float32)).sum(1) < -0.2
        assert not bool((views.view[away] == i).any())


def test_mitsuba_renders_of_a_gold_weaken_the_metallic_prior_and_of_a_plastic_keep_it(spheres):
    """Rendered by Mitsuba's path tracer under the same light: the gold's highlights keep its colour
    and the metallic term is off where they are; the plastic's highlights pale and it keeps the term."""
    weight, tints = {}, {}
    for name in ("gold", "plastic"):
        capture, scene, pos, nrm, views = _views(spheres[name], n=evidence.HITS)
        tint = evidence.highlight_tint(views)
        tints[name] = tint[~torch.isnan(tint)]
        assert len(tints[name]) > 50  # a glossy sphere under a broad sun: highlights on both
        bounds = torch.tensor(np.array(capture.mesh.bounds), dtype=torch.float32)
        weight[name] = evidence.WeightGrid.of_tints(pos, tint, bounds)(pos)
    assert float(tints["gold"].median()) > evidence.METAL
    assert float(tints["plastic"].median()) < 0.5 * (evidence.DIELECTRIC + evidence.METAL)
    weakened = weight["gold"] < 1
    assert float(weakened.float().mean()) > 0.15 and float(weight["gold"][weakened].median()) == 0.0
    assert float((weight["plastic"] < 1).float().mean()) < 0.02


def test_weights_are_whole_up_to_a_dielectric_s_tint_and_off_from_a_metal_s():
    t = torch.tensor([0.0, evidence.DIELECTRIC, 0.5 * (evidence.DIELECTRIC + evidence.METAL), evidence.METAL, 1.5,
                      float("nan")])
    assert evidence.metallic_weight(t).tolist() == pytest.approx([1.0, 1.0, 0.5, 0.0, 0.0, 1.0])


def test_the_grid_averages_the_tints_of_a_voxel_with_enough_evidence_and_keeps_the_term_elsewhere():
    bounds = torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]])
    metal, dielectric = evidence.METAL + 0.05, evidence.DIELECTRIC - 0.2
    nan = float("nan")
    points = torch.tensor([[0.1, 0.1, 0.1]] * 4 + [[0.9, 0.9, 0.9]] * 2 + [[0.6, 0.1, 0.1]] * 3
                          + [[0.1, 0.9, 0.1]] * 10)
    tint = torch.tensor([metal, metal, metal - 0.4, nan,  # mean of the three with evidence
                         metal, metal,  # too few with evidence
                         dielectric, dielectric, dielectric,
                         metal, metal, metal] + [nan] * 7)  # evidence on too small a share of the voxel's hits
    grid = evidence.WeightGrid.of_tints(points, tint, bounds, res=4)
    mean = (3 * metal - 0.4) / 3
    looked = grid(torch.tensor([[0.05, 0.2, 0.15], [0.95, 0.8, 0.9], [0.6, 0.15, 0.1], [0.5, 0.9, 0.5],
                                [0.1, 0.9, 0.1], [2.0, 0.0, 0.0]]))
    assert 0 < float(evidence.metallic_weight(torch.tensor(mean))) < 1
    assert looked.tolist() == pytest.approx([float(evidence.metallic_weight(torch.tensor(mean))), 1.0, 1.0, 1.0, 1.0,
                                             1.0])
    assert not grid.full


def _trainer(capture_path, tmp_path, extra=()):
    return Trainer(load_capture(capture_path, split="train"), RunDir(tmp_path / "run"),
                   load_config(None, QUICK + list(extra)))


@pytest.fixture(scope="module")
def learned_light_gold(tmp_path_factory):
    return write_sphere_capture(tmp_path_factory.mktemp("gold"), size=32, n_views=12, spp=16, known_envmap=False,
                                env=smooth_env(lobe_strength=40.0, lobe_width=5.0), **GOLD)


def test_a_capture_that_keeps_the_whole_prior_fits_as_without_the_rule(learned_light_gold, tmp_path, monkeypatch):
    """No voxel below 1: no grid, and every step's prior is called as with the rule off (no per-hit
    weight), so the fit is the one without the rule."""
    from vq_mitsuba.models import losses

    monkeypatch.setattr(evidence, "DIELECTRIC", 1e9)  # no highlight is metal enough
    monkeypatch.setattr(evidence, "METAL", 2e9)
    real, scales = losses.lambertian_prior, []

    def spy(*args, **kwargs):
        scales.append(args[5] if len(args) > 5 else kwargs.get("metallic_scale"))
        return real(*args, **kwargs)

    monkeypatch.setattr(losses, "lambertian_prior", spy)
    out = tmp_path / "auto"
    fit(learned_light_gold, out, load_config(None, QUICK))
    decision = json.loads((out / "fit.json").read_text())["decisions"]["prior"]
    assert decision["choice"] == "whole" and decision["hits_with_highlight"] > 0 and decision["mean_weight"] == 1.0
    assert len(scales) >= 40 and all(s is None for s in scales)


def test_where_the_images_say_metal_the_metallic_term_is_off_and_the_roughness_term_stays(learned_light_gold, tmp_path,
                                                                                          monkeypatch):
    monkeypatch.setattr(evidence, "DIELECTRIC", -2.0)  # every highlight counts as a metal's
    monkeypatch.setattr(evidence, "METAL", -1.0)
    trainer = _trainer(learned_light_gold, tmp_path)
    decision = trainer.decisions_so_far()["prior"]
    assert decision["choice"] == "weighed" and decision["hits_with_highlight"] > 0
    hits = torch.arange(64)
    pos = trainer.data.pool.position[hits]
    off = trainer.model.prior_grid(pos) == 0
    assert bool(off.any())
    out = trainer.model.field(pos)
    s = schedule_at(trainer.cfg, Progress(0, 0.0, 0.5, 0.0))  # after the barrier: the linear terms
    term = trainer.model.lambertian(out, s, None, trainer.model.prior_grid(pos))
    lam_m = trainer.cfg.loss.lam_metallic
    expected = torch.mean(torch.where(off, 0.0, lam_m * out["metallic"]) + 1.0 - out["roughness"])
    assert float(term.detach()) == pytest.approx(float(expected.detach()), rel=1e-5)
    whole = trainer.model.lambertian(out, s)
    assert float(whole.detach()) > float(term.detach())  # the metallic term of the hits where it is off is gone
    # the term's gradient no longer reaches the metallic of those hits
    metallic = out["metallic"].detach().requires_grad_(True)
    losses_term = trainer.model.lambertian({**out, "metallic": metallic}, s, None, trainer.model.prior_grid(pos))
    losses_term.backward()
    assert bool((metallic.grad[off] == 0).all()) and bool((metallic.grad[~off] > 0).all())
    # the same grid after a resume: decided again from the same seed and images
    trainer.run.create()
    trainer.checkpoint(1.0)
    again = _trainer(learned_light_gold, tmp_path)
    again.resume()
    assert torch.equal(again.model.prior_grid.values, trainer.model.prior_grid.values)


def _block_light(direction, rows=32):
    """A dark lat-long light (envmaps convention) with one bright block of texels about `direction`."""
    from vq_mitsuba.data.envmaps import direction_to_uv

    env = np.full((rows, 2 * rows, 3), 0.1, np.float32)
    u, v = direction_to_uv(np.asarray(direction, float))
    r, c = int(v * rows), int(u * 2 * rows)
    env[max(r - 2, 0):r + 2, [(c + k) % (2 * rows) for k in range(-2, 2)]] = 50.0
    return torch.tensor(env)


def _unit(v):
    v = np.asarray(v, float)
    return v / np.linalg.norm(v)


@pytest.mark.parametrize("mitsuba_world", [False, True])
def test_the_mirror_direction_looks_up_the_light_a_view_reflects_towards(mitsuba_world):
    """A hit whose normal halves a camera's direction and the bright block's sees the block about its
    mirror direction; from another camera it sees the dark light; in a Mitsuba-world capture (Y up,
    identity to_world) the same world directions are turned into the light's frame."""
    from vq_mitsuba.data.cameras import BLENDER_ENV_TO_WORLD, MITSUBA_TO_BLENDER

    sun = _unit([0.3, -0.5, 0.8])  # Blender world, the light's frame
    light = evidence.lobe_light(_block_light(sun))
    to_world = np.eye(4) if mitsuba_world else BLENDER_ENV_TO_WORLD
    to_env = BLENDER_ENV_TO_WORLD[:3, :3] @ np.linalg.inv(to_world[:3, :3])
    world = (lambda d: MITSUBA_TO_BLENDER.T @ d) if mitsuba_world else (lambda d: d)
    p = np.array([[0.1, 0.2, 0.0]])
    w = _unit([-0.6, 0.2, 0.5])
    n = world(_unit(w + sun))[None]
    towards = evidence.mirror_light(light, world(p[0])[None], n, world(p[0] + 3 * w)[None], to_env)
    away = evidence.mirror_light(light, world(p[0])[None], n, world(p[0] + 3 * _unit([0.5, 0.6, 0.4]))[None], to_env)
    assert float(towards[0]) > 10 * float(away[0])
    assert float(away[0]) == pytest.approx(0.1 * sum(evidence.LUMINANCE), rel=1e-3)


def test_rank_correlation_over_the_views_a_hit_is_seen_in():
    a = np.array([[1.0, 2.0, 3.0, 4.0, 5.0, 0.0], [1.0, 2.0, 3.0, 4.0, 5.0, 9.0], [5.0, 4.0, 3.0, 2.0, 1.0, 0.0],
                  [1.0, 1.0, 1.0, 1.0, 1.0, 1.0], [1.0, 2.0, 3.0, 0.0, 0.0, 0.0]])
    b = np.array([[10.0, 20.0, 30.0, 40.0, 50.0, -7.0]] * 5)
    valid = np.ones_like(a, bool)
    valid[0, 5] = False  # not seen: left out
    valid[4, 3:] = False  # seen in too few views
    rho = evidence.rank_correlation(a, b, valid)
    assert rho[:3].tolist() == pytest.approx([1.0, 1 - 6 * 30 / 210, 1 - 6 * 40 / 210])  # 1 - 6 sum d^2 / (n (n^2 - 1))
    assert bool(np.isnan(rho[3:]).all())  # no spread; too few views
    # ties share their mean rank
    tied = evidence.rank_correlation(np.array([[1.0, 1.0, 2.0, 3.0]]), np.array([[1.0, 2.0, 3.0, 4.0]]),
                                     np.ones((1, 4), bool))
    assert float(tied[0]) == pytest.approx(np.corrcoef([1.5, 1.5, 3, 4], [1, 2, 3, 4])[0, 1])


def test_a_bright_view_is_a_highlight_only_where_the_brightness_follows_the_light_it_mirrors():
    """Two hits alike in the images (two bright views in the surface's colour): the one whose
    bright views look, about the normal, towards the bright block keeps its evidence; the one
    whose bright views look at the dark light (its views in another order) is shading or texture."""
    sun = _unit([1.0, 0.0, 1.0])
    env = _block_light(sun)
    red, bright = [0.4, 0.1, 0.1], [1.6, 0.4, 0.4]
    samples = _samples([[red] * 5 + [bright] * 2, [red] * 5 + [bright] * 2])
    positions = torch.zeros(2, 3)
    normals = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    # cameras 0-4 low and around (their mirror directions point away from the block), 5 and 6
    # opposite the block at its elevation (their mirror direction is the block's)
    origins = np.array([[3 * np.cos(a), 3 * np.sin(a), 1.0] for a in np.linspace(0, 2, 5)]
                       + [3 * _unit([-1.0, 0.01, 1.0]), 3 * _unit([-1.0, -0.01, 1.0])])
    samples.view[1] = torch.tensor([2, 3, 4, 5, 6, 0, 1])  # the second hit's bright views: cameras 0 and 1
    kept = evidence.at_mirror(samples, positions, normals, origins, env, np.eye(3))
    assert kept.tolist() == [True, False]


def test_mitsuba_renders_of_a_gold_s_highlights_sit_about_the_mirror_direction_of_its_light(spheres):
    """Under its own light (the capture's), most of the gold sphere's hits with a highlight see the
    sun's lobe about their bright view's mirror direction, and the prior stays off where it was."""
    capture, scene, pos, nrm, views = _views(spheres["gold"], n=evidence.HITS)
    tint = evidence.highlight_tint(views)
    shown = ~torch.isnan(tint)
    origins = np.array([cam.origin for cam in capture.cameras])
    kept = evidence.at_mirror(views, pos, nrm, origins, torch.as_tensor(capture.envmap),
                              evidence.BLENDER_ENV_TO_WORLD[:3, :3] @ np.linalg.inv(capture.envmap_to_world[:3, :3]))
    assert float(kept[shown].float().mean()) > 0.5
    tint = torch.where(kept, tint, torch.full((), float("nan")))
    weight = evidence.WeightGrid.of_tints(pos, tint, torch.tensor(np.array(capture.mesh.bounds), dtype=torch.float32))(pos)
    assert float((weight < 1).float().mean()) > 0.15 and float(weight[weight < 1].median()) == 0.0
    # a fit under the capture's own light reads it before the first step, once
    pool, _ = trace_training_pixels(scene, capture, 0.5)
    reading = evidence.PriorReading(scene, capture, pool, load_config(None, []), torch.as_tensor(capture.envmap))
    assert not reading.pending and reading.grid is not None and reading.decision["choice"] == "weighed"
    assert reading.decision["read_at_step"] is None and reading.decision["hits_at_mirror"] > 50


def test_a_learned_light_is_read_once_at_its_share_of_the_schedule_and_kept_on_resume(learned_light_gold, tmp_path,
                                                                                       monkeypatch):
    monkeypatch.setattr(evidence, "DIELECTRIC", -2.0)  # every highlight counts as a metal's
    monkeypatch.setattr(evidence, "METAL", -1.0)
    monkeypatch.setattr(evidence, "MIRROR", -2.0)  # and every one follows the light it mirrors
    trainer = _trainer(learned_light_gold, tmp_path)
    assert trainer.prior.pending and "read_at_step" not in trainer.decisions_so_far()["prior"]
    reads = []
    real = trainer.prior.read
    monkeypatch.setattr(trainer.prior, "read", lambda env, step: (reads.append(step), real(env, step)))
    trainer.run.create()
    trainer.train()
    iterations = trainer.cfg.train.iterations
    assert reads == [math.ceil(evidence.READ_AT * iterations)]
    decision = trainer.decisions_so_far()["prior"]
    assert decision["read_at_step"] == reads[0] and decision["hits_at_mirror"] == decision["hits_with_highlight"] > 0
    assert decision["hits_not_at_mirror"] == 0
    trainer.checkpoint(1.0)
    monkeypatch.setattr(evidence, "MIRROR", 1e9)  # a reading now would keep nothing
    again = _trainer(learned_light_gold, tmp_path)
    again.resume()
    assert not again.prior.pending and again.decisions_so_far()["prior"] == decision
    assert torch.equal(again.model.prior_grid.values, trainer.model.prior_grid.values)
