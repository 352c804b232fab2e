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


# --- envmaps: one check wherever one is read; a file known by its bytes ----------------------

@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """(sphere capture XML with a known envmap, a 4-step run of it)."""
    from tiny_scene import write_sphere_capture
    from vq_mitsuba.config import load_config
    from vq_mitsuba.engine.pipeline import fit

    folder = tmp_path_factory.mktemp("tiny")
    capture = write_sphere_capture(folder / "cap", size=16, n_views=4, spp=8)
    fit(capture, folder / "run", load_config(None, ["train.iterations=4", "train.batch_rays=128",
                                                    "vq.warmup_frac=0.3"]))
    return capture, folder / "run"


def _envmaps(folder: Path) -> dict[str, Path]:
    """Bad envmaps, each named for what is wrong with it."""
    from vq_mitsuba.data.imageio import write_exr, write_png

    folder.mkdir(exist_ok=True)
    write_exr(folder / "one_texel.exr", np.ones((1, 1, 3), np.float32))
    write_exr(folder / "too_bright.exr", np.full((4, 8, 3), 1.7e38, np.float32))
    write_png(folder / "photo.png", np.full((4, 8, 3), 0.5, np.float32))
    (folder / "photo.hdr").write_bytes((folder / "photo.png").read_bytes())  # a PNG renamed
    header = b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n"
    (folder / "negative.hdr").write_bytes(header + b"-Y -5 +X 10\n" + bytes(64))
    (folder / "huge.hdr").write_bytes(header + b"-Y 2000000 +X 4000000\n" + bytes(64))
    (folder / "garbled.hdr").write_bytes(header + b"-Y five +X ten\n" + bytes(64))
    return {p.stem: p for p in folder.iterdir() if p.name != "photo.png"}


ENVMAP_FAULTS = {"one_texel": "at least 4 x 2", "too_bright": "brightest texel", "photo": "not a Radiance HDR image",
                 "negative": "size line", "huge": "size line", "garbled": "size line"}


def test_every_envmap_reader_refuses_a_bad_file_by_name(tmp_path):
    from vq_mitsuba.data.envmaps import load_envmap

    for name, path in _envmaps(tmp_path).items():
        with pytest.raises(InputError, match=ENVMAP_FAULTS[name]) as refused:
            load_envmap(path)
        assert refused.value.path == path


def test_a_scene_xml_emitter_gets_the_same_envmap_check(tiny, tmp_path, capsys):
    import shutil

    from vq_mitsuba.data.captures import load_capture

    capture, _ = tiny
    bad = _envmaps(tmp_path / "envs")
    for name in ("one_texel", "too_bright"):
        cap = tmp_path / name
        shutil.copytree(capture.parent, cap)
        shutil.copy(bad[name], cap / "env.exr")
        with pytest.raises(InputError, match=ENVMAP_FAULTS[name]) as refused:
            load_capture(cap / capture.name)
        assert refused.value.path == cap / "env.exr"
    out = tmp_path / "run"
    _refused(["fit", str(tmp_path / "one_texel" / capture.name), "-o", str(out), "--quiet", "--set",
              "train.iterations=2"], capsys,
             tmp_path / "one_texel" / "env.exr")
    assert not out.exists()


def test_export_and_render_refuse_the_same_envmaps_by_name(tiny, tmp_path, capsys):
    capture, run = tiny
    bad = _envmaps(tmp_path / "envs")
    for name in ("too_bright", "one_texel", "photo"):
        out = tmp_path / f"export_{name}"
        message = _refused(["export", str(run), "--format", "obj", "--envmap", str(bad[name]), "-o", str(out)],
                           capsys, bad[name])
        assert ENVMAP_FAULTS[name] in message and not out.exists()
        out = tmp_path / f"render_{name}"
        message = _refused(["render", str(run), "--cameras", str(capture), "--envmap", str(bad[name]), "-o",
                            str(out), "--quiet"], capsys, bad[name])
        assert ENVMAP_FAULTS[name] in message and not out.exists()


def test_too_bright_lighting_at_an_exposure_names_its_file(tiny, tmp_path, capsys):
    from vq_mitsuba.data.imageio import write_exr

    capture, run = tiny
    bright = tmp_path / "bright.exr"
    write_exr(bright, np.full((4, 8, 3), 1e20, np.float32))
    out = tmp_path / "renders"
    message = _refused(["render", str(run), "--cameras", str(capture), "--envmap", str(bright), "--exposure", "40",
                        "-o", str(out), "--quiet"], capsys, bright)
    assert "at exposure +40 EV" in message and not out.exists()


