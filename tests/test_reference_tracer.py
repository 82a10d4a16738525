"""Checks of the numpy reference tracer (torch_appearance.testing.reference_tracer) against closed forms.

The reference is what the fast C++ tracer is judged by, so it is itself checked here against results that
follow from first principles: Fresnel identities, Henyey-Greenstein moments, Beer-Lambert per voxel column
(with the multiple-reflection series of a dielectric slab), white-furnace energy conservation, and the
symmetries of the scene (mirrored grids, subdivided voxels). Monte Carlo results are z-tested with a
Bonferroni-corrected threshold (family-wise false-alarm rate ``ALPHA`` per test function).
"""

import math

import numpy as np
import pytest
from scipy import stats

from torch_appearance.testing.reference_tracer import (
    distance_to_box_exit,
    fresnel_dielectric,
    reference_render_texels,
    sample_henyey_greenstein,
)

ALPHA = 1e-3  # family-wise false-alarm probability of every statistical test below


def z_threshold(n_tests: int, alpha: float = ALPHA) -> float:
    """Two-sided per-test |z| threshold for ``n_tests`` tests at family-wise level ``alpha`` (Bonferroni)."""
    return float(stats.norm.isf(alpha / (2.0 * n_tests)))


def assert_z(estimate, stderr, expected, expected_stderr=0.0):
    """Assert ``|estimate - expected| / sqrt(stderr^2 + expected_stderr^2)`` is below the Bonferroni threshold."""
    estimate, stderr, expected = np.broadcast_arrays(*map(np.asarray, (estimate, stderr, expected)))
    se = np.sqrt(np.asarray(stderr) ** 2 + np.asarray(expected_stderr) ** 2)
    assert np.all(se > 0), "a standard error of 0 cannot be z-tested"
    z = np.abs(estimate - expected) / se
    threshold = z_threshold(z.size)
    assert z.max() < threshold, f"max |z| = {z.max():.2f} >= {threshold:.2f} (at {np.unravel_index(z.argmax(), z.shape)})"
    return z


def slab_reflection_series(transmittance, r):
    """Texel value of an absorbing dielectric slab at normal incidence, env = 1.

    Reflected at entry (r), or entering (1 - r) and escaping through either face after any number of
    internal reflections: ``r + (1 - r)^2 T / (1 - r T)``.
    """
    return r + (1.0 - r) ** 2 * transmittance / (1.0 - r * transmittance)


# ---------------------------------------------------------------------------------------------------
# Building blocks
# ---------------------------------------------------------------------------------------------------


def test_fresnel_matches_angle_form():
    """Compare with the textbook angle form r_s = -sin(ti-tt)/sin(ti+tt), r_p = tan(ti-tt)/tan(ti+tt)."""
    for eta in (1.5, 1.0 / 1.5, 1.33, 2.4):
        theta_i = np.linspace(0.01, 1.55, 200)
        sin_t = eta * np.sin(theta_i)
        ok = sin_t < 1.0
        theta_t = np.arcsin(sin_t[ok])
        ti = theta_i[ok]
        rs = -np.sin(ti - theta_t) / np.sin(ti + theta_t)
        rp = np.tan(ti - theta_t) / np.tan(ti + theta_t)
        np.testing.assert_allclose(fresnel_dielectric(np.cos(ti), eta), 0.5 * (rs**2 + rp**2), atol=1e-12)
        # total internal reflection beyond the critical angle
        np.testing.assert_array_equal(fresnel_dielectric(np.cos(theta_i[~ok]), eta), 1.0)


