"""UV atlases of meshes: what the texel baseline fits and what `export` bakes into."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from vq_mitsuba import messages
from vq_mitsuba.errors import InputError


def uv_unwrap(vertices: np.ndarray, faces: np.ndarray, resolution: int, padding: int = 2):
    """UV atlas of a mesh: (vmapping (V',) into the input vertices, faces (F, 3), uvs (V', 2)).

    xatlas, run in a child process: it crashes (segfault, upstream jpcy/xatlas#151) on some
    meshes, e.g. the 81920-face icosphere of the `texture` scene. Where it does, the atlas comes
    from MeshLab's Voronoi atlas parametrisation (pymeshlab) instead."""
    import subprocess
    import sys
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        src, dst = Path(tmp) / "mesh.npz", Path(tmp) / "atlas.npz"
        np.savez(src, vertices=np.asarray(vertices, np.float32), faces=np.asarray(faces, np.uint32))
        proc = subprocess.run([sys.executable, "-c", _XATLAS_CHILD, str(src), str(dst), str(int(resolution)),
                               str(int(padding))], capture_output=True, text=True)
        if proc.returncode == 0 and dst.is_file():
            out = np.load(dst)
            return out["vmapping"].astype(np.int64), out["faces"].astype(np.int64), out["uvs"].astype(np.float32)
    messages.note(f"xatlas failed on this mesh (exit code {proc.returncode}); using MeshLab's Voronoi atlas instead")
    return _voronoi_atlas(vertices, faces)


_XATLAS_CHILD = """
import sys
import numpy as np
import xatlas
src, dst, res, pad = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4])
m = np.load(src)
atlas = xatlas.Atlas()
atlas.add_mesh(np.ascontiguousarray(m["vertices"]), np.ascontiguousarray(m["faces"]))
pack = xatlas.PackOptions()
pack.resolution, pack.padding, pack.bilinear = res, pad, True
atlas.generate(pack_options=pack)
vmapping, faces, uvs = atlas[0]
np.savez(dst, vmapping=vmapping, faces=faces, uvs=uvs)
"""


def _voronoi_atlas(vertices: np.ndarray, faces: np.ndarray):
    """MeshLab's Voronoi atlas (per-wedge UVs) as (vmapping, faces, uvs); triangles keep their order."""
    import pymeshlab

    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(np.asarray(vertices, np.float64), np.asarray(faces, np.int32)))
    ms.generate_voronoi_atlas_parametrization(regionnum=max(10, len(faces) // 2000), overlapflag=False)
    m = ms.mesh(ms.mesh_number() - 1)
    new_v, new_f = m.vertex_matrix(), m.face_matrix()
    wedge = m.wedge_tex_coord_matrix().reshape(-1, 3, 2)
    # The parametrised copy may renumber vertices: map them back by position.
    from scipy.spatial import cKDTree

    dist, to_input = cKDTree(np.asarray(vertices, np.float64)).query(new_v)
    if len(new_f) != len(faces) or dist.max() > 1e-5:
        raise InputError(None, "UV atlas: MeshLab's parametrisation changed the mesh")
    corner_v = to_input[new_f].reshape(-1)
    corner_uv = wedge.reshape(-1, 2)
    key = np.concatenate([corner_v[:, None].astype(np.float64), np.round(corner_uv, 7)], 1)
    uniq, inverse = np.unique(key, axis=0, return_inverse=True)
    vmapping = uniq[:, 0].astype(np.int64)
    uvs = np.clip(uniq[:, 1:], 0.0, 1.0).astype(np.float32)
    new_faces = inverse.reshape(-1, 3).astype(np.int64)
    # Same triangles as the input, in the input's order (match by their vertex sets).
    order = {tuple(sorted(f)): i for i, f in enumerate(np.asarray(faces).tolist())}
    perm = np.array([order[tuple(sorted(f))] for f in vmapping[new_faces].tolist()])
    out = np.empty_like(new_faces)
    out[perm] = new_faces
    return vmapping, out, uvs
