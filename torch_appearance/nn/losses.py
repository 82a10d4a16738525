"""Appearance losses on texels placed in a voxel grid (Nindel et al. 2021, eqs. 11–18).

The print optimiser compares rendered texel colours ``C`` with target colours ``T``. Texels are surface voxels, so
both are stored on the voxel grid, ``(3, D, H, W)`` (or batched ``(B, 3, D, H, W)``), in **linear** RGB, with a
``mask`` saying which grid cells are texels. Values outside the mask are ignored: they are replaced by 0 before any
arithmetic, so they may be anything (also NaN) and receive zero gradient.

* :func:`color_loss` / :class:`ColorLoss` — E1 (eq. 11): mean over texels of the squared CIELAB difference
  (ΔE76²), in raw L*a*b* units.
* :func:`ssim_loss_3d` / :class:`SSIMLoss3D` — E2 (eqs. 12–16): ``1 − mean SSIM`` over texels and the three
  normalised L*a*b* channels, with a 3D Gaussian window; :func:`masked_ssim3d` gives the SSIM map itself.
* :func:`edge_loss_3d` / :class:`EdgeLoss3D` — E3 (eq. 17): squared differences of 3D Sobel responses on
  normalised L*a*b*.
* :func:`appearance_loss` / :class:`AppearanceLoss` — E (eq. 18): ``Σ γ_k E_k / Σ γ_k``.
* :meth:`AppearanceLoss.forward_texels` / :meth:`AppearanceLoss.forward_parts_texels` — the same E1, E2, E3 on
  ``(N, 3)`` texel colours and ``(N, 3)`` voxel positions, without a grid, by the sparse texel path of
  :mod:`.texel_losses` (:func:`~torch_appearance.nn.texel_losses.texel_appearance_loss`,
  :class:`~torch_appearance.nn.texel_losses.TexelFilters`; also read from this module): the Gaussian and Sobel
  filters are sparse texel-to-texel CSR matrices (built once per set of positions), so an object's loss costs its
  texels and their neighbours, not its bounding box (objects in the print pipeline use it).

Conventions shared by all losses:

* **L*a*b*** is :func:`torch_appearance.color.rgb_to_lab` (kornia's CIELAB, D65). E2 and E3 use it normalised to
  ``[0, 1]`` over the CIELAB box: ``(L*/100, (a* + 128)/255, (b* + 128)/255)``; the paper normalises to
  ``[0, 1]`` without giving the map, and the ``±128`` box is the usual 8-bit Lab encoding.
* **Mask-normalised neighbourhoods**: the local means of eqs. 12–14 are ``G∗(m·x) / G∗m`` (normalised
  convolution), so the statistics of a texel use its neighbouring texels only, weighted by the Gaussian window
  renormalised over them; empty voxels and the grid border add no bias. A one-layer texel sheet therefore gets 2D
  SSIM over the sheet, and a volume full of texels gets kornia's dense ``ssim3d`` away from the border.
* **Edges**: the Sobel responses are taken of the masked difference ``m·(C − T)``. Because the Sobel operator is
  linear, ``S∗C − S∗T = S∗(C − T)`` for any fill of the non-texel voxels that ``C`` and ``T`` share, so this is
  exactly eq. 17 on a grid whose empty voxels hold the same (arbitrary) value in both; a texel next to empty
  voxels sees zero *difference* there (not zero colour).
* **Averages** run over all texels of all batch items (``I`` = number of texels in the batch).
* **Speed**: the grid is first reduced to the occupied indices along each axis (a one-layer slab face costs one
  layer, not D), and the separable Gaussian and Sobel filters are applied as small dense matrices along each axis
  (BLAS matmuls), built from the grid positions so that skipped layers stay skipped. This is exact (empty voxels
  are zeros of the convolution) and several times faster than ``kornia.filters.filter3d`` on CPU.

All functions are differentiable in ``pred`` (and ``target``) and take float32 or float64 on any device (the code is
device-agnostic; the tests run on CPU). The filters are matmuls, not cuDNN convolutions, so float32 CUDA results do
not depend on ``torch.backends.cudnn.allow_tf32`` (which degrades kornia's ``ssim3d`` variances); they follow
``torch.backends.cuda.matmul.allow_tf32`` (off by default).
"""
import math
from collections import namedtuple