def test_fresnel_special_values():
    assert fresnel_dielectric(np.array([1.0]), 1.5)[0] == pytest.approx(0.04, abs=1e-15)
    assert fresnel_dielectric(np.array([1.0]), 1 / 1.5)[0] == pytest.approx(0.04, abs=1e-15)
    assert fresnel_dielectric(np.array([0.0]), 1 / 1.5)[0] == 1.0  # grazing from outside
    assert fresnel_dielectric(np.array([0.3]), 1.0)[0] == pytest.approx(0.0, abs=1e-30)  # index matched
    # critical angle from inside glass: sin = 1/1.5
    cos_c = math.sqrt(1 - (1 / 1.5) ** 2)
    assert fresnel_dielectric(np.array([cos_c - 1e-9]), 1.5)[0] == 1.0
    assert fresnel_dielectric(np.array([cos_c + 1e-3]), 1.5)[0] < 1.0
    # Brewster angle from outside: tan(theta_B) = n2/n1 = 1.5, r_p = 0 so F = r_s^2 / 2
    tb = math.atan(1.5)
    tt = math.asin(math.sin(tb) / 1.5)
    rs = -math.sin(tb - tt) / math.sin(tb + tt)
    assert fresnel_dielectric(np.array([math.cos(tb)]), 1 / 1.5)[0] == pytest.approx(0.5 * rs**2, rel=1e-12)


def test_fresnel_reciprocity():
    """F(cos_i, eta) = F(cos_t, 1/eta): the same interface seen from both sides."""
    cos_i = np.linspace(0.0, 1.0, 101)
    eta = 1 / 1.5
    cos_t = np.sqrt(1 - eta**2 * (1 - cos_i**2))
    np.testing.assert_allclose(fresnel_dielectric(cos_i, eta), fresnel_dielectric(cos_t, 1 / eta), atol=1e-12)


@pytest.mark.parametrize("g", [0.0, 0.4, -0.5, 0.9])
def test_henyey_greenstein_distribution(g):
    """Legendre moments E[P_l(mu)] = g^l (l = 1, 2), uniform azimuth, unit length, and a KS test on mu."""
    rng = np.random.default_rng(11)
    n = 200_000
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    new = sample_henyey_greenstein(d, g, rng.random(n), rng.random(n))
    np.testing.assert_allclose(np.linalg.norm(new, axis=1), 1.0, atol=1e-12)
    mu = np.sum(new * d, axis=1)
    p1, p2 = mu, 0.5 * (3 * mu**2 - 1)
    est = np.array([p1.mean(), p2.mean()])
    se = np.array([p1.std(ddof=1), p2.std(ddof=1)]) / math.sqrt(n)
    assert_z(est, se, np.array([g, g * g]))

    if abs(g) > 1e-4:
        def cdf(m):
            return (1 - g * g) / (2 * g) * (1 / np.sqrt(1 + g * g - 2 * g * m) - 1 / (1 + g))
    else:
        def cdf(m):
            return (m + 1) / 2
    assert stats.kstest(mu, cdf).pvalue > ALPHA

    # azimuth around a fixed axis is uniform: the perpendicular part has zero mean in the frame
    z_axis = np.tile([0.0, 0.0, 1.0], (n, 1))
    new_z = sample_henyey_greenstein(z_axis, g, rng.random(n), rng.random(n))
    assert_z(new_z[:, :2].mean(axis=0), new_z[:, :2].std(axis=0, ddof=1) / math.sqrt(n), 0.0)


def test_distance_to_box_exit():
    extent = np.array([0.4, 0.3, 0.2])
    pos = np.array([
        [0.1, 0.1, 0.2],   # on the top face, moving down: reaches the bottom
        [0.1, 0.1, 0.2],   # on the top face, moving up: leaves at once
        [0.1, 0.1, 0.1],   # leaves through the +x side face
        [0.1, 0.1, 0.1],   # leaves through the -y side face
        [0.0, 0.0, 0.0],   # corner, moving diagonally into the box
    ])
    s2 = math.sqrt(0.5)
    d = np.array([
        [0.0, 0.0, -1.0],
        [0.0, 0.0, 1.0],
        [1.0, 0.0, 0.0],
        [0.0, -s2, s2],
        [s2, s2, 0.0],
    ])
    t, axis = distance_to_box_exit(pos, d, extent)
    np.testing.assert_allclose(t, [0.2, 0.0, 0.3, 0.1 / s2, 0.3 / s2], rtol=1e-12)
    np.testing.assert_array_equal(axis, [2, 2, 0, 1, 1])