def test_eval_refuses_a_dataset_envmap_before_any_work(tiny, tmp_path, capsys):
    from vq_mitsuba.data.imageio import write_exr

    _, run = tiny
    data = tmp_path / "data"
    assert cli.main(["make-scene", "demo", "--resolution", "16", *SMALL, "-o", str(data)]) == 0
    env = next(p for p in (data / "envmaps").iterdir() if p.stem != "train")
    write_exr(env, np.ones((1, 1, 3), np.float32))
    capsys.readouterr()
    metrics = tmp_path / "metrics.json"
    message = _refused(["eval", str(run), "--gt", str(data), "-o", str(metrics), "--quiet"], capsys, env)
    assert "at least 4 x 2" in message and not metrics.exists()


@pytest.mark.parametrize("real, named", [("png", ".exr"), ("exr", ".png"), ("png", ".jpg"), ("exr", ".hdr")])
def test_image_readers_know_a_file_by_its_bytes(tmp_path, real, named):
    from vq_mitsuba.data.envmaps import read_envmap_file
    from vq_mitsuba.data.imageio import image_size, read_image, read_mask, write_exr, write_png

    source = tmp_path / f"source.{real}"
    (write_exr if real == "exr" else write_png)(source, np.full((4, 8, 3), 0.5, np.float32))
    renamed = tmp_path / f"renamed{named}"
    renamed.write_bytes(source.read_bytes())
    kind = {"png": "a PNG", "exr": "an OpenEXR"}[real]
    readers = (read_envmap_file,) if named == ".hdr" else (read_image, read_mask, image_size)
    for read in readers:
        with pytest.raises(InputError, match=f"{kind} file named {named}") as refused:
            read(renamed)
        assert refused.value.path == renamed


# --- a folder holding captures of two formats -------------------------------------------------

@pytest.fixture(scope="module")
def photographed(tmp_path_factory):
    """A make-scene dataset with its training views as NeuS/IDR, COLMAP, nerfstudio and LLFF captures."""
    data = tmp_path_factory.mktemp("photographed") / "data"
    assert cli.main(["make-scene", "demo", "--resolution", "16", "--photo-formats", *SMALL, "-o", str(data)]) == 0
    return data


def _mixed(data: Path, folder: Path, first: str, second: str) -> Path:
    import shutil

    shutil.copytree(data / first, folder)
    shutil.copytree(data / second, folder, dirs_exist_ok=True)
    return folder


@pytest.mark.parametrize("formats, read, other", [
    (("colmap", "nerfstudio"), "transforms.json", "the COLMAP model (in sparse/0/"),
    (("llff", "neus"), "cameras_sphere.npz", "poses_bounds.npy"),
])
def test_a_folder_of_two_formats_says_which_it_read(photographed, tmp_path, formats, read, other):
    from vq_mitsuba.data.captures import load_capture
    from vq_mitsuba.errors import Notice

    folder = _mixed(photographed, tmp_path / "both", *formats)
    with pytest.warns(Notice) as said:
        capture = load_capture(folder)
    assert capture.source == folder / read and len(capture.cameras) == 3
    message = str(said[0].message)
    assert f"reading {read}" in message and other in message and str(folder) in message


def test_a_folder_of_two_disagreeing_formats_is_refused(photographed, tmp_path, capsys):
    from vq_mitsuba.data.captures import load_capture

    folder = _mixed(photographed, tmp_path / "both", "colmap", "nerfstudio")
    transforms = json.loads((folder / "transforms.json").read_text())
    transforms["frames"] = transforms["frames"][:2]
    (folder / "transforms.json").write_text(json.dumps(transforms))
    with pytest.raises(InputError, match=r"disagree: transforms.json \(2 views\), the COLMAP model \(in sparse/0/, sparse/ or the folder\) "
                                         r"\(3 views\)") as refused:
        load_capture(folder)
    assert refused.value.path == folder
    # a dataset's transforms_train.json and scene.xml: the same views, no word; one view fewer: refused
    import warnings

    data = tmp_path / "data"
    import shutil

    shutil.copytree(photographed, data, ignore=shutil.ignore_patterns(*("neus", "colmap*", "nerfstudio", "llff")))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert load_capture(data).source == data / "transforms_train.json"
    train = json.loads((data / "transforms_train.json").read_text())
    train["frames"] = train["frames"][1:]
    (data / "transforms_train.json").write_text(json.dumps(train))
    out = tmp_path / "run"
    message = _refused(["fit", str(data), "-o", str(out), "--quiet", "--set", "train.iterations=2"], capsys, data)
    assert "transforms_train.json (2 views), scene.xml (3 views)" in message and not out.exists()


