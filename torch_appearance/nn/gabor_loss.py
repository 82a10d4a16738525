"""Curved-Gabor phase loss between a rendered image and a target photo (thesis ch. 2, §3.6, on images).

The wood fit of the paper compares the model's analytic phase ``J_phi = 2 pi frac(G)`` with the curved-Gabor phase
``I_phi`` of the photo. :class:`GaborPhaseLoss` compares *images* instead: the rendered image and the target go
through the same curved Gabor filter (:class:`~torch_appearance.rings.gabor.CurvedGaborFilter`), whose geometry —
orientation field, normal sign and carrier frequency — is measured on the target once, in ``__init__``. With the
geometry fixed the filter is linear in the rendered image, so the loss is differentiable with respect to every
pixel and can drive any model that renders an image (a :class:`~torch_appearance.nn.WoodModel`, a texture, a
network) in an ordinary ``torch.optim`` loop.

Loss (per image, averaged over a batch)::

    d(x)  = arg(R_pred(x) * conj(R_target(x)))       in (-pi, pi]   (cyclic phase difference, rad)
    E     = sum_x w(x) e(d(x)) / sum_x w(x),   e(d) = d^2 ("squared", the paper's wrap(J - I)^2)
                                                or 2 (1 - cos d) ("cosine": smooth, = d^2 + O(d^4))
    w(x)  = min(|R_target(x)| / mean |R_target|, weight_cap) * mask(x)

The loss is cyclic: rings that are a whole ring off also agree, so it has local minima at whole-ring offsets and
a start should be within about half a ring of the target where the weight is (e.g. from
:func:`~torch_appearance.rings.estimate_board`). The amplitude weight trusts pixels where the target has clear
rings (as the wood-fit pipeline does). The phase of a
response is undefined where it vanishes; such pixels (``|R_pred| = 0`` exactly) contribute zero loss and gradient.
A note on piecewise-constant renders: autograd does not see pixels that jump across a ring boundary (the colour map
of :class:`~torch_appearance.nn.WoodModel` is discontinuous there), so the gradient of a render with respect to the
ring geometry holds only the smooth within-ring part; for the default colour map it keeps the sign but has about a
quarter of the size of the true phase derivative (the minimum stays where the phases agree).
"""
from __future__ import annotations

import math
import numbers

import numpy as np
import torch
from torch import nn

__all__ = ["gabor_phase_loss", "GaborPhaseLoss", "LUMA_709"]

#: Rec. 709 luminance weights used to turn linear RGB into grey.
LUMA_709 = (0.2126, 0.7152, 0.0722)
_MODES = ("squared", "cosine")


def _to_gray(image, name: str, *, batch: bool) -> torch.Tensor:
    """``(H, W)``, ``(C, H, W)`` or ``(B, C, H, W)`` (C = 1 or 3) -> ``(B, H, W)`` grey (RGB: Rec. 709 luminance)."""
    if isinstance(image, np.ndarray):
        if not np.issubdtype(image.dtype, np.floating):
            raise TypeError(f"{name}: expected a floating-point array, got dtype {image.dtype}")
        image = torch.from_numpy(np.ascontiguousarray(image))
    if not isinstance(image, torch.Tensor):
        raise TypeError(f"{name}: expected a torch.Tensor of shape (H, W), (C, H, W) or (B, C, H, W), "
                        f"got {type(image).__name__}")
    if not image.dtype.is_floating_point or image.is_complex():
        raise TypeError(f"{name}: expected a real floating-point tensor, got {image.dtype}")
    if image.ndim == 2:
        image = image[None, None]
    elif image.ndim == 3:
        image = image[None]
    elif image.ndim != 4:
        raise ValueError(f"{name}: expected shape (H, W), (C, H, W) or (B, C, H, W), got {tuple(image.shape)}")
    if image.shape[1] not in (1, 3):
        hint = " (channels-last? use image.permute(2, 0, 1))" if image.shape[-1] in (1, 3) else ""
        raise ValueError(f"{name}: expected 1 or 3 channels in dimension -3, got shape {tuple(image.shape)}{hint}")
    if not batch and image.shape[0] != 1:
        raise ValueError(f"{name}: expected a single image (batch 1), got batch {image.shape[0]}")
    if min(image.shape[-2:]) < 2:
        raise ValueError(f"{name}: expected at least 2 x 2 pixels, got shape {tuple(image.shape)}")
    if image.shape[1] == 3:
        luma = torch.tensor(LUMA_709, dtype=image.dtype, device=image.device)
        return torch.einsum("bchw,c->bhw", image, luma)
    return image[:, 0]


