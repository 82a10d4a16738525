"""``VolumePathTrace``: the C++ volume path tracer as a ``torch.autograd.Function``.

Forward renders the radiance seen by the sensor (texels or pixels); backward is radiative backpropagation by path
replay (csrc/core/integrator.h): each path is regenerated once from its counter-based random numbers, its events
are kept in a bounded per-thread record (csrc/core/tape.h) and ∂(path contribution)/∂θ is deposited into the voxels
it touched when the path ends. Linear time, no tape of the render, memory independent of path length; gradient
work only for inputs with ``requires_grad``.

``VolumePathTraceWithAdjoint``: the same for a caller that knows the gradient it will send back before the render
(e.g. a loss's gradient taken at a running mean of past renders): one set of walks gives the image and deposits that
adjoint's derivative, so forward and backward cost one walk instead of two.
"""
import time
import warnings

import torch
from torch.autograd.function import once_differentiable

from .._ext import call_tracer

__all__ = ["VolumePathTrace", "VolumePathTraceWithAdjoint", "reference_medium", "sampling_lanes", "walk_options",
           "tracer"]

_TRUNCATION_WARN = 1e-3  # warn when more than this fraction of paths was cut by max_depth


def tracer(*tensors, names=("sigma_t", "albedo", "sampling_sigma_t", "sampling_albedo")):
    """The tracer's entry points for the device of ``tensors`` (None skipped): the C++ extension for CPU tensors, the
    CUDA launcher (:mod:`torch_appearance.render.cuda_launch`) for CUDA tensors of one device. Mixed devices, or CUDA
    tensors where no GPU can render them, are refused with a ValueError of one line."""
    from ..render.cuda_launch import tracer_for  # render imports this module; looked up when used

    return tracer_for(*tensors, names=list(names))


def sampling_lanes(ref_sigma_t):
    """3 if the sampling density is the same in all channels (one walk serves all three), else 1."""
    r = ref_sigma_t.detach()
    return 3 if torch.equal(r[0], r[1]) and torch.equal(r[0], r[2]) else 1


def walk_options(job, ref_sigma_t, seed, grid_shape, dtype, lanes=None):
    """The C++ ``SceneOptions`` of ``job`` (a :class:`torch_appearance.render.TraceJob`) for a walk that samples
    ``ref_sigma_t``: three lanes in one walk for an achromatic density; for a chromatic one, one walk per channel, or
    with ``job.chromatic == "hero"`` one hero-channel walk with spectral MIS (``options.hero = 1``). ``lanes``:
    :func:`sampling_lanes` of the sampling density when the caller knows it (e.g. of a grid the tracer floors as it
    reads)."""
    lanes = sampling_lanes(ref_sigma_t) if lanes is None else lanes
    hero = lanes == 1 and job.chromatic == "hero"
    options = job.scene_options(3 if hero else lanes, seed, grid_shape, dtype)
    options.hero = int(hero)
    return options


def reference_medium(sigma_t, albedo, sampling_sigma_t, sampling_albedo, sigma_t_floor=0.0, albedo_floor=0.0):
    """The detached sampling medium: explicit references as given, defaults = detached parameters with floors.

    Returns:
        (ref_sigma_t, ref_albedo, ratio): contiguous (3, D, H, W) tensors and whether they may differ from the
        parameters (then the walk carries ratio weights f(θ)/p_ref).
    """
    ratio = False
    if sampling_sigma_t is None:
        ref_s = sigma_t.detach()
        if sigma_t_floor > 0:
            ref_s = ref_s.clamp_min(sigma_t_floor)
            ratio = True
    else:
        ref_s, ratio = sampling_sigma_t.detach(), True
    if sampling_albedo is None:
        ref_a = albedo.detach()
        if albedo_floor > 0:
            ref_a = ref_a.clamp_min(albedo_floor)
            ratio = True
    else:
        ref_a, ratio = sampling_albedo.detach(), True
    return ref_s.contiguous(), ref_a.contiguous(), ratio


