"""Emitters, evaluated inside the walk when a path escapes, in its escape direction (world space).

Paths reach the lights by escaping (no next-event estimation through the specular boundary).
"""
from dataclasses import dataclass
import math
from typing import Tuple

import torch

from ..checks import check_direction, check_float_tensor, check_real, check_rgb

__all__ = ["ConstantEnvironment", "EnvironmentMap", "DiscLight"]


@dataclass(frozen=True)
class ConstantEnvironment:
    """Uniform environment radiance (linear RGB; a scalar means grey) received by every path that escapes.

    Example:
        >>> ConstantEnvironment(0.5).radiance
        (0.5, 0.5, 0.5)
    """
    radiance: Tuple[float, float, float] = (1.0, 1.0, 1.0)

    def __post_init__(self):
        object.__setattr__(self, "radiance", check_rgb("environment", self.radiance))

    @staticmethod
    def from_value(value):
        """Build from a scalar, a length-3 sequence or a 1- or 3-element tensor."""
        if isinstance(value, torch.Tensor):
            value = value.detach().flatten().tolist()
        if isinstance(value, (tuple, list)) and len(value) == 1:
            value = value[0]
        return ConstantEnvironment(value)

    def to_cpp(self, dtype):
        from .._ext import _C
        opt = _C.EmitterOptions()
        opt.kind = 0
        opt.radiance = list(self.radiance)
        return opt


@dataclass(frozen=True, eq=False)
class EnvironmentMap:
    """A lat-long environment map, linear RGB, z up.

    A direction d looks up θ = acos(d_z) ∈ [0, π] (row 0 is the zenith +z) and φ = atan2(d_y, d_x) (column 0 starts
    at φ = 0, the +x direction, and φ grows with the column): continuous pixel coordinates
    ((φ/2π mod 1)·W − ½, (θ/π)·H − ½), bilinear between pixel centres, wrapping in columns, clamped in rows.

    Args:
        image: (H, W, 3) linear RGB radiance >= 0, a tensor or numpy array (e.g. from
            :func:`torch_appearance.io.read_exr`).
        scale: a factor applied to the map (default 1).
    """
    image: torch.Tensor
    scale: float = 1.0

    def __post_init__(self):
        image = check_float_tensor("image", self.image, "(H, W, 3)", ndim=3, last=3)
        if bool((image < 0).any()):
            raise ValueError(f"image: expected radiance >= 0, got minimum {float(image.min()):g}")
        object.__setattr__(self, "image", image)
        object.__setattr__(self, "scale", check_real("scale", self.scale, lo=0.0))

    @staticmethod
    def from_exr(path, scale=1.0):
        """Read a lat-long linear-RGB OpenEXR file (corrupt or truncated files are refused by the reader)."""
        from ..io import read_exr
        return EnvironmentMap(read_exr(path, name="envmap"), scale)

    def to_cpp(self, dtype):
        from .._ext import _C
        opt = _C.EmitterOptions()
        opt.kind = 1
        opt.map = (self.image * self.scale).to(dtype).contiguous()
        return opt


@dataclass(frozen=True)
class DiscLight:
    """A distant disc light (the sun, a lamp far behind a veneer) plus an optional constant ambient term.

    An escaping path in direction d receives ``radiance + ambient`` where the angle between d and ``direction`` is
    at most ``angular_radius_deg``, and ``ambient`` elsewhere.

    Args:
        direction: 3-vector pointing from the scene towards the light (normalised here).
        angular_radius_deg: angular radius δ in (0, 180] degrees.
        radiance: radiance of the disc, scalar or RGB, >= 0.
        ambient: constant ambient radiance, scalar or RGB, >= 0.

    Example:
        >>> DiscLight((0, 0, 2), 5.0, 10.0).direction
        (0.0, 0.0, 1.0)
    """
    direction: Tuple[float, float, float]
    angular_radius_deg: float
    radiance: Tuple[float, float, float] = (1.0, 1.0, 1.0)
    ambient: Tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self):
        object.__setattr__(self, "direction", check_direction("direction", self.direction))
        object.__setattr__(self, "angular_radius_deg",
                           check_real("angular_radius_deg", self.angular_radius_deg, lo=0.0, hi=180.0, lo_open=True))
        object.__setattr__(self, "radiance", check_rgb("radiance", self.radiance))
        object.__setattr__(self, "ambient", check_rgb("ambient", self.ambient))

    @property
    def cos_max(self):
        return math.cos(math.radians(self.angular_radius_deg))

    def to_cpp(self, dtype):
        from .._ext import _C
        opt = _C.EmitterOptions()
        opt.kind = 2
        opt.radiance = list(self.radiance)
        opt.ambient = list(self.ambient)
        opt.direction = list(self.direction)
        opt.cos_max = self.cos_max
        return opt
