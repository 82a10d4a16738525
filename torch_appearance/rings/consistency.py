"""Consistency across the transects of one disc: ring curves traced between neighbouring transects.

The transects of one disc cross the same years, so a ring boundary found on one transect runs round the disc and
crosses its neighbours. :func:`link_transects` follows every boundary of every transect to the two neighbouring
transects (in angle order, the last one's neighbour the first) and uses where the curves arrive:

1. **Edge map of the sector.** Between two neighbouring transects the photo's HSV value (blurred with sigma 1 px)
   is sampled on rays from the pith, ``arc_step_px`` apart at the outer radius, 1 px steps along each ray (a polar
   image in which rings run across). A ring boundary is the sharp latewood -> earlywood rise going outwards: the
   response is the positive radial derivative (sigma ``edge_sigma_px``), smoothed along the ring over
   ``along_px``, divided by its local mean over one ring period (faint outer rings count as much as strong inner
   ones) and compressed (``log1p``). Only ridge centres are kept (local maxima along the ray above
   ``ridge_level``, capped at 1, widened to 3 px with shoulders worth 0.95), so every ring is worth about the same
   to a curve.
2. **Tracing.** From a boundary at radius ``r0`` on one transect, the curve is the best path of a Viterbi pass
   over the rays: each step may move along the radius at most ``tan(max_tilt_deg)`` times the arc step (plus one
   pixel) and pays ``smooth`` per unit of slope, so the path follows its ring's ridge and bridges gaps (a knot, a
   crack) straight, instead of hopping to a stronger ring. All boundaries of a transect are traced together
   (vectorised over starts). The arrival on the neighbour is snapped to the largest response within 2 px.
3. **Decisions** per transect, from the arrivals of both neighbours:
   - a boundary is *confirmed* when a curve from a neighbour arrives within ``tol`` of it (``tol_rings`` = 0.3 of
     the narrower ring beside it, at least ``min_tol_px``), so a curve that arrives on the next ring does not
     count;
   - where curves from *both* neighbours arrive within ``agree_px`` of each other (two independent curves agree)
     at a point snapped to the transect's own ridge: if no boundary lies within ``tol`` there, a ring is
     *inferred* there (a ring the 1D detector missed); if one lies within ``tol`` but more than ``min_tol_px``
     away, it is *moved* there (a boundary the 1D detector put on an earlywood or stain edge beside the ring).
   Boundaries that no curve meets are kept: on the TRAS discs most of them are narrow rings near the bark that the
   neighbours' curves do not reach, and dropping them cost more true rings than false ones (note of issue 26).
4. **Closed rings near the pith** (:func:`closed_rings`). Near the pith the rings are wide, often wider than the
   1D detector's filter scale, and the transects' own boundaries are what starts the curves of steps 2 - 3, so a
   ring missed on every transect is never traced. There the whole circle is one polar edge map (the same
   response, periodic along the ring) and every ridge on each transect's ray (between ``inner_px`` and
   ``closed_px``, default six ring periods) starts a curve traced once round the disc: it is a ring when it comes
   back to within ``agree_px`` of its start, scores at least 0.6 and the photo rises outwards across it on 90 % of
   its rays. A closed ring is inferred on every transect with no boundary within half a ring period of its
   crossing; a boundary lying between the innermost and outermost closed rings, farther than that from all of
   them and met by no neighbour's curve (step 3), is dropped (between them every ring closed; what does not, and
   runs to no neighbour, is a stain's or heartwood's edge; a ring that a crack or knot kept from closing is still
   met by its neighbours' curves). On the TRAS
   discs (automatic pith) this found the ring 90 - 100 px from the pith on the six transects where the 1D detector
   had skipped it, all on a human ring, and dropped four false boundaries in the wide inner rings, none of them on
   a human ring.

Nothing is traced or inferred within ``inner_px`` of the pith (rays converge there). Cost of steps 2 - 3:
``O(T J R (2 m + 1) N)`` for ``T`` sectors of ``J`` rays, ``R`` radii, ``N`` boundaries per transect and ``m`` the
largest radial step; about
1.5 s on a 3000 x 3200 disc photo with eight transects and 23 rings; step 4 adds about 1 s there.
"""
from __future__ import annotations

