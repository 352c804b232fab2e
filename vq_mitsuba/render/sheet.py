"""The material sheet: each ranked material as a sphere with its BRDF under the fitted light."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from vq_mitsuba import brdf
from vq_mitsuba.data.cameras import Camera, camera_rays, look_at
from vq_mitsuba.data.imageio import linear_to_srgb


def render_spheres(materials: list[dict], envmap: np.ndarray, env_to_world: np.ndarray, size: int = 96,
                   spp: int = 64, seed: int = 0) -> list[np.ndarray]:
    """One (size, size, 4) linear RGBA image per material (keys basecolor, metallic, roughness):
    a unit sphere seen from +Z of the envmap's frame, shaded by `ShadingScene` (Mitsuba's
    principled BSDF, envmap importance sampling; the sphere is convex, so no bounce)."""
    import trimesh

    from vq_mitsuba.render.shading import ShadingScene

    sphere = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    scene = ShadingScene(sphere.vertices, sphere.faces, envmap, env_to_world, normals=sphere.vertex_normals)
    to_world = np.asarray(env_to_world)[:3, :3]
    eye = to_world @ np.array([0.0, 0.0, 3.2])
    up = to_world @ np.array([0.0, 1.0, 0.0])
    cam = Camera("sphere", look_at(eye, np.zeros(3), up), 42.0, size, size)
    o, d = camera_rays(cam)
    hits = scene.trace(o, d)
    idx = torch.nonzero(hits.valid)[:, 0]
    dev = hits.position.device
    env_t = torch.as_tensor(np.ascontiguousarray(envmap, dtype=np.float32), device=dev)
    images = []
    for m in materials:
        n = len(idx)
        material = {i.name: torch.tensor(m[i.name], dtype=torch.float32, device=dev)
                    .expand((n, 3) if i.colour else (n,)) for i in brdf.INPUTS}  # the one material at every hit
        gen = torch.Generator(device=dev).manual_seed(seed)
        rgb = scene.shade(hits.position[idx], hits.normal[idx], hits.wi[idx], material, env_t, spp, generator=gen)
        img = np.zeros((size * size, 4), np.float32)
        img[idx.cpu().numpy(), :3] = rgb.detach().cpu().numpy()
        img[idx.cpu().numpy(), 3] = 1.0
        images.append(img.reshape(size, size, 4))
    return images


def write_material_sheet(materials: list[dict], envmap: np.ndarray, env_to_world: np.ndarray, path: Path) -> None:
    """One PNG: each ranked material (materials.json entries) as a sphere, titled with its id,
    pixel share and BRDF."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    spheres = render_spheres(materials, envmap, env_to_world)
    n = max(len(materials), 1)
    cols = min(n, 5)
    rows = (n + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(2.2 * cols, 2.6 * rows), squeeze=False)
    for ax in axes.ravel():
        ax.axis("off")
    for ax, m, img in zip(axes.ravel(), materials, spheres):
        a = img[..., 3:]
        over_grey = linear_to_srgb(np.clip(img[..., :3], 0, None)) * a + 0.5 * (1 - a)
        ax.imshow(np.clip(over_grey, 0, 1))
        ax.set_title(f"{m['id']}: {100 * m['pixel_fraction']:.1f} % of pixels\n"
                     + ", ".join(f"{i.name} {m[i.name]:.2f}" for i in brdf.INPUTS if not i.colour), fontsize=8)
    fig.suptitle("materials, ranked (sphere under the fitted light)", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
