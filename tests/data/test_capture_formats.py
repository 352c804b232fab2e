"""nerfstudio transforms.json and LLFF poses_bounds.npy captures (axes, intrinsics, lenses, masks,
bad files named), and photos shrunk as they are read (capture.max_size, --downscale, --max-size)."""

import json

import numpy as np
import pytest

from vq_mitsuba.data.cameras import Camera, camera_to_nerf, look_at
from vq_mitsuba.data.imageio import write_png
from vq_mitsuba.errors import InputError

from test_photo_captures import _refused  # one check of a refusal for every capture loader


def _cameras(n=3, width=40, height=28, centred=False):
    """Cameras around the origin; off-centre principal points unless `centred`."""
    out = []
    for i in range(n):
        a = 2 * np.pi * i / n
        eye = 2.5 * np.array([np.sin(a), 0.5, np.cos(a)])
        principal = None if centred else (width * 0.5 + 2.3 - i, height * 0.5 - 1.7 + 0.5 * i)
        out.append(Camera(f"v{i}", look_at(eye, [0, 0, 0], [0, 1, 0]), 42.0, width, height, principal=principal))
    return out


def _max_pixel_error(cam_a, cam_b, scale=(1.0, 1.0)):
    """Max distance between where cam_b sees points and where cam_a does, cam_a's pixels scaled."""
    from vq_mitsuba.data.cameras import camera_rays

    o, d = camera_rays(cam_a)
    pts = o + 1.7 * d
    return float(np.abs(cam_a.project(pts) * np.asarray(scale) - cam_b.project(pts)).max())


def _smooth(width, height, seed=0):
    ys, xs = np.meshgrid(np.arange(height) + 0.5, np.arange(width) + 0.5, indexing="ij")
    return np.stack([np.sin(xs / 9.0 + seed) * 0.4 + 0.5, np.cos(ys / 7.0) * 0.4 + 0.5,
                     (xs + ys) / (width + height)], -1).astype(np.float32)


# --------------------------------------------------------------------------------------------
# LLFF

def test_llff_axes_are_llffs_own_and_the_focal_scales_with_the_photos(tmp_path):
    from vq_mitsuba.data.captures import capture_kind, load_capture, load_cameras, resolve_capture_path
    from vq_mitsuba.data.formats.llff import llff_to_world, world_to_llff, write_poses_bounds

    cams = _cameras(3, 40, 28, centred=True)
    for cam in cams:
        pose = world_to_llff(cam.to_world, 28, 40, cam.focal_px())
        # LLFF's loader: [x, y, z] = [pose[:, 1], -pose[:, 0], pose[:, 2]] is OpenGL's camera-to-world
        opengl = np.concatenate([pose[:, 1:2], -pose[:, 0:1], pose[:, 2:4]], 1)
        assert np.allclose(opengl, camera_to_nerf(cam)[0][:3, :4])
        assert np.allclose(pose[:, 0], -cam.to_world[:3, 1])  # the first column points down
        assert np.allclose(llff_to_world(pose), cam.to_world)
    # the file's poses are for 40 x 28 images; images/ holds them at twice that: the focal doubles
    folder = tmp_path / "llff"
    write_poses_bounds(folder / "poses_bounds.npy", cams, [(0.5, 5.0)] * 3)
    for i in range(3):
        write_png(folder / "images" / f"IMG_{i:04d}.JPG.png", _smooth(80, 56, i))
    source = resolve_capture_path(folder)
    assert source.name == "poses_bounds.npy" and capture_kind(source) == "llff"
    loaded, world, _ = load_cameras(folder)
    assert world == "mitsuba" and [c.name for c in loaded] == [f"IMG_{i:04d}.JPG" for i in range(3)]
    for a, b in zip(cams, loaded):
        assert (b.width, b.height) == (80, 56) and _max_pixel_error(a, b, (2.0, 2.0)) < 1e-6
    # without images/, the least reduced images_N/ is read
    (folder / "images").rename(folder / "images_4")
    capture = load_capture(folder)
    assert capture.images.shape == (3, 56, 80, 3) and not capture.has_alpha
    # masks/ by stem, any image type: multiplied into alpha
    for i in range(3):
        write_png(folder / "masks" / f"IMG_{i:04d}.JPG.png", np.full((56, 80), 0.5), srgb=False)
    masked = load_capture(folder)
    assert masked.has_alpha and abs(float(masked.alpha.mean()) - 0.5) < 0.01


