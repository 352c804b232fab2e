"""What every export format shares: textures as image files, the envmap in a target's
convention, and the axes of Y-up formats (glTF, OBJ), which hold the capture's own world."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from vq_mitsuba.brdf import INPUTS
from vq_mitsuba.data.cameras import BLENDER_ENV_TO_WORLD, world_rotation
from vq_mitsuba.data.envmaps import direction_to_pixel, texel_directions
from vq_mitsuba.data.imageio import linear_to_srgb
from vq_mitsuba.export.bake import BakedMesh

# glTF and OBJ are Y up; Blender's importers turn their (x, y, z) into Blender's (x, -z, y).
Y_UP_TO_BLENDER = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])


def world_to_y_up(world: str) -> np.ndarray:
    """(3, 3) rotation from a run's world ("mitsuba" Y up / "blender" Z up) to glTF / OBJ axes, chosen
    so that Blender's importers put the object back at the capture's own Blender coordinates."""
    return np.eye(3) if world == "mitsuba" else Y_UP_TO_BLENDER.T


def export_axes(run_world: str, own_world: str) -> np.ndarray:
    """(3, 3) rotation from a run's world to the axes of a Y-up export (glTF, OBJ) of the capture's
    own world `own_world`: the inverse of the loader's conversion (capture -> run), then Y up."""
    return world_to_y_up(own_world) @ world_rotation(run_world, own_world)


def srgb8(linear: np.ndarray) -> np.ndarray:
    return np.round(np.clip(linear_to_srgb(np.clip(linear, 0.0, 1.0)), 0, 1) * 255).astype(np.uint8)


def unit8(values: np.ndarray) -> np.ndarray:
    return np.round(np.clip(values, 0.0, 1.0) * 255).astype(np.uint8)


def png_bytes(image: np.ndarray) -> bytes:
    import io

    import imageio.v3 as iio

    buf = io.BytesIO()
    iio.imwrite(buf, image, extension=".png")
    return buf.getvalue()


def texture_images(baked: BakedMesh) -> dict[str, np.ndarray]:
    """8-bit images: each BRDF input's (a colour sRGB, a scalar linear grey) and glTF's combined
    metallic-roughness (each input at its `gltf_channel`: G roughness, B metallic; R unused)."""
    mr = np.zeros(baked.roughness.shape + (3,), np.float32)
    for i in INPUTS:
        if i.gltf_channel is not None:
            mr[..., i.gltf_channel] = getattr(baked, i.name)
    return {**{i.name: (srgb8 if i.colour else unit8)(getattr(baked, i.name)) for i in INPUTS},
            "metallic_roughness": unit8(mr)}


def sample_latlong(env: np.ndarray, dirs_blender_convention: np.ndarray) -> np.ndarray:
    """Bilinear lookup of a lat-long map (Mitsuba's layout) along directions given in its
    Blender-convention frame, as Mitsuba's envmap reads it (longitude wraps, latitude clamps)."""
    h, w = env.shape[:2]
    col, row = direction_to_pixel(dirs_blender_convention, w, h)
    c0 = np.floor(col).astype(np.int64)
    r0 = np.clip(np.floor(row).astype(np.int64), 0, h - 1)
    fc, fr = (col - c0)[..., None], (row - r0)[..., None]
    r1 = np.clip(r0 + 1, 0, h - 1)
    c0w, c1w = c0 % w, (c0 + 1) % w
    top = env[r0, c0w] * (1 - fc) + env[r0, c1w] * fc
    bottom = env[r1, c0w] * (1 - fc) + env[r1, c1w] * fc
    return (top * (1 - fr) + bottom * fr).astype(np.float32)


def envmap_for_blender(env: np.ndarray, env_to_world: np.ndarray, world_to_blender: np.ndarray,
                       upsample: int = 4) -> np.ndarray:
    """The lat-long map that lights Blender's scene as `env` (with its `env_to_world`, in a run's
    world) lights the run, where Blender's coordinates are `world_to_blender` @ the run's.

    Blender's convention is the layout `data.envmaps` uses with BLENDER_ENV_TO_WORLD. The result
    is `upsample` times larger per axis, so Mitsuba's bilinear reading of `env` is kept."""
    h, w = env.shape[:2]
    d_target = texel_directions(w * upsample, h * upsample)  # Blender-world directions of the new texels
    d_run = d_target @ np.asarray(world_to_blender)  # inverse rotation: into the run's world
    r_e, r_b = np.asarray(env_to_world)[:3, :3], BLENDER_ENV_TO_WORLD[:3, :3]
    d_source = d_run @ r_e @ r_b.T  # into env's own frame, written in its Blender-convention layout
    return sample_latlong(np.asarray(env, np.float64), d_source)


def write_envmap(path_stem: Path, env: np.ndarray) -> list[Path]:
    """`STEM.exr` and `STEM.hdr` (Radiance RGBE) of a lat-long map."""
    import mitsuba as mi

    from vq_mitsuba.backend import init_mitsuba
    from vq_mitsuba.data.imageio import write_exr

    init_mitsuba()
    exr, hdr = path_stem.with_suffix(".exr"), path_stem.with_suffix(".hdr")
    write_exr(exr, env)
    mi.Bitmap(np.ascontiguousarray(env[..., :3], dtype=np.float32)).write(str(hdr))
    return [exr, hdr]


def blender_envmap(fitted, envmap: np.ndarray | None, axes: np.ndarray,
                   env_to_world: np.ndarray | None = None) -> np.ndarray:
    """The run's lighting (or `envmap`, in the run's envmap frame) for a Y-up export whose
    coordinates are `axes` @ the run's, imported into Blender."""
    env = fitted.envmap if envmap is None else envmap
    to_world = fitted.envmap_to_world if env_to_world is None else env_to_world
    world_to_blender = Y_UP_TO_BLENDER @ axes  # the identity for Blender-world runs of Blender captures
    return envmap_for_blender(env, to_world, world_to_blender)

