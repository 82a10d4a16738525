"""Differentiable curved Gabor filter (rings.gabor.CurvedGaborFilter / curved_gabor_response) and the Gabor phase
loss (nn.GaborPhaseLoss)."""
import math

import numpy as np
import pytest
import torch

from torch_appearance.nn import GaborPhaseLoss, WoodModel, gabor_phase_loss
from torch_appearance.rings import synthetic_board
from torch_appearance.rings.gabor import CurvedGaborFilter, curved_gabor_response

LUMA = np.array([0.2126, 0.7152, 0.0722], np.float32)


def _rings(h, w, period, shift=0.0, theta_deg=20.0, dtype=torch.float32):
    """Straight rings cos(2 pi (t - shift) / period), t along the normal (-sin theta, cos theta) (px)."""
    y, x = torch.meshgrid(torch.arange(h, dtype=dtype), torch.arange(w, dtype=dtype), indexing="ij")
    th = math.radians(theta_deg)
    t = -math.sin(th) * x + math.cos(th) * y
    return torch.cos(2 * math.pi * (t - shift) / period)


def _cyclic(a):
    return np.angle(np.exp(1j * np.asarray(a, np.float64)))


# ----------------------------------------------------------------------------------------------------------------
# the filter


def test_filter_reproduces_curved_gabor_on_a_board():
    gray = synthetic_board(72, 96, seed=5)["image"] @ LUMA
    filt = CurvedGaborFilter.from_image(gray, p=16, q=16)
    res = filt.reference
    r = filt(torch.from_numpy(gray))
    assert r.shape == gray.shape and r.dtype == torch.complex64
    mag = r.abs().numpy()
    assert np.abs(mag - res.magnitude).max() < 1e-5 * res.magnitude.max()
    strong = res.magnitude > 0.05 * res.magnitude.max()
    assert np.abs(_cyclic(r.angle().numpy() - res.phase))[strong].max() < 1e-3
    # the function traces the same geometry on every call
    r2 = curved_gabor_response(torch.from_numpy(gray), res.theta, res.frequency, res.normal, p=16, q=16)
    assert torch.allclose(r2, r, atol=1e-6)


def test_phase_of_shifted_rings_is_the_shift():
    """Truth: rings moved by d px along the normal have their phase changed by -2 pi d / period everywhere."""
    period = 9.0
    filt = CurvedGaborFilter.from_image(_rings(64, 64, period), p=18, q=10)
    n = torch.from_numpy(filt.reference.normal)
    assert float(n[32, 32, 1]) > 0  # normal of the dominant orientation points towards +y
    r0 = filt(_rings(64, 64, period))
    for shift in (-2.0, 0.7, 3.0):
        d = torch.angle(filt(_rings(64, 64, period, shift)) * r0.conj())[12:-12, 12:-12]
        assert torch.allclose(d, torch.full_like(d, -2 * math.pi * shift / period), atol=0.02), shift
    assert torch.allclose(r0.abs()[12:-12, 12:-12], torch.ones(40, 40), atol=0.03)  # unit-amplitude rings


def test_response_is_linear_and_batched():
    filt = CurvedGaborFilter.from_image(_rings(40, 48, 7.0), p=8, q=8)
    a, b = torch.rand(40, 48, generator=torch.Generator().manual_seed(0)), _rings(40, 48, 5.0, 1.0)
    r = filt(torch.stack([a, b, 2.0 * a - 3.0 * b]))
    assert r.shape == (3, 40, 48)
    assert torch.allclose(r[2], 2.0 * r[0] - 3.0 * r[1], atol=1e-5)
    assert torch.allclose(filt(a), r[0], atol=1e-6)
    # a constant image has no response (the profile mean is removed)
    assert float(filt(torch.full((40, 48), 0.7)).abs().max()) < 1e-5


def test_filter_gradcheck_float64():
    filt = CurvedGaborFilter.from_image(_rings(10, 11, 5.0), p=6, q=3)
    img = torch.rand(10, 11, dtype=torch.float64, generator=torch.Generator().manual_seed(1), requires_grad=True)
    assert torch.autograd.gradcheck(lambda x: torch.view_as_real(filt(x)), (img,), eps=1e-6, atol=1e-8)


# ----------------------------------------------------------------------------------------------------------------
# the loss


