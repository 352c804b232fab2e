"""Photographed captures: COLMAP and NeuS/IDR loaders, lens distortion, off-centre and non-square
cameras, downscale, background keying, held-out views."""

import json
import struct

import numpy as np
import pytest

from vq_mitsuba.data.cameras import Camera, camera_rays, look_at
from vq_mitsuba.errors import InputError


def _cameras(n=5, width=40, height=28):
    """Off-centre, non-square cameras around the origin."""
    out = []
    for i in range(n):
        a = 2 * np.pi * i / n
        eye = 2.5 * np.array([np.sin(a), 0.5, np.cos(a)])
        out.append(Camera(f"v{i}", look_at(eye, [0, 0, 0], [0, 1, 0]), 42.0, width, height,
                          principal=(width * 0.5 + 2.3 - i, height * 0.5 - 1.7 + 0.5 * i)))
    return out


def test_camera_rays_of_an_off_centre_non_square_camera_are_mitsubas():
    import drjit as dr
    import mitsuba as mi

    from vq_mitsuba.backend import init_mitsuba

    init_mitsuba()
    cam = _cameras(1)[0]
    sensor = mi.load_dict(cam.to_mitsuba_dict())
    h, w = cam.height, cam.width
    ys, xs = np.meshgrid(np.arange(h) + 0.5, np.arange(w) + 0.5, indexing="ij")
    film_uv = mi.Point2f(mi.Float((xs / w).ravel()), mi.Float((ys / h).ravel()))
    rays, _ = sensor.sample_ray(0.0, 0.5, film_uv, mi.Point2f(0.5, 0.5))
    d_mi = np.stack([np.array(rays.d.x), np.array(rays.d.y), np.array(rays.d.z)], -1)
    _, d_ours = camera_rays(cam)
    assert np.linalg.norm(d_mi.astype(np.float64) - d_ours, axis=-1).max() < 1e-5  # radians, float32 rays
    dr.eval()


def _round_trip_pixels(cam_a, cam_b, world_to_b=np.eye(4)):
    """Max pixel distance between where cam_a and cam_b (its copy, in the frame world_to_b) see
    points along cam_a's rays."""
    o, d = camera_rays(cam_a)
    pts = o + 1.7 * d
    pts_b = pts @ world_to_b[:3, :3].T + world_to_b[:3, 3]
    return float(np.abs(cam_a.project(pts) - cam_b.project(pts_b)).max())


def test_neus_and_colmap_files_give_the_same_rays(tmp_path):
    from vq_mitsuba.data.captures import load_cameras
    from vq_mitsuba.data.formats.colmap import read_colmap, write_colmap
    from vq_mitsuba.data.formats.idr import write_idr
    from vq_mitsuba.data.lens import Lens
    from vq_mitsuba.data.formats.common import moved_camera
    from vq_mitsuba.data.formats.copies import colmap_similarity

    cams = _cameras()
    cams[1] = Camera("v1", cams[1].to_world, 42.0, 40, 28, focal_y_ratio=1.07, principal=(18.2, 15.9))  # fx != fy
    # NeuS / IDR
    (tmp_path / "neus" / "image").mkdir(parents=True)
    write_idr(tmp_path / "neus" / "cameras_sphere.npz", cams, np.zeros(3), 1.0)
    from vq_mitsuba.data.imageio import write_png

    for i in range(len(cams)):
        write_png(tmp_path / "neus" / "image" / f"{i:03d}.png", np.full((28, 40, 3), 0.5))
    loaded, world, _ = load_cameras(tmp_path / "neus")
    assert world == "mitsuba" and len(loaded) == len(cams)
    for a, b in zip(cams, loaded):
        assert _round_trip_pixels(a, b) < 0.05
    # COLMAP binary and text, in a similarity frame
    sim = colmap_similarity()
    moved = [moved_camera(c, sim) for c in cams]
    for binary in (True, False):
        folder = tmp_path / f"colmap_{binary}"
        (folder / "images").mkdir(parents=True)
        write_colmap(folder / "sparse" / "0", moved, [f"{c.name}.png" for c in cams], binary=binary)
        loaded, _, _ = load_cameras(folder)
        assert [c.name for c in loaded] == [c.name for c in cams]
        for a, b in zip(cams, loaded):
            assert _round_trip_pixels(a, b, sim) < 0.05
    # the lens models' parameters come back as written
    lens = Lens("OPENCV", 40, 28, 30.0, 31.0, 20.5, 13.2, -0.1, 0.02, 0.001, -0.002)
    write_colmap(tmp_path / "m", cams[:1], ["a.png"], lens_of=lambda c: lens, binary=True)
    lenses, images = read_colmap(tmp_path / "m")
    assert lenses[1] == lens and images[0].name == "a.png"


