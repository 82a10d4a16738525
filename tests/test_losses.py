"""Tests of the appearance losses (torch_appearance.nn.losses, eqs. 11–18) and colour metrics (torch_appearance.metrics).

The losses are compared with slow, obviously-correct NumPy references written from the paper's equations (explicit
texel-to-texel Gaussian weights for SSIM, explicit 27-tap Sobel correlation for the edges), with kornia's dense
``ssim3d`` / ``ssim`` where the definitions coincide, and with finite differences (float64 ``gradcheck``).
"""
import math

import colour
import numpy as np
import pytest
import torch
from kornia.metrics import ssim as kornia_ssim
from kornia.metrics import ssim3d as kornia_ssim3d

from torch_appearance import metrics
from torch_appearance.color import rgb_to_lab
from torch_appearance.nn import losses
from torch_appearance.nn.losses import (AppearanceLoss, ColorLoss, EdgeLoss3D, SSIMLoss3D, appearance_loss,
                                        color_loss, edge_loss_3d, masked_ssim3d, sobel_kernels_3d, ssim_loss_3d)

KORNIA_SRGB_TO_XYZ = np.array([[0.412453, 0.357580, 0.180423],
                               [0.212671, 0.715160, 0.072169],
                               [0.019334, 0.119193, 0.950227]])
KORNIA_WHITE_XYZ = np.array([0.95047, 1.0, 1.08883])
D65 = colour.CCS_ILLUMINANTS["CIE 1931 2 Degree Standard Observer"]["D65"]


# ------------------------------------------------------------------------------------------------------------------
# helpers and NumPy references
# ------------------------------------------------------------------------------------------------------------------
def _volumes(shape=(3, 4, 5, 6), seed=0, dtype=torch.float64, lo=0.05, hi=0.95):
    g = torch.Generator().manual_seed(seed)
    pred = lo + (hi - lo) * torch.rand(shape, generator=g, dtype=dtype)
    target = lo + (hi - lo) * torch.rand(shape, generator=g, dtype=dtype)
    return pred, target


def _mask(kind, spatial, seed=0):
    d, h, w = spatial
    m = torch.zeros(spatial, dtype=torch.bool)
    if kind == "full":
        m[:] = True
    elif kind == "top":
        m[-1] = True
    elif kind == "two_sheets":  # top and bottom face: layers with a gap between them
        m[0] = True
        m[-1] = True
    elif kind == "random":
        m = torch.rand(spatial, generator=torch.Generator().manual_seed(seed)) < 0.5
        m[0, 0, 0] = True
    elif kind == "shell":  # the boundary voxels of the box, as for a mesh surface
        m[:] = True
        m[1:-1, 1:-1, 1:-1] = False
    return m


def _norm_lab(rgb):
    """(3, D, H, W) linear RGB tensor → normalised L*a*b* as an f64 ndarray (3, D, H, W)."""
    lab = rgb_to_lab(rgb.double(), dim=0).numpy()
    return lab * np.array([1 / 100, 1 / 255, 1 / 255])[:, None, None, None] + \
        np.array([0.0, 128 / 255, 128 / 255])[:, None, None, None]


def _gauss_taps(window_size, sigma):
    r = window_size // 2
    k = np.arange(-r, r + 1, dtype=np.float64)
    g = np.exp(-k**2 / (2 * sigma**2))
    return g / g.sum()


def _ssim_reference(x, y, m, window_size=11, sigma=1.5, c1=1e-4, c2=9e-4):
    """Per-texel SSIM, (C, I), from an explicit texel-to-texel weight matrix (eqs. 12–15, normalised over texels)."""
    r, g = window_size // 2, _gauss_taps(window_size, sigma)
    pos = np.argwhere(m)  # (I, 3)
    off = pos[None, :, :] - pos[:, None, :]  # (I, I, 3)
    inside = (np.abs(off) <= r).all(-1)
    weights = np.where(inside, np.prod(g[np.clip(off + r, 0, 2 * r)], axis=-1), 0.0)
    weights /= weights.sum(1, keepdims=True)
    xs, ys = x[:, m], y[:, m]  # (C, I)
    mx, my = xs @ weights.T, ys @ weights.T
    vx, vy = (xs**2) @ weights.T - mx**2, (ys**2) @ weights.T - my**2
    cxy = (xs * ys) @ weights.T - mx * my
    return (2 * mx * my + c1) * (2 * cxy + c2) / ((mx**2 + my**2 + c1) * (vx + vy + c2))


