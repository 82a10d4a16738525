"""Ink mixtures: learnable per-voxel mixture weights ρ and the linear mixing of σ_s, σ_a (eq. 9).

Nindel et al. (2021), §4.3: a voxel j holds an affine combination of the N printing inks, ρ_j ∈ Δ^{N−1}.
Scattering and absorption mix linearly,

    σ_s = Σ_n ρ_n σ_s,n,   σ_a = Σ_n ρ_n σ_a,n,   σ_t = σ_s + σ_a,   α = σ_s / σ_t        (eq. 9)

with σ_s,n = α_n μ_t,n and σ_a,n = (1 − α_n) μ_t,n. :class:`MaterialMixture` holds unconstrained logits and
maps them onto the simplex (sigmoid then per-voxel normalisation as in the paper, or softmax);
:func:`mix_inks` applies eq. 9 to any weight volume (e.g. a quantised one-hot volume).

Example:
    >>> from torch_appearance.fabrication import InkSet
    >>> from torch_appearance.nn import MaterialMixture
    >>> mixture = MaterialMixture(InkSet.from_names(), shape=(12, 32, 32))
    >>> sigma_t, albedo = mixture()             # (3, 12, 32, 32) each: mm⁻¹ and [0, 1]
    >>> mixture.weights()[4, 0, 0, 0].item()    # 97 % white at initialisation
    0.97...
"""
from collections.abc import Sequence
from dataclasses import dataclass
import math
import numbers
from typing import Any

import numpy as np
import torch

from ..checks import check_finite, check_tensor
from ..fabrication.inks import Ink, InkSet

__all__ = ["MaterialMixture", "FixedFraction", "mix_inks"]

_PARAMETERIZATIONS = ("sigmoid", "softmax")


def _as_inkset(name, inks):
    if isinstance(inks, InkSet):
        return inks
    if isinstance(inks, str):
        return InkSet.from_names(inks)
    if isinstance(inks, Sequence) and len(inks) > 0 and all(isinstance(x, str) for x in inks):
        return InkSet.from_names(inks)
    if isinstance(inks, Sequence) and len(inks) > 0 and all(isinstance(x, Ink) for x in inks):
        return InkSet(inks)
    raise TypeError(f"{name}: expected an InkSet (or a sequence of ink names or Ink objects), "
                    f"got {type(inks).__name__}")


def _check_weights(name, weights, n_inks):
    weights = check_tensor(name, weights, "(N, D, H, W)", dtypes="floating", numpy=True)
    if weights.dim() != 4 or weights.shape[0] != n_inks or min(weights.shape) < 1:
        raise ValueError(f"{name}: expected shape (N={n_inks}, D, H, W) with D, H, W >= 1, "
                         f"got {tuple(weights.shape)}")
    w = check_finite(name, weights.detach())  # in chunks: no |w| and bool copies of the volume
    if bool((w < 0).any()):
        raise ValueError(f"{name}: expected weights >= 0, got minimum {float(w.min()):g}")
    return weights


def _mix(weights, sigma_s_n, sigma_a_n, albedo_n):
    """Eq. 9 without checks: (N, ...) weights, (N, 3) σ_s,n, σ_a,n, α_n → (3, ...) σ_t and α."""
    sigma_s = torch.einsum("nc,n...->c...", sigma_s_n, weights)
    sigma_a = torch.einsum("nc,n...->c...", sigma_a_n, weights)
    sigma_t = sigma_s + sigma_a
    positive = sigma_t > 0
    if bool(positive.all()):  # (the usual case: the same numbers as below, without the fallback's temporaries)
        return sigma_t.contiguous(), (sigma_s / sigma_t).clamp(0.0, 1.0).contiguous()
    # Safe division: the unselected branch of torch.where must not produce NaN (its gradient would be NaN too).
    ratio = sigma_s / torch.where(positive, sigma_t, torch.ones_like(sigma_t))
    # σ_t = 0 only if every ink present has μ_t = 0 in that channel (built-in inks have μ_t >= 1e-4): no
    # interaction happens there, so α is irrelevant to the light transport; report the weight-averaged ink albedo.
    fallback = torch.einsum("nc,n...->c...", albedo_n, weights) / weights.sum(0).clamp_min(1e-300)
    albedo = torch.where(positive, ratio, fallback).clamp(0.0, 1.0)  # clamp: round-off only
    return sigma_t.contiguous(), albedo.contiguous()