def test_opencv_distortion_inverts_to_a_twentieth_of_a_pixel():
    from vq_mitsuba.data.lens import distort_image, Lens, undistort_image

    lens = Lens("OPENCV", 60, 44, 40.0, 41.0, 31.3, 20.8, -0.12, 0.03, 0.002, -0.0015)
    ys, xs = np.meshgrid(np.arange(44) + 0.5, np.arange(60) + 0.5, indexing="ij")
    u, v = lens.pixel_to_normalised(xs, ys)
    back = lens.normalised_to_pixel(*lens.undistort(*lens.distort(u, v)))
    assert max(np.abs(back[0] - xs).max(), np.abs(back[1] - ys).max()) < 0.05
    # a smooth image distorted then undistorted comes back inside the frame
    img = np.stack([np.sin(xs / 9.0) * 0.4 + 0.5, np.cos(ys / 7.0) * 0.4 + 0.5, (xs + ys) / 110.0], -1)
    again, inside = undistort_image(distort_image(img, lens), lens)
    core = inside.astype(bool)
    core[:4], core[-4:], core[:, :4], core[:, -4:] = False, False, False, False
    assert np.abs(again - img)[core].max() < 0.02


def _tiny_capture(tmp_path):
    """The three-sphere scene rendered with off-centre, non-square cameras, as a Mitsuba capture."""
    from tiny_scene import write_three_material_capture

    return write_three_material_capture(tmp_path / "xml", size=(40, 30), n_views=6, spp=16, principal_shift=(2.5, -1.5))


def _cropped(camera, window):
    """`camera` seeing the pixels x0..x1, y0..y1 of its image only."""
    from vq_mitsuba.data.cameras import camera_from_intrinsics

    x0, y0, x1, y1 = window
    fx, fy, cx, cy = camera.intrinsics()
    return camera_from_intrinsics(camera.name, camera.to_world, fx, fy, cx - x0, cy - y0, x1 - x0, y1 - y0)


