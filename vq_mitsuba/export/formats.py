"""`vq-mitsuba export`: a fitted (or edited) run as a glTF binary, OBJ+MTL or a Mitsuba scene.

Reads the run through `run.run_dir`; the material fields (with the run's edits) are baked into
textures on a UV atlas (`export.bake`). Each format is one writer module. glTF and OBJ hold the
capture's own world (a NeRF/Blender capture's Blender world, turned Y up as the formats ask, so
Blender's importers put the object back among the capture's cameras); the Mitsuba scene holds
the run's world, in which its sensors and envmap frame are given.
"""

from __future__ import annotations

import json
import re
import shutil
import time
from pathlib import Path

import numpy as np

from vq_mitsuba.brdf import NAMES
from vq_mitsuba.data.imageio import write_png
from vq_mitsuba.run.outputs import EXPORT_MARKER, check_output_folder
from vq_mitsuba.run.run_dir import RunDir, check_writable, write_json
from vq_mitsuba.errors import InputError
from vq_mitsuba.export.files import export_axes

FORMATS = ("gltf", "obj", "mitsuba")


def _name(run: RunDir) -> str:
    return re.sub(r"[^A-Za-z0-9_-]+", "_", run.dir.resolve().name) or "object"


def _planned_files(fmt: str, name: str) -> list[str]:
    """The names an export of `fmt` may write into its folder (what the writers below write)."""
    textures = {"gltf": [], "obj": ["png"], "mitsuba": ["exr"]}[fmt]
    files = [f"{name}_{key}.{ext}" for ext in textures for key in NAMES]
    files += {"gltf": [f"{name}.glb"], "obj": [f"{name}.obj", f"{name}.mtl"],
              "mitsuba": ["scene.xml", f"{name}.ply"]}[fmt]
    return files + ["envmap.exr", "envmap.hdr", f"{name}_material_id.png", "export.json"]


def check_export_target(out: str | Path, fmt: str) -> None:
    """Refuse, before any work, an output folder that is neither new, empty, nor an export of the
    same format (`run.outputs`): a run, a capture, another format's export, a user's files."""
    if fmt in FORMATS:
        check_output_folder(out, "export", "export", fmt=fmt)


def _earlier_files(out: Path) -> list[str]:
    """The files an earlier export into `out` wrote (its export.json), by their plain names."""
    try:
        files = json.loads((out / EXPORT_MARKER).read_text()).get("files", [])
    except (OSError, ValueError, AttributeError):
        return []
    return [f for f in files if isinstance(f, str) and f == Path(f).name and f != EXPORT_MARKER] \
        if isinstance(files, list) else []


TEXTURE_SIZES = (16, 8192)  # the texture sizes an export takes, in texels a side


def check_texture_size(texture_size, name: str = "the texture size") -> int:
    """The texture size as a whole number in TEXTURE_SIZES; InputError otherwise, its message
    starting with `name` (the option or field that gave it)."""
    low, high = TEXTURE_SIZES
    try:
        ok = not isinstance(texture_size, bool) and float(texture_size).is_integer() and low <= texture_size <= high
    except (TypeError, ValueError, OverflowError):
        ok = False
    if not ok:
        shown = repr(texture_size) if isinstance(texture_size, str) else texture_size
        raise InputError(None, f"{name} must be a whole number of texels in {low}..{high}, got {shown}")
    return int(texture_size)


def world_lamps(fitted, fitted_light: bool) -> np.ndarray | None:
    """The run's lamps fixed in the world as (K, 6) rows (position, RGB intensity) for an export
    under its fitted light; None otherwise. Lamps that ride with the camera have no place in a
    scene file: a warning says they are left out."""
    lamps = fitted.lamps
    if lamps is None or not fitted_light:
        return None
    if lamps.in_camera:
        from vq_mitsuba.errors import warn

        warn(f"the run's {len(lamps.position)} lamp(s) ride with the camera (a flash): the exported scene has no "
             "camera to hang them on and leaves them out")
        return None
    return np.concatenate([lamps.position, lamps.intensity], 1)


