"""The BRDF inputs, declared once: what the material fields predict, what Mitsuba's `principled`
BSDF takes from them, and the keys of every material dict, `materials.json`, edit and map file.

A material is a dict {name: value} over `NAMES`: per point a tensor (N, 3) for a colour and (N,)
for a scalar, or for one material a list of 3 floats and a float. Adding an input is one entry here
and its decoder (`vq_mitsuba.models.fields.BRDFDecoder`).
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class BrdfInput:
    name: str  # the key of the input everywhere (material dicts, materials.json, map files)
    channels: int  # 3: a linear RGB colour; 1: a scalar
    principled: str  # the parameter of Mitsuba's principled BSDF it feeds
    low: float = 0.0  # its range (a decoder may keep a config floor above `low`)
    high: float = 1.0

    @property
    def colour(self) -> bool:
        return self.channels == 3


INPUTS = (BrdfInput("basecolor", 3, "base_color"), BrdfInput("metallic", 1, "metallic"),
          BrdfInput("roughness", 1, "roughness"))
NAMES = tuple(i.name for i in INPUTS)
CHANNELS = sum(i.channels for i in INPUTS)  # values per point, the colours' three each
FIXED = {"specular": 0.5}  # principled's parameters the fit holds, not learned


def select(material: dict) -> dict:
    """The BRDF inputs of a dict that may hold more (a field's output, a materials.json entry)."""
    return {name: material[name] for name in NAMES}
