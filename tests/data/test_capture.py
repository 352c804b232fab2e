"""Captures: camera conventions against Mitsuba, XML / NeRF-json loading, and input validation."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import trimesh

from vq_mitsuba.data.cameras import BLENDER_ENV_TO_WORLD, Camera, nerf_to_camera
from vq_mitsuba.data.captures import load_cameras, load_capture
from vq_mitsuba.data.formats.common import ensure_variant
from vq_mitsuba.data.imageio import srgb_to_linear, write_exr, write_png
from vq_mitsuba.errors import InputError

W, H = 24, 16
RNG = np.random.default_rng(7)


# --------------------------------------------------------------------------------------------
# Builders


def _rgba_exr(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    img = rng.uniform(0.0, 2.0, (H, W, 4)).astype(np.float32)
    img[..., 3] = rng.uniform(0.0, 1.0, (H, W))
    return img


def _png_pixels(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """8-bit sRGB colours and alpha (exactly representable) as uint8 arrays."""
    rng = np.random.default_rng(seed)
    return rng.integers(0, 256, (H, W, 3), dtype=np.uint8), rng.integers(0, 256, (H, W), dtype=np.uint8)


SENSOR = """
  <sensor type="perspective" id="{id}">
    <float name="fov" value="{fov}"/>
    <string name="fov_axis" value="{axis}"/>
    <transform name="to_world"><lookat origin="{origin}" target="{target}" up="{up}"/></transform>
    <film type="hdrfilm"><integer name="width" value="{w}"/><integer name="height" value="{h}"/></film>
  </sensor>"""


def make_xml_capture(root: Path, emitter: str = "", shapes: str | None = None, sizes=None) -> Path:
    """A scene.xml with sensors cam_a (EXR RGBA, fov_axis x) and cam_b (PNG RGBA, fov_axis y)."""
    root.mkdir(parents=True, exist_ok=True)
    sizes = sizes or {"cam_a": (W, H), "cam_b": (W, H)}
    sensors = SENSOR.format(id="cam_a", fov=45, axis="x", origin="0.3, -0.2, 4", target="0, 0.1, 0",
                            up="0.2, 1, 0", w=sizes["cam_a"][0], h=sizes["cam_a"][1])
    sensors += SENSOR.format(id="cam_b", fov=30, axis="y", origin="3, 1.5, 2", target="0, 0, 0",
                             up="0, 0, 1", w=sizes["cam_b"][0], h=sizes["cam_b"][1])
    if shapes is None:
        trimesh.creation.box().export(root / "box.ply")  # 8 vertices, 12 triangles
        shapes = """
  <shape type="ply"><string name="filename" value="box.ply"/>
    <transform name="to_world"><translate x="2" y="0" z="0"/></transform></shape>
  <shape type="sphere"><point name="center" x="0" y="1" z="0"/><float name="radius" value="0.5"/></shape>"""
    (root / "scene.xml").write_text(f'<scene version="3.0.0">{sensors}{shapes}{emitter}\n</scene>\n')
    write_exr(root / "images" / "cam_a.exr", _rgba_exr(1))
    rgb8, a8 = _png_pixels(2)
    write_png(root / "images" / "cam_b.png", rgb8, alpha=a8 / 255.0)
    return root / "scene.xml"


def _rotation(axis, angle_deg) -> np.ndarray:
    axis = np.asarray(axis, dtype=np.float64)
    return trimesh.transformations.rotation_matrix(math.radians(angle_deg), axis)


def nerf_c2w() -> list[np.ndarray]:
    """OpenGL camera-to-world matrices: a tilted + rolled one, an orbit one, and an axis-aligned one."""
    m1 = _rotation([0, 0, 1], 30) @ _rotation([1, 0, 0], 70) @ _rotation([0, 0, 1], 15)  # roll last
    m1[:3, 3] = [0.5, -3.0, 1.2]
    m2 = _rotation([0, 0, 1], -120) @ _rotation([1, 0, 0], 55)
    m2[:3, 3] = m2[:3, :3] @ np.array([0.0, 0.0, 4.0])  # on the camera's +Z: looks at the origin
    m3 = np.eye(4)
    m3[:3, 3] = [0.0, 0.0, 3.0]
    return [m1, m2, m3]


def make_json_capture(root: Path, angle: float = 0.6) -> Path:
    """transforms_train.json with frames ./train/r_0 (exr + png both present), r_1 (png), r_2.png."""
    (root / "train").mkdir(parents=True, exist_ok=True)
    mats = nerf_c2w()
    frames = [
        {"file_path": "./train/r_0", "transform_matrix": mats[0].tolist()},
        {"file_path": "./train/r_1", "transform_matrix": mats[1].tolist()},
        {"file_path": "train/r_2.png", "transform_matrix": mats[2].tolist()},
    ]
    (root / "transforms_train.json").write_text(json.dumps({"camera_angle_x": angle, "frames": frames}))
    write_exr(root / "train" / "r_0.exr", _rgba_exr(10))
    write_png(root / "train" / "r_0.png", np.zeros((H, W, 3), np.uint8), alpha=np.ones((H, W)))  # ignored
    for k in (1, 2):
        rgb8, a8 = _png_pixels(10 + k)
        write_png(root / "train" / f"r_{k}.png", rgb8, alpha=a8 / 255.0)
    return root / "transforms_train.json"


def _mitsuba_rays(mi, sensor, pixels: np.ndarray, size):
    """World-space ray origins and directions of `sensor` through continuous pixel positions."""
    pos = mi.Point2f(pixels[:, 0] / size[0], pixels[:, 1] / size[1])
    n = len(pixels)
    ray, _ = sensor.sample_ray(mi.Float(np.zeros(n)), mi.Float(np.full(n, 0.5)), pos,
                               mi.Point2f(np.full(n, 0.5), np.full(n, 0.5)))
    return np.array(ray.o, dtype=np.float64).T, np.array(ray.d, dtype=np.float64).T


def _check_against_mitsuba(camera: Camera, sensor=None):
    """Pixels -> Mitsuba rays -> points on them -> Camera.project gives the pixels back."""
    mi = ensure_variant()
    if sensor is None:
        sensor = mi.load_dict(camera.to_mitsuba_dict())
    pixels = np.array([[0.5, 0.5], [camera.width / 2, camera.height / 2], [3.25, 11.75],
                       [camera.width - 1.0, 2.0], [17.5, camera.height - 0.25]])
    o, d = _mitsuba_rays(mi, sensor, pixels, (camera.width, camera.height))
    points = o + d * np.array([[1.5], [2.0], [3.0], [4.5], [2.5]])
    np.testing.assert_allclose(camera.project(points), pixels, atol=1e-3)


# --------------------------------------------------------------------------------------------
# Camera conventions


def test_xml_cameras_match_mitsuba_sensors(tmp_path):
    xml = make_xml_capture(tmp_path)
    cap = load_capture(xml)
    mi = ensure_variant()
    sensors = mi.load_file(str(xml)).sensors()  # the original sensors, fov_axis y included
    assert len(sensors) == len(cap.cameras) == 2
    for cam, sensor in zip(cap.cameras, sensors):
        _check_against_mitsuba(cam, sensor)  # against the XML's own sensor
        _check_against_mitsuba(cam)  # and against the sensor rebuilt from the Camera


def test_fov_axis_y_gives_horizontal_fov(tmp_path):
    cap = load_capture(make_xml_capture(tmp_path))
    a, b = cap.cameras
    assert a.fov_x_deg == pytest.approx(45.0, abs=1e-4)
    expected = math.degrees(2 * math.atan(math.tan(math.radians(15.0)) * W / H))
    assert b.fov_x_deg == pytest.approx(expected, abs=1e-4)


def test_nerf_camera_axes():
    angle = 0.7
    f = 0.5 * W / math.tan(0.5 * angle)
    for c2w in nerf_c2w():
        cam = nerf_to_camera("r", c2w, angle, W, H)

        def world(p_cam):  # OpenGL camera space -> world
            return (c2w @ np.append(p_cam, 1.0))[:3]

        ahead = cam.project(world([0.0, 0.0, -2.0]))[0]
        right = cam.project(world([0.3, 0.0, -2.0]))[0]
        up = cam.project(world([0.0, 0.4, -2.0]))[0]
        np.testing.assert_allclose(ahead, [W / 2, H / 2], atol=1e-9)
        assert right[0] > W / 2 and up[1] < H / 2
        np.testing.assert_allclose(right, [W / 2 + f * 0.3 / 2.0, H / 2], atol=1e-9)
        np.testing.assert_allclose(up, [W / 2, H / 2 - f * 0.4 / 2.0], atol=1e-9)
        np.testing.assert_allclose(cam.origin, c2w[:3, 3])
        _check_against_mitsuba(cam)


# --------------------------------------------------------------------------------------------
# Loading


def test_xml_capture_loads(tmp_path):
    env = RNG.uniform(0.0, 3.0, (8, 16, 3)).astype(np.float32)
    write_exr(tmp_path / "env.exr", env)
    emitter = """
  <emitter type="envmap"><string name="filename" value="env.exr"/>
    <transform name="to_world"><rotate x="1" angle="90"/></transform></emitter>"""
    xml = make_xml_capture(tmp_path, emitter=emitter)
    cap = load_capture(tmp_path)  # the folder resolves to scene.xml
    assert cap.source == xml and cap.world == "mitsuba"
    assert [c.name for c in cap.cameras] == ["cam_a", "cam_b"]
    assert all((c.width, c.height) == (W, H) for c in cap.cameras)
    assert cap.images.shape == (2, H, W, 3) and cap.images.dtype == np.float32
    assert cap.alpha.shape == (2, H, W) and cap.has_alpha
    exr = _rgba_exr(1)
    np.testing.assert_array_equal(cap.images[0], exr[..., :3])
    np.testing.assert_array_equal(cap.alpha[0], exr[..., 3])
    rgb8, a8 = _png_pixels(2)
    np.testing.assert_allclose(cap.images[1], srgb_to_linear(rgb8 / 255.0), atol=1e-6)
    np.testing.assert_allclose(cap.alpha[1], a8 / 255.0, atol=1e-6)
    # Merged mesh: the box (8 vertices, translated) and a level-4 icosphere (2562 vertices).
    assert len(cap.mesh.vertices) == 8 + 2562
    assert len(cap.mesh.faces) == 12 + 5120
    box = cap.mesh.vertices[:8] if cap.mesh.vertices[:8, 0].min() > 1 else cap.mesh.vertices[-8:]
    np.testing.assert_allclose(box.min(0), [1.5, -0.5, -0.5], atol=1e-6)
    np.testing.assert_allclose(box.max(0), [2.5, 0.5, 0.5], atol=1e-6)
    on_sphere = np.abs(cap.mesh.vertices[:, 0]) < 0.6
    sphere = cap.mesh.vertices[on_sphere]
    np.testing.assert_allclose(np.linalg.norm(sphere - [0, 1, 0], axis=1), 0.5, atol=1e-5)
    # Shading normals: the sphere's true normals, not ones averaged from its facets.
    np.testing.assert_allclose(cap.mesh.vertex_normals[on_sphere], (sphere - [0, 1, 0]) / 0.5, atol=1e-5)
    # Known lighting.
    np.testing.assert_array_equal(cap.envmap, env)
    rot = np.array([[1, 0, 0, 0], [0, 0, -1, 0], [0, 1, 0, 0], [0, 0, 0, 1]], dtype=np.float64)
    np.testing.assert_allclose(cap.envmap_to_world, rot, atol=1e-6)


def test_xml_capture_without_geometry_or_lighting(tmp_path):
    cap = load_capture(make_xml_capture(tmp_path, shapes=""))
    assert cap.mesh is None and cap.envmap is None
    np.testing.assert_array_equal(cap.envmap_to_world, np.eye(4))


def test_json_capture_loads(tmp_path):
    path = make_json_capture(tmp_path, angle=0.6)
    trimesh.creation.box().export(tmp_path / "mesh.ply")
    cap = load_capture(tmp_path)
    assert cap.source == path and cap.world == "blender"
    assert [c.name for c in cap.cameras] == ["r_0", "r_1", "r_2"]
    assert all(c.fov_x_deg == pytest.approx(math.degrees(0.6)) for c in cap.cameras)
    for cam, c2w in zip(cap.cameras, nerf_c2w()):
        np.testing.assert_allclose(cam.to_world, c2w @ np.diag([-1.0, 1.0, -1.0, 1.0]))
    np.testing.assert_array_equal(cap.images[0], _rgba_exr(10)[..., :3])  # .exr preferred to .png
    rgb8, a8 = _png_pixels(12)
    np.testing.assert_allclose(cap.images[2], srgb_to_linear(rgb8 / 255.0), atol=1e-6)
    np.testing.assert_allclose(cap.alpha[2], a8 / 255.0, atol=1e-6)
    assert cap.has_alpha and cap.envmap is None
    np.testing.assert_array_equal(cap.envmap_to_world, BLENDER_ENV_TO_WORLD)
    assert len(cap.mesh.vertices) == 8  # mesh.ply beside the json

    other = tmp_path / "elsewhere" / "ico.obj"
    other.parent.mkdir()
    trimesh.creation.icosphere(subdivisions=1).export(other)
    cap = load_capture(path, mesh=other)  # the argument wins over mesh.ply
    assert len(cap.mesh.vertices) == 42 and len(cap.mesh.faces) == 80
    # A PLY's own vertex normals are the shading normals (not recomputed from the faces).
    ico = trimesh.creation.icosphere(subdivisions=1)
    tilted = ico.vertex_normals + [0.3, 0.0, 0.0]
    tilted /= np.linalg.norm(tilted, axis=1, keepdims=True)
    trimesh.Trimesh(ico.vertices, ico.faces, vertex_normals=tilted, process=False).export(tmp_path / "n.ply")
    cap = load_capture(path, mesh=tmp_path / "n.ply")
    np.testing.assert_allclose(cap.mesh.vertex_normals, tilted, atol=1e-6)


def test_json_capture_without_alpha(tmp_path):
    (tmp_path / "a.exr").parent.mkdir(exist_ok=True)
    write_exr(tmp_path / "a.exr", np.full((H, W, 3), 0.25, np.float32))
    frames = [{"file_path": "a", "transform_matrix": np.eye(4).tolist()}]
    (tmp_path / "transforms_val.json").write_text(json.dumps({"camera_angle_x": 0.5, "frames": frames}))
    cap = load_capture(tmp_path / "transforms_val.json")
    assert not cap.has_alpha and cap.mesh is None
    np.testing.assert_array_equal(cap.alpha, np.ones((1, H, W), np.float32))


def test_load_cameras(tmp_path):
    cams, world, source = load_cameras(make_json_capture(tmp_path / "nerf"))
    assert world == "blender" and source.name == "transforms_train.json"
    assert [(c.width, c.height) for c in cams] == [(W, H)] * 3

    # Cameras only: no images needed when the json gives w/h.
    frames = [{"file_path": "./test/r_9", "transform_matrix": nerf_c2w()[1].tolist()}]
    novel = tmp_path / "transforms_test.json"
    novel.write_text(json.dumps({"camera_angle_x": 0.6, "w": 40, "h": 30, "frames": frames}))
    cams, world, _ = load_cameras(novel)
    assert (cams[0].name, cams[0].width, cams[0].height) == ("r_9", 40, 30)

    xml = make_xml_capture(tmp_path / "xml")
    (tmp_path / "xml" / "box.ply").unlink()  # geometry is not needed for cameras
    cams, world, source = load_cameras(xml)
    assert world == "mitsuba" and source == xml and [c.name for c in cams] == ["cam_a", "cam_b"]


# --------------------------------------------------------------------------------------------
# Bad input: one InputError naming the file


def _expect(call, filename: str, *phrases: str) -> InputError:
    with pytest.raises(InputError) as info:
        call()
    message = str(info.value)
    assert filename in message, message
    for phrase in phrases:
        assert phrase in message, message
    return info.value


def test_missing_capture_file(tmp_path):
    _expect(lambda: load_capture(tmp_path / "nope.json"), "nope.json", "not found")
    _expect(lambda: load_capture(tmp_path), str(tmp_path), "transforms_train.json")


def test_xml_camera_without_image(tmp_path):
    xml = make_xml_capture(tmp_path)
    (tmp_path / "images" / "cam_b.png").unlink()
    err = _expect(lambda: load_capture(xml), "cam_b.exr", "no reference image", "cam_b.png")
    assert err.path == tmp_path / "images" / "cam_b.exr"


def test_xml_image_size_differs_from_film(tmp_path):
    xml = make_xml_capture(tmp_path)
    write_exr(tmp_path / "images" / "cam_a.exr", np.ones((H + 2, W, 3), np.float32))
    _expect(lambda: load_capture(xml), "cam_a.exr", f"{W}x{H + 2}", f"{W}x{H}", "film size")


def test_xml_film_sizes_differ(tmp_path):
    xml = make_xml_capture(tmp_path, sizes={"cam_a": (W, H), "cam_b": (W, H + 4)})
    _expect(lambda: load_capture(xml), "scene.xml", f"{W}x{H + 4}", "share one film size")


def test_unknown_emitter(tmp_path):
    xml = make_xml_capture(tmp_path, emitter='<emitter type="point"><point name="position" value="0,1,0"/></emitter>')
    _expect(lambda: load_capture(xml), "scene.xml", "unknown emitter type 'point'", "only envmap")


def test_unsupported_shape(tmp_path):
    xml = make_xml_capture(tmp_path, shapes='<shape type="rectangle"/>')
    _expect(lambda: load_capture(xml), "scene.xml", "'rectangle'", "not supported")


def test_xml_parse_error_and_missing_shape_file(tmp_path):
    bad = tmp_path / "broken.xml"
    bad.write_text('<scene version="3.0.0">\n  <sensor type="perspective">\n</scene>\n')
    _expect(lambda: load_capture(bad), "broken.xml", "XML parse error", "line 3")
    xml = make_xml_capture(tmp_path / "s", shapes='<shape type="ply"><string name="filename" value="gone.ply"/></shape>')
    _expect(lambda: load_capture(xml), "gone.ply", "mesh file not found")
    (tmp_path / "s" / "gone.ply").write_bytes(b"ply\nthis is not a ply header\n")
    _expect(lambda: load_capture(xml), "gone.ply", "cannot load")


def test_xml_without_sensors(tmp_path):
    xml = tmp_path / "scene.xml"
    xml.write_text('<scene version="3.0.0"></scene>')
    _expect(lambda: load_capture(xml), "scene.xml", "no cameras")


def test_json_missing_image(tmp_path):
    path = make_json_capture(tmp_path)
    (tmp_path / "train" / "r_1.png").unlink()
    _expect(lambda: load_capture(path), "r_1.exr", "image not found", "r_1.png", "frames[1]")


def test_json_size_mismatch(tmp_path):
    path = make_json_capture(tmp_path)
    rgb8, a8 = _png_pixels(3)
    write_png(tmp_path / "train" / "r_2.png", rgb8[:, :-4], alpha=a8[:, :-4] / 255.0)
    _expect(lambda: load_capture(path), "r_2.png", f"{W - 4}x{H}", f"{W}x{H}", "r_0.exr")


def test_unreadable_image(tmp_path):
    path = make_json_capture(tmp_path)
    (tmp_path / "train" / "r_1.png").write_bytes(b"\x89PNG\r\n\x1a\n garbage garbage garbage")
    _expect(lambda: load_capture(path), "r_1.png", "cannot read image")


def test_nan_pixel(tmp_path):
    xml = make_xml_capture(tmp_path)
    img = _rgba_exr(1)
    img[3, 5, 1] = np.nan
    write_exr(tmp_path / "images" / "cam_a.exr", img)
    _expect(lambda: load_capture(xml), "cam_a.exr", "non-finite")


def test_mixed_alpha(tmp_path):
    xml = make_xml_capture(tmp_path)
    write_exr(tmp_path / "images" / "cam_a.exr", _rgba_exr(1)[..., :3])
    _expect(lambda: load_capture(xml), "cam_a.exr", "no alpha channel")


def _write_json(tmp_path: Path, payload) -> Path:
    path = make_json_capture(tmp_path)
    path.write_text(payload if isinstance(payload, str) else json.dumps(payload))
    return path


def test_json_header_errors(tmp_path):
    good = json.loads(make_json_capture(tmp_path / "ok").read_text())

    no_angle = {k: v for k, v in good.items() if k != "camera_angle_x"}
    _expect(lambda: load_capture(_write_json(tmp_path / "a", no_angle)), "transforms_train.json",
            "missing 'camera_angle_x'")

    text = json.dumps(good, indent=1).replace('"frames": [', '"frames": [,', 1)
    _expect(lambda: load_capture(_write_json(tmp_path / "b", text)), "transforms_train.json",
            "malformed json", "line 3")

    _expect(lambda: load_capture(_write_json(tmp_path / "c", {**good, "frames": []})),
            "transforms_train.json", "no cameras")

    frames = [dict(f) for f in good["frames"]]
    del frames[1]["transform_matrix"]
    _expect(lambda: load_capture(_write_json(tmp_path / "d", {**good, "frames": frames})),
            "transforms_train.json", "frames[1]", "no 'transform_matrix'")

    frames = [dict(f) for f in good["frames"]]
    frames[2]["transform_matrix"] = [[1, 0, 0], [0, 1, 0]]
    _expect(lambda: load_capture(_write_json(tmp_path / "e", {**good, "frames": frames})),
            "transforms_train.json", "frames[2]", "malformed transform_matrix")


def test_mesh_errors(tmp_path):
    path = make_json_capture(tmp_path)
    _expect(lambda: load_capture(path, mesh=tmp_path / "missing.ply"), "missing.ply", "mesh file not found")
    (tmp_path / "empty.obj").write_text("# nothing here\n")
    _expect(lambda: load_capture(path, mesh=tmp_path / "empty.obj"), "empty.obj", "empty")
    (tmp_path / "mesh.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 99\n\x00\x01")
    _expect(lambda: load_capture(path), "mesh.ply", "cannot read mesh")


@pytest.mark.parametrize("change, phrases", [
    ({"camera_angle_x": 1e-9}, ("'camera_angle_x' must be", "0.01..170 degrees")),
    ({"camera_angle_x": 3.1}, ("'camera_angle_x' must be",)),
    ({"camera_angle_x": float("inf")}, ("'camera_angle_x' must be",)),
    ({"w": float("inf"), "h": 16}, ("'w' and 'h': image width inf is not a whole number",)),
    ({"w": 24, "h": float("nan")}, ("image height nan",)),
    ({"w": 24, "h": 0}, ("image height 0",)),
    ({"w": "24", "h": 16}, ("image width '24'",)),
])
def test_json_intrinsics_are_finite_and_plausible(tmp_path, change, phrases):
    data = json.loads(make_json_capture(tmp_path).read_text())
    (tmp_path / "transforms_train.json").write_text(json.dumps({**data, **change}))
    _expect(lambda: load_cameras(tmp_path), "transforms_train.json", *phrases)


def test_json_camera_far_from_the_origin_is_refused(tmp_path):
    data = json.loads(make_json_capture(tmp_path).read_text())
    data["frames"][1]["transform_matrix"][2][3] = 1e300
    (tmp_path / "transforms_train.json").write_text(json.dumps(data))
    _expect(lambda: load_capture(tmp_path), "transforms_train.json", "frames[1] (./train/r_1)",
            "units from the origin")


@pytest.mark.parametrize("fov, phrase", [("nan", "non-finite field of view"), ("0.0001", "field of view of 0.0001")])
def test_xml_sensor_fov_is_finite_and_plausible(tmp_path, fov, phrase):
    xml = make_xml_capture(tmp_path)
    xml.write_text(xml.read_text().replace('name="fov" value="45"', f'name="fov" value="{fov}"'))
    _expect(lambda: load_cameras(xml), "scene.xml", "sensor 'cam_a'", phrase)


def test_palette_png_transparency_is_alpha(tmp_path):
    """A palette ("P") PNG with a tRNS chunk: its transparent entries are alpha 0, the rest 1."""
    from PIL import Image

    path = make_json_capture(tmp_path)
    index = np.zeros((H, W), np.uint8)
    index[4:12, 6:18] = 1
    image = Image.fromarray(index, mode="P")
    image.putpalette([0, 0, 0, 255, 128, 0] + [0] * 762)
    for k in (1, 2):
        image.save(tmp_path / "train" / f"r_{k}.png", transparency=bytes([0, 255]))
    cap = load_capture(path)
    assert cap.has_alpha
    np.testing.assert_array_equal(cap.alpha[1], (index == 1).astype(np.float32))
    orange = srgb_to_linear(np.array([1.0, 128 / 255, 0.0]))
    np.testing.assert_allclose(cap.images[1][index == 1], np.broadcast_to(orange, (int(index.sum()), 3)), atol=1e-6)