def export_run(run_dir: str | Path, fmt: str, out_dir: str | Path, texture_size: int = 1024,
               branch: str = "continuous", envmap_path: str | Path | None = None) -> dict:
    """Write the export into OUT_DIR and return its summary (also OUT_DIR/export.json)."""
    if fmt not in FORMATS:
        raise InputError(None, f"unknown export format '{fmt}' (one of {', '.join(FORMATS)})")
    check_texture_size(texture_size)
    out = Path(out_dir)
    check_export_target(out, fmt)
    check_writable(out)  # before the bake, not after it
    run = RunDir(run_dir)
    fitted = run.load()
    envmap = None
    if envmap_path is not None:
        from vq_mitsuba.data.envmaps import load_envmap

        envmap = load_envmap(envmap_path)
    cameras = [c for split in run.cameras().values() for c in split] if fmt == "mitsuba" else []
    name = _name(run)
    world = fitted.world  # a run keeps its capture's own world (loaders convert only other cameras)
    axes = export_axes(fitted.world, world)

    from vq_mitsuba.export.bake import bake

    t0 = time.perf_counter()
    baked = bake(fitted, int(texture_size), branch)
    bake_s = time.perf_counter() - t0
    missing = [p for p in (out, *out.parents) if not p.exists()]  # made here: removed again if writing fails
    out.mkdir(parents=True, exist_ok=True)
    earlier = _earlier_files(out)  # an earlier export of this format into `out`: its files are replaced
    t0 = time.perf_counter()
    try:
        if fmt == "gltf":
            from vq_mitsuba.export.gltf import write_glb

            files = [write_glb(out / f"{name}.glb", baked, axes, name, world_lamps(fitted, envmap is None))]
        elif fmt == "obj":
            from vq_mitsuba.export.obj import write_obj

            files = write_obj(out / f"{name}.obj", baked, axes, name)
        else:
            from vq_mitsuba.export.mitsuba_scene import write_mitsuba

            env = fitted.envmap if envmap is None else envmap
            files = write_mitsuba(out, baked, env, fitted.envmap_to_world, cameras, fitted.cfg.render.spp,
                                  2 + fitted.cfg.train.bounces, name, world_lamps(fitted, envmap is None))
        if fmt != "mitsuba":  # Y-up formats: the lighting in Blender's convention (the XML holds its own frame)
            from vq_mitsuba.export.files import blender_envmap, write_envmap

            files += write_envmap(out / "envmap", blender_envmap(fitted, envmap, axes))
        if baked.material is not None:
            write_png(out / f"{name}_material_id.png", baked.material)
            files.append(out / f"{name}_material_id.png")
        summary = {
            "run": str(run.dir.resolve()), "format": fmt, "branch": branch, "texture_size": int(texture_size),
            "envmap": str(Path(envmap_path).resolve()) if envmap_path else "fitted",
            "envmap_convention": "mitsuba scene frame (to_world in scene.xml)" if fmt == "mitsuba" else
            "Blender world of the imported file",
            "world": world, "run_world": fitted.world, "edits": len(fitted.edits),
            "vertices": int(len(baked.vertices)), "faces": int(len(baked.faces)),
            "texel_coverage": float(np.mean(baked.coverage)),
            "seconds": {"bake": round(bake_s, 2), **{k: round(v, 2) for k, v in baked.seconds.items()},
                        "write": round(time.perf_counter() - t0, 2)},
            "files": [str(Path(f).relative_to(out)) for f in files],
        }
        for stale in set(earlier) - set(summary["files"]):  # e.g. another run's name: no mix of two exports
            (out / stale).unlink(missing_ok=True)
        write_json(out / EXPORT_MARKER, summary)
    except BaseException:
        if missing:
            shutil.rmtree(missing[-1], ignore_errors=True)
        raise
    return summary
