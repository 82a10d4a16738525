"""Tests of the ink library (torch_appearance.fabrication.inks) and the ink mixture (torch_appearance.nn.mixture)."""
import json
import math

import numpy as np
import pytest
import torch

import torch_appearance as ta
from torch_appearance.fabrication import DEFAULT_INKS, INKS, Ink, InkSet
from torch_appearance.nn import FixedFraction, MaterialMixture, mix_inks

# Issue 3 / Nindel et al. 2021, Table 2, typed in again independently: name, μ_t (mm⁻¹) RGB, α RGB.
TABLE = {
    "cyan": ((9.0, 4.5, 7.5), (0.05, 0.7, 0.98)),
    "cyan2": ((6.0, 3.0, 5.0), (0.05, 0.95, 0.98)),
    "magenta": ((2.5, 3.0, 10.0), (0.98, 0.1, 0.9)),
    "magenta2": ((1.7, 2.0, 6.7), (0.98, 0.05, 0.97)),
    "yellow": ((2.25, 3.75, 19.0), (0.997, 0.995, 0.15)),
    "yellow2": ((3.0, 5.0, 19.0), (0.92, 0.92, 0.15)),
    "orange": ((3.0, 4.0, 15.0), (0.98, 0.32, 0.114)),
    "black": ((5.0, 5.5, 6.5), (0.35, 0.35, 0.35)),
    "white": ((6.0, 9.0, 24.0), (0.9991, 0.9997, 0.999)),
    "transparent": ((1e-4, 1e-4, 1e-4), (1.0, 1.0, 1.0)),
}


def _reference_mix(weights, inks):
    """Eq. 9 written out per voxel and channel with Python floats (slow, obviously correct)."""
    n, d, h, w = weights.shape
    sigma_t = torch.zeros(3, d, h, w, dtype=torch.float64)
    albedo = torch.zeros(3, d, h, w, dtype=torch.float64)
    for z in range(d):
        for y in range(h):
            for x in range(w):
                for c in range(3):
                    s = sum(float(weights[k, z, y, x]) * inks[k].albedo[c] * inks[k].sigma_t[c] for k in range(n))
                    a = sum(float(weights[k, z, y, x]) * (1 - inks[k].albedo[c]) * inks[k].sigma_t[c]
                            for k in range(n))
                    sigma_t[c, z, y, x] = s + a
                    albedo[c, z, y, x] = s / (s + a)
    return sigma_t, albedo


# ----------------------------------------------------------------------------------------------------------------
# inks
# ----------------------------------------------------------------------------------------------------------------
def test_builtin_table_matches_the_issue():
    assert sorted(INKS) == sorted(TABLE)
    for name, (mu, alpha) in TABLE.items():
        ink = INKS[name]
        assert ink.name == name and ink.sigma_t == mu and ink.albedo == alpha and ink.g == 0.4
    assert DEFAULT_INKS == ("cyan", "magenta", "yellow", "black", "white")
    colours = {tuple(round(255 * v) for v in ink.display_rgb) for ink in INKS.values()}
    assert len(colours) == len(INKS), "built-in palette colours must be distinct"


def test_inkset_from_names_and_lookup():
    inks = InkSet.from_names(["Cyan", " MAGENTA ", "yellow", "Black", "white"])
    assert inks.names == DEFAULT_INKS and len(inks) == 5
    assert inks == InkSet.from_names() == InkSet.from_names("cyan,magenta,yellow,black,white")
    assert inks.index("WHITE") == 4 and inks.index(INKS["cyan"]) == 0
    assert "Black" in inks and "orange" not in inks and INKS["yellow"] in inks
    assert inks[1] is INKS["magenta"] and isinstance(inks[1:3], InkSet) and inks[1:3].names == ("magenta", "yellow")
    assert inks.g == 0.4
    with pytest.raises(ValueError, match=r"names\[1\]: unknown ink 'teal'; known inks are \[.*'cyan'.*'white'"):
        InkSet.from_names(["cyan", "teal"])
    with pytest.raises(ValueError, match="duplicates \\['cyan'\\]"):
        InkSet.from_names(["cyan", "CYAN"])
    with pytest.raises(ValueError, match="'orange' is not in this ink set"):
        inks.index("orange")
    with pytest.raises(TypeError, match=r"inks\[0\]: expected an Ink"):
        InkSet(["cyan"])
    with pytest.raises(ValueError, match="1 to 256 inks"):
        InkSet([])


