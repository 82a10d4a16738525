"""Checks of the general-scene numpy reference (``reference_render_scene`` in
torch_appearance/testing/reference_tracer.py).

The general-scene reference will judge the fast C++ tracer on SDF objects, cameras and emitters, so it is
checked here against results obtained independently of its own code paths:

* white furnace on a dielectric SDF sphere (every path escapes: every value is exactly the emitter);
* Beer-Lambert through an index-matched SDF sphere, with the optical depth along each ray computed by an
  independent exact root finder (the trilinear field restricted to a ray is a cubic in every cell);
* an SDF whose zero set is the grid's inner box reproduces the existing box reference
  (``reference_render_texels``), and so does ``boundary="box"``;
* the emitters and the camera / texel ray generators against their formulas.

Monte Carlo results are z-tested with a Bonferroni-corrected threshold (family-wise false-alarm rate
``ALPHA`` per test function). The threshold is computed here with scipy (no import of conftest, which
needs the compiled extension).
"""

import math

import numpy as np
import pytest
from scipy import stats

from torch_appearance.testing.reference_tracer import (
    _march_sign_change,
    _sdf_lipschitz,
    evaluate_emitter,
    reference_render_scene,
    reference_render_texels,
    sdf_sphere,
    sensor_rays,
    trilinear_sdf,
)

ALPHA = 1e-3  # family-wise false-alarm probability of every statistical test below


def z_threshold(n_tests: int, alpha: float = ALPHA) -> float:
    """Two-sided per-test |z| threshold for ``n_tests`` tests at family-wise level ``alpha`` (Bonferroni)."""
    return float(stats.norm.isf(alpha / (2.0 * n_tests)))


def assert_z(estimate, stderr, expected, expected_stderr=0.0, tolerance=0.0, n_tests=None):
    """Assert ``(|estimate - expected| - tolerance)+ / sqrt(stderr^2 + expected_stderr^2)`` is below threshold.

    ``tolerance`` is a deterministic bound on the error of ``expected`` (e.g. quadrature), subtracted
    before the test. Returns the largest |z| (of the raw difference, without the tolerance).
    """
    estimate, stderr, expected, expected_stderr, tolerance = np.broadcast_arrays(
        *map(np.asarray, (estimate, stderr, expected, expected_stderr, tolerance)))
    se = np.sqrt(stderr**2 + expected_stderr**2)
    assert np.all(se > 0), "a standard error of 0 cannot be z-tested"
    diff = np.abs(estimate - expected)
    z = np.maximum(diff - tolerance, 0.0) / se
    threshold = z_threshold(z.size if n_tests is None else n_tests)
    worst = np.unravel_index(z.argmax(), z.shape)
    assert z.max() < threshold, (
        f"max |z| = {z.max():.2f} >= {threshold:.2f} at {worst}: estimate {estimate[worst]:.6g} "
        f"± {se[worst]:.3g}, expected {expected[worst]:.6g} (tolerance {tolerance[worst]:.3g})")
    return float((diff / se).max())


# ---------------------------------------------------------------------------------------------------
# An independent exact optical-depth finder for one ray (for Beer-Lambert)
# ---------------------------------------------------------------------------------------------------


def _field(sdf, origin, edges, p):
    """Trilinear corner field at one point (scalar code, written separately from the reference)."""
    u = (np.asarray(p) - origin) / edges
    cells = np.array([sdf.shape[2] - 1, sdf.shape[1] - 1, sdf.shape[0] - 1])
    i, j, k = (min(max(int(math.floor(u[a])), 0), cells[a] - 1) for a in range(3))
    fx, fy, fz = u[0] - i, u[1] - j, u[2] - k
    total = 0.0
    for dz, wz in ((0, 1 - fz), (1, fz)):
        for dy, wy in ((0, 1 - fy), (1, fy)):
            for dx, wx in ((0, 1 - fx), (1, fx)):
                total += wx * wy * wz * sdf[k + dz, j + dy, i + dx]
    return total