def gabor_phase_loss(response: torch.Tensor, target_response: torch.Tensor, weight: torch.Tensor | None = None,
                     mode: str = "squared") -> torch.Tensor:
    """Weighted cyclic phase difference of two complex Gabor responses.

    Args:
        response: complex ``(H, W)`` or ``(B, H, W)`` response of the prediction (differentiable).
        target_response: complex ``(H, W)`` response of the target (broadcast over the batch).
        weight: optional non-negative ``(H, W)`` weights; default uniform.
        mode: ``"squared"`` (``wrap(d)^2``, rad^2) or ``"cosine"`` (``2 (1 - cos d)``).

    Returns:
        scalar ``sum w e(d) / sum w``, averaged over the batch.

    Raises:
        TypeError: non-complex responses. ValueError: shapes that do not broadcast, unknown ``mode``, weights that
            are negative, non-finite or all zero.

    Example:
        >>> import torch
        >>> t = torch.polar(torch.ones(4, 4), torch.zeros(4, 4))
        >>> r = torch.polar(torch.full((4, 4), 2.0), torch.full((4, 4), 0.5))
        >>> round(float(gabor_phase_loss(r, t)), 4)
        0.25
    """
    for name, value in (("response", response), ("target_response", target_response)):
        if not isinstance(value, torch.Tensor) or not value.is_complex():
            raise TypeError(f"{name}: expected a complex torch.Tensor, got "
                            f"{type(value).__name__ if not isinstance(value, torch.Tensor) else value.dtype}")
    if mode not in _MODES:
        raise ValueError(f"mode: expected one of {_MODES}, got {mode!r}")
    if response.ndim not in (2, 3) or target_response.shape != response.shape[-2:]:
        raise ValueError(f"response / target_response: expected (B, H, W) or (H, W) and (H, W), got "
                         f"{tuple(response.shape)} and {tuple(target_response.shape)}")
    if weight is None:
        weight = torch.ones(response.shape[-2:], dtype=response.real.dtype, device=response.device)
    elif not isinstance(weight, torch.Tensor) or weight.shape != response.shape[-2:]:
        raise ValueError(f"weight: expected a tensor of shape {tuple(response.shape[-2:])}, got "
                         f"{tuple(weight.shape) if isinstance(weight, torch.Tensor) else type(weight).__name__}")
    if not bool(torch.isfinite(weight).all()) or bool((weight < 0).any()) or float(weight.sum()) <= 0:
        raise ValueError("weight: expected finite, non-negative weights with a positive sum")
    t = target_response.to(response.dtype)
    x = response.real * t.real + response.imag * t.imag  # R_pred * conj(R_target)
    y = response.imag * t.real - response.real * t.imag
    zero = (x * x + y * y) <= torch.finfo(x.dtype).tiny
    x = torch.where(zero, torch.ones_like(x), x)
    y = torch.where(zero, torch.zeros_like(y), y)
    if mode == "squared":
        e = torch.atan2(y, x) ** 2
    else:
        e = 2.0 * (1.0 - x / torch.sqrt(x * x + y * y))
    w = weight.to(e.dtype)
    per_image = (e * w).flatten(-2).sum(-1) / w.sum()
    return per_image.mean()


