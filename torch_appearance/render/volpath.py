"""``render_texels``: texel-space radiance of a heterogeneous voxel slab, differentiable by path replay."""

from .scene import SlabScene, check_grid, check_medium

__all__ = ["render_texels"]


def render_texels(sigma_t, albedo, *, voxel_size, face="top", g=0.4, ior=1.5, environment=1.0, spp=16, seed=0,
                  max_depth=None, rr_depth=None, sampling_sigma_t=None, sampling_albedo=None,
                  sigma_t_floor=None, albedo_floor=0.05, stats=None):
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
        sigma_t: (3, D, H, W) extinction coefficient in mm⁻¹, >= 0, float32 or float64, CPU.
        albedo: (3, D, H, W) single-scattering albedo in [0, 1], same dtype.
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
            along the grid diagonal, see :meth:`SlabScene.sigma_t_floor`).
        albedo_floor: albedo floor of the default gradient sampling, in [0, 1] (default 0.05).
        stats: optional dict, filled with ``forward_s``, ``scatter_events``, ``lanes`` and, after backward,
            ``backward_s`` and ``backward_scatter_events``.

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
    from ..autograd.volpath import VolumePathTrace

    check_medium(sigma_t, albedo)
    scene = SlabScene.create(voxel_size, face=face, g=g, ior=ior, environment=environment, spp=spp, seed=seed,
                             max_depth=max_depth, rr_depth=rr_depth, sigma_t_floor=sigma_t_floor,
                             albedo_floor=albedo_floor)
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
    return VolumePathTrace.apply(sigma_t, albedo, samp_s, samp_a, scene, stats)
