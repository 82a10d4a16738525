"""Slow, obviously-correct numpy reference for the volume path tracer (for tests and benchmarks).

This module re-implements the texel estimator of ``torch_appearance.render_texels`` from first principles,
deliberately with a *different* algorithm than the fast C++ tracer, so that the two can be compared
statistically (z-tests):

* free flights are sampled by **delta (Woodcock) tracking** against one global majorant per channel
  (the fast tracer uses exact regular tracking through the voxels);
* collisions are **analog**: a real collision (probability ``sigma_t(x) / majorant``) scatters with
  probability ``albedo`` and otherwise absorbs the path, which then contributes 0;
* the dielectric box boundary is handled by **analog Russian roulette on the Fresnel reflectance**
  (reflect with probability F, else refract and escape);
* every channel is traced on its own, so every path carries the weight 1 from start to end and its
  value is either 0 (absorbed or truncated) or the environment radiance of its channel.

Scene conventions (see the tracer spec): grid ``(D, H, W)`` of voxels of edge ``voxel_size`` (mm)
occupying ``[0, W s] x [0, H s] x [0, D s]``; x <-> W index i, y <-> H index j, z <-> D index k;
vacuum (n = 1) outside the box. Texel ``[j, i]`` of face ``"top"`` is a ray at normal incidence
``(0, 0, -1)`` through ``((i + u1) s, (j + u2) s, D s)``; face ``"bottom"`` starts at ``z = 0`` with
direction ``(0, 0, +1)``.

Everything is vectorised over all paths of a channel (all texels x spp at once); the event loop runs
while any path is alive and compacts the alive set after every event. It is meant to be read, not to be
fast: a 3 x 4 x 4 grid at 20000 samples per texel takes a few seconds.

:func:`reference_render_scene` extends the same estimator to *general scenes*: a voxel grid anywhere in
world space with anisotropic voxels, the object being either the grid box or the zero level set of a
trilinear corner SDF (found by marching + bisection, not by solving the cubic), index-matched or
dielectric, seen by surface texels or orthographic / perspective cameras, lit by a constant, lat-long
environment map or distant disc emitter. Its conventions are documented with the functions below.

It imports nothing from torch_appearance (numpy only), so that it stays independent of what it checks.

Run the module directly for a quick smoke test::

    python -m torch_appearance.testing.reference_tracer
"""

from __future__ import annotations

import math
from typing import Optional, Sequence, Tuple, Union

import numpy as np

__all__ = [
    "fresnel_dielectric",
    "sample_henyey_greenstein",
    "distance_to_box_exit",
    "reference_render_texels",
    "trilinear_sdf",
    "sdf_sphere",
    "evaluate_emitter",
    "sensor_output_shape",
    "sensor_rays",
    "reference_render_scene",
]


# --------------------------------------------------------------------------------------------------
# Physics building blocks
# --------------------------------------------------------------------------------------------------


