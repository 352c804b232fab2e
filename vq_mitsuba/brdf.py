"""The BRDF inputs, declared once: what the material fields predict, what Mitsuba's `principled`
BSDF takes from them, and the keys of every material dict, `materials.json`, edit and map file.

A material is a dict {name: value} over `NAMES`: per point a tensor (N, 3) for a colour and (N,)
for a scalar, or for one material a list of 3 floats and a float. Adding an input is one entry here
and its decoder (`vq_mitsuba.models.fields.BRDFDecoder`): everything that handles every input
(scores, the editor, edits, ground truth, exports) loops over `INPUTS`, and what is particular to one
input is a field of its entry. Code that states a rule about one input (the Lambertian prior's
metallic, metals at the roughness floor, the albedo's scale alignment) names it by its handle
(`BASECOLOR`, `METALLIC`, `ROUGHNESS`), never by a string.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class BrdfInput:
    name: str  # the key of the input everywhere (material dicts, materials.json, map files)
    channels: int  # 3: a linear RGB colour; 1: a scalar
    principled: str  # the parameter of Mitsuba's principled BSDF it feeds (and a scene spec's key)
    blender: str  # the socket of Blender's Principled BSDF it feeds (the Cycles ground truth)
    low: float = 0.0  # its range (a decoder may keep a config floor above `low`)
    high: float = 1.0
    step: float = 0.01  # the editor's slider step (a scalar's)
    default: float | None = None  # a scalar's value where a scene spec leaves it out, the editor's first; None: required
    gltf_channel: int | None = None  # its channel of glTF's metallicRoughnessTexture; None: a texture of its own

    @property
    def colour(self) -> bool:
        return self.channels == 3


BASECOLOR, METALLIC, ROUGHNESS = "basecolor", "metallic", "roughness"  # handles for rules about one input

INPUTS = (BrdfInput(BASECOLOR, 3, "base_color", "Base Color"),
          BrdfInput(METALLIC, 1, "metallic", "Metallic", default=0.0, gltf_channel=2),
          BrdfInput(ROUGHNESS, 1, "roughness", "Roughness", default=0.5, gltf_channel=1))
NAMES = tuple(i.name for i in INPUTS)
CHANNELS = sum(i.channels for i in INPUTS)  # values per point, the colours' three each
FIXED = {"specular": 0.5}  # principled's parameters the fit holds, not learned


def get(name: str) -> BrdfInput | None:
    """The declared input called `name` (None for another key); reads `INPUTS` at each call."""
    return next((i for i in INPUTS if i.name == name), None)


def select(material: dict) -> dict:
    """The BRDF inputs of a dict that may hold more (a field's output, a materials.json entry)."""
    return {i.name: material[i.name] for i in INPUTS}
