"""Colour-difference metrics for reports: CIEDE2000 and CIE76 of linear-RGB colours, via colour-science.

These are evaluation metrics, not losses: they are computed in NumPy float64 by `colour-science
<https://www.colour-science.org>`_ and are not differentiable (use :mod:`torch_appearance.nn.losses` to optimise).

L*a*b* here: linear sRGB → XYZ with the sRGB matrix *derived* by colour-science from the sRGB primaries and the
D65 white ``xy = (0.3127, 0.3290)`` (``[[0.4123908, 0.3575843, 0.1804808], ...]``), then XYZ → L*a*b* relative to
the same D65 (CIE 1931 2°), so that linear white is exactly ``(100, 0, 0)``. (colour-science's default sRGB
colourspace uses the 4-digit matrices printed in IEC 61966-2-1, which map white to ``(100, 0.008, 0.004)`` and are
not exact inverses of each other.) :func:`torch_appearance.color.rgb_to_lab` (kornia, used by the losses) uses the
6-digit matrix ``[[0.412453, 0.357580, 0.180423], ...]`` and white ``(0.95047, 1, 1.08883)``; on the unit RGB
cube the two differ by less than 0.02 ΔE76, far below a just-noticeable difference, but a report's ``dE76_mean``
is not bit-identical to the square root of the loss's E1 per texel.
"""
import functools
import warnings

import numpy as np
import torch

__all__ = ["ssim_2d", "linear_rgb_to_lab", "delta_e_2000", "delta_e_2000_lab", "delta_e_76", "color_report"]


def _as_rgb_array(name, value):
    """``value`` (tensor, ndarray or nested sequence, ``(..., 3)``) → float64 ndarray; refuse bad input by name."""
    if isinstance(value, torch.Tensor):
        if value.dtype.is_complex or value.dtype == torch.bool:
            raise TypeError(f"{name} must hold real numbers, got {value.dtype}")
        array = value.detach().to("cpu", torch.float64).numpy()
    else:
        try:
            array = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError):
            raise TypeError(f"{name} must be a tensor or array of numbers, got {type(value).__name__}") from None
    if array.ndim == 0 or array.shape[-1] != 3:
        raise ValueError(f"{name} must have shape (..., 3) (linear RGB, channels last), got {array.shape}")
    if not np.isfinite(array).all():
        raise ValueError(f"{name} has {int((~np.isfinite(array)).sum())} non-finite values (NaN or inf)")
    return array


def _pair(pred, target):
    a, b = _as_rgb_array("pred", pred), _as_rgb_array("target", target)
    if a.shape != b.shape:
        raise ValueError(f"pred and target must have the same shape, got {a.shape} and {b.shape}")
    return a, b


def _like(result, template):
    """Return ``result`` (ndarray) as a tensor on ``template``'s device and dtype when ``template`` is a tensor."""
    if isinstance(template, torch.Tensor):
        dtype = template.dtype if template.is_floating_point() else torch.float64
        return torch.as_tensor(result, dtype=dtype, device=template.device)
    return result


@functools.lru_cache(maxsize=1)
def _srgb_colourspace():
    import colour  # deferred: importing colour-science takes about a second

    space = colour.models.RGB_COLOURSPACE_sRGB.copy()
    space.use_derived_transformation_matrices(True)
    return space


def _lab(rgb):
    import colour

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", category=colour.utilities.ColourUsageWarning)
        xyz = colour.RGB_to_XYZ(rgb, _srgb_colourspace(), apply_cctf_decoding=False)
        d65 = colour.CCS_ILLUMINANTS["CIE 1931 2 Degree Standard Observer"]["D65"]
        return colour.XYZ_to_Lab(xyz, d65)


def linear_rgb_to_lab(rgb):
    """CIE 1976 L*a*b* (D65) of linear sRGB colours, computed by colour-science (see the module notes).

    Args:
        rgb: ``(..., 3)`` linear RGB, tensor or array, finite (not clipped).

    Returns:
        ``(..., 3)`` L*a*b*; a tensor (input's dtype and device) for tensor input, else a float64 ndarray.

    Example:
        >>> (linear_rgb_to_lab(np.array([1.0, 1.0, 1.0])).round(6) + 0.0).tolist()   # + 0.0: no −0.0
        [100.0, 0.0, 0.0]
    """
    return _like(_lab(_as_rgb_array("rgb", rgb)), rgb)


