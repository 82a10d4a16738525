"""Hero-channel spectral MIS (``chromatic="hero"``): one walk serves all three channels of a chromatic medium.

The walk samples free flights with the reference density of a hero channel (uniform per sample) and weights each
channel c with the balance heuristic over the channels, f_c / ((1/3) Σ_k p_k) (csrc/core/integrator.h, HERO).
Checked here:

* unbiasedness of the image against the independent numpy reference (torch_appearance.testing.reference_tracer:
  delta tracking, analog absorption, one walk per channel) with Bonferroni z-tests as in
  test_volpath_reference.py, on a chromatic scene (thin red, thick green, mixed blue), with a reference medium that
  differs from the parameters (ratio weights under MIS), and on a stiff scene whose channels' σ_t differ by 10⁴
  (optical depths up to ~10⁴);
* the gradient: exact derivative of the fixed-seed estimator (gradcheck, explicit reference), and the default
  floored replay's mean over seeds equal to that of the per-channel estimator (an independent estimator of the
  same expectation, itself checked against finite differences in test_volpath_gradients.py);
* reproducibility: the same seed gives the same image, independent of the thread count, and the single-walk tape
  replay equals the two-pass replay bit for bit.
"""
import numpy as np
import pytest
import torch
from scipy import stats as scipy_stats

import torch_appearance as ta
from torch_appearance.testing import assert_z, seed_stats
from torch_appearance.testing.reference_tracer import reference_render_texels
from torch_appearance._ext import _C

VOXEL = 0.1  # mm
ENVIRONMENT = (0.8, 1.0, 1.25)
ALPHA = 1e-3  # family-wise false-alarm probability per z-test family
FAST_SEEDS = 32
FAST_SPP = 256
REFERENCE_SPP = 12000


def chromatic_scene(seed=2024, shape=(3, 3, 4, 4)):
    """Thin red (τ 0.05–0.3 per voxel), thick green (0.5–3), log-uniform blue; albedo in [0.3, 0.999]."""
    rng = np.random.default_rng(seed)
    vox = shape[1:]
    sigma_t = np.empty(shape)
    sigma_t[0] = rng.uniform(0.5, 3.0, vox)
    sigma_t[1] = rng.uniform(5.0, 30.0, vox)
    sigma_t[2] = np.exp(rng.uniform(np.log(0.5), np.log(30.0), vox))
    return sigma_t, rng.uniform(0.3, 0.999, shape)


def stiff_scene(seed=7, shape=(3, 3, 3, 3)):
    """σ_t differs by ~10⁴ between channels: red 0.3–1, green 1–3·10⁴ (optical depth up to ~9·10³ across the
    slab), blue 3–30 mm⁻¹; bright green albedo (long walks in the dense channel)."""
    rng = np.random.default_rng(seed)
    vox = shape[1:]
    sigma_t = np.empty(shape)
    sigma_t[0] = rng.uniform(0.3, 1.0, vox)
    sigma_t[1] = rng.uniform(1e4, 3e4, vox)
    sigma_t[2] = rng.uniform(3.0, 30.0, vox)
    albedo = rng.uniform(0.5, 0.95, shape)
    albedo[1] = rng.uniform(0.97, 0.995, vox)
    return sigma_t, albedo


def bonferroni(n):
    return float(scipy_stats.norm.isf(ALPHA / (2.0 * n)))


def fast_hero(sigma_t, albedo, *, seed, sampling_sigma_t=None, **kw):
    """Mean and standard error over FAST_SEEDS hero renders, (H, W, 3) each."""
    st = {}
    renders = []
    with torch.no_grad():
        for k in range(FAST_SEEDS):
            img = ta.render_texels(torch.from_numpy(sigma_t), torch.from_numpy(albedo), voxel_size=VOXEL,
                                   environment=ENVIRONMENT, spp=FAST_SPP, seed=seed * 1000 + k, stats=st,
                                   chromatic="hero", sampling_sigma_t=sampling_sigma_t, **kw)
            renders.append(img.numpy())
    assert st["lanes"] == 3 and st["hero"], "the hero walk was not used"
    renders = np.stack(renders)
    assert np.isfinite(renders).all()
    return renders.mean(0), renders.std(0, ddof=1) / np.sqrt(FAST_SEEDS)


