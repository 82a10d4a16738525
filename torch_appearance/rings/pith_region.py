"""The pith region of a disc: the pith's own edge as one closed curve round the pith (issue 48 item 3).

Disc mode (:mod:`~torch_appearance.rings.disc`) drops every boundary within a quarter ring period of the pith, where
the strips' rows converge; but the pith, or the first year's wood around it, often ends in a sharp dark -> light step
a few px out (on the TRAS disc C13C 15 - 17 px from the pith, a ring period of 79 px), which people mark as the
innermost boundary. Along one transect that step is a few pixels of a converging strip; round the pith it is a small
closed curve. Here it is found as such:

1. **Polar unwrap.** The photo's value (blurred, sigma 1 px) on ``n_rays`` rays round the pith, radius
   ``min_radius_px .. max_radius_periods P`` (``P`` the ring period), differentiated along each ray: the ridge
   centres of the dark -> light rise outwards (the same edge map as the whole rings',
   :func:`~torch_appearance.rings.consistency.sector_edges`, periodic, smoothed ``along_px`` along the ring).
2. **Closed path.** A dynamic programme over the rays round the pith, started from every radius of the first ray
   and made to come back to it (:func:`~torch_appearance.rings.ring_polygons._band_trace`), a move of ``du`` px
   between neighbouring rays costing ``smooth du^2`` (at most 1 px per ray); the best scored path (mean response
   less the moves' costs) is the pith's edge.
3. **Support and contrast.** The support is the share of rays where the path lies on a ridge centre (response at
   least 0.5) across which the photo rises outwards; the contrast is the path's median rise (value per px) over
   the median rise at the disc's ring boundaries (``radii`` on the transects within ``ref_periods P`` of the pith;
   the edge map is normalised locally, so a faint texture can score as well as a ring). The edge is ``found`` when
   its support is at least ``min_support``, its score at least ``min_score`` and its contrast at least
   ``min_contrast``: a step round most of the circle, as sharp as the rings nearby.

:func:`place_pith_edge` then puts the edge on a transect as its innermost boundary (ring 0) when no boundary lies
within ``tol_px`` of it, and drops the boundaries inside it (the pith region holds no ring).
"""
from __future__ import annotations

import math
import time

import numpy as np
from scipy import ndimage

__all__ = ["pith_edge", "place_pith_edge"]


def pith_edge(value, pith, angles_deg, radii, *, period_px, max_radius_periods=0.5, min_radius_px=3.0,
              n_rays=128, edge_sigma_px=1.0, along_px=4.0, smooth=0.3, min_support=0.75, min_score=0.6,
              min_contrast=0.5, ref_periods=8.0):
    """The pith's own edge as a closed curve round the pith (module docstring).

    Args:
        value: ``(H, W)`` float image (HSV value in [0, 1]; blurred here with sigma 1 px, only near the pith).
        pith: ``(x, y)`` in pixels.
        angles_deg: ``(T,)`` transect directions in degrees (from +x towards +y) where the crossings are wanted.
        radii: ``T`` arrays of the boundary radii found on those transects (px), the contrast's reference (the
            support alone does not tell: a path through noise finds ridge centres on most rays of a locally
            normalised edge map).
        period_px: the disc's ring period ``P`` (px); the curve is looked for within ``max_radius_periods P``.
        min_radius_px: smallest radius of the curve (px).
        n_rays: rays round the pith.
        edge_sigma_px, along_px: derivative sigma along the rays, smoothing along the ring (px of arc at the
            largest radius).
        smooth: cost of a move of 1 px between neighbouring rays (in units of the edge response, which is at most 1).
        min_support, min_score, min_contrast: the curve is ``found`` when its support, its score and its contrast
            reach these (module docstring, step 3).
        ref_periods: the contrast's reference takes the boundaries within this many ring periods of the pith.

    Returns:
        dict: ``thetas`` ``(J,)`` ray angles in ``[0, 2 pi)``; ``radius`` ``(J,)`` float64 px, the curve on every
        ray; ``crossings`` ``(T,)`` px from the pith where the curve crosses each transect (refined to the steepest
        rise along the transect within 2 px); ``score``; ``support`` (share of rays, module docstring step 3);
        ``contrast``; ``found`` bool; ``seconds``.

    Example:
        >>> from torch_appearance.rings.dendro import hsv_value
        >>> from torch_appearance.rings.synthetic_discs import make_disc
        >>> d = make_disc(size=(200, 200), n_rings=5, inner_width_px=30.0, outer_width_px=12.0, pith_px=10.0)
        >>> truth = [d.boundaries_along(a) for a in (0, 90, 180, 270)]
        >>> e = pith_edge(hsv_value(d.rgb), d.pith, [0, 90, 180, 270], [b[1:] for b in truth], period_px=30.0)
        >>> bool(e["found"]), bool(np.abs(e["crossings"] - [b[0] for b in truth]).max() < 1.5)
        (True, True)
    """
    from .consistency import _radial_derivative, sector_edges
    from .ring_polygons import _band_trace

    t0 = time.perf_counter()
    if not (isinstance(period_px, (int, float, np.integer, np.floating)) and period_px > 0):
        raise ValueError(f"period_px: expected a positive number, got {period_px!r}")
    pith = np.asarray(pith, np.float64).reshape(2)
    ang = np.radians(np.asarray(angles_deg, np.float64).reshape(-1)) % (2 * math.pi)
    if len(radii) != len(ang):
        raise ValueError(f"radii: expected one array per angle ({len(ang)}), got {len(radii)}")
    R = int(math.ceil(max(max_radius_periods * float(period_px), min_radius_px + 4.0)))
    v = np.asarray(value)
    vb, pc = _blurred_crop(v, pith, R + 8)
    J = int(n_rays)
    E, thetas = sector_edges(vb, pc, 0.0, 2 * math.pi, R, n_rays=J, periodic=True, edge_sigma_px=edge_sigma_px,
                             along_px=along_px, period_px=period_px, ridge_level=0.5, ridge_px=3)
    d, _ = _radial_derivative(vb, pc, thetas, E.shape[1], edge_sigma_px)
    r0 = int(math.ceil(min_radius_px))
    Eb = E[:, r0:]
    B = Eb.shape[1]
    # one seed per radius of ray 0; the start ray again at the end so that the path closes
    Ebb = np.broadcast_to(np.concatenate([Eb, Eb[:1]], 0)[None], (B, J + 1, B))
    pen = np.broadcast_to(smooth * np.array([1.0, 0.0, 1.0]), (B, J, 3))
    paths, score = _band_trace(Ebb, np.arange(B, dtype=np.float64), pen, 1.0)
    best = int(np.argmax(score))
    ui = paths[best, :J]
    radius = (ui + r0).astype(np.float64)
    on = (Eb[np.arange(J), ui] >= 0.5) & (d[np.arange(J), ui + r0] > 0)
    support = float(on.mean())
    sc = float(score[best])
    # the crossings: the curve at each transect's direction, refined to the steepest rise along that ray
    rad_at = np.interp(ang, np.r_[thetas, 2 * math.pi], np.r_[radius, radius[0]])
    dt, _ = _radial_derivative(vb, pc, ang, E.shape[1], edge_sigma_px)
    crossings = rad_at.copy()
    for t in range(len(ang)):
        lo, hi = max(1, int(round(rad_at[t])) - 2), min(E.shape[1] - 2, int(round(rad_at[t])) + 2)
        if hi < lo:
            continue
        i = lo + int(np.argmax(dt[t, lo:hi + 1]))
        a_, b_, c_ = dt[t, i - 1], dt[t, i], dt[t, i + 1]
        den = a_ - 2 * b_ + c_
        crossings[t] = i + (0.5 * (a_ - c_) / den if den < 0 else 0.0)
    ref = _median_rise(v, pith, ang, radii, ref_periods * float(period_px), edge_sigma_px)
    contrast = float(np.median(d[np.arange(J), ui + r0])) / ref if ref > 0 else 0.0
    found = support >= min_support and sc >= min_score and contrast >= min_contrast
    return dict(thetas=thetas, radius=radius, crossings=crossings, score=sc, support=support, contrast=contrast,
                found=bool(found), seconds=time.perf_counter() - t0)