def _sobel_reference_kernels():
    h, d = np.array([1.0, 2.0, 1.0]), np.array([-1.0, 0.0, 1.0])
    return [h[:, None, None] * h[None, :, None] * d[None, None, :],   # S_x: derivative along W
            h[:, None, None] * d[None, :, None] * h[None, None, :],   # S_y: along H
            d[:, None, None] * h[None, :, None] * h[None, None, :]]   # S_z: along D


def _edge_reference(x, y, m):
    """Eq. 17 with explicit 27-tap correlation of m·(C − T), zero outside the grid, summed over texels."""
    diff = (x - y) * m[None]
    c, dd, hh, ww = diff.shape
    padded = np.zeros((c, dd + 2, hh + 2, ww + 2))
    padded[:, 1:-1, 1:-1, 1:-1] = diff
    total = 0.0
    for kernel in _sobel_reference_kernels():
        response = np.zeros_like(diff)
        for a in range(3):
            for b in range(3):
                for e in range(3):
                    response += kernel[a, b, e] * padded[:, a:a + dd, b:b + hh, e:e + ww]
        total += (response[:, m] ** 2).sum()
    return 100.0 * (1 / 3) * (1 / 4) * (1 / 32) * total / m.sum()


def _color_reference(pred, target, m):
    lab_p, lab_t = rgb_to_lab(pred.double(), dim=0).numpy(), rgb_to_lab(target.double(), dim=0).numpy()
    return float(((lab_p - lab_t)[:, m] ** 2).sum(0).mean())


# ------------------------------------------------------------------------------------------------------------------
# CIELAB: our rgb_to_lab against colour-science
# ------------------------------------------------------------------------------------------------------------------
def test_rgb_to_lab_matches_colour_science_with_kornias_srgb_matrix():
    """Same matrix and white as kornia: only the Lab compression and the transfer-function round trip differ."""
    rgb = np.random.default_rng(1).random((20000, 3))
    rgb = np.concatenate([rgb, np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], float),
                          np.full((1, 3), 1e-4)])  # cube corners and a near-black colour (linear Lab branch)
    ours = rgb_to_lab(torch.from_numpy(rgb)).numpy()
    ref = colour.XYZ_to_Lab(rgb @ KORNIA_SRGB_TO_XYZ.T, colour.XYZ_to_xy(KORNIA_WHITE_XYZ))
    assert np.linalg.norm(ours - ref, axis=-1).max() < 1e-3


def test_rgb_to_lab_against_exact_srgb_matrix_bounded_convention_difference():
    """kornia's 6-digit sRGB matrix vs the matrix derived from the sRGB primaries (what metrics uses): < 0.02 ΔE76.

    Documents the size of the convention difference between the loss's Lab and the report's Lab (not a tolerance
    for an error: both are correct renderings of slightly different sRGB constants).
    """
    rgb = np.random.default_rng(2).random((20000, 3))
    ours = rgb_to_lab(torch.from_numpy(rgb)).numpy()
    assert np.linalg.norm(ours - metrics.linear_rgb_to_lab(rgb), axis=-1).max() < 0.02


# ------------------------------------------------------------------------------------------------------------------
# metrics
# ------------------------------------------------------------------------------------------------------------------
# Sharma, Wu & Dalal (2005), "The CIEDE2000 color-difference formula", Table 1 (pairs 1, 2, 7, 17, 25, 34).
SHARMA_PAIRS = [
    ((50.0000, 2.6772, -79.7751), (50.0000, 0.0000, -82.7485), 2.0425),
    ((50.0000, 3.1571, -77.2803), (50.0000, 0.0000, -82.7485), 2.8615),
    ((50.0000, 0.0000, 0.0000), (50.0000, -1.0000, 2.0000), 2.3669),
    ((50.0000, 2.5000, 0.0000), (73.0000, 25.0000, -18.0000), 27.1492),
    ((60.2574, -34.0099, 36.2677), (60.4626, -34.1751, 39.4387), 1.2644),
    ((2.0776, 0.0795, -1.1350), (0.9033, -0.0636, -0.5514), 0.9082),
]