def _negative_intervals(sigma, sdf, origin, edges, o, d):
    """Intervals of t where the line ``o + t d`` is inside the object (trilinear field < 0), with sigma.

    The line is cut at every grid plane it crosses, so every piece lies in one cell, where the trilinear
    field restricted to the line is a cubic polynomial in t: it is recovered exactly from 4 samples
    (interpolation in a normalised variable) and its real roots in the piece are found by ``np.roots``.
    Between consecutive roots the sign is constant and is read off the cubic at the midpoint. No marching,
    no bisection.

    Returns:
        List of ``(t_a, t_b, sigma_cell)`` (sigma of the piece's cell, shape (3,)), in increasing t.
    """
    dims = np.array([sigma.shape[3], sigma.shape[2], sigma.shape[1]])
    lo, hi = origin, origin + dims * edges
    t_near, t_far = -np.inf, np.inf
    for a in range(3):
        t1, t2 = (lo[a] - o[a]) / d[a], (hi[a] - o[a]) / d[a]  # the tests use rays with all d_a != 0
        t_near, t_far = max(t_near, min(t1, t2)), min(t_far, max(t1, t2))
    cuts = [t_near, t_far]
    for a in range(3):
        for m in range(dims[a] + 1):
            t = (lo[a] + m * edges[a] - o[a]) / d[a]
            if t_near < t < t_far:
                cuts.append(t)
    cuts = np.sort(cuts)
    intervals = []
    nodes = np.array([0.1, 0.4, 0.6, 0.9])
    for ta, tb in zip(cuts[:-1], cuts[1:]):
        if tb - ta < 1e-12:
            continue
        values = [_field(sdf, origin, edges, o + (ta + x * (tb - ta)) * d) for x in nodes]
        coeffs = np.polyfit(nodes, values, 3)  # exact interpolation of the cubic
        roots = np.roots(coeffs) if np.any(coeffs[:-1] != 0) else np.array([])
        real = np.sort(roots[(np.abs(roots.imag) < 1e-9) & (roots.real > 0) & (roots.real < 1)].real)
        breaks = np.concatenate([[0.0], real, [1.0]])
        mid_cell = o + 0.5 * (ta + tb) * d
        i, j, k = (int(v) for v in np.clip(np.floor((mid_cell - origin) / edges), 0, dims - 1))
        for xa, xb in zip(breaks[:-1], breaks[1:]):
            if np.polyval(coeffs, 0.5 * (xa + xb)) < 0:
                intervals.append((ta + xa * (tb - ta), ta + xb * (tb - ta), sigma[:, k, j, i]))
    return intervals


def _optical_depth_exact(sigma, sdf, origin, edges, o, d):
    """Optical depth per channel (3,) and geometric chord length of the line through the object."""
    tau, chord = np.zeros(3), 0.0
    for ta, tb, sig in _negative_intervals(sigma, sdf, origin, edges, o, d):
        tau += sig * (tb - ta)
        chord += tb - ta
    return tau, chord


def _sphere_scene():
    """8^3 grid with anisotropic voxels, offset origin, an SDF sphere strictly inside, heterogeneous sigma."""
    edges = np.array([0.1, 0.09, 0.11])
    origin = np.array([-0.3, 0.2, 1.0])
    shape = (8, 8, 8)
    centre = origin + np.array([0.41, 0.37, 0.45])
    radius = 0.28
    sdf = sdf_sphere(shape, edges, origin, centre, radius)
    return edges, origin, shape, centre, radius, sdf


# ---------------------------------------------------------------------------------------------------
# Building blocks
# ---------------------------------------------------------------------------------------------------


