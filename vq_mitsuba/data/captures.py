"""Captures: posed reference images plus optional known geometry and lighting.

A capture is a Mitsuba scene XML (sensors with `images/<id>.exr|png` beside the XML, optional
`<shape>` geometry and `<emitter type="envmap">` lighting; Mitsuba world), a NeRF-synthetic
`transforms_*.json` (OpenGL camera axes, Blender world with Z up), a nerfstudio `transforms.json`
(pixel intrinsics, lens distortion, masks: vq_mitsuba.data.nerfstudio), or a photographed capture
(COLMAP, NeuS/IDR, LLFF: vq_mitsuba.data.photo_captures). Known geometry besides an XML's shapes:
a `mesh=` argument, else a `mesh.ply` in the capture's folder (beside the json, in the COLMAP,
NeuS/IDR or LLFF folder), in the capture's world. Images are shrunk as they are read
(capture.downscale, capture.max_size: vq_mitsuba.data.resize). Views are named by
vq_mitsuba.data.names (file-safe, unique). Everything is validated before returning, and every
problem is an InputError naming the offending file.
"""

from __future__ import annotations

import json
import math
import posixpath
import re
import xml.etree.ElementTree as ET
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from vq_mitsuba.config import CaptureConfig
from vq_mitsuba.errors import InputError, raise_all
from vq_mitsuba.data.cameras import BLENDER_ENV_TO_WORLD, Camera, nerf_to_camera
from vq_mitsuba.data.checks import MAX_FOV_DEG, MIN_FOV_DEG, check_camera, check_pose, check_size, finite_number
from vq_mitsuba.data.imageio import read_image
from vq_mitsuba.data.names import view_names
from vq_mitsuba.data.unposed import UNPOSED_KINDS, is_video, photo_files, unposed_error
from vq_mitsuba.data.resize import Shrink, downscaled_camera  # noqa: F401 (downscaled_camera: public here too)

if TYPE_CHECKING:
    import trimesh

IMAGE_EXTS = (".exr", ".png", ".jpg", ".jpeg")
MESH_SHAPES = ("ply", "obj", "serialized", "cube")  # loaded by Mitsuba as triangle meshes
SPHERE_SUBDIVISIONS = 4


@dataclass
class Capture:
    source: Path  # the XML or json file
    cameras: list[Camera]  # Mitsuba-convention cameras, in the capture's world
    images: np.ndarray  # (N, H, W, 3) float32 linear RGB
    alpha: np.ndarray  # (N, H, W) float32 in [0, 1]; all ones when images have no alpha
    has_alpha: bool
    mesh: trimesh.Trimesh | None  # known geometry in world space, or None
    envmap: np.ndarray | None  # known lighting: (H, W, 3) float32 lat-long linear, or None
    envmap_to_world: np.ndarray  # (4, 4) float64
    world: str  # "mitsuba" or "blender"

    @property
    def height(self) -> int:
        return int(self.images.shape[1])

    @property
    def width(self) -> int:
        return int(self.images.shape[2])


# --------------------------------------------------------------------------------------------
# Public entry points


def load_capture(path: str | Path, mesh: str | Path | None = None, options: CaptureConfig | None = None,
                 split: str = "all", cache_dir: str | Path | None = None) -> Capture:
    """Load and validate a capture (scene XML, transforms json, NeuS/IDR cameras_sphere.npz, LLFF
    poses_bounds.npy, a COLMAP folder, or a folder holding one). `options` (config section `capture`)
    sets the downscale and maximum size (applied to each image as it is read), the background keying
    and the held-out views; `split` is "all", "train" (without the held-out views) or "holdout".
    Undistorted photos are cached in `cache_dir` when given."""
    options = options or CaptureConfig()
    shrink = Shrink.of(options)
    source = resolve_capture_path(path)
    kind = capture_kind(source)
    if kind in UNPOSED_KINDS:
        raise unposed_error(source)
    if kind == "xml":
        capture = _load_xml_capture(source, mesh, shrink)
    elif kind == "json":
        capture = _load_json_capture(source, mesh, shrink, cache_dir)
    else:
        from vq_mitsuba.data.photo_captures import load_photo_views

        cameras, images, alpha, has_alpha, folder, env_to_world = load_photo_views(source, kind, cache_dir, shrink)
        mesh_file = mesh if mesh is not None else (folder / "mesh.ply" if (folder / "mesh.ply").is_file() else None)
        capture = Capture(source, cameras, images, alpha, has_alpha, load_mesh(mesh_file) if mesh_file else None,
                          None, env_to_world, "mitsuba")
    capture.cameras = named_views(capture.cameras)
    return finish_capture(capture, options, split)


