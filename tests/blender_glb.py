"""Import an exported .glb into Blender and render one view with Cycles under the exported
envmap (run with .venv-cycles/bin/python by tests/export/test_export.py, not imported by pytest).

    blender_glb.py JOB.json    JOB: glb, envmap, camera {name, transform_matrix, camera_angle_x,
                               width, height} (Blender world, OpenGL axes), samples, max_bounces, output
Prints one JSON line: the imported material's texture sizes and sockets it feeds.
"""

import json
import os
import sys

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "vq_mitsuba", "synthetic"))
import cycles_worker as worker  # noqa: E402  (removes its own folder from sys.path before importing bpy)

import bpy  # noqa: E402


def main(job_path: str) -> None:
    with open(job_path) as f:
        job = json.load(f)
    scene = worker._reset()
    worker._setup_render(scene, {"render": {"samples": job["samples"], "max_bounces": job["max_bounces"], "seed": 0},
                                  "inputs": []})  # no AOVs: the glTF importer builds the material
    bpy.ops.preferences.addon_enable(module="io_scene_gltf2")
    bpy.ops.import_scene.gltf(filepath=job["glb"])
    meshes = [o for o in scene.objects if o.type == "MESH"]
    material = meshes[0].active_material
    links = {link.to_socket.name: link.from_node.bl_idname for link in material.node_tree.links}
    images = sorted([img.size[0], img.size[1]] for img in bpy.data.images)
    cam = worker._camera_object(scene, job["camera"])
    scene.camera = cam
    scene.render.resolution_x = int(job["camera"]["width"])
    scene.render.resolution_y = int(job["camera"]["height"])
    env = worker._world(scene)
    env.image = bpy.data.images.load(job["envmap"])
    scene.render.filepath = job["output"]
    bpy.ops.render.render(write_still=True)
    print(json.dumps({"images": images, "linked_sockets": sorted(links)}))


if __name__ == "__main__":
    main(sys.argv[1])