def test_trilinear_sdf_and_sphere_grid():
    """Corner values are reproduced, affine fields are exact, the gradient matches finite differences."""
    edges, origin, shape, centre, radius, sdf = _sphere_scene()
    d_, h_, w_ = shape
    k, j, i = np.meshgrid(np.arange(d_ + 1), np.arange(h_ + 1), np.arange(w_ + 1), indexing="ij")
    corners = origin + np.stack([i, j, k], axis=-1).reshape(-1, 3) * edges
    np.testing.assert_allclose(sdf.reshape(-1), np.linalg.norm(corners - centre, axis=1) - radius, atol=1e-15)
    values, _ = trilinear_sdf(sdf, origin, edges, corners)
    np.testing.assert_allclose(values, sdf.reshape(-1), atol=1e-14)

    # an affine field a . x + b is reproduced exactly by trilinear interpolation, gradient included
    a, b = np.array([0.3, -1.2, 0.7]), 0.05
    affine = (corners @ a + b).reshape(sdf.shape)
    rng = np.random.default_rng(0)
    pts = origin + rng.random((500, 3)) * np.array([w_, h_, d_]) * edges
    values, grads = trilinear_sdf(affine, origin, edges, pts)
    np.testing.assert_allclose(values, pts @ a + b, atol=1e-13)
    np.testing.assert_allclose(grads, np.broadcast_to(a, grads.shape), atol=1e-12)

    # gradient of the sphere field against central differences, away from cell faces
    cell = rng.integers(0, 8, (200, 3))
    frac = rng.uniform(0.2, 0.8, (200, 3))
    pts = origin + (cell + frac) * edges
    _, grads = trilinear_sdf(sdf, origin, edges, pts)
    eps = 1e-6
    for ax in range(3):
        step = np.zeros(3)
        step[ax] = eps
        plus, minus = trilinear_sdf(sdf, origin, edges, pts + step)[0], trilinear_sdf(sdf, origin, edges, pts - step)[0]
        fd = (plus - minus) / (2 * eps)
        np.testing.assert_allclose(grads[:, ax], fd, atol=1e-7)
    # the independent scalar evaluator of this file agrees with the vectorised one
    np.testing.assert_allclose([_field(sdf, origin, edges, p) for p in pts[:20]],
                               trilinear_sdf(sdf, origin, edges, pts[:20])[0], atol=1e-14)


def test_march_finds_the_first_root():
    """March + bisection finds the entry / exit of the trilinear sphere found by the exact per-cell cubic roots."""
    edges, origin, shape, centre, radius, sdf = _sphere_scene()
    rng = np.random.default_rng(1)
    n = 40
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    # aim at points within 0.8 radius of the centre, starting 0.6 mm before them (outside the sphere)
    aim = centre + 0.8 * radius * rng.uniform(-1, 1, (n, 3)) / math.sqrt(3)
    start = aim - 0.6 * d
    dims = np.array([shape[2], shape[1], shape[0]])
    lo, hi = origin, origin + dims * edges
    t_in = np.max(np.minimum((lo - start) / d, (hi - start) / d), axis=1)
    t_out = np.min(np.maximum((lo - start) / d, (hi - start) / d), axis=1)
    t_hit = _march_sign_change(sdf, origin, edges, _sdf_lipschitz(sdf, edges), start, d,
                               np.maximum(t_in, 0.0), t_out, np.ones(n, dtype=bool), edges.min() / 64)
    # and the exit, marching from the aim point (inside) to the first f >= 0
    t_exit = _march_sign_change(sdf, origin, edges, _sdf_lipschitz(sdf, edges), start, d,
                                np.full(n, 0.6), t_out, np.zeros(n, dtype=bool), edges.min() / 64)
    sigma = np.ones((3,) + shape)
    for m in range(n):
        intervals = _negative_intervals(sigma, sdf, origin, edges, start[m], d[m])
        entry = min(ta for ta, _, _ in intervals if ta > 0)  # the start point is outside the sphere
        exit_ = max(tb for _, tb, _ in intervals)  # the trilinear sphere is convex along these rays
        assert abs(t_hit[m] - entry) < 1e-8, (m, t_hit[m], entry)
        assert abs(t_exit[m] - exit_) < 1e-8, (m, t_exit[m], exit_)


# ---------------------------------------------------------------------------------------------------
# 1. White furnace
# ---------------------------------------------------------------------------------------------------