def load_cameras(path: str | Path, options: CaptureConfig | None = None,
                 split: str = "all") -> tuple[list[Camera], str, Path]:
    """Cameras only (no images needed), for rendering novel views: (cameras, world, source)."""
    options = options or CaptureConfig()
    source = resolve_capture_path(path)
    kind = capture_kind(source)
    if kind in UNPOSED_KINDS:
        raise unposed_error(source)
    if kind == "xml":
        root, defaults = _parse_xml(source)
        scene = _load_mitsuba_sensors_only(source, root)
        cameras, world = _xml_cameras(source, root, defaults, scene), "mitsuba"
    elif kind == "json":
        from vq_mitsuba.data.nerfstudio import is_nerfstudio

        data = _read_json(source)
        frames = _json_frames(source, data)
        if is_nerfstudio(data):
            cameras = _nerfstudio_cameras(source, data, frames)[0]
        else:
            angle = _json_angle(source, data)
            width, height = _json_image_size(source, data, frames)
            cameras = _json_cameras(source, frames, _frame_matrices(source, frames), angle, width, height)
        world = "blender"
    else:
        from vq_mitsuba.data.photo_captures import photo_cameras

        cameras, world = photo_cameras(source, kind), "mitsuba"
    shrink = Shrink.of(options)
    cameras = [shrink.camera(c, source) for c in named_views(cameras)]
    return [cameras[i] for i in split_indices(len(cameras), options.holdout, split)], world, source


def named_views(cameras: list[Camera]) -> list[Camera]:
    """The cameras under their file-safe, unique view names (vq_mitsuba.data.names.view_names),
    given to all views of a capture before any split. The loaders find each view's files by the
    capture's own names; everything after loading knows a view by this name."""
    return [replace(c, name=n) for c, n in zip(cameras, view_names([c.name for c in cameras]))]


def capture_kind(source: Path) -> str:
    """"xml", "json", "idr" (cameras_sphere.npz), "llff" (poses_bounds.npy) or "colmap" (a folder
    with a sparse model); "photos" (a folder of photos without poses) or "video" (no poses either)."""
    if source.is_dir():
        from vq_mitsuba.data.photo_formats import colmap_model_dir

        return "colmap" if colmap_model_dir(source) is not None else "photos"
    if is_video(source):
        return "video"
    return {".xml": "xml", ".json": "json", ".npz": "idr", ".npy": "llff"}[source.suffix.lower()]


def resolve_capture_path(path: str | Path) -> Path:
    """The capture for `path`: the file itself, a folder's transforms_train.json / transforms.json /
    scene.xml / cameras_sphere.npz / poses_bounds.npy, or the folder itself when it holds a COLMAP
    sparse model or, failing all these, photos (a capture without poses, as a video file is)."""
    from vq_mitsuba.data.photo_formats import colmap_model_dir

    path = Path(path)
    if path.is_dir():
        for name in ("transforms_train.json", "transforms.json", "scene.xml", "cameras_sphere.npz",
                     "poses_bounds.npy"):
            if (path / name).is_file():
                return path / name
        if colmap_model_dir(path) is not None or photo_files(path):
            return path
        raise InputError(path, "capture folder holds no transforms_train.json, transforms.json (nerfstudio), "
                               "scene.xml, cameras_sphere.npz (NeuS/IDR), poses_bounds.npy (LLFF), COLMAP "
                               "model (sparse/0/cameras.bin or .txt) or photos (JPEG / PNG)")
    if not path.exists():
        raise InputError(path, "capture file not found")
    if path.suffix.lower() not in (".xml", ".json", ".npz", ".npy") and not is_video(path):
        raise InputError(path, "unknown capture format (expected a Mitsuba scene .xml, a transforms_*.json or "
                               "nerfstudio transforms.json, a NeuS/IDR cameras_sphere.npz, an LLFF poses_bounds.npy, "
                               "a COLMAP folder, a folder of photos or a video)")
    return path


def split_indices(count: int, holdout: int, split: str) -> list[int]:
    """The views of a split: with holdout K, every K-th view (K-1, 2K-1, ...) is held out."""
    if split not in ("all", "train", "holdout"):
        raise ValueError(f"unknown split {split!r}")
    held = {i for i in range(count) if holdout > 0 and i % holdout == holdout - 1}
    if split == "all":
        return list(range(count))
    return [i for i in range(count) if (i in held) == (split == "holdout")]