def mix_inks(weights, inks):
    """Optical properties of ink mixtures by eq. 9 (σ_s and σ_a linear in the weights).

    Args:
        weights: (N, D, H, W) non-negative ink weights ρ (tensor or ndarray, floating point), normally summing to
            1 per voxel (a mixture, or a one-hot quantised volume). Unnormalised weights scale σ_t by their sum
            and leave α unchanged. Differentiable.
        inks: the :class:`~torch_appearance.fabrication.InkSet` (N inks), or a sequence of ink names.

    Returns:
        (sigma_t, albedo): each (3, D, H, W) of the weights' dtype and device; σ_t in mm⁻¹ and α in [0, 1],
        contiguous, ready for :func:`torch_appearance.render_texels`.

    Raises:
        TypeError, ValueError: wrong type, dtype or shape (N must equal ``len(inks)``), negative or non-finite
            weights.

    Example:
        >>> onehot = torch.zeros(5, 2, 4, 4); onehot[4] = 1          # all white
        >>> sigma_t, albedo = mix_inks(onehot, InkSet.from_names())   # μ_t and α of white everywhere
    """
    inks = _as_inkset("inks", inks)
    weights = _check_weights("weights", weights, len(inks))
    dtype, device = weights.dtype, weights.device
    return _mix(weights, inks.sigma_s(dtype, device), inks.sigma_a(dtype, device), inks.albedo(dtype, device))


@dataclass(frozen=True)
class FixedFraction:
    """Hold ink ``ink`` at exactly ``fraction`` in the voxels of ``mask``; the other inks share 1 − fraction.

    Args:
        mask: (D, H, W) bool tensor or ndarray: the constrained voxels.
        ink: the ink's name (case-insensitive), e.g. ``"transparent"``.
        fraction: the fixed weight, in [0, 1].

    Example:
        >>> core = torch.zeros(12, 32, 32, dtype=torch.bool); core[:6] = True
        >>> clear = FixedFraction(core, "transparent", 0.8)      # 80 % clear in the bottom half
    """
    mask: Any
    ink: str
    fraction: float

    def __post_init__(self):
        mask = self.mask
        if isinstance(mask, np.ndarray):
            mask = torch.from_numpy(np.ascontiguousarray(mask))
        if not isinstance(mask, torch.Tensor):
            raise TypeError(f"mask: expected a bool tensor or ndarray of shape (D, H, W), got {type(mask).__name__}")
        if mask.dtype != torch.bool:
            raise TypeError(f"mask: expected dtype bool, got {mask.dtype}")
        if mask.dim() != 3:
            raise ValueError(f"mask: expected shape (D, H, W), got {tuple(mask.shape)}")
        object.__setattr__(self, "mask", mask)
        if not isinstance(self.ink, str):
            raise TypeError(f"ink: expected an ink name (str), got {type(self.ink).__name__}")
        f = self.fraction
        if isinstance(f, bool) or not isinstance(f, numbers.Real):
            raise TypeError(f"fraction: expected a real number, got {type(f).__name__}")
        if not (math.isfinite(f) and 0.0 <= f <= 1.0):
            raise ValueError(f"fraction: expected a value in [0, 1], got {f!r}")
        object.__setattr__(self, "fraction", float(f))


