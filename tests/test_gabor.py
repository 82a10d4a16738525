"""Orientation field and curved Gabor filter (torch_appearance.rings.orientation / .gabor)."""
import math

import numpy as np
import pytest
import torch

from torch_appearance.rings.gabor import GaborResult, curved_gabor
from torch_appearance.rings.orientation import orientation_field, orientation_from_phase


def _angle_diff_mod_pi(a, b):
    """Absolute difference of two orientations (mod pi), in radians."""
    return np.abs(np.angle(np.exp(2j * (np.asarray(a, np.float64) - np.asarray(b, np.float64))))) / 2.0


def _wrap(a):
    return np.angle(np.exp(1j * np.asarray(a, np.float64)))


def _grid(h, w):
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    return x, y


def _straight_rings(h, w, theta, period, phi0=0.3, amplitude=1.0):
    """cos(2 pi t / period + phi0) with t the coordinate along the ring normal (-sin theta, cos theta)."""
    x, y = _grid(h, w)
    t = -math.sin(theta) * (x - w / 2) + math.cos(theta) * (y - h / 2)
    return (amplitude * np.cos(2 * math.pi * t / period + phi0)).astype(np.float32), t


def _circle_rings(h, w, cx, cy, period, phi0=0.3, amplitude=1.0):
    """Concentric circles around (cx, cy) (px): image, radius, exact tangent orientation in [0, pi)."""
    x, y = _grid(h, w)
    r = np.hypot(x - cx, y - cy)
    theta = np.mod(np.arctan2(y - cy, x - cx) + math.pi / 2, math.pi)
    return (amplitude * np.cos(2 * math.pi * r / period + phi0)).astype(np.float32), r, theta


def _circle_phase_truth(res, r, cx, cy, period, phi0):
    """Expected phase: 2 pi r / period + phi0 where the normal points outwards, its negative where inwards."""
    x, y = _grid(*r.shape)
    outward = (res.normal[..., 0] * (x - cx) + res.normal[..., 1] * (y - cy)) / np.maximum(r, 1e-9)
    return np.sign(outward) * (2 * math.pi * r / period + phi0), outward


# ----------------------------------------------------------------------------------------------------------------
# orientation field


@pytest.mark.parametrize("deg", [0.0, 20.0, 45.0, 70.0, 90.0, 135.0, 172.0])
def test_orientation_of_sinusoid_within_2_degrees(deg):
    img, _ = _straight_rings(96, 96, math.radians(deg), period=9.0)
    theta, coherence = orientation_field(img, sigma_smooth=1.0, window=15)
    assert theta.shape == img.shape and theta.dtype == np.float32
    assert theta.min() >= 0.0 and theta.max() < math.pi
    inner = (slice(10, -10), slice(10, -10))
    err = np.degrees(_angle_diff_mod_pi(theta[inner], math.radians(deg)))
    assert err.max() < 2.0, f"orientation error up to {err.max():.3f} deg for rings at {deg} deg"
    assert coherence[inner].min() > 0.9


def test_orientation_accepts_torch_and_flags_isotropic_texture():
    img, _ = _straight_rings(64, 64, 0.4, period=8.0)
    th_np, _ = orientation_field(img)
    th_t, _ = orientation_field(torch.from_numpy(img).double())
    np.testing.assert_allclose(th_np, th_t, atol=1e-5)
    noise = np.random.default_rng(0).standard_normal((64, 64)).astype(np.float32)
    _, coh = orientation_field(noise, window=15)
    assert np.median(coh) < 0.5
    _, coh_flat = orientation_field(np.zeros((16, 16), np.float32))
    assert np.all(coh_flat == 0)


def test_orientation_from_phase_is_wrap_free():
    x, y = _grid(80, 80)
    theta_true = math.radians(30.0)
    t = -math.sin(theta_true) * x + math.cos(theta_true) * y
    phase = _wrap(2 * math.pi * t / 11.0)  # wrapped: naive gradients would see 2 pi jumps
    theta, coh = orientation_from_phase(phase, magnitude=np.ones_like(phase))
    err = np.degrees(_angle_diff_mod_pi(theta[8:-8, 8:-8], theta_true))
    assert err.max() < 1.0 and coh[8:-8, 8:-8].min() > 0.95


@pytest.mark.parametrize("bad, exc, match", [
    (np.zeros((0, 0), np.float32), ValueError, "at least"),
    (np.zeros((16, 16, 3), np.float32), ValueError, "colour image"),
    (np.zeros(16, np.float32), ValueError, r"\(H, W\)"),
    (np.full((8, 8), np.nan, np.float32), ValueError, "NaN"),
    ([[1.0, 2.0], [3.0, 4.0]], TypeError, "numpy array or torch tensor"),
])
def test_orientation_bad_inputs(bad, exc, match):
    with pytest.raises(exc, match=match):
        orientation_field(bad)


