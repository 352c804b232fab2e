"""Bake a fitted run's material fields into textures on a UV atlas of its mesh.

The mesh is unwrapped once (xatlas, `geometry.uv`); every texel whose centre lies within one
texel of a triangle in UV space is evaluated at its point on (or, near chart borders, just
beside) that triangle, so bilinear lookups inside a chart read field values, not background.
Texels outside every chart are then filled from their neighbours (padding against seams and
mipmapping). Texture row 0 is v = 0, as glTF and Mitsuba's `bitmap` read it.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import torch

from vq_mitsuba.brdf import INPUTS
from vq_mitsuba.geometry.uv import uv_unwrap
from vq_mitsuba.models.fitted import FittedModel

CHUNK = 1 << 16  # points per field evaluation
MAX_CANDIDATES = 1 << 23  # texel-triangle pairs tested at once by the rasteriser


@dataclass
class BakedMesh:
    vertices: np.ndarray  # (V, 3) float32, the run's world; seams split vertices
    faces: np.ndarray  # (F, 3) int64
    normals: np.ndarray  # (V, 3) float32, the shading normals the renderer uses
    uvs: np.ndarray  # (V, 2) float32 in [0, 1], v = 0 at texture row 0
    basecolor: np.ndarray  # (S, S, 3) linear RGB
    metallic: np.ndarray  # (S, S)
    roughness: np.ndarray  # (S, S)
    material: np.ndarray | None  # (S, S) uint8 ranked material id (0 outside every chart), None without one
    coverage: np.ndarray  # (S, S) bool, texels evaluated on the surface
    seconds: dict = field(default_factory=dict)


def rasterise_uv(uvs: np.ndarray, faces: np.ndarray, size: int, grow_px: float = 1.0):
    """Texels of an S x S texture covered by triangles in UV space.

    Returns (texel flat index (T,), triangle (T,), barycentrics (T, 3)); a texel whose centre is
    inside a triangle takes that one, others within `grow_px` texels of a triangle take the
    nearest such (barycentrics then extrapolate slightly past the triangle's edge).
    """
    p = uvs[faces].astype(np.float64) * size - 0.5  # (F, 3, 2): texel centres sit at integers
    lo = np.clip(np.floor(p.min(1) - grow_px), 0, size - 1).astype(np.int64)
    hi = np.clip(np.ceil(p.max(1) + grow_px), 0, size - 1).astype(np.int64)
    w, h = hi[:, 0] - lo[:, 0] + 1, hi[:, 1] - lo[:, 1] + 1
    a, b, c = p[:, 0], p[:, 1], p[:, 2]
    area2 = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    edge_len = np.stack([np.linalg.norm(c - b, axis=1), np.linalg.norm(a - c, axis=1),
                         np.linalg.norm(b - a, axis=1)], 1)
    ok = np.abs(area2) > 1e-12
    altitude = np.abs(area2)[:, None] / np.maximum(edge_len, 1e-12)  # distance of each vertex to its opposite edge
    best_texel, best_tri, best_bary, best_dist = [], [], [], []
    counts = np.where(ok, w * h, 0)
    starts = np.concatenate([[0], np.cumsum(counts)])
    # Triangles in groups of at most MAX_CANDIDATES texel candidates.
    tri0 = 0
    while tri0 < len(faces):
        tri1 = int(np.searchsorted(starts, starts[tri0] + MAX_CANDIDATES, side="right")) - 1
        tri1 = max(tri1, tri0 + 1)
        tris = np.arange(tri0, min(tri1, len(faces)))
        n = counts[tris]
        t = np.repeat(tris, n)
        local = np.arange(int(n.sum())) - np.repeat(starts[tris] - starts[tri0], n)
        x = lo[t, 0] + local % w[t]
        y = lo[t, 1] + local // w[t]
        px, py = x.astype(np.float64), y.astype(np.float64)
        # Barycentrics of (px, py) in triangle t.
        l1 = ((px - a[t, 0]) * (c[t, 1] - a[t, 1]) - (py - a[t, 1]) * (c[t, 0] - a[t, 0])) / area2[t]
        l2 = ((b[t, 0] - a[t, 0]) * (py - a[t, 1]) - (b[t, 1] - a[t, 1]) * (px - a[t, 0])) / area2[t]
        bary = np.stack([1.0 - l1 - l2, l1, l2], 1)
        outside = np.max(np.maximum(-bary, 0.0) * altitude[t], axis=1)  # texels past the farthest edge
        keep = outside <= grow_px
        best_texel.append(y[keep] * size + x[keep])
        best_tri.append(t[keep])
        best_bary.append(bary[keep])
        best_dist.append(outside[keep])
        tri0 = int(tris[-1]) + 1
    texel = np.concatenate(best_texel)
    tri = np.concatenate(best_tri)
    bary = np.concatenate(best_bary)
    dist = np.concatenate(best_dist)
    order = np.lexsort((dist, texel))  # per texel, the closest triangle first
    texel, tri, bary, dist = texel[order], tri[order], bary[order], dist[order]
    first = np.ones(len(texel), bool)
    first[1:] = texel[1:] != texel[:-1]
    return texel[first], tri[first], bary[first].astype(np.float32)


def pad_texture(values: np.ndarray, filled: np.ndarray, iterations: int = 16) -> np.ndarray:
    """Fill texels outside `filled` (S, S) with the mean of their filled neighbours, growing
    `iterations` texels out from the charts; the rest take the mean of all filled texels."""
    v = values.reshape(filled.shape + (-1,)).astype(np.float32).copy()
    known = filled.copy()
    for _ in range(iterations):
        if known.all():
            break
        total = np.zeros_like(v)
        count = np.zeros(known.shape, np.float32)
        for dy, dx in ((-1, 0), (1, 0), (0, -1), (0, 1), (-1, -1), (-1, 1), (1, -1), (1, 1)):
            src = np.roll(np.roll(known, dy, 0), dx, 1)
            # np.roll wraps around: neighbours across the texture's border do not count.
            if dy:
                src[0 if dy > 0 else -1, :] = False
            if dx:
                src[:, 0 if dx > 0 else -1] = False
            total += np.where(src[..., None], np.roll(np.roll(v, dy, 0), dx, 1), 0.0)
            count += src
        grow = ~known & (count > 0)
        v[grow] = total[grow] / count[grow][:, None]
        known = known | grow
    if not known.all() and filled.any():
        v[~known] = v[filled].mean(0)
    return v.reshape(values.shape)


def pad_ids(ids: np.ndarray, filled: np.ndarray, iterations: int = 16) -> np.ndarray:
    """pad_texture for an id map: a grown texel takes the largest id among its filled neighbours."""
    v, known = ids.copy(), filled.copy()
    for _ in range(iterations):
        grow_val = np.zeros_like(v)
        for dy, dx in ((-1, 0), (1, 0), (0, -1), (0, 1)):
            src = np.roll(np.roll(known, dy, 0), dx, 1)
            grow_val = np.maximum(grow_val, np.where(src, np.roll(np.roll(v, dy, 0), dx, 1), 0))
        grow = ~known & (grow_val > 0)
        if not grow.any():
            break
        v[grow] = grow_val[grow]
        known |= grow
    return v


def bake(fitted: FittedModel, size: int = 1024, branch: str = "continuous") -> BakedMesh:
    """UV-unwrap the run's mesh and bake basecolor, metallic, roughness (of `branch`,
    "continuous" or "discrete", with the run's edits) and the material ids into S x S textures."""
    from vq_mitsuba import messages

    if branch not in ("continuous", "discrete"):
        raise ValueError(f"branch must be continuous or discrete, got {branch!r}")
    if branch == "discrete" and fitted.discrete is None:
        from vq_mitsuba.errors import InputError

        raise InputError(None, "--branch discrete: this run has no discrete branch (fitted with --preset continuous?)")
    seconds = {}
    t0 = time.perf_counter()
    mesh = fitted.mesh
    vmapping, faces, uvs = uv_unwrap(mesh.vertices, mesh.faces, size, padding=max(2, size // 256))
    seconds["unwrap"] = time.perf_counter() - t0
    vertices = np.asarray(mesh.vertices, np.float32)[vmapping]
    normals = np.asarray(mesh.vertex_normals, np.float32)[vmapping]
    t0 = time.perf_counter()
    texel, tri, bary = rasterise_uv(uvs, faces, size)
    points = np.einsum("tk,tkc->tc", bary, vertices[faces[tri]])
    seconds["rasterise"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    dev = fitted.model.center.device
    n = len(points)
    values = {i.name: np.zeros((n, i.channels), np.float32) for i in INPUTS}
    ids = np.zeros(n, np.uint8) if fitted.discrete is not None else None
    for s in messages.progress(range(0, n, CHUNK), desc=f"bake {size}x{size}"):
        pts = torch.as_tensor(points[s:s + CHUNK], device=dev)
        out = fitted.materials_at(pts, discrete=branch == "discrete")
        src = out["discrete"] if branch == "discrete" else out
        for i in INPUTS:
            values[i.name][s:s + CHUNK] = src[i.name].reshape(-1, i.channels).cpu().numpy()
        if ids is not None:
            ids[s:s + CHUNK] = out["material"].cpu().numpy().astype(np.uint8)
    seconds["evaluate"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    filled = np.zeros(size * size, bool)
    filled[texel] = True
    filled = filled.reshape(size, size)

    def image(i):  # the input's texture, (S, S, 3) for a colour, (S, S) for a scalar
        img = np.zeros((size * size, i.channels), np.float32)
        img[texel] = values[i.name]
        img = pad_texture(img.reshape(size, size, i.channels), filled)
        return img if i.colour else img[..., 0]

    textures = {i.name: image(i) for i in INPUTS}
    material = None
    if ids is not None:
        material = np.zeros(size * size, np.uint8)
        material[texel] = ids
        material = pad_ids(material.reshape(size, size), filled)
    seconds["pad"] = time.perf_counter() - t0
    return BakedMesh(vertices, faces, normals, uvs.astype(np.float32), **textures, material=material,
                     coverage=filled, seconds=seconds)
