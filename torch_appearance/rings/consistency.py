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

Nothing is traced or inferred within ``inner_px`` of the pith (rays converge there). Cost: ``O(T J R (2 m + 1) N)``
for ``T`` sectors of ``J`` rays, ``R`` radii, ``N`` boundaries per transect and ``m`` the largest radial step; about
1.5 s on a 3000 x 3200 disc photo with eight transects and 23 rings.
"""
from __future__ import annotations

import math

import numpy as np
from scipy import ndimage

__all__ = ["link_transects", "sector_edges", "trace_curves"]


def sector_edges(value, pith, theta_a, theta_b, r_max, *, arc_step_px=6.0, edge_sigma_px=1.5, along_px=18.0,
                 period_px=40.0, ridge_level=0.5):
    """Edge response of the sector between two transect directions (module docstring, step 1).

    Args:
        value: ``(H, W)`` float image (HSV value, already blurred).
        pith: ``(x, y)`` in pixels.
        theta_a, theta_b: sector bounds in radians (``theta_b > theta_a``; from +x towards +y).
        r_max: largest radius in pixels.
        arc_step_px: ray spacing at ``r_max``.

    Returns:
        ``(E, thetas)``: ``E`` ``(J, R)`` float64 (ray ``j`` at ``thetas[j]``, radius ``0 .. R - 1`` px; 0 outside
        the image), ``thetas[0] = theta_a``, ``thetas[-1] = theta_b``.
    """
    R = int(math.floor(r_max)) + 1
    J = max(2, int(math.ceil((theta_b - theta_a) * r_max / arc_step_px)) + 1)
    thetas = np.linspace(theta_a, theta_b, J)
    r = np.arange(R, dtype=np.float64)
    X = pith[0] + r[None, :] * np.cos(thetas)[:, None]
    Y = pith[1] + r[None, :] * np.sin(thetas)[:, None]
    H, W = value.shape
    inside = (X >= 0) & (X <= W - 1) & (Y >= 0) & (Y <= H - 1)
    v = ndimage.map_coordinates(value, [Y, X], order=1, mode="nearest")
    d = ndimage.gaussian_filter1d(v, edge_sigma_px, axis=1, order=1, mode="nearest")
    d = ndimage.gaussian_filter1d(d, along_px / arc_step_px, axis=0, mode="nearest")
    e = np.where(inside, np.maximum(d, 0.0), 0.0)
    scale = ndimage.gaussian_filter(e, (2.0, period_px), mode="nearest")
    E = np.log1p(e / (scale + 1e-6 + 1e-3 * max(float(scale.max()), 1e-12)))
    # ridge centres only, all of (about) the same worth: a curve gains nothing by leaving its ring for a stronger one
    ridge = (E >= ndimage.maximum_filter1d(E, 5, axis=1, mode="nearest")) & (E > ridge_level)
    c = np.where(ridge, np.minimum(E, 1.0), 0.0)
    # widened to 3 px with shoulders worth 0.95 of the centre: a curve may ride one pixel beside a ridge, but ties
    # never pull it (or the snap to the largest response) to one side
    E = np.maximum(c, 0.95 * ndimage.maximum_filter1d(c, 3, axis=1, mode="nearest"))
    return E, thetas


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
    back = np.zeros((J, N, R), dtype=np.int8)
    pad = np.full((N, R + 2 * m), -np.inf, dtype=np.float64)
    pen = penalty.astype(np.float64)
    best = np.empty((N, R), dtype=np.float64)
    cand = np.empty((N, R), dtype=np.float64)
    better = np.empty((N, R), dtype=bool)
    for j in range(1, J):
        pad[:, m:m + R] = S
        best.fill(-np.inf)
        arg = back[j]
        for k, sh in enumerate(shifts):  # arriving at r from r - sh
            np.subtract(pad[:, m - sh:m - sh + R], pen[k], out=cand)
            np.greater(cand, best, out=better)
            np.copyto(best, cand, where=better)
            arg[better] = k
        np.add(best, E32[j], out=S)
    end = np.argmax(S, axis=1)
    score = S[np.arange(N), end] / J
    paths = np.zeros((N, J))
    cur = end.copy()
    for j in range(J - 1, -1, -1):
        paths[:, j] = cur
        if j > 0:
            cur = cur - shifts[back[j, np.arange(N), cur]]
    lo = np.clip(end - snap_px, 0, R - 1)
    win = np.stack([E[-1, np.clip(lo + i, 0, R - 1)] for i in range(2 * snap_px + 1)], 1)
    arrive = np.clip(lo + np.argmax(win, axis=1), 0, R - 1).astype(np.float64)
    return arrive, score, paths


def _tolerance(pos, x, tol_rings, min_tol_px):
    """Matching tolerance at radius ``x`` on a transect with sorted boundaries ``pos``: ``tol_rings`` of the
    narrower ring beside ``x`` (at least ``min_tol_px``; 10 px without rings to measure)."""
    edges = np.r_[pos[pos < x - 1e-9][-2:], pos[pos > x + 1e-9][:2]]
    gaps = np.diff(np.r_[edges[edges < x], x, edges[edges > x]])
    gaps = gaps[gaps > 1e-9]
    return max(min_tol_px, tol_rings * float(gaps.min())) if len(gaps) else max(min_tol_px, 10.0)


def link_transects(value, pith, angles_deg, radii, lengths, *, period_px, arc_step_px=6.0, smooth=3.0,
                   edge_sigma_px=1.5, along_px=18.0, ridge_level=0.5, max_tilt_deg=40.0, tol_rings=0.3,
                   min_tol_px=3.0, inner_px=None, agree_px=4.0):
    """Confirm and infer ring boundaries across neighbouring transects of one disc (module docstring).

    Args:
        value: ``(H, W)`` HSV value of the photo (float; blurred here with sigma 1 px).
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
    """
    T = len(angles_deg)
    if len(radii) != T or len(lengths) != T:
        raise ValueError(f"radii, lengths: expected one per transect ({T} angles), got {len(radii)} and "
                         f"{len(lengths)}")
    if np.ndim(value) != 2:
        raise ValueError(f"value: expected an (H, W) image, got shape {np.shape(value)}")
    radii = [np.sort(np.asarray(r, dtype=np.float64).reshape(-1)) for r in radii]
    out = [dict(radius_px=r.copy(), inferred=np.zeros(len(r), bool), confirmed=np.zeros(len(r), bool), moved=[],
                curves={}) for r in radii]
    if T < 3:
        return out
    inner = 0.5 * period_px if inner_px is None else float(inner_px)
    vb = ndimage.gaussian_filter(np.asarray(value, dtype=np.float64), 1.0, mode="nearest")
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
            if e is not None:  # snapped to the transect's own ridge within 2 px
                lo, hi = max(0, int(round(x)) - 2), min(len(e), int(round(x)) + 3)
                if hi > lo and e[lo:hi].max() > 0:
                    x = float(lo + np.argmax(e[lo:hi]))
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
                      confirmed=np.r_[confirmed, np.zeros(len(new), bool)][o], moved=moved)
    return out