def _llff(folder, rows=None, n_images=3, masks=0):
    """An LLFF folder of three 40 x 28 views; `rows` replaces the poses_bounds array."""
    from vq_mitsuba.data.formats.llff import write_poses_bounds

    npy = folder / "poses_bounds.npy"
    write_poses_bounds(npy, _cameras(3, centred=True), [(0.5, 5.0)] * 3)
    if rows is not None:
        np.save(npy, rows(np.load(npy)), allow_pickle=True)
    for i in range(n_images):
        write_png(folder / "images" / f"{i:03d}.png", np.full((28, 40, 3), 0.5))
    for i in range(masks):
        write_png(folder / "masks" / f"{i:03d}.png", np.ones((28, 40)), srgb=False)
    return npy


def _set(index, value):
    def change(a):
        a = a.copy()
        a[index] = value
        return a
    return change


@pytest.mark.parametrize("rows, phrases", [
    (lambda a: a[:, :15], ("has shape (3, 15); expected N x 17",)),
    (lambda a: a.ravel(), ("has shape (51,)",)),
    (lambda a: np.array([a, "x"], dtype=object), ("array of Python objects (a pickle)",)),
    (lambda a: a.astype(str), ("values, not numbers",)),
    (_set((1, 7), np.nan), ("row 1 holds non-finite values",)),
    (_set((2, 14), -5.0), ("row 2: focal length -5 must be positive",)),
    (_set((0, 16), 0.1), ("row 0: bounds near = 0.5, far = 0.1",)),
    (_set((0, 4), 27.5), ("row 0 (height, width): image height 27.5",)),
    (_set((1, 3), 1e9), ("row 1", "units from the origin")),
    (lambda a: a[:2], ("holds 2 poses for 3 images in images/",)),
    (_set((0, 9), 20.0), ("row 0 (000.png): the photos are 40x28 but the pose is for 20x28 images",)),
])
def test_bad_llff_poses_are_refused(tmp_path, rows, phrases):
    from vq_mitsuba.data.captures import load_cameras

    npy = _llff(tmp_path, rows)
    _refused(lambda: load_cameras(tmp_path), npy, *phrases)


def test_llff_masks_and_files_that_are_no_array_are_refused(tmp_path):
    from vq_mitsuba.data.captures import load_capture

    _llff(tmp_path / "a", masks=2)
    _refused(lambda: load_capture(tmp_path / "a"), tmp_path / "a" / "masks" / "002.png", "mask missing",
             "images/002.png has no mask")
    _llff(tmp_path / "b", masks=3)
    (tmp_path / "b" / "masks" / "002.png").rename(tmp_path / "b" / "masks" / "other.png")
    _refused(lambda: load_capture(tmp_path / "b"), tmp_path / "b" / "masks", "has no mask for 002.png")
    npy = _llff(tmp_path / "c")
    np.savez(tmp_path / "c" / "archive.npz", poses=np.eye(4))
    (tmp_path / "c" / "archive.npz").replace(npy)
    _refused(lambda: load_capture(tmp_path / "c"), npy, "is an .npz archive")
    npy.write_bytes(b"\x93NUMPY garbage")
    _refused(lambda: load_capture(tmp_path / "c"), npy, "cannot read")
    npy = _llff(tmp_path / "d", n_images=0)
    _refused(lambda: load_capture(tmp_path / "d"), tmp_path / "d" / "images", "no images")