def test_orientation_bad_parameters():
    img = np.zeros((16, 16), np.float32)
    with pytest.raises(ValueError, match="window"):
        orientation_field(img, window=4)
    with pytest.raises(ValueError, match="sigma_smooth"):
        orientation_field(img, sigma_smooth=-1.0)


# ----------------------------------------------------------------------------------------------------------------
# curved Gabor filter


@pytest.mark.parametrize("period", [6.0, 10.0, 17.0, 30.0])
def test_frequency_estimate_within_3_percent(period):
    img, _ = _straight_rings(128, 128, math.radians(25.0), period)
    res = curved_gabor(img, p=40, q=20)
    rel = np.abs(res.frequency[16:-16, 16:-16] * period - 1.0)
    print(f"period {period}: median rel. frequency error {np.median(rel):.4f}, max {rel.max():.4f}")
    assert np.median(rel) < 0.01
    assert rel.max() < 0.03


def test_barrier_filters_the_two_sides_of_a_mirror_line_apart():
    """Rings mirrored about a line (a board cut through the pith): s = cos(2π|t|/T + c). Without a barrier the
    response is real on the line and the phase of the innermost ring is bent towards 0 or π over about a ring on
    both sides; with the signed distance to the line as the barrier each side keeps the phase ±(2πt/T + c)."""
    T, c, y0 = 16.0, math.pi / 2, 47.5
    y, _ = np.mgrid[0:96, 0:96].astype(np.float32)
    t = y - y0
    img = np.cos(2 * np.pi * np.abs(t) / T + c).astype(np.float32)
    truth = 2 * np.pi * np.abs(t) / T + c  # the phase resolved to grow away from the line
    near = np.abs(t) < T / 2  # the innermost ring on each side
    rms = {}
    for name, barrier in (("plain", None), ("barrier", t)):
        res = curved_gabor(img, p=30, q=10, barrier=barrier)
        resolved = np.where(t * res.normal[..., 1] >= 0, res.phase, -res.phase)
        err = np.angle(np.exp(1j * (resolved - truth)))[:, 16:-16]
        rms[name] = float(np.sqrt((err[near[:, 16:-16]] ** 2).mean()))
    print(rms)
    assert rms["barrier"] < 0.3  # measured 0.19 (the one-sided window next to the line); 1.11 without the barrier
    assert rms["plain"] > 0.8
    with pytest.raises(ValueError, match="barrier"):
        curved_gabor(img, p=10, q=5, barrier=t[:-1])


def test_phase_of_straight_rings_and_normal_convention():
    theta_true = math.radians(60.0)
    img, t = _straight_rings(96, 96, theta_true, period=12.0, phi0=0.3, amplitude=0.7)
    res = curved_gabor(img, p=30, q=20)
    assert isinstance(res, GaborResult)
    for name in ("magnitude", "phase", "frequency", "curvature", "orientation", "theta"):
        arr = getattr(res, name)
        assert arr.shape == img.shape and arr.dtype == np.float32, name
    assert res.normal.shape == (96, 96, 2)
    # Default reference: normal of the dominant orientation, pointing towards +y.
    n_true = np.array([-math.sin(theta_true), math.cos(theta_true)])
    np.testing.assert_allclose(res.normal[48, 48], n_true, atol=0.02)
    inner = (slice(8, -8), slice(8, -8))
    err = _wrap(res.phase - (2 * math.pi * t / 12.0 + 0.3))
    assert np.sqrt(np.mean(err[inner] ** 2)) < 0.02
    # magnitude ~ ring amplitude (bilinear resampling across the rings attenuates by a few per cent)
    np.testing.assert_allclose(np.median(res.magnitude[inner]), 0.7, rtol=0.06)
    assert res.phase.min() > -math.pi - 1e-6 and res.phase.max() <= math.pi + 1e-6
    # Flipping the reference flips the normal and negates the phase.
    res_flip = curved_gabor(img, p=30, q=20, normal_reference=(-n_true[0], -n_true[1]))
    np.testing.assert_allclose(res_flip.normal, -res.normal, atol=1e-6)
    assert np.abs(_wrap(res_flip.phase + res.phase))[inner].max() < 1e-3


