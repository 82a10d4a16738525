"""Scenes of the volume path tracer: the medium's placement and the pieces around it.

A scene holds everything but the medium grids (σ_t and albedo are the differentiable inputs): the voxel size and
origin, the boundary (boundary.py), the sensor (sensor.py), the emitter (emitter.py), the phase function
(phase.py) and the integrator settings. Each piece is a frozen dataclass that validates itself and flattens once
to the C++ struct of the same role (``to_cpp``).

:meth:`Scene.slab` is the slab of :func:`render_texels` (box boundary, face texels, constant environment); a
:class:`torch_appearance.render.TraceJob` adds the per-call settings (spp, seeds, estimator, partition) and builds
the C++ ``SceneOptions``.

Conventions (DESIGN.md): lengths in mm, σ in mm⁻¹, linear RGB. A grid of D×H×W voxels with edges
``voxel_size`` = (sx, sy, sz) occupies origin + [0, W·sx]×[0, H·sy]×[0, D·sz] (x ↔ W, y ↔ H, z ↔ D); D is the
printing (z) axis, "top" is z = D·sz, "bottom" is z = 0.
"""
from dataclasses import dataclass, field
import math
from typing import Optional, Tuple

import torch

from ..checks import check_choice, check_int, check_real, check_tensor, check_vector3
from .boundary import BoxBoundary, SDFBoundary
from .emitter import ConstantEnvironment, DiscLight, EnvironmentMap
from .phase import HenyeyGreenstein
from .sensor import FACES, FaceTexels, OrthographicCamera, PerspectiveCamera, SurfaceTexels

__all__ = [
    "Scene", "PathSettings", "voxel_edges", "check_grid", "check_medium", "default_max_depth",
    "default_rr_depth", "derive_seed_grad", "default_sigma_t_floor", "CHROMATIC", "check_chromatic",
    # the pieces, re-exported for older imports
    "HenyeyGreenstein", "ConstantEnvironment", "FACES",
]

#: Default interaction limit (scatterings + internal reflections). Path lengths in a dense white slab have a
#: heavy tail. Measured on a white-furnace slab 2.5 mm thick at σ_t = 24 mm⁻¹ (60 mean free paths), ior 1.5,
#: 6.4 mm wide, centre texels: energy lost 7.7e-2 at 1024, 7.0e-4 at 4096, 0 (of 65536 paths) at 16384.
default_max_depth = 65536
#: Russian roulette starts after this many interactions; it acts on the reference throughput only.
default_rr_depth = 32


@dataclass(frozen=True)
class PathSettings:
    """Integrator settings of a scene: interaction limits and the sampling-density floors of the default reference
    (the per-call settings, spp, seeds and estimator, belong to :class:`torch_appearance.render.TraceJob`).

    ``max_depth`` counts interactions (scatterings plus internal reflections); paths beyond it contribute 0.
    ``rr_depth``: Russian roulette on the reference throughput starts after that many interactions.
    ``sigma_t_floor`` (mm⁻¹, default 0.5 optical depths along the grid diagonal) and ``albedo_floor`` (default
    0.05) bound the default sampling density of the gradient replay from below, so σ_t → 0 voxels give no unbounded
    1/σ_t terms and albedo = 0 voxels still receive their derivative. The forward pass samples the parameters
    themselves.
    """
    max_depth: int = default_max_depth
    rr_depth: int = default_rr_depth
    sigma_t_floor: Optional[float] = None
    albedo_floor: float = 0.05

    def __post_init__(self):
        object.__setattr__(self, "max_depth", check_int("max_depth", self.max_depth, lo=1))
        object.__setattr__(self, "rr_depth", check_int("rr_depth", self.rr_depth, lo=0))
        if self.sigma_t_floor is not None:
            object.__setattr__(self, "sigma_t_floor", check_real("sigma_t_floor", self.sigma_t_floor, lo=0.0))
        object.__setattr__(self, "albedo_floor", check_real("albedo_floor", self.albedo_floor, lo=0.0, hi=1.0))


