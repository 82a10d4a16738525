"""Growth-ring tracing on a Gabor phase image (Nindel et al., thesis ch. 2, §3.3).

A ring boundary is where the curved-Gabor phase ``I_φ`` equals ``level`` (π/2 by default: the negative zero
crossing of the ring signal). :func:`trace_rings` seeds walkers on every sub-pixel level crossing, walks them along
the orientation field ``θ`` in both directions (midpoint / RK2 steps, θ sampled bilinearly through its doubled-angle
vector so that the mod-π ambiguity never averages opposite directions, and its sign aligned with the previous step),
and after each step snaps the walker back onto the level set with a few Newton steps along the ring normal on the
*wrapped* phase difference. Because the walk follows θ instead of thresholding the phase, short anomalies (a few
pixels where the phase is off or the magnitude is low) are bridged.

All walkers of a round advance together (vectorised over walkers, no per-pixel Python loop); a round takes one seed
per connected group of still-uncovered crossing pixels, so typically one or two rounds trace every ring. Polylines
are then accepted longest first: points within ~1 px of an accepted polyline are cut away, and a piece that runs
into the end of an accepted polyline of the same ring is joined to it, so each ring comes back as one polyline.

Conventions: images ``(H, W)`` indexed (row y, col x); polylines are ``(K, 2)`` float64 arrays of ``(x, y)`` pixel
coordinates (pixel centres at integers); θ in radians, the ring tangent direction measured from +x towards +y.
"""
import math

import numpy as np
from scipy import ndimage

__all__ = ["trace_rings", "polyline_length", "wrap_angle"]

_TWO_PI = 2.0 * math.pi


def wrap_angle(a):
    """Wrap angles (radians, any shape) into ``[-π, π)``."""
    return (np.asarray(a) + math.pi) % _TWO_PI - math.pi


def polyline_length(polyline):
    """Length in pixels of a ``(K, 2)`` polyline (0 for fewer than two points)."""
    p = np.asarray(polyline, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 2:
        raise ValueError(f"polyline must have shape (K, 2), got {p.shape}")
    if len(p) < 2:
        return 0.0
    return float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum())


# ----------------------------------------------------------------------------------------------------------------
# input checks
# ----------------------------------------------------------------------------------------------------------------
def _as_field(name, value, shape=None):
    try:
        import torch

        if isinstance(value, torch.Tensor):
            value = value.detach().cpu().numpy()
    except ImportError:  # pragma: no cover
        pass
    if value is None or not hasattr(value, "shape") and not isinstance(value, (list, tuple)):
        raise TypeError(f"{name} must be an array (H, W), got {type(value).__name__}")
    a = np.asarray(value)
    if a.dtype.kind not in "fiu":
        raise TypeError(f"{name} must hold real numbers, got dtype {a.dtype}")
    if a.ndim != 2:
        raise ValueError(f"{name} must have shape (H, W), got {a.shape}")
    if a.shape[0] < 3 or a.shape[1] < 3:
        raise ValueError(f"{name} must be at least 3×3 pixels, got {a.shape}")
    if shape is not None and a.shape != shape:
        raise ValueError(f"{name} must have the shape of phase {shape}, got {a.shape}")
    a = a.astype(np.float64)
    if not np.isfinite(a).all():
        raise ValueError(f"{name} has {int((~np.isfinite(a)).sum())} non-finite values (NaN or inf)")
    return a


def _positive(name, value, allow_zero=False):
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise TypeError(f"{name} must be a number, got {type(value).__name__}") from None
    if not math.isfinite(v) or v < 0 or (v == 0 and not allow_zero):
        raise ValueError(f"{name} must be {'non-negative' if allow_zero else 'positive'} and finite, got {value!r}")
    return v


