"""The colour error of a print, free of the evaluation render's Monte Carlo noise.

A render at ``n`` samples per texel is the print's expected colour ``μ`` plus noise of variance ``Σ/n``. Any colour
difference ``f`` of a noisy render against the target is biased upwards by that noise. At the object default of 32
spp the noise of one render is larger than the error of a good print (two renders of the same print differ by more
ΔE00 than either differs from its target), so a raw figure says mostly how noisy the evaluation was.

:func:`noise_free_error` takes ``K`` (2, or 4 for standard errors) independent renders of ``n`` spp each, splits
them into two halves and extrapolates to infinitely many samples (Richardson in 1/spp) from the two noise levels it
has: the mean of all renders (``K·n`` spp) and the means of the halves (``K·n/2`` spp each)::

    S_∞ ≈ 2 S(all) − ½ (S(half 1) + S(half 2))

* **mean ΔE00**: per texel, ``S`` is the *square* ΔE00², so that the extrapolation is the decorrelated product
  ``(A − T)·(B − T)`` of the two halves wherever the metric is locally Euclidean (unbiased for the squared error of
  ``μ``); the texel's error is its square root (clipped at zero), and the mean is taken over the texels.
* **p95 ΔE00**: ``S`` is the percentile of the texels' ΔE00 itself.
* **rms ΔE76** (the loss's E1 is a mean ΔE76²): the root of the mean decorrelated product in L*a*b*.

Measured against 4096-spp references (``scripts/eval/eval_print_error.py``, numbers in ``docs/bench_log.md``)
the mean's remaining bias is about 1 % of the error at 128 spp and above, where the raw figure is off by 10–40 %.
Not every bias can go: no estimator of ``|μ − T|`` from noisy samples is unbiased where the noise is far larger
than the error, so a budget too small for the print still reads high (the log says how large the noise was).

Halftone grain is not noise: the quantised print's expected colour varies from texel to texel, and that variation
stays in its error; only the renderer's sampling noise is taken out. To see what quantisation costs, pass the
continuous optimum's renders as ``target``: the error is then between two expected colours, both noise-free.

The standard error of the mean comes from the halves: with ``K = 4`` each half gives its own estimate from its two
renders, and their per-texel differences estimate the estimator's Monte Carlo variance at half the samples (the
full estimate has at most half of it: the SE is an upper bound where the noise dominates and the variance falls
faster). The percentile's SE is the two halves' difference (one degree of freedom). The figure of the mean of all
renders, what a single render at ``K·n`` spp reports, is kept as ``*_raw``, and ``dE00_noise`` is the mean ΔE00
between that render and the print's expected colour (half the mean ΔE00 between the two halves): the noise alone.

Example:
    >>> from torch_appearance.metrics import delta_e_2000
    >>> g = torch.Generator().manual_seed(0)
    >>> target = torch.rand(20000, 3, generator=g) * 0.5 + 0.25
    >>> print_ = (target * 1.04).clamp(0, 1)                              # a print 4 % too light
    >>> renders = print_ + 0.03 * torch.randn(4, 20000, 3, generator=g)   # four noisy renders of it
    >>> honest = noise_free_error(renders, target)
    >>> truth = float(delta_e_2000(print_, target).mean())
    >>> abs(honest["dE00_mean"] - truth) < 0.02 * truth, honest["dE00_mean_raw"] > 1.2 * truth
    (True, True)
"""
import numpy as np
import torch

from .metrics import delta_e_2000_lab, linear_rgb_to_lab

__all__ = ["noise_free_error", "richardson", "ERROR_FIELDS", "EVAL_RENDERS"]

#: what :func:`noise_free_error` returns, in this order (the log's columns)
ERROR_FIELDS = ("dE00_mean", "dE00_mean_se", "dE00_p95", "dE00_p95_se", "dE76_rms", "dE00_mean_raw",
                "dE00_p95_raw", "dE76_mean_raw", "dE00_noise")

#: independent renders per evaluation of a print run (``eval_spp / EVAL_RENDERS`` spp each)
EVAL_RENDERS = 4


def richardson(full, halves):
    """``2 full − mean(halves)``: a statistic at ``2n`` spp (``full``) and at ``n`` spp (the pair ``halves``)
    extrapolated to infinitely many samples, removing the bias term in ``1/n``; element-wise on arrays."""
    return 2.0 * full - 0.5 * (halves[0] + halves[1])


