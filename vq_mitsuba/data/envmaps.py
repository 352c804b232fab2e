"""Lat-long HDR environment maps in Blender's world convention (Z up) and procedural presets.

Convention (Blender / Cycles equirectangular, world +Z up)
----------------------------------------------------------
A unit direction d = (x, y, z) in Blender world has

    phi   = atan2(y, x)            azimuth, counter-clockwise from +X seen from above
    theta = acos(z)                angle from the zenith (+Z)
    u     = 0.5 - phi / (2 pi)     horizontal image coordinate in [0, 1), 0 = left edge
    v     = theta / pi             vertical image coordinate in [0, 1], 0 = top edge (zenith)

so the image centre (u, v) = (0.5, 0.5) looks along +X, u = 0.25 along +Y, u = 0.75 along -Y and
the left/right edges along -X. This is Cycles' `direction_to_equirectangular` (whose v counts from
the bottom) and it is what Mitsuba's `envmap` emitter does with
`to_world = BLENDER_ENV_TO_WORLD` (checked numerically in tests/data/test_envmaps.py).

Texel positions. Mitsuba interpolates a W x H map bilinearly with texel column j centred at
u = (j + 0.5) / W (wrapping around), but texel row i centred at v = i / (H - 1): the top row sits
on the zenith and the bottom row on the nadir. `direction_to_pixel` / `pixel_to_direction` use
exactly these texel positions, so `emitter.eval(d)` returns the texel `direction_to_pixel(d)`
names. Cycles centres rows at v = (i + 0.5) / H instead: the two differ by at most half a texel
in v (at the poles, none at the horizon), which is below the resolution of the maps used here.

In a scene expressed in Mitsuba's own world (Y up, `Blender_world = R @ Mitsuba_world` with R the
3x3 part of BLENDER_ENV_TO_WORLD) the same file needs no `to_world` at all.
"""

from __future__ import annotations

import importlib.util
import math
from pathlib import Path

import numpy as np

from vq_mitsuba.data.cameras import BLENDER_ENV_TO_WORLD
from vq_mitsuba.data.imageio import checked_kind, clamp_tiny_negatives, read_image, write_exr
from vq_mitsuba.errors import InputError

PRESETS = ("sky", "sunset", "studio", "overcast", "sun")

# Sun of the training preset "sky" (Blender world): elevation above the horizon and azimuth
# counter-clockwise from +X.
SKY_SUN_ELEVATION_DEG = 35.0
SKY_SUN_AZIMUTH_DEG = 60.0


# --------------------------------------------------------------------------------------------
# Directions <-> lat-long coordinates
# --------------------------------------------------------------------------------------------
def direction_to_uv(d) -> tuple[np.ndarray, np.ndarray]:
    """Continuous lat-long coordinates (u, v) in [0, 1] of Blender-world directions (..., 3)."""
    d = np.asarray(d, dtype=np.float64)
    n = np.linalg.norm(d, axis=-1)
    n = np.where(n > 0, n, 1.0)
    phi = np.arctan2(d[..., 1], d[..., 0])
    u = np.mod(0.5 - phi / (2.0 * math.pi), 1.0)
    v = np.arccos(np.clip(d[..., 2] / n, -1.0, 1.0)) / math.pi
    return u, v


def uv_to_direction(u, v) -> np.ndarray:
    """Unit Blender-world directions (..., 3) of lat-long coordinates (u, v) in [0, 1]."""
    u = np.asarray(u, dtype=np.float64)
    v = np.asarray(v, dtype=np.float64)
    phi = math.pi * (1.0 - 2.0 * u)
    theta = math.pi * v
    st = np.sin(theta)
    return np.stack([st * np.cos(phi), st * np.sin(phi), np.cos(theta)], -1)