import math

import numpy as np
from scipy import ndimage

__all__ = ["blurred_value", "closed_rings", "link_transects", "sector_edges", "trace_curves"]


def blurred_value(value):
    """The photo's HSV value as the edge maps read it: ``(H, W)`` float64, Gaussian blur of sigma 1 px (border:
    nearest). :func:`link_transects` and :func:`~torch_appearance.rings.ring_polygons.trace_whole_rings` blur their
    ``value`` so; a caller of both blurs it once and passes ``value_blurred=True`` (disc mode)."""
    return ndimage.gaussian_filter(np.asarray(value, dtype=np.float64), 1.0, mode="nearest")


def _radial_derivative(value, pith, thetas, R, sigma_px):
    """``value`` on rays from ``pith`` at ``thetas`` (radius ``0 .. R - 1`` px), differentiated along each ray
    (Gaussian, ``sigma_px``): ``(d (J, R), inside (J, R))`` with ``inside`` the samples within the image."""
    r = np.arange(R, dtype=np.float64)
    X = pith[0] + r[None, :] * np.cos(thetas)[:, None]
    Y = pith[1] + r[None, :] * np.sin(thetas)[:, None]
    H, W = value.shape
    inside = (X >= 0) & (X <= W - 1) & (Y >= 0) & (Y <= H - 1)
    v = ndimage.map_coordinates(value, [Y, X], order=1, mode="nearest")
    return ndimage.gaussian_filter1d(v, sigma_px, axis=1, order=1, mode="nearest"), inside


def _snap_to_ridge(e, x, px=2):
    """``x`` moved to the largest edge response of ``e`` (a ray of :func:`sector_edges`) within ``px``, if any."""
    if e is None:
        return x
    lo, hi = max(0, int(round(x)) - px), min(len(e), int(round(x)) + px + 1)
    return float(lo + np.argmax(e[lo:hi])) if hi > lo and e[lo:hi].max() > 0 else x


def sector_edges(value, pith, theta_a, theta_b, r_max, *, arc_step_px=6.0, edge_sigma_px=1.5, along_px=18.0,
                 period_px=40.0, ridge_level=0.5, n_rays=None, periodic=False, ridge_px=5):
    """Edge response of the sector between two transect directions (module docstring, step 1).

    Args:
        value: ``(H, W)`` float image (HSV value, already blurred).
        pith: ``(x, y)`` in pixels.
        theta_a, theta_b: sector bounds in radians (``theta_b > theta_a``; from +x towards +y).
        r_max: largest radius in pixels.
        arc_step_px: ray spacing at ``r_max``.
        n_rays: the number of rays instead (at least 2; ``arc_step_px`` is then not used).
        periodic: the sector is the whole circle (``theta_b = theta_a + 2 pi``): the rays are spaced
            ``2 pi / J`` without repeating ``theta_a`` at ``theta_b``, and the smoothing along the ring wraps round.
        ridge_px: a ridge centre is the largest response within this window along the ray (odd, px).

    Returns:
        ``(E, thetas)``: ``E`` ``(J, R)`` float64 (ray ``j`` at ``thetas[j]``, radius ``0 .. R - 1`` px; 0 outside
        the image), ``thetas[0] = theta_a``, ``thetas[-1] = theta_b`` (not periodic).
    """
    E, thetas, _ = _sector_edges(value, pith, theta_a, theta_b, r_max, arc_step_px=arc_step_px,
                                 edge_sigma_px=edge_sigma_px, along_px=along_px, period_px=period_px,
                                 ridge_level=ridge_level, n_rays=n_rays, periodic=periodic, ridge_px=ridge_px)
    return E, thetas


