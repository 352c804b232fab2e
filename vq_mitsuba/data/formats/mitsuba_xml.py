"""Mitsuba scene XML: sensors, their reference images, optional known geometry and lighting, in
Mitsuba's world (Y up).

    scene.xml          <sensor id="ID" type="perspective"> elements (pinhole; a film size shared by
                       all), optional <shape> geometry (ply / obj / serialized meshes, spheres) and
                       at most one <emitter type="envmap">
    images/ID.exr      the reference image of sensor ID (or ID.png), alpha optional
    meshes, envmap     wherever the XML's filename parameters say (relative to the XML)

The XML text is checked before Mitsuba loads anything, for clear messages.
`write_capture` writes the synthetic scenes' XML (vq_mitsuba.synthetic.mitsuba_scenes).
"""

from __future__ import annotations

import re
import xml.etree.ElementTree as ET
from pathlib import Path
from xml.sax.saxutils import quoteattr

import numpy as np

from vq_mitsuba import brdf
from vq_mitsuba.data.cameras import Camera, principal_xml
from vq_mitsuba.data.checks import check_camera, finite_number
from vq_mitsuba.data.envmaps import check_envmap, load_envmap
from vq_mitsuba.data.formats.common import (Capture, ensure_variant, find_image, has_suffix, load_mesh,
                                            shrunk_entry, stack_images)
from vq_mitsuba.data.imageio import read_image, written
from vq_mitsuba.data.resize import Shrink
from vq_mitsuba.errors import InputError, raise_all

KIND = "xml"
SUFFIXES = (".xml",)
FOLDER_FILES = ("scene.xml",)  # the file a capture folder holds
DESCRIPTION = "a Mitsuba scene .xml (scene.xml in a folder)"  # what a person gives, in messages and help
POSED = True
points = sphere = None  # no sparse points, no region of interest
MESH_SHAPES = ("ply", "obj", "serialized", "cube")  # loaded by Mitsuba as triangle meshes
# How deep elements may nest: a scene nests a few levels, and Mitsuba's parser recurses per level
# (about 10000 levels overflow its stack: the process ends in a segmentation fault).
MAX_XML_DEPTH = 64
SPHERE_SUBDIVISIONS = 4


def detect(source: Path) -> bool:
    return has_suffix(source, SUFFIXES)


def has_geometry(xml: Path) -> bool:
    """Whether the scene brings its own geometry (<shape> elements); reads no mesh or image."""
    try:
        root = ET.parse(xml).getroot()
    except (ET.ParseError, OSError):
        return True  # the loader reports the problem
    return any(True for _ in root.iter("shape"))


def cameras(xml: Path) -> tuple[list[Camera], str]:
    """(the sensors' cameras, "mitsuba"), without loading meshes or bitmaps."""
    root, defaults = _parse_xml(xml)
    scene = _load_mitsuba_sensors_only(xml, root)
    return _xml_cameras(xml, root, defaults, scene), "mitsuba"


def load(xml: Path, mesh_arg: str | Path | None, shrink: Shrink | None = None, cache_dir=None) -> Capture:
    """The capture: sensors, their images (each shrunk as it is read), the shapes as one mesh (or
    `mesh_arg`), the envmap times its scale and its to_world."""
    root, defaults = _parse_xml(xml)
    # The text is checked before Mitsuba loads anything, for clear messages.
    env_elems = _xml_envmap_elements(xml, root, defaults)
    referenced = _xml_mesh_files(xml, root, defaults)
    env_file = _xml_envmap_file(xml, env_elems, defaults)
    if env_file is not None:
        referenced.append(env_file)
    # Read and check the envmap first (the one envmap check): clearer errors than Mitsuba's loader.
    env_rgb = load_envmap(env_file, hdr_only=False) if env_file is not None else None

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


def _matrix(transform) -> np.ndarray:
    """A Mitsuba (Affine)Transform4f as a (4, 4) float64 array, in any variant."""
    m = np.array(transform.matrix, dtype=np.float64)
    if m.ndim == 3:
        m = m[..., 0]
    return m.reshape(4, 4)


def _parse_xml(xml: Path) -> tuple[ET.Element, dict[str, str]]:
    try:
        root = ET.parse(xml).getroot()
    except ET.ParseError as exc:
        raise InputError(xml, f"XML parse error ({exc})") from exc
    except OSError as exc:
        raise InputError(xml, f"cannot read scene file ({exc})") from exc
    if root.tag != "scene":
        raise InputError(xml, f"not a Mitsuba scene (root element is <{root.tag}>, expected <scene>)")
    stack = [(root, 1)]
    while stack:  # iteratively: the check must not recurse either
        elem, depth = stack.pop()
        if depth > MAX_XML_DEPTH:
            raise InputError(xml, f"elements nest more than {MAX_XML_DEPTH} levels deep (a <{elem.tag}> at level "
                                  f"{depth}); a scene nests a few")
        stack.extend((child, depth + 1) for child in elem)
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
    mi = ensure_variant()
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
    mi = ensure_variant()
    stripped = ET.Element("scene", dict(root.attrib))
    for child in root:
        if child.tag in ("default", "sensor"):
            stripped.append(child)
    try:
        return mi.load_string(ET.tostring(stripped, encoding="unicode"))
    except Exception as exc:
        raise InputError(xml, f"Mitsuba cannot load the sensors: {exc}") from exc


