"""Whole rings of a disc as closed polygons, chained from the ring curves traced between neighbouring transects.

:func:`~torch_appearance.rings.consistency.link_transects` follows every boundary of every transect (helper
transects included) along its ring's ridge to both neighbouring transects. Chaining those curves round the disc
gives whole rings (the representation of CS-TRD): from a boundary on the first transect, the curve towards the next
transect (in angle order) arrives near one of the boundaries that transect's own curves start from (within 0.3 of
the narrower ring beside it, at least 3 px), whose curve continues to the next, and so on; the ring *closes* when
the chain comes back to the boundary it started from. A boundary whose chain breaks or comes back on another ring
closes nowhere and gives no polygon. The polygon is the concatenation of the curves (one vertex per traced ray).

**Traced round the disc** (:func:`trace_whole_rings`, the default of disc mode): rather than chaining the curves
between transects, every ring is one closed path, a dynamic programme over the rays round the pith in a polar edge
map, peeled outwards one ring at a time above the last (rings do not cross), seeded and anchored by the transects'
boundaries. The rings then act on the transects (:func:`place_whole_rings`): a boundary between rings that lies
on none of them is dropped, and (optional, off in disc mode by default) a ring is placed where a transect's
detector missed it. On the TRAS discs (human
pith, dots inpainted) 21 of C13C's 23 rings and 19 of C17C's close round the disc this way, against 5 - 9 chained;
the outermost one or two, among the narrow rings before the bark, can still hop between rings.

Written as labelme-style JSON (as CS-TRD and TRAS write their rings): ``shapes`` of ``shape_type`` ``"polygon"``
with ``label`` the ring's index from the pith, ``points`` ``[[x, y], ...]`` in pixels of the photo.
"""
from __future__ import annotations

import json
import math

import numpy as np

__all__ = ["draw_ring_polygons", "labelme_json", "place_whole_rings", "ring_polygons", "trace_whole_rings"]


def _match(radii, x, tol_rings=0.3, min_px=3.0):
    """Index of the boundary of ``radii`` (sorted) matching a curve arriving at ``x``, or -1."""
    if not len(radii):
        return -1
    k = int(np.argmin(np.abs(radii - x)))
    gaps = np.diff(radii)
    near = [g for g in (gaps[k - 1] if k > 0 else None, gaps[k] if k < len(gaps) else None) if g is not None]
    tol = max(min_px, tol_rings * min(near)) if near else min_px
    return k if abs(radii[k] - x) <= tol else -1