# --- cameras that all share one pose ------------------------------------------------------------

def _one_pose_cameras(n=3, width=24, height=16):
    from vq_mitsuba.data.cameras import Camera, look_at

    pose = look_at([0.3, 0.5, 2.5], [0, 0, 0], [0, 1, 0])
    return [Camera(f"v{i}", pose.copy(), 45.0, width, height) for i in range(n)]


def _one_pose_llff(folder: Path) -> Path:
    from vq_mitsuba.data.formats.llff import write_poses_bounds
    from vq_mitsuba.data.imageio import write_png

    write_poses_bounds(folder / "poses_bounds.npy", _one_pose_cameras(), [(0.5, 5.0)] * 3)
    for i in range(3):
        write_png(folder / "images" / f"{i:03d}.png", np.full((16, 24, 3), 0.2 + 0.2 * i))
    return folder


def _one_pose_colmap(folder: Path) -> Path:
    from vq_mitsuba.data.formats.colmap import write_colmap
    from vq_mitsuba.data.imageio import write_png

    names = [f"{i:03d}.png" for i in range(3)]
    for i, name in enumerate(names):
        write_png(folder / "images" / name, np.full((16, 24, 3), 0.2 + 0.2 * i))
    write_colmap(folder / "sparse" / "0", _one_pose_cameras(), names)
    return folder


@pytest.mark.parametrize("write, source", [(_one_pose_llff, "poses_bounds.npy"), (_one_pose_colmap, "")])
def test_a_capture_whose_cameras_share_one_pose_is_refused(tmp_path, capsys, write, source):
    from vq_mitsuba.data.captures import load_capture

    folder = write(tmp_path / "cap")
    with pytest.raises(InputError, match="all 3 cameras share one pose") as refused:
        load_capture(folder)
    assert refused.value.path == (folder / source if source else folder)
    out = tmp_path / "run"
    message = _refused(["fit", str(folder), "-o", str(out), "--quiet", "--set", "train.iterations=2"], capsys, folder)
    assert "one viewpoint" in message and not out.exists()


def test_cameras_at_one_point_looking_different_ways_are_not_one_pose():
    from vq_mitsuba.data.cameras import Camera, look_at
    from vq_mitsuba.data.checks import check_viewpoints

    turning = [Camera(f"v{i}", look_at([0, 0, 0], [np.sin(i), 0, np.cos(i)], [0, 1, 0]), 45.0, 8, 8)
               for i in range(3)]
    check_viewpoints(Path("cap"), turning)  # a panorama: one centre, three directions
    with pytest.raises(InputError, match="share one pose"):
        check_viewpoints(Path("cap"), [turning[0]] * 2)


# --- messages that name the file at fault -------------------------------------------------------

def test_a_missing_idr_or_llff_photo_is_named_not_its_mask(photographed, tmp_path):
    import shutil

    from vq_mitsuba.data.captures import load_capture

    for fmt, images in (("neus", "image"), ("llff", "images")):
        folder = tmp_path / fmt
        shutil.copytree(photographed / fmt, folder)
        first = sorted((folder / images).iterdir())[0]
        first.unlink()
        with pytest.raises(InputError, match="image missing") as refused:
            load_capture(folder)
        assert refused.value.path == first


@pytest.mark.parametrize("fmt, image, mask", [
    ("colmap", "images/001.png", "masks/001.png.png"), ("colmap_opencv", "images/001.png", "masks/001.png.png"),
    ("llff", "images/001.png", "masks/001.png"), ("neus", "image/001.png", "mask/001.png"),
    ("nerfstudio", "images/001.png", "masks/001.png"), ("scene.xml", "images/train_001.exr", None),
    ("transforms_train.json", "images/train_001.exr", None),
])
def test_a_photo_missing_with_its_mask_is_named_as_a_missing_image(photographed, tmp_path, fmt, image, mask):
    """The photo gone with its mask: the other masks do not make it a missing mask, and a format that
    pairs views with photos in order (NeuS/IDR, LLFF) does not give the next photo its pose."""
    import shutil

    from vq_mitsuba.data.captures import load_capture

    folder = tmp_path / "cap"
    if fmt.endswith((".xml", ".json")):
        shutil.copytree(photographed, folder, ignore=shutil.ignore_patterns("colmap*", "llff", "neus", "nerfstudio"))
        (folder / image).with_suffix(".png").unlink()
    else:
        shutil.copytree(photographed / fmt, folder)
        (folder / mask).unlink()
    (folder / image).unlink()
    with pytest.raises(InputError) as refused:
        load_capture(folder / fmt if fmt.endswith((".xml", ".json")) else folder)
    assert refused.value.path == folder / image, refused.value
    assert "image" in refused.value.message and "mask" not in refused.value.message, refused.value


