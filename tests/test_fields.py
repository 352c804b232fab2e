"""The continuous material field's schedules: encoding annealing and the metallic delay."""

import pytest
import torch

from vq_mitsuba.config import FieldConfig
from vq_mitsuba.materials.fields import ContinuousMaterial


@pytest.mark.parametrize("fraction,gate", [(0.0, 0.0), (0.1, 0.0), (0.15, 0.5), (0.2, 1.0), (0.9, 1.0)])
def test_metallic_delay_holds_then_fades_in(fraction, gate):
    torch.manual_seed(0)
    model = ContinuousMaterial(FieldConfig(), -torch.ones(3), torch.ones(3))
    x = torch.rand(32, 3) * 2 - 1
    model.set_progress(fraction, anneal=0.5, metallic_delay=0.0)  # same encoding, no delay
    free = model(x)
    model.set_progress(fraction, anneal=0.5, metallic_delay=0.1)
    out = model(x)
    assert free["metallic"].abs().min() > 0
    torch.testing.assert_close(out["metallic"], gate * free["metallic"])
    # Basecolor and roughness are not touched by the schedule.
    torch.testing.assert_close(out["roughness"], free["roughness"])
    torch.testing.assert_close(out["basecolor"], free["basecolor"])
    if gate > 0:  # the metallic network learns while it fades in
        out["metallic"].sum().backward()
        assert model.decoder.metallic.parameters().__next__().grad.abs().sum() > 0


def test_metallic_gate_is_saved_with_the_model():
    model = ContinuousMaterial(FieldConfig(), -torch.ones(3), torch.ones(3))
    model.set_progress(0.05, anneal=0.5, metallic_delay=0.1)
    other = ContinuousMaterial(FieldConfig(), -torch.ones(3), torch.ones(3))
    other.load_state_dict(model.state_dict())
    assert float(other.metallic_gate) == 0.0


def test_models_saved_before_the_metallic_schedule_still_load():
    old = ContinuousMaterial(FieldConfig(), -torch.ones(3), torch.ones(3)).state_dict()
    del old["metallic_gate"]
    model = ContinuousMaterial(FieldConfig(), -torch.ones(3), torch.ones(3))
    model.metallic_gate.fill_(0.0)
    model.load_state_dict(old)  # strict: the missing gate is filled in, not an error
    assert float(model.metallic_gate) == 1.0


def test_shut_metallic_gate_leaves_the_adam_state_of_the_metallic_network_alone():
    """While metallic is held at 0 its network gets no gradient at all (None, not zeros), so Adam
    neither advances its step count nor decays its moments: when the gate opens, its first steps
    are ordinary first Adam steps (about one learning rate), not bias-corrected leaps."""
    torch.manual_seed(0)
    model = ContinuousMaterial(FieldConfig(), -torch.ones(3), torch.ones(3))
    optim = torch.optim.Adam(model.parameters(), lr=1e-2)
    x = torch.rand(64, 3) * 2 - 1
    model.set_progress(0.05, anneal=0.5, metallic_delay=0.1)
    for _ in range(5):
        optim.zero_grad(set_to_none=True)
        out = model(x)
        (out["basecolor"].sum() + out["roughness"].sum() + out["metallic"].sum()).backward()
        assert all(p.grad is None for p in model.decoder.metallic.parameters())
        optim.step()
    assert all(p not in optim.state for p in model.decoder.metallic.parameters())
    assert all(int(optim.state[p]["step"]) == 5 for p in model.decoder.roughness.parameters())
    model.set_progress(0.15, anneal=0.5, metallic_delay=0.1)
    before = [p.detach().clone() for p in model.decoder.metallic.parameters()]
    optim.zero_grad(set_to_none=True)
    model(x)["metallic"].sum().backward()
    optim.step()
    steps = [float((p.detach() - b).abs().max()) for p, b in zip(model.decoder.metallic.parameters(), before)]
    assert 0 < max(steps) <= 1e-2 * 1.001


@pytest.mark.parametrize("init", [0.02, 0.05, 0.2])
def test_metallic_init_sets_the_initial_metallic_output(init):
    torch.manual_seed(0)
    model = ContinuousMaterial(FieldConfig(metallic_init=init), -torch.ones(3), torch.ones(3))
    with torch.no_grad():
        m = model(torch.rand(4096, 3) * 2 - 1)["metallic"]
    # The bias sets the logit; the random weights spread it a little around that.
    assert abs(float(m.median()) - init) < 0.5 * init
    assert float(m.max()) < min(4 * init, 0.9)


def test_metallic_init_zero_keeps_the_default_initialisation():
    torch.manual_seed(0)
    model = ContinuousMaterial(FieldConfig(metallic_init=0.0), -torch.ones(3), torch.ones(3))
    with torch.no_grad():
        m = model(torch.rand(4096, 3) * 2 - 1)["metallic"]
    assert 0.3 < float(m.median()) < 0.7


def test_metallic_init_outside_the_unit_interval_is_rejected(tmp_path):
    from vq_mitsuba.config import load_config
    from vq_mitsuba.errors import InputError

    with pytest.raises(InputError, match="metallic_init") as err:
        load_config(overrides=["field.metallic_init=1.0"])
    assert str(err.value.path) == "--set"
    bad = tmp_path / "bad.yaml"
    bad.write_text("field:\n  metallic_init: -0.1\n")
    with pytest.raises(InputError, match="metallic_init") as err:
        load_config(bad)
    assert err.value.path == bad
    # a valid file followed by a bad override names the override, not the file
    good = tmp_path / "good.yaml"
    good.write_text("field:\n  metallic_init: 0.1\n")
    with pytest.raises(InputError) as err:
        load_config(good, overrides=["field.metallic_init=2"])
    assert str(err.value.path) == "--set"


def test_decays_barrier_end_joint_scale_and_bounce_start_outside_their_range_are_rejected():
    from vq_mitsuba.config import load_config
    from vq_mitsuba.errors import InputError

    for key in ("loss.lam_decay", "vq.lam_decay", "loss.metallic_barrier_until", "vq.joint_scale"):
        for bad in ("0", "1.5", "-0.1"):
            with pytest.raises(InputError, match=key.replace(".", r"\.")) as err:
                load_config(overrides=[f"{key}={bad}"])
            assert str(err.value.path) == "--set"
    assert load_config(overrides=["loss.lam_decay=0.1"]).loss.lam_decay == 0.1
    assert load_config(overrides=["vq.lam_decay=0.5"]).vq.lam_decay == 0.5
    assert load_config(overrides=["loss.metallic_barrier_until=0.3"]).loss.metallic_barrier_until == 0.3
    for bad in ("-1", "1.5"):
        with pytest.raises(InputError, match=r"train\.bounce_after"):
            load_config(overrides=[f"train.bounce_after={bad}"])
    assert load_config(overrides=["train.bounce_after=300"]).train.bounce_after == 300
