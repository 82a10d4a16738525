"""Dendrochronology: ring-boundary detection on increment cores and along transects of disc / board images.

Boundary definition (dendrochronological practice): the *sharp* transition from the dark latewood of one year to the
light earlywood of the next, reported in order pith -> bark. Along the direction pith -> bark a ring's intensity
falls gradually (earlywood -> latewood) and then rises abruptly at the boundary.

How a boundary is located (both modes):

1. The curved Gabor filter (:func:`~torch_appearance.rings.gabor.curved_gabor`) is run with its normal oriented
   pith -> bark (this resolves the phase-sign ambiguity using ``bark``), so the phase ``I_phi`` grows by ``2 pi`` per
   ring towards the bark and the local ring signal is ``a cos(I_phi)``: light at ``I_phi = 0``, dark at ``pi``.
2. The phase along the axis (or transect) is unwrapped and split into *cycles* that start at each ``I_phi = pi/2``
   crossing (the filter's light -> dark zero crossing, which lies *inside* the ring because the ring profile is a
   sawtooth, not a cosine). One cycle covers the latewood minimum and the following rise, i.e. exactly one boundary.
3. Within each cycle the steepest intensity rise is found (largest ``dV/dt`` of the along-ring averaged V profile
   smoothed with sigma 1 px, sub-pixel by a parabola through the derivative peak) and the boundary is placed at the
   latewood-side foot of that rise, where ``dV/dt`` has dropped to ``edge_level`` (0.8) of its peak: the end of the
   latewood. (0.8 was chosen on the MtreeRing core 001; F1 at 3 px is 0.96-1.0 for levels 0.6-0.9 there, 0.88
   for the steepest point itself, which sits 1-4 px into the earlywood side of the labelled latewood edges.) Cycles whose Gabor magnitude
   is low (no ring signal) or whose rise is negligible are dropped.

So the Gabor phase decides *how many* boundaries there are and roughly where (robust to pores, cracks and noise),
while the intensity profile gives the sub-pixel position of the sharp edge. Using the phase level alone would put
the boundary a quarter period too early for sawtooth rings; using a fixed phase offset fails when the latewood
fraction varies from ring to ring.

Core mode (:func:`detect_core_boundaries`): the image is rotated so that the core axis is horizontal with the pith
on the left, its short side is resampled to a uniform width (``width_px``; as in the paper, so that the filter
parameters do not depend on the scan - the long axis keeps its resolution), converted to the HSV V channel and
filtered. The phase and V are averaged over the central half of the rows after compensating the mean ring tilt
(a shear), which also handles inclined boundaries. Boundary points are reported on the core's centre line.

Transect mode (:func:`detect_transect_boundaries`): the whole image is filtered with its normal oriented along the
transect, rings are traced (:func:`~torch_appearance.rings.tracing.trace_rings`) and their crossings with the
transect give the cycles; the boundary is then refined on the V profile sampled along the transect as above.

Ring widths: distance (px) between consecutive boundaries times the pixel size (``25.4 / dpi`` mm).

Section mode (microscopy cross-sections) lives in :mod:`~torch_appearance.rings.section`, the evaluation
(:func:`match_boundaries`, :func:`boundary_f_measure`) in :mod:`~torch_appearance.rings.evaluation`; both are
re-exported here.
"""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy import ndimage

from ..checks import check_point_in_image
from .gabor import _dominant_period, curved_gabor
from .evaluation import boundary_f_measure, mask_centerline, match_boundaries, resample_polyline
from .tracing import trace_rings

__all__ = ["RingBoundaries", "boundary_f_measure", "detect_core_boundaries", "growth_direction",
           "detect_transect_boundaries", "hsv_value", "mask_centerline", "match_boundaries", "resample_polyline",
           "ring_widths_mm"]

_BARK = ("left", "right", "top", "bottom")


@dataclass
class RingBoundaries:
    """Detected ring boundaries, ordered pith -> bark.

    Attributes:
        points: ``(N, 2)`` float64 ``(x, y)`` boundary positions in pixels of the input image.
        widths_px: ``(N,)`` distance to the previous boundary in pixels (NaN for the first).
        widths_mm: ``(N,)`` ring widths in mm (NaN for the first, all NaN without a pixel size).
        pixel_size_mm: the pixel size used, or None.
        info: diagnostics (period estimate, Gabor parameters, profile arrays).
    """

    points: np.ndarray
    widths_px: np.ndarray
    widths_mm: np.ndarray
    pixel_size_mm: float | None = None
    info: dict = field(default_factory=dict)