def test_inkset_tensors(dtype):
    inks = InkSet.from_names(["cyan", "white", "transparent"])
    mu = torch.tensor([TABLE[n][0] for n in inks.names], dtype=torch.float64)
    alpha = torch.tensor([TABLE[n][1] for n in inks.names], dtype=torch.float64)
    for got, want in ((inks.sigma_t(dtype), mu), (inks.albedo(dtype), alpha), (inks.sigma_s(dtype), alpha * mu),
                      (inks.sigma_a(dtype), (1 - alpha) * mu)):
        assert got.dtype == dtype and got.shape == (3, 3)
        torch.testing.assert_close(got, want.to(dtype), rtol=0, atol=0)


def test_inks_with_different_g_have_no_common_g():
    inks = InkSet([INKS["white"], Ink("fog", (1.0, 1.0, 1.0), (0.9, 0.9, 0.9), g=0.0)])
    with pytest.raises(ValueError, match=r"g = \[0.0, 0.4\]"):
        inks.g


@pytest.mark.parametrize("kwargs, error, message", [
    (dict(albedo=(0.5, 1.2, 0.5)), ValueError, r"albedo: expected finite values in \[0, 1\], got \[0.5, 1.2, 0.5\]"),
    (dict(albedo=(0.5, -0.1, 0.5)), ValueError, r"albedo: expected finite values in \[0, 1\]"),
    (dict(sigma_t=(1.0, -2.0, 1.0)), ValueError, r"sigma_t \(mm⁻¹\): expected finite values in \[0, inf\)"),
    (dict(sigma_t=(1.0, math.nan, 1.0)), ValueError, r"sigma_t \(mm⁻¹\): expected finite values"),
    (dict(sigma_t=(1.0, 2.0)), ValueError, r"sigma_t \(mm⁻¹\): expected 3 values \(R, G, B\), got 2"),
    (dict(albedo=(0.5, 0.5, 0.5, 0.5)), ValueError, r"albedo: expected 3 values \(R, G, B\), got 4"),
    (dict(sigma_t="abc"), TypeError, r"sigma_t \(mm⁻¹\): expected a sequence of 3 real numbers, got str"),
    (dict(albedo=(0.5, "x", 0.5)), TypeError, r"albedo: expected real numbers"),
    (dict(g=1.0), ValueError, r"g: expected a finite value in \(-1, 1\), got 1.0"),
    (dict(display_rgb=(0, 0, 2)), ValueError, r"display_rgb \(sRGB\): expected finite values in \[0, 1\]"),
    (dict(name=""), ValueError, r"name: expected a non-empty string"),
    (dict(name=3), TypeError, r"name: expected a str, got int"),
])
def test_ink_refusals(kwargs, error, message):
    args = dict(name="test", sigma_t=(1.0, 2.0, 3.0), albedo=(0.5, 0.5, 0.5))
    args.update(kwargs)
    with pytest.raises(error, match=message):
        Ink(**args)


def test_ink_default_display_rgb_and_coefficients():
    ink = Ink("grey", sigma_t=[5, 5, 5], albedo=np.array([0.6, 0.6, 0.6]))
    assert ink.sigma_t == (5.0, 5.0, 5.0) and isinstance(ink.albedo, tuple)
    assert ink.sigma_s == (3.0, 3.0, 3.0) and ink.sigma_a == (2.0, 2.0, 2.0)
    r, g, b = ink.display_rgb
    assert r == g == b and 0.0 < r < 1.0
    # a non-absorbing thick layer reflects everything, a purely absorbing one nothing
    assert Ink("w", (1, 1, 1), (1, 1, 1)).display_rgb == pytest.approx((1.0, 1.0, 1.0), abs=1e-15)
    assert Ink("k", (1, 1, 1), (0, 0, 0)).display_rgb == (0.0, 0.0, 0.0)
    # more albedo, lighter; forward scattering (g > 0) penetrates deeper and reflects less
    assert Ink("a", (1, 1, 1), (0.9, 0.6, 0.3)).display_rgb[0] > r > Ink("b", (1, 1, 1), (0.3, 0.3, 0.3)).display_rgb[0]
    forward, isotropic = (Ink(n, (1, 1, 1), (0.6, 0.6, 0.6), g=g) for n, g in (("f", 0.8), ("i", 0.0)))
    assert forward.display_rgb[0] < isotropic.display_rgb[0]


