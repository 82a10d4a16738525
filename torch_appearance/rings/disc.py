"""Disc mode: ring boundaries along several pith -> bark transects of a whole-disc photo, filtered once.

A cross-section (disc) photo shows closed, roughly concentric rings around the pith. Filtering the whole photo
again for every transect (as :func:`~torch_appearance.rings.dendro.detect_transect_boundaries` does) costs minutes
on a 3000 x 3200 photo; here only a narrow *polar strip* around each transect is resampled and filtered, once:

1. **Polar strip.** For a transect at angle ``theta`` from the pith, sample the image at radius ``r`` (columns,
   1 px steps from the pith) and arc offset ``s`` (rows, ``-half_width..half_width``, 1 px steps):
   ``pith + r (cos phi, sin phi)`` with ``phi = theta + s / max(r, half_width)``. Circular rings around the pith
   become exactly vertical lines, so the strip looks like an increment core with the pith on the left and the
   bark on the right; eccentric or wavy rings are only slightly tilted.
2. **Wood / background.** Pixels whose colour is within ``background_tol`` (RGB distance, values in [0, 1]) of the
   background colour (the median of the image border, or ``background``) are *not wood*: the background around the
   disc and open cracks; a border that is not one uniform colour (the disc fills the frame, or it lies on a cloth
   beside a ruler and a label) gives no background. The disc edge along the transect is where the wood fraction of
   the strip's central rows last drops below one half; without a background, where the wood's colour ends beyond
   60 % of the transect (the first 20 px of bark darker than 0.45 of the wood, or a rest that is mostly dark, grey,
   or bright and of another hue, like a tinted ruler against a light bark: :func:`.wood_edge.wood_colour_end`); with a
   background, a dark bark band between the wood and it (which the background mask counts as wood) ends the wood
   where it starts (:func:`.wood_edge.dark_bark_start`). The strip is
   cut there, and the edge is never a ring boundary. Non-wood pixels are replaced by the mean of the wood pixels of
   their column (i.e. filled *along the ring*), so a crack along the transect does not hide the rings.
3. **Filter.** The strip's HSV value is filtered with the curved Gabor filter (normal oriented pith -> bark), as in
   core mode (:mod:`torch_appearance.rings.dendro`), with the orientation field clamped to ``max_tilt_deg`` from
   the radial normal. ``p = p_periods P`` (default 2) and ``q = P`` scale with one ring period ``P`` for the whole
   disc: the peak of the frequency-weighted power spectra of all strips (slow brightness trends removed) summed - a
   single strip's estimate is easily pulled to the scale of heartwood or stain patterns. The filter resolves ring
   spacings up to ``p`` px, and rings vary more along a pith-to-bark radius (wide juvenile rings near the pith)
   than along a core segment, hence 2 P rather than core mode's 1.5 P (F02b, 8 transects: F1 at 5 px 0.86 with
   1.5 P, 0.89 with 2 P, 0.89 with 2.5 P). The filter sees the strip less its blur along the radius (sigma
   ``highpass_periods P``, default 1): the filter's local frequency is the peak of the spectrum in its window,
   which a brightness trend across the window (heartwood, stains) otherwise pins to the window's lowest frequency,
   so that the phase does not follow the rings there. The local ring period along the transect is reported
   (``info["local_period_px"]``).
4. **Profile.** The local ring tilt in the strip (magnitude-weighted doubled-angle mean of the Gabor orientation
   over the central rows, smoothed along the radius) gives a shear per column; the V profile and the complex
   Gabor response are averaged over the central ``band`` of rows (all by default) along that local tilt, weighted
   by the wood mask times the squared Gabor amplitude (smoothed over one ring period along the radius), so rows
   where the rings are clear count most (a crack wall or a stain along the transect counts little).
5. **Boundaries.** The cycles of the unwrapped phase and the latewood-side foot of the steepest V rise in each
   cycle give the boundaries (``_cycle_boundaries`` of core mode), converted back to image coordinates.
   Boundaries within a quarter of the strip's dominant ring period (at least 3 px) of the pith are dropped (the
   pith is not a ring boundary). Ring width changes several-fold along a radius: where one cycle at the ring
   period spans two or more narrow rings (towards the bark), the phase skips them. A second pass at ``fine_scale P``
   (default P / 2) adds its boundaries where two neighbouring first-pass boundaries are less than ``narrow_gap P``
   (0.8; leave-one-disc-out on the TRAS discs C13C / C17C 0.6 gained about one boundary per disc on both, but it
   lost 0.014 on the independent synthetic discs whose rings shrink 10x to the bark - the unseen discs' failure -
   so 0.8 stays: ``scripts/eval/measured/disc_lodo.json``, ``docs/bench_log.md``) apart and the new one lies at
   least a quarter of that gap from both
   (``_narrow_ring_boundaries``); in wide rings the fine pass's extra cycles (earlywood texture) fall in wider gaps
   and are not taken. The fine pass
   filters the strip only from two of its filter lengths before the first such narrow gap outwards
   (:func:`_fine_pass_start`). The last rings before the bark are often narrower still (3 - 6 px), below what
   either pass resolves: between the last boundary and the disc edge (``bark_zone``), the profile's own sharp rises
   are boundaries when they reach 0.2 of the rises at the outermost boundaries found
   (:func:`.wood_edge.bark_zone_boundaries`; on the independent synthetic discs of
   :mod:`~torch_appearance.rings.synthetic_discs` this finds most of the 3 - 4 px rings the passes skip). With
   ``bark_gaps`` (off by default) the same rule looks inside the last gaps before the edge too, at most one boundary
   per gap (:func:`.wood_edge.gap_boundaries`; on the TRAS discs it found one skipped narrow ring on each, and on
   the synthetic light-bark disc it cost 0.006 at 3 px: ``docs/bench_log.md``).
   Boundaries closer than ``min_ring_px`` to the previous one are merged (the
   weaker is dropped). With ``include_edge`` the disc edge (outer end of the last ring, where CS-TRD, and CooRecorder
   users at a clean bark, put the last boundary) is appended as a boundary of kind ``"edge"`` when the transect
   reaches it; a boundary within 3 px inside it is the same boundary and gives way to it.
6. **Consistency across transects** (``link``). The transects cross the same years: every boundary is followed
   along its ring's ridge in a polar edge map to the neighbouring transects
   (:func:`~torch_appearance.rings.consistency.link_transects`), with ``helpers`` helper transects (default one)
   between each pair of neighbours as further evidence. Where the curves from both neighbours arrive together and
   the transect has no boundary within 0.3 of a ring, a boundary of kind ``"inferred"`` is added; where it has
   one within that but more than 3 px away, that boundary is moved onto the curves (``info["moved_px"]``).
   ``info["confirmed"]`` says which boundaries a neighbour's curve met. On the human-labelled TRAS discs (eight
   transects) this raises the radial F1 at 5 px from 0.85 to 0.90 (human pith); every inferred or moved boundary
   there lay on a human ring. Near the pith (within six ring periods) rings are also traced as closed curves round
   the disc (:func:`~torch_appearance.rings.consistency.closed_rings`): a closed ring is inferred where a
   transect has no boundary within half a ring period of it (``info["closed"]``), and boundaries between closed
   rings far from all of them that no neighbour confirms are dropped (``info["dropped_px"]``); on the TRAS discs
   with the automatic pith this
   raises the radial F1 at 5 px from 0.87 to 0.895 (re-measured leave-one-disc-out in issue 48: it gains on each
   disc alone, 0.875 -> 0.904 on C13C and 0.886 -> 0.917 on C17C with the automatic pith).
7. **Whole rings** (``whole_rings``, with ``link``). Every ring is traced round the disc as one closed curve,
   outwards one ring at a time, each above the last
   (:func:`~torch_appearance.rings.ring_polygons.trace_whole_rings`), seeded by the linked boundaries of all
   transects (helpers included); a boundary between the innermost and the second outermost ring that lies on none
   of them is dropped, and (``whole_place``, off by default) a ring is placed on a transect whose boundaries miss
   it (:func:`~torch_appearance.rings.ring_polygons.place_whole_rings`). These rings are the polygons of
   :func:`~torch_appearance.rings.ring_polygons.ring_polygons`. On the TRAS discs (dots inpainted) dropping
   raised the radial F1 at 5 px from 0.894 to 0.904 (C13C) and 0.897 to 0.916 (C17C) with the human pith, 0.865 to
   0.880 and 0.864 to 0.894 with the automatic one; placing gained 0.012 more on C13C and lost 0.017 on C17C (most
   of the rings it placed there were on no human ring), so it is off. On the independent synthetic discs neither
   changes a boundary. Figures: ``docs/bench_log.md`` (issue 48, whole rings).

8. **The pith's edge** (``pith_edge``, off by default). The pith, or the first year's wood round it, often ends in a
   sharp dark -> light step a few px out (on C13C 15 - 17 px, inside the quarter ring period where the transects
   find nothing), which people mark as the innermost boundary. It is found as one closed curve round the pith
   (:func:`~torch_appearance.rings.pith_region.pith_edge`: a polar edge map within half a ring period of the pith
   and a closed dynamic programme round it) and, when it is a rise round most of the circle as sharp as the rings
   nearby, put on every transect as ring 0 with the boundaries inside it dropped
   (:func:`~torch_appearance.rings.pith_region.place_pith_edge`). Leave-one-disc-out on the TRAS discs it gained on
   C13C and lost on C17C (there it found the 6 px edge of the dark pith, which the people marked on one transect of
   four), so it stays off; figures in ``docs/bench_log.md`` (issue 48, the pith's edge).

The cost is ``O(n_transects * R * (2 half_width + 1) * (p + q))`` (about 1.5 times that with the fine pass, twice
that again with one helper transect between neighbours) instead of ``O(n_transects * H W (p + q))``.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from ..checks import check_point_in_image
from .dendro import RingBoundaries, _cycle_boundaries, _gabor_params, _pixel_size, hsv_value, ring_widths_mm
from .gabor import curved_gabor
from .orientation import orientation_field
from .wood_edge import background_colour, bark_zone_boundaries, dark_bark_start, gap_boundaries, wood_colour_end

__all__ = ["DiscBoundaries", "detect_disc_boundaries", "polar_strip", "synthetic_disc", "transect_angles"]


@dataclass
class DiscBoundaries:
    """Ring boundaries along several transects of one disc.

    Attributes:
        pith: ``(2,)`` float64 ``(x, y)`` pith position in pixels.
        transects: list of :class:`~torch_appearance.rings.dendro.RingBoundaries`, one per transect, points
            ordered pith -> bark; ``info["kind"]`` is a list of ``"ring"`` / ``"inferred"`` (from the neighbouring
            transects) / ``"pith_edge"`` (the pith's own edge, ``pith_edge``) / ``"edge"`` per point,
            ``info["radius_px"]`` the distance of each point from the pith,
            ``info["confirmed"]`` (per ring or inferred point: a neighbour's ring curve met it) and
            ``info["moved_px"]`` (``(from, to)`` radii of boundaries moved onto their ring's curve),
            ``info["closed"]`` (per point: inferred from a closed ring round the pith), ``info["dropped_px"]``
            (radii dropped between closed rings) and ``info["closed_crossings_px"]`` (where the closed rings
            cross the transect).
        ends: ``(T, 2)`` end point ``(x, y)`` of each transect as analysed (cut at the disc edge or image border).
        angles_deg: ``(T,)`` transect directions in degrees (from +x towards +y, i.e. clockwise on screen).
        info: ``filtered_px`` (pixels passed to the Gabor filter, all transects), ``filter_calls``, background,
            ``pith`` (``auto``, ``xy``, ``sigma_px``: the automatic pith's jackknife standard error, or None),
            ``helpers_deg`` (the helper transects' angles), ``link_seconds`` (None when not linked), ``pith_edge``
            (None, or :func:`~torch_appearance.rings.pith_region.pith_edge`'s curve, support, contrast, ``found``).
    """

    pith: np.ndarray
    transects: list
    ends: np.ndarray
    angles_deg: np.ndarray
    info: dict = field(default_factory=dict)


#: the most helper transects between two neighbouring transects (each costs a transect's filtering)
MAX_HELPERS = 16
#: the strips either side of a transect, px of arc: their filtering's cost grows with 2 half_width + 1 (default 16)
MIN_HALF_WIDTH, MAX_HALF_WIDTH = 2, 200


def _number(value, name, lo=None, hi=None, *, integer=False):
    ok = not isinstance(value, bool) and isinstance(value, (int, np.integer) if integer else
                                                     (int, float, np.integer, np.floating))
    if ok and not integer:
        ok = math.isfinite(float(value))
    if ok and lo is not None:
        ok = value >= lo
    if ok and hi is not None:
        ok = value <= hi
    if not ok:
        rng = f" in [{lo if lo is not None else '-inf'}, {hi if hi is not None else 'inf'}]"
        raise ValueError(f"{name}: expected {'an integer' if integer else 'a finite number'}{rng}, got {value!r}")
    return value


def _check_pith(pith, shape):
    return np.array(check_point_in_image("pith", pith, shape))


def transect_angles(n: int, start_deg: float = 0.0) -> np.ndarray:
    """``n`` equally spaced transect angles in degrees, starting at ``start_deg`` (from +x towards +y)."""
    _number(n, "n", 1, integer=True)
    return (float(start_deg) + 360.0 * np.arange(n) / n) % 360.0


def _ray_length_to_border(pith, u, shape):
    """Distance from ``pith`` along unit ``u`` to the last in-image sample (pixel centres span [0, W-1])."""
    H, W = shape
    t = np.inf
    for p, d, hi in ((pith[0], u[0], W - 1), (pith[1], u[1], H - 1)):
        if d > 1e-12:
            t = min(t, (hi - p) / d)
        elif d < -1e-12:
            t = min(t, (0 - p) / d)
    return float(t)


def polar_strip(image, pith, angle_deg: float, length: float, half_width: int = 16):
    """Resample ``image`` on the polar strip of a transect (module docstring, step 1).

    Args:
        image: ``(H, W)`` or ``(H, W, C)`` numpy array.
        pith: ``(x, y)`` in pixels.
        angle_deg: transect direction in degrees from +x towards +y (clockwise on screen, y down).
        length: transect length in pixels (columns ``r = 0 .. floor(length)``).
        half_width: rows ``s = -half_width .. half_width`` (pixels of arc).

    Returns:
        ``(strip, X, Y)``: ``strip`` ``(2 half_width + 1, L[, C])`` float64 (bilinear; samples outside the image
        take the nearest border value) and the sample coordinates ``X, Y`` ``(2 half_width + 1, L)``.
    """
    a = np.asarray(image)
    chans = [a] if a.ndim == 2 else [a[..., c] for c in range(a.shape[2])]
    strip, X, Y = _polar_sample(chans, pith, angle_deg, length, half_width)
    return (strip[..., 0] if a.ndim == 2 else strip), X, Y


def _polar_sample(channels, pith, angle_deg, length, half_width):
    """:func:`polar_strip` of a list of ``(H, W)`` channel arrays: ``((S, L, C) float64, X, Y)``."""
    r = np.arange(0, int(math.floor(length)) + 1, dtype=np.float64)
    s = np.arange(-half_width, half_width + 1, dtype=np.float64)
    phi = math.radians(angle_deg) + s[:, None] / np.maximum(r[None, :], float(half_width))
    X = pith[0] + r[None, :] * np.cos(phi)
    Y = pith[1] + r[None, :] * np.sin(phi)
    out = [ndimage.map_coordinates(c, [Y, X], order=1, mode="nearest", output=np.float64) for c in channels]
    return np.stack(out, -1), X, Y


def _value(rgb):
    """The photo's HSV value ``(H, W)`` float32 from its ``(H, W, C)`` channels (C = 1: the channel itself)."""
    return hsv_value(rgb) if rgb.shape[2] >= 3 else np.asarray(rgb[..., 0], np.float32)


def _detrend(v):
    """The strip's V with its slow brightness trend along the radius removed (heartwood / sapwood, stains)."""
    return v - ndimage.gaussian_filter1d(v, max(32.0, v.shape[1] / 20.0), axis=1, mode="nearest")


def _pooled_period(strips, f_max, n_bins=64):
    """Dominant ring period (px) of several detrended strips ``(S, L_k)``: the peak of the sum over strips of each
    strip's normalised, frequency-weighted power spectrum along the radius (Hann window, rows averaged, 64
    log-spaced frequency bins from ``1 / min(400, max L)`` to ``f_max``)."""
    f_min = 1.0 / min(400.0, max(s.shape[1] for s in strips))
    edges = np.logspace(math.log10(f_min), math.log10(f_max), n_bins + 1)
    total = np.zeros(n_bins)
    for s in strips:
        L = s.shape[1]
        if L < 16:
            continue
        x = (s - s.mean(1, keepdims=True)) * np.hanning(L)[None, :]
        power = (np.abs(np.fft.rfft(x, axis=1)) ** 2).mean(0)
        f = np.fft.rfftfreq(L)
        idx = np.searchsorted(edges, f, side="right") - 1
        ok = (idx >= 0) & (idx < n_bins)
        sums = np.bincount(idx[ok], weights=(power * f)[ok], minlength=n_bins)
        counts = np.bincount(idx[ok], minlength=n_bins)
        spec = np.where(counts > 0, sums / np.maximum(counts, 1), 0.0)
        # bins finer than this strip's frequency resolution get the value of the nearest filled bin
        filled = np.nonzero(counts)[0]
        if len(filled) == 0 or spec.sum() <= 0:
            continue
        spec = spec[filled[np.abs(np.arange(n_bins)[:, None] - filled[None, :]).argmin(1)]]
        total += spec / spec.sum()
    if not total.any():
        return None
    k = int(np.argmax(total))
    return 1.0 / math.sqrt(edges[k] * edges[k + 1])


def _strip_orientation(v, max_tilt_deg):
    """Ring orientation ``(S, L)`` float32 of a strip: rings run along its columns (vertical) up to the tilt of
    eccentric rings, so the orientation field is clamped to ``max_tilt_deg`` from vertical, and cracks, rays or
    stains along the transect cannot turn the filter."""
    theta, _ = orientation_field(v.astype(np.float32))
    dev = theta.astype(np.float64) - math.pi / 2  # theta in [0, pi): dev in [-pi/2, pi/2)
    lim = math.radians(max_tilt_deg)
    return (math.pi / 2 + np.clip(dev, -lim, lim)).astype(np.float32)


def _strip_boundaries(v, wood, *, period, p_periods, band, p, q, f_max, min_rel_rise, edge_level, tilt_sigma,
                      max_tilt_deg, device, num_workers, calls, mag_weight=True, highpass=1.0, theta=None):
    """Boundaries (column positions) on a filled strip ``v`` ``(S, L)`` with wood weights ``wood`` ``(S, L)``;
    ``period`` is the ring period (px) that sets the default ``p = p_periods period`` and ``q = period``. The filter
    sees ``v`` less its Gaussian blur along the radius (sigma ``highpass period``; 0: the raw strip), so that its
    local frequency follows the rings rather than brightness trends across its window. ``theta``: the strip's
    :func:`_strip_orientation`, when the caller has it already."""
    S, L = v.shape
    if period is None:  # the strip's own estimate, on the detrended strip
        _, _, period = _gabor_params(_detrend(v).astype(np.float32), p, q, f_max)
    if p is None:
        p = int(np.clip(round(p_periods * period), 8, 150))
    if q is None:
        q = int(np.clip(round(period), 2, 40))
    q = min(q, max(1, S // 2 - 1))
    if theta is None:
        theta = _strip_orientation(v, max_tilt_deg)
    calls.append(v.shape)
    vf = v - ndimage.gaussian_filter1d(v, highpass * period, axis=1, mode="nearest") if highpass > 0 else v
    # the refined orientation (from the phase image) is not read here: not computed
    res = curved_gabor(vf.astype(np.float32), theta=theta, p=p, q=q, freq_range=(1.0 / p, f_max),
                       normal_reference=(1.0, 0.0), device=device, num_workers=num_workers, refine_orientation=False)
    yc = (S - 1) / 2.0
    half = max(0.5, band * S / 2.0)
    rows = np.arange(S)[np.abs(np.arange(S) - yc) <= half]
    # local ring tilt per column: doubled-angle mean over the central rows, smoothed along the radius
    th = res.theta.astype(np.float64)[rows]
    w = res.magnitude.astype(np.float64)[rows] * wood[rows]
    c2 = ndimage.gaussian_filter1d((w * np.cos(2 * th)).sum(0), tilt_sigma * period, mode="nearest")
    s2 = ndimage.gaussian_filter1d((w * np.sin(2 * th)).sum(0), tilt_sigma * period, mode="nearest")
    mth = 0.5 * np.arctan2(s2, c2) % math.pi
    sin_m = np.sin(mth)
    shear = np.cos(mth) / np.maximum(np.abs(sin_m), 0.2) * np.where(sin_m < 0, -1.0, 1.0)
    xs = np.arange(L, dtype=np.float64)
    coords_x = xs[None, :] + (rows[:, None] - yc) * shear[None, :]
    coords_y = np.broadcast_to(rows[:, None].astype(np.float64), coords_x.shape)
    sample = lambda f: ndimage.map_coordinates(f, [coords_y, coords_x], order=1, mode="nearest")  # noqa: E731
    wt = sample(wood) + 1e-6
    if mag_weight:
        # rows where the rings are clear count more: weight by the Gabor amplitude, smoothed along the radius
        mg = ndimage.gaussian_filter1d(res.magnitude.astype(np.float64), period, axis=1, mode="nearest")
        wt = wt * sample(mg) ** 2
    z = res.magnitude * np.exp(1j * res.phase)
    norm = wt.sum(0)
    v_prof = (sample(v) * wt).sum(0) / norm
    z_prof = ((sample(z.real) + 1j * sample(z.imag)) * wt).sum(0) / norm
    f_prof = (sample(res.frequency.astype(np.float64)) * wt).sum(0) / norm
    pos = _cycle_boundaries(v_prof, z_prof, min_rel_rise=min_rel_rise, edge_level=edge_level)
    return pos, dict(period_px=period, p=p, q=q, shear=shear, profile_v=v_prof, profile_z=z_prof,
                     local_period_px=1.0 / f_prof)


def _fine_pass_start(coarse, end, narrow_px, margin_px):
    """First strip column the fine pass needs: ``margin_px`` before the first gap narrower than ``narrow_px`` among
    the coarse boundaries (the pith at 0 and ``end`` close the list); ``end`` when there is none."""
    edges = np.r_[0.0, np.asarray(coarse, np.float64), float(end)]
    narrow = np.nonzero(np.diff(edges) < narrow_px)[0]
    start = edges[narrow[0]] if len(narrow) else float(end)
    return int(max(0, math.floor(start - margin_px)))


def _narrow_ring_boundaries(coarse, fine, *, period, fine_period, end, narrow_gap=0.8, same=0.15, margin=0.25):
    """Boundaries of the fine pass that the coarse one missed where the rings are narrow (both ``(K,)`` sorted
    column positions; ``end`` the strip's outer end). A fine boundary is added when no coarse boundary lies within
    ``same fine_period`` of it, the two coarse boundaries around it (the pith at 0 and ``end`` close the list) are
    less than ``narrow_gap period`` apart - one coarse cycle that spans two or more narrow rings - and it lies at
    least ``margin`` of that gap from both. In wide rings the fine pass's extra cycles (pores, earlywood texture)
    fall in coarse gaps wider than that and are not taken."""
    coarse = np.asarray(coarse, np.float64)
    if len(fine) == 0:
        return coarse
    add = []
    for x in fine:
        if len(coarse) and np.abs(coarse - x).min() < same * fine_period:
            continue
        j = int(np.searchsorted(coarse, x))
        a = coarse[j - 1] if j > 0 else 0.0
        b = coarse[j] if j < len(coarse) else float(end)
        gap = b - a
        if gap < narrow_gap * period and min(x - a, b - x) >= margin * gap:
            add.append(x)
    return np.sort(np.r_[coarse, add])


def _merge_close(pos, v_prof, min_gap):
    """Drop boundaries closer than ``min_gap`` to the previous kept one (keep the one with the larger V rise)."""
    if len(pos) < 2 or min_gap <= 0:
        return pos
    dv = np.gradient(ndimage.gaussian_filter1d(v_prof, 1.0))
    strength = dv[np.clip(np.round(pos).astype(int), 0, len(dv) - 1)]
    keep = [0]
    for i in range(1, len(pos)):
        if pos[i] - pos[keep[-1]] < min_gap:
            if strength[i] > strength[keep[-1]]:
                keep[-1] = i
        else:
            keep.append(i)
    return pos[np.array(keep)]


def detect_disc_boundaries(image, pith, *, angles_deg=None, ends=None, half_width: int = 16, band: float = 1.0,
                           include_edge: bool = False, background=None, background_tol: float = 0.1,
                           min_ring_px: float = 0.0, max_radius: float | None = None, dpi=None,
                           pixel_size_mm=None, p: int | None = None, q: int | None = None, f_max: float = 0.4,
                           min_rel_rise: float = 0.1, edge_level: float = 1.0, tilt_sigma: float = 2.0,
                           max_tilt_deg: float = 40.0, mag_weight: bool = True, period_px: float | None = None,
                           p_periods: float = 2.0, highpass_periods: float = 1.0, fine_scale: float | None = 0.5,
                           narrow_gap: float = 0.8, link: bool = True, helpers: int = 1, closed: bool = True,
                           bark_zone: bool = True, whole_rings: bool = True, whole_place: bool = False,
                           whole_drop: bool = True, whole_min_support: float = 0.5, pith_edge: bool = False,
                           pith_edge_min_support: float = 0.75, bark_level: float | None = None,
                           bark_gaps: int = 0, device="cpu",
                           num_workers: int | None = None, progress=None) -> DiscBoundaries:
    """Ring boundaries along several pith -> bark transects of a disc photo (module docstring).

    Args:
        image: ``(H, W, 3)`` RGB in ``[0, 1]`` (sRGB values) or ``(H, W)`` gray numpy array.
        pith: ``(x, y)`` pith position in pixels (inside the image), or ``"auto"``: found from the ring orientation
            field (:func:`~torch_appearance.rings.pith.detect_pith`; ``info["pith"]`` holds the estimate and its
            uncertainty).
        angles_deg: transect directions in degrees from +x towards +y (0 = right, 90 = down on screen); each runs
            from the pith to the disc edge (or the image border / ``max_radius``).
        ends: ``(T, 2)`` transect end points ``(x, y)`` in pixels (inside the image); each transect runs from the
            pith to its end point (cut earlier at the disc edge). Angles and ends may be combined (angles first).
            Neither: four transects at 0, 90, 180, 270 degrees.
        half_width: strip half-width in pixels of arc (rows ``2 half_width + 1``).
        band: fraction of the strip's rows (around the transect) averaged for the profile.
        mag_weight: weight the rows by the squared Gabor amplitude (else only by the wood mask).
        include_edge: append the disc edge as the last boundary (kind ``"edge"``) when the transect reaches it.
        background: background colour ``(3,)`` in [0, 1] (default: median of the image border when the border
            is uniform, else none); pixels within ``background_tol`` of it are not wood.
        min_ring_px: boundaries closer than this (px) to the previous one are merged; 0 keeps all.
        max_radius: optional cap on the transect length (px).
        dpi, pixel_size_mm: pixel size for the ring widths in mm (at most one).
        p, q, f_max, min_rel_rise, edge_level: as in :func:`~torch_appearance.rings.dendro.detect_core_boundaries`
            (``p = p_periods P``, ``q = P`` by default, ``P`` the ring period), except that ``edge_level`` is 1 by
            default: the steepest point of the latewood -> earlywood step, where people click (on the human
            transects of ``scripts/eval/eval_disc_human.py`` the matched boundaries sit a median 0.08 px from the
            clicks with 1, and 1.29 px on the pith side with 0.8).
        p_periods: default ``p`` in ring periods.
        highpass_periods: the filter sees the strip less its blur along the radius with sigma this many ring periods
            (0: the raw strip); its local frequency then follows the rings, not the brightness trend in its window.
        fine_scale: a second pass at ``fine_scale P`` adds the narrow rings the first one missed (module docstring,
            step 5); None: one pass. Ignored when ``p`` or ``q`` is given.
        narrow_gap: the second pass's boundaries are taken only between first-pass boundaries less than
            ``narrow_gap P`` apart.
        link: follow every boundary's ring curve to the neighbouring transects and infer the rings that two
            neighbours' curves agree on (module docstring, step 6; :mod:`~torch_appearance.rings.consistency`).
            Needs three transects or more, helpers included.
        bark_zone: look for the narrow rings just inside the bark, between the last boundary and the wood's edge,
            as steps of the profile (:func:`.wood_edge.bark_zone_boundaries`); only where the edge is found.
        closed: with ``link``, also trace the rings near the pith as closed curves round the disc (module docstring,
            step 6); False: only the curves between neighbouring transects.
        whole_rings: with ``link``, trace every ring round the disc as a closed curve
            (:func:`~torch_appearance.rings.ring_polygons.trace_whole_rings`, module docstring step 7): the rings
            of ``ring_polygons``; then ``whole_drop``: a boundary between whole rings that lies on none of them is
            dropped (``info["dropped_px"]``), ``whole_place``: a whole ring is placed on a transect whose boundaries
            miss it (kind ``"inferred"``, ``info["whole"]``; off by default: leave-one-disc-out it helped C13C and
            hurt C17C); only rings found on at least ``whole_min_support`` of the transects act so
            (:func:`~torch_appearance.rings.ring_polygons.place_whole_rings`).
        pith_edge: find the pith's own edge as a closed curve round the pith
            (:func:`~torch_appearance.rings.pith_region.pith_edge`, module docstring step 8) and, when it is found
            (a rise round at least ``pith_edge_min_support`` of the circle, as sharp as the rings nearby), put it on
            every transect as its innermost boundary (kind ``"pith_edge"``) and drop the boundaries inside it
            (``info["dropped_px"]``); ``info["pith_edge"]`` holds the curve. Off by default: leave-one-disc-out on
            the TRAS discs it gained on C13C (whose people marked the pith's edge) and lost on C17C (whose people did
            not, on 3 of 4 transects).
        bark_level: where there is no uniform background, the wood ends this fraction of the way down the fall of
            brightness from the wood into the bark (:func:`.wood_edge.wood_colour_end`); None: at the steepest
            point of the fall. Off by default (issue 48 item 3, measured leave-one-disc-out: ``docs/bench_log.md``).
        bark_gaps: in each of this many gaps before the wood's edge, a narrow ring the passes skipped is added where
            the profile rises sharply inside the gap (:func:`.wood_edge.gap_boundaries`, at most one per gap); 0:
            none (the default; measured leave-one-disc-out: ``docs/bench_log.md``).
        helpers: with ``link``, this many helper transects between each pair of neighbouring transects (evenly
            spaced in angle): filtered like the others, their boundaries serve as evidence and are not returned
            (``info["helpers_deg"]``). 0: the transects link only to each other.
        period_px: ring period ``P`` (px) for ``p`` / ``q``; default: the dominant period pooled over all strips
            (module docstring, step 3).
        tilt_sigma: smoothing of the local ring tilt along the radius, in ring periods.
        max_tilt_deg: largest ring tilt in the strip (degrees from the radial normal); the orientation field is
            clamped to it (cracks, rays and stains along the transect would otherwise turn the filter).
        device, num_workers: passed to the curved Gabor filter.
        progress: optional callable ``progress(k, T)`` called after each transect (helpers included in ``T``).

    Returns:
        :class:`DiscBoundaries`.

    Raises:
        ValueError / TypeError: bad image, pith outside the image, an end point outside the image or a transect
            of (nearly) zero length, bad parameters.

    Example:
        >>> # res = detect_disc_boundaries(rgb, (1520, 1610), angles_deg=[0, 90, 180, 270], dpi=600)
        >>> # res.transects[0].points  # (N, 2) x, y
    """
    ps = _pixel_size(dpi, pixel_size_mm)
    _number(half_width, "half_width", MIN_HALF_WIDTH, MAX_HALF_WIDTH, integer=True)
    _number(band, "band", 1e-6, 1.0)
    _number(background_tol, "background_tol", 0.0, 2.0)
    _number(min_ring_px, "min_ring_px", 0.0)
    _number(tilt_sigma, "tilt_sigma", 1e-3)
    _number(max_tilt_deg, "max_tilt_deg", 0.0, 89.0)
    if max_radius is not None:
        _number(max_radius, "max_radius", 2.0)
    if period_px is not None:
        _number(period_px, "period_px", 2.0)
    _number(p_periods, "p_periods", 0.5, 10.0)
    _number(highpass_periods, "highpass_periods", 0.0, 100.0)
    if fine_scale is not None:
        _number(fine_scale, "fine_scale", 0.05, 0.95)
    _number(narrow_gap, "narrow_gap", 0.0, 10.0)
    _number(helpers, "helpers", 0, MAX_HELPERS, integer=True)
    _number(whole_min_support, "whole_min_support", 0.0, 1.0)
    _number(pith_edge_min_support, "pith_edge_min_support", 0.0, 1.0)
    if bark_level is not None:
        _number(bark_level, "bark_level", 0.0, 1.0)
    _number(bark_gaps, "bark_gaps", 0, 50, integer=True)
    for name, flag in (("link", link), ("closed", closed), ("bark_zone", bark_zone), ("whole_rings", whole_rings),
                       ("whole_place", whole_place), ("whole_drop", whole_drop), ("pith_edge", pith_edge)):
        if not isinstance(flag, bool):
            raise TypeError(f"{name}: expected a bool, got {type(flag).__name__}")
    trace_closed = closed  # (the name ``closed`` holds the per-transect flags below)
    if not isinstance(include_edge, bool):
        raise TypeError(f"include_edge must be a bool; got {type(include_edge).__name__}")
    a = np.asarray(image)
    if a.dtype.kind not in "fiub":
        raise TypeError(f"image must hold real numbers; got dtype {a.dtype}")
    if not (a.ndim == 2 or (a.ndim == 3 and a.shape[2] in (1, 3, 4))) or min(a.shape[:2]) < 4:
        raise ValueError(f"image must have shape (H, W) or (H, W, 3) with H, W >= 4; got {a.shape}")
    rgb = a[..., :3] if a.ndim == 3 and a.shape[2] >= 3 else (a if a.ndim == 3 else a[..., None])
    if rgb.dtype.kind != "f":
        rgb = rgb.astype(np.float32)
    # one contiguous copy per channel, shared by all strips (no float64 copy of the whole photo; the values are
    # checked for NaN / inf on the strips that are actually sampled)
    chans = [np.ascontiguousarray(rgb[..., c]) for c in range(rgb.shape[2])]
    H, W = a.shape[:2]
    pith_info = None
    if isinstance(pith, str):
        if pith != "auto":
            raise ValueError(f"pith: expected (x, y) in pixels or 'auto', got {pith!r}")
        from .pith import detect_pith
        # the pith is found on the photo's HSV value (detect_pith's own first step), kept for the linking below
        value = _value(rgb)
        estimate = detect_pith(value)
        pith = estimate.xy
        pith_info = dict(auto=True, xy=estimate.xy.copy(), sigma_px=estimate.sigma_px)
    else:
        value = None
    c = _check_pith(pith, (H, W))
    dirs = []  # (angle_deg, requested length)
    if angles_deg is not None:
        ang = np.atleast_1d(np.asarray(angles_deg, dtype=np.float64))
        if ang.ndim != 1 or not np.isfinite(ang).all():
            raise ValueError(f"angles_deg must be a sequence of finite numbers; got {angles_deg!r}")
        dirs += [(float(t) % 360.0, None) for t in ang]
    if ends is not None:
        e = np.asarray(ends, dtype=np.float64)
        if e.ndim == 1 and e.size == 2:
            e = e[None]
        if e.ndim != 2 or e.shape[1] != 2 or not np.isfinite(e).all():
            raise ValueError(f"ends: expected shape (T, 2) of finite (x, y) pixels, got shape {e.shape}")
        for i, (x, y) in enumerate(e):
            check_point_in_image(f"ends[{i}]", (x, y), (H, W))
            length = math.hypot(x - c[0], y - c[1])
            if length < 2.0:
                raise ValueError(f"ends[{i}]: expected a transect of length >= 2 px from the pith "
                                 f"({c[0]:g}, {c[1]:g}), got ({x:g}, {y:g}) (nearly zero length)")
            dirs.append((math.degrees(math.atan2(y - c[1], x - c[0])) % 360.0, length))
    if not dirs:
        dirs = [(t, None) for t in transect_angles(4)]
    n_req = len(dirs)
    if link and helpers:  # helper transects, evenly spaced between neighbouring transects, as evidence only
        srt = sorted({d for d, _ in dirs})
        for i, a0 in enumerate(srt):
            gap = (srt[(i + 1) % len(srt)] - a0) % 360.0 or 360.0
            dirs += [((a0 + gap * (k + 1) / (helpers + 1)) % 360.0, None) for k in range(helpers)]
    if background is None:
        bg = background_colour(rgb, background_tol)
    else:
        bg = np.asarray(background, dtype=np.float64).reshape(-1)
        if bg.shape != (rgb.shape[2],) or not np.isfinite(bg).all():
            raise ValueError(f"background must be {rgb.shape[2]} finite numbers; got {background!r}")
    prepared = []  # pass 1: strips, wood masks, disc edges (no filtering)
    for deg, req in dirs:
        th = math.radians(deg)
        u = np.array([math.cos(th), math.sin(th)])
        length = _ray_length_to_border(c, u, (H, W)) if req is None else req
        if max_radius is not None:
            length = min(length, float(max_radius))
        if length < 2.0:
            raise ValueError(f"transect at {deg:g} deg from the pith ({c[0]:g}, {c[1]:g}) has (nearly) zero length "
                             f"inside the image")
        strip, X, Y = _polar_sample(chans, c, deg, length, half_width)
        if not np.isfinite(strip).all():
            raise ValueError(f"image contains NaN or infinite values along the transect at {deg:g} deg")
        inside = (X >= -0.5) & (X <= W - 0.5) & (Y >= -0.5) & (Y <= H - 0.5)
        # background by colour on the strip smoothed over about a pixel: the noise of single pixels (sensor, JPEG)
        # would otherwise turn background into "wood" (and light earlywood into background) by chance
        wood = inside if bg is None else (np.linalg.norm(
            ndimage.gaussian_filter(strip, (1.0, 1.0, 0.0), mode="nearest") - bg, axis=2) > background_tol) & inside
        S, L = wood.shape
        yc = (S - 1) // 2
        central = wood[max(0, yc - S // 4):yc + S // 4 + 1].mean(0)
        frac = ndimage.uniform_filter1d(central, 5, mode="nearest")
        woody = np.nonzero(frac >= 0.5)[0]
        edge = None
        if len(woody) == 0:
            prepared.append((deg, u, None, None, None, 0))
            continue
        last = int(woody[-1])
        if bg is None and strip.shape[2] >= 3:  # no uniform background: the wood ends where its colour does
            end = wood_colour_end(strip[max(0, yc - S // 4):yc + S // 4 + 1], fall_level=bark_level)
            if end is not None and end < last:
                last = end
                frac = frac.copy()
                frac[end + 1:] = 0.0
        elif bg is not None and strip.shape[2] >= 3:  # a dark bark between the wood and the background
            end = dark_bark_start(strip[max(0, yc - S // 4):yc + S // 4 + 1, :last + 1])
            if end is not None and end < last:
                last = end
                frac = frac.copy()
                frac[end + 1:] = 0.0
        if last < L - 3:  # the wood ends before the transect does: the disc edge
            nxt = min(last + 1, L - 1)
            a_, b_ = frac[last], frac[nxt]
            edge = last + ((a_ - 0.5) / (a_ - b_) if a_ > b_ else 0.0)
        Lc = min(L, last + 1)
        v = hsv_value(strip[:, :Lc].astype(np.float32)).astype(np.float64) if strip.shape[2] >= 3 else \
            strip[:, :Lc, 0]
        wd = wood[:, :Lc].astype(np.float64)
        # fill non-wood pixels along the ring (mean of the column's wood pixels; columns without wood: interpolate)
        cnt = wd.sum(0)
        colmean = np.where(cnt > 0, (v * wd).sum(0) / np.maximum(cnt, 1), np.nan)
        good = np.isfinite(colmean)
        colmean = np.interp(np.arange(Lc), np.nonzero(good)[0], colmean[good])
        v = np.where(wd > 0, v, colmean[None, :])
        prepared.append((deg, u, v, wd, edge, Lc))
    # one ring period for all transects, pooled over the strips (a single strip's estimate is easily pulled to
    # the scale of heartwood / stain patterns); period_px overrides it
    period = period_px if period_px is not None else _pooled_period(
        [_detrend(v) for _, _, v, _, _, Lc in prepared if v is not None and Lc >= 16], f_max)
    calls, found = [], []
    for k, (deg, u, v, wd, edge, Lc) in enumerate(prepared):  # pass 2: filter each strip once, find boundaries
        pos, sinfo = np.zeros(0), {}
        if v is not None and Lc >= 16:
            common = dict(p_periods=p_periods, band=band, f_max=f_max, min_rel_rise=min_rel_rise,
                          edge_level=edge_level, tilt_sigma=tilt_sigma, max_tilt_deg=max_tilt_deg, device=device,
                          mag_weight=mag_weight, num_workers=num_workers, calls=calls, highpass=highpass_periods,
                          theta=_strip_orientation(v, max_tilt_deg))  # one orientation field for both passes
            pos, sinfo = _strip_boundaries(v, wd, period=period, p=p, q=q, **common)
            # the pith is not a ring boundary: nothing within a quarter ring period of it (the strip's rows also
            # converge there, which makes the first samples unreliable)
            pos = pos[pos >= max(3.0, 0.25 * sinfo["period_px"])]
            end = edge if edge is not None else Lc - 1
            if edge is not None:
                # the wood -> background step at the disc edge is not a ring boundary, and the last ring boundary
                # coincides with the edge when it lies within 2 px of it (a gap ending there is a ring's width)
                pos = pos[pos < edge - 2.0]
            if fine_scale is not None and p is None and q is None:
                fine_period = fine_scale * sinfo["period_px"]
                # the fine pass only adds boundaries inside gaps narrower than narrow_gap P: it filters the strip
                # from two filter lengths before the first such gap on (the same responses there, less work)
                c0 = _fine_pass_start(pos, end, sinfo["period_px"] * narrow_gap,
                                      2 * int(np.clip(round(p_periods * fine_period), 8, 150)))
                fcommon = dict(common, theta=common["theta"][:, c0:])
                fpos, finfo = _strip_boundaries(v[:, c0:], wd[:, c0:], period=fine_period, p=None, q=None,
                                                **fcommon) if Lc - c0 >= 16 else (np.zeros(0), dict(p=None, q=None))
                fpos = fpos + c0
                fpos = fpos[(fpos >= max(3.0, 0.25 * fine_period, c0 + (0.0 if c0 == 0 else 2 * fine_period)))
                            & (fpos < end - 2.0)]
                n_coarse = len(pos)
                pos = _narrow_ring_boundaries(pos, fpos, period=sinfo["period_px"], fine_period=fine_period,
                                              end=end, narrow_gap=narrow_gap)
                sinfo.update(fine_period_px=fine_period, fine_p=finfo["p"], fine_q=finfo["q"],
                             narrow_added=len(pos) - n_coarse)
            if bark_zone and edge is not None:
                extra = bark_zone_boundaries(pos, sinfo["profile_v"], edge)
                sinfo["bark_zone_added"] = len(extra)
                pos = np.sort(np.r_[pos, extra])
            pos = _merge_close(pos, sinfo["profile_v"], min_ring_px)
        found.append((pos, sinfo))
        if progress is not None:
            progress(k + 1, len(dirs))
    inferred = [np.zeros(len(f[0]), bool) for f in found]
    confirmed = [np.zeros(len(f[0]), bool) for f in found]
    moved = [[] for _ in found]
    closed = [np.zeros(len(f[0]), bool) for f in found]
    closed_x = [np.zeros(0) for _ in found]
    dropped = [[] for _ in found]
    whole = [np.zeros(len(f[0]), bool) for f in found]
    pithed = [np.zeros(len(f[0]), bool) for f in found]  # the pith's edge placed (pith_edge)
    # the per-boundary flags of every transect, which follow its boundaries wherever some are added or dropped
    flags = {"inferred": inferred, "confirmed": confirmed, "closed": closed, "whole": whole, "pith_edge": pithed}

    def insert(k, new, keep=None, marked=()):
        """Transect ``k`` keeps its boundaries where ``keep`` (bool mask; default all) and gains ``new`` (px), in
        order of radius; its flags follow, the new boundaries' True for the flags named in ``marked``; the ones not
        kept are recorded as dropped."""
        pos0 = found[k][0]
        keep = np.ones(len(pos0), bool) if keep is None else keep
        o = np.argsort(np.r_[pos0[keep], new], kind="stable")
        found[k] = (np.r_[pos0[keep], new][o], found[k][1])
        for name, per_transect in flags.items():
            per_transect[k] = np.r_[np.asarray(per_transect[k], bool)[keep], np.full(len(new), name in marked)][o]
        dropped[k] = list(dropped[k]) + pos0[~keep].tolist()

    link_s, rings_polar, whole_s = None, None, None
    usable = [k for k, (pos, sinfo) in enumerate(found) if sinfo]
    if link and len(usable) >= 3:
        from .consistency import blurred_value, link_transects
        t0 = time.perf_counter()
        # one blurred value for the linking and the whole rings (both read it so)
        vb = blurred_value(_value(rgb) if value is None else value)
        lengths = [prepared[k][4] if prepared[k][4] is not None else prepared[k][5] - 1 for k in usable]
        linked = link_transects(vb, c, [dirs[k][0] for k in usable], [found[k][0] for k in usable], lengths,
                                period_px=found[usable[0]][1]["period_px"], closed_px=None if trace_closed else 0.0,
                                value_blurred=True)
        for k, lk in zip(usable, linked):
            found[k] = (lk["radius_px"], found[k][1])
            inferred[k], confirmed[k], moved[k] = lk["inferred"], lk["confirmed"], lk["moved"]
            closed[k], closed_x[k], dropped[k] = lk["closed"], lk["closed_crossings"], lk["dropped"]
            whole[k], pithed[k] = np.zeros(len(lk["radius_px"]), bool), np.zeros(len(lk["radius_px"]), bool)
        # the traced curves between neighbouring transects (helpers included), for whole rings
        # (:func:`~torch_appearance.rings.ring_polygons.ring_polygons`)
        rings_polar = dict(angles_deg=[dirs[k][0] for k in usable], radii=[lk["radius_px"] for lk in linked],
                           curves=[lk["curves"] for lk in linked], period_px=found[usable[0]][1]["period_px"],
                           lengths_px=lengths, whole=None)
        link_s = time.perf_counter() - t0
        if whole_rings:
            from .ring_polygons import place_whole_rings, trace_whole_rings
            period = found[usable[0]][1]["period_px"]
            wr = trace_whole_rings(vb, c, rings_polar["angles_deg"], [found[k][0] for k in usable], lengths,
                                   period_px=period, value_blurred=True)
            rings_polar["whole"] = wr
            for i, k in enumerate(usable):
                keep, new = place_whole_rings(found[k][0], wr["crossings"][i], inner_px=0.5 * period,
                                              length_px=lengths[i], place=whole_place, drop=whole_drop,
                                              support=wr["support"], min_support=whole_min_support)
                insert(k, new, keep, marked=("inferred", "whole"))
            whole_s = wr["seconds"]
    pith_region = None
    if pith_edge and usable:
        from .pith_region import pith_edge as find_pith_edge, place_pith_edge
        value = _value(rgb) if value is None else value  # the automatic pith's, when it was found here
        pe = find_pith_edge(value, c, [dirs[k][0] for k in usable], [found[k][0] for k in usable],
                            period_px=found[usable[0]][1]["period_px"], min_support=pith_edge_min_support)
        pith_region = {k_: v_ for k_, v_ in pe.items() if k_ != "crossings"}
        if pe["found"]:
            for i, k in enumerate(usable):
                keep, new = place_pith_edge(found[k][0], pe["crossings"][i])
                insert(k, new, keep, marked=("pith_edge",))
    if bark_gaps:  # narrow rings skipped near the bark (wood_edge.gap_boundaries), on the transects returned
        for k in range(n_req):
            edge_k, (pos0, sinfo_k) = prepared[k][4], found[k]
            if edge_k is None or "profile_v" not in sinfo_k:
                continue
            new = gap_boundaries(pos0, sinfo_k["profile_v"], edge_k, gaps=bark_gaps)
            if len(new):
                insert(k, new)
    out, ends_out = [], []
    for k in range(n_req):
        deg, u, v, wd, edge, Lc = prepared[k]
        pos, sinfo = found[k]
        sinfo = dict(sinfo)
        if v is None:
            out.append(RingBoundaries(points=np.zeros((0, 2)), widths_px=np.zeros(0), widths_mm=np.zeros(0),
                                      pixel_size_mm=ps, info=dict(kind=[], radius_px=np.zeros(0), angle_deg=deg)))
            ends_out.append(c.copy())
            continue
        kinds = ["pith_edge" if pe_ else "inferred" if f else "ring" for f, pe_ in zip(inferred[k], pithed[k])]
        conf, clos, wh = np.asarray(confirmed[k], bool), np.asarray(closed[k], bool), np.asarray(whole[k], bool)
        if include_edge and edge is not None:
            # the wood's edge is the last ring's outer boundary; a boundary within 3 px inside it (a ring step or
            # an inferred ring found there) is that same boundary and takes its place
            near = pos > edge - 3.0
            kinds = [k_ for k_, n_ in zip(kinds, near) if not n_] + ["edge"]
            pos, conf, clos, wh = np.r_[pos[~near], edge], conf[~near], clos[~near], wh[~near]
        pts = c[None, :] + pos[:, None] * u[None, :]
        wpx, wmm = ring_widths_mm(pts, ps)
        sinfo.update(kind=kinds, radius_px=pos.copy(), angle_deg=deg, edge_px=edge, length_px=float(Lc - 1),
                     confirmed=conf.tolist(), moved_px=list(moved[k]), closed=clos.tolist(),
                     closed_crossings_px=closed_x[k].copy(), dropped_px=list(dropped[k]), whole=wh.tolist())
        out.append(RingBoundaries(points=pts.reshape(-1, 2), widths_px=wpx, widths_mm=wmm, pixel_size_mm=ps,
                                  info=sinfo))
        ends_out.append(c + (Lc - 1) * u)
    info = dict(filtered_px=int(sum(s[0] * s[1] for s in calls)), filter_calls=len(calls), background=bg,
                image_px=H * W, pith=pith_info or dict(auto=False, xy=c.copy(), sigma_px=None),
                helpers_deg=np.array([d for d, _ in dirs[n_req:]]), link_seconds=link_s, whole_rings_seconds=whole_s,
                rings_polar=rings_polar, pith_edge=pith_region)
    return DiscBoundaries(pith=c, transects=out, ends=np.array(ends_out).reshape(-1, 2),
                          angles_deg=np.array([d for d, _ in dirs[:n_req]]), info=info)


def synthetic_disc(size=(320, 300), pith=(150.0, 160.0), widths=None, *, ecc=0.06, ecc_angle=0.7, noise=0.02,
                   background=(1.0, 1.0, 1.0), seed=0, ss=3):
    """A synthetic disc photo with known rings: ``(rgb, boundary_radius)``.

    Ring ``k``'s outer boundary is the closed curve ``r = B_k (1 + ecc cos(phi - ecc_angle))`` around ``pith``
    (``B_k`` the cumulative ``widths``); each ring is light earlywood fading slowly and the last 35 % darkening to
    latewood, then a sharp step up at the boundary (as in real conifer rings). The last boundary is the disc edge:
    the background colour outside it. Rendered with ``ss`` x ``ss`` supersampling plus Gaussian noise.

    Args:
        size: ``(H, W)`` in pixels.
        pith: ``(x, y)`` in pixels.
        widths: ring widths in pixels, pith -> bark (default: 12 rings from 14 px down to 7 px).
        ecc: relative eccentricity of the rings; ``ecc_angle`` its direction (radians).

    Returns:
        ``rgb`` ``(H, W, 3)`` float32 in [0, 1]; ``boundary_radius(phi)``: a function returning the ``(K,)`` true
        boundary radii (px from the pith, the last one the disc edge) along direction ``phi`` (radians, from +x
        towards +y).
    """
    H, W = size
    widths = np.linspace(14, 7, 12) if widths is None else np.asarray(widths, dtype=np.float64)
    B = np.cumsum(widths)
    rng = np.random.default_rng(seed)
    o = (np.arange(ss) + 0.5) / ss - 0.5
    yy = (np.arange(H)[:, None] + o[None, :]).reshape(-1)
    xx = (np.arange(W)[:, None] + o[None, :]).reshape(-1)
    X, Y = np.meshgrid(xx, yy)
    dx, dy = X - pith[0], Y - pith[1]
    rho = np.hypot(dx, dy) / (1 + ecc * np.cos(np.arctan2(dy, dx) - ecc_angle))
    k = np.searchsorted(B, rho, side="right")
    start = np.r_[0.0, B][np.minimum(k, len(B))]
    wk = np.r_[widths, widths[-1]][np.minimum(k, len(widths))]
    frac = np.clip((rho - start) / wk, 0, 1)
    late = 0.35
    v = np.where(frac < 1 - late, 0.85 - 0.15 * frac / (1 - late), 0.7 - 0.4 * (frac - (1 - late)) / late)
    rgb = np.stack([v, 0.8 * v, 0.55 * v], -1)
    rgb = np.where((k >= len(B))[..., None], np.asarray(background, dtype=np.float64), rgb)
    rgb = rgb.reshape(H, ss, W, ss, 3).mean((1, 3))
    rgb = np.clip(rgb + rng.normal(0, noise, rgb.shape), 0, 1).astype(np.float32)

    def boundary_radius(phi):
        return B * (1 + ecc * math.cos(phi - ecc_angle))

    return rgb, boundary_radius

