"""Geometry: signed-distance grids of shapes; triangle meshes → voxel objects (occupancy, SDF band, texels)."""
from .primitives import box_sdf, conical_shell_sdf, corner_points, sphere_sdf, spherical_shell_sdf, torus_sdf
from .mesh import load_mesh
from .voxelize import VoxelObject, check_grid_size, voxelize

__all__ = ["corner_points", "sphere_sdf", "torus_sdf", "box_sdf", "spherical_shell_sdf", "conical_shell_sdf", "VoxelObject", "voxelize",
           "check_grid_size", "load_mesh"]
