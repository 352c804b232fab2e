"""The residual of novel views (VQ-NeRF Sec. 4): fitted after the materials, saved in the run,
added by `render` under the capture's own light only."""

import json
import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from vq_mitsuba.models.residual import HashEncoding, ResidualField, add_residual, sh_basis


def test_an_untrained_field_adds_nothing_and_the_sum_is_never_negative():
    field = ResidualField([-1, -1, -1], [1, 1, 1], scale=0.5)
    x = torch.randn(64, 3)
    n = torch.nn.functional.normalize(torch.randn(64, 3), dim=-1)
    assert torch.equal(field(x, n, n), torch.zeros(64, 3))
    assert (add_residual(torch.full((4, 3), 0.1), torch.full((4, 3), -0.3)) == 0).all()


def test_sh_basis_is_orthonormal_over_the_sphere():
    d = torch.nn.functional.normalize(torch.randn(400000, 3, dtype=torch.float64), dim=-1)
    y = sh_basis(d, 4)
    gram = 4 * np.pi * (y.T @ y) / len(d)  # Monte Carlo integral of Y_i Y_j over the sphere
    assert torch.allclose(gram, torch.eye(25, dtype=torch.float64), atol=0.02)
    # each degree's band is rotation invariant: its squared norm is (2l + 1) / (4 pi) for any direction
    for degree in range(5):
        band = y[:1000, degree * degree:(degree + 1) ** 2]
        assert torch.allclose(band.square().sum(-1), torch.full((1000,), (2 * degree + 1) / (4 * np.pi),
                                                               dtype=torch.float64), atol=1e-9)


def test_hash_encoding_interpolates_its_corners_trilinearly():
    """On a level indexed densely, features that are a linear function of the corners' grid
    coordinates come back as that function of the point, exactly, across cell boundaries;
    levels that hash keep every index inside their own part of the table."""
    enc = HashEncoding(levels=3, features=2, log2_table=12, coarsest=4, finest=32)
    assert enc.res.tolist() == [4, 11, 32] and enc.dense.tolist() == [True, True, False]
    level, res = 1, int(enc.res[1])
    g = torch.arange(res + 1, dtype=torch.float32)
    gx, gy, gz = torch.meshgrid(g, g, g, indexing="ij")
    a, b = 0.3 * gx - 0.7 * gy + 0.1 * gz + 2.0, 1.1 * gz - 0.2 * gx
    with torch.no_grad():
        start = int(enc.offsets[level])
        enc.table[start:start + (res + 1) ** 3] = torch.stack([a, b], -1).reshape(-1, 2)
    x = torch.rand(5000, 3)
    x[:10] = torch.tensor([0.0, 1.0, 0.5])  # the box's faces and a cell boundary
    out = enc(x)[:, 2 * level:2 * level + 2]
    p = x * res
    want = torch.stack([0.3 * p[:, 0] - 0.7 * p[:, 1] + 0.1 * p[:, 2] + 2.0, 1.1 * p[:, 2] - 0.2 * p[:, 0]], -1)
    assert torch.allclose(out, want, atol=1e-4)
    # the gradient reaches exactly the 8 corners of each point's cell on each level, weights summing to 1
    enc.table.grad = None
    enc(torch.tensor([[0.37, 0.52, 0.91]])).sum().backward()
    grad = enc.table.grad[:, 0]
    for lv in range(3):
        part = grad[int(enc.offsets[lv]):int(enc.offsets[lv]) + int(enc.sizes[lv])]
        assert int((part != 0).sum()) <= 8 and torch.isclose(part.sum(), torch.tensor(1.0))
    assert float(grad.sum()) == pytest.approx(3.0)


@pytest.fixture(scope="module")
def view_dependent_run(tmp_path_factory):
    """A sphere under its known envmap whose images carry a term no material explains: each view
    is brightened by an amount that depends on the camera's direction alone. Fitted briefly."""
    from tiny_scene import write_sphere_capture
    from vq_mitsuba.config import load_config
    from vq_mitsuba.data.captures import load_capture
    from vq_mitsuba.data.imageio import read_exr, write_exr
    from vq_mitsuba.engine.pipeline import fit

    out = tmp_path_factory.mktemp("residual")
    xml = write_sphere_capture(out, size=24, n_views=24, spp=32)
    for cam in load_capture(xml).cameras:
        direction = cam.to_world[:3, 3] / np.linalg.norm(cam.to_world[:3, 3])
        path = out / "images" / f"{cam.name}.exr"
        rgba = read_exr(path)
        term = 0.25 * (1.0 + direction[0]) * np.array([1.0, 0.6, 0.2])  # view-dependent, coloured
        rgba[..., :3] += term * rgba[..., 3:4]  # premultiplied
        write_exr(path, rgba)
    run = out / "run"
    fit(xml, run, load_config(None, ["train.iterations=80", "train.batch_rays=512", "train.bounce_after=1000",
                                     "vq.enabled=false", "residual.iterations=400"]))
    return xml, run


