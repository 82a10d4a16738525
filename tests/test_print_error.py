"""The print's error free of render noise (torch_appearance.print_error): against a high-spp reference of the real
tracer, on exactly known synthetic cases, and its refusals."""
import numpy as np
import pytest
import torch

from torch_appearance import render_texels
from torch_appearance.metrics import delta_e_2000
from torch_appearance.print_error import ERROR_FIELDS, noise_free_error


def _slab_print(size=32, depth=8):
    """A heterogeneous coloured slab (random σ_t and albedo per voxel, fixed seed; red albedo high, green and blue
    lower: an orange print): ``render(spp, seed)`` gives its top face, (size², 3) linear RGB."""
    gen = torch.Generator().manual_seed(7)
    sigma_t = 2.0 + 28.0 * torch.rand(3, depth, size, size, generator=gen, dtype=torch.float64)
    low = torch.tensor([0.97, 0.85, 0.6], dtype=torch.float64).view(3, 1, 1, 1)
    albedo = low + (0.999 - low) * torch.rand(3, depth, size, size, generator=gen, dtype=torch.float64)

    def render(spp, seed):
        return render_texels(sigma_t, albedo, voxel_size=0.0847, spp=spp, seed=seed).reshape(-1, 3)

    return render


@pytest.fixture(scope="module")
def colorchecker_print():
    """The naive extrusion of the built-in ColorChecker slab (the default job's target), quantised at the printer's
    resolution as a run quantises it: ``(render(spp, seed) -> (texels, 3), target (texels, 3))``."""
    from torch_appearance.pipelines.print import PrintConfig
    from torch_appearance.pipelines.print.baselines import quantize
    from torch_appearance.pipelines.print.config import iteration_seed, load_inks
    from torch_appearance.pipelines.print.loop import build_target

    cfg = PrintConfig(target="colorchecker").resolved()
    inks = load_inks(cfg.inks)
    target = build_target(cfg, log=lambda *a, **k: None)
    target.use(inks, cfg)
    indices = quantize(target, torch.as_tensor(target.naive_weights(inks, cfg)[0]), inks, cfg, iteration_seed(0, -2))

    def render(spp, seed):
        return target.render_quantized(indices, inks, cfg.printer_dpi, spp, seed)[0].reshape(-1, 3).double()

    return render, target.target[0].reshape(-1, 3).double()


def test_against_a_high_spp_reference_of_the_tracer(colorchecker_print):
    """A print of the default job: at the cost of one 256-spp render (four of 64 spp, a slab's default evaluation),
    three estimates of the mean and the p95 lie within 1.5 % + 3 SE of the error measured by brute force at 8192 spp
    (whose own noise bias, about noise² / (2 · error), is below 0.05 ΔE00), where the raw 256-spp mean is 6 % too
    high: an evaluator that returned the raw figure fails. (Measured: 13.55-13.64 against 13.73; raw 14.9. The p95,
    set by texels whose error is far above the noise, is nearly noise-free even raw: 27.8 against 27.5.)"""
    render, target = colorchecker_print
    reference_renders = torch.stack([render(2048, 1000 + k) for k in range(4)])
    expected = reference_renders.mean(0)
    texel_error = delta_e_2000(expected, target).numpy()
    reference, reference_p95 = texel_error.mean(), np.percentile(texel_error, 95)
    noise_of_reference = float(delta_e_2000(reference_renders[:2].mean(0), reference_renders[2:].mean(0)).mean()) / 2
    assert noise_of_reference ** 2 / (2 * reference) < 0.05

    estimates = [noise_free_error(torch.stack([render(64, 10 * s + k) for k in range(4)]), target) for s in range(3)]
    for est in estimates:
        assert est["dE00_mean_raw"] > 1.06 * reference, (est, reference)  # the raw figure: much of it noise
        assert abs(est["dE00_mean"] - reference) < 0.015 * reference + 3 * est["dE00_mean_se"], (est, reference)
        assert abs(est["dE00_p95"] - reference_p95) < 0.015 * reference_p95 + 3 * est["dE00_p95_se"], \
            (est, reference_p95)
    # the standard error says how far the estimates of other seeds spread (within a factor of 3, for three seeds)
    spread = np.std([e["dE00_mean"] for e in estimates], ddof=1)
    assert spread < 3 * np.mean([e["dE00_mean_se"] for e in estimates])