def test_ink_json_round_trip(tmp_path):
    inks = InkSet([INKS["cyan"], Ink("Mine", (0.1, 1e-3, 123.456789), (0.123456789, 0.0, 1.0), g=-0.3)])
    path = tmp_path / "inks.json"
    inks.save_json(path)
    assert InkSet.load_json(path) == inks
    assert InkSet.load_json(str(path)).names == ("cyan", "Mine")
    # minimal entries: g and display_rgb optional; {"inks": [...]} accepted too
    path.write_text(json.dumps({"inks": [{"name": "a", "sigma_t": [1, 2, 3], "albedo": [0.1, 0.2, 0.3]}]}))
    (ink,) = InkSet.load_json(path)
    assert ink.g == 0.4 and ink.sigma_t == (1.0, 2.0, 3.0)


@pytest.mark.parametrize("content, message", [
    ([{"name": "a", "sigma_t": [1, 2, 3], "albedo": [0.1, 1.5, 0.3]}], r"inks.json\[0\]: ink 'a': albedo"),
    ([{"name": "a", "sigma_t": [1, 2, 3], "albedo": [0.1, 0.2, 0.3]},
      {"name": "b", "sigma_t": [1, -2, 3], "albedo": [0.1, 0.2, 0.3]}], r"inks.json\[1\]: ink 'b': sigma_t"),
    ([{"name": "a", "sigma_t": [1, 2], "albedo": [0.1, 0.2, 0.3]}], r"inks.json\[0\]: .*expected 3 values"),
    ([{"name": "a", "sigma_t": [1, 2, 3]}], r"inks.json\[0\]: missing key\(s\) \['albedo'\]"),
    ([{"name": "a", "sigmat": [1, 2, 3], "sigma_t": [1, 2, 3], "albedo": [0, 0, 0]}],
     r"inks.json\[0\]: unknown key\(s\) \['sigmat'\]"),
    ([{"name": "a", "sigma_t": [1, 2, 3], "albedo": [0, 0, 0]}] * 2, r"duplicates \['a'\]"),
    ({"name": "a"}, r"expected a JSON list of inks"),
    ("white", r"expected a JSON list of inks"),
])
def test_ink_json_refusals(tmp_path, content, message):
    path = tmp_path / "inks.json"
    path.write_text(json.dumps(content))
    with pytest.raises(ValueError, match=message):
        InkSet.load_json(path)


def test_ink_json_not_json(tmp_path):
    path = tmp_path / "inks.json"
    path.write_text("[{name: 1}")
    with pytest.raises(ValueError, match="not valid JSON"):
        InkSet.load_json(path)
    with pytest.raises(FileNotFoundError):
        InkSet.load_json(tmp_path / "missing.json")


# ----------------------------------------------------------------------------------------------------------------
# mixing (eq. 9)
# ----------------------------------------------------------------------------------------------------------------
def test_mix_inks_matches_reference_and_is_linear():
    inks = InkSet.from_names(["cyan", "magenta", "yellow", "black", "white", "transparent"])
    gen = torch.Generator().manual_seed(1)
    w1 = torch.rand(6, 2, 3, 4, generator=gen, dtype=torch.float64)
    w1 /= w1.sum(0)
    w2 = torch.rand(6, 2, 3, 4, generator=gen, dtype=torch.float64) ** 4
    w2 /= w2.sum(0)
    sigma_t, albedo = mix_inks(w1, inks)
    ref_t, ref_a = _reference_mix(w1, inks)
    torch.testing.assert_close(sigma_t, ref_t, rtol=1e-14, atol=0)
    torch.testing.assert_close(albedo, ref_a, rtol=1e-13, atol=0)
    # σ_s = σ_t α and σ_a = σ_t (1 − α) are linear in ρ; σ_t too
    def parts(w):
        st, al = mix_inks(w, inks)
        return st * al, st * (1 - al), st
    for t in (0.0, 0.3, 1.0):
        mixed = parts(t * w1 + (1 - t) * w2)
        for m, a, b in zip(mixed, parts(w1), parts(w2)):
            torch.testing.assert_close(m, t * a + (1 - t) * b, rtol=1e-12, atol=1e-12)