def assert_matches_reference(f, r):
    (mf, sf), (mr, sr) = f, r
    z = (mf - mr) / np.sqrt(sf ** 2 + sr ** 2)
    threshold = bonferroni(z.size)
    worst = np.unravel_index(np.abs(z).argmax(), z.shape)
    assert np.abs(z).max() < threshold, (f"max |z| = {np.abs(z).max():.2f} >= {threshold:.2f} at {worst}: hero "
                                         f"{mf[worst]:.5f} ± {sf[worst]:.5f}, reference {mr[worst]:.5f} ± "
                                         f"{sr[worst]:.5f}")
    return z


@pytest.mark.parametrize("g, ior, face", [(0.4, 1.5, "top"), (-0.5, None, "bottom")])
def test_hero_matches_reference(g, ior, face):
    sigma_t, albedo = chromatic_scene()
    kw = dict(g=g, ior=ior, face=face)
    seed = 11 if ior else 12
    f = fast_hero(sigma_t, albedo, seed=seed, **kw)
    r = reference_render_texels(sigma_t, albedo, voxel_size=VOXEL, environment=ENVIRONMENT, spp=REFERENCE_SPP,
                                seed=seed, **kw)
    assert_matches_reference(f, r)


def test_hero_with_ratio_weights_matches_reference():
    """An explicit chromatic sampling medium unlike the parameters: the ratio weights f/p_hero under MIS."""
    sigma_t, albedo = chromatic_scene(seed=5)
    rng = np.random.default_rng(6)
    ref = sigma_t * np.array([1.6, 0.6, 1.0])[:, None, None, None] * rng.uniform(0.8, 1.25, sigma_t.shape)
    kw = dict(g=0.4, ior=1.5, face="top")
    f = fast_hero(sigma_t, albedo, seed=13, sampling_sigma_t=torch.from_numpy(ref), **kw)
    r = reference_render_texels(sigma_t, albedo, voxel_size=VOXEL, environment=ENVIRONMENT, spp=REFERENCE_SPP,
                                seed=13, **kw)
    assert_matches_reference(f, r)


def test_hero_stiff_medium_matches_reference():
    """Channels 10⁴ apart in σ_t: no overflow or NaN (log-space MIS weights), and still unbiased."""
    sigma_t, albedo = stiff_scene()
    kw = dict(g=0.4, ior=1.5, face="top")
    f = fast_hero(sigma_t, albedo, seed=14, **kw)
    r = reference_render_texels(sigma_t, albedo, voxel_size=VOXEL, environment=ENVIRONMENT, spp=REFERENCE_SPP,
                                seed=14, **kw)
    assert_matches_reference(f, r)
    # float32 (where exp overflows at 88): the same expectation, and the gradient replay (floored chromatic
    # reference, hero walk) stays finite in both precisions
    with torch.no_grad():
        f32 = np.stack([ta.render_texels(torch.from_numpy(sigma_t).float(), torch.from_numpy(albedo).float(),
                                         voxel_size=VOXEL, environment=ENVIRONMENT, spp=FAST_SPP, seed=k,
                                         chromatic="hero", **kw).double().numpy() for k in range(8)])
    assert np.isfinite(f32).all()
    assert_matches_reference((f32.mean(0), f32.std(0, ddof=1) / np.sqrt(8)), r)
    for dtype in (torch.float32, torch.float64):
        s = torch.from_numpy(sigma_t).to(dtype).requires_grad_()
        a = torch.from_numpy(albedo).to(dtype).requires_grad_()
        ta.render_texels(s, a, voxel_size=VOXEL, g=0.4, ior=1.5, spp=64, seed=3, chromatic="hero").sum().backward()
        assert torch.isfinite(s.grad).all() and torch.isfinite(a.grad).all()
        assert (a.grad != 0).any() and (s.grad != 0).any()


