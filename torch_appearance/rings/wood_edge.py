"""Where the wood ends along a disc transect, and the narrow rings just inside it (disc mode's steps 2 and 5,
:mod:`~torch_appearance.rings.disc`).

The wood's edge: against a uniform background the wood mask ends it, unless a dark bark band lies between them
(:func:`dark_bark_start`); without one (a cloth, a ruler, a label, a table round the disc: :func:`background_colour`
is None) it is where the wood's colour ends (:func:`wood_colour_end`). The rings just inside the bark are often
narrower than the Gabor passes resolve: :func:`bark_zone_boundaries` finds them between the last boundary and the
edge, :func:`gap_boundaries` (``bark_gaps``, off by default) inside the last gaps before it. ``rows`` are the central
rows of a polar strip, ``(S, L, 3)`` RGB in [0, 1] (columns: px from the pith); positions are strip columns (px).
"""
from __future__ import annotations

import math

import numpy as np
from scipy import ndimage

__all__ = ["background_colour", "wood_colour_end", "dark_bark_start", "bark_zone_boundaries", "gap_boundaries"]


def background_colour(rgb, tol):
    """Median colour ``(C,)`` of the image border, or None when the border is not one uniform colour (half of its
    pixels, averaged over 9 along the border, farther than ``tol / 2`` from the median: the disc fills the frame,
    no background to mask)."""
    # each border line averaged over 9 pixels along it: the noise of single pixels is not a second colour
    border = np.concatenate([ndimage.uniform_filter1d(np.asarray(line, np.float64), 9, axis=0, mode="nearest")
                             for line in (rgb[0], rgb[-1], rgb[:, 0], rgb[:, -1])])
    bg = np.median(border, axis=0)
    return bg if np.median(np.linalg.norm(border - bg, axis=1)) <= tol / 2 else None


def wood_colour_end(rows, *, sigma=6.0, dark=0.45, grey=0.45, hue_deg=90.0, tail=0.8, min_tail=20, min_run=20,
                     outer=0.6, fall_level=None):
    """Where the wood ends along a transect whose photo has no uniform background (a cloth, a ruler, a label, a
    table around the disc): the last column of wood, or None.

    A column is *dark* when the central rows' smoothed brightness (HSV V) is below ``dark`` times the wood's (the
    median over the inner 60 % of the transect): bark, a dark cloth; it is *not wood* when dark or when its
    saturation is below ``grey`` times the wood's (a white or grey ruler, paper), or when it is at least as bright
    as the wood and its hue lies more than ``hue_deg`` from the wood's (a tinted ruler, a blue cloth or label; wood
    runs from yellow to red-brown, and blue-stained sapwood is darker than the wood). Beyond ``outer`` of the transect
    (bark and background lie outside; knots, stains and cracks inside must not end it) the wood ends at the first
    run of ``min_run`` dark columns (the bark, even when a wooden table lies beyond it), or at the first column from
    which at least ``tail`` of the rest (and ``min_tail`` px) is not wood; the last wood column is then the one
    before the steepest fall of brightness within two smoothing widths of that column. With ``fall_level`` (a
    fraction), it is instead the last column, up to 20 px before that steepest fall, still brighter than the wood
    less ``fall_level`` of the fall from the wood (median of the 40 - 10 px before) to the bark (median of the 3 -
    15 px after): on a gradual fall into the bark, ``0.5`` is half-way down it, where the TRAS discs' people clicked.
    """
    rgb = rows.mean(0)                                            # (L, 3)
    hi, lo = rgb.max(1), rgb.min(1)
    v = ndimage.gaussian_filter1d(hi, sigma, mode="nearest")
    sat = ndimage.gaussian_filter1d(np.where(hi > 1e-6, (hi - lo) / np.maximum(hi, 1e-6), 0.0), sigma, mode="nearest")
    L = len(v)
    if L < 3 * min_run:
        return None
    inner = slice(0, int(outer * L))
    v_wood, s_wood = np.median(v[inner]), np.median(sat[inner])
    if v_wood <= 0 or s_wood <= 0.05:                              # grey wood (or a grey photo): no colour to follow
        return None
    is_dark = v < dark * v_wood
    sm = ndimage.gaussian_filter1d(rgb, sigma, axis=0, mode="nearest")
    hue = np.angle((2 * sm[:, 0] - sm[:, 1] - sm[:, 2]) + 1j * math.sqrt(3) * (sm[:, 1] - sm[:, 2]))  # radians
    w = sat[inner]
    hue_wood = np.angle((w * np.exp(1j * hue[inner])).sum())
    off_hue = (np.abs(np.angle(np.exp(1j * (hue - hue_wood)))) > math.radians(hue_deg)) & (v >= v_wood)
    nonwood = is_dark | (sat < grey * s_wood) | off_hue
    runs = np.convolve(is_dark.astype(int), np.ones(min_run, int), "valid") == min_run   # a dark run starts here
    suffix = np.cumsum(nonwood[::-1])[::-1] / np.arange(L, 0, -1)  # fraction of non-wood from each column on
    cols = np.arange(L)
    start = int(outer * L)
    hits = np.nonzero((cols[:len(runs)] >= start) & runs)[0]
    hits = np.r_[hits, np.nonzero((cols >= start) & (suffix >= tail) & (cols <= L - min_tail) & nonwood)[0]]
    if not len(hits):
        return None
    # the wood's edge itself: the steepest fall of the lightly smoothed brightness within two smoothing widths
    c = int(hits.min())
    a, b = max(1, c - int(2 * sigma)), min(L - 1, c + int(2 * sigma) + 1)
    hs = ndimage.gaussian_filter1d(hi, 1.5, mode="nearest")
    e0 = a - 1 + int(np.argmin(np.diff(hs)[a - 1:b - 1]))
    if fall_level is None or e0 < 40 or e0 + 15 > L:
        return e0
    wood, bark = np.median(hs[e0 - 40:e0 - 10]), np.median(hs[e0 + 3:e0 + 15])
    above = np.nonzero(hs[e0 - 20:e0 + 1] >= wood - fall_level * (wood - bark))[0]
    return e0 - 20 + int(above[-1]) if len(above) and wood > bark else e0


