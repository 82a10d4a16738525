"""The tracer's entry point, differentiable by path replay: ``render_scene`` (any :class:`Scene`: box or SDF
boundary, surface texels or cameras, any emitter); ``render_texels`` is its short form for a voxel slab's face texels
(:meth:`Scene.slab`), and ``render_scene_indexed`` its forward-only form for a palette medium."""

import math

import torch

from .._ext import call_tracer
from .scene import Scene, check_grid, check_medium
from .trace_job import TraceJob

__all__ = ["render_texels", "render_scene", "render_scene_indexed"]


def render_texels(sigma_t, albedo, *, voxel_size, face="top", g=0.4, ior=1.5, environment=1.0, spp=16, seed=0,
                  max_depth=None, rr_depth=None, sampling_sigma_t=None, sampling_albedo=None,
                  sigma_t_floor=None, albedo_floor=0.05, stats=None, seed_grad=None, partition=None,
                  chromatic="per_channel", adjoint=None):
    """Render the radiance leaving a voxel slab along the face normal, one texel per voxel column.

    The slab is D×H×W voxels of edge ``voxel_size`` mm occupying [0, W·sx]×[0, H·sy]×[0, D·sz] (x ↔ W,
    y ↔ H, z ↔ D, the printing axis), lit by a uniform environment. Light transport: exact regular tracking through the
    piecewise-constant voxels, Henyey–Greenstein scattering, optional smooth dielectric boundary on all six
    faces; every colour channel is estimated without bias (one walk per channel when σ_t differs between channels,
    one shared walk otherwise).

    Differentiable in ``sigma_t`` and ``albedo``: the backward pass is radiative backpropagation by path replay.
    Paths are sampled from a detached reference medium and weighted by f(θ)/p_ref. By default the forward samples
    the (detached) parameters and the gradient replay samples them with density floors (``sigma_t_floor``,
    ``albedo_floor``): an unbiased gradient with bounded variance also at σ_t → 0 and albedo = 0. With explicit
    ``sampling_sigma_t``/``sampling_albedo`` and a fixed ``seed`` the result is a smooth function of the
    parameters and the backward is its exact derivative (``torch.autograd.gradcheck`` passes in float64).

    Args:
        sigma_t: (3, D, H, W) extinction coefficient in mm⁻¹, >= 0, float32 or float64, on the CPU or a CUDA device
            (the render runs there).
        albedo: (3, D, H, W) single-scattering albedo in [0, 1], same dtype and device.
        voxel_size: voxel edge in mm, > 0, or the three edges (x, y, z) in mm for anisotropic voxels
            (e.g. a printer's native 600 × 300 × 940 DPI grid).
        face: "top" (z = D·s), "bottom" (z = 0) or "both".
        g: Henyey–Greenstein mean cosine in (−1, 1).
        ior: refractive index of the slab (>= 1) with a smooth dielectric boundary, or None for index matched.
        environment: environment radiance, scalar or RGB (linear), >= 0.
        spp: samples per texel (per channel when σ_t is chromatic), >= 1.
        seed: 64-bit seed; results are reproducible for a seed, independent of the thread count.
        max_depth: interaction limit (scatterings + internal reflections); default
            :data:`torch_appearance.render.scene.default_max_depth`.
        rr_depth: interactions before Russian roulette on the reference throughput; default
            :data:`torch_appearance.render.scene.default_rr_depth`.
        sampling_sigma_t: optional detached (3, D, H, W) sampling density, > 0 wherever ``sigma_t`` > 0.
        sampling_albedo: optional detached (3, D, H, W) sampling albedo, > 0 wherever ``albedo`` > 0.
        sigma_t_floor: density floor (mm⁻¹) of the default gradient sampling (default: 0.5 optical depths
            along the grid diagonal, see :func:`torch_appearance.render.scene.default_sigma_t_floor`).
        albedo_floor: albedo floor of the default gradient sampling, in [0, 1] (default 0.05).
        stats: optional dict, filled with ``forward_s``, ``scatter_events``, ``lanes``, ``hero`` and, after backward,
            ``backward_s`` and ``backward_scatter_events``.
        seed_grad: seed of the gradient replay; default None = ``seed`` (the replay retraces the forward's own
            random numbers, with the floored reference). :func:`torch_appearance.render.derive_seed_grad` gives
            an independent one (as :func:`render_scene` does by default).
        partition: optional (rank, world): trace only the texels t (flat index) with t % world == rank, the others
            are 0 and get no gradient; random numbers are keyed by the global t, so the images of all ranks sum to
            the full image (see :mod:`torch_appearance.distributed`).
        chromatic: estimator when the sampling density differs between channels: "per_channel" (one walk per
            channel) or "hero" (one walk, hero-channel distance sampling with the balance heuristic over the
            channels; see :data:`torch_appearance.render.scene.CHROMATIC`). Applies to the forward and the
            gradient replay alike.
        adjoint: optional, the image's gradient when known before the render: one walk gives the image and its
            gradient (see :func:`render_scene`).

    Returns:
        (H, W, 3) linear RGB texel radiance for one face, (2, H, W, 3) for "both" (0 = top, 1 = bottom).
        Texel [j, i] is the voxel column with y index j and x index i, on both faces (no mirroring).

    Raises:
        TypeError, ValueError: naming the argument, what was expected and what was received.

    Example:
        >>> import torch, torch_appearance as ta
        >>> sigma_t = torch.full((3, 4, 8, 8), 10.0, requires_grad=True)
        >>> albedo = torch.full((3, 4, 8, 8), 0.9, requires_grad=True)
        >>> img = ta.render_texels(sigma_t, albedo, voxel_size=0.1, spp=4)
        >>> img.shape
        torch.Size([8, 8, 3])
        >>> img.mean().backward()   # fills sigma_t.grad and albedo.grad
    """
    scene = Scene.slab(voxel_size, face=face, g=g, ior=ior, environment=environment, max_depth=max_depth,
                       rr_depth=rr_depth, sigma_t_floor=sigma_t_floor, albedo_floor=albedo_floor)
    seed_grad = seed if seed_grad is None else seed_grad  # documented default: replay the forward's own paths
    return render_scene(scene, sigma_t, albedo, spp=spp, seed=seed, seed_grad=seed_grad,
                        sampling_sigma_t=sampling_sigma_t, sampling_albedo=sampling_albedo, stats=stats,
                        partition=partition, chromatic=chromatic, adjoint=adjoint)


