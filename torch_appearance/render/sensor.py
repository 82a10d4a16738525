"""Sensors: face texels of a box, surface texels of a curved object, orthographic and perspective cameras.

Every sensor element (texel or pixel) is the mean over ``spp`` jittered samples of the radiance carried back along
a ray (linear RGB, no cosine weighting). Positions are world mm.
"""
from dataclasses import dataclass
import math
from typing import Tuple

import numpy as np
import torch

from ..checks import check_direction, check_float_tensor, check_int, check_real, check_vector3

__all__ = ["FACES", "FaceTexels", "SurfaceTexels", "OrthographicCamera", "PerspectiveCamera"]

FACES = {"top": 0, "bottom": 1, "both": 2}


def _face(face):
    if not isinstance(face, str) or face not in FACES:
        raise ValueError(f"face: expected one of {sorted(FACES)}, got {face!r}")
    return face


@dataclass(frozen=True)
class FaceTexels:
    """One texel per voxel column of the box's ``face`` ("top" z = D·sz, "bottom" z = 0, or "both").

    A sample starts at a uniform point of the texel's square footprint and enters along the inward normal
    (specular reflection at normal incidence included); the texel is the radiance leaving along the normal.
    Output (H, W, 3), or (2, H, W, 3) for "both" (0 = top). Needs the :class:`BoxBoundary`.
    """
    face: str = "top"

    def __post_init__(self):
        _face(self.face)

    def output_shape(self, grid_shape):
        d, h, w = grid_shape
        return (2, h, w, 3) if self.face == "both" else (h, w, 3)

    def to_cpp(self, scene, grid_shape, dtype):
        from .._ext import _C
        opt = _C.SensorOptions()
        opt.kind = 0
        opt.face = FACES[self.face]
        return opt


@dataclass(frozen=True, eq=False)
class SurfaceTexels:
    """An arbitrary list of surface texels: the texel-space sensor of curved objects (TOG 2021).

    A sample is a uniform point of the disc of radius ``footprint_mm`` around the texel's point in its tangent
    plane, lifted outwards by two voxel edges and shot along −n: it meets the surface (Fresnel reflection of the
    emitter or refraction into the medium) and the texel value is the radiance leaving the surface along n.

    Args:
        points: (N, 3) points on the surface, world mm, inside the grid.
        normals: (N, 3) outward unit normals.
        footprint_mm: footprint radius in mm, scalar or (N,), >= 0.

    Output (N, 3).
    """
    points: torch.Tensor
    normals: torch.Tensor
    footprint_mm: object = 0.0

    def __post_init__(self):
        points = check_float_tensor("points", self.points, "(N, 3)", ndim=2, last=3)
        normals = check_float_tensor("normals", self.normals, "(N, 3)", ndim=2, last=3)
        if normals.shape != points.shape:
            raise ValueError(f"normals: expected shape {tuple(points.shape)} (that of points), got {tuple(normals.shape)}")
        length = normals.double().norm(dim=1)
        worst = float((length - 1).abs().max())
        if worst > 1e-4:
            raise ValueError(f"normals: expected unit vectors, got lengths in [{float(length.min()):.6g}, "
                             f"{float(length.max()):.6g}]")
        fp = self.footprint_mm
        if isinstance(fp, (torch.Tensor, np.ndarray)) and np.size(fp) != 1:
            fp = check_float_tensor("footprint_mm", fp, "(N,)", ndim=1)
            if fp.shape[0] != points.shape[0]:
                raise ValueError(f"footprint_mm: expected a scalar or shape ({points.shape[0]},), got {tuple(fp.shape)}")
            if bool((fp < 0).any()):
                raise ValueError(f"footprint_mm: expected radii >= 0, got minimum {float(fp.min()):g}")
        else:
            fp = torch.full((points.shape[0],), check_real("footprint_mm", fp, lo=0.0), dtype=torch.float64)
        object.__setattr__(self, "points", points)
        object.__setattr__(self, "normals", normals)
        object.__setattr__(self, "footprint_mm", fp)

    def output_shape(self, grid_shape):
        return (self.points.shape[0], 3)

    def check_inside(self, origin, extent):
        """Refuse texels outside the grid box [origin, origin + extent] (mm)."""
        lo = torch.tensor(origin, dtype=torch.float64)
        hi = lo + torch.tensor(extent, dtype=torch.float64)
        p = self.points.double()
        outside = ((p < lo) | (p > hi)).any(dim=1)
        if bool(outside.any()):
            first = int(outside.nonzero()[0])
            raise ValueError(f"points: expected texels inside the grid [{tuple(lo.tolist())}, {tuple(hi.tolist())}] mm, "
                             f"got {int(outside.sum())} outside, the first at index {first}: {tuple(p[first].tolist())}")

    def to_cpp(self, scene, grid_shape, dtype):
        from .._ext import _C
        opt = _C.SensorOptions()
        opt.kind = 1
        opt.points = self.points.to(dtype).contiguous()
        opt.normals = self.normals.to(dtype).contiguous()
        opt.radius = self.footprint_mm.to(dtype).contiguous()
        opt.lift = 2.0 * max(scene.voxel_size)
        return opt


