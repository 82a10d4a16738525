"""Ring boundaries on stained microscopy cross-sections (section mode, split out of
:mod:`~torch_appearance.rings.dendro`).

Section mode (:func:`detect_section_boundaries`): stained *microscopy* cross-sections (cell-level detail, a few
hundred pixels, typically one boundary) have no Gabor-scale ring signal; the boundary is where small, flattened,
thick-walled (dark) latewood cells meet large thin-walled earlywood cells, a change of cell size / wall density.

1. Two feature maps at cell scale (``cell_px``, the typical cell diameter): the wall darkness ``1 - V`` (HSV value,
   so that saturated stains count as light and only dense / thick walls as dark) smoothed with sigma ``cell/4``,
   and its local heterogeneity (standard deviation over sigma ``cell`` of the ``cell/4``-smoothed ``V``), each
   normalised by its median absolute deviation.
2. Ring boundaries run across the radial cell files and rays, which dominate the wall-scale gradient orientation
   (sigma ``cell/12``): path directions are searched within ``angle_window_deg`` of the direction perpendicular
   to the dominant wall lines (a global, anatomical prior - no per-image tuning).
3. For each direction the image is resampled in a rotated frame, the features are smoothed along the path
   direction (sigma ``1.5 cell``) and a two-sided contrast (mean over ``1.5 cell`` px on one side minus the other,
   combined over features) is formed. A dynamic programme finds the maximum-sum path (one step sideways at most
   per pixel forward, free start and end, reward ``contrast / p99.5 - min_rel_contrast``, zero outside the image):
   the strongest long transition, which may also just clip a corner of the image.
4. Refinement: within ``1.5 cell`` of that path the sharpest step of ``V`` across the path (Gaussian derivative,
   sigma ``cell/3``, smoothed along the path) is followed by a second dynamic programme, and made sub-pixel by a
   parabola.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from .dendro import hsv_value
from .evaluation import boundary_f_measure, mask_centerline, resample_polyline

__all__ = ["SectionBoundary", "boundary_f_measure", "detect_section_boundaries", "mask_centerline",
           "resample_polyline"]


@dataclass
class SectionBoundary:
    """A ring boundary detected on a microscopy section.

    Attributes:
        points: ``(N, 2)`` float64 ``(x, y)`` pixel coordinates of the boundary polyline, ordered along the curve
            (about 1 px apart); empty ``(0, 2)`` when no boundary was found.
        angle_deg: direction of the search frame the curve was found in (degrees from +x towards +y, [0, 180)).
        score: the path score (sum of the reward along the path; larger = stronger, longer transition).
        info: diagnostics (cell scale, the radial direction estimate, the angles searched).
    """

    points: np.ndarray
    angle_deg: float
    score: float
    info: dict = field(default_factory=dict)


def _rgb_min_max(image):
    """``(min, max)`` over the colour channels of an ``(H, W, 3|4)`` or ``(H, W)`` image, float64, validated."""
    v = hsv_value(image)  # validation (dtype, shape, size, finiteness)
    a = np.asarray(image)
    if a.ndim == 3 and a.shape[2] in (3, 4):
        mn = a[..., :3].min(axis=2).astype(np.float64)
    else:
        mn = v.astype(np.float64)
    return mn, v.astype(np.float64)


def _max_sum_path(reward, move_penalty=0.05):
    """Maximum-sum path through ``reward`` ``(n_v, n_u)``, one column per step, ``|dv| <= 1`` per step.

    The path starts and ends at any column (a prefix with negative sum is dropped, as in Kadane's algorithm).
    Returns ``(score, path)`` with ``path`` ``(K, 2)`` int ``(v, u)`` rows for consecutive columns ``u``.
    """
    n, m = reward.shape
    score = np.empty((n, m))
    arg = np.full((n, m), -1, np.int64)
    score[:, 0] = reward[:, 0]
    rows = np.arange(n)
    for j in range(1, m):
        pp = np.pad(np.maximum(score[:, j - 1], 0.0), 1, constant_values=-1.0)
        cand = np.stack([pp[0:n] - move_penalty, pp[1:n + 1], pp[2:n + 2] - move_penalty])
        a = cand.argmax(0)
        best = cand[a, rows]
        arg[:, j] = np.where(best > 0, rows + a - 1, -1)
        score[:, j] = reward[:, j] + np.maximum(best, 0.0)
    vi, j = np.unravel_index(np.argmax(score), score.shape)
    total = float(score[vi, j])
    path = []
    while j >= 0 and vi >= 0:
        path.append((vi, j))
        vi = arg[vi, j]
        j -= 1
    return total, np.array(path[::-1], dtype=np.int64).reshape(-1, 2)


def _rotated_grid(shape, theta):
    """Sample grid ``(Y, X, inside)`` ``(n, n)`` of a frame whose columns run along ``theta`` through the centre."""
    H, W = shape
    n = int(math.ceil(math.hypot(H, W))) + 2
    t = np.arange(n) - (n - 1) / 2.0
    c, s = math.cos(theta), math.sin(theta)
    X = (W - 1) / 2.0 + t[None, :] * c - t[:, None] * s
    Y = (H - 1) / 2.0 + t[None, :] * s + t[:, None] * c
    inside = (X >= -0.5) & (X <= W - 0.5) & (Y >= -0.5) & (Y <= H - 0.5)
    return Y, X, inside


def detect_section_boundaries(image, *, cell_px: float = 8.0, angle_window_deg: float = 35.0, n_angles: int = 13,
                              min_rel_contrast: float = 0.5) -> SectionBoundary:
    """The ring boundary on a stained microscopy cross-section (module docstring, "Section mode").

    Args:
        image: ``(H, W, 3)`` RGB in ``[0, 1]`` (or ``(H, W)`` gray) numpy array, cell walls darker than lumens.
        cell_px: typical cell (tracheid) diameter in pixels; all scales derive from it (default 8 px, the
            256 x 256 patches of the tree-ring-analyzer data set).
        angle_window_deg: path directions searched around the perpendicular of the dominant wall-line direction
            (the radial files and rays), in degrees.
        n_angles: number of directions searched in that window (odd, >= 1).
        min_rel_contrast: the path reward is ``contrast / p99.5(contrast) - min_rel_contrast``; larger values give
            shorter paths that only follow the strongest part of the transition.

    Returns:
        :class:`SectionBoundary` (one curve: the strongest transition; empty points if none is positive).

    Raises:
        ValueError / TypeError: bad image or parameters.

    Example:
        >>> # res = detect_section_boundaries(rgb); res.points  # (N, 2) x, y polyline
    """
    for name, val, lo in (("cell_px", cell_px, 2.0), ("angle_window_deg", angle_window_deg, 0.0)):
        if isinstance(val, bool) or not isinstance(val, (int, float, np.integer, np.floating)) \
                or not math.isfinite(val) or val < lo:
            raise ValueError(f"{name} must be a finite number >= {lo:g}; got {val!r}")
    if angle_window_deg > 90:
        raise ValueError(f"angle_window_deg must be <= 90; got {angle_window_deg!r}")
    if isinstance(n_angles, bool) or not isinstance(n_angles, (int, np.integer)) or n_angles < 1:
        raise ValueError(f"n_angles must be an integer >= 1; got {n_angles!r}")
    if not (isinstance(min_rel_contrast, (int, float)) and 0 <= min_rel_contrast < 1):
        raise ValueError(f"min_rel_contrast must be in [0, 1); got {min_rel_contrast!r}")
    gmin, gv = _rgb_min_max(image)
    if min(gv.shape) < 4 * cell_px:
        raise ValueError(f"image {gv.shape} is too small for cell_px={cell_px:g} (needs >= {4 * cell_px:g} px)")
    cell = float(cell_px)
    # 1. features, z-scored by median / MAD
    dark = ndimage.gaussian_filter(1.0 - gv, cell / 4)
    a = ndimage.gaussian_filter(gv, cell / 4)
    m = ndimage.gaussian_filter(a, cell)
    het = np.sqrt(np.maximum(ndimage.gaussian_filter(a * a, cell) - m * m, 0.0))
    feats = []
    for f in (dark, het):
        med = np.median(f)
        feats.append((f - med) / (1.4826 * np.median(np.abs(f - med)) + 1e-9))
    # 2. dominant wall-line direction (doubled-angle mean of the wall-scale gradient): the radial files / rays
    gx = ndimage.gaussian_filter(gmin, cell / 12, order=(0, 1))
    gy = ndimage.gaussian_filter(gmin, cell / 12, order=(1, 0))
    grad_dir = 0.5 * math.atan2(2 * (gx * gy).sum(), (gx * gx - gy * gy).sum())  # normal of the wall lines
    k = np.arange(n_angles) - (n_angles - 1) / 2.0
    angles = grad_dir + math.radians(angle_window_deg) * (k / max((n_angles - 1) / 2.0, 1.0))
    # 3. oriented two-sided contrast per direction, then the maximum-sum path
    half = max(2, int(round(1.5 * cell)))
    su = 1.5 * cell
    w = np.r_[-np.ones(half), 0.0, np.ones(half)] / half
    frames = []
    for th in angles:
        Y, X, inside = _rotated_grid(gv.shape, th)
        c2 = 0.0
        for f in feats:
            fr = ndimage.gaussian_filter1d(ndimage.map_coordinates(f, [Y, X], order=1, mode="reflect"), su, axis=1)
            c2 = c2 + ndimage.correlate1d(fr, w, axis=0, mode="reflect") ** 2
        frames.append((th, np.sqrt(c2), Y, X, inside))
    ref = np.percentile(np.concatenate([c[ins] for _, c, _, _, ins in frames]), 99.5) + 1e-12
    best = None
    for th, c, Y, X, inside in frames:
        score, path = _max_sum_path(np.where(inside, c / ref - min_rel_contrast, 0.0))
        if best is None or score > best[0]:
            best = (score, th, path, Y, X, inside)
    score, th, path, Y, X, inside = best
    info = dict(cell_px=cell, radial_deg=(math.degrees(grad_dir) + 90) % 180,
                angles_deg=np.degrees(angles) % 180)
    if score <= 0 or len(path) < 2:
        return SectionBoundary(points=np.zeros((0, 2)), angle_deg=math.degrees(th) % 180, score=0.0, info=info)
    # 4. refinement on the sharp step of V across the path, sub-pixel by a parabola
    gr = ndimage.map_coordinates(ndimage.gaussian_filter(gv, 1.0), [Y, X], order=1, mode="reflect")
    d = np.abs(ndimage.gaussian_filter1d(ndimage.gaussian_filter1d(gr, su, axis=1), cell / 3, axis=0, order=1))
    cols, v0 = path[:, 1], path[:, 0]
    sub = d[:, cols]
    band = np.abs(np.arange(d.shape[0])[:, None] - v0[None, :]) <= int(round(1.5 * cell))
    _, p2 = _max_sum_path(np.where(band, sub / (sub[band].max() + 1e-12), -1e3), move_penalty=0.0)
    vv = p2[:, 0].astype(np.float64)
    i = np.clip(p2[:, 0], 1, d.shape[0] - 2)
    y0, y1, y2 = sub[i - 1, p2[:, 1]], sub[i, p2[:, 1]], sub[i + 1, p2[:, 1]]
    den = y0 - 2 * y1 + y2
    vv = i + np.where(den < 0, np.clip(0.5 * (y0 - y2) / np.where(den < 0, den, -1.0), -0.5, 0.5), 0.0)
    uu = cols[p2[:, 1]].astype(np.float64)
    pts = np.stack([ndimage.map_coordinates(X, [vv, uu], order=1), ndimage.map_coordinates(Y, [vv, uu], order=1)], 1)
    H, W = gv.shape
    ok = (pts[:, 0] >= -0.5) & (pts[:, 0] <= W - 0.5) & (pts[:, 1] >= -0.5) & (pts[:, 1] <= H - 0.5)
    return SectionBoundary(points=pts[ok], angle_deg=math.degrees(th) % 180, score=score, info=info)
