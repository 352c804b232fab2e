"""Camera poses of photos or a video without them: structure from motion with COLMAP
(vq_mitsuba.geometry.poses), the posed capture read by the COLMAP loader, and `fit` of photos."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from orbit_photos import RADIUS, centre_errors, write_photos, write_video
from vq_mitsuba.errors import InputError

N_VIEWS = 24


@pytest.fixture(scope="module")
def orbit(tmp_path_factory):
    """(folder of 24 PNG photos around a textured scene, name -> true camera centre)."""
    root = tmp_path_factory.mktemp("orbit")
    cams = write_photos(root / "photos", n=N_VIEWS)
    return root / "photos", {c.name: c.origin for c in cams}


def _fails(*args, **kwargs):
    raise AssertionError("structure from motion ran")


def _turned(src: Path, dst: Path) -> None:
    """`src` stored a quarter turn counter-clockwise (JPEG or PNG, as `dst` is named) with the EXIF
    orientation (6: "turn 90 degrees clockwise to display") that says so."""
    from PIL import Image

    with Image.open(src) as im:
        exif = Image.Exif()
        exif[0x0112] = 6
        turned = im.convert("RGB").transpose(Image.Transpose.ROTATE_90)
        turned.save(dst, exif=exif.tobytes(), **({"quality": 95} if dst.suffix == ".jpg" else {}))


def _check_poses(capture_folder: Path, truth: dict, name_of=lambda name: name):
    from vq_mitsuba.data.captures import load_capture

    capture = load_capture(capture_folder)
    found = {name_of(c.name): c.origin for c in capture.cameras}
    errors = centre_errors(found, truth) / RADIUS
    # 200-pixel photos: the centres come within 1.2 to 3.0 % of the scene's radius (RMS), 2.1 to 2.7 % at worst;
    # COLMAP's threaded matching and bundle adjustment vary from run to run
    assert np.sqrt(np.mean(errors ** 2)) < 0.035 and errors.max() < 0.05, np.round(errors, 4)
    return capture


def test_photos_are_posed_where_they_were_taken(orbit, tmp_path, monkeypatch):
    """Every photo is placed, one stored turned (EXIF) too, at the true centres up to a similarity,
    with sub-pixel reprojection error; a second call reuses the result, new photos do not."""
    import vq_mitsuba.geometry.poses as poses
    from PIL import Image

    photos, truth = orbit
    folder = tmp_path / "phone"
    shutil.copytree(photos, folder)
    _turned(folder / "photo_005.png", folder / "photo_005.jpg")
    (folder / "photo_005.png").unlink()
    out = tmp_path / "posed"
    lines = []
    summary = poses.pose_capture(folder, out, log=lines.append)
    assert summary["registered"] >= N_VIEWS - 1 and summary["images"] == N_VIEWS
    assert summary["mean_reprojection_error_px"] < 1.0 and summary["matcher"] == "exhaustive"
    assert any(f"placed {summary['registered']} of {N_VIEWS} photos" in line for line in lines)
    assert json.loads((out / "pose.json").read_text())["registered"] == summary["registered"]
    assert (out / "sparse" / "0" / "points3D.bin").is_file() and not (out / "database.db").exists()
    with Image.open(out / "images" / "photo_005.jpg") as im:  # upright, and told so
        assert im.getexif().get(0x0112, 1) == 1
    capture = _check_poses(out, truth)
    assert "photo_005" in [c.name for c in capture.cameras]

    monkeypatch.setattr(poses, "_sfm", _fails)
    assert poses.pose_capture(folder, out, log=lines.append)["reused"]
    shutil.copy(photos / "photo_005.png", folder / "photo_005b.png")
    with pytest.raises(AssertionError, match="structure from motion ran"):
        poses.pose_capture(folder, out, log=lines.append)
    assert (out / "pose.json").is_file() and not list(tmp_path.glob(".*pose-tmp"))  # the old result kept


def test_a_video_is_posed_from_its_sharpest_frames(orbit, tmp_path, capsys):
    """An orbit filmed as a video with two blurred frames around each sharp one: `pose` keeps the
    sharp frame of each time window and places them all."""
    from vq_mitsuba import cli

    photos, truth = orbit
    video = tmp_path / "orbit.mp4"
    write_video(video, sorted(photos.glob("*.png")), blurred=2)
    out = tmp_path / "posed"
    assert cli.main(["pose", str(video), "-o", str(out), "--set", "pose.frames=24", "--quiet"]) == 0
    assert f"of {N_VIEWS} images posed" in capsys.readouterr().out
    summary = json.loads((out / "pose.json").read_text())
    assert summary["kind"] == "video" and summary["matcher"] == "sequential"
    assert summary["video"]["frames_decoded"] == 3 * N_VIEWS
    assert [k["frame"] % 3 for k in summary["video"]["kept"]] == [1] * N_VIEWS  # the sharp ones
    assert summary["registered"] >= N_VIEWS - 1 and summary["mean_reprojection_error_px"] < 1.0
    names = sorted(truth)
    _check_poses(out, truth, name_of=lambda name: names[int(name.split("_")[1]) // 3])


def test_photos_that_do_not_overlap_are_refused_naming_how_many_were_placed(tmp_path, capsys):
    from vq_mitsuba import cli
    from vq_mitsuba.data.imageio import write_png

    rng = np.random.default_rng(0)
    for i in range(6):
        write_png(tmp_path / "noise" / f"{i}.png", rng.random((120, 160, 3)).astype(np.float32))
    assert cli.main(["pose", str(tmp_path / "noise"), "-o", str(tmp_path / "out"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "placed 0 of 6 photos (at least 3 needed" in err
    assert not (tmp_path / "out").exists() and not list(tmp_path.glob(".*"))


def test_photo_folders_and_videos_are_captures_without_poses(tmp_path, monkeypatch):
    from argparse import Namespace

    import vq_mitsuba.geometry.poses as poses
    from vq_mitsuba.cli import _run_dir
    from vq_mitsuba.data.captures import capture_kind, load_cameras, load_capture, open_capture, resolve_capture_path
    from vq_mitsuba.data.imageio import write_png

    monkeypatch.setattr(poses, "_sfm", _fails)
    photos = tmp_path / "photos"
    for name in ("IMG_0.png", "IMG_1.PNG"):
        write_png(photos / name, np.full((20, 30, 3), 0.5, np.float32))
    (photos / "notes.txt").write_text("not a photo")
    video = tmp_path / "clip.MOV"
    video.write_bytes(b"")
    assert resolve_capture_path(photos) == photos and capture_kind(photos) == "photos"
    assert resolve_capture_path(video) == video and capture_kind(video) == "video"
    assert not open_capture(photos).posed and not open_capture(video).posed
    assert _run_dir(Namespace(capture=str(photos), output=None), "fit") == Path("runs") / "photos"
    assert _run_dir(Namespace(capture=str(video), output=None), "fit") == Path("runs") / "clip"
    for source in (photos, video):
        with pytest.raises(InputError, match="vq-mitsuba pose"):
            load_capture(source)
        with pytest.raises(InputError, match="vq-mitsuba pose"):
            load_cameras(source)
    with pytest.raises(InputError, match="holds 2 photos"):
        poses.pose_capture(photos, tmp_path / "out")
    write_png(photos / "IMG_2.png", np.full((30, 20, 3), 0.5, np.float32))
    write_png(photos / "IMG_3.png", np.full((30, 20, 3), 0.5, np.float32))
    with pytest.raises(InputError, match=r"differ in size \(30x20: 2 \(IMG_0.png, IMG_1.PNG\); 20x30: 2 \(IMG_2"):
        poses.pose_capture(photos, tmp_path / "out")
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("mine")
    with pytest.raises(InputError, match="holds other files"):
        poses.pose_capture(photos, tmp_path / "mine")
    with pytest.raises(InputError, match="ffmpeg cannot read the video"):
        poses.pose_capture(video, tmp_path / "out")
    assert not (tmp_path / "out").exists() and not list(tmp_path.glob(".*"))


@pytest.mark.parametrize("suffix", [".jpg", ".png"])
def test_photos_stored_turned_are_copied_upright(tmp_path, suffix):
    from PIL import Image

    from vq_mitsuba.data.formats.photos import copy_upright

    upright = np.zeros((20, 30, 3), np.uint8)
    upright[:5, :8] = 255  # a white patch in the top-left corner
    src, dst = tmp_path / f"turned{suffix}", tmp_path / "out" / f"turned{suffix}"
    dst.parent.mkdir()
    Image.fromarray(upright).save(tmp_path / f"upright{suffix}")
    _turned(tmp_path / f"upright{suffix}", src)
    assert copy_upright(src, dst) == (30, 20)
    with Image.open(dst) as im:
        pixels = np.asarray(im.convert("RGB"))
    assert pixels.shape == (20, 30, 3) and pixels[:4, :7].mean() > 200 and pixels[8:, 12:].mean() < 40
    assert copy_upright(tmp_path / f"upright{suffix}", tmp_path / "out" / "plain.bin") == (30, 20)
    assert (tmp_path / "out" / "plain.bin").read_bytes() == (tmp_path / f"upright{suffix}").read_bytes()


def test_fit_of_photos_poses_them_in_the_run_once(orbit, tmp_path, monkeypatch):
    """`fit PHOTOS` poses them into RUN/pose and hands that COLMAP capture to the geometry stage and
    the fit; a resumed fit reuses the poses. (The stages after SfM are stand-ins here; the slow
    test below runs them.)"""
    import vq_mitsuba.engine.pipeline as pipeline
    import vq_mitsuba.geometry.poses as poses
    from vq_mitsuba.config import load_config
    from vq_mitsuba.run.run_dir import RunDir

    photos, _ = orbit
    seen = []
    monkeypatch.setattr(pipeline, "ensure_geometry", lambda capture, run, *a, **k: seen.append(capture) or
                        run / RunDir.MESH)
    monkeypatch.setattr(pipeline, "fit_materials", lambda capture, *a, **k: seen.append(capture) or {"iterations": 1})
    run = RunDir(tmp_path / "run")
    cfg = load_config(None, [])
    pipeline.fit_capture(photos, run.dir, cfg, log=lambda line: None)
    assert [c.source for c in seen] == [run / RunDir.POSE] * 2 and (run / RunDir.POSE_SUMMARY).is_file()
    assert run.holds_run_files()
    monkeypatch.setattr(poses, "_sfm", _fails)
    pipeline.fit_capture(photos, run.dir, cfg, resume=True, log=lambda line: None)
    assert [c.source for c in seen[2:]] == [run / RunDir.POSE] * 2
    with pytest.raises(InputError, match="known geometry cannot be used"):
        pipeline.fit_capture(photos, tmp_path / "other", cfg, mesh=tmp_path / "m.ply")
    with pytest.raises(InputError, match="--geometry given"):
        pipeline.fit_capture(photos, tmp_path / "other", cfg, geometry="given")


@pytest.mark.slow
@pytest.mark.parametrize("source", ["photos", "video"])
def test_fit_of_a_photo_folder_end_to_end(orbit, tmp_path, monkeypatch, capsys, source):
    """Photos (or a video of them) on a plain black backdrop: poses, NeuS and the material fit, then
    a resumed fit that does not run SfM again."""
    import vq_mitsuba.geometry.poses as poses
    from vq_mitsuba import cli
    from vq_mitsuba.run.run_dir import RunDir

    photos, _ = orbit
    if source == "video":
        photos = tmp_path / "orbit.mp4"
        write_video(photos, sorted(orbit[0].glob("*.png")), blurred=0)
    run = RunDir(tmp_path / "run")
    quick = ["--quiet", "--background-color", "0,0,0", "--set", "neus.iterations=30", "--set",
             "neus.hull_resolution=64", "--set", "neus.mesh_resolution=64", "--set", "train.batch_rays=128",
             "--set", "residual.iterations=1"] + (["--set", "pose.frames=24"] if source == "video" else [])
    assert cli.main(["fit", str(photos), "-o", str(run.dir), "--set", "train.iterations=4", *quick]) == 0
    assert (run / RunDir.POSE_SUMMARY).is_file() and run.has_mesh() and run.has_checkpoint()
    assert Path(run.info()["capture"]) == (run / RunDir.POSE).resolve()
    summary = json.loads((run / RunDir.POSE_SUMMARY).read_text())
    assert summary["kind"] == source and summary["registered"] == N_VIEWS
    monkeypatch.setattr(poses, "_sfm", _fails)
    loud = [a for a in quick if a != "--quiet"]  # the note is what is checked
    assert cli.main(["fit", str(photos), "-o", str(run.dir), "--resume", "--set", "train.iterations=6", *loud]) == 0
    assert "pose: reusing" in capsys.readouterr().out