def grad_scene(seed=1, shape=(2, 2, 3)):
    g = torch.Generator().manual_seed(seed)
    sigma = torch.rand(3, *shape, generator=g, dtype=torch.float64) * 25 + 1
    albedo = torch.rand(3, *shape, generator=g, dtype=torch.float64) * 0.85 + 0.1
    return sigma, albedo


@pytest.mark.parametrize("ior", [None, 1.5])
def test_hero_gradcheck_explicit_reference(ior):
    """Fixed seed, explicit chromatic reference: the hero estimator is smooth and backward is its derivative."""
    sigma, albedo = grad_scene(1)
    ref_s = (sigma * torch.tensor([1.2, 0.8, 1.0], dtype=torch.float64).view(3, 1, 1, 1)).detach()
    ref_a = (albedo * 0.9 + 0.05).detach()

    def f(s, a):
        return ta.render_texels(s, a, voxel_size=0.1, face="both", ior=ior, g=0.3, spp=32, seed=11,
                                sampling_sigma_t=ref_s, sampling_albedo=ref_a, rr_depth=2, chromatic="hero")

    inputs = (sigma.clone().requires_grad_(), albedo.clone().requires_grad_())
    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-7, rtol=1e-4)


def test_hero_default_gradient_matches_per_channel():
    """The default gradient (floored replay) of the hero estimator has the same mean over seeds as the per-channel
    estimator's (each seed independent; z-test of the difference of the means, all entries)."""
    sigma, albedo = grad_scene(3, shape=(3, 2, 2))
    kw = dict(voxel_size=0.1, ior=1.5, g=0.4, face="both", spp=128)
    weights = torch.rand(2, 2, 2, 3, generator=torch.Generator().manual_seed(9), dtype=torch.float64)

    def grad(chromatic, offset):
        def run(seed):
            s, a = sigma.clone().requires_grad_(), albedo.clone().requires_grad_()
            (ta.render_texels(s, a, seed=offset + seed, chromatic=chromatic, **kw) * weights).sum().backward()
            return torch.cat([s.grad.flatten(), a.grad.flatten()])
        return run

    h_mean, h_se = seed_stats(grad("hero", 0), range(24))
    p_mean, p_se = seed_stats(grad("per_channel", 500), range(24))
    assert_z(h_mean - p_mean, (h_se ** 2 + p_se ** 2).sqrt(), 0.0, family_alpha=1e-3,
             what="hero gradient − per-channel gradient")
    assert float((p_mean.abs() / p_se).median()) > 5  # the gradients are clearly resolved: the test has power


def test_hero_reproducible_thread_independent_and_replays_agree():
    sigma, albedo = grad_scene(4, shape=(3, 4, 5))
    kw = dict(voxel_size=0.1, ior=1.5, g=0.4, spp=8, seed=21, chromatic="hero")
    old = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = ta.render_texels(sigma, albedo, **kw)
        torch.set_num_threads(2)
        two = ta.render_texels(sigma, albedo, **kw)
    finally:
        torch.set_num_threads(old)
    assert torch.equal(one, two) and torch.equal(one, ta.render_texels(sigma, albedo, **kw))
    assert not torch.equal(one, ta.render_texels(sigma, albedo, **{**kw, "seed": 22}))
    assert not torch.equal(one, ta.render_texels(sigma, albedo, **{**kw, "chromatic": "per_channel"}))

    def grads():
        s, a = sigma.clone().requires_grad_(), albedo.clone().requires_grad_()
        (ta.render_texels(s, a, **kw) ** 2).sum().backward()
        return s.grad, a.grad

    tape = grads()
    previous = _C._set_tape_capacity(0)  # every path takes the two-pass replay
    try:
        two_pass = grads()
    finally:
        _C._set_tape_capacity(previous)
    assert torch.equal(tape[0], two_pass[0]) and torch.equal(tape[1], two_pass[1])
    assert float((tape[0] != 0).double().mean()) > 0.5


