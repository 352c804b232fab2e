"""Lat-long convention (checked against Mitsuba's envmap emitter) and procedural presets."""

from __future__ import annotations

import math

import numpy as np
import pytest

from vq_mitsuba.data import envmaps as E
from vq_mitsuba.data.cameras import BLENDER_ENV_TO_WORLD
from vq_mitsuba.errors import InputError


@pytest.fixture(scope="module")
def mi():
    import mitsuba

    if mitsuba.variant() is None or not mitsuba.variant().endswith("_rgb"):
        mitsuba.set_variant("llvm_ad_rgb")
    return mitsuba


def _emitter(mi, env, blender_world=True):
    return mi.load_dict(E.to_mitsuba_dict(env, blender_world=blender_world))


def _eval(mi, emitter, dirs):
    import drjit as dr

    dirs = np.asarray(dirs, dtype=np.float64).reshape(-1, 3)
    dirs = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    si = dr.zeros(mi.SurfaceInteraction3f, len(dirs))
    si.wi = mi.Vector3f(*[mi.Float(np.ascontiguousarray(-dirs[:, i], dtype=np.float32)) for i in range(3)])
    v = emitter.eval(si)
    return np.stack([np.array(v.x), np.array(v.y), np.array(v.z)], -1)


def _bilinear(env, col, row):
    """Mitsuba's lookup: bilinear, columns wrap around, rows clamp."""
    h, w = env.shape[:2]
    c0 = np.floor(col).astype(int)
    r0 = np.clip(np.floor(row).astype(int), 0, h - 2)
    fc, fr = (col - c0)[:, None], (row - r0)[:, None]
    c0w, c1w = np.mod(c0, w), np.mod(c0 + 1, w)
    top = (1 - fc) * env[r0, c0w] + fc * env[r0, c1w]
    bot = (1 - fc) * env[r0 + 1, c0w] + fc * env[r0 + 1, c1w]
    return (1 - fr) * top + fr * bot


@pytest.mark.parametrize("name", E.PRESETS)
def test_presets_finite_positive(name):
    env = E.named_envmap(name, 64, 32)
    assert env.shape == (32, 64, 3) and env.dtype == np.float32
    assert np.all(np.isfinite(env)) and np.all(env > 0)
    # Lit from above more than from below.
    assert E.irradiance(env, [0, 0, 1]).mean() > E.irradiance(env, [0, 0, -1]).mean()


def test_unknown_preset():
    with pytest.raises(InputError):
        E.named_envmap("nope")