def _lab_to_linear_rgb(lab):
    space = colour.models.RGB_COLOURSPACE_sRGB.copy()
    space.use_derived_transformation_matrices(True)
    return colour.XYZ_to_RGB(colour.Lab_to_XYZ(np.asarray(lab, float), D65), space, apply_cctf_encoding=False)


def test_linear_rgb_to_lab_white_and_grey():
    lab = metrics.linear_rgb_to_lab(np.array([[1.0, 1.0, 1.0], [0.18, 0.18, 0.18]]))
    np.testing.assert_allclose(lab[0], [100.0, 0.0, 0.0], atol=1e-9)
    np.testing.assert_allclose(lab[1, 1:], [0.0, 0.0], atol=1e-9)
    assert abs(lab[1, 0] - (116 * 0.18 ** (1 / 3) - 16)) < 1e-9  # L* of 18 % grey


def test_delta_e_2000_reproduces_sharma_table():
    a = _lab_to_linear_rgb([p[0] for p in SHARMA_PAIRS])
    b = _lab_to_linear_rgb([p[1] for p in SHARMA_PAIRS])
    expected = np.array([p[2] for p in SHARMA_PAIRS])
    de = metrics.delta_e_2000(a, b)
    assert isinstance(de, np.ndarray) and de.shape == (len(SHARMA_PAIRS),)
    assert np.abs(de - expected).max() <= 5e-5 + 1e-9  # the table is rounded to 4 decimals


def test_delta_e_76_is_lab_distance_and_types_follow_input():
    rng = np.random.default_rng(3)
    a, b = rng.random((7, 5, 3)), rng.random((7, 5, 3))
    expected = np.linalg.norm(metrics.linear_rgb_to_lab(a) - metrics.linear_rgb_to_lab(b), axis=-1)
    np.testing.assert_allclose(metrics.delta_e_76(a, b), expected, rtol=0, atol=1e-12)
    t = metrics.delta_e_76(torch.from_numpy(a).float(), torch.from_numpy(b).float())
    assert isinstance(t, torch.Tensor) and t.dtype == torch.float32 and t.shape == (7, 5)
    t00 = metrics.delta_e_2000(torch.from_numpy(a), torch.from_numpy(b))
    assert isinstance(t00, torch.Tensor) and t00.dtype == torch.float64 and t00.shape == (7, 5)


def test_color_report_values_and_mask():
    rng = np.random.default_rng(4)
    pred, target = rng.random((300, 3)), rng.random((300, 3))
    report = metrics.color_report(torch.from_numpy(pred), torch.from_numpy(target))
    assert set(report) == {"dE00_mean", "dE00_p95", "dE76_mean"}
    assert all(isinstance(v, float) for v in report.values())
    de00 = metrics.delta_e_2000(pred, target)
    assert report["dE00_mean"] == pytest.approx(de00.mean(), rel=1e-12)
    assert report["dE00_p95"] == pytest.approx(np.percentile(de00, 95), rel=1e-12)
    assert report["dE76_mean"] == pytest.approx(metrics.delta_e_76(pred, target).mean(), rel=1e-12)
    keep = rng.random(300) < 0.3
    masked = metrics.color_report(pred, target, mask=keep)
    assert masked["dE00_mean"] == pytest.approx(de00[keep].mean(), rel=1e-12)
    assert metrics.color_report(pred, pred) == {"dE00_mean": 0.0, "dE00_p95": 0.0, "dE76_mean": 0.0}