def _check_sampling(sigma_t, albedo, sampling_sigma_t, sampling_albedo, stats):
    if sampling_sigma_t is not None:
        check_grid("sampling_sigma_t", sampling_sigma_t, like=sigma_t)
        if bool(((sampling_sigma_t.detach() <= 0) & (sigma_t.detach() > 0)).any()):
            raise ValueError("sampling_sigma_t: expected > 0 wherever sigma_t > 0 (else the estimator is biased)")
    if sampling_albedo is not None:
        check_grid("sampling_albedo", sampling_albedo, like=sigma_t, hi=1.0)
        if bool(((sampling_albedo.detach() <= 0) & (albedo.detach() > 0)).any()):
            raise ValueError("sampling_albedo: expected > 0 wherever albedo > 0 (else the estimator is biased)")
    if stats is not None and not isinstance(stats, dict):
        raise TypeError(f"stats: expected a dict or None, got {type(stats).__name__}")
    samp_s = None if sampling_sigma_t is None else sampling_sigma_t.detach()
    samp_a = None if sampling_albedo is None else sampling_albedo.detach()
    return samp_s, samp_a


def render_scene(scene, sigma_t, albedo, *, spp=16, seed=0, seed_grad=None, sampling_sigma_t=None,
                 sampling_albedo=None, stats=None, partition=None, chromatic="per_channel", grad_support=None,
                 adjoint=None):
    """Render what ``scene``'s sensor sees of a heterogeneous voxel medium, differentiably.

    The medium (per-voxel, per-channel σ_t and albedo, piecewise constant, exact regular tracking) fills the grid
    placed at ``scene.origin`` and counts only inside the scene's boundary (the grid box, or the zero set of an SDF
    grid); the boundary is index matched or a smooth dielectric. Paths start at the sensor (face or surface texels,
    orthographic or perspective camera pixels) and receive the emitter's radiance in the direction they escape.

    The backward pass is radiative backpropagation by path replay, as for :func:`render_texels`: linear time, no
    tape; gradients only for inputs that require them. The replay samples a detached reference medium with
    density floors and draws its paths with ``seed_grad``, independent of the forward's noise (as Mitsuba's
    ``render(seed, seed_grad)``). With explicit ``sampling_sigma_t``/``sampling_albedo`` and ``seed_grad=seed`` the
    image is a smooth function of the parameters for a fixed seed and the backward its exact derivative
    (``torch.autograd.gradcheck`` passes in float64).

    Args:
        scene: a :class:`torch_appearance.render.Scene`.
        sigma_t: (3, D, H, W) extinction coefficient in mm⁻¹, >= 0, float32 or float64, on the CPU or a CUDA device
            (the render runs there: see the README's GPU section; the scene's own tensors follow).
        albedo: (3, D, H, W) single-scattering albedo in [0, 1], same dtype and device.
        spp: samples per sensor element (per channel when σ_t is chromatic), >= 1.
        seed: 64-bit seed of the forward pass; results are reproducible for a seed, independent of threads.
        seed_grad: 64-bit seed of the gradient replay; default :func:`derive_seed_grad` (seed).
        sampling_sigma_t, sampling_albedo: optional detached (3, D, H, W) sampling medium (see render_texels).
        stats: optional dict, filled with ``forward_s``, ``scatter_events``, ``voxel_steps``, ``outside_steps``,
            ``core_events``, ``lanes``, ``hero`` and, after backward, ``backward_s`` and ``backward_scatter_events``.
        partition: optional (rank, world): trace only the sensor elements t (flat texel or pixel index) with
            t % world == rank; the others are 0 and get no gradient. The random numbers are keyed by the global t,
            so the images of all ranks sum to the full image (see :mod:`torch_appearance.distributed`).
        chromatic: "per_channel" or "hero", the estimator for a sampling density that differs between channels
            (see :func:`render_texels`).
        grad_support: optional (D, H, W) bool tensor, the voxels whose gradients are wanted: the others get 0, and
            the replay crosses a homogeneous core outside them (a print's fixed core ink) in bricks, without
            gradient bookkeeping. The image does not depend on it.
        adjoint: optional tensor of the image's shape, the gradient the caller will send back to the image, known
            before the render (e.g. a loss's gradient taken at a running mean of past renders, as the print loop's
            ``ema`` estimator does). The render then walks the gradient replay's paths once (``seed_grad``, the
            floored reference medium): each walk adds its term to the image and deposits its derivative, so forward
            and backward cost one walk instead of two. The image is an unbiased estimate as the plain forward's
            (that of ``seed_grad``'s paths, with ratio weights where the floors bind); a backward with exactly this
            gradient (``(adjoint * image).sum().backward()``) costs nothing more, any other gradient is replayed.
            Only when the medium requires grad (else ignored). ``stats`` then has ``with_adjoint = True``.

    Returns:
        Linear RGB radiance: (rows, cols, 3) for a camera (row 0 is the camera's up side), (N, 3) for surface texels,
        (H, W, 3) or (2, H, W, 3) for face texels.

    Raises:
        TypeError, ValueError: naming the argument, what was expected and what was received.

    Example:
        >>> import torch, torch_appearance as ta
        >>> from torch_appearance.render import Scene, SDFBoundary, OrthographicCamera
        >>> k, j, i = torch.meshgrid(*(torch.arange(9.0),) * 3, indexing="ij")
        >>> sdf = ((i - 4) ** 2 + (j - 4) ** 2 + (k - 4) ** 2).sqrt() * 0.1 - 0.3      # sphere, r = 0.3 mm
        >>> scene = Scene(voxel_size=0.1, origin=(-0.4, -0.4, -0.4), boundary=SDFBoundary(sdf, ior=1.5),
        ...               sensor=OrthographicCamera(origin=(0, 0, 2), target=(0, 0, 0), up=(0, 1, 0),
        ...                                         extent_mm=(0.8, 0.8), resolution=(8, 8)))
        >>> sigma_t = torch.full((3, 8, 8, 8), 10.0, requires_grad=True)
        >>> albedo = torch.full((3, 8, 8, 8), 1.0)
        >>> image = ta.render_scene(scene, sigma_t, albedo, spp=4)
        >>> image.shape, bool(torch.allclose(image, torch.ones(()), atol=1e-5))     # white furnace
        (torch.Size([8, 8, 3]), True)
        >>> image.sum().backward()      # fills sigma_t.grad
    """
    from ..autograd.volpath import VolumePathTrace, VolumePathTraceWithAdjoint

    job = TraceJob(scene, spp=spp, seed=seed, seed_grad=seed_grad, chromatic=chromatic, partition=partition,
                   grad_support=grad_support)
    check_medium(sigma_t, albedo)
    scene.check_grid_shape(tuple(sigma_t.shape[1:]))
    job.check_grid(tuple(sigma_t.shape[1:]))
    samp_s, samp_a = _check_sampling(sigma_t, albedo, sampling_sigma_t, sampling_albedo, stats)
    if adjoint is not None:
        _check_adjoint(adjoint, scene.output_shape(tuple(sigma_t.shape[1:])), sigma_t.device)
        if torch.is_grad_enabled() and (sigma_t.requires_grad or albedo.requires_grad):
            return VolumePathTraceWithAdjoint.apply(sigma_t, albedo, samp_s, samp_a, adjoint, job, stats)
    return VolumePathTrace.apply(sigma_t, albedo, samp_s, samp_a, job, stats)


