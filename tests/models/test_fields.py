"""The continuous material field: metallic initialisation and config range checks."""

import pytest
import torch

from vq_mitsuba.config import FieldConfig, load_config
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

    doc = Path(__file__).resolve().parents[2] / "docs" / "configuration.md"
    assert doc.read_text() == markdown()
    keys = [line for line in describe() if line.startswith("  ")]
    assert all(line.split(": ", 1)[1].strip() for line in keys)  # every key says what it does, on one line
    assert all("\n" not in line for line in keys)


def test_envmap_resize_interpolates_a_smooth_light_and_wraps_in_longitude():
    """Doubling the rows of a smooth lat-long log-radiance matches the function at the new texel
    centres, also in the columns beside the seam (longitude wraps around)."""
    import math

    from vq_mitsuba.models.fields import EnvironmentMap

    def light(h):
        v = (torch.arange(h) + 0.5) / h * math.pi
        u = (torch.arange(2 * h) + 0.5) / (2 * h) * 2 * math.pi
        return (0.5 * torch.cos(v)[:, None] + torch.sin(u)[None, :] + 0.3 * torch.cos(2 * u)[None, :])[..., None] \
            * torch.tensor([1.0, 0.5, -0.2])

    env = EnvironmentMap(32, 1.0)
    with torch.no_grad():
        env.log_radiance.copy_(light(32))
    env.resize(64)
    got, want = env.log_radiance.detach(), light(64)
    assert got.shape == (64, 128, 3) and isinstance(env.log_radiance, torch.nn.Parameter)
    rows = slice(1, -1)  # the pole rows are clamped, not extrapolated
    assert float((got - want)[rows].abs().max()) < 0.01
    assert float((got - want)[rows][:, [0, 1, -2, -1]].abs().max()) < 0.01  # the seam
    with pytest.raises(ValueError):
        env.resize(96)


def test_envmap_rows_double_over_the_annealing_share():
    from vq_mitsuba.engine.trainer import envmap_height_at

    def ladder(height, anneal=0.5):
        cfg = load_config(None, [f"envmap.height={height}", f"field.pe_anneal={anneal}"])
        return [envmap_height_at(cfg, p) for p in (0.0, 0.17, 0.34, 0.5, 1.0)]

    assert ladder(128) == [32, 64, 128, 128, 128]
    assert ladder(64) == [32, 32, 64, 64, 64]
    assert ladder(32) == [32] * 5 and ladder(16) == [16] * 5 and ladder(48) == [48] * 5
    assert ladder(128, anneal=0) == [128] * 5