def finish_capture(capture: Capture, options: CaptureConfig, split: str = "all") -> Capture:
    """Apply the size (the loaders shrank the images as they read them; here the cameras follow),
    background keying and the split to a loaded capture."""
    from vq_mitsuba.config import background_rgb

    images, alpha, has_alpha = capture.images, capture.alpha, capture.has_alpha
    key = background_rgb(options)
    if key is not None:
        if has_alpha:
            raise InputError(capture.source, "capture.background_color keys out a backdrop, but this capture "
                                             "already has masks (alpha or a mask folder): drop one")
        from vq_mitsuba.data.imageio import linear_to_srgb

        dist = np.linalg.norm(linear_to_srgb(np.clip(images, 0, 1)) - np.asarray(key, np.float32), axis=-1)
        tol = options.background_tolerance
        alpha = np.clip((dist - tol) / max(tol, 1e-6), 0.0, 1.0).astype(np.float32)
        has_alpha = True
        if not (alpha > 0.5).any():
            raise InputError(capture.source, f"every pixel lies within {tol} of the background colour {key}: "
                                             "nothing left to fit (check capture.background_color)")
    cameras = [Shrink.of(options).camera(c, capture.source) for c in capture.cameras]
    for cam in cameras:
        if (cam.height, cam.width) != images.shape[1:3]:  # a loader that did not shrink its images
            raise AssertionError(f"view {cam.name}: camera {cam.width}x{cam.height}, image "
                                 f"{images.shape[2]}x{images.shape[1]}")
    keep = split_indices(len(cameras), options.holdout, split)
    if not keep:
        raise InputError(capture.source, f"capture.holdout {options.holdout} leaves no {split} view of {len(cameras)}")
    if options.holdout > 0 and split == "train" and len(keep) == len(cameras):
        raise InputError(capture.source, f"capture.holdout {options.holdout} holds out none of {len(cameras)} views")
    if len(keep) < len(cameras):  # a copy only when views are left out
        cameras, images, alpha = [cameras[i] for i in keep], images[keep], alpha[keep]
    return Capture(capture.source, cameras, np.ascontiguousarray(images), np.ascontiguousarray(alpha), has_alpha,
                   capture.mesh, capture.envmap, capture.envmap_to_world, capture.world)


def load_mesh(path: str | Path):
    """A PLY/OBJ mesh as a trimesh.Trimesh (vertices kept as stored, and the file's vertex normals
    when it has them: they are the shading normals), validated."""
    import trimesh

    path = Path(path)
    if not path.is_file():
        raise InputError(path, "mesh file not found")
    try:
        # Not force="mesh": that path drops the normals stored in the file.
        loaded = trimesh.load(str(path), process=False)
    except Exception as exc:  # trimesh raises many kinds on bad files
        raise InputError(path, f"cannot read mesh file ({type(exc).__name__}: {exc})") from exc
    if isinstance(loaded, trimesh.Scene):  # several objects, or an empty file
        geoms = [g for g in loaded.geometry.values() if isinstance(g, trimesh.Trimesh)]
        loaded = trimesh.util.concatenate(geoms) if geoms else trimesh.Trimesh()
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0 or len(loaded.vertices) == 0:
        raise InputError(path, "mesh file is empty (no triangles)")
    if not np.all(np.isfinite(loaded.vertices)):
        raise InputError(path, "mesh has non-finite vertex positions")
    return loaded


def _ensure_variant():
    """mitsuba, with the project's variant selected (vq_mitsuba.backend.init_mitsuba)."""
    import mitsuba as mi

    from vq_mitsuba.backend import init_mitsuba

    init_mitsuba()
    return mi


# --------------------------------------------------------------------------------------------
# Shared helpers


def _find_image(stem: Path) -> Path | None:
    """`stem.exr` if it exists, else `stem.png` (None when neither does)."""
    for ext in (".exr", ".png"):
        candidate = stem.parent / (stem.name + ext)
        if candidate.is_file():
            return candidate
    return None


def _shrunk_entry(shrink: Shrink, path: Path, rgb: np.ndarray, alpha: np.ndarray | None):
    """(path, rgb, alpha) at the size `shrink` gives, alpha checked first (averaging would hide a bad value)."""
    if alpha is not None and (alpha.min() < 0.0 or alpha.max() > 1.0):
        raise InputError(path, f"alpha outside [0, 1] (range {alpha.min():g}..{alpha.max():g})")
    if not shrink.active:
        return path, rgb, alpha
    return path, shrink.image(rgb, path), None if alpha is None else shrink.image(alpha, path)