def test_one_scene_through_every_format_gives_the_same_rays_and_pixels(tmp_path):
    from vq_mitsuba.data.captures import load_capture
    from vq_mitsuba.data.cameras import BLENDER_ENV_TO_WORLD
    from vq_mitsuba.data.formats.copies import format_frames, write_photo_formats
    from vq_mitsuba.data.formats.llff import llff_window

    xml = _tiny_capture(tmp_path)
    ref = load_capture(xml)
    assert ref.cameras[0].principal is not None and ref.width != ref.height
    folders = write_photo_formats(ref, tmp_path / "formats")
    assert set(folders) == {"neus", "colmap", "colmap_opencv", "nerfstudio", "llff"}
    assert (folders["nerfstudio"] / "transforms.json").is_file() and (folders["llff"] / "poses_bounds.npy").is_file()
    for name, folder in folders.items():
        cap = load_capture(folder, cache_dir=tmp_path / f"cache_{name}")
        frame = format_frames()[name]
        # LLFF's cameras are centred: its copy is the views cropped around their principal point
        window = llff_window(ref.cameras[0]) if name == "llff" else (0, 0, ref.width, ref.height)
        x0, y0, x1, y1 = window
        assert cap.has_alpha and cap.images.shape == (len(ref.cameras), y1 - y0, x1 - x0, 3), name
        for a, b in zip(ref.cameras, cap.cameras):
            assert _round_trip_pixels(_cropped(a, window), b, frame) < 0.05, name
        # the same pixels (8-bit PNG; the distorted copies are resampled twice, compared inside their frame)
        ref_images, ref_alpha = ref.images[:, y0:y1, x0:x1], ref.alpha[:, y0:y1, x0:x1]
        err = np.abs(cap.images - ref_images).mean(-1)
        inner = (cap.alpha > 0.99) & (ref_alpha > 0.99)
        inner[:, :3], inner[:, -3:], inner[:, :, :3], inner[:, :, -3:] = False, False, False, False
        assert np.median(err[inner]) < (0.03 if name in ("colmap_opencv", "nerfstudio") else 0.01), name
        # the envmap's up follows the cameras' up; nerfstudio's world is Z up, Blender's envmap frame
        up = np.asarray(cap.envmap_to_world)[:3, 1]
        assert up @ (frame[:3, :3] @ [0, 1, 0]) / np.linalg.norm(frame[:3, :3] @ [0, 1, 0]) > 0.9
        assert cap.world == ("blender" if name == "nerfstudio" else "mitsuba")
        if name == "nerfstudio":
            assert np.allclose(cap.envmap_to_world, BLENDER_ENV_TO_WORLD)
    # the undistorted photos are cached: a second load reads them back
    cache = tmp_path / "cache_colmap_opencv"
    assert len(list(cache.glob("*.npz"))) == len(ref.cameras)
    again = load_capture(folders["colmap_opencv"], cache_dir=cache)
    assert np.allclose(again.images, load_capture(folders["colmap_opencv"]).images, atol=2e-3)


def test_downscale_keying_and_holdout(tmp_path):
    from vq_mitsuba.config import CaptureConfig
    from vq_mitsuba.data.captures import load_capture
    from vq_mitsuba.data.imageio import write_png
    from vq_mitsuba.data.formats.idr import write_idr

    cams = _cameras(6, 40, 28)
    folder = tmp_path / "idr"
    for i in range(6):  # a grey backdrop (sRGB 0.5) with a bright square
        img = np.full((28, 40, 3), 0.2140, np.float32)  # linear of sRGB 0.5
        img[8:20, 10:30] = 0.9
        write_png(folder / "image" / f"{i:03d}.png", img)
    write_idr(folder / "cameras_sphere.npz", cams, np.zeros(3), 1.0)
    plain = load_capture(folder)
    assert not plain.has_alpha
    keyed = load_capture(folder, options=CaptureConfig(background_color="0.5,0.5,0.5"))
    assert keyed.has_alpha and keyed.alpha[0, 14, 20] == 1.0 and keyed.alpha[0, 2, 2] == 0.0
    half = load_capture(folder, options=CaptureConfig(downscale=2))
    assert half.images.shape[1:3] == (14, 20)
    pts = camera_rays(cams[0])[0][:1] + 2.0 * camera_rays(cams[0])[1][::97]
    assert np.abs(half.cameras[0].project(pts) - cams[0].project(pts) / 2).max() < 1e-6
    train = load_capture(folder, options=CaptureConfig(holdout=3), split="train")
    held = load_capture(folder, options=CaptureConfig(holdout=3), split="holdout")
    assert [c.name for c in held.cameras] == ["002", "005"] and len(train.cameras) == 4
    with pytest.raises(InputError, match="background"):
        load_capture(folder, options=CaptureConfig(background_color="0.9,0.9"))