#: Estimators for a sampling density that differs between the colour channels:
#: "per_channel" one walk per channel, each sampling distances with its own channel's density;
#: "hero" one walk serves all three channels: distances are sampled with the density of a hero channel (uniform
#: per sample) and every channel is weighted by the balance heuristic over the channels' path densities
#: (hero-wavelength spectral MIS, Wilkie et al. 2014). Both are unbiased; an achromatic density always takes one walk.
CHROMATIC = ("per_channel", "hero")


def check_chromatic(chromatic):
    """Validate the ``chromatic`` estimator name (see :data:`CHROMATIC`)."""
    return check_choice("chromatic", chromatic, CHROMATIC, kind=str)


def default_sigma_t_floor(settings, voxel_size, grid_shape):
    """Density floor (mm⁻¹) of the default gradient sampling: ``settings.sigma_t_floor`` if set, else 0.5 optical
    depths along the diagonal of the (…, D, H, W) grid of ``voxel_size`` (x, y, z) edges.

    Sampling thin voxels at σ̂ = f instead of σ ≈ 0 bounds the collision term's 1/σ̂ weight, but a path that flies a
    floored length Λ without colliding carries the ratio weight exp((σ̂ − σ)Λ), whose second moment grows like
    exp(f·Λ); f·diagonal = 0.5 balances the two (measured on the `thin` benchmark scene: gradient variance × time
    is lowest near it, and 20× higher at 0.05 optical depths per voxel, where TIR-guided paths pick up exponential
    weights).
    """
    if settings.sigma_t_floor is not None:
        return settings.sigma_t_floor
    d, h, w = grid_shape[-3:]
    sx, sy, sz = voxel_size
    return 0.5 / math.sqrt((w * sx) ** 2 + (h * sy) ** 2 + (d * sz) ** 2)


def derive_seed_grad(seed):
    """The default gradient seed of a forward seed: a fixed bijection of the 64-bit seeds (odd multiplier and
    offset, as in SplitMix64), so that the gradient replay draws paths independent of the forward's noise."""
    return (int(seed) * 0x9E3779B97F4A7C15 + 0x632BE59BD9B4E019) % 2 ** 64


_BOUNDARIES = (BoxBoundary, SDFBoundary)
_SENSORS = (FaceTexels, SurfaceTexels, OrthographicCamera, PerspectiveCamera)
_EMITTERS = (ConstantEnvironment, EnvironmentMap, DiscLight)