def dark_bark_start(rows, *, dark=0.45, min_px=4, sigma=1.5):
    """Where a dark bark band begins on a transect whose wood mask ran up to the background (``rows`` ``(S, L, 3)``,
    the central rows up to the last wood-or-bark column): the bark is not background, so the mask counts it as
    wood. When the last columns are dark (smoothed HSV V below ``dark`` times the median of the inner 60 %) in one
    run of at least ``min_px`` reaching to within 5 px of the end, the wood ends before the steepest fall of
    brightness at the run's start; else None."""
    v = ndimage.gaussian_filter1d(rows.mean(0).max(1), sigma, mode="nearest")
    L = len(v)
    if L < 20:
        return None
    is_dark = v < dark * np.median(v[:int(0.6 * L)])
    darks = np.nonzero(is_dark)[0]
    if not len(darks) or darks[-1] < L - 6:  # the run must reach the end (its last columns blend with background)
        return None
    stop = int(darks[-1])
    light = np.nonzero(~is_dark[:stop])[0]
    start = int(light[-1]) + 1 if len(light) else 0
    if stop + 1 - start < min_px or start < 0.6 * L:
        return None
    a, b = max(1, start - 6), min(L - 1, start + 3)
    return a - 1 + int(np.argmin(np.diff(v)[a - 1:b - 1]))


def _outward_rise(pos, v_prof, sigma, n_ref):
    """``(dv, ref)``: the profile's outward rise ``dV/dr`` (``(L,)``, ``v_prof`` smoothed with sigma ``sigma`` px) and
    the scale the rings near the bark are judged by, the median positive rise at the ``n_ref`` outermost boundaries
    ``pos`` (0.0 when none rises)."""
    dv = np.gradient(ndimage.gaussian_filter1d(np.asarray(v_prof, np.float64), sigma))
    ref = dv[np.clip(np.round(pos[-n_ref:]).astype(int), 0, len(dv) - 1)]
    return dv, float(np.median(ref[ref > 0])) if (ref > 0).any() else 0.0


