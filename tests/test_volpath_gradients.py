"""Backward pass (radiative backpropagation by path replay) against finite differences and exact physics."""
import math

import pytest
import torch

import torch_appearance as ta
from torch_appearance.testing import assert_z, seed_stats


def scene(seed=0, shape=(2, 2, 3), chromatic=True, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    n = 3 if chromatic else 1
    sigma = (torch.rand(n, *shape, generator=g, dtype=dtype) * 25 + 1).expand(3, *shape).contiguous()
    albedo = torch.rand(3, *shape, generator=g, dtype=dtype) * 0.85 + 0.1
    return sigma, albedo


@pytest.mark.parametrize("ior", [None, 1.5])
@pytest.mark.parametrize("chromatic", [True, False], ids=["chromatic", "achromatic"])
def test_gradcheck_explicit_reference(ior, chromatic):
    """With an explicit sampling medium and a fixed seed the estimator is smooth and backward is its derivative."""
    sigma, albedo = scene(1, chromatic=chromatic)
    ref_s = (sigma * 1.2).detach()  # differs from the parameters: ratio weights are exercised
    ref_a = (albedo * 0.9 + 0.05).detach()

    def f(s, a):
        return ta.render_texels(s, a, voxel_size=0.1, face="both", ior=ior, g=0.3, spp=32, seed=11,
                                sampling_sigma_t=ref_s, sampling_albedo=ref_a, rr_depth=2)

    inputs = (sigma.clone().requires_grad_(), albedo.clone().requires_grad_())
    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-7, rtol=1e-4)


def test_exact_derivative_at_zero_sigma_and_zero_albedo_voxels():
    """σ_t = 0 and albedo = 0 voxels get the exact derivative (zero-safe replay) when the reference is > 0 there.

    gradcheck's central differences would step below 0, so the zero entries are checked against one-sided
    differences of the (smooth, fixed-seed, explicit-reference) estimator.
    """
    sigma, albedo = scene(2)
    sigma[:, 0, 0, 0] = 0.0
    albedo[:, 1, 1, 2] = 0.0
    ref_s = sigma.detach().clamp_min(3.0)
    ref_a = albedo.detach().clamp_min(0.2)
    weights = linear_objective((2, 3, 3))

    def f(s, a):
        return float((ta.render_texels(s, a, voxel_size=0.1, ior=1.5, spp=256, seed=5, sampling_sigma_t=ref_s,
                                       sampling_albedo=ref_a) * weights).sum())

    s, a = sigma.clone().requires_grad_(), albedo.clone().requires_grad_()
    (ta.render_texels(s, a, voxel_size=0.1, ior=1.5, spp=256, seed=5, sampling_sigma_t=ref_s,
                      sampling_albedo=ref_a) * weights).sum().backward()
    h, base = 1e-7, f(sigma, albedo)
    for c in range(3):
        sp = sigma.clone()
        sp[c, 0, 0, 0] = h
        fd = (f(sp, albedo) - base) / h
        assert fd != 0.0
        assert math.isclose(float(s.grad[c, 0, 0, 0]), fd, rel_tol=1e-4), (c, float(s.grad[c, 0, 0, 0]), fd)
        ap = albedo.clone()
        ap[c, 1, 1, 2] = h
        fd = (f(sigma, ap) - base) / h
        assert fd != 0.0
        assert math.isclose(float(a.grad[c, 1, 1, 2]), fd, rel_tol=1e-4), (c, float(a.grad[c, 1, 1, 2]), fd)


def linear_objective(shape, seed=123):
    g = torch.Generator().manual_seed(seed)
    return torch.rand(*shape, generator=g, dtype=torch.float64)