@pytest.mark.parametrize("call, match", [
    (lambda: metrics.color_report(np.zeros((4, 3)), np.zeros((5, 3))), "same shape"),
    (lambda: metrics.color_report(np.zeros((4, 2)), np.zeros((4, 2))), r"pred must have shape \(\.\.\., 3\)"),
    (lambda: metrics.color_report(np.zeros((4, 3)), np.full((4, 3), np.nan)), "target has 12 non-finite"),
    (lambda: metrics.color_report(np.zeros((4, 3)), np.zeros((4, 3)), mask=np.zeros(4, bool)), "no colours"),
    (lambda: metrics.color_report(np.zeros((4, 3)), np.zeros((4, 3)), mask=np.ones(3, bool)), "mask must have"),
    (lambda: metrics.color_report(np.zeros((4, 3)), np.zeros((4, 3)), mask=np.ones(4)), "mask must be bool"),
    (lambda: metrics.delta_e_2000("abc", np.zeros(3)), "pred must be a tensor or array"),
])
def test_metrics_refuse_bad_input(call, match):
    with pytest.raises((TypeError, ValueError), match=match):
        call()


# ------------------------------------------------------------------------------------------------------------------
# losses against the NumPy references
# ------------------------------------------------------------------------------------------------------------------
MASKS = ["full", "top", "two_sheets", "random", "shell"]


@pytest.mark.parametrize("kind", MASKS)
@pytest.mark.parametrize("window_size, sigma", [(11, 1.5), (3, 0.8)])
def test_ssim_loss_matches_reference(kind, window_size, sigma):
    pred, target = _volumes(seed=5)
    m = _mask(kind, pred.shape[1:], seed=6)
    ssim = _ssim_reference(_norm_lab(pred), _norm_lab(target), m.numpy(), window_size, sigma)
    expected = 1.0 - ssim.mean()
    got = ssim_loss_3d(pred, target, m, window_size=window_size, sigma=sigma)
    assert abs(float(got) - expected) < 1e-10
    ssim_map = masked_ssim3d(torch.from_numpy(_norm_lab(pred)), torch.from_numpy(_norm_lab(target)), m,
                             window_size, sigma)
    np.testing.assert_allclose(ssim_map[:, m].numpy(), ssim, rtol=0, atol=1e-10)
    assert bool((ssim_map[:, ~m] == 0).all())


@pytest.mark.parametrize("kind", MASKS)
def test_edge_loss_matches_reference(kind):
    pred, target = _volumes(seed=7)
    m = _mask(kind, pred.shape[1:], seed=8)
    expected = _edge_reference(_norm_lab(pred), _norm_lab(target), m.numpy())
    assert float(edge_loss_3d(pred, target, m)) == pytest.approx(expected, rel=1e-10)


@pytest.mark.parametrize("kind", MASKS)
def test_color_loss_matches_reference(kind):
    pred, target = _volumes(seed=9)
    m = _mask(kind, pred.shape[1:], seed=10)
    assert float(color_loss(pred, target, m)) == pytest.approx(_color_reference(pred, target, m.numpy()), rel=1e-12)


def test_sobel_kernels_are_kornia_sobel_extended_to_3d():
    kernels = sobel_kernels_3d(dtype=torch.float64)
    assert kernels.shape == (3, 3, 3, 3)
    for got, expected in zip(kernels, _sobel_reference_kernels()):
        np.testing.assert_array_equal(got.numpy(), expected)
        # the paper's range: for C, T in [0, 1], S∗(C − T) reaches ±32 (C − T = ±sign(S)) and no further
        assert float(got.abs().sum()) == 32.0 and float(got.clamp(min=0).sum()) == 16.0