def _check_adjoint(adjoint, shape, device):
    if not isinstance(adjoint, torch.Tensor):
        raise TypeError(f"adjoint: expected a tensor of the image's shape {tuple(shape)}, got "
                        f"{type(adjoint).__name__}")
    if tuple(adjoint.shape) != tuple(shape):
        raise ValueError(f"adjoint: expected the image's shape {tuple(shape)}, got {tuple(adjoint.shape)}")
    if not adjoint.dtype.is_floating_point or adjoint.device != device:
        raise ValueError(f"adjoint: expected a floating-point tensor on {device} (sigma_t's device), got "
                         f"{adjoint.dtype} on {adjoint.device}")
    if not bool(torch.isfinite(adjoint).all()):
        raise ValueError("adjoint: expected finite values, got NaN or inf")


def render_scene_indexed(scene, index, sigma_t_table, albedo_table, *, spp=16, seed=0, partition=None):
    """Render a palette medium (a quantised print): forward only, not differentiable.

    Voxel v holds palette entry ``index[v]``, i.e. the medium is ``sigma_t = sigma_t_table[index].permute(3, 0, 1,
    2)`` (and the same for albedo), but the tracer reads the one-byte index and the table instead of two dense
    (3, D, H, W) grids: 1 byte per voxel instead of 24 (float32), e.g. 0.36 GB instead of 8.7 GB for the 364 M
    printer voxels of a 40 mm object at 600 × 300 × 940 DPI. The image equals :func:`render_scene` of those dense
    grids with the same ``spp``, ``seed`` and ``partition``, bitwise.

    Args:
        scene: a :class:`torch_appearance.render.Scene` for a (D, H, W) grid.
        index: (D, H, W) uint8 tensor or ndarray of palette entries (< P), on the CPU or a CUDA device (the render
            runs there; the tables on the same device).
        sigma_t_table: (P, 3) extinction coefficient of each entry in mm⁻¹, >= 0, float32 or float64.
        albedo_table: (P, 3) single-scattering albedo in [0, 1], the same dtype. The image has this dtype.
        spp, seed, partition: as for :func:`render_scene`.

    Returns:
        The image, shaped as :func:`render_scene`'s.
    """
    import numpy as np

    from ..autograd.volpath import tracer

    job = TraceJob(scene, spp=spp, seed=seed, seed_grad=seed, partition=partition, name="render_scene_indexed")
    if isinstance(index, np.ndarray):
        index = torch.from_numpy(np.ascontiguousarray(index))
    if not isinstance(index, torch.Tensor) or index.dtype != torch.uint8 or index.dim() != 3 or min(index.shape) < 1:
        raise TypeError(f"index: expected a (D, H, W) uint8 tensor or ndarray, got "
                        f"{getattr(index, 'dtype', type(index).__name__)} {tuple(getattr(index, 'shape', ()))}")
    tables = []
    for name, table, hi in (("sigma_t_table", sigma_t_table, math.inf), ("albedo_table", albedo_table, 1.0)):
        if not isinstance(table, torch.Tensor) or table.dtype not in (torch.float32, torch.float64):
            raise TypeError(f"{name}: expected a float32 or float64 tensor of shape (P, 3), got "
                            f"{getattr(table, 'dtype', type(table).__name__)}")
        if table.dim() != 2 or table.shape[1] != 3 or not 1 <= table.shape[0] <= 256:
            raise ValueError(f"{name}: expected shape (P, 3) with 1 <= P <= 256, got {tuple(table.shape)}")
        if table.device != index.device:
            raise ValueError(f"{name}: expected the device of index ({index.device}), got {table.device}")
        t = table.detach().cpu()
        if not bool((torch.isfinite(t) & (t >= 0) & (t <= hi)).all()):
            raise ValueError(f"{name}: expected finite values in [0, {hi}], got {t.tolist()}")
        tables.append(t)
    if tables[0].shape != tables[1].shape or tables[0].dtype != tables[1].dtype:
        raise ValueError(f"albedo_table: expected the shape and dtype of sigma_t_table "
                         f"{tuple(tables[0].shape)} {tables[0].dtype}, got {tuple(tables[1].shape)} {tables[1].dtype}")
    index = index.contiguous()
    top = int(index.max())
    if top >= tables[0].shape[0]:
        raise ValueError(f"index: expected entries < P = {tables[0].shape[0]} (the tables' rows), got {top}")
    scene.check_grid_shape(tuple(index.shape))
    # one walk for all channels when every entry in use is grey in σ_t (what sampling_lanes sees on dense grids)
    used = torch.zeros(tables[0].shape[0], dtype=torch.bool)
    flat = index.view(-1)
    for start in range(0, flat.numel(), 1 << 24):
        used |= torch.bincount(flat[start:start + (1 << 24)], minlength=len(used)).bool().cpu()
    st = tables[0][used]
    lanes = 3 if torch.equal(st[:, 0], st[:, 1]) and torch.equal(st[:, 0], st[:, 2]) else 1
    options = job.scene_options(lanes, job.seed, tuple(index.shape), tables[0].dtype)
    entry = tracer(index, names=("index",))
    image, _ = call_tracer(entry.scene_forward_indexed, index, tables[0].t().contiguous().to(index.device),
                           tables[1].t().contiguous().to(index.device), options)
    return image
