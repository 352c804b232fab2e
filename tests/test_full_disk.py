"""A disk that refuses a write mid-command (full, read-only) stops it with one message naming the
file, exit status 3, no traceback; the partial file is removed and what was written before kept."""

import errno
from pathlib import Path

import numpy as np
import pytest

from vq_mitsuba import cli
from vq_mitsuba.data.imageio import write_exr, write_png
from vq_mitsuba.errors import WriteError


@pytest.fixture
def full_exr(monkeypatch):
    """OpenEXR's writer as it fails on a full disk: a RuntimeError in words, after a partial file."""
    import OpenEXR

    def write(self, path):
        Path(path).write_bytes(b"partial")
        raise RuntimeError(f'Failed to write pixel data to image file "{path}". No space left on device.')

    monkeypatch.setattr(OpenEXR.File, "write", write)


def test_image_writers_name_the_file_a_full_disk_refused(tmp_path, full_exr, monkeypatch):
    with pytest.raises(WriteError, match="a.exr: cannot be written: No space left on device"):
        write_exr(tmp_path / "a.exr", np.ones((4, 4, 3), np.float32))
    assert not (tmp_path / "a.exr").exists()

    def refused(self, data):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(Path, "write_bytes", refused)
    with pytest.raises(WriteError, match="b.png: cannot be written: no space left on the device"):
        write_png(tmp_path / "b.png", np.ones((4, 4, 3), np.float32))


def test_render_on_a_full_disk_names_the_file(three_materials, tmp_path, full_exr, capsys):
    capture, run = three_materials
    out = tmp_path / "renders"
    code = cli.main(["render", str(run.dir), "--cameras", str(capture), "-o", str(out), "--spp", "1", "--quiet"])
    err = capsys.readouterr().err
    assert code == 3 and "Traceback" not in err
    assert "cannot be written: No space left on device" in err and str(out) in err


def test_export_on_a_full_disk_names_the_file(three_materials, tmp_path, monkeypatch, capsys):
    _, run = three_materials
    real = Path.write_text

    def full(self, *args, **kwargs):
        if self.suffix == ".obj":
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(self, *args, **kwargs)

    monkeypatch.setattr(Path, "write_text", full)
    out = tmp_path / "export"
    assert cli.main(["export", str(run.dir), "-o", str(out), "--format", "obj", "--texture-size", "16", "--quiet"]) == 3
    err = capsys.readouterr().err
    assert ".obj: cannot be written: no space left on the device" in err and "Traceback" not in err


def test_a_lock_that_cannot_be_written_is_not_left_behind(three_materials, tmp_path, monkeypatch, capsys):
    import os

    _, run = three_materials

    def full(fd, data, offset):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(os, "pwrite", full)
    out = tmp_path / "edited"
    assert cli.main(["edit", str(run.dir), "--material", "1", "--set", "roughness=0.5", "-o", str(out)]) == 3
    assert "no space left on the device" in capsys.readouterr().err
    assert not out.exists()  # neither an empty run.lock nor the folder made for it



TINY_SCENE = ["make-scene", "demo", "--resolution", "8", "--spp", "1", "--n-train", "2", "--n-test", "1"]


@pytest.mark.parametrize("name, extra", [("transforms_train.json", []), ("scene.xml", []), ("scene.json", []),
                                         ("images.txt", ["--photo-formats"]), ("images.bin", ["--photo-formats"]),
                                         ("poses_bounds.npy", ["--photo-formats"])])
def test_make_scene_on_a_full_disk_names_the_file(tmp_path, monkeypatch, capsys, name, extra):
    real_text, real_bytes = Path.write_text, Path.write_bytes
    real_open = open

    def full(real):
        def write(self, *args, **kwargs):
            if self.name == name:
                raise OSError(errno.ENOSPC, "No space left on device")
            return real(self, *args, **kwargs)
        return write

    def full_open(file, *args, **kwargs):  # numpy's writers open the file themselves
        if Path(str(file)).name == name:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real_open(file, *args, **kwargs)

    monkeypatch.setattr(Path, "write_text", full(real_text))
    monkeypatch.setattr(Path, "write_bytes", full(real_bytes))
    monkeypatch.setattr("builtins.open", full_open)
    out = tmp_path / "data"
    assert cli.main([*TINY_SCENE, *extra, "-o", str(out)]) == 3
    err = capsys.readouterr().err
    assert "Traceback" not in err
    error = next(line for line in err.splitlines() if line.startswith("error:"))
    assert f"{name}: cannot be written: no space left on the device" in error and str(out) in error, error
    assert "the unfinished dataset is removed" in error and not out.exists()


def test_make_scene_names_its_folder_where_a_refused_write_names_no_file(tmp_path, monkeypatch, capsys):
    from vq_mitsuba.synthetic import mitsuba_scenes

    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")  # as a library's write says it: no file name

    monkeypatch.setattr(mitsuba_scenes, "write_envmaps", full)
    out = tmp_path / "data"
    out.mkdir()
    assert cli.main([*TINY_SCENE, "-o", str(out)]) == 3
    err = capsys.readouterr().err
    assert f"error: {out}: cannot be written: no space left on the device (the unfinished dataset is removed)" in err
    assert "Traceback" not in err and out.is_dir() and not any(out.iterdir())