def test_edge_loss_of_a_step_by_hand():
    """A step of height δ in normalised L* across x inside a full 3×3×3 block of texels."""
    delta = 0.25
    target = torch.full((3, 3, 3, 3), 0.5, dtype=torch.float64)
    pred = target.clone()
    grey = lambda L: ((L + 16) / 116) ** 3  # linear grey with lightness L* (> 8)
    base_l = float(rgb_to_lab(target[:, 0, 0, 0], dim=0)[0])
    pred[:, :, :, 2] = grey(base_l + 100 * delta)  # the x = 2 plane is δ lighter
    m = torch.ones(3, 3, 3, dtype=torch.bool)
    diff = torch.from_numpy(_norm_lab(pred) - _norm_lab(target))
    assert float(diff[0, 1, 1, 2]) == pytest.approx(delta, rel=1e-9)
    # at the centre texel, S_x sees the full [1, 2, 1] ⊗ [1, 2, 1] column sum 16 of the step: S_x = 16 δ
    assert float((sobel_kernels_3d(dtype=torch.float64)[0] * diff[0]).sum()) == pytest.approx(16 * delta, rel=1e-9)
    expected = _edge_reference(_norm_lab(pred), _norm_lab(target), m.numpy())
    assert float(edge_loss_3d(pred, target, m)) == pytest.approx(expected, rel=1e-9)


# ------------------------------------------------------------------------------------------------------------------
# SSIM against kornia
# ------------------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("window_size", [5, 11])
def test_masked_ssim3d_full_mask_equals_kornia_ssim3d_inside(window_size):
    """Full mask: kornia's dense 3D SSIM wherever the window lies inside the grid (kornia reflects at the border)."""
    g = torch.Generator().manual_seed(11)
    x = torch.rand(2, 3, 13, 14, 15, generator=g, dtype=torch.float64)
    y = (x + 0.2 * torch.rand(2, 3, 13, 14, 15, generator=g, dtype=torch.float64)).clamp(0, 1)
    ours = masked_ssim3d(x, y, torch.ones(13, 14, 15, dtype=torch.bool), window_size, 1.5)
    theirs = kornia_ssim3d(x, y, window_size, padding="valid")
    r = window_size // 2
    torch.testing.assert_close(ours[..., r:-r, r:-r, r:-r], theirs, rtol=0, atol=1e-9)


def test_masked_ssim3d_on_one_layer_is_kornia_2d_ssim():
    """A texel sheet (one layer) gets 2D SSIM over the sheet: the empty layers add no bias."""
    g = torch.Generator().manual_seed(12)
    x = torch.rand(1, 3, 5, 20, 21, generator=g, dtype=torch.float64)
    y = (x + 0.3 * torch.rand(1, 3, 5, 20, 21, generator=g, dtype=torch.float64)).clamp(0, 1)
    m = torch.zeros(5, 20, 21, dtype=torch.bool)
    m[2] = True
    x_garbage = x.clone()
    x_garbage[:, :, [0, 1, 3, 4]] = 7.0
    ours = masked_ssim3d(x_garbage, y, m, 11, 1.5)[:, :, 2]
    theirs = kornia_ssim(x[:, :, 2], y[:, :, 2], 11, padding="valid")
    torch.testing.assert_close(ours[..., 5:-5, 5:-5], theirs, rtol=0, atol=1e-9)


# ------------------------------------------------------------------------------------------------------------------
# properties
# ------------------------------------------------------------------------------------------------------------------
def test_identical_inputs_give_zero(dtype):
    pred, _ = _volumes(shape=(3, 4, 16, 16), seed=13, dtype=dtype)
    m = _mask("random", pred.shape[1:], seed=14)
    assert float(color_loss(pred, pred.clone(), m)) == 0.0
    assert abs(float(ssim_loss_3d(pred, pred.clone(), m))) < (1e-6 if dtype == torch.float32 else 1e-14)
    assert float(edge_loss_3d(pred, pred.clone(), m)) == 0.0
    total, parts = AppearanceLoss().forward_parts(pred, pred.clone(), m)
    assert abs(float(total)) < (1e-6 if dtype == torch.float32 else 1e-14)


def test_ssim_loss_range():
    pred, target = _volumes(shape=(3, 3, 12, 12), seed=15)
    m = _mask("random", pred.shape[1:], seed=16)
    value = float(ssim_loss_3d(pred, target, m))
    assert 0.0 < value <= 2.0
    # anti-correlated structure with equal means: SSIM < 0, loss > 1
    base = torch.rand(3, 3, 12, 12, generator=torch.Generator().manual_seed(17), dtype=torch.float64)
    a, b = 0.3 + 0.4 * base, 0.7 - 0.4 * base
    full = torch.ones(3, 12, 12, dtype=torch.bool)
    assert 1.0 < float(ssim_loss_3d(a, b, full)) <= 2.0
    # a tiny change is seen: strictly positive
    assert float(ssim_loss_3d(pred, pred + 1e-3 * (target - pred), m)) > 0.0


