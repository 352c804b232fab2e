"""Config files and command-line values a user gets wrong are refused with a message naming the
file or the option, before any work."""

import subprocess
import sys

import pytest

from vq_mitsuba import cli
from vq_mitsuba.config import load_config
from vq_mitsuba.errors import InputError


def test_a_config_file_that_is_not_utf8_is_named(tmp_path):
    path = tmp_path / "bad.yaml"
    path.write_bytes(b"train:\n  lr: 0.01\n  \xff\xfe: 1\n")
    with pytest.raises(InputError, match="is not UTF-8 text") as err:
        load_config(path)
    assert err.value.path == path


def test_a_folder_given_as_config_is_called_a_folder(tmp_path):
    with pytest.raises(InputError, match="is a folder: --config takes a YAML file"):
        load_config(tmp_path)


def test_a_key_given_twice_in_a_config_file_is_refused_with_its_lines(tmp_path):
    path = tmp_path / "twice.yaml"
    path.write_text("train:\n  lr: 0.01\n  iterations: 10\n  lr: 0.02\n")
    with pytest.raises(InputError, match=r"'lr' is given twice \(lines 2 and 4\)"):
        load_config(path)
    path.write_text("train:\n  lr: 0.01\ntrain:\n  iterations: 10\n")  # a section twice too
    with pytest.raises(InputError, match=r"'train' is given twice \(lines 1 and 3\)"):
        load_config(path)


def test_an_empty_set_value_is_called_empty(tmp_path, capsys):
    with pytest.raises(InputError, match="the value is empty"):
        load_config(None, ["train.lr="])
    assert cli.main(["fit", str(tmp_path), "--set", "train.lr=", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "the value is empty" in err and "None" not in err


def test_an_empty_dataset_path_is_called_empty_not_read_as_the_current_folder(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as info:
        cli.main(["eval", str(tmp_path / "run"), "--gt", "", "--quiet"])
    assert info.value.code == 2
    err = capsys.readouterr().err
    assert "argument --gt: the value is empty" in err and "Traceback" not in err
    assert list(tmp_path.iterdir()) == []


def test_every_texture_size_out_of_range_gets_the_one_message_naming_the_option(tmp_path, capsys):
    for size in ("0", "1", "3", "9000", "-5", "abc"):
        out = tmp_path / "out"
        assert cli.main(["export", str(tmp_path / "run"), "--format", "obj", "--texture-size", size, "-o", str(out),
                         "--quiet"]) == 2, size
        shown = size if size.lstrip("-").isdigit() else repr(size)
        assert capsys.readouterr().err.strip() == (
            f"error: --texture-size must be a whole number of texels in 16..8192, got {shown}"), size
        assert not out.exists()


def test_an_option_given_a_list_that_starts_negative_reaches_its_check(tmp_path, capsys):
    assert cli.main(["fit", str(tmp_path), "--background-color", "-0.5,0,0", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "expected one argument" not in err and "background_color" in err


def test_neus_settings_whose_step_would_not_fit_in_memory_are_refused(tmp_path, capsys):
    from tiny_scene import write_sphere_capture
    from vq_mitsuba.geometry.neus import renderer

    capture = write_sphere_capture(tmp_path / "cap", size=16, n_views=4, spp=8)
    out = tmp_path / "run"
    assert cli.main(["geometry", str(capture), "-o", str(out), "--quiet", "--set", "neus.n_samples=100000"]) == 2
    err = capsys.readouterr().err
    assert "GiB are available: lower neus.n_samples or neus.batch_rays" in err and not out.exists()
    renderer.check_step_memory(load_config(None, ["neus.batch_rays=512"]).neus, 2 ** 30)  # the defaults fit 1 GiB
    with pytest.raises(InputError, match="need about 2.6 GiB"):
        renderer.check_step_memory(load_config(None, ["neus.batch_rays=512", "neus.n_samples=2000"]).neus, 2 ** 30)


def _laughs(depth: int = 9) -> str:
    """A value of a few hundred bytes whose aliases, nested `depth` deep, stand for 9**depth values."""
    value = "[&l0 [lol, lol, lol, lol, lol, lol, lol, lol, lol]"
    for i in range(1, depth + 1):
        value += f", &l{i} [" + ", ".join([f"*l{i - 1}"] * 9) + "]"
    return value + "]"


def test_a_billion_laughs_config_under_a_known_key_is_refused_at_once(tmp_path):
    path = tmp_path / "laughs.yaml"
    path.write_text(f"train:\n  seed: {_laughs()}\n")
    assert path.stat().st_size < 2000
    proc = subprocess.run([sys.executable, "-m", "vq_mitsuba.cli", "fit", str(tmp_path), "--config", str(path),
                           "--quiet"], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2, proc.stderr
    assert f"{path}: holds more than" in proc.stderr and "aliases" in proc.stderr
    assert "Traceback" not in proc.stderr


def test_every_yaml_the_tool_reads_is_bounded(tmp_path):
    from vq_mitsuba.config import MAX_YAML_BYTES
    from vq_mitsuba.run.run_dir import RunDir

    with pytest.raises(InputError, match="--set train.seed: holds more than"):  # a value on the command line
        load_config(None, [f"train.seed={_laughs(6)}"])
    (tmp_path / "config.yaml").write_text(f"version: 2\ntrain:\n  seed: {_laughs()}\n")  # a run's own config
    with pytest.raises(InputError, match="holds more than") as err:
        RunDir(tmp_path).saved_config()
    assert err.value.path == tmp_path / "config.yaml"
    path = tmp_path / "loop.yaml"
    path.write_text("train: &t\n  seed: *t\n")  # an alias inside the value it names has no end
    with pytest.raises(InputError, match="line 1: an alias refers to the value that holds it") as err:
        load_config(path)
    assert err.value.path == path
    path.write_text("train:\n  seed: 1\n" + "#" * MAX_YAML_BYTES)
    with pytest.raises(InputError, match="is larger than 1024 KB") as err:
        load_config(path)
    assert err.value.path == path


def test_yaml_messages_are_plain_sentences_without_pyyaml_trailers(tmp_path):
    path = tmp_path / "bad.yaml"
    cases = {"base: &b\n  lr: 0.01\ntrain:\n  <<: *b\n":  # a merge key, not PyYAML's constructor text
             "line 4: a YAML merge key ('<<') is not supported; write the keys out in full",
             "train:\n  lr: 0.01\n  lr: 0.02\n": "'lr' is given twice (lines 2 and 3)",
             "train:\n  lr: [0.01\n": "invalid YAML: line 3, column 1: expected ',' or ']', but got '<stream end>' "
                                      "(while parsing a flow sequence from line 2)"}
    for text, message in cases.items():
        path.write_text(text)
        with pytest.raises(InputError) as err:
            load_config(path)
        assert err.value.path == path and err.value.message == message