# --------------------------------------------------------------------------------------------
# nerfstudio transforms.json

def _nerfstudio(folder, frames_extra=None, top_extra=None, images=True, size=(40, 28)):
    """A three-frame transforms.json of `_cameras` (global intrinsics of view 0, per-frame of the
    others), 40 x 28 photos; `frames_extra[i]` / `top_extra` update frame i / the top level."""
    cams = _cameras(3)
    frames = []
    for i, cam in enumerate(cams):
        fx, fy, cx, cy = cam.intrinsics()
        frame = {"file_path": f"images/{cam.name}.png", "transform_matrix": camera_to_nerf(cam)[0].tolist()}
        if i > 0:
            frame.update({"fl_x": fx, "fl_y": fy, "cx": cx, "cy": cy})
        frame.update((frames_extra or {}).get(i, {}))
        frames.append(frame)
    fx, fy, cx, cy = cams[0].intrinsics()
    data = {"camera_model": "OPENCV", "fl_x": fx, "fl_y": fy, "cx": cx, "cy": cy, "w": 40, "h": 28,
            "frames": frames, **(top_extra or {})}
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "transforms.json").write_text(json.dumps(data))
    for i, cam in enumerate(cams if images else ()):
        write_png(folder / "images" / f"{cam.name}.png", _smooth(*size, i))
    return folder / "transforms.json", cams


def test_nerfstudio_intrinsics_per_frame_or_global_and_masks(tmp_path):
    from vq_mitsuba.data.captures import load_capture, load_cameras, resolve_capture_path

    path, cams = _nerfstudio(tmp_path / "ns", {1: {"mask_path": "m/1.png"}, 0: {"mask_path": "m/0.png"},
                                               2: {"mask_path": "m/2.png", "camera_model": "PINHOLE"}},
                             {"applied_transform": np.eye(4)[:3].tolist(), "w": None, "h": None})
    for i in range(3):
        write_png(tmp_path / "ns" / "m" / f"{i}.png", np.full((28, 40), 0.25 * (i + 1)), srgb=False)
    assert resolve_capture_path(tmp_path / "ns") == path
    capture = load_capture(tmp_path / "ns")
    assert capture.world == "blender" and capture.has_alpha and capture.images.shape == (3, 28, 40, 3)
    assert np.allclose(capture.alpha.mean((1, 2)), [0.25, 0.5, 0.75], atol=0.01)
    for a, b in zip(cams, capture.cameras):
        assert b.name == a.name and _max_pixel_error(a, b) < 1e-6
    only, world, _ = load_cameras(path)  # 'w' / 'h' missing: read from the photos
    assert world == "blender" and all(_max_pixel_error(a, b) < 1e-6 for a, b in zip(cams, only))
    # instant-ngp style: camera_angle_x for the focal length, no fl_y: fy = fx, a centred principal point
    path, cams = _nerfstudio(tmp_path / "ngp", {i: {"fl_x": None, "fl_y": None, "cx": None, "cy": None}
                                                for i in range(3)})
    data = json.loads(path.read_text())
    for frame in data["frames"]:
        for key in ("fl_x", "fl_y", "cx", "cy"):
            del frame[key]
    for key in ("fl_x", "fl_y", "cx", "cy"):
        del data[key]
    data["camera_angle_x"] = np.radians(42.0)
    data["camera_model"] = "PINHOLE"
    path.write_text(json.dumps(data))
    ngp, _, _ = load_cameras(path)
    centred = [Camera(c.name, c.to_world, 42.0, 40, 28) for c in cams]
    assert all(_max_pixel_error(a, b) < 1e-6 for a, b in zip(centred, ngp))