def test_mix_inks_one_hot_reproduces_each_ink(dtype):
    inks = InkSet.from_names(list(TABLE))
    n = len(inks)
    onehot = torch.eye(n, dtype=dtype).view(n, n, 1, 1)          # voxel z = k holds ink k only
    sigma_t, albedo = mix_inks(onehot, inks)
    assert sigma_t.shape == (3, n, 1, 1) and sigma_t.dtype == dtype and sigma_t.is_contiguous()
    want_t = torch.tensor([TABLE[k][0] for k in inks.names], dtype=torch.float64).T.reshape(3, n, 1, 1)
    want_a = torch.tensor([TABLE[k][1] for k in inks.names], dtype=torch.float64).T.reshape(3, n, 1, 1)
    eps = torch.finfo(dtype).eps
    torch.testing.assert_close(sigma_t, want_t.to(dtype), rtol=2 * eps, atol=0)
    torch.testing.assert_close(albedo, want_a.to(dtype), rtol=4 * eps, atol=0)
    np_t, _ = mix_inks(onehot.numpy(), inks)                        # ndarray input gives the same
    assert torch.equal(np_t, sigma_t)


def test_mix_inks_zero_extinction_is_guarded():
    inks = InkSet([Ink("void", (0.0, 0.0, 0.0), (0.3, 0.3, 0.3)), INKS["white"]])
    leaf = torch.tensor([[1.0, 0.5], [0.0, 0.5]], dtype=torch.float64, requires_grad=True)
    sigma_t, albedo = mix_inks(leaf.view(2, 1, 1, 2), inks)
    assert torch.equal(sigma_t[:, 0, 0, 0], torch.zeros(3, dtype=torch.float64))
    torch.testing.assert_close(albedo[:, 0, 0, 0], torch.full((3,), 0.3, dtype=torch.float64), rtol=0, atol=1e-15)
    torch.testing.assert_close(albedo[:, 0, 0, 1], torch.tensor(INKS["white"].albedo, dtype=torch.float64))
    (sigma_t.sum() + albedo.sum()).backward()
    assert torch.isfinite(leaf.grad).all()


def test_mix_inks_without_a_zero_extinction_is_the_guarded_mix():
    """Where every voxel has σ_t > 0, the mix skips the guard's fallback: the same values and gradients, to the bit, as
    the guarded mix of the same voxels beside one voxel without ink."""
    inks = InkSet.from_names()
    gen = torch.Generator().manual_seed(4)
    w = torch.rand((len(inks), 1, 3, 4), generator=gen, dtype=torch.float64)
    padded = torch.cat([w, torch.zeros((len(inks), 1, 3, 1), dtype=torch.float64)], dim=3)  # σ_t = 0 there
    outs = []
    for weights, keep in ((w, 4), (padded, 4)):
        leaf = weights.clone().requires_grad_()
        sigma_t, albedo = mix_inks(leaf, inks)
        g = torch.linspace(-1.0, 1.0, sigma_t[..., :keep].numel(), dtype=torch.float64).view(sigma_t[..., :keep].shape)
        ((sigma_t[..., :keep] * g).sum() + (albedo[..., :keep] * g.flip(0)).sum()).backward()
        outs.append((sigma_t[..., :keep].detach(), albedo[..., :keep].detach(), leaf.grad[..., :keep]))
    for a, b in zip(*outs):
        assert torch.equal(a, b)


def test_mix_inks_refusals():
    inks = InkSet.from_names()
    with pytest.raises(ValueError, match=r"weights: expected shape \(N=5, D, H, W\).*got \(4, 2, 2, 2\)"):
        mix_inks(torch.rand(4, 2, 2, 2), inks)
    with pytest.raises(ValueError, match=r"weights: expected shape \(N=5, D, H, W\)"):
        mix_inks(torch.rand(5, 2, 2), inks)
    with pytest.raises(ValueError, match="weights: expected weights >= 0"):
        mix_inks(-torch.rand(5, 1, 1, 1), inks)
    with pytest.raises(ValueError, match="weights: expected finite values, got 1 NaN/Inf"):
        mix_inks(torch.tensor([0.2, 0.2, math.nan, 0.2, 0.2]).view(5, 1, 1, 1), inks)
    with pytest.raises(TypeError, match="weights: expected a floating-point dtype"):
        mix_inks(torch.ones(5, 1, 1, 1, dtype=torch.long), inks)
    with pytest.raises(TypeError, match="inks: expected an InkSet"):
        mix_inks(torch.ones(5, 1, 1, 1), 5)


