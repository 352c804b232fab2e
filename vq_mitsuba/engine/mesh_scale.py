"""Plausibility checks of a capture before a fit: warnings for inputs that load but cannot be right."""

from __future__ import annotations

import numpy as np

TINY_MESH = 1e-3  # a bounding-sphere radius below this share of the nearest camera's distance is implausible


def mesh_scale_warning(mesh, cameras) -> str | None:
    """A warning when the mesh's bounding sphere is implausible next to the camera positions: it
    encloses every camera (e.g. a mesh in millimetres for cameras in metres: every ray then hits it
    from inside, coverage 1.0), or it is a speck at the cameras' distance; None when plausible."""
    lo, hi = np.asarray(mesh.bounds, np.float64)
    centre, radius = (lo + hi) / 2, float(np.linalg.norm(hi - lo)) / 2
    origins = np.array([c.origin for c in cameras], np.float64)
    if not len(origins) or not np.isfinite(radius):
        return None
    dist = np.linalg.norm(origins - centre, axis=1)
    if radius > dist.max():
        return (f"the mesh's bounding sphere (radius {radius:.3g}) encloses every camera (they are "
                f"{dist.min():.3g} to {dist.max():.3g} from its centre): is the mesh in the cameras' units and world?")
    if radius < TINY_MESH * dist.min():
        return (f"the mesh (bounding-sphere radius {radius:.3g}) is tiny next to the cameras' distance "
                f"({dist.min():.3g} and more): is the mesh in the cameras' units?")
    return None
