"""The configuration's declarations: every key's help and range in its metadata, the one validator
that reads them (errors name the layer), --help-config and docs/configuration.md from the same
metadata, and the config.yaml format version."""

import dataclasses
from pathlib import Path

import pytest
import yaml

from vq_mitsuba import config as C
from vq_mitsuba.config import Config, check, describe, load_config, markdown, save_config, setting
from vq_mitsuba.errors import InputError


def _fields(cls, prefix=""):
    """(key, dataclasses.Field) of every key under `cls`, sections walked."""
    for f in dataclasses.fields(cls):
        default = f.default_factory() if f.default is dataclasses.MISSING else f.default
        if dataclasses.is_dataclass(default):
            yield from _fields(type(default), f"{prefix}{f.name}.")
        else:
            yield f"{prefix}{f.name}", f


def _texel_config():
    from vq_mitsuba.eval.texel import TexelConfig

    return TexelConfig


# One out-of-range value per range kind (and per check that spans keys), with what the message says.
OUT_OF_RANGE = [
    (">0", "train.batch_rays", "0", "train.batch_rays must be > 0"),
    (">=2", "envmap.height", "1", "envmap.height must be >= 2"),
    ("[2,1024]", "neus.mesh_resolution", "100000", "neus.mesh_resolution must be in [2, 1024]"),
    ("[0,2]", "neus.sdf_layers", "3", r"neus.sdf_layers must be 0, 1 or 2"),
    (">=0", "loss.w_lam", "-1", "loss.w_lam must be >= 0"),
    ("[0,1]", "vq.decay", "1.5", "vq.decay must be in [0, 1]"),
    ("(0,1]", "vq.joint_scale", "0", "vq.joint_scale must be in (0, 1]"),
    (">1", "lamps.distance", "1", "lamps.distance must be > 1"),
    ("-1|[0,1]", "neus.coarse_to_fine", "-0.5", r"neus.coarse_to_fine must be -1 or in [0, 1]"),
    ("[0,1)", "field.metallic_init", "1.0", "field.metallic_init must be in [0, 1)"),
    ("square", "train.pixel_jitter", "3", "train.pixel_jitter must be a square number or 0"),
    ("square>0", "render.aa", "0", "render.aa must be a square number > 0"),
    ("choices", "neus.init", "box", "neus.init must be one of 'hull', 'sphere'"),
    ("cross", "neus.base_res", "1", "neus.base_res must be >= 2"),
    ("cross", "neus.max_res", "8", "neus.max_res 0 or >= neus.base_res"),
    ("cross", "capture.background_color", "'2,0,0'", "capture.background_color must be R,G,B"),
]


@pytest.mark.parametrize("kind, key, bad, message", OUT_OF_RANGE, ids=[f"{k}:{key}" for k, key, *_ in OUT_OF_RANGE])
def test_the_validator_refuses_each_range_kind_and_names_the_layer(kind, key, bad, message, tmp_path):
    with pytest.raises(InputError, match=message.replace("[", r"\[").replace("(", r"\(").replace(")", r"\)")) as err:
        load_config(overrides=[f"{key}={bad}"])
    assert str(err.value.path) == "--set"
    section, name = key.split(".")
    path = tmp_path / "bad.yaml"
    path.write_text(f"{section}:\n  {name}: {bad}\n")
    with pytest.raises(InputError, match=message.split(" must")[0]) as err:
        load_config(path)
    assert err.value.path == path
    # A good file followed by a bad override names the override.
    good = tmp_path / "good.yaml"
    good.write_text("train:\n  iterations: 5\n")
    with pytest.raises(InputError) as err:
        load_config(good, overrides=[f"{key}={bad}"])
    assert str(err.value.path) == "--set"


def test_every_range_kind_is_exercised_and_the_edges_are_inside():
    assert set(C.RANGES) - {"any"} <= {kind for kind, *_ in OUT_OF_RANGE}
    cfg = load_config(overrides=["train.pixel_jitter=0", "render.aa=1", "vq.joint_scale=1", "field.metallic_init=0",
                                 "vq.decay=0", "loss.w_lam=0", "neus.init=sphere", "neus.coarse_to_fine=1", "neus.init_variance=-2",
                                 "capture.background_color=1,0.5,0"])
    assert cfg.train.pixel_jitter == 0 and cfg.neus.init_variance == -2
    # A section alone is checked under its own name.
    with pytest.raises(InputError, match=r"neus\.n_samples must be > 0"):
        check(C.NeuSConfig(n_samples=0))


