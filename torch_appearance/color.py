"""Colour-space conversions: linear RGB <-> sRGB and linear RGB <-> CIELAB (D65).

Inside torch_appearance colours are *linear* RGB (sRGB primaries, D65 white); the sRGB transfer function is
applied only at image I/O, and CIELAB is used by appearance losses and error reports.

The numerical work is done by :mod:`kornia.color`; this module adapts it to the layouts used here:

* :func:`linear_to_srgb` / :func:`srgb_to_linear` are elementwise, so they take a tensor of *any* shape
  (``(H, W, 3)`` renders, ``(N, 3)`` texel sets, ``(B, 3, H, W)`` batches alike).
* :func:`rgb_to_lab` / :func:`lab_to_rgb` take the colour channel at ``dim`` (default ``-1``, channels last,
  which is what :func:`torch_appearance.render_texels` returns; pass ``dim=-3`` for kornia's
  ``(*, 3, H, W)``), and take or return **linear** RGB, unlike kornia's functions of the same names,
  which take or return non-linear sRGB.

All functions are differentiable and keep dtype and device.
"""
import numpy as np
import torch
from kornia.color import lab_to_rgb as _kornia_lab_to_rgb
from kornia.color import linear_rgb_to_rgb as _kornia_linear_rgb_to_rgb
from kornia.color import rgb_to_lab as _kornia_rgb_to_lab
from kornia.color import rgb_to_linear_rgb as _kornia_rgb_to_linear_rgb

from .checks import check_tensor, describe

__all__ = ["linear_to_srgb", "linear_to_srgb8", "srgb_to_linear", "rgb_to_lab", "lab_to_rgb"]


def _channel_dim(name, image, dim):
    """Normalise ``dim`` and check that ``image`` has 3 channels there."""
    if isinstance(dim, bool) or not isinstance(dim, int):
        raise TypeError(f"dim: expected an int, got {describe(dim)}")
    if image.dim() == 0 or not -image.dim() <= dim < image.dim():
        raise ValueError(f"dim: expected an axis of {name} of shape {tuple(image.shape)}, got {dim} (out of range)")
    dim = dim % image.dim()
    if image.shape[dim] != 3:
        raise ValueError(
            f"{name}: expected 3 colour channels at dim={dim}, got shape {tuple(image.shape)} "
            f"(pass dim=-3 for (*, 3, H, W) images, dim=-1 for (..., 3))"
        )
    return dim


def _apply_channels(fn, image, dim):
    """Apply a kornia ``(*, 3, H, W)`` function to ``image`` whose 3 channels lie at ``dim``."""
    moved = image.movedim(dim, 0)  # (3, *rest)
    rest = moved.shape[1:]
    out = fn(moved.reshape(3, -1, 1))  # (3, N, 1): kornia's (*, 3, H, W) with H = N, W = 1
    return out.reshape(3, *rest).movedim(0, dim)


def _apply_elementwise(fn, image):
    """Apply a channel-independent kornia ``(*, 3, H, W)`` function to a tensor of any shape."""
    if image.numel() % 3 == 0:
        return fn(image.reshape(3, -1, 1)).reshape(image.shape)
    # Shapes whose size is not a multiple of 3 (a single value, ...): feed a 3-channel view, keep one channel.
    return fn(image.reshape(1, -1, 1).expand(3, -1, 1))[0].reshape(image.shape)


def linear_to_srgb(image):
    """Encode linear RGB with the sRGB transfer function (IEC 61966-2-1), elementwise.

    ``12.92 x`` for ``x <= 0.0031308``, else ``1.055 x^(1/2.4) - 0.055``
    (:func:`kornia.color.linear_rgb_to_rgb`). Nothing is clamped: values above 1 follow the power branch,
    negative values the linear branch; clip before quantising.

    Args:
        image: linear RGB values, any shape ``(*)`` (for example ``(H, W, 3)`` or ``(B, 3, H, W)``),
            floating point.

    Returns:
        sRGB-encoded values, shape ``(*)``, same dtype and device.

    Example:
        >>> linear_to_srgb(torch.tensor([0.0, 0.0031308, 0.5, 1.0], dtype=torch.float64))
        tensor([0.0000, 0.0404, 0.7354, 1.0000], dtype=torch.float64)
    """
    check_tensor("image", image, "(..., 3) or (*, 3, H, W)", dtypes="floating")
    return _apply_elementwise(_kornia_linear_rgb_to_rgb, image)