def test_far_below_the_noise_it_reads_low_but_nearer_than_raw():
    """The limit of what can be taken out: a print whose texels' errors are about as large as the noise of the
    evaluation (an orange slab of random voxels, each texel 10-25 % off its target). No estimator of |μ − T| is
    unbiased there; ours reads low (measured: 5.7 against 6.5 at 256 spp) where the raw figure reads high (7.4), and
    is nearer the truth."""
    render = _slab_print()
    expected = torch.stack([render(2048, 1000 + k) for k in range(2)]).mean(0)
    gen = torch.Generator().manual_seed(8)
    amount = 0.1 + 0.15 * torch.rand(4, 4, 3, generator=gen, dtype=torch.float64)
    sign = torch.where(torch.rand(4, 4, 3, generator=gen) < 0.5, -1.0, 1.0).double()
    target = (expected * (1 + sign * amount).repeat_interleave(8, 0).repeat_interleave(8, 1).reshape(-1, 3)).clamp(0, 1)
    truth = float(delta_e_2000(expected, target).mean())
    est = noise_free_error(torch.stack([render(64, k) for k in range(4)]), target)
    assert est["dE00_mean"] < truth < est["dE00_mean_raw"]
    assert abs(est["dE00_mean"] - truth) < abs(est["dE00_mean_raw"] - truth)
    assert est["dE00_noise"] > 0.5 * truth


def test_the_same_print_on_both_sides_has_no_error():
    """Two sets of independent renders of one print: the error between their expected colours is zero. The squared
    ΔE76, an average of decorrelated products, says so; the mean ΔE00, a mean of per-texel square roots, cannot reach
    zero (no estimator of |μ − T| is unbiased at μ = T) but takes out about half of what the raw figure reads."""
    render = _slab_print(size=48)
    a = torch.stack([render(8, k) for k in range(4)])
    b = torch.stack([render(8, 100 + k) for k in range(4)])
    est = noise_free_error(a, b)
    assert est["dE00_mean_raw"] > 3.0
    assert est["dE76_rms"] < 0.25 * est["dE76_mean_raw"]
    assert est["dE00_mean"] < 0.6 * est["dE00_mean_raw"]


def test_noise_free_renders_give_the_exact_error():
    """Renders without noise (all alike): every figure equals the exact CIEDE2000 of the colours."""
    gen = torch.Generator().manual_seed(1)
    pred, target = torch.rand(2, 500, 3, generator=gen, dtype=torch.float64)
    est = noise_free_error(pred.expand(4, 500, 3), target)
    exact = delta_e_2000(pred, target).numpy()
    assert est["dE00_mean"] == pytest.approx(exact.mean(), rel=1e-9)
    assert est["dE00_mean_raw"] == pytest.approx(exact.mean(), rel=1e-9)
    assert est["dE00_p95"] == pytest.approx(np.percentile(exact, 95), rel=1e-9)
    assert est["dE00_mean_se"] == 0.0 and est["dE00_noise"] == 0.0
    assert list(est) == list(ERROR_FIELDS)