def _stack_images(entries: list[tuple[Path, np.ndarray, np.ndarray | None]]):
    """(images, alpha, has_alpha) from (path, rgb, alpha) triples of one size."""
    with_alpha = [a is not None for _, _, a in entries]
    if any(with_alpha) and not all(with_alpha):
        has = next(p for p, _, a in entries if a is not None)
        lacks = next(p for p, _, a in entries if a is None)
        raise InputError(lacks, f"image has no alpha channel but {has.name} has one; "
                                "either all images carry an alpha mask or none does")
    images = np.stack([rgb for _, rgb, _ in entries]).astype(np.float32, copy=False)
    if all(with_alpha):
        alpha = np.stack([a for _, _, a in entries]).astype(np.float32, copy=False)
        for p, _, a in entries:
            if a.min() < 0.0 or a.max() > 1.0:
                raise InputError(p, f"alpha outside [0, 1] (range {a.min():g}..{a.max():g})")
        return images, alpha, True
    return images, np.ones(images.shape[:3], dtype=np.float32), False


def _matrix(transform) -> np.ndarray:
    """A Mitsuba (Affine)Transform4f as a (4, 4) float64 array, in any variant."""
    m = np.array(transform.matrix, dtype=np.float64)
    if m.ndim == 3:
        m = m[..., 0]
    return m.reshape(4, 4)


# --------------------------------------------------------------------------------------------
# Mitsuba XML


def _parse_xml(xml: Path) -> tuple[ET.Element, dict[str, str]]:
    try:
        root = ET.parse(xml).getroot()
    except ET.ParseError as exc:
        raise InputError(xml, f"XML parse error ({exc})") from exc
    except OSError as exc:
        raise InputError(xml, f"cannot read scene file ({exc})") from exc
    if root.tag != "scene":
        raise InputError(xml, f"not a Mitsuba scene (root element is <{root.tag}>, expected <scene>)")
    defaults = {d.get("name"): d.get("value", "") for d in root.iter("default") if d.get("name")}
    return root, defaults


def _subst(value: str | None, defaults: dict[str, str]) -> str | None:
    """Mitsuba's `$name` substitution of <default> values in attribute text."""
    if value is None or "$" not in value:
        return value
    return re.sub(r"\$(\w+)", lambda m: defaults.get(m.group(1), m.group(0)), value)


def _string_param(elem: ET.Element, name: str, defaults: dict[str, str]) -> str | None:
    for child in elem:
        if child.tag == "string" and child.get("name") == name:
            return _subst(child.get("value"), defaults)
    return None


def _xml_file(xml: Path, filename: str) -> Path:
    p = Path(filename)
    return p if p.is_absolute() else xml.parent / p


def _load_mitsuba_scene(xml: Path, referenced: list[Path]):
    mi = _ensure_variant()
    try:
        return mi.load_file(str(xml))
    except Exception as exc:
        message = str(exc)
        for ref in referenced:  # name the mesh / bitmap Mitsuba choked on, when it says which
            if f'"{ref.name}"' in message or str(ref) in message:
                raise InputError(ref, f"cannot load file referenced by {xml.name}: {message}") from exc
        raise InputError(xml, f"Mitsuba cannot load the scene: {message}") from exc


def _load_mitsuba_sensors_only(xml: Path, root: ET.Element):
    """Load only <default> and <sensor> elements, so cameras need no meshes or bitmaps."""
    mi = _ensure_variant()
    stripped = ET.Element("scene", dict(root.attrib))
    for child in root:
        if child.tag in ("default", "sensor"):
            stripped.append(child)
    try:
        return mi.load_string(ET.tostring(stripped, encoding="unicode"))
    except Exception as exc:
        raise InputError(xml, f"Mitsuba cannot load the sensors: {exc}") from exc


def _xml_cameras(xml: Path, root: ET.Element, defaults: dict[str, str], scene) -> list[Camera]:
    mi = _ensure_variant()
    sensor_elems = list(root.iter("sensor"))
    if not sensor_elems:
        raise InputError(xml, "no cameras: the scene has no <sensor> element")
    ids = []
    for k, elem in enumerate(sensor_elems):
        sid = _subst(elem.get("id"), defaults)
        if not sid:
            raise InputError(xml, f"<sensor> number {k + 1} has no id attribute "
                                  "(its reference image is images/<id>.exr or .png)")
        ids.append(sid)
    sensors = list(scene.sensors())
    if len(sensors) != len(ids):
        raise InputError(xml, f"found {len(ids)} <sensor> elements but Mitsuba loaded {len(sensors)}")
    cameras = []
    for sid, sensor in zip(ids, sensors):
        kind = sensor.class_name()
        if kind != "PerspectiveCamera":
            raise InputError(xml, f"sensor '{sid}' is a {kind}; only type=\"perspective\" (pinhole) is supported")
        params = mi.traverse(sensor)
        film = sensor.film()
        size, crop = [int(v) for v in film.size()], [int(v) for v in film.crop_size()]
        if size != crop:
            raise InputError(xml, f"sensor '{sid}': film crop windows are not supported")
        ox, oy = (float(np.ravel(np.array(params[f"principal_point_offset_{a}"]))[0]) for a in "xy")
        principal = None if max(abs(ox), abs(oy)) < 1e-9 else ((0.5 - ox) * size[0], (0.5 - oy) * size[1])
        fov_x = float(np.ravel(np.array(params["x_fov"]))[0])
        to_world = _matrix(params["to_world"])
        if not (np.all(np.isfinite(to_world)) and abs(np.linalg.det(to_world[:3, :3])) > 1e-12):
            raise InputError(xml, f"sensor '{sid}': degenerate to_world transform")
        if not (finite_number(fov_x) and finite_number(ox) and finite_number(oy)):
            raise InputError(xml, f"sensor '{sid}': non-finite field of view or principal point offset")
        cameras.append(Camera(sid, to_world, fov_x, size[0], size[1], principal=principal))
        check_camera(xml, f"sensor '{sid}'", cameras[-1])
    return cameras