def test_nerfstudio_fisheye_photos_are_undistorted_into_their_pinhole_camera(tmp_path):
    from vq_mitsuba.data.captures import load_capture
    from vq_mitsuba.data.formats.nerfstudio import write_transforms_json
    from vq_mitsuba.data.formats.colmap import read_colmap, write_colmap
    from vq_mitsuba.data.lens import distort_image, Lens

    lens = Lens("OPENCV_FISHEYE", 60, 44, 40.0, 41.0, 31.3, 20.8, k1=0.05, k2=-0.01, k3=0.002)
    assert lens.distorted
    ys, xs = np.meshgrid(np.arange(44) + 0.5, np.arange(60) + 0.5, indexing="ij")
    u, v = lens.pixel_to_normalised(xs, ys)
    back = lens.normalised_to_pixel(*lens.undistort(*lens.distort(u, v)))
    assert max(np.abs(back[0] - xs).max(), np.abs(back[1] - ys).max()) < 0.05
    # a photo through the fisheye, read back as the pinhole camera sees it
    cams = [Camera("f0", look_at([0, 0, 3], [0, 0, 0], [0, 1, 0]), 10.0, 60, 44)]
    pinhole = _smooth(60, 44)
    write_png(tmp_path / "ns" / "images" / "f0.png", distort_image(pinhole, lens))
    write_transforms_json(tmp_path / "ns" / "transforms.json", cams, ["images/f0.png"], [lens])
    capture = load_capture(tmp_path / "ns", cache_dir=tmp_path / "cache")
    assert capture.cameras[0].intrinsics() == pytest.approx((40.0, 41.0, 31.3, 20.8))
    core = capture.alpha[0] > 0.99
    core[:4], core[-4:], core[:, :4], core[:, -4:] = False, False, False, False
    assert core.mean() > 0.5 and np.abs(capture.images[0] - pinhole)[core].max() < 0.03
    assert len(list((tmp_path / "cache").glob("*.npz"))) == 1
    # COLMAP's OPENCV_FISHEYE (model 5) reads back too
    write_colmap(tmp_path / "m", cams, ["f0.png"], lens_of=lambda c: lens, binary=True)
    assert read_colmap(tmp_path / "m")[0][1] == lens


@pytest.mark.parametrize("frames_extra, top_extra, phrases", [
    ({}, {"fl_x": None}, ("frames[0] (images/v0.png): no focal length: 'fl_x' is missing",)),
    ({1: {"fl_x": float("nan")}}, {}, ("frames[1] (images/v1.png): 'fl_x' = nan is not a finite number",)),
    ({}, {"fl_y": "40"}, ("frames[0] (images/v0.png): 'fl_y' = '40' is not a finite number",)),
    ({2: {"camera_model": "EQUIRECTANGULAR"}}, {}, ("frames[2]", "camera_model 'EQUIRECTANGULAR' is not supported",)),
    ({}, {"w": 0}, ("frames[0] (images/v0.png): 'w' and 'h': image width 0",)),
    ({1: {"k1": 50.0}}, {}, ("frames[1]", "implausible distortion",)),
    ({1: {"k3": float("inf")}}, {}, ("frames[1] (images/v1.png): 'k3' = inf is not a finite number",)),
    ({2: {"cx": 500.0}}, {}, ("frames[2]", "principal point cx = 500 lies far outside",)),
    ({1: {"fl_x": 1e-3}}, {}, ("frames[1]", "field of view",)),
    ({}, {"applied_transform": [[1, 0], [0, 1]]}, ("'applied_transform' must be a 3x4 or 4x4 matrix",)),
    ({0: {"mask_path": "m.png"}}, {}, ("frames[1] (images/v1.png) has no 'mask_path' but frames[0] has one",)),
    ({1: {"mask_path": 3}}, {}, ("frames[1] (images/v1.png): 'mask_path' must be a file path",)),
    ({1: {"transform_matrix": [[1, 0, 0]]}}, {}, ("frames[1] (images/v1.png): malformed transform_matrix",)),
    ({0: {"file_path": ""}}, {}, ("frames[0] has no 'file_path'",)),
])
def test_bad_nerfstudio_json_is_refused_naming_the_frame(tmp_path, frames_extra, top_extra, phrases):
    from vq_mitsuba.data.captures import load_capture

    path, _ = _nerfstudio(tmp_path, frames_extra, {k: v for k, v in top_extra.items() if v is not None})
    if any(v is None for v in top_extra.values()):
        data = json.loads(path.read_text())
        for key in (k for k, v in top_extra.items() if v is None):
            del data[key]
        path.write_text(json.dumps(data))
    _refused(lambda: load_capture(tmp_path), path, *phrases)


