"""Fuzz of the config and preset loader (Hypothesis): `--config` YAML files built from the real
sections and keys with any value (huge, negative, NaN, of the wrong type), shared values written as
nested aliases, then damaged (a line twice, a merge key, truncated, changed bytes), and `--set`
values of any kind. A config either loads with every value inside its range, or is refused with an
InputError naming the file (or the `--set` option), never another exception; nothing is written."""

import dataclasses
import math

import pytest
import yaml
from hypothesis import given
from hypothesis import strategies as st

from fuzzing import files_under, fuzz, python_text
from vq_mitsuba import cli
from vq_mitsuba.config import Config, check, load_config, presets
from vq_mitsuba.errors import InputError

FUZZ = fuzz(200)


def _keys(cfg=Config(), prefix="") -> list[str]:
    """Every dotted key of the config ("train.seed", ...)."""
    out = []
    for f in dataclasses.fields(cfg):
        value = getattr(cfg, f.name)
        out += _keys(value, f"{prefix}{f.name}.") if dataclasses.is_dataclass(value) else [prefix + f.name]
    return out


KEYS = _keys()
SECTIONS = sorted({k.split(".")[0] for k in KEYS if "." in k})
SPECIAL = [0, -1, 1, 2 ** 31, 2 ** 63, 10 ** 30, -(10 ** 30), 1e308, -1e-308, float("nan"), float("inf"), True, None,
           "", "x", "on", "auto", "1,2,3", "0.5,0.5,0.5", [], {}, [1, 2], {"a": 1}]
values = st.sampled_from(SPECIAL) | st.integers() | st.floats() | st.text(max_size=6)
# What YAML reads in a scalar's place: its own spellings of numbers, tags, anchors and broken syntax.
yaml_tokens = st.sampled_from([".nan", ".inf", "-.inf", "1e400", "0x7fffffffffffffffffffffff", "0o777", "1_000",
                               "2001-12-14", "~", "yes", "off", "!!python/object/apply:os.system ['true']",
                               "!!binary aGk=", "!!float x", "&a", "*a", "*nothere", "[", "{", "'", '"', "? x", "|",
                               "- 1", "a: b: c", "\t", "%YAML 1.1", "---", "...", "<<: *a", "1" * 5000,
                               "0x" + "f" * 4000, "2001-13-45", "2001-02-30 25:61:61", "!!bool x", "!!timestamp x",
                               "!!set [1]", "!!map [1]", "!!int", "!!binary aGk=", "!!set {a, b}"]) | st.text(max_size=8)


@st.composite
def configs(draw):
    """A config mapping: known and unknown keys under real and made-up sections, some values one
    shared object (safe_dump writes it once with an anchor, then aliases), nested `depth` deep."""
    data: dict = {}
    for key in draw(st.lists(st.sampled_from(KEYS) | st.text(max_size=5), max_size=6)):
        section, _, name = key.rpartition(".")
        place = data.setdefault(section, {}) if section else data
        if isinstance(place, dict):
            place[name] = draw(values)
    depth, width = draw(st.integers(0, 9)), draw(st.integers(1, 10))
    if depth and data:  # a value made of `width` copies of a value made of `width` copies ...
        shared = draw(values)
        for _ in range(depth):
            shared = [shared] * width
        section = draw(st.sampled_from(sorted(data)))
        if isinstance(data[section], dict) and data[section]:
            data[section][draw(st.sampled_from(sorted(data[section])))] = shared
    if draw(st.booleans()):
        data["version"] = draw(st.sampled_from([1, 2, 3, 0, -1, "2", 2.5, None]))
    return data


text_edits = st.lists(st.one_of(
    st.tuples(st.just("line twice"), st.integers(0, 50)),
    st.tuples(st.just("token"), st.integers(0, 50), yaml_tokens),
    st.tuples(st.just("truncate"), st.floats(0, 1)),
    st.tuples(st.just("bytes"), st.floats(0, 1), st.binary(min_size=1, max_size=4)),
), max_size=3)


def _edited(text: str, edits) -> bytes:
    data = text.encode()
    for edit in edits:
        lines = data.split(b"\n")
        if edit[0] == "line twice":
            i = edit[1] % len(lines)
            lines.insert(i, lines[i])
            data = b"\n".join(lines)
        elif edit[0] == "token":  # a line's value (or the whole line) replaced
            i = edit[1] % len(lines)
            head, colon, _ = lines[i].partition(b":")
            lines[i] = head + colon + b" " + edit[2].encode() if colon else edit[2].encode()
            data = b"\n".join(lines)
        elif edit[0] == "truncate":
            data = data[:int(edit[1] * len(data))]
        else:
            at = int(edit[1] * len(data))
            data = data[:at] + edit[2] + data[at + len(edit[2]):]
    return data


def _loaded_or_refused(named: str, **kwargs):
    """load_config(**kwargs): a config whose every value is in range, or None when refused with an
    InputError that names `named` (the file, or --set) in the tool's own words."""
    try:
        cfg = load_config(**kwargs)
    except InputError as exc:  # one line of a readable length, whatever the value
        assert named in str(exc) and not python_text(exc.message) and len(exc.message) < 1000, exc
        return None
    check(cfg)  # every value inside its key's range
    for key in KEYS:
        section, _, name = key.rpartition(".")
        value = getattr(getattr(cfg, section) if section else cfg, name)
        assert not isinstance(value, float) or math.isfinite(value), (key, value)
        assert isinstance(value, (bool, int, float, str)), (key, value)
    return cfg