def test_gaussian_noise_with_known_truth():
    """Gaussian noise on a known print (noise a third of the error), twelve seeds: the estimate is nearer the truth
    than the raw figure, within the second-order bias of a square root of a noisy square (about −σ²/(2e²): 3 % here),
    and its standard error matches the spread over seeds."""
    gen = torch.Generator().manual_seed(3)
    target = torch.rand(8000, 3, generator=gen, dtype=torch.float64) * 0.6 + 0.2
    print_ = (target * torch.tensor([1.15, 1.0, 0.9], dtype=torch.float64)).clamp(0, 1)
    truth = float(delta_e_2000(print_, target).mean())
    runs = [noise_free_error(print_ + 0.03 * torch.randn(4, 8000, 3, generator=gen, dtype=torch.float64), target)
            for _ in range(12)]
    mean, raw = np.mean([r["dE00_mean"] for r in runs]), np.mean([r["dE00_mean_raw"] for r in runs])
    assert abs(mean - truth) < 0.045 * truth and abs(mean - truth) < 0.6 * (raw - truth), (mean, raw, truth)
    spread, se = np.std([r["dE00_mean"] for r in runs], ddof=1), np.mean([r["dE00_mean_se"] for r in runs])
    assert 0.5 < spread / se < 1.6, (spread, se)


@pytest.mark.parametrize("renders, target, match", [
    (torch.zeros(3, 5, 3), torch.zeros(5, 3), "expected 2 or 4 independent renders"),
    (torch.zeros(4, 5, 3), torch.zeros(6, 3), "target: expected the texel shape"),
    (torch.zeros(4, 5, 3), torch.zeros(2, 5, 3), "target: expected 4 renders"),
    (torch.full((4, 5, 3), float("nan")), torch.zeros(5, 3), "renders: 60 non-finite"),
    (torch.zeros(4, 5, 2), torch.zeros(5, 2), r"renders: expected linear RGB"),
])
def test_refuses_bad_input(renders, target, match):
    with pytest.raises(ValueError, match=match):
        noise_free_error(renders, target)


def test_mask_selects_texels():
    gen = torch.Generator().manual_seed(2)
    renders, target = torch.rand(4, 10, 3, generator=gen), torch.rand(10, 3, generator=gen)
    keep = torch.arange(10) < 6
    assert noise_free_error(renders, target, mask=keep) == noise_free_error(renders[:, :6], target[:6])
    with pytest.raises(ValueError, match="mask: selects no texels"):
        noise_free_error(renders, target, mask=torch.zeros(10, dtype=torch.bool))


def test_a_random_subset_of_texels_reports_its_sampling_error():
    """An object's evaluation scores a random subset of its texels (``population``): over 120 subsets of 1024 of
    20,000 texels whose errors vary from texel to texel, the spread of the mean and of the p95 matches the reported
    SE, which the render noise alone (no ``population``) would understate several times; the subsets' mean agrees with
    the whole population's figure."""
    gen = torch.Generator().manual_seed(5)
    n, m = 20000, 1024
    target = torch.rand(n, 3, generator=gen, dtype=torch.float64) * 0.6 + 0.2
    scale = 1.0 + 0.25 * torch.rand(n, 1, generator=gen, dtype=torch.float64)  # 0-25 % too light, per texel
    renders = (target * scale).clamp(0, 1) + 0.01 * torch.randn(4, n, 3, generator=gen, dtype=torch.float64)
    whole = noise_free_error(renders, target)
    runs, noise_only = [], []
    for _ in range(120):
        pick = torch.randperm(n, generator=gen)[:m]
        runs.append(noise_free_error(renders[:, pick], target[pick], population=n))
    noise_only = noise_free_error(renders[:, pick], target[pick])
    for key in ("dE00_mean", "dE00_p95"):
        values = np.array([r[key] for r in runs])
        spread, se = values.std(ddof=1), np.mean([r[key + "_se"] for r in runs])
        assert 0.75 < spread / se < 1.33, (key, spread, se)
        assert noise_only[key + "_se"] < 0.5 * spread, (key, noise_only[key + "_se"], spread)
        assert abs(values.mean() - whole[key]) < 4 * spread / np.sqrt(len(values)), (key, values.mean(), whole[key])
    # the whole population has no sampling error; a population smaller than the sample is refused
    assert noise_free_error(renders, target, population=n)["dE00_mean_se"] == whole["dE00_mean_se"]
    with pytest.raises(ValueError, match="population: expected an int >= the 1024 scored texels"):
        noise_free_error(renders[:, :m], target[:m], population=100)
