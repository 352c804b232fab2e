"""Material edits: which surface points an edit selects and how it changes their BRDF.

An edit is data (`Edit.to_dict` / `Edit.from_dict`, stored in an edited run's `edits.json`) and
is applied where the fitted fields are evaluated, so every view, bounce and export sees it:

- a selection: ranked material ids (1..M, the discrete branch's segmentation, the same in every
  view) and / or world-space boxes; a point is selected when its material is one of the ids
  (any, if none are given) and it lies in one of the boxes (anywhere, if none are given);
- changes, applied in order: `set` a value (basecolor linear RGB, metallic, roughness), `scale`
  one (metallic, roughness or basecolor, clamped to the valid range), `hue_shift` basecolor by
  degrees in HSV (saturation and value per point kept), or a named material of the library.

Relative changes keep the continuous field's texture; absolute ones replace it.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import torch

from vq_mitsuba import brdf
from vq_mitsuba.brdf import NAMES
from vq_mitsuba.errors import InputError

LIBRARY_PATH = Path(__file__).with_name("material_library.json")
KEYS = NAMES  # the BRDF inputs an edit may change
OPS = ("set", "scale", "hue_shift")
MAX_SCALE = 1e3  # beyond, every value is clamped to its range's end anyway
MAX_HUE_SHIFT = 1e6  # degrees (the command line's bound); a hue turns every 360


def material_library() -> dict[str, dict]:
    """The named materials `--preset NAME` gives: {name: {basecolor, metallic, roughness, note}}."""
    return json.loads(LIBRARY_PATH.read_text())["materials"]


@dataclass
class Change:
    op: str  # "set", "scale" or "hue_shift"
    key: str  # a BRDF input's name (brdf.NAMES); a colour's for hue_shift
    value: float | tuple[float, float, float]  # degrees for hue_shift

    def to_dict(self) -> dict:
        v = list(self.value) if isinstance(self.value, tuple) else self.value
        return {"op": self.op, "key": self.key, "value": v}


def preset_changes(name: str) -> list[Change]:
    """The `set` changes of a library material, one per BRDF input."""
    lib = material_library()
    if name not in lib:
        raise InputError(None, f"unknown material preset '{name}' (library: {', '.join(sorted(lib))})")
    m = lib[name]
    return [Change("set", i.name, tuple(float(c) for c in m[i.name]) if i.colour else float(m[i.name]))
            for i in brdf.INPUTS]


def check_change(change: Change) -> Change:
    """The change with its value checked (raises ValueError with what is wrong)."""
    op, key, v = change.op, change.key, change.value
    if op not in OPS:
        raise ValueError(f"unknown edit operation '{op}' (one of {', '.join(OPS)})")
    inp = brdf.get(key)
    if inp is None or (op == "hue_shift" and not inp.colour):
        colours = " or ".join(i.name for i in brdf.INPUTS if i.colour)
        raise ValueError(f"cannot {op} '{key}' (keys: {', '.join(brdf.NAMES)}; hue_shift acts on {colours})")
    if op == "set" and inp.colour:
        if not isinstance(v, (tuple, list)) or len(v) != 3:
            raise ValueError(f"{key} needs three values R,G,B, got {v!r}")
        v = tuple(float(c) for c in v)
        if not all(inp.low <= c <= inp.high for c in v):
            raise ValueError(f"{key} values must lie in [{inp.low:g}, {inp.high:g}] (linear RGB), got {v}")
    else:
        if isinstance(v, (tuple, list)):
            raise ValueError(f"{op} {key} takes one number, got {v!r}")
        v = float(v)
        if not math.isfinite(v):
            raise ValueError(f"{op} {key}: value must be finite, got {v}")
        if op == "set" and not inp.low <= v <= inp.high:
            raise ValueError(f"{key} must lie in [{inp.low:g}, {inp.high:g}], got {v}")
        if op == "scale" and not 0.0 <= v <= MAX_SCALE:
            raise ValueError(f"scale {key}: factor must lie in [0, {MAX_SCALE:g}], got {v:g}")
        if op == "hue_shift" and abs(v) > MAX_HUE_SHIFT:
            raise ValueError(f"hue_shift: degrees must lie in [-{MAX_HUE_SHIFT:g}, {MAX_HUE_SHIFT:g}], got {v:g}")
    return Change(op, key, v)


@dataclass
class Selection:
    materials: tuple[int, ...] = ()  # ranked material ids 1..M; empty = any material
    boxes: tuple[tuple[tuple[float, ...], tuple[float, ...]], ...] = ()  # (min xyz, max xyz); empty = anywhere

    def to_dict(self) -> dict:
        return {"materials": list(self.materials), "boxes": [[list(lo), list(hi)] for lo, hi in self.boxes]}

    def mask(self, points: torch.Tensor, material_id: torch.Tensor | None) -> torch.Tensor:
        """(N,) bool: the points (N, 3) this selection holds; material_id (N,) ids 1..M."""
        sel = torch.ones(points.shape[0], dtype=torch.bool, device=points.device)
        if self.materials:
            if material_id is None:
                raise ValueError("a material selection needs the run's discrete branch")
            ids = torch.tensor(self.materials, device=points.device)
            sel &= torch.isin(material_id, ids)
        if self.boxes:
            inside = torch.zeros_like(sel)
            for lo, hi in self.boxes:
                lo_t, hi_t = (torch.tensor(b, dtype=points.dtype, device=points.device) for b in (lo, hi))
                inside |= ((points >= lo_t) & (points <= hi_t)).all(-1)
            sel &= inside
        return sel


@dataclass
class Edit:
    selection: Selection
    changes: list[Change] = field(default_factory=list)
    label: str = ""  # what the user asked for, e.g. "--material 2 --preset gold"

    def to_dict(self) -> dict:
        return {"label": self.label, "select": self.selection.to_dict(),
                "changes": [c.to_dict() for c in self.changes]}

    @staticmethod
    def from_dict(data: dict, source: Path | None = None, index: int = 0) -> Edit:
        """An edit read from edits.json (`source`, entry `index`); bad entries raise InputError."""
        where = f"edit {index + 1}"
        try:
            sel = data.get("select", {})
            materials = tuple(int(m) for m in sel.get("materials", []))
            if any(m < 1 for m in materials):
                raise ValueError(f"material ids start at 1, got {list(materials)}")
            boxes = []
            for box in sel.get("boxes", []):
                lo, hi = (tuple(float(x) for x in corner) for corner in box)
                if len(lo) != 3 or len(hi) != 3 or not all(a <= b for a, b in zip(lo, hi)):
                    raise ValueError(f"a box is [[x0, y0, z0], [x1, y1, z1]] with x0 <= x1 ..., got {box}")
                boxes.append((lo, hi))
            changes = []
            for c in data.get("changes", []):
                v = c["value"]
                changes.append(check_change(Change(c["op"], c["key"], tuple(v) if isinstance(v, list) else v)))
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError(source, f"{where}: {exc}") from None
        if not changes:
            raise InputError(source, f"{where}: no changes")
        return Edit(Selection(materials, tuple(boxes)), changes, str(data.get("label", "")))


def rgb_to_hsv(rgb: torch.Tensor) -> torch.Tensor:
    """(N, 3) RGB in [0, 1] -> (N, 3) HSV, hue in [0, 1)."""
    r, g, b = rgb.unbind(-1)
    mx, _ = rgb.max(-1)
    mn, _ = rgb.min(-1)
    delta = mx - mn
    safe = torch.where(delta > 0, delta, torch.ones_like(delta))
    h = torch.where(mx == r, torch.remainder((g - b) / safe, 6.0),
                    torch.where(mx == g, (b - r) / safe + 2.0, (r - g) / safe + 4.0))
    h = torch.where(delta > 0, h / 6.0, torch.zeros_like(h))
    s = torch.where(mx > 0, delta / torch.where(mx > 0, mx, torch.ones_like(mx)), torch.zeros_like(mx))
    return torch.stack([h, s, mx], -1)


def hsv_to_rgb(hsv: torch.Tensor) -> torch.Tensor:
    """Inverse of rgb_to_hsv."""
    h, s, v = hsv.unbind(-1)
    k = torch.remainder(torch.stack([5.0 + 6.0 * h, 3.0 + 6.0 * h, 1.0 + 6.0 * h], -1), 6.0)
    return v[:, None] - v[:, None] * s[:, None] * torch.clamp(torch.minimum(k, 4.0 - k), 0.0, 1.0)


def hue_shift(rgb: torch.Tensor, degrees: float) -> torch.Tensor:
    """Rotate the hue of (N, 3) colours by `degrees`; each colour keeps its saturation and value."""
    hsv = rgb_to_hsv(rgb.clamp(0.0, 1.0))
    hsv = torch.stack([torch.remainder(hsv[:, 0] + degrees / 360.0, 1.0), hsv[:, 1], hsv[:, 2]], -1)
    return hsv_to_rgb(hsv)


def apply_change(values: dict[str, torch.Tensor], change: Change, mask: torch.Tensor,
                 roughness_min: float = 0.0) -> None:
    """Change `values` (a BRDF dict: a colour (N, 3), a scalar (N,)) in place where mask (N,) holds,
    clamped to the input's range (roughness's floor raised to `roughness_min`)."""
    key, old = change.key, values[change.key]
    if change.op == "set":
        new = torch.as_tensor(change.value, dtype=old.dtype, device=old.device).expand_as(old)
    elif change.op == "scale":
        new = old * change.value
    else:
        new = hue_shift(old, float(change.value))
    inp = brdf.get(key)
    new = new.clamp(roughness_min if key == brdf.ROUGHNESS else inp.low, inp.high)
    m = mask if old.dim() == 1 else mask[:, None]
    values[key] = torch.where(m, new, old)


def apply_edits(edits: list[Edit], points: torch.Tensor, values: dict[str, torch.Tensor],
                material_id: torch.Tensor | None, roughness_min: float = 0.0) -> dict[str, torch.Tensor]:
    """`values` (a BRDF dict) with every edit applied in order at world points (N, 3) of material ids (N,)."""
    out = dict(values)
    for edit in edits:
        mask = edit.selection.mask(points, material_id)
        if not bool(mask.any()):
            continue
        for change in edit.changes:
            apply_change(out, change, mask, roughness_min)
    return out