def test_bad_photo_captures_are_named(tmp_path):
    from vq_mitsuba.data.captures import load_capture
    from vq_mitsuba.data.imageio import write_png
    from vq_mitsuba.data.formats.colmap import write_colmap
    from vq_mitsuba.data.formats.idr import write_idr

    cams = _cameras(3)
    idr = tmp_path / "idr"
    for i in range(3):
        write_png(idr / "image" / f"{i:03d}.png", np.full((28, 40, 3), 0.5))
    write_idr(idr / "cameras_sphere.npz", cams[:2], np.zeros(3), 1.0)
    with pytest.raises(InputError, match="world_mat_2"):
        load_capture(idr)
    write_idr(idr / "cameras_sphere.npz", cams, np.zeros(3), 1.0)
    write_png(idr / "mask" / "000.png", np.ones((28, 40)), srgb=False)
    with pytest.raises(InputError, match="1 masks for 3 images"):
        load_capture(idr)
    col = tmp_path / "colmap"
    write_colmap(col / "sparse" / "0", cams, ["a.png", "b.png", "c.png"], binary=True)
    with pytest.raises(InputError, match="images"):
        load_capture(col)
    for name in ("a.png", "b.png"):
        write_png(col / "images" / name, np.full((28, 40, 3), 0.5))
    write_png(col / "images" / "c.png", np.full((20, 40, 3), 0.5))
    with pytest.raises(InputError, match="c.png.*40x20 but its camera says 40x28"):
        load_capture(col)
    with open(col / "sparse" / "0" / "cameras.bin", "r+b") as f:  # camera 1 becomes FULL_OPENCV (id 6)
        f.seek(8 + 4)
        f.write(struct.pack("<i", 6))
    with pytest.raises(InputError, match="FULL_OPENCV is not supported"):
        load_capture(col)
    with open(col / "sparse" / "0" / "cameras.bin", "r+b") as f:  # back to PINHOLE
        f.seek(8 + 4)
        f.write(struct.pack("<i", 1))
    (col / "sparse" / "0" / "images.bin").write_bytes(b"\x05\x00")
    with pytest.raises(InputError, match="cannot read the COLMAP binary model"):
        load_capture(col)


def test_fit_with_holdout_scores_the_held_out_views(tmp_path, three_materials):
    from vq_mitsuba.cli import main

    capture, _ = three_materials
    run = tmp_path / "run"
    assert main(["fit", str(capture), "-o", str(run), "--holdout", "4", "--quiet",
                 "--set", "train.iterations=120", "--set", "vq.enabled=false"]) == 0
    assert json.loads((run / "run.json").read_text())["n_views"] == 8  # 10 views, 2 held out
    assert main(["eval", str(run), "--spp", "16", "--quiet"]) == 0
    metrics = json.loads((run / "metrics.json").read_text())
    assert [v["view"] for v in metrics["views"]] == ["view_03", "view_07"]
    assert 15.0 < metrics["novel_view"]["psnr"] < 60.0 and metrics["coverage_iou"] > 0.9
    # the held-out photos read smaller (--max-size): the same views, scored at 16 x 16
    small = tmp_path / "small.json"
    assert main(["eval", str(run), "--spp", "4", "--quiet", "--max-size", "16", "-o", str(small)]) == 0
    scored = json.loads(small.read_text())
    assert [v["view"] for v in scored["views"]] == ["view_03", "view_07"] and scored["novel_view"]["psnr"] > 15.0


