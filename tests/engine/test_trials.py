"""The trial of a glossier explanation where the fitted roughness sits at its floor
(vq_mitsuba/engine/trials.py): when it starts, that its copy of the fit is complete, and that the
held-aside pixels choose which explanation goes on."""

import json

import pytest
import torch

from tiny_scene import write_sphere_capture
from vq_mitsuba.config import load_config
from vq_mitsuba.engine import skips, trials
from vq_mitsuba.engine.pipeline import fit
from vq_mitsuba.engine.schedule import schedule_at
from vq_mitsuba.engine.trainer import Trainer
from vq_mitsuba.run.loop import Progress

QUICK = ["train.batch_rays=64", "residual.iterations=0", "train.iterations=40", "vq.warmup_frac=0.1"]


@pytest.fixture(scope="module")
def learned_light_sphere(tmp_path_factory):
    return write_sphere_capture(tmp_path_factory.mktemp("sphere"), size=16, n_views=4, spp=8, known_envmap=False)


def _trainer(capture_path, tmp_path, extra=()):
    from vq_mitsuba.data.captures import load_capture
    from vq_mitsuba.run.run_dir import RunDir

    return Trainer(load_capture(capture_path, split="train"), RunDir(tmp_path / "run"),
                   load_config(None, QUICK + list(extra)))


def _steps(trainer, n):
    for _ in range(n):
        p = Progress(trainer.step, 0.0, trainer.step / trainer.cfg.train.iterations, 0.0)
        assert trainer.train_step(schedule_at(trainer.cfg, p))[0]
        trainer.pace.advance()


def _params(trainer):
    return [p.detach().clone() for g in trainer.optim.param_groups for p in g["params"]]


def test_the_glossy_value_is_the_roughness_the_first_rung_resolves():
    for rows in (32, 64, 128, 256):
        assert skips.rows_for_roughness(trials.glossy_roughness(rows)) == pytest.approx(rows)
    assert 0.2 < trials.glossy_roughness(32) < 0.3


def test_a_restored_copy_repeats_the_same_steps_bit_for_bit(learned_light_sphere, tmp_path):
    """Everything a step changes is in the copy: networks (both branches), light, Adam's moments,
    the random generator, the step."""
    trainer = _trainer(learned_light_sphere, tmp_path)
    _steps(trainer, 6)  # past the discrete start
    assert trainer.model.discrete_on
    saved = trials.copy_fit(trainer)
    drawn = torch.rand(3)  # the global generator too (the codebook's dead codes are re-seeded from it)
    _steps(trainer, 4)
    after, step = _params(trainer), trainer.step
    trials.restore_fit(trainer, saved)
    assert trainer.step == step - 4 and torch.equal(torch.rand(3), drawn)
    _steps(trainer, 4)
    assert all(torch.equal(a, b) for a, b in zip(after, _params(trainer)))


def test_metals_at_the_floor_are_flagged_and_nothing_else():
    out = {"roughness": torch.tensor([0.02, 0.035, 0.12, 0.035, 0.4, 0.05, 0.03]),
           "metallic": torch.tensor([1.0, 0.0, 1.0, 0.9, 1.0, 0.9, 0.7])}
    # a dielectric at the floor, glossy and rough metals are left alone
    assert trials.flag(out, floor=0.02).tolist() == [True, False, False, True, False, False, True]


def test_the_pull_charges_flagged_roughness_below_the_glossy_value_only():
    r = torch.tensor([0.02, 0.03, 0.5, 0.02], requires_grad=True)
    flags = torch.tensor([True, True, True, False])
    term = trials.pull_term(r, flags, 0.25)
    assert float(term.detach()) == pytest.approx((0.23 ** 2 + 0.22 ** 2) / 3)
    term.backward()
    assert r.grad[0] < 0 and r.grad[1] < 0 and r.grad[2] == 0 and r.grad[3] == 0
    assert float(trials.pull_term(r, torch.zeros(4, dtype=torch.bool), 0.25).detach()) == 0.0


@pytest.mark.parametrize("copy_wins", [True, False])
def test_the_held_aside_pixels_choose_which_explanation_goes_on(learned_light_sphere, tmp_path, monkeypatch,
                                                                  copy_wins):
    """A trial forced on (every hit counts as a metal at the floor, the glossy value above them all): the copy trains with the pull, the fit
    as many steps; the explanation with the lower held-aside loss is the one that goes on, and
    fit.json records both losses."""
    monkeypatch.setattr(trials, "FLOOR_BAND", 2.0)
    monkeypatch.setattr(trials, "METAL", -1.0)
    monkeypatch.setattr(trials, "glossy_roughness", lambda rows: 0.9)  # above the fit's roughness: the pull acts
    losses = iter([1.0, 2.0] if copy_wins else [2.0, 1.0])  # the copy's, then the fit's
    monkeypatch.setattr(Trainer, "held_loss", lambda self: next(losses))
    copies = []
    copy_fit = trials.copy_fit
    monkeypatch.setattr(trials, "copy_fit", lambda t: copies.append(copy_fit(t)) or copies[-1])
    seen = {}
    finish = trials.Trials.finish

    def finish_and_look(self):
        seen["fit"] = _params(self.trainer)
        finish(self)
        seen["after"] = _params(self.trainer)
        seen["copy"] = [p.clone() for p in copies[1]["model"].values()]
        seen["model_after"] = [p.clone() for p in self.trainer.model.field.state_dict().values()]

    monkeypatch.setattr(trials.Trials, "finish", finish_and_look)
    out = tmp_path / "run"
    fit(learned_light_sphere, out, load_config(None, QUICK))
    decision = json.loads((out / "fit.json").read_text())["decisions"]["trials"]
    record = decision["trials"][0]
    assert decision["choice"] == ("swapped" if copy_wins else "kept")
    assert record["held_loss_copy"] == (1.0 if copy_wins else 2.0) and record["hits_flagged"] > 0
    assert record["steps"] == 4 and record["glossy"] == 0.9 and record["share_at_floor"] == 1.0
    assert record["roughness_copy"] > record["roughness_fit"]  # the pull moved the copy
    if copy_wins:  # the copy's networks replaced the fit's
        assert all(torch.equal(a, b) for a, b in zip(seen["copy"], seen["model_after"]))
        assert not all(torch.equal(a, b) for a, b in zip(seen["fit"], seen["after"]))
    else:
        assert all(torch.equal(a, b) for a, b in zip(seen["fit"], seen["after"]))