def _load_xml_capture(xml: Path, mesh_arg: str | Path | None, shrink: Shrink | None = None) -> Capture:
    root, defaults = _parse_xml(xml)
    # The text is checked before Mitsuba loads anything, for clear messages.
    env_elems = _xml_envmap_elements(xml, root, defaults)
    referenced = _xml_mesh_files(xml, root, defaults)
    env_file = _xml_envmap_file(xml, env_elems, defaults)
    if env_file is not None:
        referenced.append(env_file)
    # Read the envmap first: read_image gives clearer errors than Mitsuba's loader.
    env_rgb = _read_envmap(env_file) if env_file is not None else None

    # Cameras and their reference images.
    scene = _load_mitsuba_scene(xml, referenced)
    cameras = _xml_cameras(xml, root, defaults, scene)
    images, alpha, has_alpha = _xml_images(xml, cameras, shrink or Shrink())

    # Known geometry.
    if mesh_arg is not None:
        mesh = load_mesh(mesh_arg)
    else:
        mesh = _scene_mesh(xml, scene)

    envmap, env_to_world = _xml_envmap(xml, scene, env_rgb)
    return Capture(xml, cameras, images, alpha, has_alpha, mesh, envmap, env_to_world, "mitsuba")


def _xml_envmap_elements(xml: Path, root: ET.Element, defaults: dict[str, str]) -> list[ET.Element]:
    """The <emitter> elements: only envmaps, at most one."""
    env_elems = []
    for elem in root.iter("emitter"):
        etype = _subst(elem.get("type"), defaults)
        if etype != "envmap":
            raise InputError(xml, f"unknown emitter type '{etype}': only envmap is supported "
                                  "(known lighting is an <emitter type=\"envmap\">)")
        env_elems.append(elem)
    if len(env_elems) > 1:
        raise InputError(xml, f"{len(env_elems)} envmap emitters; at most one is supported")
    return env_elems


def _xml_mesh_files(xml: Path, root: ET.Element, defaults: dict[str, str]) -> list[Path]:
    """The files of the <shape> elements (triangle meshes and spheres only), each checked to exist."""
    referenced: list[Path] = []
    for elem in root.iter("shape"):
        stype = _subst(elem.get("type"), defaults)
        if stype not in MESH_SHAPES + ("sphere",):
            raise InputError(xml, f"shape type '{stype}' is not supported as known geometry "
                                  "(use ply/obj/serialized meshes or spheres)")
        filename = _string_param(elem, "filename", defaults)
        if filename is not None:
            mesh_file = _xml_file(xml, filename)
            if not mesh_file.is_file():
                raise InputError(mesh_file, f"mesh file not found (shape '{stype}' in {xml.name})")
            referenced.append(mesh_file)
    return referenced


def _xml_envmap_file(xml: Path, env_elems: list[ET.Element], defaults: dict[str, str]) -> Path | None:
    """The envmap emitter's image file, checked to exist; None without an envmap."""
    if not env_elems:
        return None
    filename = _string_param(env_elems[0], "filename", defaults)
    if filename is None:
        raise InputError(xml, "envmap emitter has no filename parameter")
    env_file = _xml_file(xml, filename)
    if not env_file.is_file():
        raise InputError(env_file, f"envmap image not found (emitter in {xml.name})")
    return env_file


