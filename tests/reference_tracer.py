"""Slow, obviously-correct numpy reference for the volume path tracer (tests only).

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

Run the module directly for a quick smoke test::

    python tests/reference_tracer.py
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


if __name__ == "__main__":  # smoke test + timing
    import time

    rng = np.random.default_rng(1)
    sig = rng.uniform(0.5, 30.0, (3, 3, 4, 4))
    alb = rng.uniform(0.3, 0.999, (3, 3, 4, 4))
    t0 = time.perf_counter()
    m, e = reference_render_texels(sig, alb, voxel_size=0.1, g=0.4, ior=1.5, spp=20000)
    print(f"{time.perf_counter() - t0:.2f} s")
    print(m[..., 0], e[..., 0].max())