def test_nerfstudio_photos_and_masks_that_do_not_fit_their_frames_are_named(tmp_path):
    from vq_mitsuba.data.captures import load_capture

    _nerfstudio(tmp_path / "a", size=(40, 30))
    _refused(lambda: load_capture(tmp_path / "a"), tmp_path / "a" / "transforms.json", "3 problems",
             "v0.png: image is 40x30 but its camera says 40x28")
    _nerfstudio(tmp_path / "b", {i: {"mask_path": f"masks/{i}.png"} for i in range(3)})
    for i in (0, 1):
        write_png(tmp_path / "b" / "masks" / f"{i}.png", np.ones((28, 40)), srgb=False)
    _refused(lambda: load_capture(tmp_path / "b"), tmp_path / "b" / "masks" / "2.png", "mask file not found")
    path, _ = _nerfstudio(tmp_path / "c", images=False)
    with pytest.raises(InputError) as info:
        load_capture(tmp_path / "c")
    assert "v0.png" in str(info.value) and "v2.png" in str(info.value)  # every missing photo at once


# --------------------------------------------------------------------------------------------
# Photos shrunk as they are read

def test_area_resize_is_the_exact_area_mean():
    from vq_mitsuba.data.resize import Shrink, area_resize

    rng = np.random.default_rng(0)
    image = rng.random((30, 40, 3)).astype(np.float32)
    assert np.allclose(area_resize(image, 20, 15), image.reshape(15, 2, 20, 2, 3).mean((1, 3)), atol=1e-6)
    odd = area_resize(image, 17, 13)  # non-integer ratios: each output pixel a weighted mean
    assert odd.shape == (13, 17, 3) and abs(float(odd.mean() - image.mean())) < 1e-5
    w = 40 / 17  # output pixel (0, 0) covers input columns [0, w) and rows [0, 30 / 13)
    h = 30 / 13
    wx = np.clip(np.minimum(np.arange(40) + 1, w) - np.arange(40), 0, 1)
    wy = np.clip(np.minimum(np.arange(30) + 1, h) - np.arange(30), 0, 1)
    assert np.allclose(odd[0, 0], (wy[:, None, None] * wx[None, :, None] * image).sum((0, 1)) / (w * h), atol=1e-5)
    assert Shrink(1, 16).size(40, 28) == (16, 11) and Shrink(2, 16).size(40, 28) == (16, 11)
    assert Shrink(1, 16).size(28, 40) == (11, 16) and Shrink(1, 64).size(40, 28) == (40, 28)
    with pytest.raises(InputError, match="capture.max_size 4 leaves 4x3 pixels of 40x28 images"):
        Shrink(1, 4).size(40, 28)