# ---------------------------------------------------------------------------------------------------
# Closed forms of the full estimator
# ---------------------------------------------------------------------------------------------------


def _column_sigma(seed=3, shape=(3, 3, 4, 4)):
    rng = np.random.default_rng(seed)
    sigma = rng.uniform(0.2, 8.0, shape)
    sigma[0] *= 0.3  # strongly chromatic
    sigma[2] *= 2.0
    return sigma


@pytest.mark.parametrize("face", ["top", "bottom"])
@pytest.mark.parametrize("ior", [None, 1.5])
def test_beer_lambert_per_column(face, ior):
    """Albedo 0: texel [j, i] = exp(-s sum_k sigma[c, k, j, i]) (index matched), or the slab series."""
    s = 0.1
    sigma = _column_sigma()
    env = np.array([0.5, 1.0, 2.0])
    mean, se = reference_render_texels(
        sigma, np.zeros_like(sigma), voxel_size=s, face=face, ior=ior, environment=env, spp=4000, seed=5
    )
    transmittance = np.exp(-s * sigma.sum(axis=1)).transpose(1, 2, 0)  # (H, W, 3)
    if ior is None:
        expected = transmittance
    else:
        expected = slab_reflection_series(transmittance, ((ior - 1) / (ior + 1)) ** 2)
    assert_z(mean, se, env * expected)


def test_beer_lambert_uniform_chromatic():
    """The plain formulas of the brief: uniform chromatic sigma_t, T = exp(-sigma_t D s), R = 0.04."""
    s, depth = 0.1, 3
    sig_c = np.array([0.5, 3.0, 10.0])
    sigma = np.broadcast_to(sig_c[:, None, None, None], (3, depth, 2, 2)).copy()
    t = np.exp(-sig_c * depth * s)
    for ior, expected in ((None, t), (1.5, 0.04 + 0.96**2 * t / (1 - 0.04 * t))):
        mean, se = reference_render_texels(sigma, np.zeros_like(sigma), voxel_size=s, ior=ior, spp=20000, seed=1)
        assert_z(mean, se, np.broadcast_to(expected, mean.shape))


@pytest.mark.parametrize("ior", [None, 1.5])
def test_forward_scattering_limit(ior):
    """g = 1 (delta-forward phase): scattering changes nothing, so T = exp(-s sum sigma (1 - albedo))."""
    s = 0.1
    sigma = _column_sigma(seed=4)
    albedo = np.random.default_rng(4).uniform(0.3, 0.95, sigma.shape)
    mean, se = reference_render_texels(sigma, albedo, voxel_size=s, g=1.0, ior=ior, spp=4000, seed=6)
    transmittance = np.exp(-s * (sigma * (1 - albedo)).sum(axis=1)).transpose(1, 2, 0)
    expected = transmittance if ior is None else slab_reflection_series(transmittance, 0.04)
    assert_z(mean, se, expected)


@pytest.mark.parametrize("ior", [None, 1.5])
def test_max_depth_zero_is_unscattered_light(ior):
    """Albedo 1 with max_depth 0: only paths that never scatter count, i.e. Beer-Lambert again."""
    s = 0.1
    sigma = _column_sigma(seed=5)
    mean, se = reference_render_texels(
        sigma, np.ones_like(sigma), voxel_size=s, face="bottom", g=0.4, ior=ior, spp=4000, seed=7, max_depth=0
    )
    transmittance = np.exp(-s * sigma.sum(axis=1)).transpose(1, 2, 0)
    expected = transmittance if ior is None else slab_reflection_series(transmittance, 0.04)
    assert_z(mean, se, expected)


def _furnace_sigma(seed=8, shape=(3, 3, 4, 4)):
    rng = np.random.default_rng(seed)
    sigma = np.exp(rng.uniform(math.log(1e-4), math.log(50.0), shape))
    flat = sigma.reshape(3, -1)
    flat[:, 0] = 1e-4
    flat[:, 1] = 50.0
    flat[:, 2] = 1e-4
    flat[:, 5] = 50.0
    return rng.permuted(sigma.reshape(3, -1), axis=1).reshape(shape)