# ----------------------------------------------------------------------------------------------------------------
# MaterialMixture
# ----------------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("parameterization", ["sigmoid", "softmax"])
def test_mixture_initial_fractions_exact(parameterization, dtype):
    inks = InkSet.from_names(["cyan", "magenta", "yellow", "black", "white", "orange"])
    mixture = MaterialMixture(inks, (3, 4, 5), parameterization=parameterization, dtype=dtype)
    rho = mixture.weights().detach()
    assert rho.shape == (6, 3, 4, 5) and rho.dtype == dtype and mixture.logits.dtype == dtype
    want = torch.full((6,), 0.03 / 5, dtype=torch.float64)
    want[4] = 0.97
    eps = torch.finfo(dtype).eps
    # "exactly" = to round-off: sigmoid(l) and exp(l) of a rounded logit l carry a relative error of about
    # |l|·eps (the condition number of exp), plus a few eps for the normalisation.
    rtol = (float(mixture.logits.detach().abs().max()) + 4) * eps
    torch.testing.assert_close(rho, want.view(6, 1, 1, 1).expand_as(rho).to(dtype), rtol=rtol, atol=0)
    # other white fraction and init ink, and the uniform start
    m2 = MaterialMixture(inks, (1, 1, 1), parameterization, white_fraction=0.5, init_ink="BLACK", dtype=dtype)
    want2 = torch.tensor([0.1, 0.1, 0.1, 0.5, 0.1, 0.1], dtype=dtype).view(6, 1, 1, 1)
    torch.testing.assert_close(m2.weights().detach(), want2, rtol=rtol, atol=0)
    m3 = MaterialMixture(inks, (1, 1, 1), parameterization, init_ink=None, dtype=dtype)
    torch.testing.assert_close(m3.weights().detach(), torch.full((6, 1, 1, 1), 1 / 6, dtype=dtype), rtol=rtol,
                               atol=0)


@pytest.mark.parametrize("parameterization", ["sigmoid", "softmax"])
def test_mixture_normalised_and_matches_reference(parameterization):
    inks = InkSet.from_names(["cyan", "magenta", "yellow", "black", "white"])
    mixture = MaterialMixture(inks, (2, 3, 4), parameterization=parameterization, dtype=torch.float64)
    with torch.no_grad():
        mixture.logits.copy_(torch.randn(5, 2, 3, 4, generator=torch.Generator().manual_seed(2),
                                         dtype=torch.float64) * 4)
    rho = mixture.weights().detach()
    assert bool((rho > 0).all())
    torch.testing.assert_close(rho.sum(0), torch.ones(2, 3, 4, dtype=torch.float64), rtol=0, atol=4e-16)
    l = mixture.logits.detach()
    want = torch.softmax(l, 0) if parameterization == "softmax" else torch.sigmoid(l) / torch.sigmoid(l).sum(0)
    torch.testing.assert_close(rho, want, rtol=1e-15, atol=0)
    sigma_t, albedo = mixture()
    ref_t, ref_a = _reference_mix(rho, inks)
    torch.testing.assert_close(sigma_t.detach(), ref_t, rtol=1e-14, atol=0)
    torch.testing.assert_close(albedo.detach(), ref_a, rtol=1e-13, atol=0)


def test_mixture_output_feeds_the_tracer():
    mixture = MaterialMixture(InkSet.from_names(), (2, 3, 3))
    sigma_t, albedo = mixture()
    image = ta.render_texels(sigma_t, albedo, voxel_size=0.1, spp=1, seed=3)
    assert image.shape == (3, 3, 3)
    image.sum().backward()
    assert mixture.logits.grad is not None and torch.isfinite(mixture.logits.grad).all()
    assert bool((mixture.logits.grad != 0).any())


