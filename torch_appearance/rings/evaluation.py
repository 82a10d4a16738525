"""Scoring ring detections against labels: one-to-one matching of boundary points (ring counting on cores and
transects) and the boundary F-measure of curves (microscopy sections).

Curves (:func:`boundary_f_measure`): a boundary-F-measure (Martin et al. 2004) at a distance tolerance:
the labelled curve is the centre line of the mask (:func:`mask_centerline`), the detected polyline is resampled at
1 px arc-length steps; sensitivity = fraction of label centre-line pixels within ``tolerance_px`` of the detected
curve, precision = fraction of detected samples within ``tolerance_px`` of the label. A one-to-one point matching
(:func:`match_boundaries`) is the right metric for *counting* rings on a core; for a single curve it would depend
on the sampling and on small length differences, so the distance-based BF measure is used instead.
"""
from __future__ import annotations

import math

import numpy as np
from scipy import ndimage

__all__ = ["boundary_f_measure", "mask_centerline", "match_boundaries", "resample_polyline"]


def mask_centerline(mask) -> np.ndarray:
    """``(M, 2)`` ``(x, y)`` centre-line pixels of a thin boundary mask (``(H, W)``, nonzero = boundary).

    The ridge of the distance transform inside the mask (pixels not smaller than any 8-neighbour): one or two px
    wide for the 1-4 px wide hand-drawn polylines; pixels of a 1 px line are all kept.
    """
    m = np.asarray(mask)
    if m.ndim == 3 and m.shape[2] == 1:
        m = m[..., 0]
    if m.ndim != 2:
        raise ValueError(f"mask must have shape (H, W); got {np.asarray(mask).shape}")
    m = m > 0
    dt = ndimage.distance_transform_edt(m)
    ridge = m & (dt >= ndimage.maximum_filter(dt, size=3) - 1e-9)
    ys, xs = np.nonzero(ridge)
    return np.stack([xs, ys], 1).astype(np.float64)