def test_the_residual_explains_what_the_materials_cannot(view_dependent_run):
    from vq_mitsuba.run.run_dir import RunDir

    _, run = view_dependent_run
    info = json.loads((run / RunDir.FIT).read_text())["residual"]
    # at most residual.iterations, and at most MAX_EPOCHS passes over a pool this small
    from vq_mitsuba.engine.residual_fit import BATCH, MAX_EPOCHS, MIN_STEPS

    fitted = info["hits"] - info["check_hits"]
    assert info["planned_iterations"] == min(400, max(MIN_STEPS, -(-MAX_EPOCHS * fitted // min(BATCH, fitted))))
    # it may stop early once the kept-aside hits stop improving; the field kept is the best scored
    assert 0 < info["kept_step"] <= info["iterations"] <= info["planned_iterations"]
    assert info["learned"] and info["rendered_hits"] == info["hits"]
    assert info["check_hits"] > 100
    # measured on training hits the field was not fitted on
    assert info["psnr_check_hits_after"] > info["psnr_check_hits_before"] + 3.0
    assert RunDir(run).load().residual is not None


def test_render_adds_it_under_the_own_light_only(view_dependent_run):
    from vq_mitsuba.data.captures import load_capture
    from vq_mitsuba.models.material_edits import Change, Edit, Selection
    from vq_mitsuba.render.views import Renderer
    from vq_mitsuba.run.run_dir import RunDir

    xml, run = view_dependent_run
    fitted = RunDir(run).load()
    cam = load_capture(xml).cameras[0]
    own = Renderer(fitted).render(cam, spp=8, aa=1, seed=3)
    fg = own["alpha"] > 0.5
    assert np.abs(own["rgb"] - own["rgb_physical"])[fg].mean() > 0.02  # the residual is there
    # The same light given as an envmap (as `render --envmap`): physically based, the same image
    relit = Renderer(fitted, envmap=fitted.envmap).render(cam, spp=8, aa=1, seed=3)
    assert "rgb_physical" not in relit
    np.testing.assert_allclose(relit["rgb"], own["rgb_physical"], atol=1e-5)
    rotated = Renderer(fitted, env_rotate_deg=90.0).render(cam, spp=8, aa=1, seed=3)
    assert "rgb_physical" not in rotated
    # An edit that changes nothing still turns the residual off where it selects: edited points
    # are physically based, the others keep it
    fitted.edits = [Edit(Selection(), [Change("scale", "roughness", 1.0)], "no-op")]
    edited = Renderer(fitted).render(cam, spp=8, aa=1, seed=3)
    np.testing.assert_allclose(edited["rgb"], own["rgb_physical"], atol=1e-5)
    half = Selection(boxes=(((-9.0, -9.0, -9.0), (9.0, 9.0, 0.0)),))  # the half z <= 0
    fitted.edits = [Edit(half, [Change("scale", "roughness", 1.0)], "no-op, half")]
    edited = Renderer(fitted).render(cam, spp=8, aa=1, seed=3)
    np.testing.assert_allclose(edited["rgb_physical"], own["rgb_physical"], atol=1e-5)
    kept = np.isclose(edited["rgb"], own["rgb"], atol=1e-5).all(-1) & fg
    dropped = np.isclose(edited["rgb"], own["rgb_physical"], atol=1e-5).all(-1) & fg
    assert kept.sum() > 0.2 * fg.sum() and dropped.sum() > 0.2 * fg.sum()


def test_a_residual_of_another_step_is_not_loaded(view_dependent_run, tmp_path):
    """A run resumed after its residual was fitted keeps the old file until its own end: the file
    names the step it belongs to, and a run loaded at another step has no residual."""
    import shutil

    from vq_mitsuba.run.run_dir import RunDir

    _, run = view_dependent_run
    copy = tmp_path / "copy"
    shutil.copytree(run, copy)
    r = RunDir(copy)
    state = torch.load(copy / RunDir.RESIDUAL, weights_only=False)
    r.save_residual(state["field"], state["step"] + 1)
    assert r.load().residual is None
    (copy / RunDir.RESIDUAL).unlink()
    assert RunDir(copy).load().residual is None


def _copy_with_earlier_residual(run, tmp_path):
    """A copy of the fitted `run` whose residual.pt holds the earlier field (no hash encoding), and
    the original residual state."""
    import shutil

    from vq_mitsuba.run.run_dir import RunDir

    copy = tmp_path / "copy"
    shutil.copytree(run, copy)
    state = torch.load(copy / RunDir.RESIDUAL, weights_only=False)
    earlier = {k: v for k, v in state["field"].items() if not k.startswith("encoding.") and k != "finest"}
    RunDir(copy).save_residual(earlier, state["step"])
    return copy, state


def test_a_residual_of_the_earlier_field_is_left_out_with_a_warning(view_dependent_run, tmp_path):
    """A run fitted before the residual was a surface light field keeps loading: its residual.pt
    (positional encoding, no hash table) is left out, and the user is told how to refit it."""
    from vq_mitsuba.errors import Notice
    from vq_mitsuba.run.run_dir import RunDir

    copy, _ = _copy_with_earlier_residual(view_dependent_run[1], tmp_path)
    with pytest.warns(Notice, match="earlier version of the field"):
        assert RunDir(copy).load().residual is None


def test_resuming_a_fitted_run_fits_a_missing_or_earlier_residual_again(view_dependent_run, tmp_path, capsys):
    """`fit --resume` on a finished run whose residual.pt is of the earlier field (or missing)
    fits the residual again on the frozen materials; with a current one it leaves the run alone."""
    from vq_mitsuba.config import load_config
    from vq_mitsuba.engine.pipeline import fit
    from vq_mitsuba.errors import Notice
    from vq_mitsuba.run.run_dir import RunDir

    xml, run = view_dependent_run
    copy, state = _copy_with_earlier_residual(run, tmp_path)
    (copy / RunDir.FIT).write_text(json.dumps({**json.loads((copy / RunDir.FIT).read_text()), "residual": None}))
    cfg = load_config(copy / "config.yaml", [])
    with pytest.warns(Notice, match="earlier version of the field"):
        fit(xml, copy, cfg, resume=True)
    assert "fitting it again" in capsys.readouterr().out
    refitted = torch.load(copy / RunDir.RESIDUAL, weights_only=False)
    assert refitted["step"] == state["step"] and "finest" in refitted["field"]
    info = json.loads((copy / RunDir.FIT).read_text())["residual"]
    assert info["psnr_check_hits_after"] > info["psnr_check_hits_before"] + 3.0
    assert RunDir(copy).load().residual is not None
    before = (copy / RunDir.RESIDUAL).stat().st_mtime_ns
    fit(xml, copy, cfg, resume=True)
    assert "nothing to do" in capsys.readouterr().out
    assert (copy / RunDir.RESIDUAL).stat().st_mtime_ns == before


class _Pool(SimpleNamespace):
    """The parts of a `PixelPool` the residual's fit reads."""

    def __len__(self):
        return len(self.rgb)

    def views_of(self, idx):
        return self.view[idx]


def _random_pool(n: int, gen: torch.Generator):
    """(a pool of `n` random hits seen from 20 views, a function drawing `n` random unit vectors)."""
    unit = lambda: torch.nn.functional.normalize(torch.randn(n, 3, generator=gen), dim=-1)  # noqa: E731
    normal = unit()
    return _Pool(position=torch.rand(n, 3, generator=gen), normal=normal,
                 wi=torch.nn.functional.normalize(normal + 0.5 * unit(), dim=-1),
                 rgb=0.05 + 0.9 * torch.rand(n, 3, generator=gen),
                 view=torch.randint(0, 20, (n,), generator=gen)), unit


def test_a_residual_with_nothing_to_learn_stops_within_a_few_early_scores(monkeypatch):
    """Targets the physically based radiance already gives up to pixel noise (a scene rendered by
    the model itself): no field beats the zero one by MIN_GAIN_DB, and the fit stops after PATIENCE
    scores FIRST_GAP steps apart, eagerly (the compiler is never waited for), long before its
    planned steps."""
    from vq_mitsuba.config import load_config
    from vq_mitsuba.engine import residual_fit

    gen = torch.Generator().manual_seed(3)
    n = 20000
    pool, unit = _random_pool(n, gen)
    rendered = []

    def physical(scene, model, pool, idx, env, cfg, generator):
        rendered.append(len(idx))
        return pool.rgb[idx] * (1.0 + 0.02 * torch.randn(len(idx), 3, generator=gen))

    monkeypatch.setattr(residual_fit, "physical_radiance", physical)
    monkeypatch.setattr(residual_fit, "FIRST_MIN_HITS", 1000)

    field, info = residual_fit.fit_residual(None, None, pool, torch.ones(4, 8, 3),
                                            ([0.0, 0.0, 0.0], [1.0, 1.0, 1.0]), load_config(None))
    assert not info["learned"] and info["step"] == "eager"
    assert info["iterations"] == residual_fit.PATIENCE * residual_fit.FIRST_GAP < info["planned_iterations"]
    # a gain under MIN_GAIN_DB is not trusted: the untrained field is kept
    assert info["kept_step"] == 0 and info["psnr_check_hits_after"] == info["psnr_check_hits_before"]
    x = torch.rand(100, 3)
    assert torch.equal(field(x, unit()[:100], unit()[:100]), torch.zeros(100, 3))
    # only the kept-aside hits and FIRST_SHARE of the others were rendered
    fitted = n - info["check_hits"]
    assert rendered == [info["rendered_hits"]] == [info["check_hits"] + math.ceil(residual_fit.FIRST_SHARE * fitted)]


def test_the_residual_is_scored_on_whole_views_it_is_not_fitted_on():
    """The kept-aside hits are hits of CHECK_SHARE of the views (at most CHECK_MAX_HITS), none of
    whose hits is fitted; with fewer than CHECK_MIN_VIEWS views, CHECK_SHARE of the hits."""
    from vq_mitsuba.engine.residual_fit import CHECK_MAX_HITS, CHECK_MIN_VIEWS, CHECK_SHARE, split_check_hits

    gen = torch.Generator().manual_seed(0)
    view = torch.randint(0, 30, (6000,), generator=gen)
    fit_ids, check_ids = split_check_hits(view, gen)
    held = torch.unique(view[check_ids])
    assert len(held) == round(CHECK_SHARE * 30) and not torch.isin(view[fit_ids], held).any()
    assert len(fit_ids) + len(check_ids) == 6000 and len(torch.unique(torch.cat([fit_ids, check_ids]))) == 6000
    assert torch.equal(torch.sort(check_ids).values, torch.nonzero(torch.isin(view, held)).squeeze(1))
    many = torch.randint(0, 30, (1 << 20,), generator=gen)
    fit_ids, check_ids = split_check_hits(many, gen)
    assert len(check_ids) == CHECK_MAX_HITS and len(torch.unique(many[check_ids])) == round(CHECK_SHARE * 30)
    assert not torch.isin(many[fit_ids], many[check_ids]).any()
    few = torch.randint(0, CHECK_MIN_VIEWS - 1, (1000,), generator=gen)
    fit_ids, check_ids = split_check_hits(few, gen)
    assert len(check_ids) == int(CHECK_SHARE * 1000) and len(fit_ids) == 1000 - len(check_ids)
    one = torch.zeros(1, dtype=torch.long)
    fit_ids, check_ids = split_check_hits(one, gen)  # a single hit: fitted, none to score
    assert fit_ids.tolist() == [0] and len(check_ids) == 0


def test_a_kept_field_goes_on_over_the_kept_aside_views(monkeypatch):
    """Once a field is kept for what it learned, it trains FINISH_SHARE of the planned steps more over
    every hit: the kept-aside views' hits past those scored are rendered too, and the field returned
    is not the one scored."""
    from vq_mitsuba.config import load_config
    from vq_mitsuba.engine import residual_fit

    gen = torch.Generator().manual_seed(5)
    n = 20000
    pool, _ = _random_pool(n, gen)
    rendered, kept = [], {}

    def physical(scene, model, pool, idx, env, cfg, generator):  # the targets miss a smooth term
        rendered.append(idx.clone())
        return (pool.rgb[idx] - 0.3 * pool.position[idx, :1] * pool.wi[idx, 2:].abs()).clamp_min(0.0)

    monkeypatch.setattr(residual_fit, "physical_radiance", physical)
    monkeypatch.setattr(residual_fit, "FIRST_MIN_HITS", 1000)
    monkeypatch.setattr(residual_fit, "CHECK_MAX_HITS", 500)  # fewer than the kept-aside views' hits
    load = residual_fit.ResidualField.load_state_dict

    def remember(self, state, *args, **kwargs):
        kept["state"] = {k: v.clone() for k, v in state.items()}
        return load(self, state, *args, **kwargs)

    monkeypatch.setattr(residual_fit.ResidualField, "load_state_dict", remember)
    cfg = load_config(None, ["residual.iterations=300"])
    field, info = residual_fit.fit_residual(None, None, pool, torch.ones(4, 8, 3),
                                            ([0.0, 0.0, 0.0], [1.0, 1.0, 1.0]), cfg)
    assert info["learned"] and info["check_hits"] == 500
    assert info["finish_steps"] == round(residual_fit.FINISH_SHARE * info["planned_iterations"]) > 0
    # every hit's radiance rendered, each once
    every = torch.cat(rendered)
    assert info["rendered_hits"] == n == len(every) == len(torch.unique(every))
    moved = [not torch.equal(v, kept["state"][k]) for k, v in field.state_dict().items()]
    assert any(moved)