def _sector_edges(value, pith, theta_a, theta_b, r_max, *, arc_step_px, edge_sigma_px, along_px, period_px,
                  ridge_level, n_rays, periodic, ridge_px):
    """:func:`sector_edges` plus the radial derivative it starts from, ``(E, thetas, d)`` with ``d`` ``(J, R)``
    (:func:`_radial_derivative`, not smoothed along the ring): whether the photo rises outwards, for the closed
    rings' test, without sampling the rays twice."""
    R = int(math.floor(r_max)) + 1
    if n_rays is None:
        J = max(2, int(math.ceil((theta_b - theta_a) * r_max / arc_step_px)) + 1)
    else:
        J = max(2, int(n_rays))
        arc_step_px = (theta_b - theta_a) * r_max / (J if periodic else J - 1)
    thetas = np.linspace(theta_a, theta_b, J, endpoint=not periodic)
    along = "wrap" if periodic else "nearest"
    d0, inside = _radial_derivative(value, pith, thetas, R, edge_sigma_px)
    d = ndimage.gaussian_filter1d(d0, along_px / arc_step_px, axis=0, mode=along)
    e = np.where(inside, np.maximum(d, 0.0), 0.0)
    scale = ndimage.gaussian_filter(e, (2.0, period_px), mode=(along, "nearest"))
    E = np.log1p(e / (scale + 1e-6 + 1e-3 * max(float(scale.max()), 1e-12)))
    # ridge centres only, all of (about) the same worth: a curve gains nothing by leaving its ring for a stronger one
    ridge = (E >= ndimage.maximum_filter1d(E, ridge_px, axis=1, mode="nearest")) & (E > ridge_level)
    c = np.where(ridge, np.minimum(E, 1.0), 0.0)
    # widened to 3 px with shoulders worth 0.95 of the centre: a curve may ride one pixel beside a ridge, but ties
    # never pull it (or the snap to the largest response) to one side
    E = np.maximum(c, 0.95 * ndimage.maximum_filter1d(c, 3, axis=1, mode="nearest"))
    return E, thetas, d0