def _xml_images(xml: Path, cameras: list[Camera], shrink: Shrink) -> tuple[np.ndarray, np.ndarray, bool]:
    """The reference image images/<id>.exr or .png of every sensor, each shrunk as it is read, stacked
    (`_stack_images`); one InputError naming every missing or mis-sized image."""
    for cam in cameras[1:]:
        if (cam.width, cam.height) != (cameras[0].width, cameras[0].height):
            raise InputError(xml, f"sensor '{cam.name}' film is {cam.width}x{cam.height} but sensor "
                                  f"'{cameras[0].name}' film is {cameras[0].width}x{cameras[0].height}; "
                                  "all sensors of a capture must share one film size")
    entries, problems = [], []
    for cam in cameras:
        try:
            stem = xml.parent / "images" / cam.name
            img_path = _find_image(stem)
            if img_path is None:
                raise InputError(stem.parent / (stem.name + ".exr"),
                                 f"no reference image for sensor '{cam.name}' in {xml.name} "
                                 f"(expected images/{cam.name}.exr or images/{cam.name}.png)")
            rgb, alpha = read_image(img_path)
            h, w = rgb.shape[:2]
            if (w, h) != (cam.width, cam.height):
                raise InputError(img_path, f"image size {w}x{h} differs from the film size "
                                           f"{cam.width}x{cam.height} of sensor '{cam.name}' in {xml.name}")
            entries.append(_shrunk_entry(shrink, img_path, rgb, alpha))
            del rgb, alpha  # the full-size photo goes before the next one is read
        except InputError as exc:
            problems.append(exc)
    raise_all(problems, xml)
    return _stack_images(entries)


def _xml_envmap(xml: Path, scene, env_rgb: np.ndarray | None) -> tuple[np.ndarray | None, np.ndarray]:
    """Known lighting: (envmap times the emitter's scale, its to_world); (None, identity) without one."""
    envmap, env_to_world = None, np.eye(4)
    if env_rgb is not None:
        mi = _ensure_variant()
        emitters = [e for e in scene.emitters() if e.class_name() == "EnvironmentMapEmitter"]
        if len(emitters) != 1:
            raise InputError(xml, "Mitsuba did not load the envmap emitter")
        params = mi.traverse(emitters[0])
        env_to_world = _matrix(params["to_world"])
        scale = float(np.ravel(np.array(params["scale"]))[0]) if "scale" in params else 1.0
        envmap = (env_rgb * np.float32(scale)).astype(np.float32)
    return envmap, env_to_world


def _read_envmap(path: Path) -> np.ndarray:
    if path.suffix.lower() in IMAGE_EXTS:
        rgb, _ = read_image(path)
        return rgb
    # Radiance .hdr / .pfm and other formats Mitsuba reads itself.
    mi = _ensure_variant()
    try:
        bmp = mi.Bitmap(str(path)).convert(mi.Bitmap.PixelFormat.RGB, mi.Struct.Type.Float32, srgb_gamma=False)
        rgb = np.array(bmp, dtype=np.float32)
    except Exception as exc:
        raise InputError(path, f"cannot read envmap image ({exc})") from exc
    if not np.all(np.isfinite(rgb)):
        raise InputError(path, "image contains non-finite pixels (NaN or Inf)")
    return rgb.reshape(rgb.shape[0], rgb.shape[1], 3)


def _scene_mesh(xml: Path, scene):
    """All shapes of a loaded scene merged into one world-space trimesh (None without shapes)."""
    import trimesh

    mi = _ensure_variant()
    vertices, faces, normals, offset = [], [], [], 0
    for shape in scene.shapes():
        kind = shape.class_name()
        if isinstance(shape, mi.Mesh):
            v = np.array(shape.vertex_positions_buffer(), dtype=np.float64).reshape(-1, 3)
            f = np.array(shape.faces_buffer(), dtype=np.int64).reshape(-1, 3)
            if len(f) == 0:
                raise InputError(xml, f"shape '{shape.id() or kind}' has no triangles")
            if shape.has_vertex_normals():  # the shading normals the scene renders with
                n = np.array(shape.vertex_normals_buffer(), dtype=np.float64).reshape(-1, 3)
            else:
                n = np.asarray(trimesh.Trimesh(v, f, process=False).vertex_normals)
        elif kind == "Sphere":
            ico = trimesh.creation.icosphere(subdivisions=SPHERE_SUBDIVISIONS, radius=1.0)
            m = _matrix(mi.traverse(shape)["to_world"])
            v = np.asarray(ico.vertices, dtype=np.float64) @ m[:3, :3].T + m[:3, 3]
            f = np.asarray(ico.faces, dtype=np.int64)
            n = np.asarray(ico.vertices, dtype=np.float64) @ np.linalg.inv(m[:3, :3])  # the sphere's true normals
            n /= np.linalg.norm(n, axis=1, keepdims=True)
        else:
            raise InputError(xml, f"shape '{shape.id() or kind}' ({kind}) is not supported as known "
                                  "geometry (use ply/obj/serialized meshes or spheres)")
        if not np.all(np.isfinite(v)):
            raise InputError(xml, f"shape '{shape.id() or kind}' has non-finite vertex positions")
        vertices.append(v)
        faces.append(f + offset)
        normals.append(n)
        offset += len(v)
    if not vertices:
        return None
    return trimesh.Trimesh(np.concatenate(vertices), np.concatenate(faces), vertex_normals=np.concatenate(normals),
                           process=False)


