"""Geometry: signed-distance grids of shapes (and, later, meshes → voxel objects)."""
from .primitives import box_sdf, corner_points, sphere_sdf, spherical_shell_sdf, torus_sdf

__all__ = ["corner_points", "sphere_sdf", "torus_sdf", "box_sdf", "spherical_shell_sdf"]
