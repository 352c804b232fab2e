"""Geometry from images: a fast NeuS stage (dense multi-resolution grids, visual-hull occupancy)
and mesh export (marching cubes, pymeshlab clean-up) with Chamfer / normal-consistency metrics."""