# ----------------------------------------------------------------------------------------------------------------
# helpers
# ----------------------------------------------------------------------------------------------------------------
def hsv_value(image) -> np.ndarray:
    """HSV V channel (``max(R, G, B)``) of an ``(H, W, 3|4)`` image, or the image itself if it is ``(H, W)``."""
    a = np.asarray(image)
    if a.dtype.kind not in "fiub":
        raise TypeError(f"image must hold real numbers; got dtype {a.dtype}")
    if a.ndim == 3 and a.shape[2] in (3, 4):
        a = a[..., :3].max(axis=2)
    elif a.ndim == 3 and a.shape[2] == 1:
        a = a[..., 0]
    if a.ndim != 2:
        raise ValueError(f"image must have shape (H, W) or (H, W, 3); got {np.asarray(image).shape}")
    a = a.astype(np.float32)
    if a.size == 0 or min(a.shape) < 4:
        raise ValueError(f"image must be at least 4x4 pixels; got shape {a.shape}")
    if not np.isfinite(a).all():
        raise ValueError("image contains NaN or infinite values")
    return a


def _pixel_size(dpi, pixel_size_mm) -> float | None:
    if dpi is not None and pixel_size_mm is not None:
        raise ValueError("give dpi or pixel_size_mm, not both")
    v = dpi if dpi is not None else pixel_size_mm
    if v is None:
        return None
    name = "dpi" if dpi is not None else "pixel_size_mm"
    if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)) or not math.isfinite(v) or v <= 0:
        raise ValueError(f"{name} must be a finite number > 0; got {v!r}")
    return 25.4 / float(v) if dpi is not None else float(v)