def test_values_outside_the_mask_are_ignored():
    pred, target = _volumes(shape=(3, 5, 9, 10), seed=18)
    m = _mask("shell", pred.shape[1:])
    m[2, 3, 4] = True  # plus an isolated interior texel
    garbage_pred, garbage_target = pred.clone(), target.clone()
    outside = ~m
    garbage_pred[:, outside] = torch.tensor([1e6, -3.0, float("nan")], dtype=torch.float64)[:, None]
    garbage_target[:, outside] = float("inf")
    fns = [color_loss, ssim_loss_3d, edge_loss_3d, AppearanceLoss()]
    for fn in fns:
        p1, p2 = pred.clone().requires_grad_(), garbage_pred.clone().requires_grad_()
        v1, v2 = fn(p1, target, m), fn(p2, garbage_target, m)
        assert float(v1.detach()) == float(v2.detach()), fn
        v1.backward()
        v2.backward()
        assert bool((p2.grad[:, outside] == 0).all())
        torch.testing.assert_close(p1.grad, p2.grad, rtol=0, atol=0)


def test_batches_average_over_texels():
    g = torch.Generator().manual_seed(19)
    pred = torch.rand(2, 3, 4, 8, 8, generator=g, dtype=torch.float64)
    target = torch.rand(2, 3, 4, 8, 8, generator=g, dtype=torch.float64)
    shared = _mask("random", (4, 8, 8), seed=20)
    per_item = torch.stack([_mask("random", (4, 8, 8), seed=21), _mask("top", (4, 8, 8))])[:, None]
    counts = per_item.flatten(1).sum(1).double()
    for fn in (color_loss, ssim_loss_3d, edge_loss_3d):
        batched = float(fn(pred, target, shared))
        singles = [float(fn(pred[i], target[i], shared)) for i in range(2)]
        assert batched == pytest.approx(sum(singles) / 2, rel=1e-12)
        batched = float(fn(pred, target, per_item))
        singles = torch.tensor([float(fn(pred[i], target[i], per_item[i, 0])) for i in range(2)], dtype=torch.float64)
        if fn is ssim_loss_3d:  # 1 − mean SSIM: average the SSIM sums, not the losses' constant 1
            expected = 1 - float(((1 - singles) * counts).sum() / counts.sum())
        else:
            expected = float((singles * counts).sum() / counts.sum())
        assert batched == pytest.approx(expected, rel=1e-12)


def test_float_mask_equals_bool_mask():
    pred, target = _volumes(seed=22)
    m = _mask("random", pred.shape[1:], seed=23)
    assert float(appearance_loss(pred, target, m)) == float(appearance_loss(pred, target, m.double()))


def test_appearance_loss_is_normalised_weighted_sum():
    pred, target = _volumes(shape=(3, 4, 8, 8), seed=24)
    m = _mask("two_sheets", pred.shape[1:])
    e1, e2, e3 = color_loss(pred, target, m), ssim_loss_3d(pred, target, m), edge_loss_3d(pred, target, m)
    loss = AppearanceLoss(gamma=(1.0, 6.0, 2.0))
    total, parts = loss.forward_parts(pred, target, m)
    assert set(parts) == {"E1", "E2", "E3"}
    for name, value in zip(("E1", "E2", "E3"), (e1, e2, e3)):
        assert float(parts[name]) == pytest.approx(float(value), rel=1e-13)
    assert float(total) == pytest.approx(float((1 * e1 + 6 * e2 + 2 * e3) / 9), rel=1e-13)
    assert float(loss(pred, target, m)) == pytest.approx(float(total), rel=1e-13)
    # γ = 0 terms: skipped by forward, reported without gradient by forward_parts
    only_color = AppearanceLoss(gamma=(2.0, 0.0, 0.0))
    p = pred.clone().requires_grad_()
    total, parts = only_color.forward_parts(p, target, m)
    assert total.item() == pytest.approx(float(e1), rel=1e-13)
    assert parts["E1"].requires_grad and not parts["E2"].requires_grad and not parts["E3"].requires_grad
    assert float(parts["E2"]) == pytest.approx(float(e2), rel=1e-13)
    assert only_color(p, target, m).item() == pytest.approx(float(e1), rel=1e-13)