@pytest.mark.parametrize("kind", ["json", "idr", "nerfstudio", "llff"])
def test_max_size_shrinks_each_photo_and_its_camera_alike(tmp_path, kind):
    from vq_mitsuba.config import CaptureConfig
    from vq_mitsuba.data.captures import load_capture, load_cameras
    from vq_mitsuba.data.formats.idr import write_idr
    from vq_mitsuba.data.resize import area_resize

    cams = _cameras(3, 60, 42, centred=kind in ("json", "llff"))
    folder = tmp_path / kind
    for i in range(3):
        write_png(folder / "images" / f"{cams[i].name}.png", _smooth(60, 42, i))
    if kind == "json":
        folder.joinpath("transforms_train.json").write_text(json.dumps({
            "camera_angle_x": np.radians(42.0), "frames": [
                {"file_path": f"images/{c.name}", "transform_matrix": camera_to_nerf(c)[0].tolist()} for c in cams]}))
    elif kind == "idr":
        (folder / "images").rename(folder / "image")
        write_idr(folder / "cameras_sphere.npz", cams, np.zeros(3), 1.0)
    elif kind == "nerfstudio":
        from vq_mitsuba.data.formats.nerfstudio import write_transforms_json
        from vq_mitsuba.data.lens import Lens

        write_transforms_json(folder / "transforms.json", cams, [f"images/{c.name}.png" for c in cams],
                              [Lens("PINHOLE", 60, 42, *c.intrinsics()) for c in cams])
    else:
        from vq_mitsuba.data.formats.llff import write_poses_bounds

        write_poses_bounds(folder / "poses_bounds.npy", cams, [(0.5, 5.0)] * 3)
    full = load_capture(folder)
    for options, (w, h) in ((CaptureConfig(max_size=25), (25, 18)), (CaptureConfig(downscale=2, max_size=25), (25, 18)),
                            (CaptureConfig(downscale=2), (30, 21))):
        small = load_capture(folder, options=options)
        assert small.images.shape == (3, h, w, 3) and small.alpha.shape == (3, h, w), options
        expected = full.images[:, :, :] if options.downscale == 1 else full.images.reshape(3, 21, 2, 30, 2, 3).mean((2, 4))
        for i in range(3):
            assert np.allclose(small.images[i], area_resize(expected[i], w, h), atol=1e-5)
        for a, b in zip(full.cameras, small.cameras):  # the same rays through the shrunk pixels
            assert _max_pixel_error(a, b, (w / 60, h / 42)) < 1e-6, options
        only, _, _ = load_cameras(folder, options)
        assert [c.intrinsics() for c in only] == [c.intrinsics() for c in small.cameras]


def test_large_jpegs_are_decoded_at_a_fraction_of_their_size(tmp_path):
    """JPEG photos and masks (LLFF) read with max_size are decoded at 1/2, 1/4 or 1/8 scale by the
    decoder, then area-averaged: the same size, cameras and (nearly) the same pixels as decoding
    them whole; sides the factor does not divide are decoded whole."""
    from PIL import Image

    from vq_mitsuba.config import CaptureConfig
    from vq_mitsuba.data.captures import load_capture
    from vq_mitsuba.data.imageio import read_image
    from vq_mitsuba.data.formats.llff import write_poses_bounds
    from vq_mitsuba.data.resize import Shrink, area_resize

    w, h = 128, 96
    cams = _cameras(3, w, h, centred=True)
    folder = tmp_path / "llff"
    (folder / "images").mkdir(parents=True)
    (folder / "masks").mkdir()
    for i, c in enumerate(cams):
        rgb = (_smooth(w, h, i) * 255).astype(np.uint8)
        Image.fromarray(rgb).save(folder / "images" / f"{c.name}.jpg", quality=95)
        mask = np.zeros((h, w), np.uint8)
        mask[20:80, 30:100] = 255
        Image.fromarray(mask).save(folder / "masks" / f"{c.name}.jpg", quality=95)
    write_poses_bounds(folder / "poses_bounds.npy", cams, [(0.5, 5.0)] * 3)
    shrink = Shrink(1, 30)
    assert shrink.decode_reduction(folder / "images" / f"{cams[0].name}.jpg") == 4  # 128 / 4 = 32 >= 30
    assert Shrink(1, 70).decode_reduction(folder / "images" / f"{cams[0].name}.jpg") == 1  # 128 / 2 = 64 < 70
    assert Shrink(3, 0).decode_reduction(folder / "images" / f"{cams[0].name}.jpg") == 1  # 3 is no multiple of 2
    full = load_capture(folder)
    small = load_capture(folder, options=CaptureConfig(max_size=30))
    assert small.images.shape == (3, 22, 30, 3)
    for a, b in zip(full.cameras, small.cameras):
        assert _max_pixel_error(a, b, (30 / w, 22 / h)) < 1e-6
    for i in range(3):
        exact = area_resize(full.images[i], 30, 22)
        assert np.abs(small.images[i] - exact).max() < 0.03
        assert np.abs(small.alpha[i] - area_resize(full.alpha[i], 30, 22)).mean() < 0.01
    odd = tmp_path / "odd.jpg"  # 130 is no multiple of 4: decoded whole
    Image.fromarray((_smooth(130, 96) * 255).astype(np.uint8)).save(odd, quality=95)
    assert Shrink(1, 30).decode_reduction(odd) == 2 and read_image(odd, 2)[0].shape == (48, 65, 3)
    assert Shrink(1, 16).decode_reduction(odd) == 2