def fresnel_dielectric(cos_i: np.ndarray, eta: float) -> np.ndarray:
    """Unpolarised Fresnel reflectance of a smooth dielectric interface.

    Light travels in a medium of index ``n1`` towards a medium of index ``n2``; ``eta = n1 / n2`` is the
    relative index *seen from the incident side* (for light inside a box of index ``ior`` hitting the
    vacuum outside, ``eta = ior``; for light entering from vacuum, ``eta = 1 / ior``).

    With ``cos_i = |cos(theta_i)|`` and Snell's law ``n1 sin(theta_i) = n2 sin(theta_t)``::

        sin^2(theta_t) = eta^2 (1 - cos_i^2)
        if sin^2(theta_t) >= 1: total internal reflection, F = 1
        cos_t = sqrt(1 - sin^2(theta_t))
        r_s = (n1 cos_i - n2 cos_t) / (n1 cos_i + n2 cos_t) = (eta cos_i - cos_t) / (eta cos_i + cos_t)
        r_p = (n2 cos_i - n1 cos_t) / (n2 cos_i + n1 cos_t) = (cos_i - eta cos_t) / (cos_i + eta cos_t)
        F   = (r_s^2 + r_p^2) / 2

    At normal incidence ``F = ((eta - 1) / (eta + 1))^2`` (0.04 for glass, eta = 1.5 or 1/1.5).

    Args:
        cos_i: cosine of the angle of incidence, any shape, values in [0, 1] (the sign is ignored).
        eta: relative index ``n1 / n2`` (> 0).

    Returns:
        Reflectance F in [0, 1], same shape as ``cos_i``.
    """
    cos_i = np.clip(np.abs(np.asarray(cos_i, dtype=np.float64)), 0.0, 1.0)
    sin2_t = eta * eta * (1.0 - cos_i * cos_i)
    tir = sin2_t >= 1.0
    cos_t = np.sqrt(np.clip(1.0 - sin2_t, 0.0, 1.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        r_s = (eta * cos_i - cos_t) / (eta * cos_i + cos_t)
        r_p = (cos_i - eta * cos_t) / (cos_i + eta * cos_t)
        f = 0.5 * (r_s * r_s + r_p * r_p)
    # Grazing incidence (cos_i = cos_t = 0) gives 0/0 above; the limit is F = 1.
    f = np.where(np.isfinite(f), f, 1.0)
    return np.where(tir, 1.0, np.clip(f, 0.0, 1.0))


def _orthonormal_frame(d: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """Two unit vectors ``t1, t2`` with ``(t1, t2, d)`` a right-handed orthonormal basis.

    Gram-Schmidt against a helper axis: ``e = x`` unless ``d`` is nearly parallel to x, then ``e = y``;
    ``t1 = normalise(e x d)``, ``t2 = d x t1``.

    Args:
        d: unit directions, shape (N, 3).

    Returns:
        ``t1, t2``, each of shape (N, 3).
    """
    helper = np.zeros_like(d)
    use_x = np.abs(d[:, 0]) < 0.9
    helper[use_x, 0] = 1.0
    helper[~use_x, 1] = 1.0
    t1 = np.cross(helper, d)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(d, t1)
    return t1, t2


def sample_henyey_greenstein(d: np.ndarray, g: float, xi1: np.ndarray, xi2: np.ndarray) -> np.ndarray:
    """Sample new directions from the Henyey-Greenstein phase function around ``d``.

    The density of ``mu = cos(theta)`` (theta between the incoming propagation direction ``d`` and the
    new direction) is::

        p(mu) = (1 - g^2) / (2 (1 + g^2 - 2 g mu)^(3/2)),   mu in [-1, 1],

    with mean cosine ``E[mu] = g``. Its CDF is::

        P(mu) = (1 - g^2) / (2 g) * ( 1 / sqrt(1 + g^2 - 2 g mu) - 1 / (1 + g) )

    and solving ``P(mu) = xi`` gives::

        s  = (1 - g^2) / (1 - g + 2 g xi)          (= sqrt(1 + g^2 - 2 g mu))
        mu = (1 + g^2 - s^2) / (2 g)

    (xi = 0 -> mu = -1, xi = 1 -> mu = +1). For ``|g| < 1e-4`` the isotropic limit ``mu = 2 xi - 1`` is
    used. The azimuth ``phi = 2 pi xi2`` is uniform; the new direction is
    ``sin(theta) cos(phi) t1 + sin(theta) sin(phi) t2 + mu d`` in an orthonormal frame ``(t1, t2, d)``.

    Args:
        d: incoming unit propagation directions, shape (N, 3).
        g: HG asymmetry parameter in [-1, 1].
        xi1: uniform numbers in [0, 1), shape (N,), for the polar angle.
        xi2: uniform numbers in [0, 1), shape (N,), for the azimuth.

    Returns:
        New unit directions, shape (N, 3).
    """
    if abs(g) < 1e-4:
        mu = 2.0 * xi1 - 1.0
    else:
        denom = 1.0 - g + 2.0 * g * xi1
        # denom is 0 only for g = 1, xi1 = 0 (or g = -1, xi1 = 1, impossible): the limit is mu = 1.
        s = (1.0 - g * g) / np.where(denom == 0.0, 1.0, denom)
        s = np.where(denom == 0.0, 0.0, s)
        mu = (1.0 + g * g - s * s) / (2.0 * g)
    mu = np.clip(mu, -1.0, 1.0)
    sin_theta = np.sqrt(np.maximum(0.0, 1.0 - mu * mu))
    phi = 2.0 * math.pi * xi2
    t1, t2 = _orthonormal_frame(d)
    new = (
        (sin_theta * np.cos(phi))[:, None] * t1
        + (sin_theta * np.sin(phi))[:, None] * t2
        + mu[:, None] * d
    )
    return new / np.linalg.norm(new, axis=1, keepdims=True)


def distance_to_box_exit(pos: np.ndarray, d: np.ndarray, extent: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """Distance along ``d`` from ``pos`` (inside the closed box) to the box boundary, and the exit axis.

    The box is ``[0, extent[0]] x [0, extent[1]] x [0, extent[2]]``. Per axis a, the ray reaches the
    plane it is moving towards after ``t_a = (extent[a] - p_a) / d_a`` if ``d_a > 0``,
    ``t_a = (0 - p_a) / d_a`` if ``d_a < 0``, and never (``t_a = inf``) if ``d_a = 0``. The exit is the
    smallest ``t_a``. A point lying exactly on a face and moving *into* the box gets the distance to the
    opposite face; a point on a face moving *out* of it gets ``t = 0`` (it leaves at once). Distances are
    clamped at 0 to absorb rounding.

    Args:
        pos: positions, shape (N, 3), inside the closed box.
        d: unit directions, shape (N, 3).
        extent: box size ``(W s, H s, D s)``, shape (3,).

    Returns:
        ``(t_exit, axis)``: distances, shape (N,), and exit axes in {0, 1, 2}, shape (N,).
    """
    t = np.full(pos.shape, np.inf)
    positive = d > 0.0
    negative = d < 0.0
    ext = np.broadcast_to(extent, pos.shape)
    t[positive] = (ext[positive] - pos[positive]) / d[positive]
    t[negative] = (0.0 - pos[negative]) / d[negative]
    t = np.maximum(t, 0.0)
    axis = np.argmin(t, axis=1)
    return t[np.arange(len(t)), axis], axis


# --------------------------------------------------------------------------------------------------
# The estimator
# --------------------------------------------------------------------------------------------------


def _trace_channel(
    sigma: np.ndarray,
    albedo: np.ndarray,
    *,
    voxel_size: float,
    face: str,
    g: float,
    ior: Optional[float],
    spp: int,
    max_depth: int,
    rng: np.random.Generator,
) -> np.ndarray:
    """Trace all paths of one channel; return the number of paths per texel that reached the environment.

    Args:
        sigma: extinction of this channel, shape (D, H, W), mm^-1.
        albedo: single-scattering albedo of this channel, shape (D, H, W).
        voxel_size, face, g, ior, spp, max_depth: as in :func:`reference_render_texels`.
        rng: numpy random generator (consumed).

    Returns:
        Escape counts, shape (H * W,), texel index ``j * W + i``.
    """
    depth_k, height, width = sigma.shape
    s = float(voxel_size)
    extent = np.array([width * s, height * s, depth_k * s])
    n_texels = height * width
    majorant = float(sigma.max())
    escaped = np.zeros(n_texels, dtype=np.int64)

    # ---- camera rays: one path per (texel, sample), ordered texel-major ----
    texel = np.repeat(np.arange(n_texels), spp)
    n = texel.size
    i_idx = texel % width
    j_idx = texel // width
    pos = np.empty((n, 3))
    pos[:, 0] = (i_idx + rng.random(n)) * s
    pos[:, 1] = (j_idx + rng.random(n)) * s
    d = np.zeros((n, 3))
    if face == "top":
        pos[:, 2] = extent[2]
        d[:, 2] = -1.0
    else:
        pos[:, 2] = 0.0
        d[:, 2] = 1.0

    # ---- entry through the face at normal incidence (from vacuum: eta = 1 / ior) ----
    if ior is not None:
        f_entry = fresnel_dielectric(np.ones(1), 1.0 / ior)[0]
        reflected = rng.random(n) < f_entry
        escaped += np.bincount(texel[reflected], minlength=n_texels)
        keep = ~reflected
        texel, pos, d = texel[keep], pos[keep], d[keep]
    # Normal incidence: the refracted direction equals the incident one.

    n_scatter = np.zeros(texel.size, dtype=np.int64)
    iterations = 0
    while texel.size > 0:
        iterations += 1
        if iterations > 100_000_000:
            raise RuntimeError("reference tracer: event loop did not terminate")
        n = texel.size
        t_exit, exit_axis = distance_to_box_exit(pos, d, extent)
        if majorant > 0.0:
            t_free = -np.log1p(-rng.random(n)) / majorant  # exponential with rate = majorant
        else:
            t_free = np.full(n, np.inf)  # pure vacuum: no collisions at all
        at_boundary = t_free >= t_exit
        alive = np.ones(n, dtype=bool)

        # ---- paths reaching the box boundary ----
        b = np.nonzero(at_boundary)[0]
        if b.size:
            ax = exit_axis[b]
            pb = pos[b] + t_exit[b, None] * d[b]
            pb = np.clip(pb, 0.0, extent)
            # put the crossing coordinate exactly on its face
            moving_up = d[b, ax] > 0.0
            pb[np.arange(b.size), ax] = np.where(moving_up, extent[ax], 0.0)
            pos[b] = pb
            if ior is None:
                leaves = np.ones(b.size, dtype=bool)
            else:
                cos_i = np.abs(d[b, ax])
                f = fresnel_dielectric(cos_i, ior)  # from inside (n = ior) to vacuum
                leaves = rng.random(b.size) >= f  # refract (and escape) with prob 1 - F
                # specular reflection: mirror the normal component, stay on the face
                refl = b[~leaves]
                d[refl, exit_axis[refl]] *= -1.0
            escaped += np.bincount(texel[b[leaves]], minlength=n_texels)
            alive[b[leaves]] = False

        # ---- paths colliding inside the medium ----
        c = np.nonzero(~at_boundary)[0]
        if c.size:
            pc = np.clip(pos[c] + t_free[c, None] * d[c], 0.0, extent)
            pos[c] = pc
            vox = np.floor(pc / s).astype(np.int64)
            ii = np.clip(vox[:, 0], 0, width - 1)
            jj = np.clip(vox[:, 1], 0, height - 1)
            kk = np.clip(vox[:, 2], 0, depth_k - 1)
            sig = sigma[kk, jj, ii]
            alb = albedo[kk, jj, ii]
            real = rng.random(c.size) * majorant < sig  # real collision with prob sigma / majorant
            # a real collision scatters with prob albedo, else the path is absorbed (value 0)
            scatters = real & (rng.random(c.size) < alb)
            absorbed = real & ~scatters
            alive[c[absorbed]] = False
            sc = c[scatters]
            if sc.size:
                n_scatter[sc] += 1
                truncated = n_scatter[sc] > max_depth  # value 0, like absorption
                alive[sc[truncated]] = False
                sc = sc[~truncated]
                d[sc] = sample_henyey_greenstein(d[sc], g, rng.random(sc.size), rng.random(sc.size))
            # null collisions: continue unchanged

        texel, pos, d, n_scatter = texel[alive], pos[alive], d[alive], n_scatter[alive]
    return escaped


def _check_medium(sigma_t, albedo):
    """(sigma_t, albedo) as float64 arrays of shape (3, D, H, W), σ_t finite >= 0, albedo in [0, 1]."""
    sigma_t = np.asarray(sigma_t, dtype=np.float64)
    albedo = np.asarray(albedo, dtype=np.float64)
    if sigma_t.ndim != 4 or sigma_t.shape[0] != 3:
        raise ValueError(f"sigma_t must have shape (3, D, H, W), got {sigma_t.shape}")
    if albedo.shape != sigma_t.shape:
        raise ValueError(f"albedo must have the shape of sigma_t {sigma_t.shape}, got {albedo.shape}")
    if not np.all(np.isfinite(sigma_t)) or sigma_t.min() < 0:
        raise ValueError("sigma_t must be finite and >= 0")
    if albedo.min() < 0 or albedo.max() > 1:
        raise ValueError("albedo must lie in [0, 1]")
    return sigma_t, albedo


def reference_render_texels(
    sigma_t: np.ndarray,
    albedo: np.ndarray,
    *,
    voxel_size: float,
    face: str = "top",
    g: float = 0.4,
    ior: Optional[float] = 1.5,
    environment: Union[float, Sequence[float]] = (1.0, 1.0, 1.0),
    spp: int = 1024,
    seed: int = 0,
    max_depth: int = 100000,
) -> Tuple[np.ndarray, np.ndarray]:
    """Reference Monte Carlo estimate of the texel radiance of one face of a voxel box.

    Each path has the value ``environment[c]`` if it leaves the box (including the specular reflection at
    the entry face) and 0 if it is absorbed or truncated, so the estimate is ``environment[c]`` times an
    escape frequency.

    Args:
        sigma_t: extinction coefficients, shape (3, D, H, W), mm^-1, >= 0.
        albedo: single-scattering albedos, shape (3, D, H, W), in [0, 1].
        voxel_size: voxel edge s in mm (> 0).
        face: ``"top"`` or ``"bottom"``.
        g: Henyey-Greenstein parameter in [-1, 1].
        ior: index of refraction of the box (>= 1), or ``None`` for an index-matched (invisible) boundary.
        environment: environment radiance, a scalar or 3 values (R, G, B).
        spp: samples (paths) per texel and channel.
        seed: seed of ``numpy.random.default_rng``.
        max_depth: maximum number of real scattering events; a path about to scatter for the
            ``max_depth + 1``-th time is terminated with value 0 (null collisions and boundary
            reflections do not count).

    Returns:
        ``(mean, stderr)``, each of shape (H, W, 3): the per-texel sample mean and its standard error
        (sample standard deviation with ddof=1, divided by ``sqrt(spp)``).

    Raises:
        ValueError: on shapes or values outside the ranges above.
    """
    sigma_t, albedo = _check_medium(sigma_t, albedo)
    if face not in ("top", "bottom"):
        raise ValueError(f"face must be 'top' or 'bottom', got {face!r}")
    if not -1.0 <= g <= 1.0:
        raise ValueError(f"g must lie in [-1, 1], got {g}")
    if ior is not None and ior < 1.0:
        raise ValueError(f"ior must be None or >= 1, got {ior}")
    if voxel_size <= 0:
        raise ValueError(f"voxel_size must be > 0, got {voxel_size}")
    if spp < 2:
        raise ValueError(f"spp must be >= 2 (for a standard error), got {spp}")
    env = np.broadcast_to(np.asarray(environment, dtype=np.float64), (3,))

    _, _, height, width = sigma_t.shape
    rng = np.random.default_rng(seed)
    mean = np.empty((height, width, 3))
    stderr = np.empty((height, width, 3))
    for c in range(3):
        count = _trace_channel(
            sigma_t[c], albedo[c], voxel_size=voxel_size, face=face, g=g, ior=ior,
            spp=spp, max_depth=max_depth, rng=rng,
        ).astype(np.float64)
        p = count / spp  # values are 0 or 1 (times env): mean and ddof=1 variance of a 0/1 sample
        var = (count - spp * p * p) / (spp - 1)
        mean[..., c] = (env[c] * p).reshape(height, width)
        stderr[..., c] = (env[c] * np.sqrt(np.maximum(var, 0.0) / spp)).reshape(height, width)
    return mean, stderr


# --------------------------------------------------------------------------------------------------
# General scenes: voxel grid in world space, box or SDF boundary, cameras / texels, emitters
# --------------------------------------------------------------------------------------------------
#
# Conventions (mm, sigma in mm^-1). The grid of D x H x W voxels with edges ``voxel_size = (sx, sy, sz)``
# occupies ``origin + [0, W sx] x [0, H sy] x [0, D sz]``; x <-> W index i, y <-> H index j, z <-> D
# index k. The *object* is either the grid box itself (``boundary="box"``) or the region where the
# trilinear interpolant of a corner SDF (shape (D+1, H+1, W+1), negative inside) is negative
# (``boundary="sdf"``). The medium counts only inside the object; outside is vacuum (n = 1).
#
# Algorithms chosen to be *different* from a fast tracer, and simple enough to be checked by eye:
#
# * SDF surfaces are found by **marching** along the ray and **bisecting** the first sign change of the
#   trilinear field (no cubic is solved). The march advances by ``sdf_step`` (default 1/64 of the smallest
#   voxel edge), or by the longer step ``|f| / L`` where that is longer: ``L`` bounds ``|df/dt|`` along the
#   ray (a Lipschitz bound of the trilinear interpolant), so such a step provably skips no sign change.
#   Roots are thus missed only where the field dips below zero and comes back within one ``sdf_step``
#   (grazing rays), exactly like a plain fixed-step march, which it merely speeds up far from the surface.
# * Free flights use **delta tracking** against one global majorant per channel; collisions are analog.
# * Dielectric boundaries use the **analog Fresnel coin** at the local angle.
# * Each channel is traced on its own; a path's value is 0 or the emitter radiance of its channel in its
#   final (escape) direction.

#: after a surface interaction the next search along the new direction starts this far away (mm), so the
#: root just handled is not found again
SURFACE_OFFSET = 1e-7
#: bisection stops when the bracket of a root is shorter than this (mm)
BISECTION_TOLERANCE = 1e-9


def _voxel_edges(voxel_size) -> np.ndarray:
    """``(sx, sy, sz)`` in mm from a scalar or a 3-sequence; all > 0."""
    edges = np.broadcast_to(np.asarray(voxel_size, dtype=np.float64), (3,)).copy()
    if not np.all(np.isfinite(edges)) or edges.min() <= 0:
        raise ValueError(f"voxel_size must be > 0, got {voxel_size}")
    return edges


def _normalise(v: np.ndarray) -> np.ndarray:
    """Rows of ``v`` scaled to unit length."""
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _cell_and_fraction(points: np.ndarray, origin: np.ndarray, edges: np.ndarray, dims: np.ndarray):
    """Cell ``floor((p - origin) / edge)`` clamped to ``[0, dims - 1]`` and the local coordinate within it.

    Args:
        points: world points, shape (N, 3), columns (x, y, z).
        origin, edges: grid origin and voxel edges, shape (3,).
        dims: number of cells along (x, y, z), i.e. ``(W, H, D)``.

    Returns:
        ``(cell, frac)``: integer cells (N, 3) in (i, j, k) order, and ``frac = local - cell`` (N, 3),
        in [0, 1] for points inside the grid (outside it, the clamped cell is extrapolated).
    """
    local = (points - origin) / edges
    cell = np.clip(np.floor(local).astype(np.int64), 0, dims - 1)
    return cell, local - cell


def _trilinear(sdf: np.ndarray, origin: np.ndarray, edges: np.ndarray, points: np.ndarray, want_gradient: bool):
    """Trilinear interpolation of corner values (see :func:`trilinear_sdf`); gradient only if asked."""
    dims = np.array([sdf.shape[2] - 1, sdf.shape[1] - 1, sdf.shape[0] - 1])  # cells along (x, y, z)
    cell, frac = _cell_and_fraction(points, origin, edges, dims)
    i, j, k = cell[:, 0], cell[:, 1], cell[:, 2]
    fx, fy, fz = frac[:, 0], frac[:, 1], frac[:, 2]
    # corner values c[dz][dy][dx]
    c = [[[sdf[k + dz, j + dy, i + dx] for dx in (0, 1)] for dy in (0, 1)] for dz in (0, 1)]
    # interpolate along x, then y, then z
    cx = [[c[dz][dy][0] * (1 - fx) + c[dz][dy][1] * fx for dy in (0, 1)] for dz in (0, 1)]
    cxy = [cx[dz][0] * (1 - fy) + cx[dz][1] * fy for dz in (0, 1)]
    value = cxy[0] * (1 - fz) + cxy[1] * fz
    if not want_gradient:
        return value, None
    # d/dfx: differences along x, then interpolated in y and z (and similarly for the other axes)
    ddx = [[c[dz][dy][1] - c[dz][dy][0] for dy in (0, 1)] for dz in (0, 1)]
    ddx_y = [ddx[dz][0] * (1 - fy) + ddx[dz][1] * fy for dz in (0, 1)]
    dfx = ddx_y[0] * (1 - fz) + ddx_y[1] * fz
    dfy = (cx[0][1] - cx[0][0]) * (1 - fz) + (cx[1][1] - cx[1][0]) * fz
    dfz = cxy[1] - cxy[0]
    gradient = np.stack([dfx, dfy, dfz], axis=1) / edges  # chain rule: frac = (p - origin) / edge
    return value, gradient


def trilinear_sdf(sdf: np.ndarray, origin, voxel_size, points: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """Trilinear SDF and its gradient at arbitrary world points.

    Corner ``(k, j, i)`` of ``sdf`` sits at ``origin + (i sx, j sy, k sz)``. A point belongs to the cell
    ``floor((p - origin) / voxel_size)`` clamped to the grid (so a point on a shared face belongs to the
    cell on its + side, and points outside the grid are extrapolated from the nearest border cell). With
    ``(fx, fy, fz)`` the local coordinates in that cell, the field is the trilinear interpolant of the
    cell's 8 corners and the gradient is its exact derivative (``d/dx = (d/dfx) / sx``, ...).

    Args:
        sdf: corner values, shape (D+1, H+1, W+1), mm.
        origin: grid origin, 3 values (mm).
        voxel_size: voxel edges ``(sx, sy, sz)`` or one edge (mm).
        points: world points, shape (N, 3) (x, y, z).

    Returns:
        ``(values, gradients)`` of shapes (N,) and (N, 3).
    """
    sdf = np.asarray(sdf, dtype=np.float64)
    points = np.atleast_2d(np.asarray(points, dtype=np.float64))
    origin = np.asarray(origin, dtype=np.float64).reshape(3)
    return _trilinear(sdf, origin, _voxel_edges(voxel_size), points, want_gradient=True)


def sdf_sphere(shape, voxel_size, origin, centre, radius: float) -> np.ndarray:
    """Corner SDF of a sphere: exact signed distance ``|x - centre| - radius`` at every voxel corner.

    Args:
        shape: the *voxel* grid shape ``(D, H, W)``; the result has one more corner per axis.
        voxel_size: voxel edges ``(sx, sy, sz)`` or one edge (mm).
        origin: grid origin, 3 values (mm).
        centre: sphere centre (mm, world).
        radius: sphere radius (mm).

    Returns:
        Array of shape (D+1, H+1, W+1), mm, negative inside.
    """
    depth, height, width = (int(v) for v in shape)
    edges = _voxel_edges(voxel_size)
    origin = np.asarray(origin, dtype=np.float64).reshape(3)
    centre = np.asarray(centre, dtype=np.float64).reshape(3)
    z = origin[2] + np.arange(depth + 1) * edges[2]
    y = origin[1] + np.arange(height + 1) * edges[1]
    x = origin[0] + np.arange(width + 1) * edges[0]
    zz, yy, xx = np.meshgrid(z, y, x, indexing="ij")
    return np.sqrt((xx - centre[0]) ** 2 + (yy - centre[1]) ** 2 + (zz - centre[2]) ** 2) - radius


def _slab_interval(pos: np.ndarray, d: np.ndarray, lo: np.ndarray, hi: np.ndarray):
    """Parametric interval ``[t_near, t_far]`` of the line ``pos + t d`` inside the box ``[lo, hi]``.

    Classic slab test: per axis with ``d_a != 0`` the line is between the two planes for t between
    ``(lo_a - p_a) / d_a`` and ``(hi_a - p_a) / d_a``; an axis with ``d_a = 0`` allows all t if
    ``lo_a <= p_a <= hi_a`` and none otherwise. The interval is empty when ``t_near > t_far``.

    Returns:
        ``(t_near, t_far, near_axis)``: arrays (N,), (N,) and the axis (N,) whose plane gives ``t_near``.
    """
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (lo - pos) / d
        t2 = (hi - pos) / d
    parallel = d == 0.0
    inside_slab = (pos >= lo) & (pos <= hi)
    t_min = np.where(parallel, np.where(inside_slab, -np.inf, np.inf), np.minimum(t1, t2))
    t_max = np.where(parallel, np.where(inside_slab, np.inf, -np.inf), np.maximum(t1, t2))
    near_axis = np.argmax(t_min, axis=1)
    rows = np.arange(len(pos))
    return t_min[rows, near_axis], t_max.min(axis=1), near_axis


def _box_entry(pos: np.ndarray, d: np.ndarray, lo: np.ndarray, hi: np.ndarray):
    """Distance at which a ray starting *outside* (or on) the box ``[lo, hi]`` enters it, ``inf`` if never.

    A ray enters when its slab interval is non-empty and starts ahead of it: ``0 <= t_near < t_far``. A
    ray on a face moving away from the box (``t_far = 0``) does not enter.

    Returns:
        ``(t_enter, axis)``: distances (N,) and the axis (N,) of the entry face.
    """
    t_near, t_far, axis = _slab_interval(pos, d, lo, hi)
    hit = (t_near >= 0.0) & (t_near < t_far)
    return np.where(hit, t_near, np.inf), axis


def _sdf_lipschitz(sdf: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """Per-axis bounds ``L_a >= |df/dx_a|`` of the trilinear interpolant anywhere in the grid.

    Inside a cell ``df/dx`` is a bilinear blend (weights in [0, 1] summing to 1) of the cell's four
    x-edge differences divided by ``sx``, so it never exceeds the largest ``|edge difference| / sx`` of the
    grid; likewise for y and z. Along a unit direction d, ``|df/dt| <= sum_a |d_a| L_a``.
    """
    lx = np.abs(np.diff(sdf, axis=2)).max() / edges[0]
    ly = np.abs(np.diff(sdf, axis=1)).max() / edges[1]
    lz = np.abs(np.diff(sdf, axis=0)).max() / edges[2]
    return np.array([lx, ly, lz])


def _march_sign_change(
    sdf: np.ndarray,
    origin: np.ndarray,
    edges: np.ndarray,
    lipschitz: np.ndarray,
    pos: np.ndarray,
    d: np.ndarray,
    t_lo: np.ndarray,
    t_hi: np.ndarray,
    want_negative: np.ndarray,
    step: float,
) -> np.ndarray:
    """First distance in ``[t_lo, t_hi]`` along each ray where the SDF has the wanted sign.

    The wanted sign is ``f < 0`` (entering the object) where ``want_negative`` and ``f >= 0`` (leaving it)
    elsewhere. Samples ``t_0 = t_lo, t_1, ...`` advance by ``max(step, 0.999 |f| / L_d)`` (``L_d`` the
    Lipschitz bound along the ray, so a longer step provably crosses no root), capped at ``t_hi`` which
    is always sampled. If the very first sample already has the wanted sign, the crossing is at ``t_lo``;
    otherwise the first sign change between samples ``t_{m-1}, t_m`` is bisected until the bracket is
    shorter than :data:`BISECTION_TOLERANCE`, and its midpoint is returned.

    Returns:
        Distances, shape (N,), ``inf`` where no sample in ``[t_lo, t_hi]`` has the wanted sign.
    """
    n = len(pos)
    t_hit = np.full(n, np.inf)
    idx = np.nonzero(t_lo <= t_hi)[0]
    t = t_lo[idx].astype(np.float64)
    t_prev = np.full(idx.size, np.nan)  # nan: no previous sample yet
    lip_d = np.abs(d[idx]) @ lipschitz
    bracket_idx, bracket_a, bracket_b = [], [], []
    while idx.size:
        f, _ = _trilinear(sdf, origin, edges, pos[idx] + t[:, None] * d[idx], want_gradient=False)
        on_target = (f < 0.0) == want_negative[idx]
        first = np.isnan(t_prev)
        immediate = on_target & first
        t_hit[idx[immediate]] = t[immediate]
        found = on_target & ~first
        bracket_idx.append(idx[found])
        bracket_a.append(t_prev[found])
        bracket_b.append(t[found])
        go_on = ~on_target & (t < t_hi[idx])
        idx, t, f, lip_d = idx[go_on], t[go_on], f[go_on], lip_d[go_on]
        with np.errstate(divide="ignore"):
            safe = np.where(lip_d > 0.0, 0.999 * np.abs(f) / lip_d, np.inf)
        t_prev = t
        t = np.minimum(t + np.maximum(step, safe), t_hi[idx])

    b_idx = np.concatenate(bracket_idx)
    if b_idx.size:
        ta, tb = np.concatenate(bracket_a), np.concatenate(bracket_b)  # f(ta): old side, f(tb): new side
        want = want_negative[b_idx]
        while np.max(tb - ta) > BISECTION_TOLERANCE:
            tm = 0.5 * (ta + tb)
            f, _ = _trilinear(sdf, origin, edges, pos[b_idx] + tm[:, None] * d[b_idx], want_gradient=False)
            new_side = (f < 0.0) == want
            tb = np.where(new_side, tm, tb)
            ta = np.where(new_side, ta, tm)
        t_hit[b_idx] = 0.5 * (ta + tb)
    return t_hit


def _dielectric_event(d: np.ndarray, n_out: np.ndarray, inside: np.ndarray, ior: float, xi: np.ndarray):
    """Analog Fresnel choice at a smooth dielectric surface: reflect with probability F, else refract.

    The normal is flipped to face the incoming ray, ``n_f = -sign(d . n_out) n_out``, and
    ``cos_i = -d . n_f >= 0``. The relative index seen from the incident side is ``eta = ior`` from inside
    and ``1 / ior`` from outside. Reflection: ``d + 2 cos_i n_f``. Refraction (Snell, vector form):
    ``eta d + (eta cos_i - cos_t) n_f`` with ``cos_t = sqrt(1 - eta^2 (1 - cos_i^2))``. Total internal
    reflection is ``F = 1``.

    Args:
        d: incoming unit directions (N, 3).
        n_out: outward unit normals (N, 3).
        inside: whether each path arrives from inside the object (N,).
        ior: index of the object.
        xi: uniform numbers (N,) for the coin.

    Returns:
        ``(new_d, reflected)``: unit directions (N, 3) and the boolean mask of reflected paths (N,).
    """
    dn = np.sum(d * n_out, axis=1)
    n_f = np.where((dn > 0.0)[:, None], -n_out, n_out)
    cos_i = np.abs(dn)
    eta = np.where(inside, ior, 1.0 / ior)
    f = np.empty(len(d))
    f[inside] = fresnel_dielectric(cos_i[inside], ior)
    f[~inside] = fresnel_dielectric(cos_i[~inside], 1.0 / ior)
    reflected = xi < f
    sin2_t = eta * eta * (1.0 - cos_i * cos_i)
    cos_t = np.sqrt(np.clip(1.0 - sin2_t, 0.0, 1.0))
    refl = d + (2.0 * cos_i)[:, None] * n_f
    refr = eta[:, None] * d + (eta * cos_i - cos_t)[:, None] * n_f
    return _normalise(np.where(reflected[:, None], refl, refr)), reflected


# ---- emitters ---------------------------------------------------------------------------------------


def evaluate_emitter(emitter: dict, d: np.ndarray) -> np.ndarray:
    """Radiance (linear RGB) that an escaping path sees in its final world direction ``d``.

    * ``{"kind": "constant", "radiance": L}``: L (scalar or 3 values) in every direction.
    * ``{"kind": "envmap", "image": E}``: E of shape (Hm, Wm, 3), lat-long with z up:
      ``theta = arccos(d_z)``, ``phi = atan2(d_y, d_x)``, continuous pixel coordinates
      ``x = (phi / 2pi mod 1) Wm - 0.5`` (columns) and ``y = (theta / pi) Hm - 0.5`` (rows); bilinear between
      pixel centres, columns wrap around (column -1 is column Wm - 1), rows clamp to [0, Hm - 1].
    * ``{"kind": "disc", "direction": w, "angle_deg": delta, "radiance": L, "ambient": A}``: distant disc
      towards ``w`` (normalised here) of angular radius delta: ``L + A`` where ``d . w >= cos(delta)``,
      else ``A`` (``ambient`` defaults to 0).

    Args:
        emitter: one of the dictionaries above.
        d: unit directions, shape (N, 3).

    Returns:
        Radiance, shape (N, 3).
    """
    d = np.atleast_2d(np.asarray(d, dtype=np.float64))
    kind = emitter.get("kind")
    if kind == "constant":
        radiance = np.broadcast_to(np.asarray(emitter["radiance"], dtype=np.float64), (3,))
        return np.broadcast_to(radiance, (len(d), 3)).copy()
    if kind == "envmap":
        image = np.asarray(emitter["image"], dtype=np.float64)
        if image.ndim != 3 or image.shape[2] != 3:
            raise ValueError(f"envmap image must have shape (Hm, Wm, 3), got {image.shape}")
        hm, wm = image.shape[:2]
        theta = np.arccos(np.clip(d[:, 2], -1.0, 1.0))
        phi = np.arctan2(d[:, 1], d[:, 0])
        x = np.mod(phi / (2.0 * math.pi), 1.0) * wm - 0.5
        y = np.clip(theta / math.pi * hm - 0.5, 0.0, hm - 1.0)
        x0 = np.floor(x).astype(np.int64)
        fx = (x - x0)[:, None]
        c0, c1 = np.mod(x0, wm), np.mod(x0 + 1, wm)
        y0 = np.clip(np.floor(y).astype(np.int64), 0, max(hm - 2, 0))
        fy = (y - y0)[:, None]
        y1 = np.minimum(y0 + 1, hm - 1)
        top = image[y0, c0] * (1.0 - fx) + image[y0, c1] * fx
        bottom = image[y1, c0] * (1.0 - fx) + image[y1, c1] * fx
        return top * (1.0 - fy) + bottom * fy
    if kind == "disc":
        w = np.asarray(emitter["direction"], dtype=np.float64).reshape(3)
        w = w / np.linalg.norm(w)
        cos_delta = math.cos(math.radians(float(emitter["angle_deg"])))
        radiance = np.broadcast_to(np.asarray(emitter["radiance"], dtype=np.float64), (3,))
        ambient = np.broadcast_to(np.asarray(emitter.get("ambient", 0.0), dtype=np.float64), (3,))
        in_cone = (d @ w) >= cos_delta
        return np.where(in_cone[:, None], radiance + ambient, ambient)
    raise ValueError(f"unknown emitter kind {kind!r} (expected 'constant', 'envmap' or 'disc')")


# ---- sensors ----------------------------------------------------------------------------------------


def sensor_output_shape(sensor: dict) -> Tuple[int, ...]:
    """Shape of the sensor's output without the RGB axis: ``(N,)`` for texels, ``(rows, cols)`` for cameras."""
    kind = sensor.get("kind")
    if kind == "surface_texels":
        return (len(np.atleast_2d(sensor["points"])),)
    if kind in ("orthographic", "perspective"):
        rows, cols = (int(v) for v in sensor["resolution"])
        return (rows, cols)
    raise ValueError(f"unknown sensor kind {kind!r} (expected 'surface_texels', 'orthographic' or 'perspective')")


def _camera_frame(sensor: dict) -> Tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(o, f, right, up')``: ``f = normalise(target - o)``, ``right = normalise(f x up)``, ``up' = right x f``."""
    o = np.asarray(sensor["origin"], dtype=np.float64).reshape(3)
    f = np.asarray(sensor["target"], dtype=np.float64).reshape(3) - o
    f /= np.linalg.norm(f)
    right = np.cross(f, np.asarray(sensor["up"], dtype=np.float64).reshape(3))
    right /= np.linalg.norm(right)
    return o, f, right, np.cross(right, f)


def sensor_rays(sensor: dict, element: np.ndarray, xi1: np.ndarray, xi2: np.ndarray, voxel_size):
    """Ray origins and unit directions of the samples ``element`` (flat output index) with numbers ``xi``.

    * ``{"kind": "surface_texels", "points": P (N, 3), "normals": Nrm (N, 3), "radius": r (N,)}``: a point
      uniform in the disc of radius r around P in the tangent plane of Nrm (radius ``r sqrt(xi1)``, angle
      ``2 pi xi2``, frame of :func:`_orthonormal_frame`), lifted to ``q = point + Nrm h`` with
      ``h = 2 max(voxel edges)``; direction ``-Nrm``.
    * ``{"kind": "orthographic", "origin": o, "target": t, "up": u, "extent": (width, height),
      "resolution": (rows, cols)}``: pixel ``(r, c)`` = element ``r cols + c``; origin
      ``o + right ((c + xi1) / cols - 1/2) width + up' (1/2 - (r + xi2) / rows) height``, direction f.
    * ``{"kind": "perspective", "origin": o, "target": t, "up": u, "fov_y_deg": fov,
      "resolution": (rows, cols)}``: ``tan_h = tan(fov / 2)``, ``aspect = cols / rows``,
      ``x = (2 (c + xi1) / cols - 1) tan_h aspect``, ``y = (1 - 2 (r + xi2) / rows) tan_h``, direction
      ``normalise(f + x right + y up')``, origin o.

    Args:
        sensor: one of the dictionaries above.
        element: flat output indices, shape (N,).
        xi1, xi2: numbers in [0, 1), shape (N,).
        voxel_size: voxel edges (for the texel lift h).

    Returns:
        ``(origins, directions)``, each (N, 3).
    """
    element = np.asarray(element, dtype=np.int64)
    xi1 = np.asarray(xi1, dtype=np.float64)
    xi2 = np.asarray(xi2, dtype=np.float64)
    kind = sensor.get("kind")
    if kind == "surface_texels":
        points = np.atleast_2d(np.asarray(sensor["points"], dtype=np.float64))
        normals = _normalise(np.atleast_2d(np.asarray(sensor["normals"], dtype=np.float64)))
        radius = np.broadcast_to(np.asarray(sensor["radius"], dtype=np.float64), (len(points),))
        nrm = normals[element]
        t1, t2 = _orthonormal_frame(nrm)
        rho = radius[element] * np.sqrt(xi1)
        ang = 2.0 * math.pi * xi2
        point = points[element] + (rho * np.cos(ang))[:, None] * t1 + (rho * np.sin(ang))[:, None] * t2
        lift = 2.0 * _voxel_edges(voxel_size).max()
        return point + lift * nrm, -nrm
    rows, cols = sensor_output_shape(sensor)
    o, f, right, up = _camera_frame(sensor)
    r = element // cols
    c = element % cols
    if kind == "orthographic":
        width, height = (float(v) for v in sensor["extent"])
        a = ((c + xi1) / cols - 0.5) * width
        b = (0.5 - (r + xi2) / rows) * height
        origins = o + a[:, None] * right + b[:, None] * up
        return origins, np.broadcast_to(f, origins.shape).copy()
    if kind == "perspective":
        tan_h = math.tan(math.radians(float(sensor["fov_y_deg"])) / 2.0)
        aspect = cols / rows
        x = (2.0 * (c + xi1) / cols - 1.0) * tan_h * aspect
        y = (1.0 - 2.0 * (r + xi2) / rows) * tan_h
        dirs = _normalise(f + x[:, None] * right + y[:, None] * up)
        return np.broadcast_to(o, dirs.shape).copy(), dirs
    raise ValueError(f"unknown sensor kind {kind!r}")


# ---- the walk ---------------------------------------------------------------------------------------


def _trace_scene_channel(
    sigma: np.ndarray,
    albedo: np.ndarray,
    *,
    origin: np.ndarray,
    edges: np.ndarray,
    boundary: str,
    sdf: Optional[np.ndarray],
    lipschitz: Optional[np.ndarray],
    sdf_step: float,
    g: float,
    ior: Optional[float],
    ray_o: np.ndarray,
    ray_d: np.ndarray,
    max_depth: int,
    rng: np.random.Generator,
    counters: dict,
) -> Tuple[np.ndarray, np.ndarray]:
    """Walk all paths of one channel from their camera rays until they escape or die.

    Every path is in one of two states: *outside* (in vacuum, looking for the object's surface) or
    *inside* (in the medium). One event per alive path and iteration:

    * outside: find the surface ahead (box: slab entry; SDF: march to ``f < 0`` within the grid). None:
      the path escapes in its direction d. Otherwise a surface event.
    * inside: sample a free flight ``t ~ Exp(majorant)`` and look for the exit ahead (box: analytic slab
      exit; SDF: march to ``f >= 0`` up to ``t``). The exit comes first (``t_exit <= t``): a surface event;
      otherwise a collision at ``t``: real with probability ``sigma / majorant`` (voxel by floor of the
      local coordinate), which scatters (HG) with probability albedo and otherwise absorbs the path (value
      0). Null collisions change nothing.
    * surface event at the crossing point with the outward normal there (box: the face's axis; SDF: the
      normalised trilinear gradient): index matched, the path just changes state; dielectric, the analog
      Fresnel coin reflects it (same state) or refracts it (other state). SDF searches after a surface
      event start at :data:`SURFACE_OFFSET`.

    ``max_depth`` counts real scatterings and internal reflections (those of paths inside, TIR included);
    a path exceeding it is dropped with value 0.

    Safety net: a path with more than ``4 (W + H + D) + 16`` surface events in a row (refractions,
    index-matched crossings and external reflections; a collision or an internal reflection resets the
    streak) is dropped with value 0 and counted as ``stuck``. A straight line crosses the trilinear zero set
    at most 3 times per cell, so a physical path cannot get there unless it bounces between outside lobes
    with probability ~F^k; the streak only guards against endless inside/outside flips at one spot, which
    inconsistent normals (never seen in the tests) could otherwise cause.

    Returns:
        ``(escaped, direction)``: mask (N,) of paths that escaped and their final directions (N, 3).
    """
    depth_k, height, width = sigma.shape
    dims = np.array([width, height, depth_k])
    lo = origin
    hi = origin + dims * edges
    majorant = float(sigma.max())
    n_paths = len(ray_o)
    escaped = np.zeros(n_paths, dtype=bool)
    escape_dir = np.zeros((n_paths, 3))

    pid = np.arange(n_paths)
    pos = ray_o.astype(np.float64).copy()
    d = ray_d.astype(np.float64).copy()
    inside = np.zeros(n_paths, dtype=bool)
    offset = np.zeros(n_paths, dtype=bool)  # start the next SDF search at SURFACE_OFFSET
    depth = np.zeros(n_paths, dtype=np.int64)
    streak = np.zeros(n_paths, dtype=np.int64)  # surface events since the last collision / internal reflection
    max_streak = 4 * int(dims.sum()) + 16
    iterations = 0
    while pid.size:
        iterations += 1
        if iterations > 100_000_000:
            raise RuntimeError("reference tracer: event loop did not terminate")
        n = pid.size
        counters["events"] += n
        t_free = np.full(n, np.inf)
        n_in = int(inside.sum())
        if majorant > 0.0:
            t_free[inside] = -np.log1p(-rng.random(n_in)) / majorant
        axis = np.zeros(n, dtype=np.int64)  # box face of the crossing
        if boundary == "box":
            t_surf = np.full(n, np.inf)
            out = ~inside
            t_surf[out], axis[out] = _box_entry(pos[out], d[out], lo, hi)
            t_surf[inside], axis[inside] = distance_to_box_exit(pos[inside] - lo, d[inside], hi - lo)
        else:
            t_in, t_out, _ = _slab_interval(pos, d, lo, hi)  # the part of the ray inside the grid
            t_start = np.where(offset, SURFACE_OFFSET, 0.0)
            t_lo = np.where(inside, t_start, np.maximum(t_start, t_in))
            t_hi = np.where(inside, np.minimum(t_free, t_out), t_out)
            t_surf = _march_sign_change(sdf, origin, edges, lipschitz, pos, d, t_lo, t_hi, ~inside, sdf_step)
            lost = inside & ~(t_surf <= t_hi) & (t_free > t_out)
            if lost.any():
                raise RuntimeError("reference tracer: a path inside the SDF object found no exit in the grid")
        crossing = np.isfinite(t_surf) & (t_surf <= t_free)  # a surface ahead, before the collision
        alive = np.ones(n, dtype=bool)

        # ---- escapes: outside with no surface ahead ----
        esc = np.nonzero(~inside & ~crossing)[0]
        escaped[pid[esc]] = True
        escape_dir[pid[esc]] = d[esc]
        alive[esc] = False
        counters["escaped"] += esc.size

        # ---- surface events ----
        s = np.nonzero(crossing)[0]
        if s.size:
            counters["surface_events"] += s.size
            ps = pos[s] + t_surf[s, None] * d[s]
            if boundary == "box":
                ax = axis[s]
                rows = np.arange(s.size)
                ps = np.clip(ps, lo, hi)
                # the + face is the one a path leaves by moving in +, or enters by moving in -
                plus_face = (d[s, ax] > 0.0) == inside[s]
                ps[rows, ax] = np.where(plus_face, hi[ax], lo[ax])  # exactly on the face
                sign_out = np.where(plus_face, 1.0, -1.0)
                n_out = np.zeros((s.size, 3))
                n_out[rows, ax] = sign_out
            else:
                _, grad = _trilinear(sdf, origin, edges, ps, want_gradient=True)
                norm = np.linalg.norm(grad, axis=1)
                degenerate = ~(norm > 0.0)  # vanishing gradient: treat as normal incidence
                n_out = grad / np.where(degenerate, 1.0, norm)[:, None]
                fallback = np.where(inside[s, None], d[s], -d[s])
                n_out[degenerate] = fallback[degenerate]
            pos[s] = ps
            offset[s] = True
            streak[s] += 1
            if ior is None:
                inside[s] = ~inside[s]
            else:
                new_d, reflected = _dielectric_event(d[s], n_out, inside[s], ior, rng.random(s.size))
                d[s] = new_d
                counters["reflections"] += int(reflected.sum())
                internal = s[reflected & inside[s]]
                streak[internal] = 0
                depth[internal] += 1
                truncated = internal[depth[internal] > max_depth]
                alive[truncated] = False
                counters["truncated"] += truncated.size
                refracted = s[~reflected]
                inside[refracted] = ~inside[refracted]
            stuck = s[streak[s] > max_streak]
            alive[stuck] = False
            counters["stuck"] += stuck.size

        # ---- collisions inside the medium ----
        c = np.nonzero(inside & ~crossing)[0]
        if c.size:
            pc = pos[c] + t_free[c, None] * d[c]
            pos[c] = pc
            offset[c] = False
            streak[c] = 0
            cell, _ = _cell_and_fraction(pc, origin, edges, dims)
            sig = sigma[cell[:, 2], cell[:, 1], cell[:, 0]]
            alb = albedo[cell[:, 2], cell[:, 1], cell[:, 0]]
            real = rng.random(c.size) * majorant < sig
            scatters = real & (rng.random(c.size) < alb)
            absorbed = c[real & ~scatters]
            alive[absorbed] = False
            counters["absorbed"] += absorbed.size
            sc = c[scatters]
            if sc.size:
                counters["scatterings"] += sc.size
                depth[sc] += 1
                truncated = sc[depth[sc] > max_depth]
                alive[truncated] = False
                counters["truncated"] += truncated.size
                sc = sc[depth[sc] <= max_depth]
                d[sc] = sample_henyey_greenstein(d[sc], g, rng.random(sc.size), rng.random(sc.size))

        pid, pos, d = pid[alive], pos[alive], d[alive]
        inside, offset, depth, streak = inside[alive], offset[alive], depth[alive], streak[alive]
    return escaped, escape_dir


def reference_render_scene(
    sigma_t: np.ndarray,
    albedo: np.ndarray,
    *,
    voxel_size,
    origin=(0.0, 0.0, 0.0),
    g: float = 0.0,
    boundary: str = "box",
    sdf: Optional[np.ndarray] = None,
    ior: Optional[float] = None,
    sensor: dict,
    emitter: dict,
    spp: int = 1024,
    rng: Optional[np.random.Generator] = None,
    max_depth: int = 100000,
    sdf_step: Optional[float] = None,
    diagnostics: Optional[dict] = None,
) -> Tuple[np.ndarray, np.ndarray]:
    """Reference Monte Carlo render of a general scene (voxel medium in a box or SDF object).

    Every sample of an output element is one camera ray (:func:`sensor_rays`, fresh jitter per channel),
    walked by :func:`_trace_scene_channel`; its value is the emitter radiance of the channel in the
    path's final direction (:func:`evaluate_emitter`) if it escapes, and 0 if it is absorbed or truncated.
    Rays missing the object see the emitter in their own direction.

    Args:
        sigma_t: extinction, shape (3, D, H, W), mm^-1, >= 0 (channel-planar linear RGB).
        albedo: single-scattering albedo, shape (3, D, H, W), in [0, 1].
        voxel_size: voxel edges ``(sx, sy, sz)`` or one edge, mm.
        origin: world position of the grid corner ``(i, j, k) = (0, 0, 0)``, mm.
        g: Henyey-Greenstein parameter in [-1, 1].
        boundary: ``"box"`` (the object is the grid box) or ``"sdf"`` (the object is where the trilinear
            interpolant of ``sdf`` is negative).
        sdf: corner SDF, shape (D+1, H+1, W+1), mm, > 0 on every outer corner of the grid (object strictly
            inside the grid); required for ``boundary="sdf"``.
        ior: index of the object (>= 1), or ``None`` for an index-matched boundary.
        sensor: see :func:`sensor_rays`.
        emitter: see :func:`evaluate_emitter`.
        spp: samples per output element and channel (>= 2).
        rng: numpy random generator (consumed); ``None``: ``default_rng(0)``.
        max_depth: maximum number of interactions (real scatterings plus internal reflections); paths
            exceeding it contribute 0.
        sdf_step: largest step of the SDF march near the surface, mm; default ``min(voxel edges) / 64``.
        diagnostics: if a dict is given, event counts summed over the channels are stored in it
            (``events``, ``escaped``, ``absorbed``, ``truncated``, ``stuck`` (see
            :func:`_trace_scene_channel`; should be 0), ``scatterings``, ``surface_events``, ``reflections``).

    Returns:
        ``(mean, stderr)``, each of shape ``sensor_output_shape(sensor) + (3,)``: the per-element sample
        mean over the spp samples and its standard error (sample standard deviation with ddof=1 divided
        by ``sqrt(spp)``).

    Raises:
        ValueError: on shapes or values outside the ranges above.
    """
    sigma_t, albedo = _check_medium(sigma_t, albedo)
    if not -1.0 <= g <= 1.0:
        raise ValueError(f"g must lie in [-1, 1], got {g}")
    if ior is not None and ior < 1.0:
        raise ValueError(f"ior must be None or >= 1, got {ior}")
    if spp < 2:
        raise ValueError(f"spp must be >= 2 (for a standard error), got {spp}")
    edges = _voxel_edges(voxel_size)
    origin = np.asarray(origin, dtype=np.float64).reshape(3)
    _, depth_k, height, width = sigma_t.shape
    lipschitz = None
    if boundary == "sdf":
        if sdf is None:
            raise ValueError("boundary='sdf' needs an sdf array")
        sdf = np.asarray(sdf, dtype=np.float64)
        if sdf.shape != (depth_k + 1, height + 1, width + 1):
            raise ValueError(f"sdf must have shape {(depth_k + 1, height + 1, width + 1)}, got {sdf.shape}")
        outer = np.ones(sdf.shape, dtype=bool)
        outer[1:-1, 1:-1, 1:-1] = False
        if not np.all(np.isfinite(sdf)) or not np.all(sdf[outer] > 0.0):
            raise ValueError("sdf must be finite and > 0 on every outer corner of the grid")
        lipschitz = _sdf_lipschitz(sdf, edges)
    elif boundary != "box":
        raise ValueError(f"boundary must be 'box' or 'sdf', got {boundary!r}")
    if sdf_step is None:
        sdf_step = float(edges.min()) / 64.0
    if rng is None:
        rng = np.random.default_rng(0)

    out_shape = sensor_output_shape(sensor)
    n_elements = int(np.prod(out_shape))
    element = np.repeat(np.arange(n_elements), spp)  # element-major samples
    counters = dict(events=0, escaped=0, absorbed=0, truncated=0, stuck=0, scatterings=0, surface_events=0,
                    reflections=0)
    mean = np.empty((n_elements, 3))
    stderr = np.empty((n_elements, 3))
    for c in range(3):
        ray_o, ray_d = sensor_rays(sensor, element, rng.random(element.size), rng.random(element.size), edges)
        escaped, direction = _trace_scene_channel(
            sigma_t[c], albedo[c], origin=origin, edges=edges, boundary=boundary, sdf=sdf, lipschitz=lipschitz,
            sdf_step=sdf_step, g=g, ior=ior, ray_o=ray_o, ray_d=ray_d, max_depth=max_depth, rng=rng,
            counters=counters,
        )
        value = np.zeros(element.size)
        if escaped.any():
            value[escaped] = evaluate_emitter(emitter, direction[escaped])[:, c]
        total = np.bincount(element, weights=value, minlength=n_elements)
        total_sq = np.bincount(element, weights=value * value, minlength=n_elements)
        m = total / spp
        var = (total_sq - spp * m * m) / (spp - 1)
        mean[:, c] = m
        stderr[:, c] = np.sqrt(np.maximum(var, 0.0) / spp)
    if diagnostics is not None:
        diagnostics.update(counters)
    return mean.reshape(out_shape + (3,)), stderr.reshape(out_shape + (3,))


if __name__ == "__main__":  # smoke test + timing
    import time

    rng = np.random.default_rng(1)
    sig = rng.uniform(0.5, 30.0, (3, 3, 4, 4))
    alb = rng.uniform(0.3, 0.999, (3, 3, 4, 4))
    t0 = time.perf_counter()
    m, e = reference_render_texels(sig, alb, voxel_size=0.1, g=0.4, ior=1.5, spp=20000)
    print(f"{time.perf_counter() - t0:.2f} s")
    print(m[..., 0], e[..., 0].max())

    shape, s = (8, 8, 8), 0.1
    centre = np.array([0.41, 0.39, 0.42])
    cam = dict(kind="perspective", origin=centre + np.array([1.5, 0.4, 0.7]), target=centre, up=(0, 0, 1),
               fov_y_deg=30.0, resolution=(4, 4))
    t0 = time.perf_counter()
    m, e = reference_render_scene(
        sig[:, :1].repeat(8, axis=1).repeat(2, axis=2).repeat(2, axis=3), np.full((3,) + shape, 0.9),
        voxel_size=s, g=0.4, boundary="sdf", sdf=sdf_sphere(shape, s, (0, 0, 0), centre, 0.3), ior=1.5,
        sensor=cam, emitter=dict(kind="envmap", image=rng.uniform(0, 2, (8, 16, 3))), spp=500, rng=rng,
    )
    print(f"{time.perf_counter() - t0:.2f} s")
    print(m[..., 0], e[..., 0].max())