@pytest.mark.slow  # over 10 s: CI runs it after the default suite (.ci/run)
def test_the_same_scene_fits_alike_from_every_photo_format(tmp_path):
    """COLMAP, COLMAP with a distorting lens, nerfstudio (per-frame distorting lenses, masks, read
    with --max-size) and LLFF (centred crops): the fitted basecolor at the same surface points agrees
    (the copies differ in coordinates, lens, size and resampling only; NeuS/IDR holds the COLMAP
    copy's pixels and cameras, test_one_scene_through_every_format_gives_the_same_rays_and_pixels)."""
    from vq_mitsuba.cli import main
    from vq_mitsuba.data.captures import load_capture
    from vq_mitsuba.run.run_dir import RunDir
    from vq_mitsuba.data.formats.copies import format_frames, write_photo_formats

    import torch

    from tiny_scene import THREE_MATERIALS, three_material_ids

    ref = load_capture(_tiny_capture(tmp_path))
    folders = write_photo_formats(ref, tmp_path / "formats")
    points = np.asarray(ref.mesh.vertices)[::7]
    truth = np.array([THREE_MATERIALS[k - 1][1] for k in three_material_ids(points)])
    fitted = {}
    for name in ("colmap", "colmap_opencv", "nerfstudio", "llff"):
        run = tmp_path / f"run_{name}"
        size = ["--max-size", "32"] if name == "nerfstudio" else []
        assert main(["fit", str(folders[name]), "-o", str(run), "--quiet", "--set", "train.iterations=200",
                     "--set", "vq.enabled=false", "--set", "train.batch_rays=512",
                     "--set", "residual.iterations=0"] + size) == 0
        if size:
            assert RunDir(run).config().capture.max_size == 32
        model = RunDir(run).load()
        frame = format_frames()[name]
        p = torch.tensor(points @ frame[:3, :3].T + frame[:3, 3], dtype=torch.float32)
        fitted[name] = model.materials_at(p)["basecolor"].numpy()
    # each fit lands near the truth up to the global scale the unknown light leaves open
    aligned, errors = {}, {}
    for name, bc in fitted.items():
        aligned[name] = bc * (bc * truth).sum() / (bc * bc).sum()
        errors[name] = float(np.median(np.abs(aligned[name] - truth)))
        assert errors[name] < 0.08, name
    # and the formats agree with the COLMAP copy at least as closely as with the truth
    for name in ("colmap_opencv", "nerfstudio", "llff"):
        between = float(np.median(np.abs(aligned[name] - aligned["colmap"])))
        assert between < max(errors["colmap"], errors[name], 0.02), (name, between, errors)


def test_reconstruction_refused_without_masks_says_what_is_needed(tmp_path, capsys):
    """With neus.background masks (auto reconstructs without them: tests/geometry/test_maskfree.py)."""
    from vq_mitsuba.cli import main
    from vq_mitsuba.data.imageio import write_png
    from vq_mitsuba.data.formats.idr import write_idr

    cams = _cameras(3)
    for i in range(3):
        write_png(tmp_path / "idr" / "image" / f"{i:03d}.png", np.full((28, 40, 3), 0.5))
    write_idr(tmp_path / "idr" / "cameras_sphere.npz", cams, np.zeros(3), 1.0)
    assert main(["fit", str(tmp_path / "idr"), "-o", str(tmp_path / "run"), "--quiet",
                 "--set", "neus.background=masks"]) == 2
    err = capsys.readouterr().err
    assert "neus.background is masks" in err and "--background-color" in err and "mask/" in err


# --------------------------------------------------------------------------------------------
# What the camera files say is checked before any work: one InputError naming the file and entry

def _colmap(folder, binary, lens=None, names=("a.png", "b.png", "c.png"), images=True):
    """A three-view COLMAP capture (sparse/0 and, when asked, 40x28 photos); `lens` for the first
    view (camera 1), a plausible one of its model for the others."""
    from vq_mitsuba.data.imageio import write_png
    from vq_mitsuba.data.formats.colmap import write_colmap
    from vq_mitsuba.data.lens import Lens

    def lens_of(camera):
        return lens if camera.name == "v0" else Lens(lens.model, 40, 28, 30.0, 30.0, 20.5, 13.2)

    model = folder / "sparse" / "0"
    write_colmap(model, _cameras(3), list(names), lens_of=None if lens is None else lens_of, binary=binary)
    (folder / "images").mkdir(parents=True, exist_ok=True)
    for name in names if images else ():
        write_png(folder / "images" / name, np.full((28, 40, 3), 0.5))
    return model


def _refused(call, path, *parts):
    with pytest.raises(InputError) as info:
        call()
    assert info.value.path == path, (info.value.path, path)
    for part in parts:
        assert part in info.value.message, (part, info.value.message)
    return info.value


