"""The pith of a disc photo from its ring orientation field (``--pith auto``), with its uncertainty.

Every ring is a closed curve around the pith, so the ring *normal* at any point of the wood points at the pith: the
pith is where the normal lines of all pixels meet. As in the automatic pith detector of Marichal et al. (APD, "An
automatic pith detection method for tree cross-section images", 2023) the lines come from the local orientation
(here :func:`~torch_appearance.rings.orientation.orientation_field`, the structure tensor), and their meeting point is
found robustly, then refined in a smaller window around the estimate. Instead of APD's LO-RANSAC over line segments,
this module solves a weighted least-squares problem for the point nearest all lines and re-weights it:

1. **Scale.** The image's HSV value is reduced so that its long side is ``work_px`` (512 by default); the structure
   tensor is averaged over ``window`` px of that image (15: one or two rings of the discs measured).
2. **Lines.** Each pixel ``p`` with coherence ``c`` (1 for parallel rings, 0 for flat background or knots) gives the
   line through ``p`` along its ring normal ``n``. The point ``x`` nearest all lines solves
   ``sum w (I - n n^T) x = sum w (I - n n^T) p``.
3. **Robust weights.** The residual of a line is its *angle* to ``x`` (distance over ``|x - p|``), so that far and
   near pixels count alike; lines off by more than a few degrees (knots, cracks, the disc edge) get Cauchy weights
   ``1 / (1 + (angle / 5 deg)^2)``, and only pixels within a shrinking radius of the current estimate take part
   (the whole image, then 60 %, 36 %, ... down to ``min_radius`` of the long side), since rings are most circular
   near the pith.
4. **Refine.** The same at twice the resolution in a crop around the estimate (40 % of the long side), then again
   at twice that in a crop half as wide, ``refine_levels`` times (3 by default) or up to the input's resolution.
   On the three labelled discs the error against the human (TRAS C13C, C17C) or CS-TRD (F02b) pith went from 7.2,
   1.3, 3.9 px with one level to 2.4, 2.7, 2.4 px with three (two: 10.8, 5.0, 2.4).
5. **Uncertainty.** Jackknife over eight angular sectors around the pith (each left out once): ``sigma_px`` is the
   jackknife standard error of the position, in input pixels.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np

from .dendro import hsv_value
from .orientation import orientation_field

__all__ = ["PithEstimate", "detect_pith"]


@dataclass
class PithEstimate:
    """``xy``: the pith ``(x, y)`` in input pixels; ``sigma_px``: its jackknife standard error (px); ``info``:
    diagnostics (the coarse estimate, the number of lines used, the sectors' estimates, the refinement levels run
    and the resolution of the last, as a fraction of the input's)."""

    xy: np.ndarray
    sigma_px: float
    info: dict = field(default_factory=dict)


def _lines(v, window):
    """Pixel centres ``(N, 2)``, ring normals ``(N, 2)`` and coherence weights ``(N,)`` of a gray image."""
    theta, coh = orientation_field(v, sigma_smooth=1.0, window=window)
    # flat regions (a removed background, a saturated highlight) have no rings: their coherence is noise
    gy, gx = np.gradient(cv2.GaussianBlur(v.astype(np.float32), (0, 0), 1.0))
    energy = cv2.blur(gx * gx + gy * gy, (window, window))
    keep = (coh > 0.3) & (energy > 0.05 * np.percentile(energy, 90))
    ys, xs = np.nonzero(keep)
    th = theta[keep].astype(np.float64)
    normals = np.stack([-np.sin(th), np.cos(th)], 1)
    return np.stack([xs, ys], 1).astype(np.float64), normals, coh[keep].astype(np.float64)


def _to_input(q, frame):
    """Input-pixel ``(x, y)`` of a point ``q`` of a reduced (and cropped) image ``frame = (fx, fy, x0, y0)``."""
    fx, fy, x0, y0 = frame
    return np.array([(q[0] + 0.5) / fx - 0.5 + x0, (q[1] + 0.5) / fy - 0.5 + y0])


def _meet(p, n, w, x0, radius, min_radius, iterations=12, scale_deg=5.0):
    """Robust meeting point of the lines ``(p, n)`` with weights ``w``, starting at ``x0`` (module docstring, 3)."""
    x = np.asarray(x0, np.float64)
    r = float(radius)
    s = math.radians(scale_deg)
    for _ in range(iterations):
        d = x[None] - p
        dist = np.hypot(d[:, 0], d[:, 1])
        used = dist <= r
        if used.sum() < 20:
            break
        dd, nn, ww, pp = d[used], n[used], w[used], p[used]
        dist_u = np.maximum(dist[used], 2.0)
        off = np.abs(dd[:, 0] * nn[:, 1] - dd[:, 1] * nn[:, 0])  # distance of x from the line through p along n
        angle = off / dist_u
        ww = ww / (1.0 + (angle / s) ** 2) / dist_u ** 2  # angular residuals: each line weighs 1/dist^2
        # sum w (I - n n^T) x = sum w (I - n n^T) p
        a11 = (ww * (1 - nn[:, 0] ** 2)).sum()
        a22 = (ww * (1 - nn[:, 1] ** 2)).sum()
        a12 = -(ww * nn[:, 0] * nn[:, 1]).sum()
        proj_p = pp - (pp * nn).sum(1, keepdims=True) * nn
        b = (ww[:, None] * proj_p).sum(0)
        det = a11 * a22 - a12 * a12
        if not det > 1e-12 * (a11 + a22) ** 2:
            break
        x = np.array([a22 * b[0] - a12 * b[1], a11 * b[1] - a12 * b[0]]) / det
        r = max(min_radius, 0.6 * r)
    return x


def detect_pith(image, *, work_px: int = 512, window: int = 15, min_radius: float = 0.08,
                refine: bool = True, refine_levels: int = 3) -> PithEstimate:
    """The pith of a disc photo (module docstring).

    Args:
        image: ``(H, W, 3)`` RGB in ``[0, 1]`` or ``(H, W)`` gray, the whole disc (a background around it is fine).
        work_px: long side of the reduced image the lines come from (>= 64).
        window: structure-tensor window in pixels of that image (odd, >= 3): 15 of 512 px averages the orientation
            over one or two rings of the discs measured (``scripts/eval/eval_disc.py``), not over flat earlywood.
        min_radius: the smallest window around the estimate, as a fraction of the long side.
        refine: refine at twice the resolution in a crop around the coarse estimate.
        refine_levels: how many times (each at twice the resolution of the last, in a crop half as wide).

    Returns:
        :class:`PithEstimate` in input pixels.

    Raises:
        ValueError: a bad image or parameter, or an image without ring structure (too few coherent pixels).
    """
    v = np.asarray(hsv_value(image), np.float64)
    if v.ndim != 2 or min(v.shape) < 16:
        raise ValueError(f"image: expected a disc photo of at least 16 x 16 pixels, got shape {np.shape(image)}")
    if not np.all(np.isfinite(v)):
        raise ValueError("image contains NaN or infinite values")
    if isinstance(work_px, bool) or not isinstance(work_px, (int, np.integer)) or work_px < 64:
        raise ValueError(f"work_px: expected an integer >= 64, got {work_px!r}")
    if isinstance(window, bool) or not isinstance(window, (int, np.integer)) or window < 3 or window % 2 == 0:
        raise ValueError(f"window: expected an odd integer >= 3, got {window!r}")
    if not 0 < min_radius <= 1:
        raise ValueError(f"min_radius: expected a fraction in (0, 1], got {min_radius!r}")
    if isinstance(refine_levels, bool) or not isinstance(refine_levels, (int, np.integer)) or refine_levels < 0:
        raise ValueError(f"refine_levels: expected an integer >= 0, got {refine_levels!r}")
    H, W = v.shape
    scale = min(1.0, work_px / max(H, W))
    small = cv2.resize(v.astype(np.float32), (max(16, round(W * scale)), max(16, round(H * scale))),
                       interpolation=cv2.INTER_AREA) if scale < 1 else v.astype(np.float32)
    sy, sx = small.shape[0] / H, small.shape[1] / W
    p, n, w = _lines(small, window)
    if len(p) < 50:
        raise ValueError("image: too few pixels with ring structure to find the pith (is it a disc photo?)")
    long_side = max(small.shape)
    # start at the coherence-weighted centroid of the wood, with a window of the whole image
    x0 = (w[:, None] * p).sum(0) / w.sum()
    x = _meet(p, n, w, x0, radius=long_side, min_radius=min_radius * long_side)
    frame = (sx, sy, 0, 0)  # (x scale, y scale, crop's x0, y0) of the image the current estimate lives in
    coarse = _to_input(x, frame)
    est, lines_in = x, (p, n, w)
    level, used_scale, half = 0, scale, 0.2 * max(H, W)
    centre = coarse
    while refine and used_scale < 1 and level < refine_levels:
        # twice the resolution of the previous level, in a crop around its estimate (40 % of the long side, then
        # half of that at each further level)
        s_k = min(1.0, 2 * used_scale)
        x0i, y0i = int(max(0, centre[0] - half)), int(max(0, centre[1] - half))
        x1i, y1i = int(min(W, centre[0] + half + 1)), int(min(H, centre[1] + half + 1))
        crop = v[y0i:y1i, x0i:x1i].astype(np.float32)
        if min(crop.shape) < 32:
            break
        cw, ch = max(16, round(crop.shape[1] * s_k)), max(16, round(crop.shape[0] * s_k))
        cs = cv2.resize(crop, (cw, ch), interpolation=cv2.INTER_AREA) if s_k < 1 else crop
        fx, fy = cs.shape[1] / crop.shape[1], cs.shape[0] / crop.shape[0]
        p2, n2, w2 = _lines(cs, window)
        if len(p2) < 50:
            break
        start = np.array([(centre[0] - x0i + 0.5) * fx - 0.5, (centre[1] - y0i + 0.5) * fy - 0.5])
        x2 = _meet(p2, n2, w2, start, radius=max(cs.shape), min_radius=min_radius * max(cs.shape))
        est, lines_in, frame, used_scale = x2, (p2, n2, w2), (fx, fy, x0i, y0i), s_k
        centre = _to_input(est, frame)
        level += 1
        half *= 0.5
    xy = _to_input(est, frame)
    # jackknife over eight angular sectors around the estimate
    p, n, w = lines_in
    sector = (np.floor((np.arctan2(p[:, 1] - est[1], p[:, 0] - est[0]) + math.pi) / (math.pi / 4)).astype(int)) % 8
    radius_final = max(min_radius * max(np.ptp(p[:, 0]) + 1, np.ptp(p[:, 1]) + 1), 8.0)
    leave_out = []
    for k in range(8):
        keep = sector != k
        if keep.sum() < 50:
            continue
        xk = _meet(p[keep], n[keep], w[keep], est, radius=radius_final * 2, min_radius=radius_final,
                      iterations=6)
        leave_out.append(_to_input(xk, frame))
    if len(leave_out) >= 3:
        lo = np.array(leave_out)
        m = len(lo)
        sigma = float(math.sqrt((m - 1) / m * ((lo - lo.mean(0)) ** 2).sum(1).sum()))
    else:
        lo, sigma = np.zeros((0, 2)), float("nan")
    return PithEstimate(xy=xy, sigma_px=sigma, info=dict(coarse=coarse, lines=len(p), sectors=lo, scale=scale,
                                                                window=window, levels=level, final_scale=used_scale))