def test_modules_match_functions():
    pred, target = _volumes(seed=25)
    m = _mask("random", pred.shape[1:], seed=26)
    assert float(ColorLoss()(pred, target, m)) == float(color_loss(pred, target, m))
    assert float(SSIMLoss3D(5, 1.0)(pred, target, m)) == float(ssim_loss_3d(pred, target, m, 5, 1.0))
    assert float(EdgeLoss3D()(pred, target, m)) == float(edge_loss_3d(pred, target, m))
    assert "gamma=(1.0, 3.0, 1.0)" in repr(AppearanceLoss())


# ------------------------------------------------------------------------------------------------------------------
# gradients
# ------------------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("kind", ["random", "two_sheets"])
@pytest.mark.parametrize("name, fn", [
    ("E1", color_loss),
    ("E2", ssim_loss_3d),
    ("E2_w3", lambda p, t, m: ssim_loss_3d(p, t, m, 3, 0.7)),
    ("E3", edge_loss_3d),
    ("E", AppearanceLoss((1.0, 3.0, 1.0))),
])
def test_gradcheck(name, fn, kind):
    pred, target = _volumes(shape=(3, 3, 4, 5), seed=27)
    m = _mask(kind, pred.shape[1:], seed=28)
    pred.requires_grad_()
    target.requires_grad_()
    assert torch.autograd.gradcheck(lambda p, t: fn(p, t, m), (pred, target), eps=1e-6, atol=1e-7, rtol=1e-5)


def test_gradcheck_batched_per_item_masks():
    g = torch.Generator().manual_seed(29)
    pred = (0.1 + 0.8 * torch.rand(2, 3, 3, 4, 4, generator=g, dtype=torch.float64)).requires_grad_()
    target = 0.1 + 0.8 * torch.rand(2, 3, 3, 4, 4, generator=g, dtype=torch.float64)
    m = torch.rand(2, 1, 3, 4, 4, generator=g) < 0.6
    assert torch.autograd.gradcheck(lambda p: AppearanceLoss()(p, target, m), (pred,), eps=1e-6, atol=1e-7)