@FUZZ
@given(data=configs(), edits=text_edits)
def test_any_config_file_loads_in_range_or_is_refused_by_name(tmp_path_factory, data, edits):
    folder = tmp_path_factory.mktemp("config")
    path = folder / "config.yaml"
    path.write_bytes(_edited(yaml.safe_dump(data, sort_keys=False), edits))
    _loaded_or_refused(str(path), path=path)
    assert files_under(folder) == {"config.yaml"}


overrides = st.lists(st.tuples(st.sampled_from(KEYS) | st.sampled_from(SECTIONS) | st.text(max_size=6),
                               st.sampled_from(["=", "", "=="]),
                               yaml_tokens | values.map(lambda v: yaml.safe_dump(v, default_flow_style=True).strip()
                                                        .removesuffix("\n...").strip())
                               | st.sampled_from(["&a [*a]", "[" * 2000 + "]" * 2000, "&a [1, 1] ",
                                                  "{a: &a [*a, *a]}"])),
                     min_size=1, max_size=4)


@FUZZ
@given(items=overrides, preset=st.none() | st.sampled_from(presets()))
def test_any_set_value_loads_in_range_or_is_refused_naming_the_option(items, preset):
    _loaded_or_refused("--set", overrides=[f"{k}{eq}{v}" for k, eq, v in items], preset=preset)


@FUZZ
@given(name=st.text(max_size=12) | st.sampled_from(["../presets/demo", "demo.yaml", "DEMO", " demo", ""]))
def test_an_unknown_preset_is_refused_naming_it(name):
    try:
        cfg = load_config(preset=name)
    except InputError as exc:
        assert f"'{name}'" in exc.message and not python_text(exc.message), exc
        return
    assert name in presets()
    check(cfg)


def test_a_hostile_config_on_the_command_line_exits_2_naming_the_file_and_writes_nothing(tmp_path, capsys,
                                                                                        monkeypatch):
    """One command-line check of the loader: nested aliases under a known key, a merge key and a key
    given twice, each in a config file given to `fit`: exit 2, one error line naming the file, no
    traceback, no run folder, nothing written in the working folder."""
    monkeypatch.chdir(tmp_path)
    laughs = "a: &a [1, 1, 1, 1, 1, 1, 1, 1, 1, 1]\n" + "".join(
        f"{c}: &{c} [{', '.join(['*' + p] * 10)}]\n" for p, c in zip("abcdefgh", "bcdefghi")) + "train:\n  seed: *i\n"
    for text in (laughs, "base: &b {lr: 0.1}\ntrain:\n  <<: *b\n", "train:\n  seed: 1\n  seed: 2\n"):
        (tmp_path / "hostile.yaml").write_text(text)
        assert cli.main(["fit", str(tmp_path), "--config", "hostile.yaml", "-o", "run", "--quiet"]) == 2
        err = capsys.readouterr().err
        assert err.startswith("error: hostile.yaml: ") and err.count("\n") == 1 and "Traceback" not in err, err
        assert files_under(tmp_path) == {"hostile.yaml"}


@pytest.mark.parametrize("item, words", [
    ("train.seed=" + "1" * 5000, "--set train.seed: line 1: '" + "1" * 60 + "... (5000 characters)' cannot be read "
                                 "as a whole number (more than 4300 digits)"),
    ("train.seed=2001-13-45", "--set train.seed: line 1: '2001-13-45' cannot be read as a date (month must be in "
                              "1..12)"),
    ("train.seed=!!float x", "--set train.seed: line 1: 'x' cannot be read as a number"),
    ("train.seed=!!bool x", "--set train.seed: line 1: 'x' cannot be read as true or false"),
    ("train.seed=!!timestamp x", "--set train.seed: line 1: 'x' cannot be read as a date"),
    ("train.snapshot_s=[30, 60]", "--set: 'train.snapshot_s' expects text, got a list: [30, 60]"),
    ("train.snapshot_s=!!binary aGk=", "--set: 'train.snapshot_s' expects text, got binary data: b'hi'"),
    ("train.seed=[" + "1, " * 2000 + "1]", "--set: 'train.seed' expects int, got a list: [1, 1, 1,"),
])
def test_values_found_by_the_config_fuzz_are_refused_in_a_sentence(tmp_path, item, words):
    """Found by the fuzz: a YAML integer of more than 4300 digits, a date that is none (month 13) or a
    value its tag cannot be (`!!float x`, `!!bool x`, `!!timestamp x`) ended in Python's ValueError,
    KeyError or AttributeError; a list or binary data for a text key passed as its text; a refused
    value of thousands of items was quoted whole. Each is one sentence, in a file as after --set."""
    with pytest.raises(InputError) as refused:
        load_config(overrides=[item])
    assert str(refused.value).startswith(words) and len(str(refused.value)) < 200, refused.value
    key, value = item.split("=", 1)
    section, name = key.split(".")
    (tmp_path / "c.yaml").write_text(f"{section}:\n  {name}: {value}\n")
    with pytest.raises(InputError) as refused:
        load_config(tmp_path / "c.yaml")
    assert refused.value.path == tmp_path / "c.yaml" and len(refused.value.message) < 200, refused.value


def test_a_preset_is_a_name_never_a_path():
    """Found by the fuzz: `--preset ../presets/demo` read the file the path led to."""
    with pytest.raises(InputError, match=r"unknown preset '\.\./presets/demo' \(presets: "):
        load_config(preset="../presets/demo")
