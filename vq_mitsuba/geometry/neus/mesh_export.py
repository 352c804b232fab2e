"""A trained NeuS model's surface as a mesh in the world: its SDF on a grid (inside the visual hull,
never below the hull's distance by more than a tolerance), marching cubes, without masks the
supporting plane cut away, then cleaned and its normals smoothed."""

from __future__ import annotations

import numpy as np
import torch

from vq_mitsuba.errors import InputError
from vq_mitsuba.geometry.neus.networks import trilinear
from vq_mitsuba.geometry.neus.renderer import NeuS


@torch.no_grad()
def sdf_volume(neus: NeuS, res: int, chunk: int = 131072) -> np.ndarray:
    """SDF on a res^3 grid spanning [-1, 1]^3 (box units), limited to the visual hull."""
    axis = torch.linspace(-1.0, 1.0, res, device=neus.device)
    hull_res = neus.cfg.hull_resolution
    lw = [1.0] * neus.cfg.levels
    vol = torch.empty(res, res, res, device=neus.device)
    # Outside the (dilated) hull the SDF is the hull's own distance; inside, the network's,
    # never below the hull distance minus a tolerance (the visual-hull constraint).
    tol = 2.0 * 2.0 / hull_res
    for i in range(res):
        p = torch.stack(torch.meshgrid(axis[i:i + 1], axis, axis, indexing="ij"), -1).reshape(-1, 3)
        hs = trilinear(neus.box.hull_sdf.reshape(-1, 1), hull_res, p)[:, 0]
        inside = neus._lookup(neus.box.hull_dilated, p)
        s = hs.clone()
        if bool(inside.any()):
            q = p[inside]
            s[inside] = torch.cat([neus.model.sdf(q[j:j + chunk], lw)[0] for j in range(0, len(q), chunk)])
            s = torch.maximum(s, hs - tol)
        vol[i] = s.view(res, res)
    return vol.cpu().numpy()


def _without_support(neus: NeuS, vol: np.ndarray, mesh):
    """(the mesh (box units) cut above a supporting plane, the known one or the one the mesh shows
    (`support_plane`): the volume below the plane plus two grid cells made empty and the surface
    extracted again; the plane in world units ({normal, point, from}) or None)."""
    from vq_mitsuba.geometry.mesh import marching_cubes, support_plane

    res = vol.shape[0]
    cell = 2.0 / (res - 1)
    if neus.box.plane is not None:
        plane = (neus.box.plane[0].cpu().numpy().astype(np.float64), neus.box.plane[1])
    else:
        views = neus.to_box(torch.from_numpy(neus.views)).numpy()
        points = None if neus.points is None else neus.to_box(torch.from_numpy(neus.points)).numpy()
        plane = support_plane(mesh, views, radius=1.0, tol=1.5 * cell, seed=neus.cfg.seed, points=points)
    if plane is None:
        return mesh, None
    n, c = plane
    axis = np.linspace(-1.0, 1.0, res)
    x, y, z = np.meshgrid(axis, axis, axis, indexing="ij")
    above = (c + 2.0 * cell) - (n[0] * x + n[1] * y + n[2] * z)  # positive (empty) below the cut
    try:
        cut = marching_cubes(np.maximum(vol, above.astype(np.float32)), (-1.0, -1.0, -1.0), (1.0, 1.0, 1.0))
    except ValueError:  # nothing stands on the plane: keep the surface as it is
        return mesh, None
    return cut, {"normal": [float(v) for v in n], "point": neus.to_world(n * c).tolist(),
                 "from": "sparse points" if neus.box.plane is not None else "mesh"}


def extract_mesh(neus: NeuS, res: int | None = None, clean: bool = True):
    """(the surface as a trimesh in the world, the supporting plane cut away or None); `clean`: only
    sizeable pieces (without masks the largest), smoothed normals, at most neus.max_faces faces."""
    from vq_mitsuba.geometry.mesh import clean_mesh, marching_cubes, smooth_vertex_normals

    res = res or neus.cfg.mesh_resolution
    vol = sdf_volume(neus, res)
    support = None
    try:
        mesh = marching_cubes(vol, (-1.0, -1.0, -1.0), (1.0, 1.0, 1.0))
        if neus.box.mask_free and clean:
            mesh, support = _without_support(neus, vol, mesh)
    except ValueError as exc:
        raise InputError(neus.source, f"NeuS produced no surface ({exc}); check the masks and cameras") from exc
    mesh.vertices = neus.to_world(mesh.vertices)
    if clean:
        c = neus.cfg
        # without masks only the largest piece is the object (the rest: background the SDF took)
        mesh = clean_mesh(mesh, c.min_component, c.keep_largest or neus.box.mask_free, c.smooth_iterations,
                          c.max_faces)
        if c.normal_smoothing > 0:
            mesh = smooth_vertex_normals(mesh, c.normal_smoothing, c.normal_smoothing_angle)
    return mesh, support