def test_white_furnace_sdf_sphere_dielectric():
    """Albedo 1, constant emitter, dielectric SDF sphere: every value is exactly the emitter (stderr 0)."""
    edges, origin, shape, centre, radius, sdf = _sphere_scene()
    rng = np.random.default_rng(2)
    sigma = rng.uniform(2.0, 8.0, (3,) + shape)  # ~5 mm^-1: optical radius ~1.4, many scatterings + TIR
    albedo = np.ones_like(sigma)
    cam = dict(kind="perspective", origin=centre + np.array([1.2, -0.5, 0.7]), target=centre, up=(0, 0, 1),
               fov_y_deg=30.0, resolution=(4, 5))
    diag = {}
    mean, se = reference_render_scene(sigma, albedo, voxel_size=edges, origin=origin, g=0.5, boundary="sdf",
                                      sdf=sdf, ior=1.5, sensor=cam, emitter=dict(kind="constant", radiance=1.0),
                                      spp=300, rng=rng, diagnostics=diag)
    assert mean.shape == (4, 5, 3)
    np.testing.assert_array_equal(mean, 1.0)
    np.testing.assert_array_equal(se, 0.0)
    assert diag["absorbed"] == 0 and diag["truncated"] == 0 and diag["stuck"] == 0
    assert diag["scatterings"] > 0 and diag["reflections"] > 0 and diag["surface_events"] > 0

    # surface texels on the sphere, chromatic emitter, stronger forward scattering and a higher index
    normals = rng.normal(size=(6, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    texels = dict(kind="surface_texels", points=centre + radius * normals, normals=normals, radius=0.05)
    env = np.array([0.25, 1.0, 3.0])
    diag = {}
    mean, se = reference_render_scene(sigma, albedo, voxel_size=edges, origin=origin, g=0.8, boundary="sdf",
                                      sdf=sdf, ior=2.4, sensor=texels, emitter=dict(kind="constant", radiance=env),
                                      spp=300, rng=rng, diagnostics=diag)
    assert mean.shape == (6, 3)
    np.testing.assert_array_equal(mean, np.broadcast_to(env, mean.shape))
    np.testing.assert_array_equal(se, 0.0)
    assert diag["absorbed"] == 0 and diag["truncated"] == 0 and diag["stuck"] == 0 and diag["reflections"] > 0


# ---------------------------------------------------------------------------------------------------
# 2. Beer-Lambert through an index-matched SDF sphere
# ---------------------------------------------------------------------------------------------------


def test_beer_lambert_sdf_sphere_orthographic():
    """Albedo 0, ior None: pixel = L exp(-tau), tau = sigma-weighted chord through the trilinear zero set.

    Each of 8 rays (random view directions and offsets, all crossing the sphere well inside its
    silhouette) is the single pixel of an orthographic camera of extent 1e-6 mm, so the pixel *is* the
    ray. tau along the central ray is computed by the exact per-cell cubic roots
    (:func:`_negative_intervals`); the footprint's effect is bounded by the spread of the exact tau over
    the four footprint corners, used as a deterministic tolerance (it is ~1e-6 relative, far below the
    Monte Carlo error). sigma is heterogeneous per voxel and channel, and the voxels around the sphere
    carry a medium too, which must be ignored.
    """
    edges, origin, shape, centre, radius, sdf = _sphere_scene()
    rng = np.random.default_rng(3)
    sigma = rng.uniform(1.0, 6.0, (3,) + shape)
    sigma[2] *= 0.4
    env = np.array([1.0, 2.0, 0.5])
    extent = 1e-6
    means, ses, expected, tolerance = [], [], [], []
    events = dict(scatterings=0, reflections=0, surface_events=0, stuck=0)
    for ray in range(8):
        view = rng.normal(size=3)
        view /= np.linalg.norm(view)
        up = rng.normal(size=3)
        aim = centre + np.cross(view, up) / np.linalg.norm(np.cross(view, up)) * rng.uniform(0.0, 0.7) * radius
        cam = dict(kind="orthographic", origin=aim + 2.0 * view, target=aim, up=up, extent=(extent, extent),
                   resolution=(1, 1))
        diag = {}
        mean, se = reference_render_scene(sigma, np.zeros_like(sigma), voxel_size=edges, origin=origin,
                                          boundary="sdf", sdf=sdf, ior=None, sensor=cam,
                                          emitter=dict(kind="constant", radiance=env), spp=4000, rng=rng,
                                          diagnostics=diag)
        for key in events:
            events[key] += diag[key]
        taus = []
        for xi in ((0.5, 0.5), (0.0, 0.0), (1.0, 0.0), (0.0, 1.0), (1.0, 1.0)):
            o, d = sensor_rays(cam, np.zeros(1, dtype=int), np.array([xi[0]]), np.array([xi[1]]), edges)
            tau, chord = _optical_depth_exact(sigma, sdf, origin, edges, o[0], d[0])
            assert chord > 0.2  # the ray really crosses the sphere
            taus.append(tau)
        taus = np.array(taus)
        means.append(mean[0, 0])
        ses.append(se[0, 0])
        expected.append(env * np.exp(-taus[0]))
        tolerance.append(env * np.abs(np.exp(-taus) - np.exp(-taus[0])).max(axis=0))
    assert events["scatterings"] == 0 and events["reflections"] == 0 and events["stuck"] == 0
    assert events["surface_events"] > 0
    zmax = assert_z(np.array(means), np.array(ses), np.array(expected), tolerance=np.array(tolerance))
    print(f"Beer-Lambert sphere: max |z| = {zmax:.2f} over {3 * len(means)}, "
          f"footprint tol <= {max(map(np.max, tolerance)):.1e}")


# ---------------------------------------------------------------------------------------------------
# 3. Box as an SDF equals the box reference
# ---------------------------------------------------------------------------------------------------


def _box_sdf_padded(inner_shape, s):
    """Corner SDF of the inner box of a grid padded by one voxel on every side (exact box distance).

    Computed in voxel units (half-integers, exact in binary) and scaled by s, so the corners on the box
    faces are exactly 0, the inside ones negative and the outside ones positive.
    """
    d_, h_, w_ = inner_shape
    k, j, i = np.meshgrid(np.arange(d_ + 3), np.arange(h_ + 3), np.arange(w_ + 3), indexing="ij")
    q = [np.abs(i - (w_ + 2) / 2) - w_ / 2, np.abs(j - (h_ + 2) / 2) - h_ / 2, np.abs(k - (d_ + 2) / 2) - d_ / 2]
    q = np.stack(q, axis=-1)
    outside = np.linalg.norm(np.maximum(q, 0.0), axis=-1)
    inside = np.minimum(q.max(axis=-1), 0.0)
    return (outside + inside) * s


def test_box_as_sdf_equals_box_reference():
    """Top-face texels of a layered box: SDF box, ``boundary="box"`` and ``reference_render_texels`` agree.

    Layers differ (sigma, albedo per channel and depth) but the medium is laterally homogeneous, so the
    texel value varies smoothly across a texel (edge effects only). The disc footprint of radius s/sqrt(3)
    has the same first and second moments as the s x s square footprint of the box reference, so the two
    footprint averages differ only at 4th order (negligible). That disc (radius 0.577 s) overhangs the
    square, so on the border texels it sticks out of the top face: only the 3 x 3 centre texels of the
    5 x 5 x 2 box are compared. The padding voxels of the SDF grid hold an absorbing medium (albedo 0)
    that must be ignored.
    """
    s = 0.1
    inner = (2, 5, 5)
    rng = np.random.default_rng(4)
    layer_sigma = rng.uniform(10.0, 40.0, (3, inner[0]))
    layer_albedo = rng.uniform(0.5, 0.95, (3, inner[0]))
    sigma = np.broadcast_to(layer_sigma[:, :, None, None], (3,) + inner).copy()
    albedo = np.broadcast_to(layer_albedo[:, :, None, None], (3,) + inner).copy()
    kw = dict(g=0.4, ior=1.5)

    ref, ref_se = reference_render_texels(sigma, albedo, voxel_size=s, face="top", spp=6000, seed=5, **kw)
    ref, ref_se = ref[1:4, 1:4].reshape(9, 3), ref_se[1:4, 1:4].reshape(9, 3)

    jj, ii = np.meshgrid(np.arange(1, 4), np.arange(1, 4), indexing="ij")
    points = np.stack([(ii.ravel() + 0.5) * s, (jj.ravel() + 0.5) * s, np.full(9, inner[0] * s)], axis=1)
    texels = dict(kind="surface_texels", points=points, normals=np.tile([0.0, 0.0, 1.0], (9, 1)),
                  radius=s / math.sqrt(3.0))
    env = dict(kind="constant", radiance=1.0)

    sig_pad = np.pad(sigma, ((0, 0), (1, 1), (1, 1), (1, 1)), constant_values=0.0)
    alb_pad = np.pad(albedo, ((0, 0), (1, 1), (1, 1), (1, 1)), constant_values=0.0)
    sig_pad[sig_pad == 0.0] = 10.0  # absorbing padding (albedo 0), below the majorant of the inside
    sdf = _box_sdf_padded(inner, s)
    diag_sdf, diag_box = {}, {}
    as_sdf, as_sdf_se = reference_render_scene(sig_pad, alb_pad, voxel_size=s, origin=(-s, -s, -s),
                                               boundary="sdf", sdf=sdf, sensor=texels, emitter=env, spp=6000,
                                               rng=np.random.default_rng(6), diagnostics=diag_sdf, **kw)
    as_box, as_box_se = reference_render_scene(sigma, albedo, voxel_size=s, boundary="box", sensor=texels,
                                               emitter=env, spp=6000, rng=np.random.default_rng(7),
                                               diagnostics=diag_box, **kw)
    for diag in (diag_sdf, diag_box):
        assert diag["stuck"] == 0 and diag["truncated"] == 0 and diag["reflections"] > 0
    n = 2 * ref.size
    z_sdf = assert_z(as_sdf, as_sdf_se, ref, ref_se, n_tests=n)
    z_box = assert_z(as_box, as_box_se, ref, ref_se, n_tests=n)
    print(f"box as SDF vs reference_render_texels: max |z| = {z_sdf:.2f}; box: {z_box:.2f} (n = {n})")


# ---------------------------------------------------------------------------------------------------
# 4. Emitters
# ---------------------------------------------------------------------------------------------------


def _direction(theta, phi):
    return np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], axis=-1)