@pytest.mark.parametrize("noise", [0.0, 0.3])
def test_phase_of_arches_matches_truth(noise):
    # Concentric circles around a centre above the image: nested arches, as on a flat-sawn board.
    h, w, cx, cy, period, phi0 = 128, 160, 80.0, -40.0, 11.0, 1.1
    img, r, theta_true = _circle_rings(h, w, cx, cy, period, phi0)
    img = img + noise * np.random.default_rng(1).standard_normal(img.shape).astype(np.float32)
    res = curved_gabor(img, p=40, q=40)
    truth, _ = _circle_phase_truth(res, r, cx, cy, period, phi0)
    inner = (slice(10, -10), slice(10, -10))
    err = _wrap(res.phase - truth)[inner]
    rms = float(np.sqrt(np.mean(err ** 2)))
    print(f"arches, noise {noise}: wrapped phase error RMS {rms:.4f} rad, max {np.abs(err).max():.3f} rad")
    assert rms < (0.03 if noise == 0 else 0.1)
    rel = np.abs(res.frequency[inner] * period - 1.0)
    assert np.median(rel) < 0.02
    # Refined orientation (from the phase image) follows the true ring tangent.
    assert np.degrees(_angle_diff_mod_pi(res.orientation, theta_true)[inner]).mean() < 1.0


def test_phase_of_full_circles_and_curvature():
    h = w = 160
    cx, cy, period, phi0 = 80.0, 80.0, 9.0, -0.4
    img, r, theta_true = _circle_rings(h, w, cx, cy, period, phi0)
    res = curved_gabor(img, theta=theta_true, p=25, q=15)
    truth, outward = _circle_phase_truth(res, r, cx, cy, period, phi0)
    # Exclude the centre (rings too curved for the patch) and the line where the normal flips (|outward| ~ 0).
    mask = (r > 30) & (r < 75) & (np.abs(outward) > 0.3)
    err = _wrap(res.phase - truth)[mask]
    rms = float(np.sqrt(np.mean(err ** 2)))
    print(f"full circles: wrapped phase error RMS {rms:.4f} rad")
    assert rms < 0.05
    # Curvature of a circle of radius R is 1 / R (rad/px).
    ring = (r > 40) & (r < 60)
    kr = res.curvature[ring] * r[ring]
    assert abs(np.median(kr) - 1.0) < 0.1, np.median(kr)
    assert np.median(res.curvature[:, :][np.abs(r - 70) < 2]) < np.median(res.curvature[np.abs(r - 35) < 2])


def _naive_response(img, theta, normal, px, py, p, q, f, sigma_along, sigma_across):
    """Slow reference: sample the full curved (2p+1) x (2q+1) patch of one pixel and apply the 2-D Gabor kernel."""
    h, w = img.shape
    c2, s2 = np.cos(2 * theta), np.sin(2 * theta)

    def bilinear(a, x, y):
        x = min(max(x, 0.0), w - 1.0)
        y = min(max(y, 0.0), h - 1.0)
        x0, y0 = min(int(x), w - 2), min(int(y), h - 2)
        fx, fy = x - x0, y - y0
        return ((1 - fx) * (1 - fy) * a[y0, x0] + fx * (1 - fy) * a[y0, x0 + 1]
                + (1 - fx) * fy * a[y0 + 1, x0] + fx * fy * a[y0 + 1, x0 + 1])

    def direction(x, y, prev, normal):
        ang = 0.5 * math.atan2(bilinear(s2, x, y), bilinear(c2, x, y))
        d = np.array([math.cos(ang), math.sin(ang)])
        if normal:
            d = np.array([-d[1], d[0]])
        return d if d @ prev >= 0 else -d

    def walk(x, y, d, steps, normal):
        pts = []
        for _ in range(steps):
            d1 = direction(x, y, d, normal)
            d = direction(x + 0.5 * d1[0], y + 0.5 * d1[1], d1, normal)
            x, y = x + d[0], y + d[1]
            pts.append((x, y))
        return pts

    n0 = np.asarray(normal, np.float64)  # oriented normal at the pixel: the sign convention of the phase
    centre = walk(px, py, -n0, p, True)[::-1] + [(px, py)] + walk(px, py, n0, p, True)  # j = -p..p
    patch = np.empty((2 * p + 1, 2 * q + 1))
    for jj, (x, y) in enumerate(centre):
        t0 = np.array([math.cos(theta[int(round(y)), int(round(x))]), math.sin(theta[int(round(y)), int(round(x))])])
        t0 = direction(x, y, t0, False)
        row = walk(x, y, -t0, q, False)[::-1] + [(x, y)] + walk(x, y, t0, q, False)
        patch[jj] = [bilinear(img, a, b) for a, b in row]
    j = np.arange(-p, p + 1)[:, None]
    k = np.arange(-q, q + 1)[None, :]
    g = np.exp(-0.5 * (j / sigma_across) ** 2 - 0.5 * (k / sigma_along) ** 2)
    patch = patch - (g * patch).sum() / g.sum()
    return 2.0 * (g * patch * np.exp(-2j * math.pi * f * j)).sum() / g.sum()