def trace_curves(E, thetas, starts, *, smooth=3.0, max_tilt_deg=40.0, snap_px=2):
    """Trace ring curves across a sector's edge map from ray 0 to the last ray (module docstring, step 2).

    Args:
        E: ``(J, R)`` edge response (:func:`sector_edges`).
        thetas: ``(J,)`` ray angles in radians.
        starts: ``(N,)`` starting radii (px) on ray 0.
        smooth: penalty per unit of slope (radial move / arc step) per ray.
        max_tilt_deg: largest slope of a curve against the circle about the pith.

    Returns:
        ``(arrive, score, paths)``: ``arrive`` ``(N,)`` radius on the last ray (px, snapped to the largest edge
        response within ``snap_px``), ``score`` ``(N,)`` the path's mean edge response, ``paths`` ``(N, J)`` the
        radius of each curve on every ray.

    Memory: the best score of every start, ray and radius is kept (``J N R`` float64, 60 - 90 MB on a
    3000 x 3200 disc photo) and the moves are recovered along the paths only.
    """
    J, R = E.shape
    starts = np.asarray(starts, dtype=np.float64).reshape(-1)
    N = len(starts)
    if N == 0:
        return np.zeros(0), np.zeros(0), np.zeros((0, J))
    dth = abs(thetas[1] - thetas[0]) if J > 1 else 1.0
    r = np.arange(R, dtype=np.float64)
    arc = np.maximum(r * dth, 1e-3)                                   # arc step at each radius (px)
    tilt = math.tan(math.radians(max_tilt_deg))
    m = int(min(R - 1, 63, math.ceil(tilt * (R - 1) * dth) + 1))
    shifts = np.arange(-m, m + 1)
    # penalty[k, r]: moving by shifts[k] px along the radius at radius r; moves steeper than the tilt are forbidden
    slope = np.abs(shifts)[:, None] / arc[None, :]
    penalty = np.where(np.abs(shifts)[:, None] <= tilt * arc[None, :] + 1.0, smooth * slope, np.inf)
    E32 = E.astype(np.float64)
    S = np.full((N, R), -np.inf, dtype=np.float64)
    r0 = np.clip(np.round(starts).astype(int), 0, R - 1)
    for k in range(-1, 2):  # start within 1 px of the boundary (sub-pixel positions, the click's own spread)
        S[np.arange(N), np.clip(r0 + k, 0, R - 1)] = E32[0, np.clip(r0 + k, 0, R - 1)] - (0.0 if k == 0 else 0.1)
    pad = np.full((N, R + 2 * m), -np.inf, dtype=np.float64)
    pen = penalty.astype(np.float64)
    best = np.empty((N, R), dtype=np.float64)
    cand = np.empty((N, R), dtype=np.float64)
    hist = np.empty((J, N, R), dtype=np.float64)  # the best scores on every ray; the moves recovered on the path only
    hist[0] = S
    for j in range(1, J):
        pad[:, m:m + R] = hist[j - 1]
        np.subtract(pad[:, 2 * m:2 * m + R], pen[0], out=best)  # arriving at r from r - shifts[0]
        for k in range(1, 2 * m + 1):  # arriving at r from r - shifts[k]
            np.subtract(pad[:, 2 * m - k:2 * m - k + R], pen[k], out=cand)
            np.maximum(best, cand, out=best)
        np.add(best, E32[j], out=hist[j])
    S = hist[-1]
    end = np.argmax(S, axis=1)
    score = S[np.arange(N), end] / J
    paths = np.zeros((N, J))
    cur = end.copy()
    nn = np.arange(N)
    for j in range(J - 1, -1, -1):
        paths[:, j] = cur
        if j > 0:
            # the move into the path's radius on ray j, as the forward pass scored it; the first best wins
            src = cur[:, None] - shifts[None, :]                                     # (N, 2 m + 1)
            ok = (src >= 0) & (src < R)
            came = np.where(ok, hist[j - 1][nn[:, None], np.clip(src, 0, R - 1)], -np.inf) - pen[:, cur].T
            cur = cur - shifts[np.argmax(came, axis=1)]
    lo = np.clip(end - snap_px, 0, R - 1)
    win = np.stack([E[-1, np.clip(lo + i, 0, R - 1)] for i in range(2 * snap_px + 1)], 1)
    arrive = np.clip(lo + np.argmax(win, axis=1), 0, R - 1).astype(np.float64)
    return arrive, score, paths