def test_envmap_lookup():
    """Pixel centres, bilinear blend, column wrap at phi = 0, continuity across phi = +-pi, row clamping."""
    hm, wm = 6, 8
    image = np.random.default_rng(5).uniform(0.0, 4.0, (hm, wm, 3))
    env = dict(kind="envmap", image=image)

    # exactly at every pixel centre: theta = (r + 1/2) pi / Hm, phi = (c + 1/2) 2 pi / Wm (atan2 folds phi > pi)
    r, c = np.meshgrid(np.arange(hm), np.arange(wm), indexing="ij")
    d = _direction((r.ravel() + 0.5) * math.pi / hm, (c.ravel() + 0.5) * 2 * math.pi / wm)
    np.testing.assert_allclose(evaluate_emitter(env, d), image.reshape(-1, 3), rtol=1e-12, atol=1e-12)

    # a point between four centres: weights (1 - fx)(1 - fy) etc.
    fx, fy = 0.3, 0.8
    d = _direction((2 + 0.5 + fy) * math.pi / hm, (4 + 0.5 + fx) * 2 * math.pi / wm)[None]
    expected = ((1 - fy) * ((1 - fx) * image[2, 4] + fx * image[2, 5])
                + fy * ((1 - fx) * image[3, 4] + fx * image[3, 5]))
    np.testing.assert_allclose(evaluate_emitter(env, d)[0], expected, rtol=1e-12)

    # phi = 0 (+x) sits half-way between column Wm - 1 and column 0 (wrap-around), on both sides of it
    theta = 3.5 * math.pi / hm  # row 3 centre
    for eps, w0 in ((0.0, 0.5), (0.25, 0.25), (-0.25, 0.75)):
        d = _direction(theta, eps * 2 * math.pi / wm)[None]  # x = eps - 1/2 (mod Wm)
        np.testing.assert_allclose(evaluate_emitter(env, d)[0], w0 * image[3, -1] + (1 - w0) * image[3, 0],
                                   rtol=1e-12)
    # continuity across the atan2 branch cut at phi = +-pi (no jump between just below and just above)
    below = evaluate_emitter(env, _direction(theta, math.pi - 1e-9)[None])
    above = evaluate_emitter(env, _direction(theta, -math.pi + 1e-9)[None])
    np.testing.assert_allclose(below, above, atol=1e-7)
    np.testing.assert_allclose(below[0], 0.5 * (image[3, 3] + image[3, 4]), atol=1e-7)  # x = Wm/2 - 1/2

    # rows clamp: above the first row centre / below the last row centre only columns are blended
    d = _direction(np.array([0.2 * math.pi / hm, math.pi - 0.1 * math.pi / hm]), np.full(2, 2.5 * 2 * math.pi / wm))
    np.testing.assert_allclose(evaluate_emitter(env, d), image[[0, hm - 1], 2], rtol=1e-12)
    pole = evaluate_emitter(env, np.array([[0.0, 0.0, 1.0]]))[0]  # theta = 0, phi = atan2(0, 0) = 0
    np.testing.assert_allclose(pole, 0.5 * (image[0, -1] + image[0, 0]))

    # end to end: an empty index-matched box seen by an orthographic camera shows E(f) in every pixel
    sigma = np.zeros((3, 2, 2, 2))
    f_dir = np.array([-0.3, 0.5, -0.81])
    f_dir /= np.linalg.norm(f_dir)
    cam = dict(kind="orthographic", origin=np.array([0.1, 0.1, 0.1]) - f_dir, target=(0.1, 0.1, 0.1), up=(0, 0, 1),
               extent=(0.3, 0.2), resolution=(2, 3))
    mean, se = reference_render_scene(sigma, sigma, voxel_size=0.1, sensor=cam, emitter=env, spp=4,
                                      rng=np.random.default_rng(0))
    np.testing.assert_allclose(mean, np.broadcast_to(evaluate_emitter(env, f_dir[None])[0], mean.shape), rtol=1e-12)
    np.testing.assert_allclose(se, 0.0, atol=1e-12)