def test_hero_on_achromatic_medium_is_the_shared_walk():
    """An achromatic sampling density already takes one walk; "hero" changes nothing there."""
    sigma, albedo = grad_scene(5)
    sigma = sigma[:1].expand(3, -1, -1, -1).contiguous()
    st = {}
    a = ta.render_texels(sigma, albedo, voxel_size=0.1, spp=4, seed=2, chromatic="hero", stats=st)
    assert st["lanes"] == 3 and not st["hero"]
    assert torch.equal(a, ta.render_texels(sigma, albedo, voxel_size=0.1, spp=4, seed=2))


def test_chromatic_option_is_validated():
    sigma, albedo = grad_scene(6)
    with pytest.raises(ValueError, match="chromatic"):
        ta.render_texels(sigma, albedo, voxel_size=0.1, spp=1, chromatic="spectral")
    with pytest.raises(TypeError, match="chromatic"):
        ta.render_texels(sigma, albedo, voxel_size=0.1, spp=1, chromatic=1)
    from torch_appearance.render import Scene
    scene = Scene(voxel_size=0.1)
    with pytest.raises(ValueError, match="chromatic"):
        ta.render_scene(scene, sigma, albedo, spp=1, chromatic="Hero")
    st = {}
    image = ta.render_scene(scene, sigma, albedo, spp=2, chromatic="hero", stats=st)
    assert st["hero"] and torch.isfinite(image).all()


@pytest.mark.parametrize("case", ["sdf-1.5-texels-envmap", "sdf-matched-orthographic-disc"])
def test_hero_scene_matches_reference(case):
    """General scenes (SDF sphere, surface texels or a camera, direction-dependent emitters): the hero walk's
    escape direction and weights against the reference's per-channel delta tracking."""
    from torch_appearance.testing.reference_tracer import reference_render_scene
    from test_scene_reference import CASES, H, ORIGIN, CENTRE, RADIUS, N, medium, ours, reference_dicts
    from torch_appearance.geometry import sphere_sdf
    from torch_appearance.render import Scene
    name, boundary, ior, sensor, emitter, g, scale = next(c for c in CASES if c[0] == case)
    sigma, albedo = medium(scale)
    b, s, e = ours(boundary, ior, sensor, emitter)
    scene = Scene(voxel_size=H, origin=ORIGIN, boundary=b, sensor=s, emitter=e, g=g)
    st = {}
    xs = torch.stack([ta.render_scene(scene, sigma, albedo, spp=128, seed=k, chromatic="hero", stats=st)
                      for k in range(32)])
    assert st["hero"]
    mean, se = xs.mean(0), xs.std(0) / 32 ** 0.5
    rs, re = reference_dicts(sensor, emitter)
    sdf = sphere_sdf((N,) * 3, H, ORIGIN, CENTRE, RADIUS).numpy()
    ref_mean, ref_se = reference_render_scene(sigma.numpy(), albedo.numpy(), voxel_size=H, origin=ORIGIN, g=g,
                                              boundary=boundary, sdf=sdf, ior=ior, sensor=rs, emitter=re, spp=4096,
                                              rng=np.random.default_rng(12))
    ref_mean, ref_se = torch.as_tensor(ref_mean), torch.as_tensor(ref_se)
    flat = (se == 0) & (ref_se == 0)  # pixels that see only the emitter: exact in both
    assert torch.allclose(mean[flat], ref_mean[flat], rtol=1e-5, atol=1e-6)
    assert_z(mean - ref_mean, (se ** 2 + ref_se ** 2).sqrt().clamp_min(1e-12), 0.0, what=f"hero {name}")