# ----------------------------------------------------------------------------------------------------------------
# bilinear sampling of several fields at once
# ----------------------------------------------------------------------------------------------------------------
class _Fields:
    """Stack of (H, W) fields sampled bilinearly at float (x, y) positions (clamped to the image)."""

    def __init__(self, fields):
        self.stack = np.stack(fields, axis=0)  # (C, H, W)
        self.h, self.w = self.stack.shape[1:]

    def sample(self, x, y):
        """x, y: (N,) → (C, N) bilinear samples (positions clamped to the image)."""
        x = np.clip(x, 0.0, self.w - 1.0)
        y = np.clip(y, 0.0, self.h - 1.0)
        x0 = np.minimum(np.floor(x).astype(np.int64), self.w - 2)
        y0 = np.minimum(np.floor(y).astype(np.int64), self.h - 2)
        fx, fy = x - x0, y - y0
        s = self.stack
        v00, v01 = s[:, y0, x0], s[:, y0, x0 + 1]
        v10, v11 = s[:, y0 + 1, x0], s[:, y0 + 1, x0 + 1]
        return (v00 * (1 - fx) + v01 * fx) * (1 - fy) + (v10 * (1 - fx) + v11 * fx) * fy


# ----------------------------------------------------------------------------------------------------------------
# seeds
# ----------------------------------------------------------------------------------------------------------------
def _level_crossings(err, valid):
    """Sub-pixel crossings of ``err = wrap(phase - level)`` through 0 between 4-neighbours.

    Returns (x, y, pixel_index) arrays: crossing position and the flat index of the neighbour closer to it.
    A sign change with |err0 - err1| ≥ π is the wrap at level + π, not a crossing.
    """
    h, w = err.shape
    xs, ys, idx = [], [], []
    for axis in (0, 1):
        e0 = err[:-1, :] if axis == 0 else err[:, :-1]
        e1 = err[1:, :] if axis == 0 else err[:, 1:]
        v = (valid[:-1, :] & valid[1:, :]) if axis == 0 else (valid[:, :-1] & valid[:, 1:])
        hit = v & (np.signbit(e0) != np.signbit(e1)) & (np.abs(e0 - e1) < math.pi)
        r, c = np.nonzero(hit)
        a, b = e0[r, c], e1[r, c]
        t = a / (a - b)
        if axis == 0:
            xs.append(c.astype(np.float64)), ys.append(r + t)
            near = np.where(t < 0.5, r, r + 1) * w + c
        else:
            xs.append(c + t), ys.append(r.astype(np.float64))
            near = r * w + np.where(t < 0.5, c, c + 1)
        idx.append(near)
    return np.concatenate(xs), np.concatenate(ys), np.concatenate(idx)


# ----------------------------------------------------------------------------------------------------------------
# occupancy of accepted polylines
# ----------------------------------------------------------------------------------------------------------------
class _Occupancy:
    """Raster of polyline ids (−1 = free); each polyline point claims the pixels within ``radius``."""

    def __init__(self, h, w, radius):
        self.ids = np.full((h, w), -1, dtype=np.int64)
        self.h, self.w = h, w
        r = int(math.ceil(radius))
        oy, ox = np.mgrid[-r:r + 1, -r:r + 1]
        keep = ox ** 2 + oy ** 2 <= radius ** 2 + 1e-9
        self.offsets = np.stack([ox[keep], oy[keep]], axis=1)  # (M, 2)

    def query(self, x, y):
        """Polyline id at the nearest pixel of each position (−1 if free or outside)."""
        xi, yi = np.rint(x).astype(np.int64), np.rint(y).astype(np.int64)
        inside = (xi >= 0) & (xi < self.w) & (yi >= 0) & (yi < self.h)
        out = np.full(x.shape, -1, dtype=np.int64)
        out[inside] = self.ids[yi[inside], xi[inside]]
        return out

    def mark(self, polyline, pid):
        p = np.rint(polyline).astype(np.int64)
        q = (p[:, None, :] + self.offsets[None, :, :]).reshape(-1, 2)
        ok = (q[:, 0] >= 0) & (q[:, 0] < self.w) & (q[:, 1] >= 0) & (q[:, 1] < self.h)
        q = q[ok]
        free = self.ids[q[:, 1], q[:, 0]] < 0  # never overwrite another ring's claim
        self.ids[q[free, 1], q[free, 0]] = pid