def direction_to_pixel(d, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Fractional texel indices (col, row) that Mitsuba's envmap reads for directions d.

    col is in [-0.5, width - 0.5) (wraps around), row in [0, height - 1]; round them to get the
    nearest texel: `img[int(round(row)), int(round(col)) % width]`.
    """
    u, v = direction_to_uv(d)
    col = u * width - 0.5
    col = np.where(col < -0.5, col + width, col)
    row = v * (height - 1)
    return col, row


def pixel_to_direction(col, row, width: int, height: int) -> np.ndarray:
    """Inverse of direction_to_pixel: Blender-world unit directions of (fractional) texel indices."""
    col = np.asarray(col, dtype=np.float64)
    row = np.asarray(row, dtype=np.float64)
    return uv_to_direction((col + 0.5) / width, row / max(height - 1, 1))


def texel_directions(width: int, height: int) -> np.ndarray:
    """(H, W, 3) Blender-world unit direction of every texel, as Mitsuba samples the map."""
    rows, cols = np.meshgrid(np.arange(height), np.arange(width), indexing="ij")
    return pixel_to_direction(cols, rows, width, height)


def texel_solid_angles(width: int, height: int) -> np.ndarray:
    """(H, W) solid angle (sr) each texel stands for; sums to 4 pi."""
    edges = np.clip((np.arange(height + 1) - 0.5) / max(height - 1, 1), 0.0, 1.0) * math.pi
    band = np.cos(edges[:-1]) - np.cos(edges[1:])
    return np.repeat((band * 2.0 * math.pi / width)[:, None], width, 1)


def sun_direction(elevation_deg: float, azimuth_deg: float) -> np.ndarray:
    """Blender-world unit direction towards a sun at this elevation / azimuth (from +X to +Y)."""
    e, a = math.radians(elevation_deg), math.radians(azimuth_deg)
    return np.array([math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)])


def irradiance(env: np.ndarray, normal) -> np.ndarray:
    """RGB irradiance on a surface with this Blender-world normal (no occlusion)."""
    env = np.asarray(env, dtype=np.float64)
    h, w = env.shape[:2]
    cos = np.clip(texel_directions(w, h) @ np.asarray(normal, dtype=np.float64), 0.0, None)
    return np.einsum("hwc,hw->c", env, cos * texel_solid_angles(w, h))


# --------------------------------------------------------------------------------------------
# Procedural maps
# --------------------------------------------------------------------------------------------
def _smoothstep(e0: float, e1: float, x: np.ndarray) -> np.ndarray:
    t = np.clip((x - e0) / (e1 - e0), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def _sun_disc(dirs: np.ndarray, omega: np.ndarray, sun: np.ndarray, radius_deg: float,
              irradiance_: float) -> np.ndarray:
    """(H, W) limb-darkened disc whose irradiance at normal incidence is `irradiance_`."""
    h, w = dirs.shape[:2]
    texel = math.pi / max(h - 1, 1)
    radius = max(math.radians(radius_deg), 0.75 * texel)  # keep it resolvable on coarse maps
    ang = np.arccos(np.clip(dirs @ sun, -1.0, 1.0))
    r = np.clip(ang / radius, 0.0, 1.0)
    shape = 1.0 - 0.6 * (1.0 - np.sqrt(1.0 - r * r))  # limb darkening, brightest at the centre
    cover = np.clip((radius + 0.5 * texel - ang) / texel, 0.0, 1.0)  # anti-aliased edge
    disc = shape * cover
    e = float(np.sum(disc * omega * np.clip(dirs @ sun, 0.0, None)))
    return disc * (irradiance_ / e if e > 0 else 0.0)


def _finish(img: np.ndarray) -> np.ndarray:
    img = np.nan_to_num(np.asarray(img, dtype=np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    return np.maximum(img, 1e-4).astype(np.float32)


def sky(width: int = 256, height: int = 128, sun_elevation_deg: float = SKY_SUN_ELEVATION_DEG,
        sun_azimuth_deg: float = SKY_SUN_AZIMUTH_DEG, sun_intensity: float = 2.5,
        sun_radius_deg: float = 2.0, turbidity: float = 3.0, sky_intensity: float = 1.0,
        zenith_color=(0.16, 0.30, 0.60), horizon_color=(0.75, 0.82, 0.90),
        ground_color=(0.16, 0.14, 0.12), sun_color=(1.0, 0.95, 0.86)) -> np.ndarray:
    """A clear sky: zenith-to-horizon gradient, glow around the sun, a small sun disc, dark ground.

    sun_intensity is the sun disc's irradiance on a surface facing it (the whole sky above a
    horizontal surface gives roughly pi * the mean sky radiance, ~2 at sky_intensity 1);
    turbidity (about 2..10) widens the horizon haze and the glow around the sun.
    Returns float32 (H, W, 3), Blender convention, all values > 0.
    """
    dirs = texel_directions(width, height)
    omega = texel_solid_angles(width, height)
    sun = sun_direction(sun_elevation_deg, sun_azimuth_deg)
    z = dirs[..., 2]
    zen, hor, gnd, sc = (np.asarray(c, dtype=np.float64) for c in
                         (zenith_color, horizon_color, ground_color, sun_color))
    haze = max(float(turbidity), 1.0)
    t = np.clip(z, 0.0, 1.0) ** (0.35 + 0.08 * haze)  # thicker haze band at higher turbidity
    above = hor[None, None] * (1.0 - t[..., None]) + zen[None, None] * t[..., None]
    cos_sun = np.clip(dirs @ sun, -1.0, 1.0)
    ang = np.arccos(cos_sun)
    glow_w = math.radians(6.0 + 3.0 * haze)
    glow = 0.35 * (haze / 3.0) * np.exp(-ang / glow_w) + 0.15 * (1.0 + cos_sun) ** 2 / 4.0
    above = above + glow[..., None] * sc[None, None]
    # Ground: darker, slightly brighter towards the horizon (bounce light).
    below = gnd[None, None] * (0.6 + 0.4 * (1.0 - np.clip(-z, 0.0, 1.0)) ** 2)[..., None]
    s = _smoothstep(-0.03, 0.01, z)[..., None]
    img = sky_intensity * (above * s + below * (1.0 - s))
    img = img + _sun_disc(dirs, omega, sun, sun_radius_deg, sun_intensity)[..., None] * sc[None, None]
    return _finish(img)


def overcast(width: int = 256, height: int = 128, intensity: float = 1.0,
             color=(0.82, 0.85, 0.90), ground_color=(0.18, 0.17, 0.16)) -> np.ndarray:
    """CIE overcast sky, L = Lz (1 + 2 sin(elevation)) / 3, over a darker ground; no sun."""
    dirs = texel_directions(width, height)
    z = dirs[..., 2]
    c, g = np.asarray(color, dtype=np.float64), np.asarray(ground_color, dtype=np.float64)
    above = (1.0 + 2.0 * np.clip(z, 0.0, 1.0))[..., None] / 3.0 * c[None, None] * 1.4
    below = g[None, None] * (0.7 + 0.3 * (1.0 - np.clip(-z, 0.0, 1.0)))[..., None]
    s = _smoothstep(-0.04, 0.02, z)[..., None]
    return _finish(intensity * (above * s + below * (1.0 - s)))


def _area_light(dirs: np.ndarray, elevation_deg: float, azimuth_deg: float, width_deg: float,
                height_deg: float, softness_deg: float) -> np.ndarray:
    """(H, W) mask of a soft rectangle seen from the origin, centred at (elevation, azimuth)."""
    c = sun_direction(elevation_deg, azimuth_deg)
    up0 = np.array([0.0, 0.0, 1.0]) if abs(c[2]) < 0.99 else np.array([1.0, 0.0, 0.0])
    right = np.cross(c, up0)
    right /= np.linalg.norm(right)
    up = np.cross(right, c)
    fwd = dirs @ c
    x = np.degrees(np.arctan2(dirs @ right, fwd))
    y = np.degrees(np.arctan2(dirs @ up, fwd))
    soft = max(softness_deg, 1e-3)
    mx = 1.0 - _smoothstep(0.5 * width_deg - soft, 0.5 * width_deg + soft, np.abs(x))
    my = 1.0 - _smoothstep(0.5 * height_deg - soft, 0.5 * height_deg + soft, np.abs(y))
    return np.where(fwd > 0.0, mx * my, 0.0)


def studio(width: int = 256, height: int = 128, intensity: float = 1.0, background: float = 0.03,
           lights=None) -> np.ndarray:
    """Dark grey studio with large soft rectangular lights (key, fill, rim by default).

    lights: list of dicts with elevation, azimuth (deg, Blender world), width, height (angular
    size, deg), softness (deg), radiance (RGB).
    """
    if lights is None:
        lights = [
            dict(elevation=30.0, azimuth=30.0, width=40.0, height=30.0, softness=6.0,
                 radiance=(3.2, 3.0, 2.7)),  # key, warm
            dict(elevation=10.0, azimuth=-80.0, width=50.0, height=35.0, softness=10.0,
                 radiance=(0.8, 0.9, 1.1)),  # fill, cool
            dict(elevation=55.0, azimuth=170.0, width=30.0, height=60.0, softness=5.0,
                 radiance=(2.2, 2.2, 2.2)),  # rim / top
        ]
    dirs = texel_directions(width, height)
    z = dirs[..., 2]
    base = background * (0.7 + 0.3 * _smoothstep(-1.0, 1.0, z))
    img = np.repeat(base[..., None], 3, -1)
    for light in lights:
        mask = _area_light(dirs, light["elevation"], light["azimuth"], light["width"],
                           light["height"], light.get("softness", 5.0))
        img = img + mask[..., None] * np.asarray(light["radiance"], dtype=np.float64)[None, None]
    return _finish(intensity * img)


def named_envmap(name: str, width: int = 256, height: int = 128) -> np.ndarray:
    """A preset: "sky" (training default: sun at 35 deg elevation), "sunset", "studio", "overcast",
    "sun" (a strong sun high over a pale sky: most of the light from one direction)."""
    if name == "sky":
        return sky(width, height)
    if name == "sun":
        return sky(width, height, sun_elevation_deg=50.0, sun_azimuth_deg=-40.0, sun_intensity=7.0,
                   sun_radius_deg=1.5, turbidity=2.0, sky_intensity=0.6)
    if name == "sunset":
        return sky(width, height, sun_elevation_deg=4.0, sun_azimuth_deg=-120.0, sun_intensity=2.0,
                   sun_radius_deg=2.5, turbidity=6.0, sky_intensity=0.8,
                   zenith_color=(0.10, 0.14, 0.32), horizon_color=(1.0, 0.55, 0.28),
                   ground_color=(0.12, 0.09, 0.07), sun_color=(1.0, 0.55, 0.25))
    if name == "studio":
        return studio(width, height)
    if name == "overcast":
        return overcast(width, height)
    raise InputError(None, f"unknown environment map '{name}' (choose from {', '.join(PRESETS)})")


def blender_probes() -> dict[str, Path]:
    """Blender's eight CC0 studio-light HDRs (name -> path) when `bpy` is installed, else {}."""
    try:
        spec = importlib.util.find_spec("bpy")
    except (ImportError, ValueError):
        return {}
    if spec is None:
        return {}
    roots = [Path(p) for p in (spec.submodule_search_locations or [])]
    if spec.origin:
        roots.append(Path(spec.origin).parent)
    found: dict[str, Path] = {}
    for root in roots:
        for path in sorted(root.glob("*/datafiles/studiolights/world/*.exr")):
            found.setdefault(path.stem, path)
    return found