@dataclass(frozen=True, eq=False)
class Scene:
    """A voxel medium placed in world space with a boundary, a sensor and an emitter (the medium grids are the
    differentiable inputs of :func:`render_scene`).

    Args:
        voxel_size: voxel edge in mm, or the three edges (x, y, z).
        origin: world position (mm) of the grid corner: the grid spans origin + (W, H, D)·voxel_size.
        boundary: :class:`BoxBoundary` (default, dielectric 1.5) or :class:`SDFBoundary`.
        sensor: :class:`FaceTexels` (default "top"; box only), :class:`SurfaceTexels`,
            :class:`OrthographicCamera` or :class:`PerspectiveCamera`.
        emitter: :class:`ConstantEnvironment` (default 1), :class:`EnvironmentMap` or :class:`DiscLight`.
        g: Henyey–Greenstein mean cosine in (−1, 1).
        max_depth, rr_depth: interaction limit and start of Russian roulette (see :class:`PathSettings`); SDF
            boundaries count surface crossings as interactions too.
        sigma_t_floor, albedo_floor: floors of the default gradient sampling (see :class:`PathSettings`).

    Example:
        >>> import torch
        >>> from torch_appearance.render import Scene, SDFBoundary, OrthographicCamera
        >>> k, j, i = torch.meshgrid(*(torch.arange(9.0),) * 3, indexing="ij")
        >>> sdf = ((i - 4) ** 2 + (j - 4) ** 2 + (k - 4) ** 2).sqrt() * 0.1 - 0.3
        >>> scene = Scene(voxel_size=0.1, origin=(-0.4, -0.4, -0.4), boundary=SDFBoundary(sdf, ior=1.5),
        ...               sensor=OrthographicCamera(origin=(0, 0, 2), target=(0, 0, 0), up=(0, 1, 0),
        ...                                         extent_mm=(0.8, 0.8), resolution=(8, 8)))
        >>> scene.output_shape((8, 8, 8))
        (8, 8, 3)
    """
    voxel_size: Tuple[float, float, float]
    origin: Tuple[float, float, float] = (0.0, 0.0, 0.0)
    boundary: object = field(default_factory=BoxBoundary)
    sensor: object = field(default_factory=FaceTexels)
    emitter: object = field(default_factory=ConstantEnvironment)
    g: float = 0.4
    max_depth: int = default_max_depth
    rr_depth: int = default_rr_depth
    sigma_t_floor: Optional[float] = None
    albedo_floor: float = 0.05

    def __post_init__(self):
        object.__setattr__(self, "voxel_size", voxel_edges(self.voxel_size))
        object.__setattr__(self, "origin", check_vector3("origin", self.origin))
        object.__setattr__(self, "g", HenyeyGreenstein(self.g).g)
        for name, value, kinds in (("boundary", self.boundary, _BOUNDARIES), ("sensor", self.sensor, _SENSORS),
                                   ("emitter", self.emitter, _EMITTERS)):
            if not isinstance(value, kinds):
                raise TypeError(f"{name}: expected one of {', '.join(k.__name__ for k in kinds)}, "
                                f"got {type(value).__name__}")
        if isinstance(self.sensor, FaceTexels) and not isinstance(self.boundary, BoxBoundary):
            raise ValueError("sensor: FaceTexels read the faces of the grid box and need boundary=BoxBoundary(...); "
                             "use SurfaceTexels for an SDF boundary")
        settings = PathSettings(max_depth=self.max_depth, rr_depth=self.rr_depth, sigma_t_floor=self.sigma_t_floor,
                                albedo_floor=self.albedo_floor)
        object.__setattr__(self, "settings", settings)

    @classmethod
    def slab(cls, voxel_size, *, face="top", g=0.4, ior=1.5, environment=1.0, max_depth=None, rr_depth=None,
             sigma_t_floor=None, albedo_floor=0.05):
        """The slab of :func:`torch_appearance.render_texels`: the grid at the origin, its box as the boundary
        (smooth dielectric of index ``ior``, or index matched for ``ior=None``), the texels of ``face`` ("top",
        "bottom" or "both") as the sensor and a constant environment of radiance ``environment`` (scalar or RGB).
        ``max_depth``/``rr_depth`` None take :data:`default_max_depth`/:data:`default_rr_depth`.

        Example:
            >>> scene = Scene.slab(0.1, face="both", ior=None, environment=(1.0, 0.5, 0.25))
            >>> scene.boundary, scene.sensor, scene.output_shape((4, 8, 6))
            (BoxBoundary(ior=None), FaceTexels(face='both'), (2, 8, 6, 3))
        """
        return cls(voxel_size=voxel_size, boundary=BoxBoundary(ior), sensor=FaceTexels(face),
                   emitter=ConstantEnvironment.from_value(environment), g=g,
                   max_depth=default_max_depth if max_depth is None else max_depth,
                   rr_depth=default_rr_depth if rr_depth is None else rr_depth,
                   sigma_t_floor=sigma_t_floor, albedo_floor=albedo_floor)

    def extent(self, grid_shape):
        """(x, y, z) size of the grid box in mm for a (D, H, W) grid."""
        d, h, w = grid_shape
        sx, sy, sz = self.voxel_size
        return (w * sx, h * sy, d * sz)

    def output_shape(self, grid_shape):
        """Shape of the rendered image for a (D, H, W) grid."""
        return self.sensor.output_shape(tuple(grid_shape))

    def check_grid_shape(self, grid_shape):
        """Refuse pieces that do not fit a (D, H, W) grid (SDF shape, texels outside the grid)."""
        if isinstance(self.boundary, SDFBoundary) and tuple(grid_shape) != self.boundary.grid_shape:
            raise ValueError(f"sdf: expected shape (D+1, H+1, W+1) = {tuple(n + 1 for n in grid_shape)} for the "
                             f"(D, H, W) = {tuple(grid_shape)} medium grid, got {tuple(self.boundary.sdf.shape)}")
        if isinstance(self.sensor, SurfaceTexels):
            self.sensor.check_inside(self.origin, self.extent(grid_shape))