# ----------------------------------------------------------------------------------------------------------------
# the walkers
# ----------------------------------------------------------------------------------------------------------------
def _walk(fields, seeds_xy, seed_dir, *, level, step, max_steps, newton_steps, snap_tol_px, max_gap_px,
          max_turn, min_magnitude, occupancy, margin, closure_after):
    """Advance all walkers together. Returns list of (K_i, 2) paths (seed excluded) and a 'closed' flag per walker.

    ``fields`` holds (cos2θ, sin2θ, cosφ, sinφ, ∂φ/∂x, ∂φ/∂y, magnitude).
    """
    n = len(seeds_xy)
    pos = seeds_xy.copy()
    direction = seed_dir.copy()
    active = np.ones(n, dtype=bool)
    closed = np.zeros(n, dtype=bool)
    miss = np.zeros(n, dtype=np.int64)       # consecutive steps without a successful snap
    last_good = np.zeros(n, dtype=np.int64)  # number of path points up to the last successful snap
    travelled = np.zeros(n)
    paths = np.full((max_steps, n, 2), np.nan)
    max_miss = max(1, int(max_gap_px / step))
    cos_turn = math.cos(max_turn)
    h, w = fields.h, fields.w
    cl, sl = math.cos(level), math.sin(level)

    def tangent(x, y, ref):
        c2, s2 = fields.sample(x, y)[:2]
        ang = 0.5 * np.arctan2(s2, c2)
        t = np.stack([np.cos(ang), np.sin(ang)], axis=1)
        flip = (t * ref).sum(1) < 0
        t[flip] *= -1.0
        return t

    for k in range(max_steps):
        idx = np.nonzero(active)[0]
        if len(idx) == 0:
            break
        p, d = pos[idx], direction[idx]
        t1 = tangent(p[:, 0], p[:, 1], d)
        mid = p + 0.5 * step * t1
        t2 = tangent(mid[:, 0], mid[:, 1], t1)
        new = p + step * t2
        # Newton snap onto phase == level along the normal of t2
        nrm = np.stack([-t2[:, 1], t2[:, 0]], axis=1)
        snapped = new.copy()
        for _ in range(newton_steps):
            c, s, gx, gy = fields.sample(snapped[:, 0], snapped[:, 1])[2:6]
            err = np.arctan2(s * cl - c * sl, c * cl + s * sl)  # wrap(φ − level), interpolated on the circle
            g = gx * nrm[:, 0] + gy * nrm[:, 1]
            g = np.where(np.abs(g) < 1e-6, np.copysign(1e-6, g), g)
            ds = np.clip(-err / g, -0.5, 0.5)
            snapped = snapped + ds[:, None] * nrm
        c, s, gx, gy, mag = fields.sample(snapped[:, 0], snapped[:, 1])[2:7]
        err = np.arctan2(s * cl - c * sl, c * cl + s * sl)
        gn = np.abs(gx * nrm[:, 0] + gy * nrm[:, 1])
        good = (np.abs(err) < snap_tol_px * np.maximum(gn, 1e-6)) & (gn > 1e-3)
        good &= np.linalg.norm(snapped - new, axis=1) < 0.75
        if min_magnitude is not None:
            good &= mag >= min_magnitude
        good &= fields.sample(snapped[:, 0], snapped[:, 1])[7] > 0.5   # not on a phase discontinuity
        new = np.where(good[:, None], snapped, new)
        # stop conditions
        inside = (new[:, 0] >= -margin) & (new[:, 0] <= w - 1 + margin) & \
                 (new[:, 1] >= -margin) & (new[:, 1] <= h - 1 + margin)
        move = new - p
        length = np.linalg.norm(move, axis=1)
        unit = move / np.maximum(length, 1e-12)[:, None]
        smooth = (unit * d).sum(1) >= cos_turn
        taken = occupancy.query(new[:, 0], new[:, 1]) >= 0 if occupancy is not None else np.zeros(len(idx), bool)
        miss[idx] = np.where(good, 0, miss[idx] + 1)
        ok = inside & smooth & ~taken & (miss[idx] <= max_miss)
        # loop closure: back at the seed after having gone round
        travelled[idx] += length
        near_seed = np.linalg.norm(new - seeds_xy[idx], axis=1) < 0.75 * step + 0.25
        closing = ok & near_seed & (travelled[idx] > closure_after)
        # a walker that ran into an accepted ring keeps that last point (and any bridged gap): it is joined later
        hit = inside & smooth & taken & (miss[idx] <= max_miss)
        paths[k, idx[hit]] = new[hit]
        last_good[idx[hit]] = k + 1
        paths[k, idx[ok & ~closing]] = new[ok & ~closing]
        last_good[idx[ok & good & ~closing]] = k + 1
        closed[idx[closing]] = True
        pos[idx] = new
        direction[idx] = np.where(ok[:, None], unit, d)
        active[idx[~ok | closing]] = False

    out = []
    for i in range(n):
        m = last_good[i] if not closed[i] else max_steps  # drop an unsnapped tail
        path = paths[:m, i]
        out.append(path[~np.isnan(path[:, 0])])
    return out, closed


