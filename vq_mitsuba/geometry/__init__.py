"""Geometry from images: a fast NeuS stage (dense multi-resolution grids, visual-hull occupancy)
and mesh export (marching cubes, pymeshlab clean-up) with Chamfer / normal-consistency metrics."""

from .config import NeuSConfig, apply_overrides

__all__ = ["NeuSConfig", "apply_overrides"]