def test_disc_emitter():
    """Distant disc: L + A inside the cone d . w >= cos(delta), A outside."""
    w = np.array([0.3, -0.4, 0.866])
    w /= np.linalg.norm(w)
    light = dict(kind="disc", direction=w * 5.0, angle_deg=10.0, radiance=(3.0, 2.0, 1.0), ambient=(0.1, 0.2, 0.3))
    axis = np.cross(w, [1.0, 0.0, 0.0])
    axis /= np.linalg.norm(axis)

    def tilted(deg):  # rotate w by deg about a perpendicular axis (Rodrigues)
        a = math.radians(deg)
        return w * math.cos(a) + np.cross(axis, w) * math.sin(a)

    d = np.array([w, tilted(5.0), tilted(9.99), tilted(10.01), tilted(90.0), -w])
    expected = np.array([[3.1, 2.2, 1.3]] * 3 + [[0.1, 0.2, 0.3]] * 3)
    np.testing.assert_allclose(evaluate_emitter(light, d), expected, rtol=1e-12)
    no_ambient = dict(kind="disc", direction=w, angle_deg=10.0, radiance=1.0)
    np.testing.assert_array_equal(evaluate_emitter(no_ambient, d)[:, 0], [1, 1, 1, 0, 0, 0])


# ---------------------------------------------------------------------------------------------------
# 5. Cameras and texels
# ---------------------------------------------------------------------------------------------------