def camera_frame(origin, target, up):
    """Orthonormal (forward, right, up) of a camera at ``origin`` looking at ``target``; right = forward × up."""
    origin = check_vector3("origin", origin)
    target = check_vector3("target", target)
    up = check_direction("up", up)
    f = [t - o for t, o in zip(target, origin)]
    norm = math.sqrt(sum(c * c for c in f))
    if not norm > 1e-12:
        raise ValueError(f"target: expected a point other than the camera origin {origin}, got {target}")
    f = [c / norm for c in f]
    r = [f[1] * up[2] - f[2] * up[1], f[2] * up[0] - f[0] * up[2], f[0] * up[1] - f[1] * up[0]]
    rn = math.sqrt(sum(c * c for c in r))
    if rn < 1e-6:
        raise ValueError(f"up: expected a direction not parallel to the viewing direction {tuple(f)}, got {up}")
    r = [c / rn for c in r]
    u = [r[1] * f[2] - r[2] * f[1], r[2] * f[0] - r[0] * f[2], r[0] * f[1] - r[1] * f[0]]
    return tuple(f), tuple(r), tuple(u)


def _resolution(resolution):
    if not isinstance(resolution, (tuple, list)) or len(resolution) != 2:
        raise ValueError(f"resolution: expected (rows, cols), got {resolution!r}")
    rows, cols = (check_int("resolution", v, lo=1) for v in resolution)
    if rows * cols >= 2 ** 32:
        raise ValueError(f"resolution: expected rows·cols < 2**32, got {rows}·{cols}")
    return rows, cols


@dataclass(frozen=True)
class _Camera:
    origin: Tuple[float, float, float]
    target: Tuple[float, float, float]
    up: Tuple[float, float, float]

    def output_shape(self, grid_shape):
        return (*self.resolution, 3)

    def _check_frame(self):
        """Validate origin, target, up (a proper frame) and the resolution; called by each camera."""
        object.__setattr__(self, "origin", check_vector3("origin", self.origin))
        object.__setattr__(self, "target", check_vector3("target", self.target))
        object.__setattr__(self, "up", check_vector3("up", self.up))
        camera_frame(self.origin, self.target, self.up)
        object.__setattr__(self, "resolution", _resolution(self.resolution))

    def _cpp(self, kind):
        from .._ext import _C
        f, r, u = camera_frame(self.origin, self.target, self.up)
        opt = _C.SensorOptions()
        opt.kind = kind
        opt.origin = list(self.origin)
        opt.forward, opt.right, opt.up = list(f), list(r), list(u)
        opt.rows, opt.cols = self.resolution
        return opt


@dataclass(frozen=True)
class OrthographicCamera(_Camera):
    """Parallel projection: pixel (r, c) starts at origin + right·((c + ½)/W − ½)·width + up·(½ − (r + ½)/H)·height
    (jittered over the pixel) and looks along forward = normalise(target − origin); right = forward × up.

    Args:
        origin, target, up: world mm (up is a direction, not parallel to target − origin).
        extent_mm: (width, height) of the image plane in mm.
        resolution: (rows, cols).

    Row 0 is the ``up`` side, column 0 the left side. Output (rows, cols, 3).
    """
    extent_mm: Tuple[float, float] = (1.0, 1.0)
    resolution: Tuple[int, int] = (64, 64)

    def __post_init__(self):
        self._check_frame()
        ext = self.extent_mm
        if not isinstance(ext, (tuple, list)) or len(ext) != 2:
            raise ValueError(f"extent_mm: expected (width, height) in mm, got {ext!r}")
        object.__setattr__(self, "extent_mm", tuple(check_real("extent_mm", v, lo=0.0, lo_open=True) for v in ext))

    def to_cpp(self, scene, grid_shape, dtype):
        opt = self._cpp(2)
        opt.width, opt.height = self.extent_mm
        return opt


@dataclass(frozen=True)
class PerspectiveCamera(_Camera):
    """Pinhole camera at ``origin`` looking at ``target``; ``fov_y_deg`` is the full vertical field of view.

    Pixel (r, c) looks along normalise(forward + x·right + y·up) with x = (2(c + ½)/W − 1)·tan(fov/2)·W/H and
    y = (1 − 2(r + ½)/H)·tan(fov/2) (jittered over the pixel). Row 0 is the ``up`` side. Output (rows, cols, 3).
    """
    fov_y_deg: float = 30.0
    resolution: Tuple[int, int] = (64, 64)

    def __post_init__(self):
        self._check_frame()
        object.__setattr__(self, "fov_y_deg", check_real("fov_y_deg", self.fov_y_deg, lo=0.0, hi=180.0,
                                                         lo_open=True, hi_open=True))

    def to_cpp(self, scene, grid_shape, dtype):
        opt = self._cpp(3)
        opt.tan_half_fov = math.tan(math.radians(self.fov_y_deg) / 2)
        return opt