def linear_to_srgb8(linear):
    """Linear RGB (array or tensor, any shape) clipped to [0, 1], sRGB-encoded and rounded to ``uint8`` bytes: the
    display colour of a rendered texel (point clouds, mesh colours, figures).

    >>> linear_to_srgb8([0.0, 0.2159, 1.5, -0.2]).tolist()
    [0, 128, 255, 0]
    """
    x = torch.as_tensor(np.clip(np.asarray(linear, dtype=np.float64), 0.0, 1.0))
    return np.round(linear_to_srgb(x).numpy() * 255).astype(np.uint8)


def srgb_to_linear(image):
    """Decode sRGB to linear RGB (inverse of :func:`linear_to_srgb`), elementwise.

    ``x / 12.92`` for ``x <= 0.04045``, else ``((x + 0.055) / 1.055)^2.4``
    (:func:`kornia.color.rgb_to_linear_rgb`).

    Args:
        image: sRGB-encoded values, any shape ``(*)``, floating point (8-bit images: divide by 255 first).

    Returns:
        linear RGB values, shape ``(*)``, same dtype and device.

    Example:
        >>> srgb_to_linear(torch.tensor([0.04045, 1.0], dtype=torch.float64))
        tensor([0.0031, 1.0000], dtype=torch.float64)
    """
    check_tensor("image", image, "(..., 3) or (*, 3, H, W)", dtypes="floating")
    return _apply_elementwise(_kornia_rgb_to_linear_rgb, image)


def rgb_to_lab(image, *, dim=-1):
    """Convert **linear** RGB to CIE 1976 L*a*b* (D65 white, 2° observer).

    :func:`kornia.color.rgb_to_lab` expects *non-linear sRGB*: it first decodes with
    :func:`kornia.color.rgb_to_linear_rgb`, then applies the sRGB→XYZ matrix (D65), divides by the white
    point ``(0.95047, 1.0, 1.08883)`` and applies the L*a*b* compression (cube root above 0.008856, else
    ``7.787 t + 4/29``). This wrapper encodes the linear input with :func:`linear_to_srgb` first, so the
    two transfer steps cancel (up to floating-point rounding) and the result is the L*a*b* of the given
    linear colour. Values outside ``[0, 1]`` are not clamped. L* is 100 for linear white ``(1, 1, 1)``.

    Args:
        image: linear RGB, shape ``(..., 3)`` with the channels at ``dim`` (default ``-1``; use ``dim=-3`` for
            ``(*, 3, H, W)``), floating point.
        dim: index of the colour-channel dimension.

    Returns:
        L*a*b* with the same shape as ``image`` (channels L*, a*, b* at ``dim``).

    Example:
        >>> rgb_to_lab(torch.tensor([[1.0, 1.0, 1.0], [0.18, 0.18, 0.18]], dtype=torch.float64)).round(decimals=1)
        tensor([[100.0000,  -0.0000,   0.0000],
                [ 49.5000,  -0.0000,   0.0000]], dtype=torch.float64)
    """
    check_tensor("image", image, "(..., 3) or (*, 3, H, W)", dtypes="floating")
    dim = _channel_dim("image", image, dim)
    return _apply_channels(lambda x: _kornia_rgb_to_lab(_kornia_linear_rgb_to_rgb(x)), image, dim)


def lab_to_rgb(image, *, dim=-1, clip=False):
    """Convert CIE 1976 L*a*b* (D65 white, 2° observer) to **linear** RGB.

    Calls :func:`kornia.color.lab_to_rgb` with ``clip=False`` (which returns non-linear sRGB; note that
    kornia clamps the intermediate ``f_z`` at 0 for colours with negative Z) and decodes the result with
    :func:`srgb_to_linear`. Out-of-gamut colours give linear values outside ``[0, 1]`` unless ``clip``.

    Args:
        image: L*a*b*, shape ``(..., 3)`` with the channels at ``dim`` (default ``-1``; ``-3`` for
            ``(*, 3, H, W)``), floating point.
        dim: index of the colour-channel dimension.
        clip: clamp the linear RGB result to ``[0, 1]``.

    Returns:
        linear RGB with the same shape as ``image``.

    Example:
        >>> lab_to_rgb(torch.tensor([100.0, 0.0, 0.0], dtype=torch.float64)).round(decimals=3)
        tensor([1., 1., 1.], dtype=torch.float64)
    """
    check_tensor("image", image, "(..., 3) or (*, 3, H, W)", dtypes="floating")
    dim = _channel_dim("image", image, dim)
    if not isinstance(clip, bool):
        raise TypeError(f"clip: expected a bool, got {describe(clip)}")
    rgb = _apply_channels(lambda x: _kornia_rgb_to_linear_rgb(_kornia_lab_to_rgb(x, clip=False)), image, dim)
    return rgb.clamp(0.0, 1.0) if clip else rgb