class VolumePathTrace(torch.autograd.Function):
    """Radiance seen by a scene's sensor; differentiable in ``sigma_t`` and ``albedo``.

    Inputs are validated by :func:`torch_appearance.render_scene` (or its slab form
    :func:`torch_appearance.render_texels`), the function to call. ``job`` is the
    :class:`torch_appearance.render.TraceJob` (scene, spp, seed, seed_grad, chromatic, partition) that builds the C++
    options of the forward walk and of the gradient replay; ``stats`` an optional dict that receives ``forward_s``,
    ``scatter_events``, ``voxel_steps``, ``outside_steps`` (the scalar walk's voxel visits inside the object and
    outside it), ``core_events`` (scattering events in the homogeneous core) and, after backward, ``backward_s``, ``backward_scatter_events``.
    """

    @staticmethod
    def forward(ctx, sigma_t, albedo, sampling_sigma_t, sampling_albedo, job, stats):
        from ..render.trace_job import TraceJob  # render imports this module; the job type is looked up when used

        if not isinstance(job, TraceJob):
            raise TypeError(f"job: expected a torch_appearance.render.TraceJob, got {type(job).__name__}")
        sigma_t = sigma_t.contiguous()
        albedo = albedo.contiguous()
        entry = tracer(sigma_t, albedo, sampling_sigma_t, sampling_albedo)
        ref_s, ref_a, ratio = reference_medium(sigma_t, albedo, sampling_sigma_t, sampling_albedo)
        options = walk_options(job, ref_s, job.seed, tuple(sigma_t.shape[1:]), sigma_t.dtype)
        start = time.perf_counter()
        image, counts = call_tracer(entry.scene_forward, sigma_t.detach(), albedo.detach(), ref_s, ref_a, ratio,
                                    options)
        if stats is not None:
            stats["forward_s"] = time.perf_counter() - start
            stats["scatter_events"] = counts.scatter_events
            stats["truncated_paths"] = counts.truncated_paths
            stats["voxel_steps"] = counts.voxel_steps
            stats["outside_steps"] = counts.outside_steps
            stats["core_events"] = counts.core_events
            if counts.tally:  # diagnostics (_C._set_tally): (events, voxel moves) per bin
                stats["tally"] = torch.tensor(counts.tally, dtype=torch.int64).view(-1, 2)
            stats["lanes"] = options.lanes
            stats["hero"] = bool(options.hero)
        _warn_truncated(job, options, counts, image)
        ctx.job, ctx.stats = job, stats
        ctx.save_for_backward(sigma_t, albedo,
                              sampling_sigma_t if sampling_sigma_t is not None else None,
                              sampling_albedo if sampling_albedo is not None else None)
        return image

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_image):
        need_s, need_a = ctx.needs_input_grad[0], ctx.needs_input_grad[1]
        if not (need_s or need_a):
            return None, None, None, None, None, None
        sigma_t, albedo, samp_s, samp_a = ctx.saved_tensors
        grad_s, grad_a = _replay(ctx.job, sigma_t, albedo, samp_s, samp_a, grad_image, need_s, need_a, ctx.stats)
        return (grad_s if need_s else None,
                grad_a if need_a else None,
                None,  # sampling_sigma_t: detached by definition
                None,  # sampling_albedo
                None,  # job
                None)  # stats


def _warn_truncated(job, options, counts, image):
    """Warns when more than _TRUNCATION_WARN of the image's walks were cut at max_depth (a bias towards dark)."""
    walks = image.numel() // 3 * options.spp * (3 if options.lanes == 1 else 1)
    if counts.truncated_paths > _TRUNCATION_WARN * walks:
        warnings.warn(f"{job.name}: {counts.truncated_paths} of {walks} paths were cut at max_depth="
                      f"{options.max_depth} interactions; the image is biased dark by up to that fraction. "
                      f"Raise max_depth (optically very thick, bright media have heavy-tailed path lengths).",
                      RuntimeWarning, stacklevel=4)


def _gradient_walks(job, sigma_t, albedo, samp_s, samp_a):
    """(ref_sigma_t, sigma_t_floor, ref_albedo, albedo_floor, options) of ``job``'s gradient walks (seed_grad)."""
    # the sampling medium: explicit references as given, else the parameters floored on the fly in C++
    # (max(σ_t, floor), max(α, floor): the same numbers as clamp_min, without two copies of the grids)
    ref_s, floor_s = _floored(sigma_t, samp_s, job.sigma_t_floor(sigma_t.shape))
    ref_a, floor_a = _floored(albedo, samp_a, job.albedo_floor)
    options = walk_options(job, ref_s, job.seed_grad, tuple(sigma_t.shape[1:]), sigma_t.dtype,
                           lanes=_floored_lanes(ref_s, floor_s))
    return ref_s, floor_s, ref_a, floor_a, options


def _replay(job, sigma_t, albedo, samp_s, samp_a, grad_image, need_s, need_a, stats):
    """(grad_sigma_t, grad_albedo) of ``grad_image`` by path replay of ``job``'s gradient walks."""
    ref_s, floor_s, ref_a, floor_a, options = _gradient_walks(job, sigma_t, albedo, samp_s, samp_a)
    entry = tracer(sigma_t, albedo, samp_s, samp_a)
    start = time.perf_counter()
    grad_s, grad_a, events = call_tracer(entry.scene_backward, grad_image.to(sigma_t.dtype).contiguous(),
                                         sigma_t.detach(), albedo.detach(), ref_s, ref_a, need_s, need_a, options,
                                         floor_s, floor_a)
    if stats is not None:
        stats["backward_s"] = time.perf_counter() - start
        stats["backward_scatter_events"] = int(events)
    return grad_s, grad_a