def test_an_odd_sized_idr_photo_is_blamed_not_the_others(photographed, tmp_path):
    import shutil

    from vq_mitsuba.data.captures import load_capture
    from vq_mitsuba.data.imageio import write_png

    folder = tmp_path / "neus"
    shutil.copytree(photographed / "neus", folder)
    first = sorted((folder / "image").iterdir())[0]
    write_png(first, np.full((20, 12, 3), 0.5))
    with pytest.raises(InputError, match="image is 12x20, but 2 of the 3 photos are 16x16") as refused:
        load_capture(folder)
    assert refused.value.path == first


@pytest.mark.parametrize("fmt, name", [("neus", "cameras_sphere.npz"), ("llff", "poses_bounds.npy")])
def test_random_bytes_for_numpy_files_are_not_called_a_pickle(photographed, tmp_path, fmt, name):
    import shutil

    from vq_mitsuba.data.captures import load_capture

    folder = tmp_path / fmt
    shutil.copytree(photographed / fmt, folder)
    (folder / name).write_bytes(np.random.default_rng(0).bytes(300))
    with pytest.raises(InputError, match=rf"not a valid \.{name[-3:]} file") as refused:
        load_capture(folder)
    assert refused.value.path == folder / name and "pickle" not in refused.value.message


def test_a_file_without_a_video_stream_is_refused_in_a_sentence(tmp_path):
    import subprocess

    import imageio_ffmpeg

    from vq_mitsuba.data.formats.video import pick_frames

    sound = tmp_path / "sound.mp4"
    subprocess.run([imageio_ffmpeg.get_ffmpeg_exe(), "-y", "-loglevel", "error", "-f", "lavfi", "-i", "sine=d=0.3",
                    "-c:a", "aac", str(sound)], check=True)
    with pytest.raises(InputError, match=r"holds no video stream \(only audio\)") as refused:
        pick_frames(sound, tmp_path / "frames", 3)
    assert refused.value.path == sound
    junk = tmp_path / "junk.mp4"
    junk.write_bytes(np.random.default_rng(1).bytes(200))
    with pytest.raises(InputError, match="ffmpeg cannot read the video: it holds no streams") as refused:
        pick_frames(junk, tmp_path / "frames", 3)
    assert refused.value.path == junk and not (tmp_path / "frames").exists()


def test_evaluation_knows_its_ground_truth_files_by_their_bytes(tmp_path):
    from vq_mitsuba.eval.evaluate import load_ground_truth
    from vq_mitsuba.data.imageio import write_exr, write_png

    for kind in ("basecolor", "metallic", "roughness"):
        write_exr(tmp_path / "gt" / f"v_{kind}.exr", np.full((4, 4, 3), 0.5, np.float32))
    write_exr(tmp_path / "images" / "v.exr", np.ones((4, 4, 4), np.float32))
    write_png(tmp_path / "gt" / "v_alpha.png", np.ones((4, 4)), srgb=False)
    assert load_ground_truth(tmp_path, "v")["mask"].all()
    metallic = tmp_path / "gt" / "v_metallic.exr"
    write_png(tmp_path / "photo.png", np.full((4, 4, 3), 0.5))
    metallic.write_bytes((tmp_path / "photo.png").read_bytes())  # a PNG under the EXR's name
    with pytest.raises(InputError, match="not an OpenEXR image.*a PNG file named .exr") as refused:
        load_ground_truth(tmp_path, "v")
    assert refused.value.path == metallic
    write_exr(metallic, np.full((4, 4, 3), 0.5, np.float32))
    alpha = tmp_path / "gt" / "v_alpha.png"
    alpha.write_bytes(metallic.read_bytes())  # an EXR under the PNG's name
    with pytest.raises(InputError, match="an OpenEXR file named .png") as refused:
        load_ground_truth(tmp_path, "v")
    assert refused.value.path == alpha
