"""One call of the tracer: a :class:`Scene` with its per-call settings, flattened once to the C++ ``SceneOptions``.

:func:`torch_appearance.render_scene` (and through it :func:`torch_appearance.render_texels`) and
:func:`torch_appearance.render.render_scene_indexed` build a :class:`TraceJob`; the autograd Function
(:class:`torch_appearance.autograd.VolumePathTrace`) takes nothing else. The job validates itself: the scene's type,
``spp``, the two 64-bit seeds, the ``chromatic`` estimator, the ``partition`` and the ``grad_support``.
"""
from dataclasses import dataclass
from typing import Optional, Tuple

from ..checks import check_seed, check_spp, is_int
from .scene import Scene, check_chromatic, default_sigma_t_floor, derive_seed_grad

__all__ = ["TraceJob", "check_grad_support", "check_partition"]


def check_grad_support(grad_support):
    """``grad_support``: None, or a CPU (or CUDA) bool tensor (D, H, W) (the grid's shape is checked against the
    medium's by :meth:`TraceJob.check_grid`), returned contiguous on the CPU (the scene is built on the host)."""
    if grad_support is None:
        return None
    import torch
    if not isinstance(grad_support, torch.Tensor):
        raise TypeError(f"grad_support: expected a bool tensor (D, H, W) or None, got {type(grad_support).__name__}")
    if grad_support.dtype != torch.bool or grad_support.dim() != 3 or grad_support.device.type not in ("cpu", "cuda"):
        raise ValueError(f"grad_support: expected a CPU or CUDA bool tensor (D, H, W), got {grad_support.dtype} "
                         f"{tuple(grad_support.shape)} on {grad_support.device}")
    return grad_support.detach().cpu().contiguous()


def check_partition(partition):
    """``partition`` = (rank, world), two ints with 0 <= rank < world, as a tuple; None stays None."""
    if partition is None:
        return None
    if (not isinstance(partition, (tuple, list)) or len(partition) != 2
            or not all(is_int(v) for v in partition)):
        raise TypeError(f"partition: expected (rank, world), two ints, got {partition!r}")
    rank, world = partition
    if not (world >= 1 and 0 <= rank < world):
        raise ValueError(f"partition: expected 0 <= rank < world, got rank {rank} of world {world}")
    return (int(rank), int(world))


def _signed64(seed):
    seed = int(seed) % 2 ** 64
    return seed if seed < 2 ** 63 else seed - 2 ** 64  # the same 64 bits, as a signed int64


@dataclass(frozen=True, eq=False)
class TraceJob:
    """What one render asks of the tracer, for the forward pass and its gradient replay.

    Args:
        scene: the :class:`Scene` (placement, boundary, sensor, emitter, phase, path limits, density floors).
        spp: samples per sensor element (per channel when σ_t is chromatic), >= 1.
        seed: 64-bit seed of the forward pass.
        seed_grad: 64-bit seed of the gradient replay; None: :func:`derive_seed_grad` (seed), paths independent of
            the forward's noise. ``seed_grad = seed`` replays the forward's own random numbers.
        chromatic: estimator for a sampling density that differs between channels (see
            :data:`torch_appearance.render.scene.CHROMATIC`).
        partition: optional (rank, world): trace only the sensor elements t with t % world == rank.
        grad_support: optional (D, H, W) bool tensor: the voxels whose gradients the backward returns (the others
            get 0). The replay then crosses the homogeneous core outside it without gradient bookkeeping (a print's
            fixed core ink; see ``Medium::core`` in csrc/core/medium.h).
        name: the entry point that made the job, for messages.

    Example:
        >>> import torch
        >>> from torch_appearance.render import Scene, TraceJob
        >>> job = TraceJob(Scene.slab(0.1, face="both"), spp=4, seed=3, partition=(1, 2))
        >>> job.seed_grad == job.seed
        False
        >>> opt = job.scene_options(3, job.seed, (2, 4, 4), torch.float32)
        >>> opt.spp, opt.seed, opt.part_rank, opt.part_world, opt.sensor.face
        (4, 3, 1, 2, 2)
    """
    scene: Scene
    spp: int = 16
    seed: int = 0
    seed_grad: Optional[int] = None
    chromatic: str = "per_channel"
    partition: Optional[Tuple[int, int]] = None
    grad_support: Optional[object] = None
    name: str = "render_scene"

    def __post_init__(self):
        if not isinstance(self.scene, Scene):
            raise TypeError(f"scene: expected a torch_appearance.render.Scene, got {type(self.scene).__name__}")
        object.__setattr__(self, "spp", check_spp(self.spp))
        object.__setattr__(self, "seed", check_seed("seed", self.seed))
        seed_grad = derive_seed_grad(self.seed) if self.seed_grad is None else check_seed("seed_grad", self.seed_grad)
        object.__setattr__(self, "seed_grad", seed_grad)
        object.__setattr__(self, "chromatic", check_chromatic(self.chromatic))
        object.__setattr__(self, "partition", check_partition(self.partition))
        object.__setattr__(self, "grad_support", check_grad_support(self.grad_support))

    def check_grid(self, grid_shape):
        """Raises ValueError when ``grad_support`` is not of the medium's (D, H, W) ``grid_shape``."""
        if self.grad_support is not None and tuple(self.grad_support.shape) != tuple(grid_shape):
            raise ValueError(f"grad_support: expected the grid's shape {tuple(grid_shape)}, got "
                             f"{tuple(self.grad_support.shape)}")

    @property
    def albedo_floor(self):
        """Albedo floor of the default gradient sampling (the scene's)."""
        return self.scene.settings.albedo_floor

    def sigma_t_floor(self, grid_shape):
        """Density floor (mm⁻¹) of the default gradient sampling for a (…, D, H, W) grid (see
        :func:`torch_appearance.render.scene.default_sigma_t_floor`)."""
        return default_sigma_t_floor(self.scene.settings, self.scene.voxel_size, grid_shape)

    def scene_options(self, lanes, seed, grid_shape, dtype):
        """The C++ ``SceneOptions`` of a walk with ``seed`` (the forward's or the replay's) over a (D, H, W) grid of
        ``dtype``, ``lanes`` channels per walk (3: one walk serves all channels, 1: one walk per channel)."""
        from .._ext import _C
        scene = self.scene
        opt = _C.SceneOptions()
        opt.voxel_size = list(scene.voxel_size)
        opt.origin = list(scene.origin)
        opt.g = scene.g
        opt.boundary = scene.boundary.to_cpp(grid_shape, dtype)
        opt.sensor = scene.sensor.to_cpp(scene, grid_shape, dtype)
        opt.emitter = scene.emitter.to_cpp(dtype)
        opt.spp = self.spp
        opt.seed = _signed64(seed)
        opt.max_depth = scene.settings.max_depth
        opt.rr_depth = scene.settings.rr_depth
        opt.lanes = lanes
        if self.partition is not None:
            opt.part_rank, opt.part_world = self.partition
        if self.grad_support is not None:
            opt.grad_support = self.grad_support
        return opt