# ----------------------------------------------------------------------------------------------------------------
# public API
# ----------------------------------------------------------------------------------------------------------------
def trace_rings(phase, theta, magnitude=None, level=math.pi / 2, step=0.5, min_length=10.0, *,
                min_magnitude=None, newton_steps=3, snap_tol_px=0.35, max_gap_px=6.0, max_turn_deg=30.0,
                dedup_radius=1.0, max_rounds=8, max_length=None, max_phase_step=math.pi / 2,
                return_closed=False):
    """Trace growth-ring boundaries (the level set ``I_φ = level``) along the orientation field.

    Args:
        phase: ``(H, W)`` Gabor phase ``I_φ`` in radians (any branch; it is used wrapped).
        theta: ``(H, W)`` ring orientation in radians (tangent direction, mod π; [0, π) by convention).
        magnitude: optional ``(H, W)`` Gabor magnitude; walkers stop (after ``max_gap_px``) where it is below
            ``min_magnitude`` and seeds there are ignored.
        level: phase level of the traced boundary, radians (π/2: the negative zero crossing of the ring signal).
        step: walker step length along the ring, pixels (0 < step ≤ 2).
        min_length: polylines shorter than this (pixels of arc length) are dropped.
        min_magnitude: absolute magnitude threshold; default ``0.1 × median(magnitude)`` when ``magnitude`` is
            given, none otherwise.
        newton_steps: Newton iterations per step snapping the walker back onto the level along the normal.
        snap_tol_px: a snap counts as successful if the remaining phase error, converted to pixels with the
            local phase gradient, is below this.
        max_gap_px: how far (pixels) a walker may continue along θ without a successful snap (bridges anomalies;
            the unsnapped tail is removed when it stops).
        max_turn_deg: a step turning more than this against the previous step stops the walker.
        dedup_radius: pixels around an accepted polyline that count as "the same ring" (seeds there are skipped,
            walkers of later rounds stop there, overlapping pieces are cut). Rings must be more than
            ``2·dedup_radius + 1`` pixels apart (ring period ≳ 4 px).
        max_rounds: rounds of seeding (each round seeds every still-uncovered group of crossing pixels).
        max_length: maximum arc length per direction and walker in pixels (default ``4·(H + W)``).
        max_phase_step: largest wrapped phase difference between neighbouring pixels (rad) that is not a
            discontinuity; pixels at larger jumps or reversed phase gradients (where the Gabor normal sign flips)
            neither seed nor snap. The default π/2 assumes ring periods above 4 px.
        return_closed: also return a list of booleans, True for closed loops (e.g. concentric circles).

    Returns:
        list of ``(K, 2)`` float64 arrays of sub-pixel ``(x, y)`` points (spacing ≈ ``step``), longest first; with
        ``return_closed`` a tuple ``(polylines, closed)``. A closed polyline does not repeat its first point.

    Raises:
        TypeError, ValueError: for arrays of the wrong type/shape, non-finite values or bad parameters.

    Example:
        >>> yy, xx = np.mgrid[0:64, 0:64].astype(float)
        >>> phase = 2 * np.pi * xx / 8.0          # vertical rings, period 8 px
        >>> theta = np.full_like(phase, np.pi / 2)
        >>> rings = trace_rings(phase, theta)
        >>> len(rings), bool(np.allclose(rings[0][:, 0] % 8, 2.0, atol=1e-3))
        (8, True)
    """
    phase = _as_field("phase", phase)
    theta = _as_field("theta", theta, phase.shape)
    mag = None if magnitude is None else _as_field("magnitude", magnitude, phase.shape)
    level = float(level)
    if not math.isfinite(level):
        raise ValueError(f"level must be finite, got {level!r}")
    step = _positive("step", step)
    if step > 2.0:
        raise ValueError(f"step must be at most 2 px (the walk samples θ bilinearly), got {step}")
    min_length = _positive("min_length", min_length, allow_zero=True)
    dedup_radius = _positive("dedup_radius", dedup_radius)
    snap_tol_px = _positive("snap_tol_px", snap_tol_px)
    max_phase_step = _positive("max_phase_step", max_phase_step)
    max_gap_px = _positive("max_gap_px", max_gap_px, allow_zero=True)
    if int(newton_steps) < 0 or int(max_rounds) < 1:
        raise ValueError(f"newton_steps must be ≥ 0 and max_rounds ≥ 1, got {newton_steps}, {max_rounds}")
    if not 0.0 < float(max_turn_deg) < 180.0:
        raise ValueError(f"max_turn_deg must be in (0, 180), got {max_turn_deg!r}")
    if min_magnitude is None and mag is not None:
        min_magnitude = 0.1 * float(np.median(mag))
    elif min_magnitude is not None:
        min_magnitude = _positive("min_magnitude", min_magnitude, allow_zero=True)
        if mag is None:
            raise ValueError("min_magnitude needs magnitude")

    h, w = phase.shape
    # wrapped central differences of the phase (∂φ/∂x, ∂φ/∂y), one-sided at the border
    gx = np.empty_like(phase)
    gy = np.empty_like(phase)
    gx[:, 1:-1] = wrap_angle(phase[:, 2:] - phase[:, :-2]) / 2
    gx[:, 0], gx[:, -1] = wrap_angle(phase[:, 1] - phase[:, 0]), wrap_angle(phase[:, -1] - phase[:, -2])
    gy[1:-1] = wrap_angle(phase[2:] - phase[:-2]) / 2
    gy[0], gy[-1] = wrap_angle(phase[1] - phase[0]), wrap_angle(phase[-1] - phase[-2])
    # phase discontinuities (e.g. where the Gabor normal sign flips): jumps between neighbours larger than
    # max_phase_step, or reversed phase gradients; seeds and snaps are refused there
    smooth = np.ones_like(phase, dtype=bool)
    for axis in (0, 1):
        a = [slice(None), slice(None)]
        b = [slice(None), slice(None)]
        a[axis], b[axis] = slice(None, -1), slice(1, None)
        a, b = tuple(a), tuple(b)
        bad = np.abs(wrap_angle(phase[b] - phase[a])) > max_phase_step
        bad |= (gx[a] * gx[b] + gy[a] * gy[b]) < 0
        smooth[a] &= ~bad
        smooth[b] &= ~bad
    fields = _Fields([np.cos(2 * theta), np.sin(2 * theta), np.cos(phase), np.sin(phase), gx, gy,
                      mag if mag is not None else np.ones_like(phase), smooth.astype(np.float64)])

    # seeds: sub-pixel crossings of the level, grouped into 8-connected components of their pixels
    err = wrap_angle(phase - level)
    valid = smooth if min_magnitude is None else smooth & (mag >= min_magnitude)
    sx, sy, spix = _level_crossings(err, valid)
    if len(sx) == 0:
        return ([], []) if return_closed else []
    cross_mask = np.zeros(h * w, dtype=bool)
    cross_mask[spix] = True
    labels, n_labels = ndimage.label(cross_mask.reshape(h, w), structure=np.ones((3, 3), dtype=bool))
    seed_label = labels.reshape(-1)[spix]
    seed_score = -np.abs(err.reshape(-1)[spix])  # prefer clean crossings (phase close to the level at the pixel)
    if mag is not None:
        seed_score = seed_score + mag.reshape(-1)[spix] / (np.abs(mag).max() + 1e-12)
    # the filter responses are least reliable in the outermost pixels: seed there only as a last resort
    border = np.minimum(np.minimum(sx, w - 1 - sx), np.minimum(sy, h - 1 - sy))
    seed_score = seed_score - 2.0 * (border < 2.0)
    tried = np.zeros(len(sx), dtype=bool)   # crossings already used as a seed (never seeded twice)

    max_steps = int(math.ceil((max_length if max_length is not None else 4.0 * (h + w)) / step))
    occupancy = _Occupancy(h, w, dedup_radius)
    accepted = []   # list of (K, 2) arrays
    closed_flags = []

    for _ in range(int(max_rounds)):
        free = (occupancy.query(sx, sy) < 0) & ~tried
        if not free.any():
            break
        # one seed per component: the best-scoring free crossing
        cand = np.nonzero(free)[0]
        order = np.lexsort((-seed_score[cand], seed_label[cand]))
        cand = cand[order]
        first = np.ones(len(cand), dtype=bool)
        first[1:] = seed_label[cand][1:] != seed_label[cand][:-1]
        counts = np.bincount(seed_label[cand], minlength=n_labels + 1)
        seeds = cand[first]
        seeds = seeds[counts[seed_label[seeds]] >= 2]  # a lone crossing pixel is noise
        if len(seeds) == 0:
            break
        tried[seeds] = True
        xy = np.stack([sx[seeds], sy[seeds]], axis=1)
        c2, s2 = fields.sample(xy[:, 0], xy[:, 1])[:2]
        ang = 0.5 * np.arctan2(s2, c2)
        t0 = np.stack([np.cos(ang), np.sin(ang)], axis=1)
        # snap the seeds onto the level along the ring normal: a crossing interpolated between neighbours that lie
        # nearly along the ring is off the level set by up to a pixel, and the first walker step would then turn
        # by more than max_turn and stop both walkers at once
        xy, ok = _snap_seeds(fields, xy, t0, level, int(newton_steps), snap_tol_px)
        xy, t0, seeds = xy[ok], t0[ok], seeds[ok]
        if len(seeds) == 0:
            continue
        both_xy = np.concatenate([xy, xy])
        both_dir = np.concatenate([t0, -t0])
        paths, closed = _walk(fields, both_xy, both_dir, level=level, step=step, max_steps=max_steps,
                              newton_steps=int(newton_steps), snap_tol_px=snap_tol_px, max_gap_px=max_gap_px,
                              max_turn=math.radians(float(max_turn_deg)), min_magnitude=min_magnitude,
                              occupancy=occupancy if accepted else None, margin=0.0,
                              closure_after=max(4.0, 4.0 * step))
        m = len(seeds)
        new_lines, new_closed = [], []
        for i in range(m):
            if closed[i]:
                line, is_closed = np.concatenate([xy[i:i + 1], paths[i]]), True
            else:
                line = np.concatenate([paths[m + i][::-1], xy[i:i + 1], paths[i]])
                is_closed = False
            new_lines.append(line)
            new_closed.append(is_closed)
        _accept(new_lines, new_closed, accepted, closed_flags, occupancy, min_length, step)

    order = np.argsort([-polyline_length(p) for p in accepted], kind="stable")
    polylines = [accepted[i] for i in order]
    closed_out = [closed_flags[i] for i in order]
    return (polylines, closed_out) if return_closed else polylines