@pytest.mark.parametrize("kind", ["idr", "json"])
def test_large_photos_are_never_all_held_at_full_size(tmp_path, kind):
    """Peak memory of loading 8 photos of 480 x 360 with max_size 48 stays near that of reading
    one photo; without a limit it holds them all."""
    import tracemalloc

    from vq_mitsuba.config import CaptureConfig
    from vq_mitsuba.data.captures import load_capture
    from vq_mitsuba.data.imageio import read_image
    from vq_mitsuba.data.formats.idr import write_idr

    n, w, h = 8, 480, 360
    cams = _cameras(n, w, h, centred=True)
    folder = tmp_path / kind
    image_dir = folder / ("image" if kind == "idr" else "images")
    for i in range(n):
        write_png(image_dir / f"{i:03d}.png", _smooth(w, h, i))
    if kind == "idr":
        write_idr(folder / "cameras_sphere.npz", cams, np.zeros(3), 1.0)
    else:
        folder.joinpath("transforms_train.json").write_text(json.dumps({
            "camera_angle_x": np.radians(42.0), "frames": [
                {"file_path": f"images/{i:03d}", "transform_matrix": camera_to_nerf(c)[0].tolist()}
                for i, c in enumerate(cams)]}))

    def peak(call):
        tracemalloc.start()
        try:
            call()
            return tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()

    one_photo = w * h * 3 * 4
    single = peak(lambda: read_image(image_dir / "000.png"))
    small = peak(lambda: load_capture(folder, options=CaptureConfig(max_size=48)))
    every = peak(lambda: load_capture(folder))
    assert every > n * one_photo  # without a limit: all of them at full size
    assert small < single + 2 * one_photo, (small, single, one_photo)


def test_max_size_and_downscale_reach_fit_render_and_eval(tmp_path, three_materials):
    from vq_mitsuba import cli
    from vq_mitsuba.data.imageio import read_exr

    parser = cli.build_parser()
    subs = {a.dest: a for a in parser._actions if a.dest == "command"}["command"].choices
    for flag in ("--downscale", "--max-size"):
        actions = {id(subs[name]._option_string_actions[flag]) for name in ("fit", "geometry", "render", "eval")}
        assert len(actions) == 1, flag  # one definition, shared
    args = parser.parse_args(["fit", "capture", "--max-size", "640", "--downscale", "2"])
    cfg = cli._config(args)
    assert (cfg.capture.max_size, cfg.capture.downscale) == (640, 2)
    assert cli.main(["fit", str(tmp_path), "--max-size", "-3", "-o", str(tmp_path / "r")]) == 2
    # render: the cameras of the capture, shrunk
    capture, run = three_materials
    out = tmp_path / "small"
    assert cli.main(["render", str(run.dir), "--cameras", str(capture), "--max-size", "16", "--spp", "1", "--quiet",
                     "-o", str(out)]) == 0
    assert read_exr(out / "view_00_rgb.exr").shape[:2] == (16, 16)
    assert json.loads((out / "render.json").read_text())["max_size"] == 16
    assert cli.main(["eval", str(run.dir), "--gt", str(tmp_path), "--max-size", "16"]) == 2