@pytest.mark.parametrize("parameterization", ["sigmoid", "softmax"])
def test_fixed_fractions_held_exactly_also_after_steps(parameterization, dtype):
    inks = InkSet.from_names(["cyan", "magenta", "yellow", "black", "white", "transparent"])
    shape = (4, 3, 5)
    gen = torch.Generator().manual_seed(5)
    core = torch.rand(shape, generator=gen) < 0.5
    rim = torch.zeros(shape, dtype=torch.bool)
    rim[:, 0] = True                                    # overlaps the core in some voxels
    fixed = [FixedFraction(core, "Transparent", 0.8), FixedFraction(rim.numpy(), "black", 0.15)]
    mixture = MaterialMixture(inks, shape, parameterization=parameterization, fixed=fixed, dtype=dtype)
    optimizer = torch.optim.Adam(mixture.parameters(), lr=0.3)
    target = torch.rand(3, *shape, generator=gen, dtype=dtype)
    it, ik = inks.index("transparent"), inks.index("black")
    free = [k for k in range(6) if k not in (it, ik)]
    eps = torch.finfo(dtype).eps
    for step in range(4):
        rho = mixture.weights()
        assert torch.equal(rho[it][core], torch.full_like(rho[it][core], 0.8))
        assert torch.equal(rho[ik][rim], torch.full_like(rho[ik][rim], 0.15))
        fixed_sum = 0.8 * core.to(torch.float64) + 0.15 * rim.to(torch.float64)
        free_sum = rho.sum(0).double() - (rho[it] * core).double() - (rho[ik] * rim).double()
        torch.testing.assert_close(free_sum, 1.0 - fixed_sum, rtol=0, atol=8 * eps)
        torch.testing.assert_close(rho.sum(0).double(), torch.ones(shape, dtype=torch.float64), rtol=0, atol=8 * eps)
        assert bool((rho >= 0).all())
        if step == 0:   # away from constraints the initial 97 % white still holds
            untouched = ~(core | rim)
            torch.testing.assert_close(rho[4][untouched], torch.full_like(rho[4][untouched], 0.97), rtol=4 * eps,
                                       atol=0)
        optimizer.zero_grad()
        sigma_t, albedo = mixture()
        loss = ((albedo - target) ** 2).mean() + 1e-2 * sigma_t.mean()
        loss.backward()
        # the logits of a fixed ink get no gradient where it is fixed
        assert torch.equal(mixture.logits.grad[it][core], torch.zeros_like(mixture.logits.grad[it][core]))
        assert bool((mixture.logits.grad[free] != 0).any())
        optimizer.step()
    # the optimisation did move the free inks (the test is not vacuous)
    assert not torch.allclose(mixture.weights()[4][~(core | rim)], torch.tensor(0.97, dtype=dtype))


def test_fixed_fraction_whole_voxel_and_refusals():
    inks = InkSet.from_names(["black", "white"])
    m = torch.ones(1, 1, 2, dtype=torch.bool)
    mixture = MaterialMixture(inks, (1, 1, 2), fixed=[FixedFraction(m, "black", 0.25), FixedFraction(m, "white", 0.75)])
    assert torch.equal(mixture.weights().detach().flatten(), torch.tensor([0.25, 0.25, 0.75, 0.75]))
    with pytest.raises(ValueError, match=r"every ink is fixed in 2 voxel\(s\) but the fractions there do not sum"):
        MaterialMixture(inks, (1, 1, 2), fixed=[FixedFraction(m, "black", 0.25), FixedFraction(m, "white", 0.5)])
    with pytest.raises(ValueError, match=r"fixed fractions sum to more than 1 in 2 voxel\(s\)"):
        MaterialMixture(inks, (1, 1, 2), fixed=[FixedFraction(m, "black", 0.5), FixedFraction(m, "white", 0.75)])
    with pytest.raises(ValueError, match=r"fixed\[1\]: ink 'black' is already fixed to a different fraction"):
        MaterialMixture(inks, (1, 1, 2), fixed=[FixedFraction(m, "black", 0.5), FixedFraction(m, "black", 0.4)])
    with pytest.raises(ValueError, match=r"fixed\[0\].ink: ink 'cyan' is not in the ink set \['black', 'white'\]"):
        MaterialMixture(inks, (1, 1, 2), fixed=[FixedFraction(m, "cyan", 0.5)])
    with pytest.raises(ValueError, match=r"fixed\[0\].mask: expected shape \(1, 1, 3\)"):
        MaterialMixture(inks, (1, 1, 3), fixed=[FixedFraction(m, "black", 0.5)])
    with pytest.raises(TypeError, match="mask: expected dtype bool"):
        FixedFraction(torch.ones(1, 1, 2), "black", 0.5)
    with pytest.raises(ValueError, match=r"fraction: expected a value in \[0, 1\], got 1.5"):
        FixedFraction(m, "black", 1.5)