def _snap_seeds(fields, xy, tangent, level, newton_steps, snap_tol_px):
    """Newton steps (along the normal of ``tangent``) moving seeds onto the level; returns (xy, ok)."""
    cl, sl = math.cos(level), math.sin(level)
    nrm = np.stack([-tangent[:, 1], tangent[:, 0]], axis=1)
    p = xy.copy()
    for _ in range(max(newton_steps, 1)):
        c, s, gx, gy = fields.sample(p[:, 0], p[:, 1])[2:6]
        err = np.arctan2(s * cl - c * sl, c * cl + s * sl)
        g = gx * nrm[:, 0] + gy * nrm[:, 1]
        g = np.where(np.abs(g) < 1e-6, np.copysign(1e-6, g), g)
        p = p + np.clip(-err / g, -0.5, 0.5)[:, None] * nrm
    c, s, gx, gy = fields.sample(p[:, 0], p[:, 1])[2:6]
    err = np.arctan2(s * cl - c * sl, c * cl + s * sl)
    gn = np.abs(gx * nrm[:, 0] + gy * nrm[:, 1])
    ok = (np.abs(err) < snap_tol_px * np.maximum(gn, 1e-6)) & (gn > 1e-3)
    ok &= np.linalg.norm(p - xy, axis=1) < 1.5
    ok &= (p[:, 0] >= 0) & (p[:, 0] <= fields.w - 1) & (p[:, 1] >= 0) & (p[:, 1] <= fields.h - 1)
    return np.where(ok[:, None], p, xy), ok