def _xml_cameras(xml: Path, root: ET.Element, defaults: dict[str, str], scene) -> list[Camera]:
    mi = ensure_variant()
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
    (`stack_images`); one InputError naming every missing or mis-sized image."""
    for cam in cameras[1:]:
        if (cam.width, cam.height) != (cameras[0].width, cameras[0].height):
            raise InputError(xml, f"sensor '{cam.name}' film is {cam.width}x{cam.height} but sensor "
                                  f"'{cameras[0].name}' film is {cameras[0].width}x{cameras[0].height}; "
                                  "all sensors of a capture must share one film size")
    entries, problems = [], []
    for cam in cameras:
        try:
            stem = xml.parent / "images" / cam.name
            img_path = find_image(stem)
            if img_path is None:
                raise InputError(stem.parent / (stem.name + ".exr"),
                                 f"no reference image for sensor '{cam.name}' in {xml.name} "
                                 f"(expected images/{cam.name}.exr or images/{cam.name}.png)")
            rgb, alpha = read_image(img_path)
            h, w = rgb.shape[:2]
            if (w, h) != (cam.width, cam.height):
                raise InputError(img_path, f"image size {w}x{h} differs from the film size "
                                           f"{cam.width}x{cam.height} of sensor '{cam.name}' in {xml.name}")
            entries.append(shrunk_entry(shrink, img_path, rgb, alpha))
            del rgb, alpha  # the full-size photo goes before the next one is read
        except InputError as exc:
            problems.append(exc)
    raise_all(problems, xml)
    return stack_images(entries)


def _xml_envmap(xml: Path, scene, env_rgb: np.ndarray | None) -> tuple[np.ndarray | None, np.ndarray]:
    """Known lighting: (envmap times the emitter's scale, its to_world); (None, identity) without one."""
    envmap, env_to_world = None, np.eye(4)
    if env_rgb is not None:
        mi = ensure_variant()
        emitters = [e for e in scene.emitters() if e.class_name() == "EnvironmentMapEmitter"]
        if len(emitters) != 1:
            raise InputError(xml, "Mitsuba did not load the envmap emitter")
        params = mi.traverse(emitters[0])
        env_to_world = _matrix(params["to_world"])
        scale = float(np.ravel(np.array(params["scale"]))[0]) if "scale" in params else 1.0
        envmap = check_envmap(env_rgb * np.float32(scale), xml)  # times the emitter's scale: checked again
    return envmap, env_to_world


def _scene_mesh(xml: Path, scene):
    """All shapes of a loaded scene merged into one world-space trimesh (None without shapes)."""
    import trimesh

    mi = ensure_variant()
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
# Writer
# --------------------------------------------------------------------------------------------
def write_capture(path: Path, cameras: list[Camera], materials: list[dict], shapes: list[dict], spp: int,
                  sampler: str, note: str) -> None:
    """A scene XML: principled `materials` ({"name", and each BRDF input's value under its principled
    parameter: an RGB, or None for the meshes' vertex_color attribute, or a float}; bsdf id "mat_NAME"), ply `shapes` ({"name",
    "material", "file" relative to the XML}), one perspective sensor per camera (its RGBA film, a
    `sampler` of `spp` samples), no emitter; `note` is its opening comment."""
    parts = ['<?xml version="1.0" encoding="utf-8"?>', f"<!-- {note} -->", '<scene version="3.0.0">']
    parts += [_bsdf_xml(m) for m in materials]
    for s in shapes:
        parts += [f'    <shape type="ply" id={quoteattr(s["name"])}>',
                  f'        <string name="filename" value="{s["file"]}"/>',
                  f'        <ref id={quoteattr("mat_" + s["material"])}/>',
                  '    </shape>']
    parts += [_sensor_xml(c, spp, sampler) for c in cameras]
    parts.append("</scene>\n")
    written(path, lambda: path.write_text("\n".join(parts)))


def _fmt(x) -> str:
    return f"{float(x):.9g}"


def _bsdf_xml(mat: dict) -> str:
    lines = [f'    <bsdf type="principled" id={quoteattr("mat_" + mat["name"])}>']
    for i in brdf.INPUTS:
        key, value = i.principled, mat[i.principled]
        if i.colour and value is None:
            lines += [f'        <texture type="mesh_attribute" name="{key}">',
                      '            <string name="name" value="vertex_color"/>',
                      '        </texture>']
        elif i.colour:
            lines.append(f'        <rgb name="{key}" value="{", ".join(_fmt(c) for c in value)}"/>')
        else:
            lines.append(f'        <float name="{key}" value="{_fmt(value)}"/>')
    lines += [f'        <float name="{key}" value="{_fmt(value)}"/>' for key, value in brdf.FIXED.items()]
    lines.append('    </bsdf>')
    return "\n".join(lines)


def _sensor_xml(cam: Camera, spp: int, sampler: str) -> str:
    m = " ".join(_fmt(x) for x in cam.to_world.ravel())
    return "\n".join([
        f'    <sensor type="perspective" id={quoteattr(cam.name)}>',
        f'        <float name="fov" value="{_fmt(cam.fov_x_deg)}"/>',
        '        <string name="fov_axis" value="x"/>',
        *([principal_xml(cam, "        ").rstrip("\n")] if cam.principal is not None else []),
        '        <float name="near_clip" value="0.001"/>',
        '        <float name="far_clip" value="10000"/>',
        f'        <transform name="to_world"><matrix value="{m}"/></transform>',
        f'        <sampler type="{sampler}"><integer name="sample_count" value="{int(spp)}"/></sampler>',
        '        <film type="hdrfilm">',
        f'            <integer name="width" value="{cam.width}"/>',
        f'            <integer name="height" value="{cam.height}"/>',
        '            <string name="pixel_format" value="rgba"/>',
        '            <rfilter type="box"/>',
        '        </film>',
        '    </sensor>'])