def voxel_edges(voxel_size):
    """``voxel_size`` (mm) as the (x, y, z) edge tuple: a positive number, or a sequence of three."""
    if isinstance(voxel_size, torch.Tensor):
        voxel_size = voxel_size.detach().flatten().tolist()
        voxel_size = voxel_size[0] if len(voxel_size) == 1 else voxel_size
    if isinstance(voxel_size, (tuple, list)):
        if len(voxel_size) != 3:
            raise ValueError(f"voxel_size: expected one edge or three edges (x, y, z) in mm, got {voxel_size!r}")
        return tuple(check_real("voxel_size", v, lo=0.0, lo_open=True) for v in voxel_size)
    edge = check_real("voxel_size", voxel_size, lo=0.0, lo_open=True)
    return (edge, edge, edge)


def check_grid(name, x, *, like=None, lo=0.0, hi=math.inf):
    """Validate a medium grid: a float32/float64 CPU or CUDA tensor of shape (3, D, H, W), finite, in [lo, hi].

    Raises:
        TypeError: not a tensor, or not a floating dtype.
        ValueError: wrong shape, device, dtype or shape differing from ``like`` (or a device other than its), non-finite
            or out-of-range values.
    """
    check_tensor(name, x, "(3, D, H, W)", dtypes=(torch.float32, torch.float64))
    if like is not None and x.device != like.device:
        raise ValueError(f"{name}: expected the device of sigma_t ({like.device}), got {x.device}")
    if x.device.type not in ("cpu", "cuda"):
        raise ValueError(f"{name}: expected a CPU or CUDA tensor (the tracer's devices), got device {x.device}")
    if x.dim() != 4 or x.shape[0] != 3 or min(x.shape) < 1:
        raise ValueError(f"{name}: expected shape (3, D, H, W) with D, H, W >= 1, got {tuple(x.shape)}")
    if like is not None:
        if x.shape != like.shape:
            raise ValueError(f"{name}: expected shape {tuple(like.shape)} (that of sigma_t), got {tuple(x.shape)}")
        if x.dtype != like.dtype:
            raise ValueError(f"{name}: expected dtype {like.dtype} (that of sigma_t), got {x.dtype}")
    xd = x.detach()
    lo_v, hi_v = (float(v) for v in torch.aminmax(xd))  # one pass, no copy; NaN propagates to both
    if not (math.isfinite(lo_v) and math.isfinite(hi_v)):
        raise ValueError(f"{name}: expected finite values, got {int((~torch.isfinite(xd)).sum())} NaN/Inf entries")
    if lo_v < lo or hi_v > hi:
        raise ValueError(f"{name}: expected values in [{lo:g}, {hi:g}], got range [{lo_v:g}, {hi_v:g}]")
    return x


def check_medium(sigma_t, albedo):
    """Validate the pair (sigma_t in mm⁻¹ >= 0, albedo in [0, 1]), both (3, D, H, W) of one dtype."""
    check_grid("sigma_t", sigma_t)
    check_grid("albedo", albedo, like=sigma_t, hi=1.0)