def closed_rings(value, pith, angles_rad, r_min, r_max, *, arc_step_px=4.0, smooth=3.0, edge_sigma_px=1.5,
                 along_px=18.0, period_px=40.0, ridge_level=0.5, max_tilt_deg=40.0, close_px=4.0, min_score=0.6,
                 min_rise=0.9):
    """Rings near the pith as closed curves traced once round the disc (module docstring, step 4).

    Args:
        value: ``(H, W)`` float image (HSV value, already blurred).
        pith: ``(x, y)`` in pixels.
        angles_rad: ``(A,)`` directions (radians) whose rays seed the curves: every ridge centre on each of them
            between ``r_min`` and ``r_max`` starts one curve.
        r_min, r_max: radii (px) of the zone.
        close_px: a curve is a ring when it comes back round to within ``close_px`` of its start ...
        min_score: ... and its mean edge response (:func:`trace_curves`' score: 1 on a ridge all the way round,
            less the slope penalties) is at least this ...
        min_rise: ... and the photo rises outwards across it (radial derivative of the value, sigma
            ``edge_sigma_px``, not smoothed along the ring) on at least this fraction of its rays: a ring boundary
            is a latewood -> earlywood rise all the way round, where the edge of a stain or of heartwood is not
            (on the TRAS discs: 0.96 - 1.00 on the rings people marked, 0.82 - 0.83 on the two closed curves
            they did not).

    Returns:
        ``(thetas, rings, scores)``: ``thetas`` ``(J,)`` ray angles in ``[0, 2 pi)``; ``rings`` ``(K, J)`` the
        radius of each ring on every ray (sorted by mean radius; curves that stay within ``close_px`` of one
        another on average are one ring, the better scored kept); ``scores`` ``(K,)``.
    """
    if not (0 <= r_min < r_max and math.isfinite(r_max)):
        raise ValueError(f"r_min, r_max: expected 0 <= r_min < r_max (finite), got {r_min!r}, {r_max!r}")
    J = max(8, int(math.ceil(2 * math.pi * r_max / arc_step_px)))
    E, thetas, d = _sector_edges(value, pith, 0.0, 2 * math.pi, r_max, arc_step_px=arc_step_px, n_rays=J,
                                 periodic=True, edge_sigma_px=edge_sigma_px, along_px=along_px, period_px=period_px,
                                 ridge_level=ridge_level, ridge_px=5)
    rise = d > 0
    found, scores = [], []
    for a in np.asarray(angles_rad, dtype=np.float64).reshape(-1):
        j0 = int(round((a % (2 * math.pi)) / (2 * math.pi) * J)) % J
        Er = np.roll(E, -j0, axis=0)
        Er = np.concatenate([Er, Er[:1]])                       # once round, back onto the start ray
        thr = thetas[0] + (np.arange(J + 1) + j0) * (2 * math.pi / J)
        e0 = Er[0]
        peak = (e0 >= ndimage.maximum_filter1d(e0, 5, mode="nearest")) & (e0 > 0)
        rr = np.arange(len(e0))
        starts = rr[peak & (rr >= r_min)].astype(np.float64)
        if len(starts) == 0:
            continue
        _, score, paths = trace_curves(Er, thr, starts, smooth=smooth, max_tilt_deg=max_tilt_deg)
        ok = (np.abs(paths[:, -1] - paths[:, 0]) <= close_px) & (score >= min_score)
        for path, sc in zip(paths[ok], score[ok]):
            path = np.roll(path[:-1], j0)                       # back to ray order 0 .. J - 1
            if rise[np.arange(J), path.astype(int)].mean() >= min_rise:
                found.append(path)
                scores.append(float(sc))
    rings, kept = [], []
    for i in np.argsort(scores)[::-1]:
        if all(np.abs(found[i] - ring).mean() > close_px for ring in rings):
            rings.append(found[i])
            kept.append(scores[i])
    if not rings:
        return thetas, np.zeros((0, J)), np.zeros(0)
    o = np.argsort([ring.mean() for ring in rings])
    return thetas, np.asarray(rings)[o], np.asarray(kept)[o]


def _tolerance(pos, x, tol_rings, min_tol_px):
    """Matching tolerance at radius ``x`` on a transect with sorted boundaries ``pos``: ``tol_rings`` of the
    narrower ring beside ``x`` (at least ``min_tol_px``; 10 px without rings to measure)."""
    edges = np.r_[pos[pos < x - 1e-9][-2:], pos[pos > x + 1e-9][:2]]
    gaps = np.diff(np.r_[edges[edges < x], x, edges[edges > x]])
    gaps = gaps[gaps > 1e-9]
    return max(min_tol_px, tol_rings * float(gaps.min())) if len(gaps) else max(min_tol_px, 10.0)