def test_uv_and_pixel_round_trip():
    rng = np.random.default_rng(0)
    d = rng.normal(size=(500, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    u, v = E.direction_to_uv(d)
    assert np.all((u >= 0) & (u < 1) & (v >= 0) & (v <= 1))
    np.testing.assert_allclose(E.uv_to_direction(u, v), d, atol=1e-9)
    col, row = E.direction_to_pixel(d, 64, 32)
    np.testing.assert_allclose(E.pixel_to_direction(col, row, 64, 32), d, atol=1e-9)
    # Named axes: image centre is +X, u = 0.25 is +Y, top row is +Z.
    u, v = E.direction_to_uv(np.array([[1.0, 0, 0], [0, 1.0, 0], [0, -1.0, 0], [0, 0, 1.0]]))
    np.testing.assert_allclose(u[:3], [0.5, 0.25, 0.75], atol=1e-12)
    np.testing.assert_allclose(v, [0.5, 0.5, 0.5, 0.0], atol=1e-12)
    assert E.texel_solid_angles(64, 32).sum() == pytest.approx(4 * math.pi)


def test_mitsuba_eval_matches_texels(mi):
    """emitter.eval(d) with to_world = BLENDER_ENV_TO_WORLD returns the texel direction_to_pixel(d) names."""
    h, w = 16, 32
    rng = np.random.default_rng(1)
    env = rng.uniform(0.1, 2.0, size=(h, w, 3)).astype(np.float32)
    emitter = _emitter(mi, env)
    # Texel positions: exact texel values (rows 0 and h-1 sit on the poles, where all their
    # texels share one direction: procedural maps are constant along them).
    rows, cols = np.meshgrid(np.arange(1, h - 1), np.arange(w), indexing="ij")
    dirs = E.pixel_to_direction(cols.ravel(), rows.ravel(), w, h)
    np.testing.assert_allclose(_eval(mi, emitter, dirs), env[1:-1].reshape(-1, 3), rtol=1e-4, atol=1e-5)
    # Arbitrary directions: Mitsuba interpolates bilinearly between the texels named.
    d = rng.normal(size=(300, 3))
    col, row = E.direction_to_pixel(d, w, h)
    np.testing.assert_allclose(_eval(mi, emitter, d), _bilinear(env, col, row), rtol=1e-3, atol=1e-4)
    # The same map in Mitsuba world with identity to_world: direction R^-1 d gives the same value.
    r = BLENDER_ENV_TO_WORLD[:3, :3]
    np.testing.assert_allclose(_eval(mi, _emitter(mi, env, blender_world=False), d @ r),
                               _eval(mi, emitter, d), rtol=1e-4, atol=1e-5)


def test_sun_position_and_brightest_in_mitsuba(mi):
    env = E.named_envmap("sky")
    h, w = env.shape[:2]
    sun = E.sun_direction(E.SKY_SUN_ELEVATION_DEG, E.SKY_SUN_AZIMUTH_DEG)
    i, j = np.unravel_index(np.argmax(env.sum(-1)), (h, w))
    d = E.pixel_to_direction(j, i, w, h)
    texel_deg = 180.0 / (h - 1)
    assert math.degrees(math.acos(np.clip(d @ sun, -1, 1))) < texel_deg
    assert math.degrees(math.asin(d[2])) == pytest.approx(E.SKY_SUN_ELEVATION_DEG, abs=texel_deg)
    assert math.degrees(math.atan2(d[1], d[0])) == pytest.approx(E.SKY_SUN_AZIMUTH_DEG, abs=2 * texel_deg)
    col, row = E.direction_to_pixel(d, w, h)
    assert (int(round(float(row))), int(round(float(col))) % w) == (i, j)
    # Mitsuba sees the brightest texel in the sun's direction and nowhere else.
    emitter = _emitter(mi, env)
    at_sun = _eval(mi, emitter, d[None])[0]
    np.testing.assert_allclose(at_sun, env[i, j], rtol=1e-4)
    rng = np.random.default_rng(2)
    others = rng.normal(size=(2000, 3))
    others /= np.linalg.norm(others, axis=1, keepdims=True)
    others = others[others @ sun < math.cos(math.radians(10))]
    assert _eval(mi, emitter, others).sum(-1).max() < 0.1 * at_sun.sum()
    # Sunlight dominates the sunny side.
    assert E.irradiance(env, sun).mean() > 2 * E.irradiance(env, -sun).mean()


def test_rotate_z_moves_sun():
    env = E.sky(128, 64, sun_elevation_deg=30.0, sun_azimuth_deg=10.0)
    rot = E.rotate_z(env, 45.0)
    h, w = rot.shape[:2]
    i, j = np.unravel_index(np.argmax(rot.sum(-1)), (h, w))
    d = E.pixel_to_direction(j, i, w, h)
    assert math.degrees(math.atan2(d[1], d[0])) == pytest.approx(55.0, abs=4.0)


def test_save_load_round_trip(tmp_path):
    env = E.named_envmap("studio", 32, 16)
    E.save_envmap(tmp_path / "env.exr", env)
    np.testing.assert_array_equal(E.load_envmap(tmp_path / "env.exr"), env)
    bad = tmp_path / "bad.exr"
    bad.write_bytes(b"not an exr")
    with pytest.raises(InputError, match="bad.exr"):
        E.load_envmap(bad)
    with pytest.raises(InputError):
        E.load_envmap(tmp_path / "missing.exr")
    with pytest.raises(ValueError):
        E.save_envmap(tmp_path / "nan.exr", np.full((4, 8, 3), np.nan, dtype=np.float32))


def test_blender_probes_is_a_dict():
    probes = E.blender_probes()
    assert isinstance(probes, dict)
    for path in probes.values():
        assert path.suffix == ".exr" and path.is_file()