import torch
from kornia.filters import get_gaussian_kernel1d
from kornia.filters.kernels import get_sobel_kernel_3x3

from ..checks import check_odd_int, check_positive, check_tensor, describe, is_real
from ..color import rgb_to_lab

__all__ = [
    "color_loss",
    "ColorLoss",
    "masked_ssim3d",
    "ssim_loss_3d",
    "SSIMLoss3D",
    "sobel_kernels_3d",
    "edge_loss_3d",
    "EdgeLoss3D",
    "appearance_loss",
    "AppearanceLoss",
]

#: the sparse texel path lives in :mod:`.texel_losses` (it builds on this module's checks and constants); its names
#: are still read from here (``from torch_appearance.nn.losses import TexelFilters``)
_TEXEL_PATH = ("TexelFilters", "texel_appearance_loss")

#: Normalisation of L*a*b* to [0, 1] used by E2 and E3: ``lab * LAB_SCALE + LAB_OFFSET``.
LAB_SCALE = (1.0 / 100.0, 1.0 / 255.0, 1.0 / 255.0)
LAB_OFFSET = (0.0, 128.0 / 255.0, 128.0 / 255.0)

#: SSIM stabilising constants of eq. 15 (for signals in [0, 1]).
SSIM_C1 = 0.01**2
SSIM_C2 = 0.03**2

#: Normalisation of eq. 17: 3 axes, 1/4 for the squared range, 1/32 for the Sobel range, times 100.
_EDGE_FACTOR = 100.0 / (3.0 * 4.0 * 32.0)

_FLOAT_DTYPES = (torch.float32, torch.float64)

# A texel volume reduced to the occupied indices along each axis.
#   pred, target: (B, 3, d, h, w) linear RGB, zero outside the mask;  mask: (Bm, 1, d, h, w) in {0, 1}, Bm ∈ {1, B};
#   positions: grid indices (z, y, x) of the kept layers/rows/columns;  count: number of texels in the batch.
_Texels = namedtuple("_Texels", "pred target mask positions count")


# ------------------------------------------------------------------------------------------------------------------
# validation and preparation
# ------------------------------------------------------------------------------------------------------------------
def _check_volume(name, x, channels=3):
    want = f"{channels}" if channels is not None else "C"
    shape_desc = f"({want}, D, H, W) or (B, {want}, D, H, W)"
    check_tensor(name, x, shape_desc, ndim=(4, 5), dtypes=_FLOAT_DTYPES)
    if channels is not None and x.shape[-4] != channels:
        raise ValueError(f"{name}: expected shape {shape_desc}, got {tuple(x.shape)}")
    if x.dim() == 5 and x.shape[0] == 0:
        raise ValueError(f"{name}: expected a batch of B >= 1, got shape {tuple(x.shape)}")


def _check_like(names, pred, target):
    """``target`` has the shape, dtype and device of ``pred`` (the loss pair's semantics)."""
    if pred.shape != target.shape:
        raise ValueError(f"{names[1]}: expected the shape of {names[0]} {tuple(pred.shape)}, "
                         f"got {tuple(target.shape)}")
    if pred.dtype != target.dtype:
        raise TypeError(f"{names[1]}: expected the dtype of {names[0]} ({pred.dtype}), got {target.dtype}")
    if pred.device != target.device:
        raise ValueError(f"{names[1]}: expected the device of {names[0]} ({pred.device}), got {target.device}")


def _check_pair(pred, target, channels=3, names=("pred", "target")):
    _check_volume(names[0], pred, channels)
    _check_volume(names[1], target, channels)
    _check_like(names, pred, target)


