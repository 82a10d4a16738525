"""Forward pass against exact physics: Beer–Lambert, white furnace, energy bounds, mirror symmetry."""
import math

import pytest
import torch

import torch_appearance as ta
from torch_appearance.testing import assert_z, seed_stats

INK_SIGMA = (2.25, 3.75, 19.0)  # Vero yellow: strongly chromatic extinction, mm⁻¹


def uniform(shape, values, dtype=torch.float64):
    return torch.tensor(values, dtype=dtype).view(3, 1, 1, 1).expand(3, *shape).contiguous()


def beer_lambert_expected(sigma, thickness, ior):
    t = torch.exp(-torch.tensor(sigma, dtype=torch.float64) * thickness)
    if ior is None:
        return t
    r = ((ior - 1) / (ior + 1)) ** 2
    return r + (1 - r) ** 2 * t / (1 - r * t)


@pytest.mark.parametrize("ior", [None, 1.5])
@pytest.mark.parametrize("face", ["top", "bottom", "both"])
def test_beer_lambert_chromatic(ior, face, dtype):
    """Albedo 0: a path is either transmitted (value 1) or absorbed, so per-sample variance is p(1 − p)."""
    shape, s = (5, 4, 6), 0.1
    sigma = uniform(shape, INK_SIGMA, dtype) * 0.4  # optical depths 0.45, 0.75, 3.8
    albedo = torch.zeros_like(sigma)
    spp = 4096
    img = ta.render_texels(sigma, albedo, voxel_size=s, face=face, ior=ior, spp=spp, seed=7)
    expected = beer_lambert_expected([0.4 * v for v in INK_SIGMA], shape[0] * s, ior)
    # per texel and channel: Bernoulli-like (value 0 or 1) => stderr = sqrt(p(1-p)/spp)
    p = expected.expand_as(img.double())
    stderr = (p * (1 - p) / spp).sqrt()
    assert_z(img, stderr, p, what=f"Beer–Lambert ior={ior} face={face}")


@pytest.mark.parametrize("ior", [None, 1.5, 3.0])
def test_white_furnace_heterogeneous(ior, dtype):
    """Albedo 1 in a uniform environment: every texel equals the environment, for any σ_t field."""
    g = torch.Generator().manual_seed(1)
    shape = (4, 5, 5)
    sigma = torch.rand(3, *shape, generator=g, dtype=torch.float64) * 30
    sigma[:, 0, 0, 0] = 1e-4
    sigma[:, 1, 2, 3] = 50.0
    sigma[0, 2, 1, 1] = 1e-4
    sigma[2, 3, 4, 4] = 0.0
    sigma = sigma.to(dtype)
    albedo = torch.ones_like(sigma)
    env = (0.5, 1.0, 2.0)
    img = ta.render_texels(sigma, albedo, voxel_size=0.1, face="both", ior=ior, environment=env, spp=256, seed=3)
    expected = torch.tensor(env, dtype=dtype).expand_as(img)
    # each path returns exactly 0 or env (no path here gets near max_depth), so equality is exact
    torch.testing.assert_close(img, expected, rtol=1e-6, atol=0)


@pytest.mark.parametrize("ior", [None, 1.5])
def test_white_furnace_achromatic_one_walk(ior):
    """Achromatic σ_t takes the one-walk path (lanes = 3); the furnace still holds exactly."""
    g = torch.Generator().manual_seed(2)
    sigma = (torch.rand(1, 3, 4, 4, generator=g) * 40).expand(3, -1, -1, -1).contiguous()
    stats = {}
    img = ta.render_texels(sigma, torch.ones_like(sigma), voxel_size=0.2, ior=ior, spp=256, stats=stats)
    assert stats["lanes"] == 3
    torch.testing.assert_close(img, torch.ones_like(img), rtol=1e-6, atol=0)


def test_dense_white_slab_energy_loss_below_documented_bound():
    """Default max_depth: a white-furnace slab 2.5 mm thick at σ_t = 24 mm⁻¹ (ior 1.5) loses < 0.1 % of its energy.

    The slab is wide (6.4 mm) so that the centre texels see the long diffusive paths of an infinite slab; a
    truncation at 1024 interactions visibly loses energy there, which shows the scene is stiff enough to matter.
    """
    sigma = torch.full((3, 25, 64, 64), 24.0)
    kw = dict(voxel_size=0.1, ior=1.5, spp=8, seed=5)
    centre = (slice(16, 48), slice(16, 48))
    loss = 1.0 - float(ta.render_texels(sigma, torch.ones_like(sigma), **kw)[centre].double().mean())
    assert 0.0 <= loss < 1e-3, f"energy loss {loss:.3g} with the default max_depth"
    with pytest.warns(RuntimeWarning, match="cut at max_depth=1024"):
        short = ta.render_texels(sigma, torch.ones_like(sigma), max_depth=1024, **kw)
    short = 1.0 - float(short[centre].double().mean())
    assert short > 1e-2, f"max_depth=1024 should truncate long paths here, lost only {short:.3g}"