@pytest.mark.parametrize("binary", [True, False])
@pytest.mark.parametrize("model, field, value, message", [
    ("OPENCV", "fx", float("nan"), "fx = nan is not a finite number"),
    ("OPENCV", "k1", float("nan"), "k1 = nan is not a finite number"),
    ("OPENCV", "p2", float("inf"), "p2 = inf is not a finite number"),
    ("OPENCV", "cy", float("-inf"), "cy = -inf is not a finite number"),
    ("PINHOLE", "fy", float("nan"), "fy = nan is not a finite number"),
    ("PINHOLE", "fx", 0.0, "focal length fx = 0 must be positive"),
    ("SIMPLE_PINHOLE", "fx", -30.0, "focal length fx = -30 must be positive"),
    ("PINHOLE", "fx", 1e-3, "field of view"),
    ("PINHOLE", "cx", 500.0, "principal point cx = 500 lies far outside"),
    ("OPENCV", "k1", 50.0, "implausible distortion"),
    ("RADIAL", "k2", -40.0, "implausible distortion"),
    ("SIMPLE_RADIAL", "k1", -3.0, "implausible distortion"),
])
def test_bad_colmap_intrinsics_are_refused_before_any_work(tmp_path, binary, model, field, value, message):
    from dataclasses import replace

    from vq_mitsuba.data.captures import load_capture
    from vq_mitsuba.data.lens import Lens

    lens = replace(Lens(model, 40, 28, 30.0, 30.0, 20.5, 13.2), **{field: value})
    if model.startswith("SIMPLE"):
        lens = replace(lens, fy=lens.fx)
    sparse = _colmap(tmp_path, binary, lens)
    cache = tmp_path / "undistorted"
    _refused(lambda: load_capture(tmp_path, cache_dir=cache), sparse / f"cameras.{'bin' if binary else 'txt'}",
             f"camera 1 ({model})", message)
    assert not cache.exists()  # nothing written before the check


def test_colmap_camera_lines_of_the_wrong_length_or_listed_twice_are_refused(tmp_path):
    from vq_mitsuba.data.captures import load_cameras

    sparse = _colmap(tmp_path, binary=False, images=False)
    text = (sparse / "cameras.txt").read_text()
    lines = text.splitlines()
    (sparse / "cameras.txt").write_text("\n".join(lines[:1] + [lines[1] + " 0.5"] + lines[2:]) + "\n")
    _refused(lambda: load_cameras(tmp_path), sparse / "cameras.txt", "camera 1: PINHOLE has 4 parameters", "got 5")
    (sparse / "cameras.txt").write_text("\n".join(lines[:1] + [" ".join(lines[1].split()[:-1])] + lines[2:]) + "\n")
    _refused(lambda: load_cameras(tmp_path), sparse / "cameras.txt", "got 3")
    (sparse / "cameras.txt").write_text(text + lines[2] + "\n")
    _refused(lambda: load_cameras(tmp_path), sparse / "cameras.txt", "camera id 2 is listed 2 times")
    (sparse / "cameras.txt").write_text(text.replace(" PINHOLE 40 ", " PINHOLE forty ", 1))
    _refused(lambda: load_cameras(tmp_path), sparse / "cameras.txt", "line 2", "is not CAMERA_ID MODEL")


def _patch_first_image(model, binary, qvec=None, tvec=None, camera_id=None):
    """Overwrite the first image entry's quaternion, translation or camera id in place."""
    if binary:  # <Q count> then <i id, 4d qvec, 3d tvec, i camera_id> name\0 ...
        raw = bytearray((model / "images.bin").read_bytes())
        for offset, fmt, value in ((12, "<4d", qvec), (44, "<3d", tvec), (68, "<i", camera_id)):
            if value is not None:
                struct.pack_into(fmt, raw, offset, *np.atleast_1d(value))
        (model / "images.bin").write_bytes(bytes(raw))
        return
    lines = (model / "images.txt").read_text().splitlines()
    parts = lines[1].split()
    for start, value in ((1, qvec), (5, tvec), (8, camera_id)):
        if value is not None:
            values = np.atleast_1d(value)
            parts[start:start + len(values)] = [str(v) for v in values]
    (model / "images.txt").write_text("\n".join(lines[:1] + [" ".join(parts)] + lines[2:]) + "\n")