class GaborPhaseLoss(nn.Module):
    """Magnitude-weighted cyclic phase difference between the curved-Gabor responses of an image and a target.

    The target's ring geometry (curved patches, normal sign, local frequency) and its response are computed once
    here; :meth:`forward` filters the prediction through the same geometry (see the module docstring).

    Args:
        target: the target image, ``(H, W)`` grey or ``(C, H, W)`` / ``(1, C, H, W)`` with C = 1 or 3 (RGB is turned
            into grey with Rec. 709 weights; give target and prediction in the same colour space, e.g. both linear).
        p, q: curved-Gabor half-lengths across / along the rings (px); the patches should span a few rings.
        sigma_along, sigma_across: Gabor envelopes (px), as in :func:`~torch_appearance.rings.curved_gabor`.
        mask: optional ``(H, W)`` non-negative weights (e.g. 0 outside the board).
        mode: ``"squared"`` (default, the paper's ``wrap(d)^2``) or ``"cosine"`` (``2 (1 - cos d)``).
        weight_cap: cap of the amplitude weight ``|R_target| / mean |R_target|``; None: no cap.
        device: device of the geometry buffers (``.to()`` moves them later).
        **gabor_kwargs: further keyword arguments of :func:`~torch_appearance.rings.curved_gabor` for the target
            (``freq_range``, ``normal_reference``, ``sigma_smooth``, ``window``, ``chunk_size``, ``num_workers``).

    Attributes:
        filter: the :class:`~torch_appearance.rings.gabor.CurvedGaborFilter` (``filter.reference`` is the target's
            :class:`~torch_appearance.rings.GaborResult`).
        target_response: complex ``(H, W)`` buffer; weight: ``(H, W)`` buffer.

    Example:
        >>> import torch
        >>> from torch_appearance.nn import GaborPhaseLoss, WoodModel
        >>> model = WoodModel(ring_scale_mm=0.8, distortion=None)
        >>> with torch.no_grad():
        ...     _ = model.translation.copy_(torch.tensor([-2.4, -2.4, 0.0]))
        ...     target = model.render_board(48, 48, 0.1)["image"].permute(2, 0, 1)
        ...     _ = model.log_ring_scale.fill_(torch.log(torch.tensor(0.9)))
        >>> loss_fn = GaborPhaseLoss(target, p=10, q=10)
        >>> loss = loss_fn(model.render_board(48, 48, 0.1)["image"].permute(2, 0, 1))
        >>> loss.backward()
        >>> bool(model.log_ring_scale.grad > 0)   # lowering the scale lowers the loss
        True
    """

    def __init__(self, target, p: int = 20, q: int = 20, sigma_along: float | None = None,
                 sigma_across: float | None = None, *, mask=None, mode: str = "squared",
                 weight_cap: float | None = 3.0, device="cpu", **gabor_kwargs):
        super().__init__()
        from ..rings.gabor import CurvedGaborFilter  # rings imports nn.wood; import here to keep nn importable alone

        if mode not in _MODES:
            raise ValueError(f"mode: expected one of {_MODES}, got {mode!r}")
        if weight_cap is not None and (isinstance(weight_cap, bool) or not isinstance(weight_cap, numbers.Real)
                                       or not math.isfinite(weight_cap) or weight_cap <= 0):
            raise ValueError(f"weight_cap: expected a finite number > 0 or None, got {weight_cap!r}")
        gray = _to_gray(target, "target", batch=False)[0].detach().to("cpu", torch.float32)
        if not bool(torch.isfinite(gray).all()):
            raise ValueError("target: expected finite values, got NaN or infinity")
        self.mode = mode
        self.filter = CurvedGaborFilter.from_image(gray, p, q, sigma_along, sigma_across, device=device,
                                                   **gabor_kwargs)
        with torch.no_grad():
            response = self.filter(gray.to(device))
        magnitude = response.abs()
        weight = magnitude / magnitude.mean().clamp_min(1e-30)
        if weight_cap is not None:
            weight = weight.clamp(max=float(weight_cap))
        if mask is not None:
            if isinstance(mask, np.ndarray):
                mask = torch.from_numpy(np.ascontiguousarray(mask, dtype=np.float32))
            if not isinstance(mask, torch.Tensor) or tuple(mask.shape) != tuple(gray.shape):
                raise ValueError(f"mask: expected a tensor or array of shape {tuple(gray.shape)}, got "
                                 f"{tuple(mask.shape) if hasattr(mask, 'shape') else type(mask).__name__}")
            mask = mask.detach().to(device=device, dtype=torch.float32)
            if not bool(torch.isfinite(mask).all()) or bool((mask < 0).any()) or float(mask.sum()) <= 0:
                raise ValueError("mask: expected finite, non-negative values with a positive sum")
            weight = weight * mask
        if float(weight.sum()) <= 0:
            raise ValueError("target: its curved-Gabor response is zero everywhere (no rings to compare)")
        self.register_buffer("target_response", response)
        self.register_buffer("weight", weight)

    def phase_difference(self, image) -> torch.Tensor:
        """Per-pixel cyclic phase difference ``d`` (rad, ``(B, H, W)``) of ``image`` against the target."""
        r = self.filter(_to_gray(image, "image", batch=True))
        return torch.angle(r * self.target_response.to(r.dtype).conj())

    def forward(self, image) -> torch.Tensor:
        """Loss of ``image`` (``(H, W)``, ``(C, H, W)`` or ``(B, C, H, W)``, C = 1 or 3; float32/float64): scalar."""
        gray = _to_gray(image, "image", batch=True)
        if tuple(gray.shape[-2:]) != self.filter.shape:
            raise ValueError(f"image: expected height and width {self.filter.shape} (the target's), got "
                             f"{tuple(gray.shape[-2:])}")
        return gabor_phase_loss(self.filter(gray), self.target_response, self.weight, self.mode)

    def extra_repr(self) -> str:
        return f"mode={self.mode!r}"
