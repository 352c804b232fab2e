"""Render a job file with Blender Cycles (run by `vq_mitsuba.synthetic.cycles`, not imported by the package).

    .venv-cycles/bin/python vq_mitsuba/synthetic/cycles_worker.py JOB.json

This script runs inside Blender-as-a-module's own environment (`make cycles`), so it imports only
bpy, numpy and the standard library. The job file (written by `vq_mitsuba.synthetic.cycles.build_job`)
holds everything in Blender world (Z up):

    render     samples, seed, max_bounces, denoise, filter_width, threads
    inputs     [{name, channels, principled, blender, patterned}]: the BRDF inputs (vq_mitsuba.brdf)
    materials  [{name, id, vertex_colors, and each input's value under its principled name (the
                patterned colour's null where vertex_colors)}]
    shapes     [{name, material, vertices, faces, normals, colors (per-vertex RGB or null)}]
    cameras    [{name, transform_matrix (camera-to-world, OpenGL axes), camera_angle_x, width, height}]
    renders    [{camera, envmap (lat-long EXR path), output (multilayer EXR path)}]

Every render is written as one multilayer OpenEXR (32-bit float) holding the view layer's
passes: Combined (RGBA, linear, premultiplied, transparent film), Normal (world), Material
Index (IndexMA: the material pass index = the material's id, 0 = background) and one shader AOV per
BRDF input, named as the input (a colour's COLOR, a scalar's VALUE). The calling process turns them into the dataset
layout. One line `rendered I/N NAME` is printed per finished render.
"""

from __future__ import annotations

import json
import os
import sys
import time

# The folder of this script holds vq_mitsuba/cycles.py, which would shadow Blender's own `cycles`
# add-on package: take it off the import path before bpy loads its add-ons.
_HERE = os.path.dirname(os.path.abspath(__file__))
sys.path[:] = [p for p in sys.path if os.path.abspath(p or os.curdir) != _HERE]

import bpy  # noqa: E402
import mathutils  # noqa: E402  (ships with bpy)
import numpy as np  # noqa: E402

def _reset() -> bpy.types.Scene:
    bpy.ops.wm.read_factory_settings(use_empty=True)
    return bpy.context.scene


def _setup_render(scene, job: dict) -> None:
    r = job["render"]
    scene.render.engine = "CYCLES"
    cy = scene.cycles
    cy.device = "CPU"
    cy.samples = int(r["samples"])
    cy.use_adaptive_sampling = False
    cy.use_denoising = bool(r.get("denoise", False))
    cy.max_bounces = int(r["max_bounces"])
    cy.diffuse_bounces = int(r["max_bounces"])
    cy.glossy_bounces = int(r["max_bounces"])
    cy.transmission_bounces = int(r["max_bounces"])
    cy.transparent_max_bounces = 8
    cy.sample_clamp_direct = 0.0  # no clamping: unbiased, like Mitsuba's path tracer
    cy.sample_clamp_indirect = 0.0
    cy.blur_glossy = 0.0
    cy.caustics_reflective = True
    cy.caustics_refractive = True
    cy.pixel_filter_type = "BOX"
    cy.filter_width = float(r.get("filter_width", 1.0))
    scene.render.film_transparent = True
    scene.render.use_compositing = False  # save the render layers' passes, not a compositor output
    scene.render.use_sequencer = False
    scene.render.resolution_percentage = 100
    scene.render.pixel_aspect_x = scene.render.pixel_aspect_y = 1.0
    scene.render.use_persistent_data = True  # keep the BVH and textures between renders
    threads = int(r.get("threads", 0))
    scene.render.threads_mode = "FIXED" if threads > 0 else "AUTO"
    if threads > 0:
        scene.render.threads = threads
    scene.view_settings.view_transform = "Standard"
    scene.view_settings.look = "None"
    scene.view_settings.exposure = 0.0
    scene.view_settings.gamma = 1.0
    img = scene.render.image_settings
    if hasattr(img, "media_type"):  # Blender >= 5.0: multilayer EXR is a media type
        img.media_type = "MULTI_LAYER_IMAGE"
    img.file_format = "OPEN_EXR_MULTILAYER"
    img.color_depth = "32"
    img.exr_codec = "ZIP"
    img.color_mode = "RGBA"
    vl = scene.view_layers[0]
    vl.use_pass_combined = True
    vl.use_pass_normal = True
    vl.use_pass_material_index = True
    for inp in job["inputs"]:
        aov = vl.aovs.add()
        aov.name = inp["name"]
        aov.type = "COLOR" if inp["channels"] == 3 else "VALUE"


def _material(m: dict, inputs: list[dict]) -> bpy.types.Material:
    mat = bpy.data.materials.new(m["name"])
    mat.use_nodes = True
    mat.pass_index = int(m["id"])
    nt = mat.node_tree
    for node in list(nt.nodes):
        nt.nodes.remove(node)
    out = nt.nodes.new("ShaderNodeOutputMaterial")
    bsdf = nt.nodes.new("ShaderNodeBsdfPrincipled")
    bsdf.distribution = "GGX"  # single-scatter GGX, as Mitsuba's principled
    bsdf.inputs["IOR"].default_value = 1.5
    bsdf.inputs["Specular IOR Level"].default_value = 0.5  # F0 = 0.04, Mitsuba's specular 0.5
    nt.links.new(bsdf.outputs["BSDF"], out.inputs["Surface"])
    for inp in inputs:  # each BRDF input feeds its Principled socket and its AOV
        value = m[inp["principled"]]
        if inp["channels"] == 3:
            if inp["patterned"] and m.get("vertex_colors"):
                node = nt.nodes.new("ShaderNodeAttribute")  # the mesh's "vertex_color" attribute
                node.attribute_type = "GEOMETRY"
                node.attribute_name = "vertex_color"
            else:
                node = nt.nodes.new("ShaderNodeRGB")
                node.outputs["Color"].default_value = (*map(float, value), 1.0)
            nt.links.new(node.outputs["Color"], bsdf.inputs[inp["blender"]])
        else:
            bsdf.inputs[inp["blender"]].default_value = float(value)
        aov = nt.nodes.new("ShaderNodeOutputAOV")
        aov.aov_name = inp["name"]
        if inp["channels"] == 3:
            nt.links.new(node.outputs["Color"], aov.inputs["Color"])
        else:
            aov.inputs["Value"].default_value = float(value)
    return mat