def test_perspective_camera_corners_match_fov():
    """Corner rays: tan of the vertical / horizontal angles = tan(fov/2) and tan(fov/2) * cols / rows."""
    o = np.array([1.0, -2.0, 0.5])
    target = np.array([0.2, 0.3, 0.1])
    rows, cols, fov = 4, 6, 40.0
    cam = dict(kind="perspective", origin=o, target=target, up=(0, 0, 1), fov_y_deg=fov, resolution=(rows, cols))
    f = (target - o) / np.linalg.norm(target - o)
    right = np.cross(f, [0, 0, 1])
    right /= np.linalg.norm(right)
    up = np.cross(right, f)
    tan_h = math.tan(math.radians(fov / 2))
    # top-left corner of pixel (0, 0) and bottom-right corner of pixel (rows-1, cols-1)
    origins, d = sensor_rays(cam, np.array([0, rows * cols - 1]), np.array([0.0, 1.0]), np.array([0.0, 1.0]), 0.1)
    np.testing.assert_allclose(origins, np.broadcast_to(o, origins.shape))
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-14)
    fwd = d @ f
    np.testing.assert_allclose((d @ up) / fwd, [tan_h, -tan_h], rtol=1e-12)
    np.testing.assert_allclose((d @ right) / fwd, [-tan_h * cols / rows, tan_h * cols / rows], rtol=1e-12)
    # the vertical field of view: angle between the top-centre and bottom-centre edge rays
    edge_pixels = np.array([cols // 2, (rows - 1) * cols + cols // 2])
    _, d = sensor_rays(cam, edge_pixels, np.zeros(2), np.array([0.0, 1.0]), 0.1)
    assert math.degrees(math.acos(np.clip(d[0] @ d[1], -1, 1))) == pytest.approx(fov, abs=1e-9)
    # the centre of a 2 x 2 pixel block at the image centre looks straight ahead
    _, d = sensor_rays(cam, np.array([(rows // 2) * cols + cols // 2]), np.zeros(1), np.zeros(1), 0.1)
    np.testing.assert_allclose(d[0], f, atol=1e-14)


def test_orthographic_and_texel_rays():
    """Orthographic corner origins span the extent; texel samples lie in the lifted footprint disc."""
    o = np.array([0.0, 0.0, 2.0])
    cam = dict(kind="orthographic", origin=o, target=(0.0, 0.0, 0.0), up=(0, 1, 0), extent=(0.6, 0.4),
               resolution=(2, 3))
    origins, d = sensor_rays(cam, np.array([0, 5]), np.array([0.0, 1.0]), np.array([0.0, 1.0]), 0.1)
    # f = -z, right = f x up = (0,0,-1) x (0,1,0) = (1,0,0), up' = right x f = (0,1,0)
    np.testing.assert_allclose(origins, [[-0.3, 0.2, 2.0], [0.3, -0.2, 2.0]], atol=1e-15)
    np.testing.assert_allclose(d, [[0, 0, -1], [0, 0, -1]], atol=1e-15)

    rng = np.random.default_rng(6)
    normal = np.array([0.2, -0.5, 0.8])
    normal /= np.linalg.norm(normal)
    p = np.array([0.3, 0.2, 0.1])
    texels = dict(kind="surface_texels", points=p[None], normals=normal[None], radius=0.05)
    n = 20000
    edges = (0.1, 0.12, 0.08)
    origins, d = sensor_rays(texels, np.zeros(n, dtype=int), rng.random(n), rng.random(n), edges)
    np.testing.assert_allclose(d, np.broadcast_to(-normal, d.shape), atol=1e-15)
    rel = origins - p
    np.testing.assert_allclose(rel @ normal, 2 * 0.12, atol=1e-14)  # lifted by h = 2 max(voxel edges)
    lateral = rel - np.outer(rel @ normal, normal)
    rho = np.linalg.norm(lateral, axis=1)
    assert rho.max() <= 0.05 + 1e-14
    # uniform in the disc: rho^2 / r^2 ~ U(0, 1), and the lateral offset has zero mean
    assert stats.kstest(rho**2 / 0.05**2, "uniform").pvalue > ALPHA
    assert_z(lateral.mean(axis=0), lateral.std(axis=0, ddof=1) / math.sqrt(n), 0.0)