def link_transects(value, pith, angles_deg, radii, lengths, *, period_px, arc_step_px=6.0, smooth=3.0,
                   edge_sigma_px=1.5, along_px=18.0, ridge_level=0.5, max_tilt_deg=40.0, tol_rings=0.3,
                   min_tol_px=3.0, inner_px=None, agree_px=4.0, closed_px=None, closed_gap=0.5,
                   value_blurred=False):
    """Confirm and infer ring boundaries across neighbouring transects of one disc (module docstring).

    Args:
        value: ``(H, W)`` HSV value of the photo (float; blurred here with sigma 1 px, :func:`blurred_value`, unless
            ``value_blurred``: then it is that already and used as it is).
        pith: ``(x, y)`` in pixels.
        angles_deg: ``(T,)`` transect directions (degrees from +x towards +y), ``T >= 3``.
        radii: list of ``T`` arrays of boundary radii (px from the pith).
        lengths: ``(T,)`` analysed length of each transect (px; rings are inferred only inside it).
        period_px: ring period (px): the edge normalisation's window along the radius; ``inner_px`` (default half
            of it) the radius inside which nothing is traced or inferred.

    Returns:
        ``list`` of ``T`` dicts: ``radius_px`` (sorted, found, moved and inferred), ``inferred`` and ``confirmed``
        (bool per radius: inferred from both neighbours; found and met by a neighbour's curve), ``moved`` (list of
        ``(from, to)`` radii), ``curves``: ``{neighbour: (thetas (J,), paths (N, J))}`` the traced curves in polar
        coordinates (radians, px) for drawing.
        closed_px: outer radius of the zone round the pith where rings are also traced as closed curves
            (:func:`closed_rings`; default 6 ring periods, at most the shortest transect; 0: not traced). A
            closed ring is inferred on a transect that has no boundary within ``closed_gap`` ring periods of
            its crossing (a wide ring near the pith that the 1D detector skipped); it never moves a boundary. A
            boundary between the transect's innermost and outermost closed crossings, farther than that from all
            of them, and not confirmed by a neighbour's curve, is dropped.

    The dicts also hold ``closed`` (bool per radius: inferred from a closed ring), ``closed_rings``: ``(thetas
    (J,), rings (K, J))`` the closed rings traced, ``closed_crossings`` ``(K,)`` where they cross the transect, and
    ``dropped`` (radii of the boundaries dropped between closed rings).
    """
    T = len(angles_deg)
    if len(radii) != T or len(lengths) != T:
        raise ValueError(f"radii, lengths: expected one per transect ({T} angles), got {len(radii)} and "
                         f"{len(lengths)}")
    if np.ndim(value) != 2:
        raise ValueError(f"value: expected an (H, W) image, got shape {np.shape(value)}")
    radii = [np.sort(np.asarray(r, dtype=np.float64).reshape(-1)) for r in radii]
    out = [dict(radius_px=r.copy(), inferred=np.zeros(len(r), bool), confirmed=np.zeros(len(r), bool), moved=[],
                curves={}, closed=np.zeros(len(r), bool), closed_rings=(np.zeros(0), np.zeros((0, 0))),
                closed_crossings=np.zeros(0), dropped=[])
           for r in radii]
    if T < 3:
        return out
    inner = 0.5 * period_px if inner_px is None else float(inner_px)
    vb = np.asarray(value, dtype=np.float64) if value_blurred else blurred_value(value)
    ang = np.radians(np.asarray(angles_deg, dtype=np.float64) % 360.0)
    order = np.argsort(ang, kind="stable")
    arrivals = [[] for _ in range(T)]  # per transect: (radius, source transect)
    own = {}                           # per transect: its own ray's edge response
    for i in range(T):
        a, b = int(order[i]), int(order[(i + 1) % T])
        ta, tb = ang[a], ang[b] + (2 * math.pi if i + 1 == T else 0.0)
        if tb - ta <= 1e-9:
            continue
        E, th = sector_edges(vb, pith, ta, tb, float(max(lengths[a], lengths[b])), arc_step_px=arc_step_px,
                             edge_sigma_px=edge_sigma_px, along_px=along_px, period_px=period_px,
                             ridge_level=ridge_level)
        own.setdefault(a, E[0])
        own.setdefault(b, E[-1])
        for s, t, Es, ths in ((a, b, E, th), (b, a, E[::-1], th[::-1])):
            st = radii[s][(radii[s] >= inner) & (radii[s] <= lengths[s])]
            arrive, _, paths = trace_curves(Es, ths, st, smooth=smooth, max_tilt_deg=max_tilt_deg)
            out[s]["curves"][t] = (ths, paths)
            arrivals[t] += [(float(x), s) for x in arrive if inner <= x <= lengths[t]]
    for t in range(T):
        pos = radii[t]
        confirmed = np.zeros(len(pos), bool)
        for x, _ in arrivals[t]:
            k = int(np.argmin(np.abs(pos - x))) if len(pos) else -1
            if k >= 0 and abs(pos[k] - x) <= _tolerance(pos, pos[k], tol_rings, min_tol_px):
                confirmed[k] = True
        # crossings where the curves from both neighbours arrive together (within agree_px)
        arr = sorted(arrivals[t])
        cross, used = [], set()
        for i, (x, s) in enumerate(arr):
            if i in used:
                continue
            js = [j for j in range(i + 1, len(arr)) if j not in used and arr[j][1] != s and arr[j][0] - x <= agree_px]
            if js:
                j = min(js, key=lambda j: arr[j][0] - x)
                used.update((i, j))
                cross.append(0.5 * (x + arr[j][0]))
        new, moved = [], []
        pos = pos.copy()
        e = own.get(t)
        for x in cross:
            x = _snap_to_ridge(e, x)  # to the transect's own ridge
            k = int(np.argmin(np.abs(pos - x))) if len(pos) else -1
            d = abs(pos[k] - x) if k >= 0 else np.inf
            if d <= min_tol_px:
                continue
            # the boundary sits off its ring's curve: within tol_rings of the rings about the crossing, the
            # transect's other boundaries measuring them
            if k >= 0 and d <= _tolerance(np.delete(pos, k), x, tol_rings, min_tol_px):
                moved.append((float(pos[k]), x))
                pos[k] = x
                continue
            if all(abs(x - y) > min_tol_px for y in new):
                new.append(x)
        allr = np.r_[pos, new]
        o = np.argsort(allr, kind="stable")
        out[t].update(radius_px=allr[o], inferred=np.r_[np.zeros(len(pos), bool), np.ones(len(new), bool)][o],
                      confirmed=np.r_[confirmed, np.zeros(len(new), bool)][o], moved=moved,
                      closed=np.zeros(len(allr), bool))
    zone = 6.0 * period_px if closed_px is None else float(closed_px)
    zone = min(zone, float(np.min(lengths)))
    if zone > inner + 2 * min_tol_px:
        thetas, rings, _ = closed_rings(vb, pith, ang, inner, zone, smooth=smooth, edge_sigma_px=edge_sigma_px,
                                        along_px=along_px, period_px=period_px, ridge_level=ridge_level,
                                        max_tilt_deg=max_tilt_deg, close_px=agree_px)
        for t in range(T):
            pos, e = out[t]["radius_px"], own.get(t)
            new, cross = [], []
            for ring in rings:
                x = _snap_to_ridge(e, float(np.interp(ang[t], thetas, ring, period=2 * math.pi)))
                cross.append(x)
                if inner <= x <= lengths[t] and np.all(np.abs(np.r_[pos, new] - x) > closed_gap * period_px):
                    new.append(x)
            # between the innermost and outermost closed ring every ring closed: a boundary there far from all
            # of them, that no neighbour's curve met either, is a stain's or the earlywood's edge
            cx = np.sort(np.asarray(cross))
            drop = np.zeros(len(pos), bool)
            if len(cx) >= 2:
                far = np.abs(pos[:, None] - cx[None, :]).min(1) > closed_gap * period_px
                drop = far & (pos > cx[0]) & (pos < cx[-1]) & ~out[t]["confirmed"]
            out[t]["dropped"] = pos[drop].tolist()
            k = np.ones(len(new), bool)
            allr = np.r_[pos[~drop], new]
            o = np.argsort(allr, kind="stable")
            out[t].update(radius_px=allr[o], inferred=np.r_[out[t]["inferred"][~drop], k][o],
                          confirmed=np.r_[out[t]["confirmed"][~drop], ~k][o],
                          closed=np.r_[out[t]["closed"][~drop], k][o])
            out[t]["closed_rings"] = (thetas, rings)
            out[t]["closed_crossings"] = np.asarray(cross, dtype=np.float64)
    return out