def ring_polygons(res) -> list[dict]:
    """Closed rings of a :class:`~torch_appearance.rings.disc.DiscBoundaries` (module docstring).

    Returns:
        list (sorted by mean radius) of dicts: ``points`` ``(N, 2)`` ``(x, y)`` pixels, ``radius_px`` the mean
        distance from the pith, ``start_radius_px`` the boundary on the first transect it was chained from. Empty
        when the transects were not linked (``link=False`` or fewer than three transects).

    Raises:
        ValueError: ``res`` is not a disc result.
    """
    info = getattr(res, "info", None)
    if not isinstance(info, dict) or "rings_polar" not in info or not hasattr(res, "pith"):
        raise ValueError(f"res: expected a DiscBoundaries (detect_disc_boundaries' result), got {type(res).__name__}")
    rp = info["rings_polar"]
    if rp is None:
        return []
    if rp.get("whole") is not None:  # traced round the disc (trace_whole_rings)
        th, rings = rp["whole"]["thetas"], rp["whole"]["rings"]
        pith = np.asarray(res.pith, np.float64)
        return [dict(points=pith[None, :] + r[:, None] * np.stack([np.cos(th), np.sin(th)], 1),
                     radius_px=float(r.mean()), start_radius_px=float(r[0])) for r in rings]
    ang = np.asarray(rp["angles_deg"], np.float64) % 360.0
    order = [int(i) for i in np.argsort(ang, kind="stable")]
    T = len(order)
    pith = np.asarray(res.pith, np.float64)
    # the curves leave each transect from its own (1D) boundaries: the ring is followed from curve start to curve
    # start (a boundary inferred or moved by the linking has no curve of its own)
    starts = []
    for step in range(T):
        k, nxt = order[step], order[(step + 1) % T]
        c = rp["curves"][k].get(nxt)
        if c is None:  # a sector was not traced (two transects at one angle): no ring goes round
            return []
        starts.append(np.asarray(c[1][:, 0] if len(c[1]) else np.zeros(0), np.float64))
    out = []
    for i0, r0 in enumerate(starts[0]):
        idx, thetas, rs, ok = i0, [], [], True
        for step in range(T):
            k, nxt = order[step], order[(step + 1) % T]
            th, paths = rp["curves"][k][nxt]
            th = np.asarray(th, np.float64)
            if step + 1 == T and th[-1] < th[0]:
                th = th + 2 * math.pi
            thetas.append(th[:-1])
            rs.append(paths[idx, :-1])
            idx = _match(starts[(step + 1) % T], float(paths[idx, -1]))
            if idx < 0:
                ok = False
                break
        if not ok or idx != i0:
            continue
        th, r = np.concatenate(thetas), np.concatenate(rs)
        pts = pith[None, :] + r[:, None] * np.stack([np.cos(th), np.sin(th)], 1)
        out.append(dict(points=pts, radius_px=float(r.mean()), start_radius_px=float(r0)))
    out.sort(key=lambda p: p["radius_px"])
    kept = []
    for p in out:  # two starts that chained onto the same ring: keep one
        if not kept or np.abs(p["radius_px"] - kept[-1]["radius_px"]) > 1.0:
            kept.append(p)
    return kept


def labelme_json(polygons, image_path: str, image_shape, pith=None) -> str:
    """labelme-style JSON text of ring polygons (module docstring); ``image_shape`` ``(H, W)``; ``pith`` ``(x, y)``
    is written as ``"center"`` ``[row, col]`` as CS-TRD does."""
    H, W = (int(v) for v in image_shape[:2])
    shapes = [dict(label=str(i), points=np.round(p["points"], 2).tolist(), group_id=None, shape_type="polygon",
                   flags={}) for i, p in enumerate(polygons)]
    blob = dict(version="5.0.1", flags={}, shapes=shapes, imagePath=str(image_path), imageData=None, imageHeight=H,
                imageWidth=W)
    if pith is not None:
        blob["center"] = [float(pith[1]), float(pith[0])]
    return json.dumps(blob, indent=1)


def draw_ring_polygons(bgr, polygons, thickness=None):
    """Draw the polygons on a ``(H, W, 3)`` uint8 BGR image in place (alternating colours, so that neighbouring rings
    tell apart); returns it."""
    import cv2
    t = thickness or max(1, round(max(bgr.shape[:2]) / 1500))
    colours = ((0, 255, 255), (255, 0, 255))
    for i, p in enumerate(polygons):
        pts = np.round(p["points"]).astype(np.int32).reshape(-1, 1, 2)
        cv2.polylines(bgr, [pts], True, colours[i % 2], t, cv2.LINE_AA)
    return bgr