# --------------------------------------------------------------------------------------------
# Files and Mitsuba
# --------------------------------------------------------------------------------------------
ENV_PEAK_RANGE = (1e-30, 1e30)  # brightest texel an envmap may have (float32 sums of its light stay finite)
HDR_MAX_TEXELS = 1 << 27  # the largest Radiance .hdr read (16384 x 8192 texels)


def read_envmap_file(path: str | Path) -> np.ndarray:
    """The linear radiance (H, W, 3) float32 of an envmap image file, as stored, its format known by
    its bytes (vq_mitsuba.data.imageio.checked_kind: they must agree with its suffix): EXR, PNG and JPEG
    through read_image; Radiance .hdr (its header checked first) and .pfm through Mitsuba's Bitmap.
    Non-finite texels are refused, tiny negative ones clamped (vq_mitsuba.data.imageio)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "environment map not found")
    kind = checked_kind(path)
    if kind in ("exr", "png", "jpeg"):
        return read_image(path)[0]
    if kind == "hdr":
        _check_hdr_header(path)
    import mitsuba as mi

    from vq_mitsuba.backend import init_mitsuba

    init_mitsuba()
    try:
        bmp = mi.Bitmap(str(path)).convert(mi.Bitmap.PixelFormat.RGB, mi.Struct.Type.Float32, srgb_gamma=False)
        rgb = np.array(bmp, dtype=np.float32)
    except Exception as exc:
        raise InputError(path, f"cannot read environment map ({type(exc).__name__}: {exc})") from exc
    if not np.all(np.isfinite(rgb)):
        raise InputError(path, "environment map contains non-finite values")
    return clamp_tiny_negatives(rgb.reshape(rgb.shape[0], rgb.shape[1], 3), path)


def _check_hdr_header(path: Path) -> None:
    """A Radiance .hdr's header: its lines up to a blank one, then a size line such as `-Y 256 +X 512`
    with both sides whole numbers of at least 1 and at most HDR_MAX_TEXELS texels in all; an InputError
    naming the file otherwise (Mitsuba's reader would try to allocate whatever the line says)."""
    import re

    with open(path, "rb") as f:
        head = f.read(1 << 16)
    blank = head.find(b"\n\n")
    if blank < 0:
        raise InputError(path, "not a valid Radiance .hdr: its header does not end (no blank line in its first 64 KiB)")
    line = head[blank + 2:].split(b"\n", 1)[0].decode("latin-1").strip()
    m = re.fullmatch(r"([-+])([XY]) +(-?\d+) +([-+])([XY]) +(-?\d+)", line)
    if m is None or m.group(2) == m.group(5):
        raise InputError(path, f"not a valid Radiance .hdr: its size line is {line[:40]!r}, not like '-Y 256 +X 512'")
    sides = int(m.group(3)), int(m.group(6))
    if min(sides) < 1 or sides[0] * sides[1] > HDR_MAX_TEXELS:
        raise InputError(path, f"not a valid Radiance .hdr: its size line gives {sides[0]} x {sides[1]} texels "
                               f"(each side at least 1, at most {HDR_MAX_TEXELS} texels in all)")


def check_envmap(rgb: np.ndarray, path: str | Path, exposure_ev: float = 0.0) -> np.ndarray:
    """The one check of every envmap read (`render --envmap`, `export --envmap`, a scene XML's
    emitter, a dataset's envmaps): an (H, W, 3) lat-long map, twice as wide as high, of at least 4 x 2
    texels, finite, with some light, and whose brightest texel (at this exposure) lies in
    ENV_PEAK_RANGE; an InputError naming `path` otherwise. Returns the map as float32."""
    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[0] < 2 or rgb.shape[1] < 4 or rgb.shape[2] != 3:
        raise InputError(path, f"environment map must be an (H, W, 3) image of at least 4 x 2 texels, got shape "
                               f"{rgb.shape}")
    if rgb.shape[1] != 2 * rgb.shape[0]:
        raise InputError(path, f"a lat-long environment map is twice as wide as high, got {rgb.shape[1]} x "
                               f"{rgb.shape[0]} texels")
    if not np.all(np.isfinite(rgb)):
        raise InputError(path, "environment map contains non-finite values")
    if not float(rgb.max()) > 0.0:
        raise InputError(path, "environment map is black everywhere: it gives no light")
    check_peak(rgb, path, exposure_ev)
    return np.ascontiguousarray(rgb, dtype=np.float32)


def check_peak(rgb: np.ndarray, path: str | Path, exposure_ev: float = 0.0) -> None:
    """Refuse (InputError naming `path`) lighting whose brightest texel, at this exposure, lies
    outside ENV_PEAK_RANGE."""
    peak = float(rgb.max()) * 2.0 ** exposure_ev
    if not ENV_PEAK_RANGE[0] <= peak <= ENV_PEAK_RANGE[1]:
        at = f" at exposure {exposure_ev:+g} EV" if exposure_ev else ""
        raise InputError(path, f"the lighting's brightest texel would be {peak:.3g}{at}: outside "
                               f"{ENV_PEAK_RANGE[0]:g}..{ENV_PEAK_RANGE[1]:g}, where the renders could not be "
                               "finite; choose another envmap" + (" or --exposure" if exposure_ev else ""))


def load_envmap(path: str | Path, exposure_ev: float = 0.0, hdr_only: bool = True) -> np.ndarray:
    """Read a lat-long EXR/HDR as float32 (H, W, 3), checked (`check_envmap`, at this exposure);
    raises InputError naming a bad file. `hdr_only` False also takes what a scene XML's emitter may
    name (PNG, JPEG, PFM)."""
    path = Path(path)
    if hdr_only and path.suffix.lower() not in (".exr", ".hdr"):
        raise InputError(path, "an environment map holds HDR radiance: give an .exr or .hdr lat-long image "
                               f"(not '{path.suffix}')")
    return check_envmap(read_envmap_file(path), path, exposure_ev)


def save_envmap(path: str | Path, array: np.ndarray) -> None:
    """Write a lat-long map as a linear RGB EXR."""
    array = np.asarray(array, dtype=np.float32)
    if array.ndim != 3 or array.shape[-1] != 3:
        raise ValueError(f"environment map must have shape (H, W, 3), got {array.shape}")
    if not np.all(np.isfinite(array)):
        raise ValueError("environment map contains non-finite values")
    if Path(path).suffix.lower() != ".exr":
        raise ValueError(f"{path}: environment maps are written as .exr")
    write_exr(path, array)


def rotate_z(array: np.ndarray, degrees: float) -> np.ndarray:
    """Rotate the lighting by `degrees` about Blender's +Z (counter-clockwise seen from above)."""
    array = np.asarray(array, dtype=np.float32)
    w = array.shape[1]
    shift = degrees / 360.0 * w  # new(col) = old(col + shift)
    i0 = int(math.floor(shift))
    f = shift - i0
    a = np.roll(array, -i0, axis=1)
    b = np.roll(array, -(i0 + 1), axis=1)
    return ((1.0 - f) * a + f * b).astype(np.float32)


def to_mitsuba_dict(env, blender_world: bool = True, scale: float = 1.0) -> dict:
    """An `envmap` emitter dict from an array or a file path.

    blender_world=True: the scene is in Blender world (Z up) and the map is rotated in with
    BLENDER_ENV_TO_WORLD; False: the scene is in Mitsuba world (Y up), identity to_world.
    """
    import mitsuba as mi

    if isinstance(env, (str, Path)):
        env = load_envmap(env)
    d = {"type": "envmap", "bitmap": mi.Bitmap(np.ascontiguousarray(env, dtype=np.float32)),
         "scale": float(scale)}
    if blender_world:
        d["to_world"] = mi.ScalarTransform4f(BLENDER_ENV_TO_WORLD.tolist())
    return d