@pytest.mark.slow
@pytest.mark.parametrize("ior,chromatic", [(1.5, True), (None, False)])
def test_default_gradient_unbiased_against_finite_differences(ior, chromatic):
    """Mean of the default (detached-sampling, floored replay) gradient over 24 seeds equals the central finite
    difference of the expectation (common random numbers, explicit reference) within 4 standard errors."""
    sigma, albedo = scene(3, shape=(3, 2, 2), chromatic=chromatic)
    kw = dict(voxel_size=0.1, ior=ior, g=0.4, face="both")
    weights = linear_objective((2, 2, 2, 3))

    def grad(seed):
        s, a = sigma.clone().requires_grad_(), albedo.clone().requires_grad_()
        (ta.render_texels(s, a, spp=256, seed=seed, **kw) * weights).sum().backward()
        return torch.cat([s.grad.flatten(), a.grad.flatten()])

    g_mean, g_se = seed_stats(grad, range(24))

    # entries checked by finite differences: σ_t and albedo of a few voxels, all channels
    n = sigma.numel()
    entries = [0, 5, n // 2 + 1, n - 1, n + 0, n + 4, n + n // 2, 2 * n - 2]
    ref_s, ref_a = sigma.clone(), albedo.clone()
    h = 1e-4

    def fd(seed):
        out = []
        for e in entries:
            vals = []
            for sign in (1, -1):
                s, a = sigma.clone(), albedo.clone()
                (s if e < n else a).view(-1)[e % n] += sign * h
                img = ta.render_texels(s, a, spp=512, seed=1000 + seed, sampling_sigma_t=ref_s,
                                       sampling_albedo=ref_a, **kw)
                vals.append(float((img * weights).sum()))
            out.append((vals[0] - vals[1]) / (2 * h))
        return torch.tensor(out, dtype=torch.float64)

    f_mean, f_se = seed_stats(fd, range(16))
    idx = torch.tensor(entries)
    assert_z(g_mean[idx] - f_mean, (g_se[idx] ** 2 + f_se ** 2).sqrt(), 0.0, family_alpha=1e-4,
             what="default gradient − finite difference")
    # the test has power: the gradients are clearly non-zero compared with their errors
    assert float((f_mean.abs() / f_se).median()) > 5


def test_gradient_beer_lambert_exact():
    """Albedo 0, uniform σ: ∂T/∂σ_t summed over a texel's column is −L·T exactly (T = exp(−σ L)); other voxels 0."""
    D, s = 4, 0.1
    sigma = torch.full((3, D, 2, 2), 5.0, dtype=torch.float64).mul_(torch.tensor([0.5, 1.0, 3.0],
                                                                                 dtype=torch.float64).view(3, 1, 1, 1))
    sigma.requires_grad_()
    albedo = torch.zeros_like(sigma, requires_grad=True)
    mask = torch.zeros(2, 2, 3, dtype=torch.float64)
    mask[1, 0] = 1.0  # only texel (j=1, i=0)
    img = ta.render_texels(sigma, albedo, voxel_size=s, ior=None, spp=20000, seed=2)
    (img * mask).sum().backward()
    L = D * s
    T = torch.exp(-sigma.detach()[:, 0, 0, 0] * L)
    column = sigma.grad[:, :, 1, 0].sum(1)
    # per path the column derivative is −L·(transmitted ? 1 : 0) (+ collision terms that vanish at albedo 0):
    # a Bernoulli(T) scaled by L, so stderr = L·sqrt(T(1−T)/spp)
    se = L * (T * (1 - T) / 20000).sqrt()
    assert_z(column, se, -L * T, what="column ∂T/∂σ_t")
    others = sigma.grad.clone()
    others[:, :, 1, 0] = 0
    assert float(others.abs().max()) == 0.0
    # albedo derivative: d/dα of the transmitted light at α = 0 is the single-scattering contribution, > 0
    assert float(albedo.grad[:, :, 1, 0].sum()) > 0


def test_only_requested_gradients_are_computed():
    sigma, albedo = scene(4, dtype=torch.float32)
    s = sigma.clone().requires_grad_()
    stats = {}
    ta.render_texels(s, albedo, voxel_size=0.1, spp=4, stats=stats).sum().backward()
    assert s.grad is not None and albedo.grad is None
    a = albedo.clone().requires_grad_()
    img = ta.render_texels(sigma, a, voxel_size=0.1, spp=4)
    img.sum().backward()
    assert a.grad is not None and float(a.grad.abs().sum()) > 0
    stats = {}
    img = ta.render_texels(sigma, albedo, voxel_size=0.1, spp=4, stats=stats)
    assert not img.requires_grad and "backward_s" not in stats


@pytest.mark.parametrize("sigma_value", [0.0, 1e-6, 1e4])
@pytest.mark.parametrize("albedo_value", [0.0, 1.0])
@pytest.mark.parametrize("g,ior", [(-0.99, 1.0), (0.99, 3.0), (0.4, None)])
def test_stiff_inputs_finite(sigma_value, albedo_value, g, ior, dtype):
    """Extreme σ_t, albedo, g and ior: finite, bounded outputs and finite gradients; references still hold."""
    shape = (3, 3, 3)
    sigma = torch.full((3, *shape), sigma_value, dtype=dtype)
    sigma[:, 1, 1, 1] = 10.0  # one ordinary voxel in the middle
    albedo = torch.full((3, *shape), albedo_value, dtype=dtype)
    s, a = sigma.clone().requires_grad_(), albedo.clone().requires_grad_()
    # 1e4 mm⁻¹ over 0.3 mm is 3000 mean free paths: with albedo 1 the path-length tail reaches ~(3000)² interactions
    # (see test_truncation_is_reported); a large max_depth keeps the furnace exact
    img = ta.render_texels(s, a, voxel_size=0.1, g=g, ior=ior, spp=64, face="both", max_depth=10 ** 9)
    assert bool(torch.isfinite(img).all()) and bool((img >= 0).all()) and bool((img <= 1 + 1e-6).all())
    if albedo_value == 1.0:  # white furnace
        torch.testing.assert_close(img, torch.ones_like(img), rtol=1e-5, atol=0)
    (img * linear_objective(img.shape).to(dtype)).sum().backward()
    assert bool(torch.isfinite(s.grad).all()) and bool(torch.isfinite(a.grad).all())
    # the floors bound the replay's 1/σ̂ and 1/p_s factors
    bound = 64 * 2 * 9 * 3 / 0.05 * 100
    assert float(s.grad.abs().max()) < bound and float(a.grad.abs().max()) < bound


@pytest.mark.slow
def test_floor_gives_unbiased_bounded_gradient_for_thin_voxels():
    """σ_t → 0: the default density floor keeps the gradient unbiased with bounded variance.

    A thin layer (σ_t = 1e-2 or 1e-6 mm⁻¹) above a dense scattering layer. ∂/∂σ_t of the thin layer has an
    attenuation term and an in-scattering (collision) term. Sampling the thin voxels at their own density almost
    never samples the collision term (probability ~σ_t·ℓ, weight 1/σ_t: unbounded variance, and in practice the
    term is simply missing); the floored replay samples it at a bounded rate with a bounded weight.
    """
    weights = linear_objective((2, 2, 3))
    kw = dict(voxel_size=0.1, ior=None, g=0.0)
    ses = {}
    for thin in (1e-2, 1e-6):
        sigma = torch.full((3, 4, 2, 2), thin, dtype=torch.float64)
        sigma[:, 2:] = 5.0
        albedo = torch.full_like(sigma, 0.9)

        def grad(seed, floor):
            s = sigma.clone().requires_grad_()
            (ta.render_texels(s, albedo, spp=128, seed=seed, sigma_t_floor=floor, **kw) * weights).sum().backward()
            return s.grad[:, :2].sum().reshape(1)

        mean_f, se_f = seed_stats(lambda k: grad(k, None), range(24))
        ses[thin] = float(se_f)
        # reference: central difference of the expectation along "all thin voxels", common random numbers
        ref_s = sigma.clamp_min(0.5 / (0.1 * math.sqrt(4 ** 2 + 2 ** 2 + 2 ** 2)))  # = the default floor
        h = thin / 2
        step = torch.zeros_like(sigma)
        step[:, :2] = h

        def fd(seed):
            vals = [float((ta.render_texels(sigma + sign * step, albedo, spp=512, seed=500 + seed,
                                            sampling_sigma_t=ref_s, sampling_albedo=albedo, **kw) * weights).sum())
                    for sign in (1, -1)]
            return torch.tensor([(vals[0] - vals[1]) / (2 * h)], dtype=torch.float64)

        mean_fd, se_fd = seed_stats(fd, range(12))
        assert_z(mean_f - mean_fd, (se_f ** 2 + se_fd ** 2).sqrt(), 0.0, n_tests=4, what=f"thin σ_t={thin}")
        if thin == 1e-6:  # without the floor the collision term is (almost surely) never sampled
            mean_0, _ = seed_stats(lambda k: grad(k, 0.0), range(24))
            assert abs(float(mean_0 - mean_fd)) > 10 * float((se_f ** 2 + se_fd ** 2).sqrt())
    assert ses[1e-6] < 2.0 * ses[1e-2], ses  # variance does not grow as σ_t → 0


def test_truncation_is_reported():
    """Paths cut by max_depth are counted in stats and warned about: the bias is never silent."""
    sigma = torch.full((3, 3, 3, 3), 1e3)
    stats = {}
    with pytest.warns(RuntimeWarning, match="max_depth"):
        img = ta.render_texels(sigma, torch.ones_like(sigma), voxel_size=0.1, spp=32, max_depth=50, stats=stats)
    lost = 1.0 - float(img.double().mean())
    walks = 9 * 32  # achromatic σ_t: one walk per sample serves all channels
    assert stats["truncated_paths"] > 0 and lost == pytest.approx(stats["truncated_paths"] / walks)