def test_loss_gradcheck_float64_both_modes():
    target = _rings(12, 12, 5.0)
    gen = torch.Generator().manual_seed(2)
    pred = (_rings(12, 12, 5.0, 0.4, dtype=torch.float64) + 0.05 * torch.randn(12, 12, generator=gen,
                                                                              dtype=torch.float64))
    for mode in ("squared", "cosine"):
        loss_fn = GaborPhaseLoss(target, p=6, q=3, mode=mode)
        assert float(loss_fn.phase_difference(pred).abs().max()) < 2.5  # away from the wrap at +-pi
        x = pred.clone().requires_grad_(True)
        assert torch.autograd.gradcheck(loss_fn, (x,), eps=1e-6, atol=1e-7), mode


def test_loss_values_against_truth():
    target = _rings(48, 48, 8.0, theta_deg=-10.0)
    loss_fn = GaborPhaseLoss(target, p=12, q=8)
    assert float(loss_fn(target)) < 1e-10
    # the phase ignores contrast and offset; an inverted image is half a period (pi) away everywhere
    assert float(loss_fn(0.3 * target + 2.0)) < 1e-8
    assert float(loss_fn(-target)) == pytest.approx(math.pi ** 2, rel=1e-4)
    # rings shifted by 1 px: d = -2 pi / 8 in the interior, the loss is the weighted mean of d^2
    d = loss_fn.phase_difference(_rings(48, 48, 8.0, 1.0, theta_deg=-10.0))[0]
    assert float((d[10:-10, 10:-10] + math.pi / 4).abs().max()) < 0.02
    w = loss_fn.weight
    shifted = _rings(48, 48, 8.0, 1.0, theta_deg=-10.0)
    assert float(loss_fn(shifted)) == pytest.approx(float((w * d ** 2).sum() / w.sum()), rel=1e-5)
    cos_fn = GaborPhaseLoss(target, p=12, q=8, mode="cosine")
    assert float(cos_fn(shifted)) == pytest.approx(float((w * 2 * (1 - torch.cos(d))).sum() / w.sum()), rel=1e-5)
    # the weight follows the target's ring amplitude: rings of 1/4 the contrast weigh 1/4 as much
    half = target.clone()
    half[:, 24:] *= 0.25
    wh = GaborPhaseLoss(half, p=12, q=8).weight
    assert float(wh[14:34, 30:40].mean() / wh[14:34, 8:18].mean()) == pytest.approx(0.25, rel=0.05)
    # RGB (C, H, W) and batches: grey by Rec. 709 luminance, the batch mean
    # Rec. 709 grey of (t, -t, t) is -0.4304 t: half a period away
    assert float(loss_fn(torch.stack([target, -target, target]))) == pytest.approx(math.pi ** 2, rel=1e-4)
    rgb = torch.stack([target, target, target])
    assert float(GaborPhaseLoss(rgb, p=12, q=8)(torch.stack([rgb, -rgb]))) == pytest.approx(math.pi ** 2 / 2,
                                                                                            rel=1e-4)


def test_gabor_phase_loss_function():
    t = torch.polar(torch.ones(3, 3), torch.zeros(3, 3))
    r = torch.polar(torch.full((2, 3, 3), 0.5), torch.tensor([0.2, -3.0])[:, None, None].expand(2, 3, 3))
    assert float(gabor_phase_loss(r, t)) == pytest.approx((0.2 ** 2 + 3.0 ** 2) / 2, rel=1e-6)
    w = torch.zeros(3, 3)
    w[0, 0] = 1.0
    r2 = r.clone()
    r2[:, 1:] = 0  # a vanishing response contributes nothing (and no NaN)
    assert float(gabor_phase_loss(r2, t, w, mode="cosine")) == pytest.approx(
        (2 * (1 - math.cos(0.2)) + 2 * (1 - math.cos(3.0))) / 2, rel=1e-6)


def test_loss_recovers_wood_ring_scale():
    """A WoodModel render with the ring scale 15 % too large is driven back to the truth by Adam on the loss."""
    h = w = 56
    px, s_true = 0.1, 0.8
    model = WoodModel(ring_scale_mm=s_true, distortion=None)
    with torch.no_grad():
        model.translation.copy_(torch.tensor([-2.5, -3.1, 0.0]))  # pith inside the image
        target = model.render_board(h, w, px)["image"].permute(2, 0, 1)
        model.log_ring_scale.fill_(math.log(1.15 * s_true))
    loss_fn = GaborPhaseLoss(target, p=12, q=12)
    opt = torch.optim.Adam([model.log_ring_scale], lr=0.02)
    losses = []
    for _ in range(80):
        opt.zero_grad()
        loss = loss_fn(model.render_board(h, w, px)["image"].permute(2, 0, 1))
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert model.ring_scale.item() == pytest.approx(s_true, rel=0.01)
    assert min(losses[-10:]) < 0.01 * losses[0]


