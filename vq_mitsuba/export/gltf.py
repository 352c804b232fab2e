"""glTF 2.0 binary (.glb): one mesh with the metallic-roughness PBR material.

basecolor is an sRGB texture; metallic and roughness share one linear texture (roughness in G,
metallic in B), as the specification asks. glTF's roughness is the same perceptual roughness
as Mitsuba's `principled` (alpha = roughness^2). Axes are Y up, in the capture's own world
(`files.export_axes`). Fitted point lamps become `KHR_lights_punctual` point lights: their colour
the RGB intensity over its largest channel, their intensity that channel in candela at 683 lm/W
(the factor Blender's importer divides by again).
"""

from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np

from vq_mitsuba import brdf
from vq_mitsuba.data.imageio import written
from vq_mitsuba.export.bake import BakedMesh
from vq_mitsuba.export.files import png_bytes, texture_images

FLOAT, UINT32 = 5126, 5125
ARRAY_BUFFER, ELEMENT_ARRAY_BUFFER = 34962, 34963
LINEAR, LINEAR_MIPMAP_LINEAR, CLAMP_TO_EDGE = 9729, 9987, 33071
LUMENS_PER_WATT = 683.0  # radiant (W/sr) to luminous (cd) intensity, as glTF importers convert back


def _pad4(data: bytes, fill: bytes = b"\0") -> bytes:
    return data + fill * (-len(data) % 4)


def _lights(lamps: np.ndarray | None, rot: np.ndarray) -> tuple[list[dict], list[dict]]:
    """(KHR_lights_punctual's lights, their nodes) of lamps (K, 6: run-world position, RGB intensity)."""
    lights, nodes = [], []
    for k, lamp in enumerate(() if lamps is None else np.asarray(lamps, np.float64)):
        peak = float(max(lamp[3:].max(), 1e-12))
        lights.append({"type": "point", "name": f"lamp_{k}", "color": (lamp[3:] / peak).tolist(),
                       "intensity": LUMENS_PER_WATT * peak})
        nodes.append({"name": f"lamp_{k}", "translation": (rot @ lamp[:3]).tolist(),
                      "extensions": {"KHR_lights_punctual": {"light": k}}})
    return lights, nodes


def write_glb(path: Path, baked: BakedMesh, axes: np.ndarray, name: str = "object",
              lamps: np.ndarray | None = None) -> Path:
    """`path` holding the baked mesh turned by `axes` (3, 3), run world -> the file's axes, and the
    point `lamps` (K, 6: position, RGB intensity) as lights."""
    rot = np.asarray(axes, np.float64)
    positions = (baked.vertices.astype(np.float64) @ rot.T).astype(np.float32)
    normals = baked.normals.astype(np.float64) @ rot.T
    normals = (normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)).astype(np.float32)
    uvs = baked.uvs.astype(np.float32)
    indices = baked.faces.astype(np.uint32)
    images = texture_images(baked)
    blobs = [positions.tobytes(), normals.tobytes(), uvs.tobytes(), indices.tobytes(),
             png_bytes(images[brdf.BASECOLOR]), png_bytes(images["metallic_roughness"])]  # glTF's two slots
    views, body, offset = [], b"", 0
    targets = [ARRAY_BUFFER, ARRAY_BUFFER, ARRAY_BUFFER, ELEMENT_ARRAY_BUFFER, None, None]
    for blob, target in zip(blobs, targets):
        view = {"buffer": 0, "byteOffset": offset, "byteLength": len(blob)}
        if target is not None:
            view["target"] = target
        views.append(view)
        padded = _pad4(blob)
        body += padded
        offset += len(padded)
    lights, light_nodes = _lights(lamps, rot)
    doc = {
        "asset": {"version": "2.0", "generator": "vq-mitsuba"},
        "scene": 0,
        "scenes": [{"nodes": list(range(1 + len(light_nodes)))}],
        "nodes": [{"mesh": 0, "name": name}, *light_nodes],
        "meshes": [{"name": name, "primitives": [{
            "attributes": {"POSITION": 0, "NORMAL": 1, "TEXCOORD_0": 2}, "indices": 3, "material": 0}]}],
        "materials": [{"name": f"{name}_material", "doubleSided": True, "pbrMetallicRoughness": {
            "baseColorTexture": {"index": 0}, "metallicRoughnessTexture": {"index": 1},
            "baseColorFactor": [1.0, 1.0, 1.0, 1.0], "metallicFactor": 1.0, "roughnessFactor": 1.0}}],
        "textures": [{"sampler": 0, "source": 0}, {"sampler": 0, "source": 1}],
        "images": [{"bufferView": 4, "mimeType": "image/png", "name": brdf.BASECOLOR},
                   {"bufferView": 5, "mimeType": "image/png", "name": "metallic_roughness"}],
        "samplers": [{"magFilter": LINEAR, "minFilter": LINEAR_MIPMAP_LINEAR, "wrapS": CLAMP_TO_EDGE,
                      "wrapT": CLAMP_TO_EDGE}],
        "accessors": [
            {"bufferView": 0, "componentType": FLOAT, "count": len(positions), "type": "VEC3",
             "min": positions.min(0).tolist(), "max": positions.max(0).tolist()},
            {"bufferView": 1, "componentType": FLOAT, "count": len(normals), "type": "VEC3"},
            {"bufferView": 2, "componentType": FLOAT, "count": len(uvs), "type": "VEC2"},
            {"bufferView": 3, "componentType": UINT32, "count": int(indices.size), "type": "SCALAR"},
        ],
        "bufferViews": views,
        "buffers": [{"byteLength": len(body)}],
    }
    if lights:
        doc["extensionsUsed"] = ["KHR_lights_punctual"]
        doc["extensions"] = {"KHR_lights_punctual": {"lights": lights}}
    js = _pad4(json.dumps(doc, separators=(",", ":")).encode(), b" ")
    total = 12 + 8 + len(js) + 8 + len(body)
    data = (struct.pack("<III", 0x46546C67, 2, total) + struct.pack("<II", len(js), 0x4E4F534A) + js
            + struct.pack("<II", len(body), 0x004E4942) + body)
    written(path, lambda: Path(path).write_bytes(data))
    return path
