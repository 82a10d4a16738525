"""Signed-distance grids of analytic shapes, sampled at voxel corners for :class:`~torch_appearance.render.SDFBoundary`.

Every function returns a (D+1, H+1, W+1) float64 tensor of exact signed distances in mm (negative inside) at the
corners of a (D, H, W) grid of voxels with edges ``voxel_size`` placed at ``origin``: corner (k, j, i) sits at
``origin + (i·sx, j·sy, k·sz)``. Useful for tests, previews and calibration objects.
"""
import torch

from ..checks import check_int, check_real, check_vector3
from ..render.scene import voxel_edges

__all__ = ["corner_points", "sphere_sdf", "torus_sdf", "box_sdf", "spherical_shell_sdf", "conical_shell_sdf"]


def corner_points(grid_shape, voxel_size, origin=(0.0, 0.0, 0.0)):
    """World positions (mm) of the voxel corners: (D+1, H+1, W+1, 3) float64, last axis (x, y, z)."""
    if not isinstance(grid_shape, (tuple, list)) or len(grid_shape) != 3:
        raise ValueError(f"grid_shape: expected (D, H, W), got {grid_shape!r}")
    d, h, w = (check_int("grid_shape", n, lo=1) for n in grid_shape)
    sx, sy, sz = voxel_edges(voxel_size)
    ox, oy, oz = check_vector3("origin", origin)
    z = oz + sz * torch.arange(d + 1, dtype=torch.float64)
    y = oy + sy * torch.arange(h + 1, dtype=torch.float64)
    x = ox + sx * torch.arange(w + 1, dtype=torch.float64)
    zz, yy, xx = torch.meshgrid(z, y, x, indexing="ij")
    return torch.stack([xx, yy, zz], dim=-1)


def sphere_sdf(grid_shape, voxel_size, origin, centre, radius):
    """Sphere of ``radius`` mm around ``centre`` (mm).

    Example:
        >>> sphere_sdf((8, 8, 8), 0.1, (-0.4, -0.4, -0.4), (0, 0, 0), 0.3)[4, 4, 4].item()
        -0.3
    """
    p = corner_points(grid_shape, voxel_size, origin) - torch.tensor(check_vector3("centre", centre), dtype=torch.float64)
    return p.norm(dim=-1) - check_real("radius", radius, lo=0.0, lo_open=True)


def torus_sdf(grid_shape, voxel_size, origin, centre, major_radius, minor_radius):
    """Torus around the z axis through ``centre``: tube of radius ``minor_radius`` around a circle of ``major_radius``."""
    major = check_real("major_radius", major_radius, lo=0.0, lo_open=True)
    minor = check_real("minor_radius", minor_radius, lo=0.0, lo_open=True)
    if minor >= major:
        raise ValueError(f"minor_radius: expected < major_radius = {major:g}, got {minor:g}")
    p = corner_points(grid_shape, voxel_size, origin) - torch.tensor(check_vector3("centre", centre), dtype=torch.float64)
    q = torch.stack([p[..., :2].norm(dim=-1) - major, p[..., 2]], dim=-1)
    return q.norm(dim=-1) - minor


def box_sdf(grid_shape, voxel_size, origin, lo, hi):
    """Axis-aligned box [lo, hi] (mm): exact Euclidean distance outside, minus the distance to the nearest face
    inside (so a box whose faces lie on corner planes has exact zeros there and its trilinear zero set is the box)."""
    lo_t = torch.tensor(check_vector3("lo", lo), dtype=torch.float64)
    hi_t = torch.tensor(check_vector3("hi", hi), dtype=torch.float64)
    if not bool((hi_t > lo_t).all()):
        raise ValueError(f"hi: expected > lo = {tuple(lo_t.tolist())} on every axis, got {tuple(hi_t.tolist())}")
    p = corner_points(grid_shape, voxel_size, origin)
    c, half = (lo_t + hi_t) / 2, (hi_t - lo_t) / 2
    q = (p - c).abs() - half
    outside = q.clamp_min(0).norm(dim=-1)
    inside = q.max(dim=-1).values.clamp_max(0)
    return outside + inside


def spherical_shell_sdf(grid_shape, voxel_size, origin, centre, radius, thickness):
    """A thin curved shell: the points within ``thickness``/2 of the sphere of ``radius`` around ``centre``."""
    t = check_real("thickness", thickness, lo=0.0, lo_open=True)
    return sphere_sdf(grid_shape, voxel_size, origin, centre, radius).abs() - t / 2


def conical_shell_sdf(grid_shape, voxel_size, origin, centre, bottom_radius, top_radius, height, thickness):
    """A lamp shade: the open conical (or, with equal radii, cylindrical) shell around the z axis through ``centre``.

    The mid-surface is the cone through the circles of ``bottom_radius`` at z = centre_z − height/2 and
    ``top_radius`` at z = centre_z + height/2 (mm); the shell is the set of points within ``thickness``/2 of it (the
    rims are rounded). Exact: the distance to a surface of revolution is the 2D distance to its generating segment.

    Example:
        >>> sdf = conical_shell_sdf((8, 16, 16), 0.5, (-4, -4, -2), (0, 0, 0), 3.0, 2.0, 3.0, 0.5)
        >>> round(sdf[4, 8, 8].item(), 3), sdf.shape   # axis point: 2.5·cos(atan(1/3)) − 0.25 mm from the wall
        (2.122, torch.Size([9, 17, 17]))
    """
    r0 = check_real("bottom_radius", bottom_radius, lo=0.0, lo_open=True)
    r1 = check_real("top_radius", top_radius, lo=0.0, lo_open=True)
    hgt = check_real("height", height, lo=0.0, lo_open=True)
    t = check_real("thickness", thickness, lo=0.0, lo_open=True)
    if t >= 2 * min(r0, r1):
        raise ValueError(f"thickness: expected < 2·min(bottom_radius, top_radius) = {2 * min(r0, r1):g} mm, got {t:g}")
    p = corner_points(grid_shape, voxel_size, origin) - torch.tensor(check_vector3("centre", centre), dtype=torch.float64)
    rho, z = p[..., :2].norm(dim=-1), p[..., 2]
    a = torch.tensor([r0, -hgt / 2], dtype=torch.float64)
    b = torch.tensor([r1, hgt / 2], dtype=torch.float64)
    q = torch.stack([rho, z], dim=-1)
    ab = b - a
    s = ((q - a) @ ab / (ab @ ab)).clamp(0.0, 1.0)
    return (q - a - s[..., None] * ab).norm(dim=-1) - t / 2
