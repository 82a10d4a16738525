"""The fast C++ volume path tracer against the independent numpy reference (torch_appearance.testing.reference_tracer).

The two estimators share nothing but the scene conventions: the fast tracer uses regular tracking through
the voxels, the reference uses delta tracking against a per-channel majorant with analog absorption and an
analog Fresnel coin (the reference itself is checked against closed forms in test_reference_tracer.py).
Both estimate the same texel expectation, so for every texel and channel

    z = (fast - reference) / sqrt(stderr_fast^2 + stderr_reference^2)

is approximately standard normal. The fast tracer's standard error comes from the spread of K independent
renders (different seeds); K is large (64) so that this estimated standard error is itself accurate and z
is close to normal out in the tails where the Bonferroni threshold lies. All texels x channels of one
configuration form one family, tested at family-wise false-alarm rate ``ALPHA``.

The scene is tiny, heterogeneous, chromatic and scattering: D = 3, H = W = 4, voxel 0.1 mm, sigma_t in
[0.5, 30] mm^-1 with a different range per channel (thin red, thick green, log-uniform blue), albedo in
[0.3, 0.999], chromatic environment. ``test_z_test_has_power`` shows that the same test rejects a
reference whose sigma_t is only 10 % off, so passing means something.
"""

import functools

import numpy as np
import pytest
import torch
from scipy import stats

import torch_appearance
from torch_appearance.testing.reference_tracer import reference_render_texels

ALPHA = 1e-3  # family-wise false-alarm probability per configuration
VOXEL_SIZE = 0.1  # mm
ENVIRONMENT = (0.8, 1.0, 1.25)
REFERENCE_SPP = 16000  # per texel
FAST_SEEDS = 64  # independent fast renders ...
FAST_SPP = 256  # ... of this many samples per texel each (16384 samples per texel in all)
MEDIA = [(0.4, None), (0.4, 1.5), (-0.5, None), (-0.5, 1.5)]  # (g, ior)
FACES = ["top", "bottom", "both"]
CONFIGS = [(g, ior, face) for g, ior in MEDIA for face in FACES[:2]]


def make_scene(seed: int = 2024, shape=(3, 3, 4, 4)):
    """Heterogeneous chromatic scattering medium; sigma_t (3, D, H, W) in [0.5, 30], albedo in [0.3, 0.999]."""
    rng = np.random.default_rng(seed)
    _, depth, height, width = shape
    vox = (depth, height, width)
    sigma_t = np.empty(shape)
    sigma_t[0] = rng.uniform(0.5, 3.0, vox)  # red: optically thin (tau 0.05 .. 0.3 per voxel)
    sigma_t[1] = rng.uniform(5.0, 30.0, vox)  # green: thick
    sigma_t[2] = np.exp(rng.uniform(np.log(0.5), np.log(30.0), vox))  # blue: both, voxel to voxel
    albedo = rng.uniform(0.3, 0.999, shape)
    return sigma_t, albedo


def bonferroni_threshold(n_tests: int, alpha: float = ALPHA) -> float:
    """Two-sided per-test |z| threshold for ``n_tests`` tests at family-wise level ``alpha``."""
    return float(stats.norm.isf(alpha / (2.0 * n_tests)))


def config_seed(g, ior, face) -> int:
    """A distinct seed per configuration, so that the configurations' errors are independent."""
    return 1 + len(FACES) * MEDIA.index((g, ior)) + FACES.index(face)


@functools.lru_cache(maxsize=None)
def reference(g, ior, face, sigma_scale=1.0, spp=REFERENCE_SPP, seed=None):
    """Reference (mean, stderr), each (H, W, 3)."""
    seed = config_seed(g, ior, face) if seed is None else seed
    sigma_t, albedo = make_scene()
    return reference_render_texels(
        sigma_t * sigma_scale, albedo, voxel_size=VOXEL_SIZE, face=face, g=g, ior=ior,
        environment=ENVIRONMENT, spp=spp, seed=seed,
    )


@functools.lru_cache(maxsize=None)
def fast(g, ior, face):
    """Fast tracer (mean, stderr) from FAST_SEEDS independent renders; (H, W, 3) or (2, H, W, 3)."""
    sigma_t, albedo = make_scene()
    sigma_t = torch.from_numpy(sigma_t)
    albedo = torch.from_numpy(albedo)
    renders = []
    with torch.no_grad():
        for k in range(FAST_SEEDS):
            image = torch_appearance.render_texels(
                sigma_t, albedo, voxel_size=VOXEL_SIZE, face=face, g=g, ior=ior,
                environment=ENVIRONMENT, spp=FAST_SPP, seed=1000 * config_seed(g, ior, face) + k,
            )
            renders.append(image.double().numpy())
    renders = np.stack(renders)
    return renders.mean(axis=0), renders.std(axis=0, ddof=1) / np.sqrt(FAST_SEEDS)


def z_scores(fast_result, reference_result):
    (mean_f, se_f), (mean_r, se_r) = fast_result, reference_result
    se = np.sqrt(se_f**2 + se_r**2)
    assert np.all(se > 0)
    return (mean_f - mean_r) / se