def test_energy_bounds_and_monotonicity():
    """0 <= L <= environment; more absorption never brightens (same seed, common random numbers, one lane)."""
    g = torch.Generator().manual_seed(4)
    sigma = torch.rand(3, 4, 6, 6, generator=g, dtype=torch.float64) * 20 + 0.5
    albedo = torch.rand(3, 4, 6, 6, generator=g, dtype=torch.float64)
    img = ta.render_texels(sigma, albedo, voxel_size=0.1, ior=1.5, spp=64, face="both")
    assert bool((img >= 0).all()) and bool((img <= 1).all())
    darker = ta.render_texels(sigma, albedo * 0.5, voxel_size=0.1, ior=1.5, spp=256, seed=9)
    brighter = ta.render_texels(sigma, albedo, voxel_size=0.1, ior=1.5, spp=256, seed=9)
    assert float(darker.mean()) < float(brighter.mean())


def test_top_bottom_mirror_symmetry():
    """The bottom view of a medium equals the top view of the z-mirrored medium (in distribution)."""
    g = torch.Generator().manual_seed(6)
    sigma = torch.rand(3, 4, 3, 3, generator=g, dtype=torch.float64) * 20 + 1
    albedo = torch.rand(3, 4, 3, 3, generator=g, dtype=torch.float64) * 0.5 + 0.5
    kw = dict(voxel_size=0.1, ior=1.5, spp=512, g=0.6)
    bottom, se_b = seed_stats(lambda s: ta.render_texels(sigma, albedo, face="bottom", seed=s, **kw), range(8))
    top, se_t = seed_stats(lambda s: ta.render_texels(sigma.flip(1), albedo.flip(1), face="top", seed=100 + s, **kw),
                           range(8))
    assert_z(bottom - top, (se_b ** 2 + se_t ** 2).sqrt(), 0.0, what="bottom vs mirrored top")


def test_index_matched_vacuum_is_transparent():
    """σ_t = 0 everywhere: every path crosses unchanged, radiance = environment."""
    sigma = torch.zeros(3, 2, 3, 3)
    img = ta.render_texels(sigma, torch.zeros_like(sigma), voxel_size=1.0, ior=None, environment=0.7, spp=8)
    torch.testing.assert_close(img, torch.full_like(img, 0.7))


def test_layered_slab_beer_lambert_heterogeneous_in_depth():
    """Transmittance multiplies through layers of different σ_t: exp(−Σ σ_k s) per channel."""
    layers = torch.tensor([0.5, 4.0, 1e-4, 12.0, 0.0], dtype=torch.float64)
    sigma = layers.view(1, -1, 1, 1).expand(3, -1, 2, 2).contiguous() * torch.tensor([1.0, 0.5, 0.25],
                                                                                       dtype=torch.float64).view(3, 1, 1, 1)
    spp = 8192
    img = ta.render_texels(sigma, torch.zeros_like(sigma), voxel_size=0.05, ior=None, spp=spp, face="both")
    p = torch.exp(-(sigma[:, :, 0, 0].sum(1) * 0.05)).expand_as(img)
    assert_z(img, (p * (1 - p) / spp).sqrt(), p, what="layered Beer–Lambert")
    assert math.isclose(float(p[0, 0, 0, 0]), math.exp(-16.5001 * 0.05), rel_tol=1e-9)


@pytest.mark.parametrize("ior", [None, 1.5])
def test_anisotropic_voxels_beer_lambert_and_furnace(ior):
    """Anisotropic voxels (printer-native 600 × 300 × 940 DPI): thickness is D·sz; the furnace holds."""
    edges = (25.4 / 600, 25.4 / 300, 25.4 / 940)
    sigma = uniform((37, 4, 5), INK_SIGMA)
    img = ta.render_texels(sigma, torch.ones_like(sigma), voxel_size=edges, ior=ior, spp=64, face="both")
    torch.testing.assert_close(img, torch.ones_like(img), rtol=1e-6, atol=0)
    spp = 4096
    img = ta.render_texels(sigma * 0.3, torch.zeros_like(sigma), voxel_size=edges, ior=ior, spp=spp, seed=2)
    p = beer_lambert_expected([0.3 * v for v in INK_SIGMA], 37 * edges[2], ior).expand_as(img)
    assert_z(img, (p * (1 - p) / spp).sqrt(), p, what="anisotropic Beer–Lambert")


def test_anisotropic_voxels_equal_refined_isotropic_grid():
    """A (2s, s, s) voxel grid equals the isotropic s grid with each voxel split in two along x (scattering,
    chromatic, dielectric): each coarse texel is the mean of its two fine texels, in distribution."""
    g = torch.Generator().manual_seed(8)
    s = 0.1
    sigma = torch.rand(3, 3, 3, 2, generator=g, dtype=torch.float64) * 20 + 1
    albedo = torch.rand(3, 3, 3, 2, generator=g, dtype=torch.float64) * 0.5 + 0.5
    kw = dict(ior=1.5, g=0.5, spp=256, face="both")
    coarse, se_c = seed_stats(lambda k: ta.render_texels(sigma, albedo, voxel_size=(2 * s, s, s), seed=k, **kw),
                              range(16))
    fine_sigma, fine_albedo = sigma.repeat_interleave(2, dim=3), albedo.repeat_interleave(2, dim=3)
    fine, se_f = seed_stats(lambda k: ta.render_texels(fine_sigma, fine_albedo, voxel_size=s, seed=100 + k, **kw)
                            .unflatten(2, (2, 2)).mean(3), range(16))
    assert_z(coarse - fine, (se_c ** 2 + se_f ** 2).sqrt(), 0.0, what="anisotropic vs refined grid")
