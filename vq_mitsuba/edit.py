"""`vq-mitsuba edit`: select materials of a fitted run and change them, writing a new run.

Reads the fitted run through `run.run_dir` only. The new run holds the edit list
(`models.material_edits.Edit`), applied wherever the run's fields are read (render, export, eval).
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np

from vq_mitsuba import brdf
from vq_mitsuba.data.cameras import Camera
from vq_mitsuba.run.outputs import check_output_folder
from vq_mitsuba.run.run_dir import RunDir
from vq_mitsuba.errors import InputError
from vq_mitsuba.models.material_edits import Change, Edit, Selection, check_change, preset_changes
from vq_mitsuba.models.fitted import FittedModel


def parse_numbers(text: str, count: int | None, what: str) -> tuple[float, ...]:
    try:
        values = tuple(float(x) for x in text.split(","))
    except ValueError:
        raise InputError(None, f"{what}: '{text}' is not a comma-separated list of numbers") from None
    if count is not None and len(values) != count:
        raise InputError(None, f"{what}: expected {count} numbers, got {len(values)} in '{text}'")
    if not all(np.isfinite(values)):
        raise InputError(None, f"{what}: values must be finite, got '{text}'")
    return values


def parse_box(text: str) -> tuple[tuple[float, ...], tuple[float, ...]]:
    v = parse_numbers(text, 6, "--box x0,y0,z0,x1,y1,z1")
    lo, hi = v[:3], v[3:]
    return tuple(min(a, b) for a, b in zip(lo, hi)), tuple(max(a, b) for a, b in zip(lo, hi))


def parse_pick(text: str) -> tuple[str, int, int]:
    view, sep, xy = text.rpartition(":")
    if not sep or not view:
        raise InputError(None, f"--pick VIEW:X,Y: '{text}' names no view (e.g. --pick r_0:120,84)")
    x, y = parse_numbers(xy, 2, f"--pick {text}")
    if x != int(x) or y != int(y) or x < 0 or y < 0:
        raise InputError(None, f"--pick {text}: X,Y are pixel indices (integers >= 0)")
    return view, int(x), int(y)


def parse_basecolor(text: str) -> tuple[float, float, float]:
    """Linear R,G,B in [0, 1], or #RRGGBB (sRGB, as colour pickers give it)."""
    text = text.strip()
    if text.startswith("#"):
        from vq_mitsuba.data.imageio import srgb_to_linear

        if len(text) != 7:
            raise InputError(None, f"basecolor '{text}': a hex colour is #RRGGBB")
        try:
            srgb = np.array([int(text[i:i + 2], 16) for i in (1, 3, 5)], np.float64) / 255.0
        except ValueError:
            raise InputError(None, f"basecolor '{text}' is not a hex colour #RRGGBB") from None
        return tuple(float(c) for c in srgb_to_linear(srgb))
    return parse_numbers(text, 3, f"basecolor={text}")


def parse_changes(sets: Sequence[str] = (), scales: Sequence[str] = (), hue_shift: float | None = None,
                  preset: str | None = None) -> list[Change]:
    """Changes in the order: preset, set, scale, hue shift (a preset then adjusted by the others)."""
    changes = preset_changes(preset) if preset else []
    for text, op in [(t, "set") for t in sets] + [(t, "scale") for t in scales]:
        key, sep, value = text.partition("=")
        key = key.strip()
        if not sep:
            raise InputError(None, f"--{op} {text}: expected KEY=VALUE, e.g. --{op} roughness=0.5")
        inp = brdf.get(key)
        if op == "set" and inp is not None and inp.colour:
            parsed = parse_basecolor(value)
        else:
            parsed = parse_numbers(value, 1, f"--{op} {text}")[0]
        try:
            changes.append(check_change(Change(op, key, parsed)))
        except ValueError as exc:
            raise InputError(None, f"--{op} {text}: {exc}") from None
    if hue_shift is not None:
        if not np.isfinite(hue_shift):
            raise InputError(None, f"--hue-shift must be finite, got {hue_shift}")
        changes.append(Change("hue_shift", brdf.BASECOLOR, float(hue_shift)))  # --hue-shift turns the basecolor
    if not changes:
        raise InputError(None, "no change given: use --set, --scale, --hue-shift or --preset")
    return changes


def find_view(run: RunDir, view: str) -> Camera:
    """The camera named `view` among the fitted run's capture views (train, then test / val
    cameras beside the capture), in the run's world."""
    names = []
    for cameras in run.cameras().values():
        for cam in cameras:
            if cam.name == view:
                return cam
        names += [c.name for c in cameras]
    shown = ", ".join(names[:8]) + (", ..." if len(names) > 8 else "")
    raise InputError(None, f"--pick: no view named '{view}' among the capture's views ({shown})")