@pytest.mark.parametrize("binary", [True, False])
@pytest.mark.parametrize("patch, message", [
    ({"qvec": [np.nan, 0, 0, 1]}, "quaternion (QW, QX, QY, QZ) = (nan, 0, 0, 1) is not a rotation"),
    ({"qvec": [0, 0, 0, 0]}, "quaternion (QW, QX, QY, QZ) = (0, 0, 0, 0) is not a rotation"),
    ({"tvec": [0, np.inf, 1]}, "translation (TX, TY, TZ) = (0, inf, 1) is not finite"),
    ({"tvec": [0, 1e300, 1]}, "units from the origin"),
    ({"camera_id": 9}, "refers to camera 9, which cameras"),
])
def test_bad_colmap_images_are_refused(tmp_path, binary, patch, message):
    from vq_mitsuba.data.captures import load_cameras

    model = _colmap(tmp_path, binary, images=False)
    _patch_first_image(model, binary, **patch)
    _refused(lambda: load_cameras(tmp_path), model / f"images.{'bin' if binary else 'txt'}", "image 1 ('a.png')",
             message)


@pytest.mark.parametrize("binary", [True, False])
def test_a_colmap_image_listed_twice_is_refused_not_an_extra_view(tmp_path, binary):
    from vq_mitsuba.data.captures import load_capture

    model = _colmap(tmp_path, binary, names=("a.png", "b.png", "a.png"))
    _refused(lambda: load_capture(tmp_path), model / f"images.{'bin' if binary else 'txt'}",
             "image name a.png is listed 2 times")


def test_every_problem_of_a_colmap_model_is_reported_at_once(tmp_path):
    from dataclasses import replace

    from vq_mitsuba.data.captures import load_cameras
    from vq_mitsuba.data.lens import Lens

    model = _colmap(tmp_path, True, replace(Lens("PINHOLE", 40, 28, 30.0, 30.0, 20.5, 13.2), fx=np.nan),
                    images=False)
    _patch_first_image(model, True, qvec=[0, 0, 0, 0])
    message = _refused(lambda: load_cameras(tmp_path), model, "problems in this capture").message
    assert "2 problems" in message and "cameras.bin: camera 1 (PINHOLE): fx = nan" in message
    assert "images.bin: image 1 ('a.png'): quaternion" in message


@pytest.mark.parametrize("name, damage", [
    ("cameras.bin", lambda raw: raw[:30]),  # truncated inside the first camera
    ("cameras.bin", lambda raw: b""),
    ("images.bin", lambda raw: raw[:-9]),  # truncated inside the last entry
    ("images.bin", lambda raw: raw[:8] + b"\xff" * 40),  # garbled
])
def test_broken_colmap_binaries_are_named_by_file(tmp_path, name, damage):
    from vq_mitsuba.data.captures import load_cameras

    model = _colmap(tmp_path, True, images=False)
    (model / name).write_bytes(damage((model / name).read_bytes()))
    _refused(lambda: load_cameras(tmp_path), model / name, "cannot read the COLMAP binary model")


def _idr(folder, n=3, **entries):
    """A NeuS/IDR capture of n 40x28 views whose archive entries `entries` replace (None: removed)."""
    from vq_mitsuba.data.imageio import write_png
    from vq_mitsuba.data.formats.idr import write_idr

    for i in range(n):
        write_png(folder / "image" / f"{i:03d}.png", np.full((28, 40, 3), 0.5))
    npz = folder / "cameras_sphere.npz"
    write_idr(npz, _cameras(n), np.zeros(3), 1.0)
    data = dict(np.load(npz))
    data.update(entries)
    np.savez(npz, **{k: v for k, v in data.items() if v is not None})
    return npz


