"""Photos without poses, for the SfM tests: a textured scene of the synthetic generator
(vq_mitsuba.synthetic) rendered from cameras that circle it, as a phone would, written as plain
sRGB PNGs (no alpha, no camera file). The true cameras come back for the pose checks."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

# Textures SIFT finds corners in: high-contrast value noise on a base, a block and a sphere.
SPEC = {
    "materials": [
        {"name": "speckle", "base_color": {"pattern": "noise", "frequency": 28.0, "softness": 0.15,
                                           "colors": [[0.08, 0.08, 0.1], [0.85, 0.8, 0.7]]},
         "metallic": 0.0, "roughness": 0.8},
        {"name": "paint", "base_color": {"pattern": "noise", "frequency": 36.0, "softness": 0.2, "seed": 3,
                                         "colors": [[0.7, 0.1, 0.05], [0.95, 0.85, 0.3]]},
         "metallic": 0.0, "roughness": 0.6},
    ],
    "shapes": [
        {"name": "base", "type": "box", "extents": [1.2, 1.2, 0.1], "max_edge": 0.01, "center": [0.0, 0.0, -0.05],
         "material": "speckle"},
        {"name": "block", "type": "box", "extents": [0.4, 0.3, 0.3], "max_edge": 0.01, "center": [0.2, -0.15, 0.15],
         "rotation_deg": [0.0, 0.0, 20.0], "material": "paint"},
        {"name": "ball", "type": "icosphere", "subdivisions": 5, "radius": 0.2, "center": [-0.25, 0.2, 0.2],
         "material": "paint"},
    ],
}
RADIUS = 0.9  # about the scene's bounding radius (Blender and Mitsuba world alike)


def orbit_cameras(n: int, size: int, elevation_deg: float = 35.0, distance: float = 1.9, turns: float = 1.0):
    """Mitsuba-world cameras (Y up) on a circle about the origin at `elevation_deg`, covering
    `turns` of a full turn, in order (as a phone walking around the object records them)."""
    from vq_mitsuba.data.cameras import Camera, look_at

    el = math.radians(elevation_deg)
    cams = []
    for i in range(n):
        az = 2 * math.pi * turns * i / n
        origin = distance * np.array([math.cos(el) * math.cos(az), math.sin(el), math.cos(el) * math.sin(az)])
        cams.append(Camera(f"photo_{i:03d}", look_at(origin, [0.0, 0.05, 0.0], [0.0, 1.0, 0.0]), 50.0, size, size))
    return cams


def render_orbit(folder: Path, cameras, spp: int = 8) -> list[np.ndarray]:
    """Render `cameras` (Mitsuba world) of SPEC under the `overcast` envmap (direct light: the photos
    need texture, not interreflections); returns the linear RGB
    images. The scene's meshes go to folder/meshes."""
    import mitsuba as mi

    from vq_mitsuba.backend import init_mitsuba
    from vq_mitsuba.data import envmaps
    from vq_mitsuba.synthetic import mitsuba_scenes as ms

    init_mitsuba()
    (folder / "meshes").mkdir(parents=True, exist_ok=True)
    ms.write_geometry(SPEC, folder)
    base = dict(ms._mitsuba_scene_dict(SPEC, folder), integrator={"type": "direct", "hide_emitters": True})
    scene = ms._scene_with(base, envmaps.named_envmap("overcast"))
    images = []
    for i, cam in enumerate(cameras):
        img = np.array(mi.render(scene, sensor=mi.load_dict(cam.to_mitsuba_dict(spp)), seed=i))
        images.append(np.clip(img[..., :3], 0, None))
    return images


def write_photos(folder: Path, n: int = 24, size: int = 200, spp: int = 8, **orbit) -> list:
    """folder/photo_NNN.png of an orbit (nothing else in the folder); returns the true cameras."""
    from vq_mitsuba.data.imageio import write_png

    folder = Path(folder)
    cams = orbit_cameras(n, size, **orbit)
    scratch = folder.parent / f".{folder.name}-scene"
    for cam, img in zip(cams, render_orbit(scratch, cams, spp)):
        write_png(folder / f"{cam.name}.png", img)
    return cams


def write_video(path: Path, photos: list[Path], fps: int = 24, blurred: int = 2) -> None:
    """An H.264 video (the ffmpeg imageio-ffmpeg ships) showing each photo for 1 + `blurred`
    frames: blurred copies (as a moving phone records them) around the sharp one."""
    import imageio.v3 as iio
    import imageio_ffmpeg
    from scipy.ndimage import gaussian_filter

    first = iio.imread(photos[0])
    h, w = first.shape[:2]
    writer = imageio_ffmpeg.write_frames(str(path), (w, h), fps=fps, codec="libx264", macro_block_size=2,
                                         quality=None, output_params=["-crf", "12"], ffmpeg_log_level="error")
    writer.send(None)
    for photo in photos:
        sharp = iio.imread(photo)[..., :3]
        soft = np.clip(gaussian_filter(sharp.astype(np.float32), (2.0, 2.0, 0)), 0, 255).astype(np.uint8)
        for k in range(1 + blurred):
            writer.send(np.ascontiguousarray(sharp if k == blurred // 2 else soft))
    writer.close()


def umeyama(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Similarity (s, R, t) minimising |s R src + t - dst|^2 over points (N, 3) (Umeyama 1991)."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    a, b = src - mu_s, dst - mu_d
    u, d, vt = np.linalg.svd(b.T @ a / len(src))
    e = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        e[2, 2] = -1
    r = u @ e @ vt
    s = float(np.trace(np.diag(d) @ e) / a.var(0).sum())
    return s, r, mu_d - s * r @ mu_s


def centre_errors(found: dict, truth: dict) -> np.ndarray:
    """Distances between the true camera centres and the found ones (name -> (3,) centre) after
    the best similarity takes the found onto the true, for the names both hold."""
    names = sorted(set(found) & set(truth))
    src = np.array([found[n] for n in names])
    dst = np.array([truth[n] for n in names])
    s, r, t = umeyama(src, dst)
    return np.linalg.norm(src @ (s * r).T + t - dst, axis=1)