def _band_trace(Eb, u0, pen, close_px):
    """Closed paths through band images, one per seed (:func:`trace_whole_rings`).

    ``Eb`` ``(N, J + 1, B)``: edge response of seed ``n`` on ray ``i`` (its start ray first, the start ray again
    last) at height ``u`` above the inner ring; ``u0`` ``(N,)`` start heights; ``pen`` ``(N, J, 2 m + 1)``: the
    cost of moving by ``m - k`` between rays ``i`` and ``i + 1``. Returns ``(paths (N, J + 1) int, score (N,))``:
    each path starts within 1 px of ``u0`` and ends within ``close_px`` of it; ``score`` is its mean response less
    the moves' costs (-inf where no such path exists)."""
    N, J1, B = Eb.shape
    m = (pen.shape[2] - 1) // 2
    S = np.full((N, B), -np.inf)
    u0 = np.clip(np.round(u0).astype(int), 0, B - 1)
    for k in (-1, 0, 1):
        S[np.arange(N), np.clip(u0 + k, 0, B - 1)] = Eb[np.arange(N), 0, np.clip(u0 + k, 0, B - 1)] - 0.1 * abs(k)
    pad = np.full((N, B + 2 * m), -np.inf)
    pen_k = np.ascontiguousarray(pen.transpose(1, 2, 0))[..., None]  # (J, 2 m + 1, N, 1)
    best = np.empty((N, B))
    cand = np.empty((N, B))
    hist = np.empty((J1, N, B))  # the best scores on every ray; the moves are recovered on the path only
    hist[0] = S
    for i in range(1, J1):
        pad[:, m:m + B] = hist[i - 1]
        # window k of u holds pad[u + k] = S[u + k - m]: arriving at u from u + k - m, a move of m - k; the windows
        # compared one by one (cheaper here than sliding_window_view and a reduction over the short window axis)
        np.subtract(pad[:, 0:B], pen_k[i - 1, 0], out=best)
        for k in range(1, 2 * m + 1):
            np.subtract(pad[:, k:k + B], pen_k[i - 1, k], out=cand)
            np.maximum(best, cand, out=best)
        np.add(best, Eb[:, i], out=hist[i])
    uu = np.arange(B)
    S = np.where(np.abs(uu[None, :] - u0[:, None]) <= close_px, hist[-1], -np.inf)
    end = np.argmax(S, axis=1)
    score = S[np.arange(N), end] / J1
    paths = np.zeros((N, J1), dtype=int)
    cur = end.copy()
    nn = np.arange(N)
    ks = np.arange(2 * m + 1)
    for i in range(J1 - 1, -1, -1):
        paths[:, i] = cur
        if i > 0:
            # the move into the path's height on ray i, as the forward pass scored it; the first best wins
            src = cur[:, None] + ks[None, :] - m                                     # (N, 2 m + 1)
            ok = (src >= 0) & (src < B)
            came = np.where(ok, hist[i - 1][nn[:, None], np.clip(src, 0, B - 1)], -np.inf) - pen[:, i - 1, :]
            cur = cur + np.argmax(came, axis=1) - m
    return paths, score