def delta_e_2000(pred, target):
    """CIEDE2000 colour difference (``colour.delta_E(..., method="CIE 2000")``) of linear-RGB colours.

    Args:
        pred: ``(..., 3)`` linear RGB, tensor or array.
        target: ``(..., 3)`` linear RGB, same shape.

    Returns:
        ``(...)`` ΔE00; a tensor (``pred``'s dtype and device, no gradient) for tensor input, else an ndarray.

    Example:
        >>> float(delta_e_2000(np.array([0.2, 0.3, 0.4]), np.array([0.2, 0.3, 0.4])))
        0.0
    """
    a, b = _pair(pred, target)
    return _like(delta_e_2000_lab(_lab(a), _lab(b)), pred)


def delta_e_2000_lab(lab_a, lab_b):
    """CIEDE2000 of colours already in L*a*b* (``(..., 3)`` float ndarrays, e.g. from :func:`linear_rgb_to_lab`):
    for a caller that compares one colour set with several others and converts each set once.

    Returns:
        ``(...)`` float64 ndarray.

    Example:
        >>> lab = linear_rgb_to_lab(np.array([[0.2, 0.3, 0.4], [0.5, 0.5, 0.5]]))
        >>> delta_e_2000_lab(lab, lab).tolist()
        [0.0, 0.0]
    """
    import colour

    return np.asarray(colour.delta_E(lab_a, lab_b, method="CIE 2000"), dtype=np.float64)


def delta_e_76(pred, target):
    """CIE 1976 colour difference (Euclidean distance in L*a*b*) of linear-RGB colours.

    Args:
        pred: ``(..., 3)`` linear RGB, tensor or array.
        target: ``(..., 3)`` linear RGB, same shape.

    Returns:
        ``(...)`` ΔE76; a tensor (``pred``'s dtype and device, no gradient) for tensor input, else an ndarray.
    """
    a, b = _pair(pred, target)
    return _like(np.linalg.norm(_lab(a) - _lab(b), axis=-1), pred)


def color_report(pred, target, mask=None):
    """Summary colour error of a texel set: mean and 95th percentile of ΔE00, mean ΔE76.

    Args:
        pred: ``(N, 3)`` (or any ``(..., 3)``) linear RGB, tensor or array.
        target: linear RGB of the same shape.
        mask: optional bool ``(...)`` (``pred.shape[:-1]``) selecting the colours to include; default all.

    Returns:
        ``{"dE00_mean": float, "dE00_p95": float, "dE76_mean": float}`` (p95: linear interpolation,
        ``numpy.percentile``).

    Raises:
        TypeError, ValueError: bad types or shapes, non-finite colours, an empty selection.

    Example:
        >>> x = np.random.default_rng(0).random((100, 3))
        >>> color_report(x, x)
        {'dE00_mean': 0.0, 'dE00_p95': 0.0, 'dE76_mean': 0.0}
    """
    a, b = _pair(pred, target)
    if mask is not None:
        keep = mask.detach().cpu().numpy() if isinstance(mask, torch.Tensor) else np.asarray(mask)
        if keep.dtype != np.bool_:
            raise TypeError(f"mask must be bool, got {keep.dtype}")
        if keep.shape != a.shape[:-1]:
            raise ValueError(f"mask must have shape {a.shape[:-1]} (the colours' shape without the channel), "
                             f"got {keep.shape}")
        a, b = a[keep], b[keep]
    if a.size == 0:
        raise ValueError("no colours to report (empty input or all-False mask)")
    lab_a, lab_b = _lab(a.reshape(-1, 3)), _lab(b.reshape(-1, 3))
    de00 = delta_e_2000_lab(lab_a, lab_b)
    de76 = np.linalg.norm(lab_a - lab_b, axis=-1)
    return {"dE00_mean": float(de00.mean()), "dE00_p95": float(np.percentile(de00, 95)),
            "dE76_mean": float(de76.mean())}


def ssim_2d(pred, target, window_size=11):
    """Mean SSIM (kornia, Gaussian window) of two linear-RGB images (H, W, 3), compared in sRGB encoding.

    Args:
        pred, target: (H, W, 3) linear RGB (numpy or torch), values clipped to [0, 1].
        window_size: odd Gaussian window size in pixels.

    Returns:
        float in [−1, 1] (1 for identical images).
    """
    import kornia

    from .color import linear_to_srgb

    def prep(name, x):
        x = torch.as_tensor(np.asarray(x) if not isinstance(x, torch.Tensor) else x).detach().double()
        if x.dim() != 3 or x.shape[-1] != 3:
            raise ValueError(f"{name}: expected an (H, W, 3) image, got shape {tuple(x.shape)}")
        return linear_to_srgb(x.clamp(0, 1)).permute(2, 0, 1).unsqueeze(0)

    a, b = prep("pred", pred), prep("target", target)
    if a.shape != b.shape:
        raise ValueError(f"target: expected shape {tuple(pred.shape)} (that of pred), got {tuple(target.shape)}")
    return float(kornia.metrics.ssim(a, b, window_size).mean())
