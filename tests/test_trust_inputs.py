"""Readers that trust nothing: a dataset folder never holds two datasets, an envmap is checked alike
wherever it is read, a file is known by its bytes (not its name), a folder holding two capture
formats says which it read, and every refusal names the file at fault."""

import json
from pathlib import Path

import numpy as np
import pytest

from vq_mitsuba import cli
from vq_mitsuba.errors import InputError


def _snapshot(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def _refused(argv: list[str], capsys, named) -> str:
    """Run the command: exit 2, one error line naming `named`, no traceback; returns the message."""
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    errors = [line for line in err.splitlines() if line.startswith("error")]
    assert len(errors) == 1 and str(named) in errors[0] and "Traceback" not in err, err
    return errors[0]


# --- make-scene: one folder, one dataset ------------------------------------------------------

SMALL = ["--spp", "2", "--n-train", "3", "--n-test", "1"]


def test_make_scene_refuses_a_dataset_it_cannot_prove_its_own(tmp_path, capsys):
    data = tmp_path / "data"
    assert cli.main(["make-scene", "demo", "--resolution", "16", "--photo-formats", *SMALL, "-o", str(data)]) == 0
    capsys.readouterr()
    (data / "scene.json").write_bytes(b"\x00garbled")
    before = _snapshot(data)
    message = _refused(["make-scene", "demo", "--resolution", "8", *SMALL, "-o", str(data)], capsys, data)
    assert "colmap/" in message and "scene.json cannot be read" in message
    assert _snapshot(data) == before
    (data / "scene.json").write_text(json.dumps({"name": "mine"}))  # readable, but not make-scene's
    assert "is not make-scene's" in _refused(["make-scene", "demo", "-o", str(data)], capsys, data)


def test_make_scene_replaces_its_own_dataset_whole(tmp_path, capsys):
    data = tmp_path / "data"
    assert cli.main(["make-scene", "demo", "--resolution", "16", "--photo-formats", *SMALL, "-o", str(data)]) == 0
    assert {p.name for p in data.iterdir()} >= {"colmap", "nerfstudio", "llff", "neus"}
    assert cli.main(["make-scene", "demo", "--resolution", "8", *SMALL, "-o", str(data)]) == 0
    left = {p.name for p in data.iterdir()}
    assert not left & {"colmap", "colmap_opencv", "nerfstudio", "llff", "neus"}, left
    assert json.loads((data / "scene.json").read_text())["resolution"] == [8, 8]
    capsys.readouterr()
    (data / "notes.txt").write_text("mine")  # a file make-scene did not write: refused, kept
    message = _refused(["make-scene", "demo", "--resolution", "8", *SMALL, "-o", str(data)], capsys, data)
    assert "notes.txt" in message and (data / "notes.txt").read_text() == "mine"