def trace_whole_rings(value, pith, angles_deg, radii, lengths, *, period_px, arc_step_px=6.0, edge_sigma_px=1.0,
                      along_px=10.0, ridge_level=0.5, smooth=8.0, max_step_px=3, gap_px=2.0, close_px=3.0,
                      min_score=0.6, min_rise=0.85, tol_rings=0.3, min_tol_px=3.0, inner_px=None, anchor=2.0,
                      pressure=0.05, ridge_px=3, value_blurred=False):
    """Every ring of a disc as a closed curve round the pith, traced outwards one ring at a time (issue 48).

    The whole circle is one polar edge map (:func:`~torch_appearance.rings.consistency.sector_edges`, periodic,
    rays ``arc_step_px`` apart at the largest radius; ridge centres of the latewood -> earlywood rise, sigma
    ``edge_sigma_px``, smoothed along the ring over ``along_px``, a ridge the largest within ``ridge_px``: narrow
    rings near the bark keep their own ridges). Rings are peeled from the pith outwards. Above the last ring found
    (at first the circle of radius ``inner_px``), the next boundary of every transect (``radii``, helpers included)
    seeds one closed path: a dynamic programme over the rays round the disc that starts on the seed and comes back to
    within ``close_px`` of it, in a band at least ``gap_px`` *above the last ring* at every angle, so that rings
    never cross. A ring runs roughly parallel to its inner neighbour: a move of ``du`` px across the band between
    rays ``a`` px apart costs ``smooth (du / a)^2`` (at most ``max_step_px`` per ray), so a ring whose width changes
    slowly round the disc pays little and a hop onto the next ring pays much. The path collects the edge response,
    ``anchor`` more where it passes (within 1 px) the transects' seeds, and pays ``pressure`` per seed height of
    height above the last ring (the next ring is the nearest one). A path qualifies when its score (mean response
    less the moves' costs, without the anchors) is at least ``min_score`` and the photo rises outwards across it on
    ``min_rise`` of the rays. Of the qualifying paths that pass through at least half as many seeds as the best of
    them (a path seeded on the ring after next, where a transect missed the next ring, passes through few), the best
    scored is the next ring (a path from a false boundary between rings must come back to it and pays for the
    detour). The seeds it passes within ``tol_rings`` of the ring's width (at least ``min_tol_px``) are used up, and
    so are the seeds it leaves below it (boundaries that close nowhere). When no path qualifies, the seeds tried are
    used up and the next ones tried. The band ends at the wood's edge (``lengths`` interpolated round the disc).

    Cost: one band of ``J x B`` per round (``J`` rays, ``B`` about 2.5 ring widths), vectorised over the seeds; on
    the TRAS discs (3000 x 3200 px, 8 transects, 21 - 22 rings) 3 - 4 CPU s (5 before issue 48 item 5's
    speed-ups, 10 - 30 s wall on a loaded machine; ``docs/bench_log.md``).

    Args:
        value: ``(H, W)`` HSV value of the photo (blurred here with sigma 1 px,
            :func:`~torch_appearance.rings.consistency.blurred_value`, unless ``value_blurred``: then it is that already
            and used as it is).
        pith: ``(x, y)`` pixels.
        angles_deg: ``(T,)`` transect directions (degrees from +x towards +y).
        radii: ``T`` arrays of boundary radii (px) on the transects.
        lengths: ``(T,)`` analysed length of each transect (px).
        period_px: the disc's ring period (px; edge normalisation window, ``inner_px`` default half of it).

    Returns:
        dict: ``thetas`` ``(J,)`` ray angles in ``[0, 2 pi)``; ``rings`` ``(K, J)`` radius of each ring on every
        ray, pith outwards; ``scores`` ``(K,)``; ``crossings`` ``(T, K)`` where each ring crosses each transect
        (snapped to the transect's ridge within 2 px); ``used`` ``T`` bool arrays (per boundary: on a ring);
        ``support`` ``(K,)`` the share of transects with a boundary on the ring (within the tolerance above);
        ``seconds``.
    """
    import time

    from .consistency import _sector_edges, _snap_to_ridge, blurred_value

    t0 = time.perf_counter()
    T = len(angles_deg)
    if len(radii) != T or len(lengths) != T:
        raise ValueError(f"radii, lengths: expected one per transect ({T} angles), got {len(radii)} and "
                         f"{len(lengths)}")
    pith = np.asarray(pith, np.float64)
    radii = [np.sort(np.asarray(r, np.float64).reshape(-1)) for r in radii]
    lengths = np.asarray(lengths, np.float64)
    inner = 0.5 * period_px if inner_px is None else float(inner_px)
    r_max = float(lengths.max())
    J = max(16, int(math.ceil(2 * math.pi * r_max / arc_step_px)))
    vb = np.asarray(value, np.float64) if value_blurred else blurred_value(value)
    E, thetas, d = _sector_edges(vb, pith, 0.0, 2 * math.pi, r_max, arc_step_px=arc_step_px, n_rays=J,
                                 periodic=True, edge_sigma_px=edge_sigma_px, along_px=along_px, period_px=period_px,
                                 ridge_level=ridge_level, ridge_px=ridge_px)
    R = E.shape[1]
    rise = d > 0                                                          # the photo rises outwards (unsmoothed)
    ang = np.radians(np.asarray(angles_deg, np.float64)) % (2 * math.pi)
    o = np.argsort(ang)
    lim = np.interp(thetas, ang[o], lengths[o], period=2 * math.pi)       # the wood's edge round the disc
    lim = np.clip(np.floor(lim) - 1, 0, R - 1).astype(int)
    jt = np.round(ang / (2 * math.pi) * J).astype(int) % J                # each transect's ray
    dth = 2 * math.pi / J
    used = [np.zeros(len(r), bool) for r in radii]
    for t in range(T):
        used[t] |= (radii[t] < inner) | (radii[t] > lengths[t] - 1)
    prev = np.full(J, int(math.ceil(inner)))                              # the last ring found (integer px)
    E_ext = np.pad(E, ((0, 0), (0, R)), mode="edge")                      # room for a band beyond the edge map
    rings, scores = [], []
    shifts = np.arange(max_step_px, -max_step_px - 1, -1)                 # window k: a move of m - k
    ii = np.arange(J + 1)
    while True:
        seeds = []  # (transect, index, height above prev on its ray)
        for t in range(T):
            free = np.nonzero(~used[t] & (radii[t] >= prev[jt[t]] + gap_px))[0]
            if len(free):
                seeds.append((t, int(free[0]), float(radii[t][free[0]] - prev[jt[t]] - gap_px)))
        if not seeds:
            break
        N = len(seeds)
        B = int(min(R, max(16, math.ceil(2.5 * max(s[2] for s in seeds) + 3 * close_px + 2))))
        rays = (jt[[s[0] for s in seeds]][:, None] + ii[None, :]) % J       # (N, J + 1)
        base = prev[rays] + int(gap_px)                                    # radius of u = 0
        # the band of every ray: B radii from its base, copied as rows (the edge map runs on past the image; those
        # radii lie beyond the wood's edge and read -1)
        if int(base.max()) + B > E_ext.shape[1]:
            E_ext = np.pad(E, ((0, 0), (0, int(base.max()) + B - R)), mode="edge")
        Eb = np.lib.stride_tricks.sliding_window_view(E_ext, B, axis=1)[rays, base]    # (N, J + 1, B)
        np.putmask(Eb, np.arange(B)[None, None, :] > (lim[rays] - base)[..., None], -1.0)
        u0 = np.array([s[2] for s in seeds])
        # a little pressure towards the inner ring (the next ring is the nearest one that closes) ...
        Eb -= pressure * np.arange(B)[None, None, :] / np.maximum(u0, 2.0)[:, None, None]
        # ... and the transects' next boundaries as anchors
        for t, k, _ in seeds:
            i_t = (jt[t] - rays[:, 0]) % J                                 # (N,) the ray of transect t per seed
            for i_ in (i_t, np.where(i_t == 0, J, -1)):
                ok = i_ >= 0
                u_t = np.round(radii[t][k] - base[np.arange(N), np.maximum(i_, 0)]).astype(int)
                for du in (-1, 0, 1):
                    uu = u_t + du
                    sel = ok & (uu >= 0) & (uu < B)
                    Eb[np.nonzero(sel)[0], i_[sel], uu[sel]] += anchor
        arc = np.maximum((base[:, :-1] + 0.5 * B) * dth, 1e-3)            # (N, J) px between rays
        pen = smooth * (shifts[None, None, :] / arc[..., None]) ** 2
        paths, score = _band_trace(Eb, u0, pen, close_px)
        score = score - anchor * len(seeds) / (J + 1)                     # (about) the edges' own score
        r_path = base + paths                                              # (N, J + 1) absolute radius
        good = []
        for n in range(N):
            if not np.isfinite(score[n]) or score[n] < min_score:
                continue
            curve = np.empty(J, int)
            curve[rays[n, :-1]] = r_path[n, :-1]
            if rise[np.arange(J), np.minimum(curve, R - 1)].mean() >= min_rise:
                # the seeds it passes through: the ring most transects agree on is the next one
                agree = sum(abs(radii[t][k] - curve[jt[t]])
                            <= max(min_tol_px, tol_rings * (curve[jt[t]] - prev[jt[t]])) for t, k, _ in seeds)
                good.append((agree, float(score[n]), n, curve))
        tried = {(s[0], s[1]) for s in seeds}
        if not good:
            for t, k in tried:
                used[t][k] = True
            continue
        most = max(g[0] for g in good)
        _, _, n, curve = max((g for g in good if 2 * g[0] >= most), key=lambda g: g[1])
        rings.append(curve.astype(np.float64))
        scores.append(float(score[n]))
        for t in range(T):  # the seeds on this ring, and those it leaves below it, are used up
            x = float(curve[jt[t]])
            used[t] |= radii[t] <= x + max(min_tol_px, tol_rings * (x - prev[jt[t]]))
        prev = np.maximum(prev, curve)
    K = len(rings)
    rings = np.asarray(rings).reshape(K, J)
    crossings = np.zeros((T, K))
    for t in range(T):
        e = E[jt[t]]
        for k in range(K):
            crossings[t, k] = _snap_to_ridge(e, float(rings[k, jt[t]]))
    on = [np.zeros(len(r), bool) for r in radii]
    support = np.zeros(K)
    for t in range(T):
        if K:
            x = crossings[t]
            tol = np.maximum(min_tol_px, tol_rings * np.diff(np.r_[inner, x]))
            near = np.abs(radii[t][:, None] - x[None, :]) <= tol[None, :]
            on[t] = near.any(1)
            support += near.any(0)
    return dict(thetas=thetas, rings=rings, scores=np.asarray(scores), crossings=crossings, used=on,
                support=support / max(T, 1), seconds=time.perf_counter() - t0)