@pytest.mark.parametrize("ior", [None, 1.5, 2.4])
@pytest.mark.parametrize("g", [0.4, -0.5])
def test_white_furnace(ior, g):
    """Albedo 1: every path leaves eventually, so every texel is exactly the environment (stderr 0)."""
    sigma = _furnace_sigma()
    env = np.array([0.25, 1.0, 3.0])
    for face in ("top", "bottom"):
        mean, se = reference_render_texels(
            sigma, np.ones_like(sigma), voxel_size=0.1, face=face, g=g, ior=ior, environment=env, spp=200, seed=9
        )
        np.testing.assert_array_equal(mean, np.broadcast_to(env, mean.shape))
        np.testing.assert_array_equal(se, 0.0)


def test_pure_vacuum():
    """sigma_t = 0 (majorant 0): the ray passes; with a dielectric the slab series with T = 1."""
    sigma = np.zeros((3, 2, 2, 3))
    mean, _ = reference_render_texels(sigma, np.zeros_like(sigma), voxel_size=0.1, ior=None, spp=50)
    np.testing.assert_array_equal(mean, 1.0)
    mean, _ = reference_render_texels(sigma, np.zeros_like(sigma), voxel_size=0.1, ior=1.5, spp=50)
    np.testing.assert_array_equal(mean, 1.0)


# ---------------------------------------------------------------------------------------------------
# Symmetries with scattering (expectations known only through a second Monte Carlo estimate)
# ---------------------------------------------------------------------------------------------------


def _scattering_scene(seed=12, shape=(3, 3, 4, 4)):
    rng = np.random.default_rng(seed)
    sigma = rng.uniform(0.5, 30.0, shape)
    sigma[1] *= 0.3
    albedo = rng.uniform(0.3, 0.999, shape)
    return sigma, albedo


def test_symmetries_with_scattering():
    """Bottom face == top face of the z-mirrored grid; x-mirroring the grid mirrors the texels."""
    sigma, albedo = _scattering_scene()
    kw = dict(voxel_size=0.1, g=0.4, ior=1.5, spp=6000)
    bottom, se_b = reference_render_texels(sigma, albedo, face="bottom", seed=1, **kw)
    top_zflip, se_z = reference_render_texels(sigma[:, ::-1], albedo[:, ::-1], face="top", seed=2, **kw)
    assert_z(bottom, se_b, top_zflip, se_z)
    top, se_t = reference_render_texels(sigma, albedo, face="top", seed=3, **kw)
    top_xflip, se_x = reference_render_texels(sigma[..., ::-1], albedo[..., ::-1], face="top", seed=4, **kw)
    assert_z(top, se_t, top_xflip[:, ::-1], se_x[:, ::-1])


def test_subdivided_voxels_give_the_same_texels():
    """The same medium on voxels of half the size: every coarse texel is the mean of its 2 x 2 fine texels."""
    sigma, albedo = _scattering_scene(seed=13, shape=(3, 2, 3, 3))
    up = lambda a: a.repeat(2, axis=1).repeat(2, axis=2).repeat(2, axis=3)  # noqa: E731
    kw = dict(g=-0.5, ior=1.5, face="top")
    coarse, se_c = reference_render_texels(sigma, albedo, voxel_size=0.1, spp=8000, seed=1, **kw)
    fine, se_f = reference_render_texels(up(sigma), up(albedo), voxel_size=0.05, spp=2000, seed=2, **kw)
    h, w = coarse.shape[:2]
    fine_mean = fine.reshape(h, 2, w, 2, 3).mean(axis=(1, 3))
    fine_se = np.sqrt((se_f.reshape(h, 2, w, 2, 3) ** 2).sum(axis=(1, 3))) / 4
    assert_z(coarse, se_c, fine_mean, fine_se)