def ring_widths_mm(points, pixel_size_mm=None) -> tuple[np.ndarray, np.ndarray]:
    """Widths between consecutive ``(N, 2)`` boundary points: ``(widths_px, widths_mm)``, NaN for the first."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    wpx = np.full(len(pts), np.nan)
    if len(pts) > 1:
        wpx[1:] = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    wmm = wpx * pixel_size_mm if pixel_size_mm is not None else np.full(len(pts), np.nan)
    return wpx, wmm


def _cycle_boundaries(v, z, *, min_rel_magnitude=0.15, min_rel_rise=0.1, smooth=1.0, cycle_start=None,
                      edge_level=0.8, max_back=8):
    """Boundaries on a 1D profile ordered pith -> bark (index 0 = pith side).

    Args:
        v: ``(L,)`` intensity (V) profile.
        z: ``(L,)`` complex Gabor response (phase grows towards the bark), or None when ``cycle_start`` is given.
        cycle_start: optional sorted float positions of the ``pi/2`` crossings (transect mode, from traced rings).

    Returns:
        ``(K,)`` sub-pixel positions (profile index units) of the steepest rise in each accepted cycle.
    """
    L = len(v)
    if cycle_start is None:
        phi = np.unwrap(np.angle(z))
        # cycle index: cycle k spans phi in [2 pi k + pi/2, 2 pi (k + 1) + pi/2)
        cyc = np.floor((phi - math.pi / 2) / (2 * math.pi)).astype(np.int64)
        # phase may locally run backwards (noise); make the index monotone so that every sample has one cycle
        cyc = np.maximum.accumulate(cyc)
        mag = np.abs(z)
    else:
        cyc = np.searchsorted(np.asarray(cycle_start, dtype=np.float64), np.arange(L), side="right") - 1
        mag = None
    # derivative of the profile smoothed with sigma = smooth px, reduced to sigma = smooth / 2 in short cycles
    # (< 10 px) where it would flatten the rise of narrow rings (sigma 1 px leaves 11 % of a 3 px period)
    v64 = v.astype(np.float64)
    dv = np.gradient(ndimage.gaussian_filter1d(v64, smooth)) if smooth > 0 else np.gradient(v64)
    if smooth > 0:
        _, inv, counts = np.unique(cyc, return_inverse=True, return_counts=True)
        short = counts[inv] < 10
        if short.any():
            dv = np.where(short, np.gradient(ndimage.gaussian_filter1d(v64, 0.5 * smooth)), dv)
    c = cyc
    # steepest rise per cycle (vectorised group-by: sort by (cycle, -dv)); partial cycles at the profile ends are
    # kept - their maximum is rejected below if it sits on the end or is not a real rise
    keep_idx = c >= 0 if cycle_start is not None else np.ones(L, bool)
    idx = np.nonzero(keep_idx)[0]
    if len(idx) == 0:
        return np.zeros(0)
    c = c[idx]
    order = np.lexsort((-dv[idx], c))
    first = np.r_[True, c[order][1:] != c[order][:-1]]
    best = idx[order[first]]
    keep = (best > 0) & (best < L - 1)
    # acceptance: a real rise, and (core mode) a ring signal
    scale = np.percentile(np.abs(dv), 99) + 1e-12
    keep &= dv[best] > min_rel_rise * scale
    if mag is not None:
        keep &= mag[best] > min_rel_magnitude * np.median(mag)
    best = best[keep]
    # sub-pixel: parabola through the derivative peak
    y0, y1, y2 = dv[best - 1], dv[best], dv[best + 1]
    den = y0 - 2 * y1 + y2
    off = np.where(den < 0, 0.5 * (y0 - y2) / np.where(den < 0, den, -1.0), 0.0)
    pos = best + np.clip(off, -0.5, 0.5)
    if edge_level < 1.0 and len(best):
        # move to the latewood-side foot of the rise: where dV/dt has fallen to edge_level x its peak (linear
        # interpolation between samples), searching at most max_back samples towards the pith
        thr = edge_level * dv[best]
        foot = pos.copy()
        active = np.ones(len(best), bool)
        for k in range(1, max_back + 1):
            i = best - k
            inside = i >= 0
            below = inside & (dv[np.maximum(i, 0)] <= thr)
            hit = active & below
            if hit.any():
                a_, b_ = dv[i[hit]], dv[i[hit] + 1]
                foot[hit] = i[hit] + (thr[hit] - a_) / np.where(b_ > a_, b_ - a_, 1.0)
            active &= ~below & inside
            if not active.any():
                break
        pos = np.where(foot <= pos, foot, pos)
    return pos


def _gabor_params(img, p, q, f_max):
    period = _dominant_period(__import__("torch").from_numpy(img), 1.0 / min(400, max(img.shape)), f_max)
    if p is None:
        p = int(np.clip(round(1.5 * period), 8, 150))
    if q is None:
        q = int(np.clip(min(img.shape[0] // 2 - 1, round(period)), 2, MAX_CORE_Q))
    return p, q, period


# ----------------------------------------------------------------------------------------------------------------
# core mode
# ----------------------------------------------------------------------------------------------------------------
def growth_direction(image, axis: str | None = None, blocks: int | None = None) -> dict:
    """Which end of a core holds the bark, from the shape of its rings alone.

    Along the direction pith → bark a ring lightens at its start (the sharp latewood → earlywood step) and darkens
    gradually through the year, so the derivative of the intensity profile has a few large positive values and many
    small negative ones: its skewness is positive pith → bark and negative the other way. The profile is the HSV
    value averaged over the middle 40 % of the core's width, detrended over a tenth of its length and smoothed by
    1 px; its derivative's skewness is taken over ``blocks`` equal pieces, whose mean and standard error give ``z``.

    Args:
        image: ``(H, W, 3)`` RGB or ``(H, W)`` gray core image. axis: ``"x"`` (bark left or right) or ``"y"``
            (top or bottom); default: the image's long side. blocks: pieces for the standard error (>= 3, at least
            16 px each; default: as many as fit, at most 8).

    Returns:
        dict: ``bark`` (``left|right|top|bottom``), ``skewness`` (of the whole profile's derivative along +axis),
        ``z`` (block mean over its standard error; the sign says the direction), ``confident`` (``|z| >= 3``),
        ``block_skewness``.
    """
    v = np.asarray(hsv_value(image), np.float64)
    if axis is None:
        axis = "x" if v.shape[1] >= v.shape[0] else "y"
    if axis not in ("x", "y"):
        raise ValueError(f"axis must be 'x', 'y' or None; got {axis!r}")
    if axis == "y":
        v = v.T
    H, L = v.shape
    if blocks is None:
        blocks = min(8, L // 16)
    elif isinstance(blocks, bool) or not isinstance(blocks, (int, np.integer)) or blocks < 3:
        raise ValueError(f"blocks must be an integer >= 3; got {blocks!r}")
    if L < 16 * max(3, blocks):
        raise ValueError(f"the core is too short along its axis ({L} px) to tell its growth direction (at least "
                         f"{16 * max(3, blocks)} px)")
    band = v[int(0.3 * H):max(int(0.3 * H) + 1, int(0.7 * H))].mean(0)
    window = max(31, (L // 10) | 1)
    prof = ndimage.gaussian_filter1d(band - ndimage.uniform_filter1d(band, window, mode="nearest"), 1.0)
    d = np.diff(prof)

    def skew(x):
        x = x - x.mean()
        m2 = (x * x).mean()
        return float((x ** 3).mean() / m2 ** 1.5) if m2 > 0 else 0.0

    per_block = np.array([skew(b) for b in np.array_split(d, int(blocks))])
    se = per_block.std(ddof=1) / math.sqrt(len(per_block))
    z = float(per_block.mean() / se) if se > 0 else (math.copysign(math.inf, per_block.mean()) if
                                                     per_block.mean() else 0.0)
    forward = z >= 0
    bark = ("right" if forward else "left") if axis == "x" else ("bottom" if forward else "top")
    return dict(bark=bark, skewness=skew(d), z=z, confident=bool(abs(z) >= 3.0), block_skewness=per_block)


#: the longest half contour along the rings (px) that a core's curved Gabor filter uses by default
MAX_CORE_Q = 40


def detect_core_boundaries(image, *, bark: str | None = None, width_px: int | None = 32, dpi=None, pixel_size_mm=None,
                           p: int | None = None, q: int | None = None, f_max: float = 0.4,
                           band: float = 0.5, min_rel_magnitude: float = 0.15, min_rel_rise: float = 0.1,
                           edge_level: float = 0.8, device="cpu", num_workers: int | None = None) -> RingBoundaries:
    """Ring boundaries of an increment core image (rings cross the core's long axis).

    Args:
        image: ``(H, W, 3)`` RGB in ``[0, 1]`` (sRGB values, not linearised) or ``(H, W)`` gray; numpy array.
        bark: side of the image holding the bark (youngest rings): ``left|right|top|bottom``. The core axis is
            horizontal for left/right and vertical for top/bottom. None (default): found from the rings' shape
            (:func:`growth_direction` along the image's long side). A given side that a confident estimate
            contradicts is used, with a warning (a wrong side puts every boundary on the wrong edge of its
            latewood). ``info["growth"]`` holds the estimate.
        width_px: the core's short side is resampled to this many pixels (uniform width, the long axis keeps its
            resolution); None keeps it. At most the core's own width or ``2 q + 2`` (``q`` at most
            :data:`MAX_CORE_Q` by default), whichever is larger: a wider resampling adds no detail.
        dpi, pixel_size_mm: scan resolution for the ring widths in mm (at most one).
        p, q: curved-Gabor half lengths across / along the rings (px); default scaled to the dominant ring period
            ``P``: ``p = clip(1.5 P, 8, 150)``, ``q = clip(P, 2, min(40, width/2 - 1))``.
        f_max: highest ring frequency searched (cycles/px; 0.4 = rings down to 2.5 px).
        band: fraction of the (resampled) core width around the centre line averaged for the profile.
        min_rel_magnitude: cycles whose Gabor magnitude is below this fraction of the median are dropped.
        min_rel_rise: cycles whose steepest rise is below this fraction of the 99th percentile of ``|dV/dx|`` are
            dropped.
        edge_level: the boundary is placed on the latewood side of the steepest rise, where ``dV/dt`` has fallen
            to this fraction of its peak (the end of the latewood); 1.0 = the steepest point.
        device, num_workers: passed to :func:`~torch_appearance.rings.gabor.curved_gabor`.

    Returns:
        :class:`RingBoundaries` with points on the core's centre line in input-image pixel coordinates.

    Raises:
        ValueError / TypeError: bad image, bark, width or pixel size.

    Example:
        >>> from torch_appearance.rings.dendro import detect_core_boundaries
        >>> # res = detect_core_boundaries(rgb, bark="left", dpi=1200); res.points, res.widths_mm
    """
    if bark is not None and bark not in _BARK:
        raise ValueError(f"bark must be one of {_BARK} or None; got {bark!r}")
    try:
        growth = growth_direction(image, axis=None if bark is None else ("x" if bark in ("left", "right") else "y"))
    except ValueError as e:
        if bark is None:
            raise ValueError(f"bark: {e}; give the side with the bark") from None
        growth = None
    if bark is None:
        bark = growth["bark"]
    elif growth is not None and growth["confident"] and growth["bark"] != bark:
        warnings.warn(f"bark={bark!r}, but the rings' shape says the bark is on the {growth['bark']} (z = "
                      f"{growth['z']:.1f}: sharp latewood -> earlywood steps face that way); check the side, a wrong "
                      f"one puts every boundary on the wrong edge of its latewood", stacklevel=2)
    if width_px is not None and (isinstance(width_px, bool) or not isinstance(width_px, (int, np.integer))
                                 or width_px < 8):
        raise ValueError(f"width_px must be an integer >= 8 or None; got {width_px!r}")
    if not (0 < band <= 1):
        raise ValueError(f"band must be in (0, 1]; got {band!r}")
    ps = _pixel_size(dpi, pixel_size_mm)
    v = hsv_value(image)
    H0, W0 = v.shape
    # canonical orientation: axis along x, pith at x = 0, bark at +x
    if bark in ("top", "bottom"):
        v = v.T
    if bark in ("left", "top"):
        v = v[:, ::-1]
    v = np.ascontiguousarray(v)
    Hc, L = v.shape
    if L < 16:
        raise ValueError(f"the core is too short along its axis ({L} px)")
    contour = 2 * (MAX_CORE_Q if q is None else int(q)) + 2
    if width_px is not None and width_px > max(Hc, contour):  # refused before the filter's work, which grows with it
        raise ValueError(f"width_px: expected at most {max(Hc, contour)} px, the larger of the core's width across its "
                         f"axis ({Hc} px) and the curved Gabor's longest contour ({contour} px): a wider resampling "
                         f"adds no detail, only time and memory ({L} px along the core per row); got {width_px}")
    Hs = Hc if width_px is None else int(width_px)
    vs = cv2.resize(v, (L, Hs), interpolation=cv2.INTER_AREA if Hs < Hc else cv2.INTER_LINEAR) if Hs != Hc else v
    p, q, period = _gabor_params(vs, p, q, f_max)
    q = min(q, max(1, Hs // 2 - 1))
    res = curved_gabor(vs, p=p, q=q, freq_range=(1.0 / p, f_max), normal_reference=(1.0, 0.0), device=device,
                       num_workers=num_workers)
    # mean ring tilt (dx per row) from the magnitude-weighted doubled-angle orientation
    th = res.theta.astype(np.float64)
    w = res.magnitude.astype(np.float64)
    mth = 0.5 * math.atan2((w * np.sin(2 * th)).sum(), (w * np.cos(2 * th)).sum()) % math.pi
    shear = math.cos(mth) / max(abs(math.sin(mth)), 0.2) * math.copysign(1.0, math.sin(mth) or 1.0)
    yc = (Hs - 1) / 2.0
    half = max(0.5, band * Hs / 2.0)
    rows = np.arange(Hs)[np.abs(np.arange(Hs) - yc) <= half]
    xs = np.arange(L, dtype=np.float64)
    coords_x = xs[None, :] + (rows[:, None] - yc) * shear
    coords_y = np.broadcast_to(rows[:, None].astype(np.float64), coords_x.shape)
    zfield = res.magnitude * np.exp(1j * res.phase)
    sample = lambda f: ndimage.map_coordinates(f, [coords_y, coords_x], order=1, mode="nearest")  # noqa: E731
    v_prof = sample(vs.astype(np.float64)).mean(0)
    z_prof = (sample(zfield.real) + 1j * sample(zfield.imag)).mean(0)
    pos = _cycle_boundaries(v_prof, z_prof, min_rel_magnitude=min_rel_magnitude, min_rel_rise=min_rel_rise,
                            edge_level=edge_level)
    # back to input coordinates (centre line of the core)
    xc = pos
    ycen = (Hc - 1) / 2.0
    if bark in ("left", "top"):
        xc = (L - 1) - xc
    pts = np.stack([xc, np.full_like(xc, ycen)], 1) if bark in ("left", "right") else \
        np.stack([np.full_like(xc, ycen), xc], 1)
    wpx, wmm = ring_widths_mm(pts, ps)
    info = dict(period_px=period, p=p, q=q, width_px=Hs, shear=shear, profile_v=v_prof, profile_z=z_prof,
                shape=(H0, W0), bark=bark, growth=growth)
    return RingBoundaries(points=pts, widths_px=wpx, widths_mm=wmm, pixel_size_mm=ps, info=info)


# ----------------------------------------------------------------------------------------------------------------
# transect mode
# ----------------------------------------------------------------------------------------------------------------
def _check_transect(transect, shape):
    try:
        x0, y0, x1, y1 = (float(t) for t in transect)
    except (TypeError, ValueError):
        raise ValueError(f"transect: expected four numbers (x0, y0, x1, y1), got {transect!r}") from None
    check_point_in_image("transect start", (x0, y0), shape)
    check_point_in_image("transect end", (x1, y1), shape)
    if math.hypot(x1 - x0, y1 - y0) < 2.0:
        raise ValueError(f"transect: expected a length >= 2 px, got (nearly) zero length: ({x0:g}, {y0:g}) -> "
                         f"({x1:g}, {y1:g})")
    return x0, y0, x1, y1


def _segment_crossings(polylines, a, b):
    """Arc positions ``t`` (px from ``a``) where polylines cross the segment ``a -> b``."""
    d = b - a
    length = float(np.hypot(*d))
    u = d / length
    nrm = np.array([-u[1], u[0]])
    ts = []
    for pl in polylines:
        if len(pl) < 2:
            continue
        s = (pl - a) @ nrm  # signed distance to the transect line
        t = (pl - a) @ u
        i = np.nonzero(np.sign(s[:-1]) * np.sign(s[1:]) <= 0)[0]
        i = i[(s[i] != s[i + 1]) | (s[i] == 0)]
        frac = np.where(s[i] != s[i + 1], s[i] / np.where(s[i] != s[i + 1], s[i] - s[i + 1], 1.0), 0.0)
        tt = t[i] + frac * (t[i + 1] - t[i])
        ts.extend(tt[(tt >= 0) & (tt <= length)].tolist())
    return np.unique(np.round(np.sort(np.asarray(ts, dtype=np.float64)), 3))


def detect_transect_boundaries(image, transect, *, dpi=None, pixel_size_mm=None, p: int | None = None,
                               q: int | None = None, f_max: float = 0.4, min_rel_rise: float = 0.1,
                               edge_level: float = 0.8, device="cpu", num_workers: int | None = None) -> RingBoundaries:
    """Ring boundaries where traced rings cross a transect ``(x0, y0, x1, y1)`` drawn pith -> bark (pixels).

    The Gabor normal is oriented along the transect, rings are traced at the phase level ``pi/2`` and each crossing
    starts a cycle; the boundary is the steepest V rise of that cycle along the transect (module docstring).

    Raises:
        ValueError: transect outside the image or of (nearly) zero length, bad pixel size or image.
    """
    ps = _pixel_size(dpi, pixel_size_mm)
    v = hsv_value(image)
    x0, y0, x1, y1 = _check_transect(transect, v.shape)
    a, b = np.array([x0, y0]), np.array([x1, y1])
    length = float(np.hypot(*(b - a)))
    p, q, period = _gabor_params(v, p, q, f_max)
    res = curved_gabor(v, p=p, q=q, freq_range=(1.0 / p, f_max), normal_reference=(b - a) / length, device=device,
                       num_workers=num_workers)
    lines = trace_rings(res.phase, res.orientation, res.magnitude)
    starts = _segment_crossings(lines, a, b)
    n = int(math.floor(length)) + 1
    t = np.linspace(0.0, length, n)
    xy = a[None, :] + t[:, None] * (b - a)[None, :] / length
    v_prof = ndimage.map_coordinates(v.astype(np.float64), [xy[:, 1], xy[:, 0]], order=1, mode="nearest")
    step = length / (n - 1)
    pos = _cycle_boundaries(v_prof, None, cycle_start=starts / step, min_rel_rise=min_rel_rise,
                            edge_level=edge_level)
    pts = a[None, :] + (pos * step)[:, None] * (b - a)[None, :] / length
    wpx, wmm = ring_widths_mm(pts, ps)
    info = dict(period_px=period, p=p, q=q, crossings=starts, polylines=lines, profile_v=v_prof)
    return RingBoundaries(points=pts.reshape(-1, 2), widths_px=wpx, widths_mm=wmm, pixel_size_mm=ps, info=info)


_SECTION = ("SectionBoundary", "detect_section_boundaries")


def __getattr__(name):
    """Section mode moved to :mod:`~torch_appearance.rings.section` (which imports this module): its names are still
    importable from here, resolved on first use."""
    if name in _SECTION:
        from . import section
        return getattr(section, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