# --------------------------------------------------------------------------------------------
# NeRF-synthetic json


def _read_json(path: Path) -> dict:
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(path, f"cannot read json file ({exc})") from exc
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise InputError(path, f"malformed json at line {exc.lineno}, column {exc.colno}: {exc.msg}") from exc
    if not isinstance(data, dict):
        raise InputError(path, "malformed capture json: the top level must be an object")
    return data


def _json_angle(path: Path, data: dict) -> float:
    if "camera_angle_x" not in data:
        raise InputError(path, "missing 'camera_angle_x' (horizontal field of view in radians; or nerfstudio's "
                               "'fl_x' / 'fl_y' focal lengths in pixels)")
    angle = data["camera_angle_x"]
    if not finite_number(angle) or not (MIN_FOV_DEG <= math.degrees(angle) <= MAX_FOV_DEG):
        raise InputError(path, f"'camera_angle_x' must be a number of radians in (0, pi) (a field of view of "
                               f"{MIN_FOV_DEG:g}..{MAX_FOV_DEG:g} degrees), got {angle!r}")
    return float(angle)


def _json_frames(path: Path, data: dict) -> list[dict]:
    frames = data.get("frames")
    if not isinstance(frames, list) or not frames:
        raise InputError(path, "no cameras: 'frames' is missing or empty")
    for i, frame in enumerate(frames):
        if not isinstance(frame, dict):
            raise InputError(path, f"frames[{i}] is not an object")
        if not isinstance(frame.get("file_path"), str) or not frame["file_path"]:
            raise InputError(path, f"frames[{i}] has no 'file_path'")
        if "transform_matrix" not in frame:
            raise InputError(path, f"frames[{i}] ({frame['file_path']}) has no 'transform_matrix'")
    first: dict[str, int] = {}
    for i, frame in enumerate(frames):  # one image counted twice would weigh twice in the fit
        key = _frame_key(frame["file_path"])
        if key in first:
            raise InputError(path, f"frames[{i}] ({frame['file_path']}) lists the image of frames[{first[key]}] "
                                   f"({frames[first[key]]['file_path']}) again: each image may appear once")
        first[key] = i
    return frames


def _frame_key(file_path: str) -> str:
    """A frame's image as a relative path spelled one way, without its image suffix (the frames
    "./a/../b/r_0" and "b/r_0.png" name one image)."""
    path = posixpath.normpath(file_path.replace("\\", "/"))
    return path[: -len(Path(path).suffix)] if Path(path).suffix.lower() in IMAGE_EXTS else path


def _frame_matrices(path: Path, frames: list[dict]) -> list[np.ndarray]:
    out = []
    for i, frame in enumerate(frames):
        try:
            m = np.array(frame["transform_matrix"], dtype=np.float64)
        except (TypeError, ValueError):
            m = None
        if m is None or m.shape != (4, 4) or not np.all(np.isfinite(m)):
            raise InputError(path, f"frames[{i}] ({frame['file_path']}): malformed transform_matrix "
                                   "(expected 4x4 finite numbers)")
        if abs(np.linalg.det(m[:3, :3])) < 1e-12:
            raise InputError(path, f"frames[{i}] ({frame['file_path']}): degenerate transform_matrix")
        check_pose(path, f"frames[{i}] ({frame['file_path']})", m)
        out.append(m)
    return out


def _json_cameras(path: Path, frames: list[dict], matrices: list[np.ndarray], angle: float, width: int,
                  height: int) -> list[Camera]:
    """The frames' cameras, each checked (vq_mitsuba.data.checks)."""
    cameras = []
    for i, (name, matrix) in enumerate(zip(_frame_names(frames), matrices)):
        cameras.append(nerf_to_camera(name, matrix, angle, width, height))
        check_camera(path, f"frames[{i}] ({frames[i]['file_path']})", cameras[-1])
    return cameras


def _frame_names(frames: list[dict]) -> list[str]:
    """The frames' names: their image file names without the image suffix, or, where two of these
    agree (train/r_0 and test/r_0), the relative paths (made file names by `named_views`)."""
    paths = [_frame_key(f["file_path"]) for f in frames]
    stems = [posixpath.basename(p) for p in paths]
    return stems if len(set(stems)) == len(stems) else paths