def test_every_key_has_one_line_of_help_and_a_valid_range():
    keys = list(_fields(Config)) + [(f"texel.{k}", f) for k, f in _fields(_texel_config())]
    assert len(keys) > 100
    for key, f in keys:
        help_, range_ = f.metadata.get("help"), f.metadata.get("range", "missing")
        assert help_ and help_.strip() and "\n" not in help_, key
        default = f.default_factory() if f.default is dataclasses.MISSING else f.default
        assert C._range_error(default, range_) is None, key
    check(Config())  # every default is inside its range
    check(_texel_config()())
    with pytest.raises(ValueError, match="unknown range"):
        setting(1, "a count", ">2")
    with pytest.raises(ValueError, match="not one of"):
        setting("cube", "a shape", ("hull", "sphere"))
    with pytest.raises(ValueError, match="one line"):
        setting(1, "two\nlines")


def test_describe_and_markdown_list_every_key_with_its_range():
    lines, doc = describe(), markdown()
    for key, f in _fields(Config):
        shown = C.range_text(f.default, f.metadata["range"])
        assert any(line.startswith(f"  {key} = ") and f"({shown}): {f.metadata['help']}" in line
                   for line in lines), key
        assert f"| `{key}` | `{f.default!r}` | {shown} | {f.metadata['help']} |" in doc, key
    assert "texel" not in {f.name for f in dataclasses.fields(Config)}
    assert "`texel." not in doc and "## `texel`" not in doc and not any(line.startswith("  texel.") for line in lines)


def test_the_configuration_doc_is_markdown():
    """docs/configuration.md is `python -m vq_mitsuba.config > docs/configuration.md`: regenerate it."""
    doc = Path(__file__).resolve().parents[2] / "docs" / "configuration.md"
    assert doc.read_text() == markdown()


def _v1_config_yaml(cfg: Config) -> str:
    """config.yaml as version 1 wrote it: no version, lr_decay in train and neus, a texel section."""
    data = C.to_dict(cfg)
    data["train"] = {("lr_decay" if k == "lr_end_exponential" else k): v for k, v in data["train"].items()}
    data["neus"] = {("lr_decay" if k == "lr_end_cosine" else k): v for k, v in data["neus"].items()}
    data["texel"] = {"resolution": 256, "lr_decay": 0.1, "seed": 0}
    return yaml.safe_dump(data, sort_keys=False)


def test_a_version_1_config_yaml_loads_under_the_new_names(tmp_path):
    old = load_config(overrides=["train.lr_end_exponential=0.25", "neus.lr_end_cosine=0.5", "field.hidden=32"])
    path = tmp_path / "config.yaml"
    path.write_text(_v1_config_yaml(old))
    assert "version" not in path.read_text() and "lr_decay" in path.read_text()
    cfg = load_config(base=yaml.safe_load(path.read_text()))
    assert cfg == old
    assert cfg.train.lr_end_exponential == 0.25 and cfg.neus.lr_end_cosine == 0.5 and cfg.field.hidden == 32
    # Saved again, it is version 2 (first) and reads back the same.
    save_config(cfg, path)
    assert path.read_text().startswith("version: 2\n")
    assert load_config(base=yaml.safe_load(path.read_text())) == cfg
    # The same file given with --config is read by its version too.
    assert load_config(path) == cfg
    with pytest.raises(InputError, match="newer") as err:
        load_config(base={"version": 3, "train": {"iterations": 5}})
    assert str(err.value.path) == "config.yaml"
    # A hand-written file in the old names is told the new one.
    hand = tmp_path / "mine.yaml"
    hand.write_text("train:\n  lr_decay: 0.5\n")
    with pytest.raises(InputError, match="'train.lr_decay' is now 'train.lr_end_exponential'"):
        load_config(hand)


def test_a_neus_checkpoint_saved_under_version_1_names_still_resumes(tmp_path):
    """A NeuS checkpoint keeps asdict(NeuSConfig) of its time; resuming compares only the keys that
    shape the networks, so the renamed learning-rate key does not matter."""
    from vq_mitsuba.geometry.neus import check_architecture

    saved = {("lr_decay" if k == "lr_end_cosine" else k): v for k, v in dataclasses.asdict(C.NeuSConfig()).items()}
    check_architecture(tmp_path / "neus.pt", saved, load_config(overrides=["neus.lr_end_cosine=0.3"]).neus)


def test_texel_config_lives_with_the_baseline():
    TexelConfig = _texel_config()
    assert TexelConfig().lr_end_exponential == 0.1
    assert not hasattr(C, "TexelConfig")