def _as_renders(name, value):
    array = value.detach().to("cpu", torch.float64).numpy() if isinstance(value, torch.Tensor) else \
        np.asarray(value, np.float64)
    if array.ndim < 1 or array.shape[-1] != 3:
        raise ValueError(f"{name}: expected linear RGB with channels last (..., 3), got shape {array.shape}")
    if not np.isfinite(array).all():
        raise ValueError(f"{name}: {int((~np.isfinite(array)).sum())} non-finite values (NaN or inf)")
    return array


class _Means:
    """L*a*b* of the means of subsets of K renders ((K, M, 3) linear RGB), each converted once however many
    comparisons use it; a noise-free target ((M, 3), no leading K) is the same colours for every subset."""

    def __init__(self, renders):
        self.renders, self._lab = renders, {}

    def lab(self, subset):
        """(M, 3) L*a*b* of the mean of the renders ``subset`` (a tuple of indices)."""
        key = () if self.renders.ndim == 2 else tuple(subset)
        if key not in self._lab:
            rgb = self.renders if not key else self.renders[list(key)].mean(0)
            self._lab[key] = np.asarray(linear_rgb_to_lab(rgb))
        return self._lab[key]


def _splits(subset):
    """The ways of cutting ``subset`` (2 or 4 render indices) into two halves: one for 2; all three for 4, so that
    every pair of renders meets (the decorrelated product becomes the mean over all pairs, the least noisy of them)."""
    if len(subset) == 2:
        return [((subset[0],), (subset[1],))]
    a, b, c, d = subset
    return [((a, b), (c, d)), ((a, c), (b, d)), ((a, d), (b, c))]


def _extrapolated(pred, ref, subset):
    """Extrapolated ``[dE00 mean, dE00 p95, dE76 rms]`` of the renders ``subset`` of ``pred`` against ``ref``
    (:class:`_Means`), the per-texel extrapolated ΔE00 (M,) and the raw ``[dE00 mean, dE00 p95, dE76 mean]`` of the
    mean of those renders."""
    lab_full = pred.lab(subset) - ref.lab(subset)
    de00_full = delta_e_2000_lab(pred.lab(subset), ref.lab(subset))
    squares, p95, products = [], [], []
    for split in _splits(subset):
        halves = [delta_e_2000_lab(pred.lab(h), ref.lab(h)) for h in split]
        squares.append(richardson(de00_full ** 2, [x ** 2 for x in halves]))
        p95.append(richardson(np.percentile(de00_full, 95), [np.percentile(x, 95) for x in halves]))
        lab = [pred.lab(h) - ref.lab(h) for h in split]
        products.append((lab[0] * lab[1]).sum(-1).mean())
    texel = np.sqrt(np.maximum(np.mean(squares, 0), 0.0))
    rms76 = np.sqrt(max(float(np.mean(products)), 0.0))
    return (np.array([texel.mean(), np.mean(p95), rms76]), texel,
            np.array([de00_full.mean(), np.percentile(de00_full, 95), np.linalg.norm(lab_full, axis=-1).mean()]))


def _sampling_se(per_texel, population):
    """Standard errors ``[mean, p95]`` of the texels' estimates ``per_texel`` (M,) as a uniform sample without
    replacement of ``population`` texels, for the figures of the whole population."""
    m = per_texel.size
    if isinstance(population, bool) or not isinstance(population, (int, np.integer)) or population < m:
        raise ValueError(f"population: expected an int >= the {m} scored texels, got {population!r}")
    if m < 2:
        return np.zeros(2)
    fpc = 1.0 - m / population
    mean_se = np.sqrt(fpc * per_texel.var(ddof=1) / m)
    # the 0.95 quantile's rank is Binomial(M, 0.95) about its place: one sd of ranks each side is ±1 SE
    q, x = 0.95, np.sort(per_texel)
    half = np.sqrt(m * q * (1 - q))
    lo, hi = (int(np.clip(np.round(m * q + s * half), 0, m - 1)) for s in (-1, 1))
    return np.array([mean_se, np.sqrt(fpc) * (x[hi] - x[lo]) / 2.0])