def _mesh_object(scene, s: dict, mat: bpy.types.Material) -> bpy.types.Object:
    v = np.asarray(s["vertices"], dtype=np.float64).reshape(-1, 3)
    f = np.asarray(s["faces"], dtype=np.int64).reshape(-1, 3)
    n = np.asarray(s["normals"], dtype=np.float64).reshape(-1, 3)
    mesh = bpy.data.meshes.new(s["name"])
    mesh.from_pydata(v.tolist(), [], f.tolist())
    mesh.update()
    if len(mesh.vertices) != len(v) or len(mesh.polygons) != len(f):
        raise RuntimeError(f"shape {s['name']}: Blender changed the mesh topology "
                           f"({len(mesh.vertices)} vertices / {len(mesh.polygons)} faces)")
    mesh.shade_smooth()
    mesh.normals_split_custom_set_from_vertices(n.tolist())  # the exact normals Mitsuba uses
    if s.get("colors") is not None:
        c = np.asarray(s["colors"], dtype=np.float32).reshape(-1, 3)
        attr = mesh.color_attributes.new(name="vertex_color", type="FLOAT_COLOR", domain="POINT")
        rgba = np.concatenate([c, np.ones((len(c), 1), np.float32)], 1)
        attr.data.foreach_set("color", rgba.ravel())  # FLOAT_COLOR: scene-linear, as given
    mesh.materials.append(mat)
    obj = bpy.data.objects.new(s["name"], mesh)
    scene.collection.objects.link(obj)
    return obj


def _camera_object(scene, c: dict) -> bpy.types.Object:
    cam = bpy.data.cameras.new(c["name"])
    cam.sensor_fit = "HORIZONTAL"
    cam.angle_x = float(c["camera_angle_x"])
    cam.clip_start = 1e-3
    cam.clip_end = 1e4
    obj = bpy.data.objects.new(c["name"], cam)
    scene.collection.objects.link(obj)
    # A plain list is silently ignored by matrix_world: it takes a mathutils.Matrix (rows).
    m = mathutils.Matrix([list(map(float, row)) for row in np.asarray(c["transform_matrix"]).reshape(4, 4)])
    obj.matrix_world = m
    if (obj.matrix_world.translation - m.translation).length > 1e-6:
        raise RuntimeError(f"camera {c['name']}: matrix_world was not applied")
    return obj


def _world(scene) -> bpy.types.ShaderNode:
    world = bpy.data.worlds.new("World")
    world.use_nodes = True
    nt = world.node_tree
    for node in list(nt.nodes):
        nt.nodes.remove(node)
    out = nt.nodes.new("ShaderNodeOutputWorld")
    bg = nt.nodes.new("ShaderNodeBackground")
    bg.inputs["Strength"].default_value = 1.0
    env = nt.nodes.new("ShaderNodeTexEnvironment")
    env.projection = "EQUIRECTANGULAR"
    env.interpolation = "Linear"
    nt.links.new(env.outputs["Color"], bg.inputs["Color"])
    nt.links.new(bg.outputs["Background"], out.inputs["Surface"])
    scene.world = world
    return env


def run(job: dict) -> None:
    scene = _reset()
    _setup_render(scene, job)
    mats = {m["name"]: _material(m, job["inputs"]) for m in job["materials"]}
    for s in job["shapes"]:
        _mesh_object(scene, s, mats[s["material"]])
    cams = {c["name"]: (_camera_object(scene, c), c) for c in job["cameras"]}
    env_node = _world(scene)
    images: dict[str, bpy.types.Image] = {}
    base_seed = int(job["render"].get("seed", 0))
    renders = job["renders"]
    t0 = time.time()
    for i, r in enumerate(renders):
        obj, c = cams[r["camera"]]
        scene.camera = obj
        scene.render.resolution_x = int(c["width"])
        scene.render.resolution_y = int(c["height"])
        path = r["envmap"]
        if path not in images:
            img = bpy.data.images.load(path, check_existing=True)
            img.colorspace_settings.is_data = False
            images[path] = img
        if env_node.image != images[path]:
            env_node.image = images[path]
        scene.cycles.seed = (base_seed * 1_000_003 + i) % 2**31  # a new noise pattern per render
        scene.render.filepath = r["output"]
        bpy.ops.render.render(write_still=True)
        print(f"rendered {i + 1}/{len(renders)} {r['camera']} ({time.time() - t0:.1f} s)", flush=True)


def main(argv: list[str]) -> int:
    if len(argv) != 1:
        print("usage: cycles_worker.py JOB.json", file=sys.stderr)
        return 2
    with open(argv[0]) as f:
        job = json.load(f)
    run(job)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