def material_under_pixel(fitted: FittedModel, camera: Camera, x: int, y: int) -> int:
    """The ranked material id (1..M) that the discrete segmentation gives pixel (x, y) of a view
    (camera in the run's world): the majority of 16 rays spread over the pixel."""
    import torch

    from vq_mitsuba.data.cameras import camera_rays, pixel_jitter
    from vq_mitsuba.render.shading import scene_for_mesh

    if fitted.discrete is None:
        raise InputError(None, "--pick selects a material of the discrete branch; this run has none "
                               "(fitted with --preset continuous?): use --box")
    if not (0 <= x < camera.width and 0 <= y < camera.height):
        raise InputError(None, f"--pick {camera.name}:{x},{y}: pixel outside the {camera.width}x{camera.height} view")
    rng = np.random.default_rng(0)
    jitter = np.concatenate([pixel_jitter(1, a, 16, rng) for a in range(16)])
    origins, directions = camera_rays(camera, jitter, pixels=np.full(16, y * camera.width + x))
    scene = scene_for_mesh(fitted.mesh, fitted.envmap, fitted.envmap_to_world)
    hits = scene.trace(origins, directions)
    if int(hits.valid.sum()) * 2 < len(origins):
        raise InputError(None, f"--pick {camera.name}:{x},{y}: the pixel shows the background, not the object")
    ids = fitted.materials_at(hits.position[hits.valid])["material"]
    return int(torch.bincount(ids).argmax())


def build_edit(run: RunDir, fitted: FittedModel, materials: Sequence[int] = (), picks: Sequence[str] = (),
               boxes: Sequence[str] = (), sets: Sequence[str] = (), scales: Sequence[str] = (),
               hue_shift: float | None = None, preset: str | None = None, label: str = "") -> Edit:
    """One edit from command-line style arguments (checked; raises InputError)."""
    if not (materials or picks or boxes):
        raise InputError(None, "select what to edit: --material K, --pick VIEW:X,Y and / or --box x0,y0,z0,x1,y1,z1")
    changes = parse_changes(sets, scales, hue_shift, preset)
    m = fitted.num_materials
    ids = []
    for k in materials:
        if m is None:
            raise InputError(None, "--material selects a material of the discrete branch; this run has none: use --box")
        if not 1 <= int(k) <= m:
            raise InputError(None, f"--material {k}: the run has materials 1..{m} (see materials.json)")
        ids.append(int(k))
    for text in picks:
        view, x, y = parse_pick(text)
        ids.append(material_under_pixel(fitted, find_view(run, view), x, y))
    edit = Edit(Selection(tuple(dict.fromkeys(ids)), tuple(parse_box(b) for b in boxes)), changes, label)
    if edit.selection.boxes:
        check_box_selects_surface(fitted, edit.selection)
    return edit


SURFACE_SAMPLES = 20000  # points of the run's surface (besides its vertices) a box selection is tried on


def check_box_selects_surface(fitted: FittedModel, selection: Selection) -> None:
    """Refuse a selection with boxes that holds no point of the run's surface (a box beside the
    object, or none of the selected materials inside it): such an edit would change nothing."""
    import torch
    import trimesh

    mesh = fitted.mesh
    samples, _ = trimesh.sample.sample_surface(mesh, SURFACE_SAMPLES, seed=0)
    points = torch.as_tensor(np.concatenate([np.asarray(mesh.vertices), samples]), dtype=torch.float32)
    ids = None
    if selection.materials:
        device = next(fitted.model.parameters()).device
        with torch.no_grad():
            ids = fitted.materials_at(points.to(device))["material"].cpu()
    if not bool(selection.mask(points, ids).any()):
        lo, hi = np.asarray(mesh.bounds)
        what = "no surface point of the selected materials" if selection.materials else "no surface point"
        raise InputError(None, f"--box: the box(es) hold {what}: the edit would change nothing (the object spans "
                               f"{', '.join(f'{a:.3g}..{b:.3g}' for a, b in zip(lo, hi))} in x, y, z)")


def edit_run(run_dir: str | Path | RunDir, out_dir: str | Path, edit: Edit) -> RunDir:
    """Write OUT_DIR, a new or empty folder: an edited run of RUN_DIR's fitted run, with RUN_DIR's
    edits and `edit` (another run, edited or not, is never written over)."""
    run = run_dir if isinstance(run_dir, RunDir) else RunDir(run_dir)
    out = RunDir(out_dir)
    check_output_folder(out.dir, "edit", "edit")
    out.write_edit(run, run.edits() + [edit])
    return out