def _runs(mask):
    """Start/stop indices of the runs of True in a 1-D boolean array."""
    d = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    return list(zip(np.nonzero(d == 1)[0], np.nonzero(d == -1)[0]))


def _accept(lines, closed, accepted, closed_flags, occupancy, min_length, step):
    """Add new polylines longest first, cutting parts already covered and joining continuations of a ring."""
    order = np.argsort([-len(p) for p in lines], kind="stable")
    join_dist = 2.0 + step
    for i in order:
        line = lines[i]
        if len(line) < 2:
            continue
        owner = occupancy.query(line[:, 0], line[:, 1])
        if closed[i] and (owner < 0).all():
            if polyline_length(line) >= min_length:
                accepted.append(line)
                closed_flags.append(True)
                occupancy.mark(line, len(accepted) - 1)
            continue
        for a, b in _runs(owner < 0):
            piece = line[a:b]
            # a piece cut because it runs into an accepted polyline: join it to that polyline's nearby end
            for end, nb in ((0, a - 1), (1, b)):
                if not 0 <= nb < len(line) or owner[nb] < 0 or closed_flags[owner[nb]]:
                    continue
                j = owner[nb]
                other = accepted[j]
                tip = piece[0] if end == 0 else piece[-1]
                d_start, d_end = np.linalg.norm(other[0] - tip), np.linalg.norm(other[-1] - tip)
                if min(d_start, d_end) > join_dist:
                    continue
                if d_end <= d_start:   # other's end meets piece → other + piece (oriented away from other)
                    ext = piece if end == 0 else piece[::-1]
                    merged = np.concatenate([other, ext])
                else:                  # piece meets other's start → piece + other
                    ext = piece[::-1] if end == 0 else piece
                    merged = np.concatenate([ext, other])
                accepted[j] = merged
                occupancy.mark(piece, j)
                piece = None
                break
            if piece is None or polyline_length(piece) < min_length:
                continue
            accepted.append(piece)
            closed_flags.append(False)
            occupancy.mark(piece, len(accepted) - 1)
