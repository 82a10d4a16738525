"""The kornia-based filters under rings.orientation against independent references (scipy.ndimage, OpenCV)."""
import cv2
import numpy as np
import pytest
import torch
from scipy import ndimage

from torch_appearance.rings.orientation import _box_mean, _gaussian_blur, _scharr


def _image(h, w, c=2, seed=0):
    return np.random.default_rng(seed).random((c, h, w)).astype(np.float64)


@pytest.mark.parametrize("shape", [(40, 52), (5, 30), (30, 4), (3, 3)])
@pytest.mark.parametrize("sigma", [1.0, 1.7])
def test_gaussian_blur_matches_scipy(shape, sigma):
    """Radius ceil(3 sigma); reflect padding (scipy 'mirror'), replicate (scipy 'nearest') on axes not longer
    than the radius."""
    x = _image(*shape)
    r = int(np.ceil(3 * sigma))
    out = _gaussian_blur(torch.from_numpy(x), sigma).numpy()
    modes = ["mirror" if r < n else "nearest" for n in shape]
    for c in range(x.shape[0]):
        ref = ndimage.gaussian_filter(x[c], sigma, mode=modes, truncate=r / sigma)
        np.testing.assert_allclose(out[c], ref, atol=1e-12)
    t = torch.from_numpy(x)
    assert _gaussian_blur(t, 0.0) is t


def test_scharr_matches_opencv():
    x = _image(23, 31)
    gx, gy = _scharr(torch.from_numpy(x))
    for c in range(x.shape[0]):
        np.testing.assert_allclose(gx[c].numpy(), cv2.Scharr(x[c], cv2.CV_64F, 1, 0, borderType=cv2.BORDER_REPLICATE)
                                   / 32.0, atol=1e-12)
        np.testing.assert_allclose(gy[c].numpy(), cv2.Scharr(x[c], cv2.CV_64F, 0, 1, borderType=cv2.BORDER_REPLICATE)
                                   / 32.0, atol=1e-12)
    ramp = torch.arange(10.0)[None, None, :].expand(1, 6, 10) * 0.5  # unit-normalised: slope 0.5 -> 0.5
    assert torch.allclose(_scharr(ramp)[0][0, :, 1:-1], torch.full((6, 8), 0.5))


@pytest.mark.parametrize("window", [1, 3, 15, 61])
def test_box_mean_matches_opencv(window):
    x = _image(40, 33)
    out = _box_mean(torch.from_numpy(x), window).numpy()
    for c in range(x.shape[0]):
        ref = cv2.blur(x[c], (window, window), borderType=cv2.BORDER_REPLICATE)
        np.testing.assert_allclose(out[c], ref, atol=1e-12)