def _check_mask(mask, like):
    """Validate ``mask`` against the volume ``like`` (4D or 5D); return it as bool ``(Bm, 1, D, H, W)``."""
    check_tensor("mask", mask, "(D, H, W) or (B, 1, D, H, W)")
    if mask.dtype.is_complex:
        raise TypeError(f"mask: expected bool or real values in {{0, 1}}, got {mask.dtype}")
    spatial = tuple(like.shape[-3:])
    batch = like.shape[0] if like.dim() == 5 else 1
    if mask.dim() == 3 and tuple(mask.shape) == spatial:
        mask = mask[None, None]
    elif like.dim() == 5 and mask.dim() == 5 and tuple(mask.shape[2:]) == spatial and mask.shape[1] == 1 \
            and mask.shape[0] in (1, batch):
        pass
    else:
        allowed = f"{spatial}" + (f" or {(batch, 1) + spatial}" if like.dim() == 5 else "")
        raise ValueError(f"mask: expected shape {allowed} to match the colours of shape {tuple(like.shape)}, "
                         f"got {tuple(mask.shape)}")
    if mask.device != like.device:
        raise ValueError(f"mask: expected the colours' device {like.device}, got {mask.device}")
    if mask.dtype != torch.bool:
        if not bool(((mask == 0) | (mask == 1)).all()):
            raise ValueError("mask: expected only 0 and 1 (or bool), got other values")
        mask = mask != 0
    if not bool(mask.any()):
        raise ValueError(f"mask: expected at least one texel (the loss is undefined without), got all False in "
                         f"shape {tuple(mask.shape)}")
    return mask


def _occupied(mask):
    """Indices along D, H, W of the layers/rows/columns holding at least one texel (``None`` where all do)."""
    positions, index = [], []
    for axis in (2, 3, 4):
        others = tuple(a for a in range(5) if a != axis)
        idx = mask.any(dim=others).nonzero().flatten()
        full = idx.numel() == mask.shape[axis]
        index.append(None if full else idx)
        positions.append(idx)
    return positions, index


def _compact(x, index):
    for axis, idx in zip((2, 3, 4), index):
        if idx is not None:
            x = x.index_select(axis, idx)
    return x


def _sanitize(name, x, mask):
    """Zero ``x`` outside ``mask`` (so garbage there cannot leak, not even NaN) and refuse non-finite texels."""
    x = torch.where(mask, x, x.new_zeros(()))
    bad = ~torch.isfinite(x.detach())
    if bool(bad.any()):
        raise ValueError(f"{name}: expected finite values where mask is True, got {int(bad.sum())} NaN/Inf entries")
    return x


