"""One rule for every command that writes (vq_mitsuba/run/outputs.py): a new folder, an empty one,
or a folder of its own kind it made before. Anything else is refused before any work: exit 2, one
message naming the folder, no traceback, and the other files byte for byte as they were. A command
refused once it began leaves nothing behind."""

import json
from pathlib import Path

import numpy as np
import pytest

from tiny_scene import write_sphere_capture
from vq_mitsuba import cli
from vq_mitsuba.config import load_config
from vq_mitsuba.errors import InputError
from vq_mitsuba.run import outputs
from vq_mitsuba.run.run_dir import RunDir

FIT_TINY = ["--set", "train.iterations=6", "--set", "train.batch_rays=128", "--set", "vq.enabled=false", "--quiet"]


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """(capture XML, fitted run folder, folder for the module's own outputs)."""
    from vq_mitsuba.engine.pipeline import fit

    folder = tmp_path_factory.mktemp("outputs")
    capture = write_sphere_capture(folder / "cap", size=16, n_views=4, spp=8)
    fit(capture, folder / "run", load_config(None, ["train.iterations=6", "train.batch_rays=128", "vq.enabled=false"]))
    return capture, folder / "run", folder


def _snapshot(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def _refused(argv: list[str], capsys, named: Path) -> str:
    """Run the command: exit 2, one error line naming `named`, no traceback; returns the message."""
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    errors = [line for line in err.splitlines() if line.startswith("error")]
    assert len(errors) == 1 and str(named) in errors[0] and "Traceback" not in err, err
    return errors[0]


# --- eval -o ---------------------------------------------------------------------------------

@pytest.mark.parametrize("name", [RunDir.CHECKPOINT, RunDir.INFO, RunDir.CONFIG, RunDir.MESH])
def test_eval_never_writes_its_metrics_over_a_runs_file(tiny, tmp_path, capsys, name):
    _, run, _ = tiny
    before = _snapshot(run)
    _refused(["eval", str(run), "--gt", str(tmp_path / "data"), "-o", str(run / name)], capsys, run / name)
    assert _snapshot(run) == before


def test_eval_refuses_any_file_it_did_not_write_and_a_runs_file_name(tiny, tmp_path, capsys):
    _, run, _ = tiny
    other = tmp_path / "other_run"
    other.mkdir()
    (other / RunDir.MATERIALS).write_text('{"num_materials": 3}')
    mine = tmp_path / "notes.json"
    mine.write_text('{"mine": true}')
    for target in (other / RunDir.MATERIALS, mine):
        message = _refused(["eval", str(run), "--gt", str(tmp_path / "data"), "-o", str(target)], capsys, target)
        assert "not a metrics file" in message
    assert (other / RunDir.MATERIALS).read_text() == '{"num_materials": 3}' and mine.read_text() == '{"mine": true}'
    # a run's own file name that is not there yet (an unfinished run without materials.json)
    message = _refused(["eval", str(run), "--gt", str(tmp_path / "data"), "-o", str(run / RunDir.MATERIALS)], capsys,
                       run / RunDir.MATERIALS)
    assert "file of the run" in message and not (run / RunDir.MATERIALS).exists()


def test_eval_replaces_a_metrics_file_it_wrote(tiny, tmp_path, capsys):
    _, run, _ = tiny
    metrics = tmp_path / "metrics.json"
    metrics.write_text(json.dumps({**outputs.EVAL_MARK, "run": str(run), "novel_view": {"psnr": 20.0}}))
    outputs.check_metrics_file(metrics)  # no refusal
    outputs.check_metrics_file(run / RunDir.METRICS)
    # the command goes on to the dataset, which is missing here: that is what it names
    assert cli.main(["eval", str(run), "--gt", str(tmp_path / "no_data"), "-o", str(metrics)]) == 2
    assert "no_data" in capsys.readouterr().err


# --- export -----------------------------------------------------------------------------------

def test_export_never_writes_into_a_capture(tiny, capsys):
    capture, run, _ = tiny
    dataset = capture.parent
    before = _snapshot(dataset)
    message = _refused(["export", str(run), "--format", "mitsuba", "-o", str(dataset), "--quiet"], capsys, dataset)
    assert "other files" in message and "another -o" in message
    assert _snapshot(dataset) == before


def test_export_replaces_its_own_export_of_the_same_format_only(tiny, capsys):
    _, run, folder = tiny
    out = folder / "export_gltf"
    argv = ["export", str(run), "--format", "gltf", "--texture-size", "16", "-o", str(out), "--quiet"]
    assert cli.main(argv) == 0
    (out / "old_name.glb").write_bytes(b"an earlier export's file")  # as if another run had been exported here
    summary = json.loads((out / "export.json").read_text())
    json.dump({**summary, "files": summary["files"] + ["old_name.glb"]}, (out / "export.json").open("w"))
    assert cli.main(argv) == 0  # the same format: its own files replaced
    assert not (out / "old_name.glb").exists()
    capsys.readouterr()
    before = _snapshot(out)
    message = _refused(["export", str(run), "--format", "obj", "--texture-size", "16", "-o", str(out), "--quiet"],
                       capsys, out)
    assert "gltf export" in message
    assert _snapshot(out) == before


# --- render -----------------------------------------------------------------------------------

def test_render_never_writes_over_ground_truth_or_a_users_folder(tiny, capsys):
    capture, run, folder = tiny
    gt = folder / "data" / "gt"
    gt.mkdir(parents=True)
    (gt / "test_000_basecolor.exr").write_bytes(b"ground truth")
    for target in (gt, run):
        before = _snapshot(target)
        message = _refused(["render", str(run), "--cameras", str(capture), "-o", str(target), "--quiet"], capsys,
                           target)
        assert "render.json" in message and "another -o" in message
        assert _snapshot(target) == before


def test_render_writes_again_into_its_own_render_folder(tiny, capsys):
    capture, run, folder = tiny
    out = folder / "views"
    argv = ["render", str(run), "--cameras", str(capture), "-o", str(out), "--spp", "1", "--max-size", "8", "--quiet"]
    assert cli.main(argv) == 0 and (out / "render.json").is_file()
    assert cli.main(argv) == 0
    capsys.readouterr()


# --- geometry ---------------------------------------------------------------------------------

@pytest.mark.parametrize("resume", [False, True])
def test_geometry_never_replaces_the_mesh_of_a_fitted_run(tiny, capsys, resume):
    capture, run, _ = tiny
    before = _snapshot(run)
    message = _refused(["geometry", str(capture), "-o", str(run), "--quiet", *(["--resume"] if resume else [])],
                       capsys, run)
    assert "checkpoint.pt" in message and "mesh.ply" in message
    assert _snapshot(run) == before


def test_geometry_writes_into_a_geometry_only_run(tmp_path):
    from vq_mitsuba.geometry.stage import check_geometry_target

    run = RunDir(tmp_path / "geometry_only")
    run.create()
    (run / RunDir.GEOMETRY).write_text("{}")
    (run / RunDir.MESH).write_bytes(b"ply")
    check_geometry_target(run)  # its own stage's folder: no refusal
    check_geometry_target(RunDir(tmp_path / "new"))


def test_geometry_never_writes_into_an_edited_run(tiny, capsys):
    capture, run, folder = tiny
    edited = folder / "edited_for_geometry"
    assert cli.main(["edit", str(run), "--box=-9,-9,-9,9,9,9", "--set", "roughness=0.5", "-o", str(edited)]) == 0
    before = _snapshot(edited)
    _refused(["geometry", str(capture), "-o", str(edited), "--quiet"], capsys, edited)
    assert _snapshot(edited) == before


def test_make_scene_writes_again_into_its_own_dataset(tmp_path, capsys):
    out = tmp_path / "scene"
    assert cli.main(["make-scene", "demo", "-o", str(out), "--resolution", "8", "--spp", "4", "--n-train", "2",
                     "--n-test", "1"]) == 0
    first = json.loads((out / "scene.json").read_text())
    assert cli.main(["make-scene", "demo", "-o", str(out), "--resolution", "12", "--spp", "4", "--n-train", "2",
                     "--n-test", "1"]) == 0
    again = json.loads((out / "scene.json").read_text())
    assert first["resolution"] == [8, 8] and again["resolution"] == [12, 12]


# --- make-scene, edit -------------------------------------------------------------------------

def test_make_scene_never_writes_into_a_users_folder(tmp_path, capsys):
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "scene.xml").write_text("<scene/>")
    (mine / "images").mkdir()
    (mine / "images" / "a.png").write_bytes(b"my photo")
    before = _snapshot(mine)
    message = _refused(["make-scene", "demo", "-o", str(mine), "--resolution", "8"], capsys, mine)
    assert "other files" in message and "scene.json" in message
    assert _snapshot(mine) == before