def test_mixture_refusals():
    inks = InkSet.from_names()
    with pytest.raises(ValueError, match=r"shape: expected \(D, H, W\), three ints >= 1, got \(2, 0, 3\)"):
        MaterialMixture(inks, (2, 0, 3))
    with pytest.raises(ValueError, match=r"shape: expected \(D, H, W\)"):
        MaterialMixture(inks, (2, 3))
    with pytest.raises(ValueError, match=r"parameterization: expected one of \('sigmoid', 'softmax'\), got 'relu'"):
        MaterialMixture(inks, (1, 1, 1), parameterization="relu")
    with pytest.raises(ValueError, match=r"white_fraction: expected a value in \(0, 1\), got 1.0"):
        MaterialMixture(inks, (1, 1, 1), white_fraction=1.0)
    with pytest.raises(ValueError, match=r"init_ink: expected one of \['cyan', .*'white'\] or None, got 'orange'"):
        MaterialMixture(inks, (1, 1, 1), init_ink="orange")
    with pytest.raises(TypeError, match="dtype: expected torch.float32 or torch.float64"):
        MaterialMixture(inks, (1, 1, 1), dtype=torch.float16)
    with pytest.raises(ValueError, match="unknown ink 'teal'"):
        MaterialMixture(["white", "teal"], (1, 1, 1))


def test_mixture_state_dict_holds_only_the_logits():
    mixture = MaterialMixture(InkSet.from_names(), (2, 2, 2), fixed=[FixedFraction(torch.ones(2, 2, 2, dtype=bool),
                                                                                       "black", 0.1)])
    assert list(mixture.state_dict()) == ["logits"]
    m64 = mixture.to(torch.float64)
    assert m64.weights().dtype == torch.float64 and m64().__getitem__(0).dtype == torch.float64


# ----------------------------------------------------------------------------------------------------------------
# gradients
# ----------------------------------------------------------------------------------------------------------------
class _Weights(torch.nn.Module):
    def __init__(self, mixture):
        super().__init__()
        self.mixture = mixture

    def forward(self):
        return self.mixture.weights()


@pytest.mark.parametrize("parameterization", ["sigmoid", "softmax"])
@pytest.mark.parametrize("with_fixed", [False, True], ids=["free", "fixed"])
def test_mixture_gradcheck(parameterization, with_fixed):
    inks = InkSet.from_names(["cyan", "magenta", "yellow", "black", "white"])
    shape = (2, 2, 3)
    fixed = []
    if with_fixed:
        mask = torch.zeros(shape, dtype=torch.bool)
        mask[0] = True
        fixed = [FixedFraction(mask, "white", 0.6)]
    mixture = MaterialMixture(inks, shape, parameterization=parameterization, fixed=fixed, dtype=torch.float64)
    logits = torch.randn(5, *shape, generator=torch.Generator().manual_seed(7), dtype=torch.float64,
                         requires_grad=True)
    weights_module = _Weights(mixture)

    def weights(l):
        return torch.func.functional_call(weights_module, {"mixture.logits": l}, ())

    def forward(l):
        return torch.func.functional_call(mixture, {"logits": l}, ())

    assert torch.autograd.gradcheck(weights, (logits,), eps=1e-6, atol=1e-8, rtol=1e-6)
    assert torch.autograd.gradcheck(forward, (logits,), eps=1e-6, atol=1e-8, rtol=1e-6)
    assert torch.autograd.gradgradcheck(forward, (logits,), eps=1e-6, atol=1e-6, rtol=1e-5)


def test_mix_inks_gradcheck():
    inks = InkSet.from_names(["cyan", "black", "white", "transparent"])
    weights = torch.rand(4, 2, 2, 2, generator=torch.Generator().manual_seed(8), dtype=torch.float64) + 0.05
    weights.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda w: mix_inks(w, inks), (weights,), eps=1e-6, atol=1e-8, rtol=1e-6)