def _prepare(pred, target, mask):
    """Validate, reduce to the occupied part of the grid, and zero everything outside the mask."""
    _check_pair(pred, target)
    mask = _check_mask(mask, pred)
    if pred.dim() == 4:
        pred, target = pred[None], target[None]
    positions, index = _occupied(mask)
    pred, target, mask = _compact(pred, index), _compact(target, index), _compact(mask, index)
    pred, target = _sanitize("pred", pred, mask), _sanitize("target", target, mask)
    count = int(mask.sum()) * (pred.shape[0] // mask.shape[0])
    return _Texels(pred, target, mask, positions, count)


def _normalize_lab(lab):
    """``(B, 3, ...)`` raw L*a*b* → the ``[0, 1]`` normalisation of E2/E3 (see :data:`LAB_SCALE`)."""
    shape = (1, 3) + (1,) * (lab.dim() - 2)
    scale = torch.tensor(LAB_SCALE, dtype=lab.dtype, device=lab.device).view(shape)
    offset = torch.tensor(LAB_OFFSET, dtype=lab.dtype, device=lab.device).view(shape)
    return lab * scale + offset


def _check_window(window_size, sigma):
    check_odd_int("window_size", window_size)
    check_positive("sigma", sigma)


# ------------------------------------------------------------------------------------------------------------------
# separable filtering on (possibly gappy) grids
# ------------------------------------------------------------------------------------------------------------------
def _toeplitz(taps, positions):
    """Correlation with ``taps`` (odd length, centred) along an axis sampled at ``positions``, as a matrix.

    ``out[i] = Σ_j taps[r + p_j − p_i] · in[j]`` with zero padding; ``(n, n)`` for ``n`` positions.
    """
    r = taps.numel() // 2
    offset = positions[None, :] - positions[:, None]
    inside = offset.abs() <= r
    return torch.where(inside, taps[(offset + r).clamp(0, 2 * r)], taps.new_zeros(()))


def _along(x, matrix, axis):
    """Apply ``matrix`` (n, n) along ``axis`` (2, 3 or 4) of a 5D tensor."""
    if axis == 4:
        return x @ matrix.T
    if axis == 3:
        return matrix @ x
    b, c, d, h, w = x.shape
    return (matrix @ x.reshape(b, c, d, h * w)).view(b, c, d, h, w)


def _gaussian_filter(x, matrices):
    for axis, matrix in zip((4, 3, 2), matrices[::-1]):
        x = _along(x, matrix, axis)
    return x


def _gaussian_matrices(positions, window_size, sigma, dtype, device):
    taps = get_gaussian_kernel1d(window_size, sigma, device=device, dtype=dtype).reshape(-1)
    return [_toeplitz(taps, p.to(device)) for p in positions]


def _sobel_taps(dtype, device):
    """``(h, d)``: kornia's Sobel smoothing ``[1, 2, 1]`` and derivative ``[−1, 0, 1]`` taps."""
    sobel = get_sobel_kernel_3x3(device=device, dtype=dtype)  # [[-1, 0, 1], [-2, 0, 2], [-1, 0, 1]]
    return sobel[:, 2], sobel[1] / 2


def sobel_kernels_3d(*, dtype=torch.float32, device=None):
    """The three 3D Sobel kernels of eq. 17, unnormalised, as used by :func:`edge_loss_3d`.

    ``S_x[z, y, x] = h[z] h[y] d[x]`` (likewise ``S_y``, ``S_z``) with ``h = [1, 2, 1]`` and ``d = [−1, 0, 1]``:
    kornia's 2D Sobel kernel (:func:`kornia.filters.get_sobel_kernel_3x3`, unnormalised) extended by the
    ``[1, 2, 1]`` smoothing along the third axis. Kornia has no 3D Sobel (``spatial_gradient3d`` implements only
    ``mode='diff'``, a central difference ``(x[i+1] − x[i−1]) / 2`` whose taps sum to 1 in absolute value). Each
    kernel's positive taps sum to 16 and its absolute taps to 32, so for colours in ``[0, 1]``
    ``S∗C − S∗T = S∗(C − T)`` lies in ``[−32, 32]``: the paper's range.

    Args:
        dtype: floating dtype of the result.
        device: device of the result.

    Returns:
        ``(3, 3, 3, 3)``: ``[S_x, S_y, S_z]``, each indexed ``[z, y, x]`` (cross-correlation taps, offset −1, 0, 1).

    Example:
        >>> k = sobel_kernels_3d()
        >>> k.shape, float(k[0].abs().sum()), float(k[0].clamp(min=0).sum())
        (torch.Size([3, 3, 3, 3]), 32.0, 16.0)
    """
    h, d = _sobel_taps(dtype, device)
    return torch.stack([
        torch.einsum("z,y,x->zyx", h, h, d),
        torch.einsum("z,y,x->zyx", h, d, h),
        torch.einsum("z,y,x->zyx", d, h, h),
    ])


# ------------------------------------------------------------------------------------------------------------------
# the three terms on prepared (compact, masked) data
# ------------------------------------------------------------------------------------------------------------------
def _color_term(lab_pred, lab_target, mask, count):
    sq = (lab_pred - lab_target).square().sum(dim=1, keepdim=True)  # (B, 1, d, h, w)
    return (sq * mask).sum() / count


def _ssim_map(x, y, mask, matrices, c1, c2):
    """Mask-normalised SSIM map ``(B, C, d, h, w)`` (finite everywhere; meaningful where ``mask``)."""
    m = mask.to(x.dtype)
    n = x.shape[1]
    mx, my = m * x, m * y
    weight = _gaussian_filter(m, matrices)  # (Bm, 1, ...): Σ of window weights over texels
    inv = 1.0 / torch.where(mask, weight, weight.new_ones(()))
    moments_x = _gaussian_filter(torch.cat([mx, mx * x, mx * y], dim=1), matrices) * inv
    moments_y = _gaussian_filter(torch.cat([my, my * y], dim=1), matrices) * inv
    mu_x, e_xx, e_xy = moments_x.split(n, dim=1)
    mu_y, e_yy = moments_y.split(n, dim=1)
    mu_xy = mu_x * mu_y
    var_x, var_y, cov = e_xx - mu_x.square(), e_yy - mu_y.square(), e_xy - mu_xy
    luminance = (2.0 * mu_xy + c1) / (mu_x.square() + mu_y.square() + c1)
    structure = (2.0 * cov + c2) / (var_x + var_y + c2)
    return luminance * structure


def _ssim_term(norm_pred, norm_target, texels, window_size, sigma):
    matrices = _gaussian_matrices(texels.positions, window_size, sigma, norm_pred.dtype, norm_pred.device)
    ssim = _ssim_map(norm_pred, norm_target, texels.mask, matrices, SSIM_C1, SSIM_C2)
    return 1.0 - (ssim * texels.mask).sum() / (3 * texels.count)


def _edge_term(norm_pred, norm_target, texels):
    mask = texels.mask
    diff = (norm_pred - norm_target) * mask
    h, d = _sobel_taps(diff.dtype, diff.device)
    hz, hy, hx = (_toeplitz(h, p.to(diff.device)) for p in texels.positions)
    dz, dy, dx = (_toeplitz(d, p.to(diff.device)) for p in texels.positions)
    smooth_z = _along(diff, hz, 2)
    s_x = _along(_along(smooth_z, hy, 3), dx, 4)
    s_y = _along(_along(smooth_z, hx, 4), dy, 3)
    s_z = _along(_along(_along(diff, hy, 3), hx, 4), dz, 2)
    total = sum(((s * mask).square()).sum() for s in (s_x, s_y, s_z))
    return _EDGE_FACTOR * total / texels.count


def _lab_pair(texels):
    return rgb_to_lab(texels.pred, dim=1), rgb_to_lab(texels.target, dim=1)


# ------------------------------------------------------------------------------------------------------------------
# E1
# ------------------------------------------------------------------------------------------------------------------
def color_loss(pred, target, mask):
    r"""E1 (eq. 11): mean over texels of the squared CIELAB difference, :math:`\frac1I\sum_i \Delta E_{76,i}^2`.

    Args:
        pred: ``(3, D, H, W)`` or ``(B, 3, D, H, W)`` linear RGB on the voxel grid, float32/float64.
        target: linear RGB of the same shape, dtype and device.
        mask: ``(D, H, W)`` (or ``(B, 1, D, H, W)`` / ``(1, 1, D, H, W)`` for batched colours), bool or {0, 1}:
            the texels. Values of ``pred``/``target`` outside it are ignored.

    Returns:
        scalar tensor, in raw L*a*b* units squared (L* ∈ [0, 100]).

    Raises:
        TypeError, ValueError: wrong type, dtype, shape or device; an empty mask; non-finite values at texels.

    Example:
        >>> pred, target = torch.rand(3, 2, 4, 4), torch.rand(3, 2, 4, 4)
        >>> mask = torch.zeros(2, 4, 4, dtype=torch.bool); mask[-1] = True
        >>> color_loss(pred, target, mask).shape
        torch.Size([])
    """
    texels = _prepare(pred, target, mask)
    lab_pred, lab_target = _lab_pair(texels)
    return _color_term(lab_pred, lab_target, texels.mask, texels.count)


class ColorLoss(torch.nn.Module):
    """Module form of :func:`color_loss` (E1, eq. 11).

    Example:
        >>> ColorLoss()(torch.rand(3, 1, 4, 4), torch.rand(3, 1, 4, 4), torch.ones(1, 4, 4, dtype=torch.bool)).shape
        torch.Size([])
    """

    def forward(self, pred, target, mask):
        """See :func:`color_loss`."""
        return color_loss(pred, target, mask)


# ------------------------------------------------------------------------------------------------------------------
# E2
# ------------------------------------------------------------------------------------------------------------------
def masked_ssim3d(img1, img2, mask, window_size=11, sigma=1.5, c1=SSIM_C1, c2=SSIM_C2):
    r"""Mask-normalised 3D SSIM map (eqs. 12–15) of arbitrary channels, zero outside the mask.

    Local statistics use a separable Gaussian window ``G`` (``window_size`` taps per axis, std ``sigma``, from
    :func:`kornia.filters.get_gaussian_kernel1d`), normalised over the texels: :math:`\bar c = G∗(m c) / G∗m`,
    :math:`\sigma_c^2 = G∗(m c^2)/G∗m - \bar c^2`, :math:`\sigma_{ct} = G∗(m c t)/G∗m - \bar c \bar t`, and

    .. math:: SSIM = \frac{2\bar c\bar t + c_1}{\bar c^2 + \bar t^2 + c_1}
                     \cdot \frac{2\sigma_{ct} + c_2}{\sigma_c^2 + \sigma_t^2 + c_2}.

    With a full mask this is :func:`kornia.metrics.ssim3d` (``sigma=1.5``, ``max_val=1``) wherever the window lies
    inside the grid; at the border the window is renormalised instead of reflected.

    Args:
        img1: ``(C, D, H, W)`` or ``(B, C, D, H, W)``, float32/float64 (values meant to lie in ``[0, 1]`` for the
            default constants).
        img2: same shape, dtype and device.
        mask: ``(D, H, W)`` (or ``(B, 1, D, H, W)`` / ``(1, 1, D, H, W)``), bool or {0, 1}.
        window_size: odd number of Gaussian taps per axis.
        sigma: Gaussian standard deviation in voxels.
        c1, c2: stabilising constants (eq. 15: 0.01², 0.03²).

    Returns:
        the SSIM map, same shape as ``img1``, 0 outside the mask.

    Example:
        >>> x = torch.rand(3, 1, 16, 16)
        >>> ssim = masked_ssim3d(x, x, torch.ones(1, 16, 16, dtype=torch.bool))
        >>> bool(torch.allclose(ssim, torch.ones_like(ssim)))
        True
    """
    _check_pair(img1, img2, channels=None, names=("img1", "img2"))
    _check_window(window_size, sigma)
    for name, value in (("c1", c1), ("c2", c2)):
        if not is_real(value) or not (math.isfinite(value) and value > 0):
            raise ValueError(f"{name}: expected a finite number > 0, got {value!r}")
    mask = _check_mask(mask, img1)
    squeeze = img1.dim() == 4
    if squeeze:
        img1, img2 = img1[None], img2[None]
    positions, index = _occupied(mask)
    x, y, m = _compact(img1, index), _compact(img2, index), _compact(mask, index)
    x, y = _sanitize("img1", x, m), _sanitize("img2", y, m)
    matrices = _gaussian_matrices(positions, window_size, sigma, x.dtype, x.device)
    ssim = torch.where(m, _ssim_map(x, y, m, matrices, float(c1), float(c2)), x.new_zeros(()))
    if any(i is not None for i in index):
        full = ssim.new_zeros(ssim.shape[:2] + img1.shape[2:])
        z, yy, xx = positions
        full[:, :, z[:, None, None], yy[None, :, None], xx[None, None, :]] = ssim
        ssim = full
    return ssim[0] if squeeze else ssim


def ssim_loss_3d(pred, target, mask, window_size=11, sigma=1.5):
    r"""E2 (eqs. 12–16): ``1 − mean SSIM`` over texels and the normalised L*, a*, b* channels.

    The colours are converted to L*a*b* and normalised to ``[0, 1]`` (``L*/100``, ``(a*+128)/255``,
    ``(b*+128)/255``); SSIM is :func:`masked_ssim3d` with ``c1 = 0.01²``, ``c2 = 0.03²``. The result is 0 for
    identical colours and lies in ``(0, 2]`` otherwise.

    Args:
        pred, target, mask: as in :func:`color_loss`.
        window_size: odd number of Gaussian taps per axis (default 11).
        sigma: Gaussian standard deviation in voxels (default 1.5).

    Returns:
        scalar tensor.

    Example:
        >>> x = torch.rand(3, 2, 8, 8)
        >>> float(ssim_loss_3d(x, x, torch.ones(2, 8, 8, dtype=torch.bool)))
        0.0
    """
    _check_window(window_size, sigma)
    texels = _prepare(pred, target, mask)
    lab_pred, lab_target = _lab_pair(texels)
    return _ssim_term(_normalize_lab(lab_pred), _normalize_lab(lab_target), texels, window_size, sigma)


class SSIMLoss3D(torch.nn.Module):
    """Module form of :func:`ssim_loss_3d` (E2).

    Args:
        window_size: odd number of Gaussian taps per axis.
        sigma: Gaussian standard deviation in voxels.
    """

    def __init__(self, window_size=11, sigma=1.5):
        super().__init__()
        _check_window(window_size, sigma)
        self.window_size, self.sigma = window_size, float(sigma)

    def forward(self, pred, target, mask):
        """See :func:`ssim_loss_3d`."""
        return ssim_loss_3d(pred, target, mask, self.window_size, self.sigma)

    def extra_repr(self):
        return f"window_size={self.window_size}, sigma={self.sigma}"


# ------------------------------------------------------------------------------------------------------------------
# E3
# ------------------------------------------------------------------------------------------------------------------
def edge_loss_3d(pred, target, mask):
    r"""E3 (eq. 17): 3D Sobel edge differences on normalised L*a*b*.

    .. math:: E_3 = 100 \cdot \frac13 \sum_{x,y,z} \sum_{L^*a^*b^*} \frac1I \frac14 \frac1{32}
                    \sum_{i=1}^{I} (S∗C - S∗T)_i^2

    with the unnormalised Sobel kernels of :func:`sobel_kernels_3d` (``|S∗C − S∗T| ≤ 32`` for colours in
    ``[0, 1]``), applied to ``m·(C − T)`` with zero padding and summed over texels (see the module notes). The
    constants are the paper's as printed: ``1/32`` is not squared, so one texel, channel and axis contributes at
    most ``32² / (4·32) = 8``, not 1. 0 for identical colours.

    Args:
        pred, target, mask: as in :func:`color_loss`.

    Returns:
        scalar tensor.

    Example:
        >>> x = torch.rand(3, 2, 8, 8)
        >>> float(edge_loss_3d(x, x, torch.ones(2, 8, 8, dtype=torch.bool)))
        0.0
    """
    texels = _prepare(pred, target, mask)
    lab_pred, lab_target = _lab_pair(texels)
    return _edge_term(_normalize_lab(lab_pred), _normalize_lab(lab_target), texels)


class EdgeLoss3D(torch.nn.Module):
    """Module form of :func:`edge_loss_3d` (E3)."""

    def forward(self, pred, target, mask):
        """See :func:`edge_loss_3d`."""
        return edge_loss_3d(pred, target, mask)


# ------------------------------------------------------------------------------------------------------------------
# E
# ------------------------------------------------------------------------------------------------------------------
def _check_gamma(gamma):
    try:
        values = tuple(float(g) for g in gamma)
    except TypeError:
        raise TypeError(f"gamma: expected a sequence of 3 numbers, got {describe(gamma)}") from None
    if len(values) != 3:
        raise ValueError(f"gamma: expected 3 weights (γ1, γ2, γ3), got {len(values)}")
    if not all(math.isfinite(g) and g >= 0 for g in values) or sum(values) <= 0:
        raise ValueError(f"gamma: expected finite weights >= 0, not all 0, got {values}")
    return values


def _combine_terms(gamma, terms, return_parts):
    """E = Σ γ_k E_k / Σ γ (eq. 18) from lazily evaluated terms (E1, E2, E3); a term with weight 0 is skipped, or
    evaluated without gradient when ``return_parts`` asks for it."""
    parts, total = {}, 0.0
    for name, weight, term in zip(("E1", "E2", "E3"), gamma, terms):
        if weight > 0:
            value = term()
            total = total + weight * value
        elif return_parts:
            with torch.no_grad():
                value = term()
        else:
            continue
        parts[name] = value
    total = total / sum(gamma)
    return (total, parts) if return_parts else total


def appearance_loss(pred, target, mask, gamma=(1.0, 3.0, 1.0), window_size=11, sigma=1.5, return_parts=False):
    r"""E (eq. 18): :math:`E = \sum_k \gamma_k E_k / \sum_k \gamma_k` of E1 (colour), E2 (SSIM), E3 (edges).

    The colours are validated and converted to L*a*b* once for all terms. A term whose weight is 0 is skipped,
    or, with ``return_parts``, evaluated without gradient for reporting only.

    Args:
        pred, target, mask: as in :func:`color_loss`.
        gamma: ``(γ1, γ2, γ3)``, finite, >= 0, not all 0. The paper recommends γ1 = 1, γ2 ∈ [3, 9], γ3 <= 3.
        window_size, sigma: the SSIM window (see :func:`ssim_loss_3d`).
        return_parts: also return ``{"E1": ..., "E2": ..., "E3": ...}`` (scalar tensors).

    Returns:
        the scalar total, or ``(total, parts)`` with ``return_parts``.

    Example:
        >>> x, t = torch.rand(3, 2, 8, 8), torch.rand(3, 2, 8, 8)
        >>> total, parts = appearance_loss(x, t, torch.ones(2, 8, 8, dtype=torch.bool), return_parts=True)
        >>> sorted(parts)
        ['E1', 'E2', 'E3']
    """
    gamma = _check_gamma(gamma)
    _check_window(window_size, sigma)
    texels = _prepare(pred, target, mask)
    lab_pred, lab_target = _lab_pair(texels)
    norm_pred, norm_target = _normalize_lab(lab_pred), _normalize_lab(lab_target)
    terms = (
        lambda: _color_term(lab_pred, lab_target, texels.mask, texels.count),
        lambda: _ssim_term(norm_pred, norm_target, texels, window_size, sigma),
        lambda: _edge_term(norm_pred, norm_target, texels),
    )
    return _combine_terms(gamma, terms, return_parts)


class AppearanceLoss(torch.nn.Module):
    """Module form of :func:`appearance_loss` (eq. 18); ``forward`` returns the total only.

    Args:
        gamma: ``(γ1, γ2, γ3)`` weights of E1 (ΔE76² colour), E2 (3D SSIM), E3 (3D Sobel edges).
        window_size, sigma: the SSIM window.

    Example:
        >>> loss = AppearanceLoss(gamma=(1.0, 3.0, 1.0))
        >>> x, t = torch.rand(3, 2, 8, 8), torch.rand(3, 2, 8, 8)
        >>> total, parts = loss.forward_parts(x, t, torch.ones(2, 8, 8, dtype=torch.bool))
    """

    def __init__(self, gamma=(1.0, 3.0, 1.0), window_size=11, sigma=1.5):
        super().__init__()
        self.gamma = _check_gamma(gamma)
        _check_window(window_size, sigma)
        self.window_size, self.sigma = window_size, float(sigma)

    def forward(self, pred, target, mask):
        """Total loss E (scalar tensor); arguments as in :func:`color_loss`."""
        return appearance_loss(pred, target, mask, self.gamma, self.window_size, self.sigma)

    def forward_parts(self, pred, target, mask):
        """``(total, {"E1": ..., "E2": ..., "E3": ...})``; parts with γ = 0 are computed without gradient."""
        return appearance_loss(pred, target, mask, self.gamma, self.window_size, self.sigma, return_parts=True)

    def texel_filters(self, positions):
        """The :class:`TexelFilters` of ``positions`` ``(N, 3)`` for this loss's window, cached: the last one is
        kept and reused while the positions are equal (one O(N) comparison per call)."""
        cached = getattr(self, "_texel_filters", None)
        if cached is None or not cached.matches(positions, self.window_size, self.sigma):
            from .texel_losses import TexelFilters
            cached = self._texel_filters = TexelFilters(positions, self.window_size, self.sigma)
        return cached

    def forward_texels(self, pred, target, positions):
        """Total loss E on per-texel colours ``(N, 3)`` at voxel ``positions`` ``(N, 3)`` (sparse path, see
        :func:`texel_appearance_loss`); equal to :meth:`forward` on the colours placed on the grid."""
        from .texel_losses import texel_appearance_loss
        return texel_appearance_loss(pred, target, self.texel_filters(positions), self.gamma)

    def forward_parts_texels(self, pred, target, positions):
        """``(total, {"E1", "E2", "E3"})`` of :meth:`forward_texels`; parts with γ = 0 without gradient."""
        from .texel_losses import texel_appearance_loss
        return texel_appearance_loss(pred, target, self.texel_filters(positions), self.gamma, return_parts=True)

    def extra_repr(self):
        return f"gamma={self.gamma}, window_size={self.window_size}, sigma={self.sigma}"


def __getattr__(name):
    """The sparse texel path's names, from :mod:`.texel_losses` (imported on first use: it imports this module)."""
    if name in _TEXEL_PATH:
        from . import texel_losses
        return getattr(texel_losses, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