def test_separable_filter_matches_naive_curved_patch():
    # Wavy rings (curved, non-uniform) with the analytic orientation field.
    h, w = 90, 90
    x, y = _grid(h, w)
    u = y + 6.0 * np.sin(2 * math.pi * x / 70.0)
    img = (np.cos(2 * math.pi * u / 10.0) + 0.3 * np.cos(2 * math.pi * x / 23.0)).astype(np.float32)
    du_dx = 6.0 * 2 * math.pi / 70.0 * np.cos(2 * math.pi * x / 70.0)
    theta = np.mod(np.arctan2(-du_dx, 1.0), math.pi)  # tangent of the level lines u = const
    p = q = 12
    res = curved_gabor(img, theta=theta, p=p, q=q, sigma_along=5.0, sigma_across=4.0)
    for px, py in [(45, 45), (30, 40), (60, 52), (40, 60)]:
        ref = _naive_response(img.astype(np.float64), theta, res.normal[py, px], px, py, p, q, float(res.frequency[py, px]), 5.0, 4.0)
        assert abs(_wrap(res.phase[py, px] - np.angle(ref))) < 0.03, (px, py)
        assert abs(res.magnitude[py, px] / abs(ref) - 1.0) < 0.03, (px, py)


def test_bad_inputs_raise_clear_errors():
    img, _ = _straight_rings(32, 32, 0.0, 8.0)
    with pytest.raises(ValueError, match="at least"):
        curved_gabor(np.zeros((0, 5), np.float32))
    with pytest.raises(ValueError, match=r"single-channel image of shape \(H, W\); got shape \(32, 32, 3\)"):
        curved_gabor(np.repeat(img[..., None], 3, axis=2))
    for name in ("p", "q"):
        with pytest.raises(ValueError, match=f"{name} must be an integer >= 1; got 0"):
            curved_gabor(img, **{name: 0})
    with pytest.raises(ValueError, match="p must be an integer"):
        curved_gabor(img, p=2.5)
    with pytest.raises(ValueError, match="theta must have the shape of gray"):
        curved_gabor(img, theta=np.zeros((31, 32), np.float32))
    with pytest.raises(ValueError, match="sigma_across"):
        curved_gabor(img, sigma_across=0.0)
    with pytest.raises(ValueError, match="freq_range"):
        curved_gabor(img, freq_range=(0.3, 0.2))
    with pytest.raises(ValueError, match="normal_reference"):
        curved_gabor(img, normal_reference=(0.0, 0.0))
    with pytest.raises(TypeError, match="gray"):
        curved_gabor("image.png")
    with pytest.raises(ValueError, match="NaN"):
        curved_gabor(np.where(img > 0, np.nan, img))


def test_threads_and_chunks_do_not_change_the_result():
    img, _ = _straight_rings(48, 40, 0.7, 7.0)
    img = img + 0.2 * np.random.default_rng(3).standard_normal(img.shape).astype(np.float32)
    a = curved_gabor(img, p=10, q=10, chunk_size=1 << 20, num_workers=1)
    b = curved_gabor(img, p=10, q=10, chunk_size=97, num_workers=2)
    for name in ("magnitude", "phase", "frequency", "curvature"):
        np.testing.assert_allclose(getattr(a, name), getattr(b, name), atol=1e-5, err_msg=name)
    assert torch.get_num_threads() >= 1


def test_unrefined_orientation_changes_no_other_field():
    # refine_orientation=False (disc mode) skips the orientation from the phase image and nothing else
    img, _ = _straight_rings(40, 48, 0.4, 9.0)
    img = img + 0.2 * np.random.default_rng(4).standard_normal(img.shape).astype(np.float32)
    theta = np.full(img.shape, 0.4, np.float32)
    for th in (None, theta):
        a = curved_gabor(img, theta=th, p=12, q=8)
        b = curved_gabor(img, theta=th, p=12, q=8, refine_orientation=False)
        assert a.orientation is not None and b.orientation is None
        for name in ("magnitude", "phase", "frequency", "curvature", "theta", "normal"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    with pytest.raises(TypeError, match="refine_orientation"):
        curved_gabor(img, refine_orientation=1)


def test_large_filter_256_p80_q80_is_finite():
    """The issue's size (256², p = q = 80) runs through and gives finite output. Its time is a benchmark target
    (≤ 5 s on 2 idle cores: ``scripts/bench/bench_ring_filters.py``), not a test: a shared machine took 16.5 s."""
    h, w = 256, 256
    img, _, _ = _circle_rings(h, w, 128.0, -150.0, 14.0)
    img = img + 0.1 * np.random.default_rng(0).standard_normal(img.shape).astype(np.float32)
    res = curved_gabor(img, p=80, q=80)
    assert res.phase.shape == (h, w)
    assert np.isfinite(res.phase).all() and np.isfinite(res.magnitude).all()
