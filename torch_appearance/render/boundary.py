"""Boundaries of the medium: the grid's box, or the zero level set of a signed-distance grid.

Each boundary is index matched (``ior=None``: paths cross it unchanged) or a smooth dielectric of index ``ior``
(exact unpolarised Fresnel at the local angle, refraction by Snell's law, total internal reflection). Outside the
object is vacuum; the medium counts only inside.
"""
from dataclasses import dataclass
from typing import Optional

import torch

from ..checks import check_float_tensor, check_real

__all__ = ["BoxBoundary", "SDFBoundary"]


def _ior(value):
    return None if value is None else check_real("ior", value, lo=1.0)


@dataclass(frozen=True)
class BoxBoundary:
    """The grid's own bounding box is the object's surface (the slab of :func:`render_texels`).

    Args:
        ior: refractive index (>= 1) of a smooth dielectric surface, or None for index matched.
    """
    ior: Optional[float] = 1.5

    def __post_init__(self):
        object.__setattr__(self, "ior", _ior(self.ior))

    def to_cpp(self, grid_shape, dtype):
        from .._ext import _C
        opt = _C.BoundaryOptions()
        opt.kind = 0
        opt.ior = -1.0 if self.ior is None else self.ior
        return opt


@dataclass(frozen=True, eq=False)
class SDFBoundary:
    """A surface given as the zero level set of signed distances sampled at the voxel corners.

    The field is trilinear inside each voxel cell; the outward normal is the normalised gradient of that
    interpolant. Rays meet it exactly (the cubic along the ray inside each cell, csrc/core/boundary.h).

    Args:
        sdf: (D+1, H+1, W+1) signed distances in mm, negative inside; corner (k, j, i) sits at
            ``origin + (i·sx, j·sy, k·sz)``. Must be > 0 on the grid's outer corners (pad the object by a voxel).
        ior: refractive index (>= 1) of a smooth dielectric surface, or None for index matched.

    Example:
        >>> import torch
        >>> from torch_appearance.render import SDFBoundary
        >>> k, j, i = torch.meshgrid(*(torch.arange(9.0),) * 3, indexing="ij")
        >>> sdf = ((i - 4) ** 2 + (j - 4) ** 2 + (k - 4) ** 2).sqrt() * 0.1 - 0.3   # sphere, r = 0.3 mm
        >>> SDFBoundary(sdf, ior=1.5).grid_shape
        (8, 8, 8)
    """
    sdf: torch.Tensor
    ior: Optional[float] = None

    def __post_init__(self):
        sdf = check_float_tensor("sdf", self.sdf, "(D+1, H+1, W+1)", ndim=3)
        if min(sdf.shape) < 2:
            raise ValueError(f"sdf: expected shape (D+1, H+1, W+1) with D, H, W >= 1, got {tuple(sdf.shape)}")
        outer = torch.cat([sdf[0].flatten(), sdf[-1].flatten(), sdf[:, 0].flatten(), sdf[:, -1].flatten(),
                           sdf[:, :, 0].flatten(), sdf[:, :, -1].flatten()])
        if not bool((outer > 0).all()):
            raise ValueError(f"sdf: expected > 0 on the grid's outer corners (the object must lie strictly inside "
                             f"the grid; pad it by a voxel), got minimum {float(outer.min()):g} mm there")
        if not bool((sdf < 0).any()):
            raise ValueError("sdf: expected some negative (inside) values, got none: the grid holds no object")
        object.__setattr__(self, "sdf", sdf)
        object.__setattr__(self, "ior", _ior(self.ior))

    @property
    def grid_shape(self):
        """(D, H, W) of the voxel grid this SDF belongs to."""
        return tuple(n - 1 for n in self.sdf.shape)

    def to_cpp(self, grid_shape, dtype):
        if tuple(grid_shape) != self.grid_shape:
            raise ValueError(f"sdf: expected shape (D+1, H+1, W+1) = {tuple(n + 1 for n in grid_shape)} for a "
                             f"(D, H, W) = {tuple(grid_shape)} grid, got {tuple(self.sdf.shape)}")
        from .._ext import _C
        opt = _C.BoundaryOptions()
        opt.kind = 1
        opt.ior = -1.0 if self.ior is None else self.ior
        opt.sdf = self.sdf.to(dtype).contiguous()
        return opt