def _blurred_crop(value, pith, pad):
    """``(vb, pc)``: the crop of ``value`` within ``pad`` px of ``pith`` (clipped to the image) blurred with sigma
    1 px (border: nearest), float64, and the pith in the crop's pixels; only the pith's surroundings are read."""
    H, W = value.shape
    x0, y0 = max(0, int(pith[0]) - pad), max(0, int(pith[1]) - pad)
    x1, y1 = min(W, int(pith[0]) + pad + 1), min(H, int(pith[1]) + pad + 1)
    vb = ndimage.gaussian_filter(value[y0:y1, x0:x1].astype(np.float64), 1.0, mode="nearest")
    return vb, pith - np.array([x0, y0], np.float64)


def _median_rise(value, pith, ang, radii, r_max, sigma_px):
    """Median over the boundaries ``radii`` (``T`` arrays, px) below ``r_max`` on the rays at ``ang`` (radians) of
    the largest outward rise of ``value`` (blurred as in :func:`pith_edge`) within 2 px (derivative along the ray,
    sigma ``sigma_px``); 0 if none."""
    from .consistency import _radial_derivative

    R = int(r_max) + 4
    vb, pc = _blurred_crop(value, pith, R + 8)
    rises = []
    for a, rr in zip(ang, radii):
        d, inside = _radial_derivative(vb, pc, np.array([a]), R, sigma_px)
        for r in np.asarray(rr, np.float64).reshape(-1):
            i = int(round(r))
            if 2 <= i < R - 3 and inside[0, i]:
                rises.append(float(d[0, i - 2:i + 3].max()))
    return float(np.median(rises)) if rises else 0.0


def place_pith_edge(radii, crossing_px, *, tol_px=3.0):
    """One transect's boundaries made to agree with the pith's edge (:func:`pith_edge`).

    Args:
        radii: ``(N,)`` boundary radii along the transect (px from the pith).
        crossing_px: where the pith's edge crosses the transect (px).
        tol_px: a boundary within this of the crossing is the pith's edge already.

    Returns:
        ``(keep, new)``: ``keep`` ``(N,)`` bool, False for the boundaries more than ``tol_px`` inside the edge (the
        pith region holds no ring); ``new`` ``(0,)`` or ``(1,)`` float64, the edge placed when no boundary lies
        within ``tol_px`` of it.

    Example:
        >>> keep, new = place_pith_edge([5.0, 40.0, 80.0], 16.0)
        >>> keep.tolist(), new.tolist()
        ([False, True, True], [16.0])
    """
    pos = np.asarray(radii, np.float64).reshape(-1)
    x = float(crossing_px)
    keep = pos >= x - tol_px
    new = np.zeros(0) if (np.abs(pos - x) <= tol_px).any() else np.array([x])
    return keep, new