def test_wood_render_gradient_matches_finite_differences():
    """End to end in float64: d loss / d log s_r of a WoodModel render whose colour map is periodic in the lateness
    (no jump at ring boundaries, so the render is differentiable) equals the central finite difference."""
    h = w = 40
    model = WoodModel(ring_scale_mm=0.8, distortion=None, n_rings=4, dtype=torch.float64)
    with torch.no_grad():
        model.translation.copy_(torch.tensor([-1.8, -2.2, 0.0], dtype=torch.float64))
        late = torch.linspace(0, 1, model.color_bins, dtype=torch.float64)
        model.color_map.copy_((0.5 - 0.3 * torch.cos(2 * math.pi * late))[None, :, None].expand_as(model.color_map))
        target = model.render_board(h, w, 0.1)["image"].permute(2, 0, 1)
    loss_fn = GaborPhaseLoss(target, p=10, q=8)

    def loss_at(log_s):
        with torch.no_grad():
            model.log_ring_scale.fill_(log_s)
            return loss_fn(model.render_board(h, w, 0.1)["image"].permute(2, 0, 1)).item()

    for factor in (1.03, 0.96):
        log_s = math.log(0.8 * factor)
        loss_at(log_s)
        model.zero_grad()
        loss_fn(model.render_board(h, w, 0.1)["image"].permute(2, 0, 1)).backward()
        # small step: the colour map is piecewise linear in the lateness, and a larger step straddles its kinks
        fd = (loss_at(log_s + 1e-7) - loss_at(log_s - 1e-7)) / 2e-7
        assert abs(fd) > 1.0
        assert model.log_ring_scale.grad.item() == pytest.approx(fd, rel=1e-6), factor


# ----------------------------------------------------------------------------------------------------------------
# bad input


def test_bad_input_is_refused():
    target = _rings(24, 24, 6.0)
    with pytest.raises(ValueError, match="mode"):
        GaborPhaseLoss(target, p=6, q=6, mode="abs")
    with pytest.raises(ValueError, match="permute"):
        GaborPhaseLoss(torch.rand(24, 24, 3), p=6, q=6)
    with pytest.raises(ValueError, match="batch 1"):
        GaborPhaseLoss(torch.rand(2, 1, 24, 24), p=6, q=6)
    with pytest.raises(TypeError, match="target"):
        GaborPhaseLoss([[0.0] * 24] * 24, p=6, q=6)
    with pytest.raises(ValueError, match="mask"):
        GaborPhaseLoss(target, p=6, q=6, mask=torch.ones(23, 24))
    with pytest.raises(ValueError, match="weight_cap"):
        GaborPhaseLoss(target, p=6, q=6, weight_cap=0.0)
    loss_fn = GaborPhaseLoss(target, p=6, q=6)
    with pytest.raises(ValueError, match=r"\(24, 24\)"):
        loss_fn(torch.rand(24, 25))
    with pytest.raises(TypeError, match="floating"):
        loss_fn(torch.ones(24, 24, dtype=torch.int64))
    with pytest.raises(ValueError, match="target"):
        GaborPhaseLoss(torch.zeros(24, 24), p=6, q=6)
    with pytest.raises(TypeError, match="complex"):
        gabor_phase_loss(torch.ones(3, 3), torch.ones(3, 3, dtype=torch.complex64))
    filt = CurvedGaborFilter.from_image(target, p=6, q=6)
    with pytest.raises(ValueError, match="image"):
        filt(torch.rand(2, 24, 20))
    with pytest.raises(ValueError, match="frequency"):
        CurvedGaborFilter(np.zeros((8, 8)), np.full((8, 8), 0.7), p=3, q=3)
    with pytest.raises(ValueError, match="normal"):
        CurvedGaborFilter(np.zeros((8, 8)), np.full((8, 8), 0.2), np.zeros((8, 8, 2)), p=3, q=3)
    with pytest.raises(ValueError, match="p must be"):
        curved_gabor_response(torch.rand(8, 8), np.zeros((8, 8)), np.full((8, 8), 0.2), p=0)