# ------------------------------------------------------------------------------------------------------------------
# refusals
# ------------------------------------------------------------------------------------------------------------------
def _bad_calls():
    p, t = _volumes(shape=(3, 2, 3, 4))
    m = torch.ones(2, 3, 4, dtype=torch.bool)
    nan_target = t.clone()
    nan_target[1, 1, 1, 1] = float("nan")
    return [
        (lambda: color_loss(p, t[:, :, :, :3], m), r"target: expected the shape of pred"),
        (lambda: color_loss(p[:2], t[:2], m), r"pred: expected shape \(3, D, H, W\)"),
        (lambda: color_loss(p[0], t[0], m), r"pred: expected shape \(3, D, H, W\)"),
        (lambda: color_loss(p.numpy(), t, m), "pred: expected a torch.Tensor"),
        (lambda: color_loss(p, t.float(), m),
         r"target: expected the dtype of pred \(torch.float64\), got torch.float32"),
        (lambda: color_loss(p.half(), t.half(), m),
         "pred: expected dtype torch.float32 or torch.float64, got torch.float16"),
        (lambda: color_loss(p, t, m[:, :, :3]), r"mask: expected shape \(2, 3, 4\)"),
        (lambda: color_loss(p, t, m[None]), r"mask: expected shape \(2, 3, 4\)"),
        (lambda: color_loss(p[None].expand(2, -1, -1, -1, -1), t[None].expand(2, -1, -1, -1, -1),
                            m[None, None].expand(3, 1, -1, -1, -1)), r"mask: expected shape"),
        (lambda: color_loss(p, t, torch.zeros_like(m)), "mask: expected at least one texel"),
        (lambda: color_loss(p, t, m.double() * 0.5), "mask: expected only 0 and 1"),
        (lambda: color_loss(p, t, [[1]]), "mask: expected a torch.Tensor"),
        (lambda: color_loss(p, nan_target, m), "target: expected finite values where mask is True, got 1 NaN/Inf"),
        (lambda: ssim_loss_3d(p, nan_target, m), "target: expected finite values where mask is True, got 1 NaN/Inf"),
        (lambda: edge_loss_3d(nan_target, t, m), "pred: expected finite values where mask is True, got 1 NaN/Inf"),
        (lambda: ssim_loss_3d(p, t, m, window_size=4), "window_size: expected an odd int >= 1, got 4"),
        (lambda: ssim_loss_3d(p, t, m, sigma=0.0), r"sigma: expected a finite value in \(0, inf\], got 0.0"),
        (lambda: SSIMLoss3D(window_size=2.5), "window_size: expected an odd int, got float"),
        (lambda: AppearanceLoss(gamma=(1.0, 2.0)), r"gamma: expected 3 weights \(γ1, γ2, γ3\), got 2"),
        (lambda: AppearanceLoss(gamma=(1.0, -1.0, 0.0)), "gamma: expected finite weights >= 0"),
        (lambda: AppearanceLoss(gamma=(0.0, 0.0, 0.0)), "not all 0"),
        (lambda: AppearanceLoss(gamma=3.0), "gamma: expected a sequence of 3 numbers, got float"),
        (lambda: masked_ssim3d(p, t, m, c1=0.0), "c1: expected a finite number > 0, got 0.0"),
    ]


@pytest.mark.parametrize("index", range(len(_bad_calls())))
def test_bad_input_is_refused_with_a_named_message(index):
    call, match = _bad_calls()[index]
    with pytest.raises((TypeError, ValueError), match=match):
        call()


def test_module_constants_match_the_paper():
    assert losses.SSIM_C1 == 0.01**2 and losses.SSIM_C2 == 0.03**2
    assert math.isclose(losses._EDGE_FACTOR, 100 / 3 / 4 / 32)


def test_losses_on_the_curved_texel_shell_of_a_voxelised_sphere():
    """Object prints put texel colours on the voxel grid (VoxelObject.texels_to_grid) and mask the texels: on the
    curved one-voxel shell of a sphere (rows and layers with texels only at their ends, padding planes empty) E1,
    E2 and E3 equal the explicit references computed from the texel list."""
    import trimesh

    from torch_appearance.geometry import voxelize

    obj = voxelize(trimesh.creation.icosphere(subdivisions=3, radius=1.0), 0.2)
    n = len(obj.texel_voxels)
    g = torch.Generator().manual_seed(3)
    pred, target = 0.05 + 0.9 * torch.rand(n, 3, generator=g, dtype=torch.float64), \
        0.05 + 0.9 * torch.rand(n, 3, generator=g, dtype=torch.float64)
    pred_grid, target_grid = obj.texels_to_grid(pred), obj.texels_to_grid(target)
    m = obj.texels_to_grid(torch.ones(n, 1, dtype=torch.bool))[0]
    assert 100 < n == int(m.sum()) and not bool(m[0].any())  # a padding layer without texels
    mn = m.numpy()
    ssim = _ssim_reference(_norm_lab(pred_grid), _norm_lab(target_grid), mn)
    assert abs(float(ssim_loss_3d(pred_grid, target_grid, m)) - (1.0 - ssim.mean())) < 1e-10
    expected = _edge_reference(_norm_lab(pred_grid), _norm_lab(target_grid), mn)
    assert float(edge_loss_3d(pred_grid, target_grid, m)) == pytest.approx(expected, rel=1e-10)
    assert float(color_loss(pred_grid, target_grid, m)) == pytest.approx(
        _color_reference(pred_grid, target_grid, mn), rel=1e-12)