def _floored(x, sampling, floor):
    """(reference grid, floor the tracer applies to it): an explicit sampling grid as is, else ``x`` with ``floor``."""
    if sampling is not None:
        return sampling.detach().contiguous(), 0.0
    return x.detach().contiguous(), float(floor) if floor > 0 else 0.0


def _floored_lanes(ref_sigma_t, floor, chunk=1 << 22):
    """:func:`sampling_lanes` of ``ref_sigma_t.clamp_min(floor)``, a chunk of voxels at a time (no copy of the grid)."""
    if floor == 0:
        return sampling_lanes(ref_sigma_t)
    r = ref_sigma_t.detach().reshape(3, -1)
    for start in range(0, r.shape[1], chunk):
        c = r[:, start:start + chunk].clamp_min(floor)
        if not (torch.equal(c[0], c[1]) and torch.equal(c[0], c[2])):
            return 1
    return 3


class VolumePathTraceWithAdjoint(torch.autograd.Function):
    """:class:`VolumePathTrace` for an ``adjoint`` (the image's gradient) known before the render.

    The forward walks the replay's paths (the detached reference medium with the job's density floors, drawn with
    ``job.seed_grad``): each walk adds its term to the image and deposits its derivative weighted by ``adjoint``
    (``_C.scene_forward_backward``), so the render and its gradient take one walk. The image is an unbiased
    estimate like the plain forward's: bitwise the ratio-weighted forward of that floored reference with seed
    ``job.seed_grad`` on the scalar walk. The backward returns the deposited gradients when the gradient that
    reaches the image equals ``adjoint`` (as from ``(adjoint * image).sum()``); for any other gradient it replays
    the paths as :class:`VolumePathTrace` does (correct, but a second walk).
    """

    @staticmethod
    def forward(ctx, sigma_t, albedo, sampling_sigma_t, sampling_albedo, adjoint, job, stats):
        from ..render.trace_job import TraceJob

        if not isinstance(job, TraceJob):
            raise TypeError(f"job: expected a torch_appearance.render.TraceJob, got {type(job).__name__}")
        sigma_t = sigma_t.contiguous()
        albedo = albedo.contiguous()
        entry = tracer(sigma_t, albedo, sampling_sigma_t, sampling_albedo, adjoint,
                       names=("sigma_t", "albedo", "sampling_sigma_t", "sampling_albedo", "adjoint"))
        adjoint = adjoint.detach().to(sigma_t.dtype).contiguous()
        ref_s, floor_s, ref_a, floor_a, options = _gradient_walks(job, sigma_t, albedo, sampling_sigma_t,
                                                                  sampling_albedo)
        need_s, need_a = ctx.needs_input_grad[0], ctx.needs_input_grad[1]
        start = time.perf_counter()
        image, grad_s, grad_a, counts = call_tracer(entry.scene_forward_backward, adjoint, sigma_t.detach(),
                                                    albedo.detach(), ref_s, ref_a, need_s, need_a, options,
                                                    floor_s, floor_a)
        if stats is not None:
            stats["forward_s"] = time.perf_counter() - start
            stats["scatter_events"] = counts.scatter_events
            stats["truncated_paths"] = counts.truncated_paths
            stats["lanes"] = options.lanes
            stats["hero"] = bool(options.hero)
            stats["with_adjoint"] = True
        _warn_truncated(job, options, counts, image)
        ctx.job, ctx.stats = job, stats
        ctx.grads = (grad_s, grad_a)
        ctx.save_for_backward(sigma_t, albedo, sampling_sigma_t, sampling_albedo, adjoint)
        return image

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_image):
        sigma_t, albedo, samp_s, samp_a, adjoint = ctx.saved_tensors
        grad_s, grad_a = ctx.grads
        need_s, need_a = ctx.needs_input_grad[0], ctx.needs_input_grad[1]
        if not torch.equal(grad_image.to(adjoint.dtype), adjoint):  # another gradient: replay the paths for it
            grad_s, grad_a = _replay(ctx.job, sigma_t, albedo, samp_s, samp_a, grad_image, need_s, need_a, ctx.stats)
        elif ctx.stats is not None:
            ctx.stats["backward_s"] = 0.0
            ctx.stats["backward_scatter_events"] = 0
        return (grad_s if need_s else None, grad_a if need_a else None, None, None, None, None, None)