def test_no_trial_without_a_surface_at_the_floor_or_without_a_learned_light(learned_light_sphere, tmp_path):
    out = tmp_path / "matte"
    fit(learned_light_sphere, out, load_config(None, QUICK))
    decision = json.loads((out / "fit.json").read_text())["decisions"]["trials"]
    assert decision["choice"] == "none" and "within 0.02 of the roughness floor" in decision["reason"]
    known = write_sphere_capture(tmp_path / "known", size=16, n_views=4, spp=8)
    fit(known, tmp_path / "known_run", load_config(None, QUICK))
    decision = json.loads((tmp_path / "known_run" / "fit.json").read_text())["decisions"]["trials"]
    assert decision["choice"] == "none" and "no learned light" in decision["reason"]


def test_a_checkpoint_between_the_copy_and_the_choice_keeps_the_copy(learned_light_sphere, tmp_path, monkeypatch):
    monkeypatch.setattr(trials, "FLOOR_BAND", 2.0)
    monkeypatch.setattr(trials, "METAL", -1.0)
    trainer = _trainer(learned_light_sphere, tmp_path)
    _steps(trainer, 20)  # every stage of the schedule has begun
    trainer.trials.after_step(Progress(trainer.step, 0.0, 0.5, 0.0))
    pending = trainer.trials.pending
    assert pending is not None and pending["until"] == 24 and trainer.step == 20
    trainer.run.create()
    trainer.checkpoint(1.0)
    again = _trainer(learned_light_sphere, tmp_path)
    again.resume()
    assert again.trials.checked and again.step == 20
    assert again.trials.pending["record"] == pending["record"] and again.trials.pending["until"] == 24
    assert all(torch.equal(a, b) for a, b in zip(again.trials.pending["copy"]["model"].values(),
                                                 pending["copy"]["model"].values()))
    assert torch.equal(again.trials.pending["probe"], pending["probe"])


def test_the_model_returns_only_declared_terms_each_weighted_by_its_key(learned_light_sphere, tmp_path):
    """Past the discrete start the model returns both branches' terms by name; each is declared in
    losses.TERMS, and the trainer's loss is each term times its config weight."""
    from vq_mitsuba.models import losses

    trainer = _trainer(learned_light_sphere, tmp_path)
    _steps(trainer, 6)
    s = schedule_at(trainer.cfg, Progress(trainer.step, 0.0, 0.5, 0.0))
    idx, weight = trainer.data.draw(trainer.step, trainer.gen)
    returned = []
    loss_dict = trainer.model.loss_dict
    trainer.model.loss_dict = lambda *a: returned.append(loss_dict(*a)) or returned[-1]
    weighted, _, _ = trainer.loss_terms(idx, s, False, weight)
    raw = returned[0][0]
    assert {"rec_c", "rec_d", "vq", "chr", "met", "lam_c", "lam_d"} <= set(raw) <= set(losses.TERMS)
    assert set(weighted) == set(raw)
    for name, value in raw.items():
        w = losses.weight_of(trainer.cfg, name, s.progress)
        assert float(weighted[name].detach()) == pytest.approx(w * float(value.detach()), rel=1e-5, abs=1e-9), name


def test_the_metallic_agreement_trains_the_discrete_decoder_alone(learned_light_sphere, tmp_path):
    """L_met moves each codeword's metallic towards the continuous field's at its hits through the
    discrete decoder only: no gradient reaches the shared encoder or the continuous decoder."""
    trainer = _trainer(learned_light_sphere, tmp_path)
    _steps(trainer, 6)
    model = trainer.model
    assert model.discrete_on
    s = schedule_at(trainer.cfg, Progress(trainer.step, 0.0, 0.5, 0.0))
    idx, weight = trainer.data.draw(trainer.step, trainer.gen)
    terms, _, _ = model.loss_dict(trainer.data, idx, s, False, trainer.gen, weight)
    trainer.optim.zero_grad(set_to_none=True)
    terms["met"].backward()
    assert float(terms["met"].detach()) > 0
    decoder = [p.grad for p in model.discrete.decoder.parameters()]
    assert any(g is not None and float(g.abs().sum()) > 0 for g in decoder)
    assert all(p.grad is None or float(p.grad.abs().sum()) == 0 for p in model.field.parameters())