def test_edit_writes_a_new_run_only(tiny, tmp_path, capsys):
    _, run, _ = tiny
    edit = ["--box", "-1,-1,-1,1,1,1", "--set", "roughness=0.5"]  # the fit has no discrete branch
    first = tmp_path / "edited"
    assert cli.main(["edit", str(run), *edit, "-o", str(first)]) == 0
    capsys.readouterr()
    before = _snapshot(first)
    for source in (run, first):  # over another edited run (also its own source): refused
        message = _refused(["edit", str(source), *edit, "-o", str(first)], capsys, first)
        assert "edited run" in message
    assert _snapshot(first) == before
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("mine")
    _refused(["edit", str(run), *edit, "-o", str(mine)], capsys, mine)
    assert _snapshot(mine) == {"notes.txt": b"mine"}


# --- pose -------------------------------------------------------------------------------------

def _photos(folder: Path, n: int = 3) -> Path:
    from vq_mitsuba.data.imageio import write_png

    for i in range(n):
        write_png(folder / f"IMG_{i}.png", np.full((12, 16, 3), 0.1 * (i + 1), np.float32))
    return folder


def test_pose_never_empties_a_folder_it_cannot_tell_it_made(tmp_path, monkeypatch):
    from vq_mitsuba.geometry import poses

    monkeypatch.setattr(poses, "_sfm", lambda *a, **kw: pytest.fail("structure from motion ran"))
    photos = _photos(tmp_path / "photos")
    out = tmp_path / "posed"
    (out / "sparse" / "0").mkdir(parents=True)
    (out / "my_notes.txt").write_text("mine")
    (out / "pose.json").write_text("{ not json")
    before = _snapshot(out)
    with pytest.raises(InputError, match="cannot be read") as info:
        poses.pose_capture(photos, out)
    assert str(out / "pose.json") in str(info.value)
    (out / "pose.json").write_text(json.dumps({"version": 1, "source": str(tmp_path / "other_photos"),
                                               "inputs": {}}))
    before = _snapshot(out)
    with pytest.raises(InputError, match="poses of other photos"):
        poses.pose_capture(photos, out)
    assert _snapshot(out) == before
    # its own photos, posed again (they changed): only a folder of pose's own files is replaced
    (out / "pose.json").write_text(json.dumps({"version": 1, "source": str(photos.resolve()), "inputs": {}}))
    with pytest.raises(InputError, match=r"files pose did not write \(my_notes.txt\)"):
        poses.pose_capture(photos, out)
    assert (out / "my_notes.txt").read_text() == "mine"