def _frame_image_candidates(path: Path, frame: dict) -> list[Path]:
    p = path.parent / frame["file_path"]
    if p.suffix.lower() in IMAGE_EXTS:
        return [p]
    return [p.parent / (p.name + ".exr"), p.parent / (p.name + ".png")]


def _frame_image(path: Path, i: int, frame: dict) -> Path:
    candidates = _frame_image_candidates(path, frame)
    for c in candidates:
        if c.is_file():
            return c
    expected = " or ".join(str(c) for c in candidates)
    raise InputError(candidates[0], f"image not found for frames[{i}] of {path.name} (expected {expected})")


def _json_image_size(path: Path, data: dict, frames: list[dict]) -> tuple[int, int]:
    """(width, height) for cameras-only loading: 'w'/'h' keys, else the first image found."""
    w, h = data.get("w"), data.get("h")
    if w is not None and h is not None:
        check_size(path, "'w' and 'h'", w, h)
        return int(w), int(h)
    for frame in frames:
        for c in _frame_image_candidates(path, frame):
            if c.is_file():
                rgb, _ = read_image(c)
                return int(rgb.shape[1]), int(rgb.shape[0])
    raise InputError(path, "cannot tell the image size: no 'w'/'h' keys and no frame image exists")


def _nerfstudio_cameras(path: Path, data: dict, frames: list[dict]):
    """(cameras, lenses) of a nerfstudio-style json (vq_mitsuba.data.nerfstudio)."""
    from vq_mitsuba.data.nerfstudio import nerfstudio_cameras

    return nerfstudio_cameras(path, data, frames, _frame_matrices(path, frames), _frame_names(frames),
                              lambda i: _frame_image(path, i, frames[i]))


def _json_mesh(path: Path, mesh_arg: str | Path | None):
    if mesh_arg is not None:
        return load_mesh(mesh_arg)
    if (path.parent / "mesh.ply").exists():
        return load_mesh(path.parent / "mesh.ply")
    return None


def _load_nerfstudio_capture(path: Path, data: dict, frames: list[dict], mesh_arg, shrink: Shrink,
                             cache_dir) -> Capture:
    """A nerfstudio transforms.json: distorted photos undistorted (and cached), masks multiplied into
    alpha, each photo shrunk as it is read."""
    from vq_mitsuba.data.nerfstudio import envmap_frame, mask_paths
    from vq_mitsuba.data.photo_captures import read_views

    cameras, lenses = _nerfstudio_cameras(path, data, frames)
    masks = mask_paths(path, frames)
    problems, paths = [], []
    for i, frame in enumerate(frames):
        try:
            paths.append(_frame_image(path, i, frame))
        except InputError as exc:
            problems.append(exc)
    raise_all(problems, path)
    images, alpha, has_alpha = read_views(path, cameras, paths, masks, lenses, cache_dir, shrink)
    return Capture(path, cameras, images, alpha, has_alpha, _json_mesh(path, mesh_arg), None, envmap_frame(cameras),
                   "blender")


def _load_json_capture(path: Path, mesh_arg: str | Path | None, shrink: Shrink | None = None,
                       cache_dir=None) -> Capture:
    from vq_mitsuba.data.nerfstudio import is_nerfstudio

    shrink = shrink or Shrink()
    data = _read_json(path)
    frames = _json_frames(path, data)
    if is_nerfstudio(data):
        return _load_nerfstudio_capture(path, data, frames, mesh_arg, shrink, cache_dir)
    angle = _json_angle(path, data)
    matrices = _frame_matrices(path, frames)

    entries, first, problems = [], None, []
    for i, frame in enumerate(frames):
        try:
            img_path = _frame_image(path, i, frame)
            rgb, alpha = read_image(img_path)
            h, w = rgb.shape[:2]
            if first is None:
                first = (img_path, w, h)
            elif (w, h) != first[1:]:
                raise InputError(img_path, f"image size {w}x{h} differs from {first[0].name} "
                                           f"({first[1]}x{first[2]}); all frames must share one size")
            entries.append(_shrunk_entry(shrink, img_path, rgb, alpha))
            del rgb, alpha  # the full-size photo goes before the next one is read
        except InputError as exc:
            problems.append(exc)
    raise_all(problems, path)
    images, alpha, has_alpha = _stack_images(entries)
    width, height = first[1], first[2]
    cameras = _json_cameras(path, frames, matrices, angle, width, height)
    return Capture(path, cameras, images, alpha, has_alpha, _json_mesh(path, mesh_arg), None,
                   BLENDER_ENV_TO_WORLD.copy(), "blender")