def test_support_mixture_matches_full_grid_and_holds_the_core():
    """Shell-only parameters: logits only on the support; there the weights and optics equal those of a full-grid
    mixture with the same logits, elsewhere the core ink holds exactly, and gradients reach only the support."""
    inks = InkSet.from_names()
    shape = (5, 6, 7)
    support = torch.zeros(shape, dtype=torch.bool)
    support[1:4, 2:5, 1:6] = True
    support[0, 0, 0] = True
    gen = torch.Generator().manual_seed(0)
    full = MaterialMixture(inks, shape, dtype=torch.float64)
    with torch.no_grad():
        full.logits.copy_(torch.randn(full.logits.shape, generator=gen, dtype=torch.float64))
    shell = MaterialMixture(inks, shape, dtype=torch.float64, support=support, core_ink="cyan")
    assert tuple(shell.logits.shape) == (len(inks), int(support.sum()))
    with torch.no_grad():
        shell.logits.copy_(full.logits[:, support])
    w, w_full = shell.weights(), full.weights()
    assert torch.allclose(w[:, support], w_full[:, support], rtol=1e-14, atol=1e-16)
    core = torch.zeros(len(inks), dtype=torch.float64)
    core[inks.index("cyan")] = 1
    assert torch.equal(w[:, ~support], core.view(-1, 1).expand(-1, int((~support).sum())))
    sigma_t, albedo = shell()
    ref_t, ref_a = mix_inks(w, inks)
    assert torch.allclose(sigma_t, ref_t, rtol=1e-13, atol=0) and torch.allclose(albedo, ref_a, rtol=1e-13, atol=0)
    (sigma_t.sum() + albedo.sum()).backward()
    assert shell.logits.grad.shape == shell.logits.shape and bool(shell.logits.grad.abs().sum() > 0)
    mask = torch.zeros(shape, dtype=torch.bool)
    mask[0, 5, 6] = True  # outside the support
    with pytest.raises(ValueError, match="outside the optimised support"):
        MaterialMixture(inks, shape, support=support, fixed=[FixedFraction(mask, "white", 0.5)])
    with pytest.raises(ValueError, match="support: expected shape"):
        MaterialMixture(inks, shape, support=support[:-1])
    with pytest.raises(ValueError, match="core_ink"):
        MaterialMixture(inks, shape, support=support, core_ink="gold")
    inside = torch.zeros(shape, dtype=torch.bool)
    inside[2, 3, 3] = True
    fixed = MaterialMixture(inks, shape, support=support, fixed=[FixedFraction(inside, "white", 0.25)])
    assert float(fixed.weights().detach()[inks.index("white"), 2, 3, 3]) == 0.25


@pytest.mark.parametrize("parameterization", ["sigmoid", "softmax"])
def test_set_weights_starts_from_given_mixtures(parameterization):
    """set_weights (the naive-extrusion warm start): weights() reproduces the given mixtures up to the floor (an
    absent ink starts at about `floor`), on a support the core stays and fixed fractions stay exact."""
    inks = InkSet.from_names()
    shape = (3, 4, 5)
    gen = torch.Generator().manual_seed(1)
    target = torch.rand((len(inks), *shape), generator=gen, dtype=torch.float64) ** 4
    target[1, 0] = 0.0  # an absent ink
    target /= target.sum(0, keepdim=True)
    floor = 1e-3
    mixture = MaterialMixture(inks, shape, parameterization=parameterization, dtype=torch.float64)
    assert mixture.set_weights(target, floor=floor) is mixture
    w = mixture.weights().detach()
    assert torch.allclose(w, target, atol=len(inks) * floor, rtol=0)
    assert float(w[1, 0].min()) > 0.5 * floor  # the absent ink can still move
    clamped = target.clamp(floor, 1 - floor)
    assert torch.allclose(w, clamped / clamped.sum(0, keepdim=True), atol=1e-12, rtol=0)

    support = torch.zeros(shape, dtype=torch.bool)
    support[1:, 1:3] = True
    mask = torch.zeros(shape, dtype=torch.bool)
    mask[2, 2, 2] = True
    shell = MaterialMixture(inks, shape, parameterization=parameterization, dtype=torch.float64, support=support,
                            core_ink="white", fixed=[FixedFraction(mask, "cyan", 0.8)])
    shell.set_weights(target, floor=floor)
    w = shell.weights().detach()
    free = support & ~mask
    assert torch.allclose(w[:, free], (clamped / clamped.sum(0, keepdim=True))[:, free], atol=1e-12, rtol=0)
    assert bool((w[inks.index("white"), ~support] == 1).all())
    assert float(w[inks.index("cyan"), 2, 2, 2]) == 0.8
    with pytest.raises(ValueError, match=r"weights: expected shape \(5, 3, 4, 5\)"):
        mixture.set_weights(target[:, :2])
    with pytest.raises(ValueError, match="floor"):
        mixture.set_weights(target, floor=0.7)
    with pytest.raises(ValueError, match="weights >= 0"):
        mixture.set_weights(-target)