# --- refused commands leave nothing behind --------------------------------------------------------

def test_a_fit_refused_after_reading_a_distorted_capture_leaves_no_undistorted_folder(tmp_path, capsys):
    from vq_mitsuba.data.cameras import Camera, look_at
    from vq_mitsuba.data.imageio import write_png
    from vq_mitsuba.data.formats.nerfstudio import write_transforms_json
    from vq_mitsuba.data.lens import Lens, distort_image

    lens = Lens("OPENCV", 24, 16, 20.0, 20.0, 12.0, 8.0, k1=0.05)
    cams = [Camera(f"v{i}", look_at([3 * np.sin(i), 0, 3 * np.cos(i)], [0, 0, 0], [0, 1, 0]), 40.0, 24, 16)
            for i in range(3)]
    ns = tmp_path / "ns"
    for cam in cams:
        write_png(ns / "images" / f"{cam.name}.png", distort_image(np.full((16, 24, 3), 0.5, np.float32), lens))
    write_transforms_json(ns / "transforms.json", cams, [f"images/{c.name}.png" for c in cams], [lens] * 3)
    run = tmp_path / "run"
    message = _refused(["fit", str(ns), "-o", str(run), "--geometry", "given", *FIT_TINY], capsys, ns)
    assert "no known geometry" in message
    assert not run.exists()


def test_a_fit_refused_on_a_mesh_that_misses_every_pixel_leaves_no_config_or_mesh(tiny, tmp_path, capsys):
    import trimesh

    capture, _, _ = tiny
    far = tmp_path / "far.ply"
    trimesh.creation.icosphere(subdivisions=1, radius=0.1).apply_translation([100.0, 0, 0]).export(far)
    run = tmp_path / "run"
    message = _refused(["fit", str(capture), "-o", str(run), "--mesh", str(far), *FIT_TINY], capsys, capture)
    assert "no training pixel hits the geometry" in message
    assert not run.exists()


def test_an_edit_that_fails_writing_run_json_leaves_no_edits_json(tiny, tmp_path, monkeypatch, capsys):
    from vq_mitsuba.errors import WriteError

    _, run, _ = tiny

    def full_disk(self, info):
        raise WriteError(self.dir / RunDir.INFO, "cannot be written: no space left on the device")

    monkeypatch.setattr(RunDir, "write_info", full_disk)
    out = tmp_path / "edited"
    assert cli.main(["edit", str(run), "--box", "-1,-1,-1,1,1,1", "--set", "roughness=0.5", "-o", str(out)]) != 0
    assert "no space left" in capsys.readouterr().err
    assert not out.exists()


def test_a_folder_holding_only_a_runs_cache_is_a_runs_own(tmp_path):
    run = RunDir(tmp_path / "run")
    (run / RunDir.UNDISTORTED).mkdir(parents=True)
    outputs.check_output_folder(run.dir, "run", "fit")  # left by an earlier version's refused fit: no refusal