def describe(z, fast_result, reference_result, threshold):
    """Message listing every texel/channel beyond the threshold."""
    lines = [f"max |z| = {np.abs(z).max():.2f}, threshold {threshold:.2f}"]
    for idx in zip(*np.nonzero(np.abs(z) >= threshold)):
        lines.append(
            f"  texel/channel {tuple(int(v) for v in idx)}: fast {fast_result[0][idx]:.5f} +- {fast_result[1][idx]:.5f}, "
            f"reference {reference_result[0][idx]:.5f} +- {reference_result[1][idx]:.5f}, z = {z[idx]:+.2f}"
        )
    return "\n".join(lines)


@pytest.mark.parametrize("g, ior, face", CONFIGS)
def test_fast_tracer_matches_reference(g, ior, face):
    f, r = fast(g, ior, face), reference(g, ior, face)
    assert f[0].shape == r[0].shape == (4, 4, 3)
    z = z_scores(f, r)
    threshold = bonferroni_threshold(z.size)
    assert np.abs(z).max() < threshold, describe(z, f, r, threshold)


def test_both_faces_match_reference():
    """face='both' stacks top (index 0) and bottom (index 1), each matching the reference."""
    g, ior = 0.4, 1.5
    mean_f, se_f = fast(g, ior, "both")
    assert mean_f.shape == (2, 4, 4, 3)
    r_top, r_bottom = reference(g, ior, "top"), reference(g, ior, "bottom")
    mean_r = np.stack([r_top[0], r_bottom[0]])
    se_r = np.stack([r_top[1], r_bottom[1]])
    z = z_scores((mean_f, se_f), (mean_r, se_r))
    threshold = bonferroni_threshold(z.size)
    assert np.abs(z).max() < threshold, describe(z, (mean_f, se_f), (mean_r, se_r), threshold)


def test_z_test_has_power():
    """The same z-test rejects a reference whose sigma_t is 10 % too large.

    A plausible bug (e.g. sampling distances with one randomly chosen channel and weighting the others
    without the ratio / MIS weights) biases texels by at least this much; if this test ever passes with
    the wrong medium, the comparison above is too weak to catch such bugs.
    """
    g, ior, face = 0.4, 1.5, "top"
    f = fast(g, ior, face)
    wrong = reference(g, ior, face, sigma_scale=1.1, spp=2 * REFERENCE_SPP, seed=99)
    z = z_scores(f, wrong)
    assert np.abs(z).max() > bonferroni_threshold(z.size), "z-test failed to detect sigma_t scaled by 1.1"


def _fast_vs_reference(sigma_t, albedo, *, g, ior, seed, shape_hw, expect_lanes):
    kw = dict(voxel_size=VOXEL_SIZE, face="top", g=g, ior=ior, environment=ENVIRONMENT)
    renders, stats = [], {}
    with torch.no_grad():
        for k in range(FAST_SEEDS):
            renders.append(torch_appearance.render_texels(torch.from_numpy(sigma_t), torch.from_numpy(albedo),
                                                          spp=FAST_SPP, seed=seed * 1000 + k, stats=stats,
                                                          **kw).numpy())
    assert stats["lanes"] == expect_lanes
    renders = np.stack(renders)
    f = renders.mean(axis=0), renders.std(axis=0, ddof=1) / np.sqrt(FAST_SEEDS)
    r = reference_render_texels(sigma_t, albedo, spp=REFERENCE_SPP, seed=seed, **kw)
    assert f[0].shape == (*shape_hw, 3)
    z = z_scores(f, r)
    threshold = bonferroni_threshold(z.size)
    assert np.abs(z).max() < threshold, describe(z, f, r, threshold)


def test_vero_yellow_over_white_ink_slab():
    """Measured printer inks: yellow (σ_t = (2.25, 3.75, 19) mm⁻¹, albedo (0.997, 0.995, 0.15)) over white.

    Extinction differs ~8× between channels; an estimator that samples one channel's distances without the
    correct weights is biased by tens of percent on such a slab. Each channel must match the reference.
    """
    shape = (3, 4, 3, 3)
    sigma_t, albedo = np.empty(shape), np.empty(shape)
    sigma_t[:, :2] = np.array([6.0, 9.0, 24.0])[:, None, None, None]  # white base (bottom two layers)
    albedo[:, :2] = np.array([0.9991, 0.9997, 0.999])[:, None, None, None]
    sigma_t[:, 2:] = np.array([2.25, 3.75, 19.0])[:, None, None, None]  # yellow on top
    albedo[:, 2:] = np.array([0.997, 0.995, 0.15])[:, None, None, None]
    _fast_vs_reference(sigma_t, albedo, g=0.4, ior=1.5, seed=31, shape_hw=(3, 3), expect_lanes=1)


@pytest.mark.parametrize("ior", [None, 1.5])
def test_one_shared_walk_with_chromatic_albedo(ior):
    """Grey σ_t, chromatic albedo: one walk serves all channels with albedo weights α_c / max α; unbiased."""
    sigma_t, albedo = make_scene(seed=7)
    sigma_t = np.repeat(sigma_t[1:2], 3, axis=0)
    _fast_vs_reference(sigma_t, albedo, g=0.4, ior=ior, seed=41 if ior else 43, shape_hw=(4, 4), expect_lanes=3)


if __name__ == "__main__":  # print the z statistics of every configuration
    for config in CONFIGS:
        z = z_scores(fast(*config), reference(*config))
        print(config, f"max |z| = {np.abs(z).max():.2f} (threshold {bonferroni_threshold(z.size):.2f})")