def resample_polyline(points, step_px: float = 1.0) -> np.ndarray:
    """Points every ``step_px`` of arc length along an ``(N, 2)`` polyline (both ends included)."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    if not (step_px > 0):
        raise ValueError(f"step_px must be > 0; got {step_px!r}")
    if len(p) < 2:
        return p.copy()
    s = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))]
    t = np.r_[np.arange(0.0, s[-1], step_px), s[-1]]
    return np.stack([np.interp(t, s, p[:, 0]), np.interp(t, s, p[:, 1])], 1)


def boundary_f_measure(detected, labels, tolerance_px: float = 3.0) -> dict:
    """Boundary F-measure of detected polyline(s) against labelled curve pixels (module docstring).

    Args:
        detected: ``(N, 2)`` ``(x, y)`` polyline (consecutive points are joined; resampled at 1 px steps), or a
            list of such polylines (e.g. several ring boundaries), pooled.
        labels: ``(M, 2)`` ``(x, y)`` label curve pixels (e.g. :func:`mask_centerline`).
        tolerance_px: distance tolerance (inclusive), > 0.

    Returns:
        dict with ``sensitivity`` (label pixels within tolerance of the detection), ``precision`` (detected samples
        within tolerance of a label), ``f1``, ``mean_error_px`` (mean distance of the detected samples to the label,
        NaN without detection), ``detected`` (samples) and ``labelled`` (pixels). Empty sets give 0.
    """
    from scipy.spatial import cKDTree

    tol = float(tolerance_px) if not isinstance(tolerance_px, bool) else float("nan")
    if not math.isfinite(tol) or tol <= 0:
        raise ValueError(f"tolerance_px must be a finite number > 0; got {tolerance_px!r}")
    lines = list(detected) if isinstance(detected, (list, tuple)) else [detected]
    checked = []
    for name, x in [("detected", line) for line in lines] + [("labels", labels)]:
        a = np.asarray(x, dtype=np.float64)
        if a.size == 0:
            a = a.reshape(0, 2)
        if a.ndim != 2 or a.shape[1] != 2:
            raise ValueError(f"{name} must have shape (N, 2); got {np.asarray(x).shape}")
        if not np.isfinite(a).all():
            raise ValueError(f"{name} contains NaN or infinite coordinates")
        checked.append(a)
    lab = checked.pop()

    def samples(step):
        pts = [resample_polyline(a, step) for a in checked if len(a)]
        return np.concatenate(pts) if pts else np.zeros((0, 2))

    det = samples(1.0)
    if len(det) == 0 or len(lab) == 0:
        return dict(sensitivity=0.0, precision=0.0, f1=0.0, mean_error_px=float("nan"), detected=len(det),
                    labelled=len(lab))
    d_lab = cKDTree(samples(0.25)).query(lab)[0]
    d_det = cKDTree(lab).query(det)[0]
    sens, prec = float((d_lab <= tol).mean()), float((d_det <= tol).mean())
    f1 = 2 * sens * prec / (sens + prec) if sens + prec > 0 else 0.0
    return dict(sensitivity=sens, precision=prec, f1=f1, mean_error_px=float(d_det.mean()), detected=len(det),
                labelled=len(lab))



def match_boundaries(detected, labels, tolerance_px: float = 3.0) -> dict:
    """One-to-one matching of detected and labelled boundary points within a tolerance (Fabijanska et al. 2017).

    Pairs are chosen by an optimal assignment (:func:`scipy.optimize.linear_sum_assignment`) that maximises the
    number of pairs closer than ``tolerance_px`` and, among those, minimises the summed distance; each detection
    and each label is used at most once, so duplicates count as false positives.

    Args:
        detected: ``(N, 2)`` (or ``(N,)`` / ``(N, 1)`` for 1D positions along the axis) pixel coordinates.
        labels: ``(M, 2)`` (or 1D) pixel coordinates in the same units.
        tolerance_px: largest distance of a match (inclusive), > 0.

    Returns:
        dict with ``sensitivity`` (matched / labelled), ``precision`` (matched / detected), ``f1``,
        ``mean_error_px`` (mean distance of the matches, NaN without matches), ``matched``, ``detected``,
        ``labelled`` and ``pairs`` (``(K, 2)`` int indices ``(detected, label)``). Empty sets give 0 (not NaN)
        sensitivity / precision.

    Example:
        >>> r = match_boundaries([[10, 0], [20, 0], [21, 0]], [[11, 0], [20, 0], [40, 0]], tolerance_px=3)
        >>> r["matched"], round(r["sensitivity"], 3), round(r["precision"], 3)
        (2, 0.667, 0.667)
    """
    from scipy.optimize import linear_sum_assignment

    tol = float(tolerance_px) if not isinstance(tolerance_px, bool) else float("nan")
    if not math.isfinite(tol) or tol <= 0:
        raise ValueError(f"tolerance_px must be a finite number > 0; got {tolerance_px!r}")

    def as_pts(x, name):
        a = np.asarray(x, dtype=np.float64)
        if a.ndim == 1:
            a = a[:, None]
        if a.ndim != 2 or a.shape[1] not in (1, 2):
            raise ValueError(f"{name} must have shape (N, 2) or (N,); got {np.asarray(x).shape}")
        if not np.isfinite(a).all():
            raise ValueError(f"{name} contains NaN or infinite coordinates")
        return a

    d, l = as_pts(detected, "detected"), as_pts(labels, "labels")
    if d.shape[1] != l.shape[1] and len(d) and len(l):
        raise ValueError(f"detected and labels must have the same dimension; got {d.shape[1]} and {l.shape[1]}")
    pairs = np.zeros((0, 2), dtype=np.int64)
    if len(d) and len(l):
        dist = np.linalg.norm(d[:, None, :] - l[None, :, :], axis=2)
        ok = dist <= tol
        # cost: a large reward per admissible pair dominates, the distance breaks ties
        cost = np.where(ok, dist - (tol + 1.0) * 1e3, 0.0)
        r, c = linear_sum_assignment(cost)
        sel = ok[r, c]
        pairs = np.stack([r[sel], c[sel]], 1).astype(np.int64)
        errors = dist[pairs[:, 0], pairs[:, 1]]
    else:
        errors = np.zeros(0)
    m = len(pairs)
    sens = m / len(l) if len(l) else 0.0
    prec = m / len(d) if len(d) else 0.0
    f1 = 2 * sens * prec / (sens + prec) if sens + prec > 0 else 0.0
    return dict(sensitivity=sens, precision=prec, f1=f1, mean_error_px=float(errors.mean()) if m else float("nan"),
                matched=m, detected=len(d), labelled=len(l), pairs=pairs)
