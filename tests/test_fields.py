"""The continuous material field: metallic initialisation and config range checks."""

import pytest
import torch

from vq_mitsuba.config import FieldConfig
from vq_mitsuba.models.fields import ContinuousMaterial


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


def test_configuration_doc_is_generated_from_the_config():
    """docs/configuration.md is `python -m vq_mitsuba.config` (regenerate it after changing a key)."""
    from pathlib import Path

    from vq_mitsuba.config import describe, markdown

    doc = Path(__file__).resolve().parent.parent / "docs" / "configuration.md"
    assert doc.read_text() == markdown()
    keys = [line for line in describe() if line.startswith("  ")]
    assert all(line.split(": ", 1)[1].strip() for line in keys)  # every key says what it does, on one line
    assert all("\n" not in line for line in keys)