def bark_zone_boundaries(pos, v_prof, end, *, min_rel=0.2, min_gap_px=2.0, sigma=0.7, n_ref=5):
    """Ring boundaries in the bark zone (issue 48): the rings just inside the bark are often narrower (3 - 6 px)
    than even the fine pass's scale resolves, so the Gabor phase runs over them and the transect ends some rings
    short of the bark. Between the last boundary ``pos[-1]`` and the wood's edge ``end`` (column positions on the
    strip), every local maximum of the profile's outward rise ``dV/dr`` (``v_prof`` smoothed with sigma ``sigma``
    px) is a boundary when the rise is at least ``min_rel`` of the median rise at the ``n_ref`` outermost boundaries
    already found (those rings' own latewood -> earlywood steps set the scale: faint outer rings are judged against
    their neighbours, not against the strong juvenile rings), it lies at least ``min_gap_px`` from the boundaries
    beside it and the edge, and the zone holds room for a ring (it is wider than 1.5 times the last ring). Returns
    the added positions (sorted)."""
    pos = np.asarray(pos, np.float64)
    if len(pos) < 3 or end is None:
        return np.zeros(0)
    gaps = np.diff(pos[-(n_ref + 1):])
    last = float(pos[-1])
    if end - last < 1.5 * max(float(np.median(gaps[-3:])), min_gap_px):
        return np.zeros(0)
    dv, ref = _outward_rise(pos, v_prof, sigma, n_ref)
    L = len(dv)
    if ref <= 0:
        return np.zeros(0)
    lo, hi = int(math.floor(last + min_gap_px)), int(math.ceil(end - min_gap_px))
    cand = [i for i in range(max(lo, 1), min(hi, L - 1)) if dv[i] >= dv[i - 1] and dv[i] > dv[i + 1]
            and dv[i] >= min_rel * ref]
    out, prev = [], last
    for i in sorted(cand, key=lambda i: -dv[i]):  # strongest first, spacing kept
        if all(abs(i - x) >= min_gap_px for x in out + [prev, end]):
            out.append(i)
    out = np.sort(np.asarray(out, np.float64))
    if len(out):  # sub-pixel: a parabola through the derivative peak
        i = out.astype(int)
        y0, y1, y2 = dv[i - 1], dv[i], dv[i + 1]
        den = y0 - 2 * y1 + y2
        out = out + np.clip(np.where(den < 0, 0.5 * (y0 - y2) / np.where(den < 0, den, -1.0), 0.0), -0.5, 0.5)
    return out


def gap_boundaries(pos, v_prof, end, *, gaps, min_rel=0.2, sigma=0.7, sep_frac=0.3, min_sep_px=5.0, n_ref=5):
    """Narrow rings skipped between boundaries near the bark (``bark_gaps``, issue 48 item 3): in each of the last
    ``gaps`` gaps before the wood's edge ``end`` (between the boundaries ``pos`` more than 3 px inside it, and from the
    last of them to the edge), the strongest local maximum of the profile's outward rise (``v_prof`` smoothed with
    sigma ``sigma`` px, as in :func:`bark_zone_boundaries`) that reaches ``min_rel`` of the median rise at the
    ``n_ref`` outermost boundaries and lies at least ``max(min_sep_px, sep_frac * gap)`` from both ends of its gap is
    a boundary. Near the bark the rings narrow to a fraction of the disc's ring period, and both passes can run one
    cycle over two rings there; the bark zone only looks beyond the last boundary. Returns the added positions
    (sorted), at most one per gap."""
    pos = np.sort(np.asarray(pos, np.float64))
    if end is None or gaps < 1:
        return np.zeros(0)
    pos = pos[pos < end - 3.0]
    if len(pos) < max(3, gaps):
        return np.zeros(0)
    dv, ref = _outward_rise(pos, v_prof, sigma, n_ref)
    L = len(dv)
    if ref <= 0:
        return np.zeros(0)
    bounds = np.r_[pos[-gaps:], end]
    out = []
    for a, b in zip(bounds[:-1], bounds[1:]):
        sep = max(min_sep_px, sep_frac * (b - a))
        cand = [i for i in range(max(1, int(math.ceil(a + sep))), min(L - 1, int(math.floor(b - sep)) + 1))
                if dv[i] >= dv[i - 1] and dv[i] > dv[i + 1] and dv[i] >= min_rel * ref]
        if cand:
            out.append(float(max(cand, key=lambda i: dv[i])))
    return np.asarray(out, np.float64)