def place_whole_rings(radii, crossings, *, inner_px, length_px, place=True, drop=True, support=None,
                      min_support=0.5, tol_rings=0.3, min_tol_px=3.0):
    """One transect's boundaries made to agree with the whole rings that cross it (:func:`trace_whole_rings`).

    With ``place``, a ring whose crossing (``crossings``, px from the pith) has no boundary within ``tol_rings`` of
    its width there (at least ``min_tol_px``) is placed on the transect (between ``inner_px`` and
    ``length_px - 2``); with ``drop``, a boundary between the innermost and the second outermost crossing that lies
    within that tolerance of no crossing is dropped (a boundary that closes nowhere). Beyond the second outermost
    ring nothing is dropped: the outermost ring is where the tracer stopped, often past narrow rings near the bark it
    could not follow (on the independent synthetic discs dropping there cost 0.04 at 3 px on the light-bark disc and
    0.016 on the blurred one, and changed nothing on the TRAS discs). Only rings with ``support`` (per
    crossing, :func:`trace_whole_rings`' share of transects that found the ring) of at least ``min_support`` count:
    on the TRAS discs the rings that few transects found were mostly false rings the people did not mark
    (leave-one-disc-out in ``docs/bench_log.md``).

    Returns:
        ``(keep, new)``: ``keep`` bool per boundary of ``radii`` (in its order), ``new`` the radii placed.
    """
    pos = np.asarray(radii, np.float64).reshape(-1)
    x = np.asarray(crossings, np.float64).reshape(-1)
    if support is not None:
        x = x[np.asarray(support, np.float64).reshape(-1) >= min_support]
    x = np.sort(x)
    x = x[(x >= inner_px) & (x <= length_px - 2.0)]
    keep = np.ones(len(pos), bool)
    if not len(x):
        return keep, np.zeros(0)
    tol = np.maximum(min_tol_px, tol_rings * np.diff(np.r_[inner_px, x]))
    near = np.abs(pos[:, None] - x[None, :]) <= tol[None, :]
    new = x[~near.any(0)] if place else np.zeros(0)
    if drop and len(x) >= 3:
        keep = near.any(1) | (pos <= x[0]) | (pos >= x[-2])
    return keep, new