def _initial_logits(n_inks, init_index, white_fraction, parameterization):
    """(N,) float64 logits whose weights are ``white_fraction`` for ``init_index`` and equal shares otherwise."""
    if init_index is None or n_inks == 1:
        rho = np.full(n_inks, 1.0 / n_inks)
    else:
        rho = np.full(n_inks, (1.0 - white_fraction) / (n_inks - 1))
        rho[init_index] = white_fraction
    if parameterization == "softmax":
        return np.log(rho)  # softmax(log ρ) = ρ / Σρ = ρ
    # sigmoid: choose sigmoid(l_n) = ρ_n, so the unnormalised values already sum to 1 (normalising is exact).
    # A single ink (ρ = 1) gets logit 0: its normalised weight is 1 for any logit.
    with np.errstate(divide="ignore"):
        return np.where(rho < 1.0, np.log(rho) - np.log1p(-rho), 0.0)


class MaterialMixture(torch.nn.Module):
    """Learnable per-voxel ink mixture ρ (N inks × D × H × W) and its optical properties by eq. 9.

    Parameterisations (``logits`` l, shape (N, D, H, W)):

    * ``"sigmoid"`` (the paper): u = sigmoid(l), ρ = u / Σ_n u_n.
    * ``"softmax"``: ρ = softmax(l) over the ink axis.

    Initialisation: ρ = ``white_fraction`` for ``init_ink`` and (1 − white_fraction)/(N − 1) for each other ink
    in every voxel (to round-off; for sigmoid the logits are logit(ρ), so Σu = 1 already), so every ink starts
    with a non-zero gradient.

    Fixed fractions: for each :class:`FixedFraction` the given ink's weight is *exactly* ``fraction`` in the
    masked voxels, and the remaining inks share 1 − Σ fixed there in proportion to their u = sigmoid(l)
    (or exp(l) for softmax); the fixed inks' logits are unused (zero gradient) in those voxels. Several
    constraints may overlap if the sum of fixed fractions per voxel is <= 1 (= 1 exactly when every ink is fixed)
    and one ink is not fixed to two different values.

    Shell-only parameters: with ``support`` (a (D, H, W) bool mask, e.g. the voxels within a few mm of an object's
    surface) only those S voxels carry logits (N, S); every other voxel holds ``core_ink`` exactly and costs
    neither parameters nor gradient memory.

    Args:
        inks: :class:`~torch_appearance.fabrication.InkSet` (or a sequence of built-in ink names).
        shape: (D, H, W) voxel counts, D the printing z axis.
        parameterization: ``"sigmoid"`` or ``"softmax"``.
        white_fraction: initial weight of ``init_ink``, in (0, 1) (ignored for a single ink).
        init_ink: name of the dominant initial ink, or ``None`` for a uniform 1/N start.
        fixed: sequence of :class:`FixedFraction`.
        dtype: ``torch.float32`` or ``torch.float64`` (of the logits and all outputs).
        support: optional (D, H, W) bool tensor/ndarray of the optimised voxels (None: all).
        core_ink: the ink of the voxels outside ``support`` (default: ``init_ink``, or white).

    Attributes:
        logits: ``nn.Parameter`` (N, D, H, W), or (N, S) with a support.
        inks: the :class:`InkSet`.

    Example:
        >>> mixture = MaterialMixture(InkSet.from_names(), (12, 32, 32))
        >>> optimizer = torch.optim.Adagrad(mixture.parameters(), lr=0.1)
        >>> sigma_t, albedo = mixture()          # feed to torch_appearance.render_texels
    """

    def __init__(self, inks, shape, parameterization="sigmoid", white_fraction=0.97, init_ink="white", fixed=(),
                 dtype=torch.float32, support=None, core_ink=None):
        super().__init__()
        self.inks = _as_inkset("inks", inks)
        n = len(self.inks)
        if isinstance(shape, torch.Size):
            shape = tuple(shape)
        if (isinstance(shape, (str, bytes)) or not isinstance(shape, Sequence) or len(shape) != 3
                or not all(isinstance(s, numbers.Integral) and not isinstance(s, bool) and s >= 1 for s in shape)):
            raise ValueError(f"shape: expected (D, H, W), three ints >= 1, got {shape!r}")
        self.shape = tuple(int(s) for s in shape)
        if parameterization not in _PARAMETERIZATIONS:
            raise ValueError(f"parameterization: expected one of {_PARAMETERIZATIONS}, got {parameterization!r}")
        self.parameterization = parameterization
        if dtype not in (torch.float32, torch.float64):
            raise TypeError(f"dtype: expected torch.float32 or torch.float64, got {dtype}")
        wf = white_fraction
        if isinstance(wf, bool) or not isinstance(wf, numbers.Real):
            raise TypeError(f"white_fraction: expected a real number, got {type(wf).__name__}")
        if not (math.isfinite(wf) and 0.0 < wf < 1.0):
            raise ValueError(f"white_fraction: expected a value in (0, 1), got {wf!r}")
        self.white_fraction = float(wf)
        if init_ink is None:
            init_index = None
        else:
            try:
                init_index = self.inks.index(init_ink)
            except (TypeError, ValueError):
                raise ValueError(f"init_ink: expected one of {list(self.inks.names)} or None, "
                                 f"got {init_ink!r}") from None
        self.init_ink = None if init_index is None else self.inks.names[init_index]

        support_index = self._build_support(support)
        self.param_shape = self.shape if support_index is None else (len(support_index),)
        core_name = core_ink if core_ink is not None else (self.init_ink or "white")
        try:
            core_index = self.inks.index(core_name)
        except (TypeError, ValueError):
            raise ValueError(f"core_ink: expected one of {list(self.inks.names)}, got {core_name!r}") from None
        self.core_ink = self.inks.names[core_index]

        init = torch.from_numpy(_initial_logits(n, init_index, self.white_fraction, parameterization))
        ones = (1,) * len(self.param_shape)
        self.logits = torch.nn.Parameter(init.to(dtype).view(n, *ones).expand(n, *self.param_shape).contiguous())

        fixed_mask, fixed_value, remaining = self._build_fixed(fixed, dtype, support_index)
        self.fixed = (fixed,) if isinstance(fixed, FixedFraction) else tuple(fixed)
        self.register_buffer("fixed_mask", fixed_mask, persistent=False)
        self.register_buffer("fixed_value", fixed_value, persistent=False)
        self.register_buffer("free_share", remaining, persistent=False)
        self.register_buffer("ink_sigma_s", self.inks.sigma_s(dtype), persistent=False)
        self.register_buffer("ink_sigma_a", self.inks.sigma_a(dtype), persistent=False)
        self.register_buffer("ink_albedo", self.inks.albedo(dtype), persistent=False)
        self.register_buffer("support_index", support_index, persistent=False)
        core = torch.zeros(n, dtype=dtype)
        core[core_index] = 1
        self.register_buffer("core_weights", core, persistent=False)

    def _build_support(self, support):
        """(S,) int64 flat indices of the support voxels, or None."""
        if support is None:
            return None
        if isinstance(support, np.ndarray):
            support = torch.from_numpy(np.ascontiguousarray(support))
        if not isinstance(support, torch.Tensor) or support.dtype != torch.bool:
            raise TypeError(f"support: expected a bool tensor or ndarray of shape {self.shape}, got "
                            f"{getattr(support, 'dtype', type(support).__name__)}")
        if tuple(support.shape) != self.shape:
            raise ValueError(f"support: expected shape {self.shape} (the mixture's shape), got {tuple(support.shape)}")
        index = support.reshape(-1).nonzero().flatten()
        if index.numel() == 0:
            raise ValueError("support: selects no voxels; there is nothing to optimise")
        return index

    def _build_fixed(self, fixed, dtype, support_index=None):
        n = len(self.inks)
        if isinstance(fixed, FixedFraction):
            fixed = (fixed,)
        if isinstance(fixed, (str, bytes)) or not isinstance(fixed, Sequence):
            raise TypeError(f"fixed: expected a sequence of FixedFraction, got {type(fixed).__name__}")
        shape = self.shape if support_index is None else (len(support_index),)
        mask = torch.zeros((n, *shape), dtype=torch.bool)
        value = torch.zeros((n, *shape), dtype=torch.float64)
        for i, constraint in enumerate(fixed):
            if not isinstance(constraint, FixedFraction):
                raise TypeError(f"fixed[{i}]: expected a FixedFraction, got {type(constraint).__name__}")
            if tuple(constraint.mask.shape) != self.shape:
                raise ValueError(f"fixed[{i}].mask: expected shape {self.shape} (the mixture's shape), "
                                 f"got {tuple(constraint.mask.shape)}")
            try:
                k = self.inks.index(constraint.ink)
            except ValueError:
                raise ValueError(f"fixed[{i}].ink: ink {constraint.ink!r} is not in the ink set "
                                 f"{list(self.inks.names)}") from None
            m = constraint.mask.cpu()
            if support_index is not None:
                outside = int(m.sum()) - int(m.reshape(-1)[support_index].sum())
                if outside:
                    raise ValueError(f"fixed[{i}].mask: {outside} of its voxels lie outside the optimised support "
                                     f"(they hold the core ink {self.core_ink!r}); widen the support (shell)")
                m = m.reshape(-1)[support_index]
            clash = m & mask[k] & (value[k] != constraint.fraction)
            if bool(clash.any()):
                raise ValueError(f"fixed[{i}]: ink {self.inks.names[k]!r} is already fixed to a different fraction "
                                 f"in {int(clash.sum())} of its voxels")
            mask[k] |= m
            value[k] = torch.where(m, torch.full_like(value[k], constraint.fraction), value[k])
        total = value.sum(0)
        if bool((total > 1.0 + 1e-12).any()):
            raise ValueError(f"fixed: the fixed fractions sum to more than 1 in {int((total > 1.0 + 1e-12).sum())} "
                             f"voxel(s) (largest sum {float(total.max()):.6g})")
        all_fixed = mask.all(0)
        bad = all_fixed & ((total - 1.0).abs() > 1e-12)
        if bool(bad.any()):
            raise ValueError(f"fixed: every ink is fixed in {int(bad.sum())} voxel(s) but the fractions there do not "
                             f"sum to 1 (e.g. {float(total[bad][0]):.6g})")
        # What the free inks share: 1 − Σ fixed (clamped at 0 against round-off such as 0.1 + 0.2 + 0.7 > 1).
        remaining = (1.0 - total).clamp_min(0.0).unsqueeze(0)
        return mask, value.to(dtype), remaining.to(dtype)

    @torch.no_grad()
    def set_weights(self, weights, floor=1e-3):
        """Start from given mixtures (e.g. the naive extrusion): set the logits so that ``weights()`` ≈ ``weights``.

        Each weight is clamped to [``floor``, 1 − ``floor``] before the inverse parameterisation (logit for
        sigmoid, log for softmax), so that every ink keeps a non-zero gradient; the result is then renormalised,
        so an ink at weight 0 ends at about ``floor``. Fixed fractions stay exact (their logits are unused), and
        voxels outside the support keep the core ink.

        Args:
            weights: (N, D, H, W) non-negative mixture weights (tensor or ndarray), N = ``n_inks``, (D, H, W) =
                ``shape``; each voxel's weights should sum to 1.
            floor: in (0, 0.5): the smallest weight an ink starts with.

        Returns:
            self.
        """
        weights = _check_weights("weights", weights, self.n_inks)
        if tuple(weights.shape[1:]) != self.shape:
            raise ValueError(f"weights: expected shape ({self.n_inks}, {', '.join(map(str, self.shape))}), "
                             f"got {tuple(weights.shape)}")
        if isinstance(floor, bool) or not isinstance(floor, numbers.Real) or not 0.0 < floor < 0.5:
            raise ValueError(f"floor: expected a number in (0, 0.5), got {floor!r}")
        w = weights.detach().reshape(self.n_inks, -1)
        if self.support_index is not None:  # select first, then float64: no float64 copy of the whole grid
            w = w[:, self.support_index.to(w.device)]
        w = w.to(torch.float64)
        w = w.clamp(floor, 1.0 - floor)
        logits = torch.log(w) - torch.log1p(-w) if self.parameterization == "sigmoid" else torch.log(w)
        self.logits.copy_(logits.view(self.logits.shape).to(self.logits.dtype))
        return self

    @property
    def n_inks(self):
        """Number of inks N."""
        return len(self.inks)

    def weights(self):
        """Mixture weights ρ, shape (N, D, H, W): >= 0 and summing to 1 per voxel; fixed fractions exact; the core
        ink (weight 1) outside the support."""
        w = self.free_weights()
        if self.support_index is None:
            return w
        return self._scatter(w, self.core_weights)

    def _scatter(self, values, core):
        """(C, S) support values → (C, D, H, W), ``core`` (C,) elsewhere (differentiable in ``values``)."""
        full = core.to(values.dtype).view(-1, 1).expand(values.shape[0], math.prod(self.shape))
        return full.index_copy(1, self.support_index, values).view(values.shape[0], *self.shape)

    def free_weights(self):
        """Weights of the optimised voxels: (N, D, H, W), or (N, S) with a support."""
        logits = self.logits
        constrained = len(self.fixed) > 0  # without fixed fractions the where()s below are identities: skipped,
        free = ~self.fixed_mask if constrained else None  # with their (N, ...) temporaries (same numbers)
        if self.parameterization == "sigmoid":
            u = torch.sigmoid(logits)
        else:
            # exp(l − max over the free inks): stable, and the largest free term is 1, so Σ_free u >= 1.
            masked = logits.detach().masked_fill(self.fixed_mask, -math.inf) if constrained else logits.detach()
            shift = masked.amax(0, keepdim=True)
            shift = torch.where(torch.isfinite(shift), shift, torch.zeros_like(shift))
            u = torch.exp(logits - shift)
        u_free = torch.where(free, u, torch.zeros_like(u)) if constrained else u
        total_free = u_free.sum(0, keepdim=True)
        safe = torch.where(total_free > 0, total_free, torch.ones_like(total_free))
        weights = u_free * (self.free_share / safe)
        return torch.where(free, weights, self.fixed_value) if constrained else weights

    def forward(self):
        """Optical properties of the current mixture by eq. 9.

        Returns:
            (sigma_t, albedo): each (3, D, H, W), the logits' dtype; σ_t in mm⁻¹ (> 0 for the built-in inks),
            α in [0, 1]; contiguous, ready for :func:`torch_appearance.render_texels`.
        """
        if self.support_index is None:
            return _mix(self.weights(), self.ink_sigma_s, self.ink_sigma_a, self.ink_albedo)
        sigma_t, albedo = _mix(self.free_weights(), self.ink_sigma_s, self.ink_sigma_a, self.ink_albedo)
        core_t, core_a = _mix(self.core_weights.view(-1, 1), self.ink_sigma_s, self.ink_sigma_a, self.ink_albedo)
        return (self._scatter(sigma_t, core_t.view(-1)).contiguous(),
                self._scatter(albedo, core_a.view(-1)).contiguous())

    def extra_repr(self):
        support = "" if self.support_index is None else f", support={len(self.support_index)}, core={self.core_ink!r}"
        return (f"inks={list(self.inks.names)}, shape={self.shape}, parameterization={self.parameterization!r}, "
                f"fixed={len(self.fixed)}{support}")