def _rank_two():
    m = np.eye(4)
    m[2, :3] = m[0, :3] + m[1, :3]
    return m


@pytest.mark.parametrize("entries, message", [
    ({"world_mat_1": np.eye(3)}, "world_mat_1 has shape (3, 3); expected 3x4 or 4x4"),
    ({"world_mat_1": np.array("a string")}, "world_mat_1 holds <U8 values, not numbers"),
    ({"world_mat_1": np.array([np.eye(4), "x"], dtype=object)}, "world_mat_1 is an array of Python objects"),
    ({"world_mat_1": np.full((4, 4), np.nan)}, "world_mat_1 holds non-finite values"),
    ({"world_mat_1": np.zeros((4, 4))}, "world_mat_1 is singular"),
    ({"world_mat_1": _rank_two()}, "world_mat_1 is singular"),
    ({"world_mat_2": None}, "has no world_mat_2, but the capture has 3 images"),
    ({"scale_mat_0": np.eye(3)}, "scale_mat_0 has shape (3, 3); expected 4x4"),
    ({"scale_mat_0": np.diag([0.0, 0, 0, 1])}, "scale_mat_0 is singular"),
    ({"scale_mat_0": np.diag([1.0, np.inf, 1, 1])}, "scale_mat_0 holds non-finite values"),
])
def test_bad_neus_matrices_are_refused(tmp_path, entries, message):
    from vq_mitsuba.data.captures import load_cameras

    npz = _idr(tmp_path, **entries)
    _refused(lambda: load_cameras(tmp_path), npz, message)


def test_neus_intrinsics_and_poses_are_checked_and_a_plain_array_is_not_an_archive(tmp_path):
    from vq_mitsuba.data.captures import load_cameras

    far = np.load(_idr(tmp_path / "far"))["world_mat_0"].copy()
    far[:3, 3] *= 1e9  # the camera moves 1e9 units away
    _refused(lambda: load_cameras(tmp_path / "far"), _idr(tmp_path / "far", world_mat_0=far), "world_mat_0",
             "units from the origin")
    tele = np.diag([1e9, 1e9, 1.0, 1.0]) @ np.load(_idr(tmp_path / "tele"))["world_mat_1"]  # fx = 1e9 pixels
    _refused(lambda: load_cameras(tmp_path / "tele"), _idr(tmp_path / "tele", world_mat_1=tele), "world_mat_1",
             "field of view")
    npz = _idr(tmp_path / "plain")
    np.save(tmp_path / "plain" / "array.npy", np.eye(4))
    (tmp_path / "plain" / "array.npy").replace(npz)
    _refused(lambda: load_cameras(tmp_path / "plain"), npz, "not an .npz archive")


def test_a_neus_capture_with_images_and_masks_folders_loads_its_masks(tmp_path):
    """Copies of DTU made for other tools name the NeuS folders images/ and masks/."""
    from vq_mitsuba.data.captures import load_capture
    from vq_mitsuba.data.imageio import write_png
    from vq_mitsuba.data.formats.idr import write_idr

    cams = _cameras(3)
    (tmp_path / "images").mkdir()
    (tmp_path / "masks").mkdir()
    write_idr(tmp_path / "cameras_sphere.npz", cams, np.zeros(3), 1.0)
    for i in range(len(cams)):
        write_png(tmp_path / "images" / f"{i:03d}.png", np.full((28, 40, 3), 0.5))
        mask = np.zeros((28, 40, 3))
        mask[5:20, 10:30] = 1.0
        write_png(tmp_path / "masks" / f"{i:03d}.png", mask)
    capture = load_capture(tmp_path)
    assert capture.has_alpha and len(capture.cameras) == 3
    assert capture.alpha[:, 5:20, 10:30].min() > 0.99 and capture.alpha[:, :5].max() < 0.01
    write_png(tmp_path / "masks" / "003.png", np.zeros((28, 40, 3)))
    with pytest.raises(InputError, match="4 masks for 3 images in images/"):
        load_capture(tmp_path)