def noise_free_error(renders, target, mask=None, texels=False, population=None):
    """Mean and p95 CIEDE2000 of a print's expected colour against its target, from ``K`` independent renders.

    Args:
        renders: ``(K, ..., 3)`` linear RGB: ``K`` = 2 or 4 independent renders (other seeds) of one print at one
            spp (4 for standard errors).
        target: ``(..., 3)`` linear RGB, or ``(K, ..., 3)`` independent renders of another print (the error is then
            between the two prints' expected colours, e.g. a quantised print against its continuous optimum).
        mask: optional bool ``(...)`` selecting the texels to score.
        texels: also return the per-texel extrapolated ΔE00 (for heat maps).
        population: the scored texels are a uniform random sample, without replacement, of this many texels (an
            object's evaluation subset): the standard errors then include the sampling error over texels (the
            variance of the texels' estimates over M, with the finite-population factor 1 − M/population; for the
            p95 the spread of the order statistics around rank 0.95·M), so that they bound the error of the
            figure for the whole population, not only for the texels drawn.

    Returns:
        dict of floats (:data:`ERROR_FIELDS`): ``dE00_mean``, ``dE00_p95``, ``dE76_rms`` extrapolated to infinitely
        many samples; ``dE00_mean_se``, ``dE00_p95_se`` their Monte Carlo standard errors (NaN for ``K = 2``);
        ``dE00_mean_raw``, ``dE00_p95_raw``, ``dE76_mean_raw`` of the mean of the ``K`` renders (a render at ``K``
        times the spp); ``dE00_noise``, the mean ΔE00 of that render's noise. With ``texels=True`` a pair (that dict,
        the (M,) per-texel estimates of the selected texels).

    Raises:
        ValueError: bad shapes, ``K`` other than 2 or 4, non-finite colours, an empty mask.
    """
    renders, target = _as_renders("renders", renders), _as_renders("target", target)
    k, noisy_target = renders.shape[0], target.ndim == renders.ndim
    texel_shape = renders.shape[1:]
    if renders.ndim < 2 or (target.shape[1:] if noisy_target else target.shape) != texel_shape:
        raise ValueError(f"target: expected the texel shape of renders {texel_shape} (or {k} renders of it), got "
                         f"{target.shape}")
    if noisy_target and target.shape[0] != k:
        raise ValueError(f"target: expected {k} renders like renders, got {target.shape[0]}")
    if k not in (2, 4):
        raise ValueError(f"renders: expected 2 or 4 independent renders (average more into 4 groups), got {k}")
    renders = renders.reshape(k, -1, 3)
    target = target.reshape((k, -1, 3) if noisy_target else (-1, 3))
    if mask is not None:
        keep = mask.detach().cpu().numpy() if isinstance(mask, torch.Tensor) else np.asarray(mask)
        if keep.dtype != np.bool_ or keep.size != renders.shape[1]:
            raise ValueError(f"mask: expected a bool array of {renders.shape[1]} elements, got {keep.dtype} "
                             f"{keep.shape}")
        keep = keep.reshape(-1)
        renders, target = renders[:, keep], target[..., keep, :]
    if renders.shape[1] == 0:
        raise ValueError("mask: selects no texels")
    pred, ref = _Means(renders), _Means(target)
    estimate, per_texel, raw = _extrapolated(pred, ref, tuple(range(k)))
    se = np.full(2, np.nan)
    if k == 4:
        # each half's own estimate from its two renders: two independent estimates at half the samples
        parts = [_extrapolated(pred, ref, half) for half in ((0, 1), (2, 3))]
        # per texel: Var(one half's estimate) ≈ d²/2; the full estimate has twice the samples, at most half of that
        d = parts[0][1] - parts[1][1]
        se[0] = np.sqrt((d ** 2).sum() / 4.0) / renders.shape[1]
        se[1] = abs(parts[0][0][1] - parts[1][0][1]) / 2.0
    if population is not None:
        se = np.hypot(se, _sampling_se(per_texel, population))
    halves = _splits(tuple(range(k)))[0]
    noise = delta_e_2000_lab(pred.lab(halves[0]), pred.lab(halves[1])).mean() / 2.0
    result = {name: float(v) for name, v in zip(ERROR_FIELDS, [estimate[0], se[0], estimate[1], se[1], estimate[2],
                                                               *raw, noise])}
    return (result, per_texel) if texels else result
