"""Board location in the log from traced rings (Nindel et al., thesis ch. 2, §3.4).

Geometry of a tangential ("flat-sawn") board. The stem axis runs nearly parallel to the board; its projection onto
the board is a line (the *projected tree centre*) with direction ``a = (cos ψ, sin ψ)`` in the image and normal
``b = (−sin ψ, cos ψ)``. With board-plane coordinates measured from the image centre ``p_c`` (mm),
``a' = a·(p − p_c)`` along and ``w' = b·(p − p_c)`` across the axis, the distance of the axis from the board is
``d0 − γ·a'`` (``d0`` at the image centre, ``γ = sin β`` for the out-of-plane tilt β) and a board point lies at radius

    r(p) = sqrt((d0 − γ·a')² + (w' − c)²)                                           (mm)

from the axis, ``c`` being the offset of the projected centre line. Rings are the circles ``r = s_r·(k + φ0)``;
with tilt they appear as nested arches (ellipses around the point where the axis pierces the board plane).

:func:`estimate_board` follows §3.4: rings are ordered across the board along transversals (lines across the
axis), the projected tree centre is put in the widest gap between neighbouring rings with gaps decreasing
monotonically to both sides, the ring scale starts from the median gap, and the axis distance (the paper's
x-translation; its sign is unobservable, we report d0 > 0) and tilt are found by brute-force search of the ring
shapes followed by a least-squares fit of all parameters to the traced ring points. The result converts to the
``rotation`` / ``translation`` of :class:`torch_appearance.nn.wood.WoodModel`. What follows the estimate lives
beside it: the phase sign and the growth direction in :mod:`.board_phase`, the initial WoodModel in
:mod:`.board_init`.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np
from scipy import optimize, sparse

from ..checks import check_finite, check_image_shape, check_positive, describe
from .tracing import polyline_length

__all__ = ["BoardEstimate", "estimate_board", "find_centre_gap"]

_TWO_PI = 2.0 * math.pi


# ----------------------------------------------------------------------------------------------------------------
# the estimate
# ----------------------------------------------------------------------------------------------------------------
@dataclasses.dataclass
class BoardEstimate:
    """Location of a tangential board in the log, estimated from traced rings (all lengths mm unless "px").

    Attributes:
        image_shape: ``(H, W)`` of the analysed image (pixels).
        pixel_size_mm: pixel pitch (mm); pixel (y, x) is the board point (u, v) = (x, y)·pixel_size_mm.
        axis_angle: ψ, direction of the projected stem axis in the image (rad, [0, π), from +x towards +y).
        centre_offset_mm: c, signed offset of the projected axis from the image centre along b = (−sin ψ, cos ψ).
        centre_point_px: ``(x, y)`` point of the projected axis closest to the image centre (pixels).
        centre_visible: whether the projected axis crosses the image.
        axis_distance_mm: d0 > 0, distance of the stem axis from the board plane at the image centre.
        tilt: β, out-of-plane inclination of the axis (rad); the distance is d0 − sin β · a'.
        ring_scale_mm: s_r, mean ring width (mm).
        ring_phase: ``(φ0 on the side w' > c, φ0 on the side w' < c)``: traced rings lie at r = s_r·(k + φ0)
            (the two differ by 0.5 when the traced phase level flips sign beyond the centre).
        rotation: ``(3,)`` axis-angle (rad) of the WoodModel board→tree rotation.
        translation: ``(3,)`` WoodModel translation (mm): q = R·(u, v, 0) + translation (z = 0 at the image centre).
        fit_rms_mm: RMS distance (radial, mm) of the ring points from their ideal circles.
        ring_index: per input ring, its integer ring index k (−1 for rings not used: too short or outliers).
        ring_radius_mm: per input ring, the mean radius of its points (NaN if not used).
        ring_order: ring ids ordered across the board along the middle transversal.
        neighbour_distances_mm: mean distance between consecutive rings of ``ring_order`` (over transversals).
        rings: the input polylines, ``(K, 2)`` (x, y) pixel arrays.
    """

    image_shape: tuple
    pixel_size_mm: float
    axis_angle: float
    centre_offset_mm: float
    centre_point_px: tuple
    centre_visible: bool
    axis_distance_mm: float
    tilt: float
    ring_scale_mm: float
    ring_phase: tuple
    rotation: np.ndarray
    translation: np.ndarray
    fit_rms_mm: float
    ring_index: list
    ring_radius_mm: list
    ring_order: list
    neighbour_distances_mm: list
    rings: list = dataclasses.field(repr=False, default_factory=list)

    # ------------------------------------------------------------------------------------------------------------
    def to_dict(self) -> dict:
        """JSON-serialisable dict (plain floats, ints and lists; NaN radii become ``None``)."""
        out = {}
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if f.name == "rings":
                v = [np.asarray(p, dtype=float).tolist() for p in v]
            elif f.name == "ring_radius_mm":
                v = [None if not np.isfinite(x) else float(x) for x in v]
            elif isinstance(v, np.ndarray):
                v = v.astype(float).tolist()
            elif isinstance(v, tuple):
                v = [x.item() if isinstance(x, np.generic) else x for x in v]
            elif isinstance(v, list):
                v = [x.item() if isinstance(x, np.generic) else x for x in v]
            elif isinstance(v, np.generic):
                v = v.item()
            out[f.name] = v
        return out

    @classmethod
    def from_dict(cls, d: dict) -> "BoardEstimate":
        """Inverse of :meth:`to_dict`."""
        names = {f.name for f in dataclasses.fields(cls)}
        missing = names - set(d) - {"rings"}
        if missing:
            raise ValueError(f"d is missing BoardEstimate fields {sorted(missing)}")
        kw = {k: d[k] for k in names if k in d}
        kw["image_shape"] = tuple(int(x) for x in kw["image_shape"])
        kw["centre_point_px"] = tuple(float(x) for x in kw["centre_point_px"])
        kw["ring_phase"] = tuple(float(x) for x in kw["ring_phase"])
        kw["rotation"] = np.asarray(kw["rotation"], dtype=np.float64)
        kw["translation"] = np.asarray(kw["translation"], dtype=np.float64)
        kw["ring_radius_mm"] = [np.nan if x is None else float(x) for x in kw["ring_radius_mm"]]
        kw["rings"] = [np.asarray(p, dtype=np.float64).reshape(-1, 2) for p in kw.get("rings", [])]
        return cls(**kw)

    # ------------------------------------------------------------------------------------------------------------
    def _params(self):
        return (self.axis_angle, self.centre_offset_mm, self.axis_distance_mm, math.sin(self.tilt))

    def rotation_matrix(self) -> np.ndarray:
        """``(3, 3)`` board→tree rotation R (rows: tree x, y, z axes in board coordinates)."""
        return _rotation_matrix(self.axis_angle, self.tilt)

    def tree_points(self, xy_px) -> np.ndarray:
        """Tree-space points ``(N, 3)`` (mm) of pixel positions ``xy_px`` ``(N, 2)`` (x, y) on the board surface."""
        xy = np.asarray(xy_px, dtype=np.float64)
        if xy.ndim != 2 or xy.shape[1] != 2:
            raise ValueError(f"xy_px must have shape (N, 2), got {xy.shape}")
        uv = np.concatenate([xy * self.pixel_size_mm, np.zeros((len(xy), 1))], axis=1)
        return uv @ self.rotation_matrix().T + self.translation

    def pixel_grid(self):
        """``(H, W, 3)`` tree-space points of all pixel centres (mm)."""
        h, w = self.image_shape
        yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
        return self.tree_points(np.stack([xx.ravel(), yy.ravel()], 1)).reshape(h, w, 3)

    def radius_map(self) -> np.ndarray:
        """``(H, W)`` undistorted radius r (mm) of every pixel."""
        q = self.pixel_grid()
        return np.hypot(q[..., 0], q[..., 1])

    def centre_distance_map(self) -> np.ndarray:
        """``(H, W)`` signed distance (mm) of every pixel from the projected tree centre line, w' − c."""
        h, w = self.image_shape
        yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
        _, wp = _board_coords(np.stack([xx, yy], -1).reshape(-1, 2) * self.pixel_size_mm,
                              self.axis_angle, _image_centre_mm(self.image_shape, self.pixel_size_mm))
        return wp.reshape(h, w) - self.centre_offset_mm

    def side_map(self) -> np.ndarray:
        """``(H, W)`` ±1: side of the projected tree centre (+1 where w' > c). The Gabor phase sign typically
        flips across this line."""
        return np.where(self.centre_distance_map() >= 0, 1.0, -1.0)


# ----------------------------------------------------------------------------------------------------------------
# geometry helpers
# ----------------------------------------------------------------------------------------------------------------
def _image_centre_mm(image_shape, pixel_size_mm):
    h, w = image_shape
    return np.array([(w - 1) / 2.0, (h - 1) / 2.0]) * pixel_size_mm


def _board_coords(p_mm, psi, centre_mm):
    """(a', w') of board points ``(N, 2)`` mm for axis angle ψ."""
    d = p_mm - centre_mm
    ca, sa = math.cos(psi), math.sin(psi)
    return d[:, 0] * ca + d[:, 1] * sa, -d[:, 0] * sa + d[:, 1] * ca


def _radius(ap, wp, c, d0, g):
    return np.sqrt((d0 - g * ap) ** 2 + (wp - c) ** 2)


def _rotation_matrix(psi, tilt):
    a = np.array([math.cos(psi), math.sin(psi), 0.0])
    cb, sb = math.cos(tilt), math.sin(tilt)
    z_b = np.array([cb * a[0], cb * a[1], sb])
    x_b = np.array([-sb * a[0], -sb * a[1], cb])
    y_b = np.cross(z_b, x_b)   # = (a_y, −a_x, 0) = −b  ⇒ q_y = −(w' − c)
    return np.stack([x_b, y_b, z_b])


def _transform(psi, c, d0, tilt, image_shape, pixel_size_mm):
    """WoodModel (rotation, translation) for the board geometry."""
    from scipy.spatial.transform import Rotation

    rot = _rotation_matrix(psi, tilt)
    p_c = np.append(_image_centre_mm(image_shape, pixel_size_mm), 0.0)
    t_prime = np.array([d0, c, 0.0])      # tree-space point of the image centre
    translation = t_prime - rot @ p_c
    return Rotation.from_matrix(rot).as_rotvec(), translation


# ----------------------------------------------------------------------------------------------------------------
# input checks
# ----------------------------------------------------------------------------------------------------------------
def _check_rings(rings):
    """Ring polylines: a list of (K, 2) arrays of finite (x, y) pixel positions, as float64 arrays."""
    if not isinstance(rings, (list, tuple)):
        raise TypeError(f"rings: expected a list of (K, 2) arrays, got {describe(rings)}")
    out = []
    for i, p in enumerate(rings):
        try:
            a = np.asarray(p, dtype=np.float64)
        except (TypeError, ValueError):
            raise TypeError(f"rings[{i}]: expected a (K, 2) array of numbers, got {describe(p)}") from None
        if a.ndim != 2 or a.shape[1] != 2:
            raise ValueError(f"rings[{i}]: expected shape (K, 2), got {a.shape}")
        out.append(check_finite(f"rings[{i}]", a))
    return out


def _resample(poly, spacing):
    """Resample a polyline at (about) constant arc-length spacing (px)."""
    seg = np.linalg.norm(np.diff(poly, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    if s[-1] <= 0:
        return poly[:1]
    n = max(2, int(round(s[-1] / spacing)) + 1)
    t = np.linspace(0.0, s[-1], n)
    return np.stack([np.interp(t, s, poly[:, 0]), np.interp(t, s, poly[:, 1])], axis=1)


# ----------------------------------------------------------------------------------------------------------------
# §3.4 steps
# ----------------------------------------------------------------------------------------------------------------
def find_centre_gap(gaps, tolerance=0.1):
    """Index of the gap holding the projected tree centre (paper §3.4).

    The centre lies in the widest gap between neighbouring rings such that the gaps decrease monotonically on both
    sides of it. Gaps are tried widest first; the first whose sides are monotone (each gap at most
    ``1 + tolerance`` times the one before it, going outwards) wins; if none is, the widest with the fewest
    violations.

    Args:
        gaps: ``(n,)`` distances between consecutive ring crossings along a transversal.
        tolerance: relative slack of the monotonicity test (noise in ring positions).

    Returns:
        int index into ``gaps``.
    """
    g = np.asarray(gaps, dtype=np.float64)
    if g.ndim != 1 or len(g) == 0:
        raise ValueError(f"gaps must be a non-empty 1-D array, got shape {g.shape}")
    best, best_viol = None, None
    for i in np.argsort(-g, kind="stable"):
        right = g[i:]
        left = g[: i + 1][::-1]
        viol = int((right[1:] > right[:-1] * (1 + tolerance)).sum() + (left[1:] > left[:-1] * (1 + tolerance)).sum())
        if viol == 0:
            return int(i)
        if best_viol is None or viol < best_viol:
            best, best_viol = int(i), viol
    return best


def _transversals(points_ap, points_wp, ring_of, seg_ok, n_transversals):
    """Crossings of the ring polylines with lines a' = const. Returns list of (A, w' sorted, ring ids sorted)."""
    a0, a1 = points_ap[:-1][seg_ok], points_ap[1:][seg_ok]
    w0, w1 = points_wp[:-1][seg_ok], points_wp[1:][seg_ok]
    rid = ring_of[:-1][seg_ok]
    lo, hi = np.percentile(points_ap, [5, 95])
    out = []
    for A in np.linspace(lo, hi, n_transversals):
        hit = (a0 - A) * (a1 - A) < 0
        hit |= (a0 == A) & (a1 != A)
        if hit.sum() < 2:
            continue
        t = (A - a0[hit]) / (a1[hit] - a0[hit])
        w = w0[hit] + t * (w1[hit] - w0[hit])
        o = np.argsort(w)
        out.append((A, w[o], rid[hit][o]))
    return out


def _assign_rings(rbar, side_major, s_r, phi):
    """Ring indices k_j = round(r̄_j / s_r − φ0[side])."""
    ph = np.where(side_major > 0, phi[0], phi[1])
    return np.rint(rbar / s_r - ph).astype(np.int64)


def _spacing_gaps(rbar, min_gap=0.0):
    """Gaps between sorted mean radii that are single ring widths (legs or fragments of the same ring, with nearly
    equal radii, are merged: gaps below 0.35 × the median gap or below ``min_gap`` mm; a missed ring shows up as a
    double gap and is dropped)."""
    r = np.sort(rbar)
    d = np.diff(r)
    if len(d) == 0:
        return np.zeros(0)
    scale = np.median(d[d > 0]) if (d > 0).any() else 0.0
    d = d[d > max(0.35 * scale, min_gap)]
    if len(d) == 0:
        return d
    med = np.median(d)
    single = d[d < 1.5 * med]
    return single if len(single) else d


def _spacing(rbar):
    """Robust ring spacing from sorted mean radii (median single gap), None if there is no gap."""
    d = _spacing_gaps(rbar)
    return float(np.median(d)) if len(d) else None


def _fit_phase_offsets(rbar, weights, side_major, s_r):
    """Circular mean of r̄/s_r per side → φ0 in [0, 1) (side +1, side −1)."""
    out = []
    for sgn in (1, -1):
        m = side_major == sgn
        if not m.any():
            m = np.ones_like(m)
        z = (weights[m] * np.exp(1j * _TWO_PI * rbar[m] / s_r)).sum()
        out.append((np.angle(z) / _TWO_PI) % 1.0)
    return np.array(out)


def estimate_board(rings, image_shape, pixel_size_mm, *, min_ring_length_px=10.0, n_transversals=15,
                   max_tilt_deg=20.0, max_points=3000, centre_hint_px=None,
                   centre_tolerance_mm=None) -> BoardEstimate:
    """Estimate the board location in the log from traced rings (paper §3.4).

    Args:
        rings: list of ``(K, 2)`` (x, y) pixel polylines (e.g. from :func:`~torch_appearance.rings.trace_rings`).
        image_shape: ``(H, W)`` or ``(H, W, C)`` of the analysed image.
        pixel_size_mm: pixel pitch (mm).
        min_ring_length_px: rings shorter than this are ignored.
        n_transversals: number of lines across the axis used to order rings and locate the centre.
        max_tilt_deg: largest out-of-plane tilt searched.
        max_points: ring points used by the fits (rings are resampled uniformly to stay below it).
        centre_hint_px: optional ``(x, y)`` pixel point that the projected tree centre line must pass within
            ``centre_tolerance_mm`` of (e.g. from :func:`choose_pith_side`); the search and the fit of the
            centre offset c are restricted to that band.
        centre_tolerance_mm: half width of that band (mm); default one ring spacing.

    Returns:
        :class:`BoardEstimate`.

    Raises:
        TypeError, ValueError: bad argument types/shapes; fewer than three usable rings.
    """
    rings = _check_rings(rings)
    h, w = check_image_shape("image_shape", image_shape, channels=True, min_size=2)
    ps = check_positive("pixel_size_mm", pixel_size_mm)
    lengths = np.array([polyline_length(p) for p in rings])
    used = np.nonzero(lengths >= float(min_ring_length_px))[0]
    if len(used) < 3:
        raise ValueError(f"rings: need at least 3 rings of length ≥ {min_ring_length_px} px, got {len(used)}")

    spacing = max(1.0, lengths[used].sum() / max_points)
    pts, ring_of = [], []
    for j, i in enumerate(used):
        p = _resample(rings[i], spacing)
        pts.append(p)
        ring_of.append(np.full(len(p), j))
    pts_px = np.concatenate(pts)
    ring_of = np.concatenate(ring_of)
    seg_ok = ring_of[1:] == ring_of[:-1]
    p_mm = pts_px * ps
    centre = _image_centre_mm((h, w), ps)
    n_rings = len(used)
    counts = np.bincount(ring_of, minlength=n_rings).astype(np.float64)

    # --- axis direction: length-weighted mean of the doubled ring tangent angles
    d = np.diff(p_mm, axis=0)[seg_ok]
    z2 = (np.linalg.norm(d, axis=1) * np.exp(2j * np.arctan2(d[:, 1], d[:, 0]))).sum()
    psi = (0.5 * np.angle(z2)) % math.pi

    # --- order rings across the board along transversals; the centre is in the widest monotone gap
    def transversal_stats(psi_):
        ap, wp = _board_coords(p_mm, psi_, centre)
        trans = _transversals(ap, wp, ring_of, seg_ok, n_transversals)
        centres, all_gaps = [], []
        for A, ws, _ids in trans:
            gaps = np.diff(ws)
            all_gaps.append(gaps)
            i = find_centre_gap(gaps)
            if 0 < i < len(gaps) - 1 or len(gaps) <= 2:
                centres.append((A, 0.5 * (ws[i] + ws[i + 1])))
        return ap, wp, trans, centres, all_gaps

    ap, wp, trans, centres, all_gaps = transversal_stats(psi)
    if len(centres) >= 3:   # the centre line gives a second estimate of the axis direction
        cc = np.array(centres)
        slope = np.polyfit(cc[:, 0], cc[:, 1], 1)[0]
        if abs(slope) < 0.5:
            psi = (psi + math.atan(slope)) % math.pi
            ap, wp, trans, centres, all_gaps = transversal_stats(psi)
    gaps_all = np.concatenate(all_gaps) if all_gaps else np.diff(np.sort(wp))
    s_r0 = float(np.median(gaps_all[gaps_all > 0])) if (gaps_all > 0).any() else float(np.ptp(wp) / n_rings)
    c0 = float(np.median([c for _, c in centres])) if centres else None
    hint = None
    if centre_hint_px is not None:
        hint = np.asarray(centre_hint_px, dtype=np.float64).reshape(-1)
        if hint.shape != (2,) or not np.isfinite(hint).all():
            raise ValueError(f"centre_hint_px: expected a finite (x, y) pair, got {centre_hint_px!r}")
        hint = hint * ps
        tol = s_r0 if centre_tolerance_mm is None else check_positive("centre_tolerance_mm", centre_tolerance_mm)

    def hint_c(psi_):   # offset c of the hinted point for axis angle ψ
        return float(-(hint[0] - centre[0]) * math.sin(psi_) + (hint[1] - centre[1]) * math.cos(psi_))

    # ring order and mean neighbour distances along the middle transversal
    ring_order, neighbour = [], []
    if trans:
        A, ws, ids = trans[len(trans) // 2]
        ring_order = [int(used[i]) for i in ids]
        pair_gaps = {}
        for _, ws_t, ids_t in trans:
            for k in range(len(ids_t) - 1):
                pair_gaps.setdefault((ids_t[k], ids_t[k + 1]), []).append(ws_t[k + 1] - ws_t[k])
        for k in range(len(ids) - 1):
            neighbour.append(float(np.mean(pair_gaps[(ids[k], ids[k + 1])])))

    # --- brute force over (ψ, c, d0, γ): rings must be circles around the axis (normalised within-ring variance)
    sub = np.arange(len(p_mm)) if len(p_mm) <= 600 else np.linspace(0, len(p_mm) - 1, 600).astype(np.int64)
    rs = ring_of[sub]
    cnt_s = np.maximum(np.bincount(rs, minlength=n_rings), 1)
    onehot = sparse.csr_matrix((np.ones(len(rs)), (np.arange(len(rs)), rs)), shape=(len(rs), n_rings))
    span = float(np.ptp(wp))
    psi_grid = psi + np.radians(np.linspace(-12.0, 12.0, 7))
    d_grid = s_r0 * np.geomspace(0.2, 60.0, 20)
    g_grid = np.sin(np.radians(_tilt_grid(float(max_tilt_deg))))
    starts = []
    for psi_k in psi_grid:
        ap_k, wp_k = _board_coords(p_mm[sub], psi_k, centre)
        if hint is not None:
            c_grid = hint_c(psi_k) + tol * np.linspace(-1, 1, 9)
        else:
            c_grid = [np.linspace(wp_k.min() - 1.5 * span, wp_k.max() + 1.5 * span, 25)]
            if c0 is not None:
                c_grid.append(c0 + s_r0 * np.linspace(-2, 2, 9))
            c_grid = np.concatenate(c_grid)
        C, D, Gm = (x.ravel() for x in np.meshgrid(c_grid, d_grid, g_grid, indexing="ij"))
        scores = np.empty(len(C))
        for s0 in range(0, len(C), 4096):
            sl = slice(s0, s0 + 4096)
            r = np.sqrt((D[sl, None] - Gm[sl, None] * ap_k[None]) ** 2 + (wp_k[None] - C[sl, None]) ** 2)
            means = (onehot.T @ r.T).T / cnt_s[None]
            ss_w = ((r - means[:, rs]) ** 2).sum(1)
            ss_t = ((r - r.mean(1, keepdims=True)) ** 2).sum(1)
            scores[sl] = ss_w / np.maximum(ss_t, 1e-300)
        # starts: the best geometry for each axis distance (the paper's brute-force search of the x-translation)
        sc = scores.reshape(len(c_grid), len(d_grid), len(g_grid))
        for j in range(len(d_grid)):
            i, k = np.unravel_index(np.argmin(sc[:, j, :]), (len(c_grid), len(g_grid)))
            starts.append((sc[i, j, k], psi_k, c_grid[i], d_grid[j], g_grid[k]))
    starts.sort(key=lambda t: t[0])
    starts = starts[:6]

    # --- full fit: ring points on circles r = s_r (k_j + φ0[side]) with integer k_j
    # (on ≤ 600 points per start; the winner is polished on all points)
    sub = np.arange(len(p_mm)) if len(p_mm) <= 600 else np.linspace(0, len(p_mm) - 1, 600).astype(np.int64)
    counts_sub = np.bincount(ring_of[sub], minlength=n_rings).astype(np.float64)
    best = None
    for _, psi_s, c_s, d_s, g_s in starts:
        c_band = None if hint is None else (hint_c(psi_s) - tol, hint_c(psi_s) + tol)
        res = _refine(p_mm[sub], ring_of[sub], counts_sub, centre, psi_s, c_s, d_s, g_s, s_r0, rounds=2,
                      c_band=c_band)
        if res is not None and (best is None or res["cost"] < best["cost"]):
            best = res
    if best is not None:
        c_band = None if hint is None else (hint_c(best["psi"]) - tol, hint_c(best["psi"]) + tol)
        full = _refine(p_mm, ring_of, counts, centre, best["psi"], best["c"], best["d0"], best["gamma"], s_r0,
                       rounds=2, c_band=c_band)
        best = full if full is not None else best
    if best is None:
        raise ValueError("rings: could not fit a board geometry to the rings (are they growth rings of a "
                         "tangential board?)")

    psi_f, c_f, d_f, g_f, s_f = best["psi"], best["c"], best["d0"], best["gamma"], best["s_r"]
    # normalise: d0 > 0 (the sign of the x-translation is unobservable), ψ in [0, π)
    if d_f < 0:
        d_f, g_f = -d_f, -g_f
    if not 0 <= psi_f < math.pi:
        k = math.floor(psi_f / math.pi)
        psi_f -= k * math.pi
        if k % 2:   # a → −a flips a', w'
            c_f, g_f = -c_f, -g_f
            best["phi"] = best["phi"][::-1]
    tilt = math.asin(float(np.clip(g_f, -1.0, 1.0)))
    rotation, translation = _transform(psi_f, c_f, d_f, tilt, (h, w), ps)
    b = np.array([-math.sin(psi_f), math.cos(psi_f)])
    centre_pt = (centre + c_f * b) / ps
    corners = np.array([[0, 0], [w - 1, 0], [0, h - 1], [w - 1, h - 1]], dtype=np.float64) * ps
    _, wc = _board_coords(corners, psi_f, centre)
    ring_index = [-1] * len(rings)
    ring_radius = [float("nan")] * len(rings)
    for j, i in enumerate(used):
        if best["keep"][j]:
            ring_index[i] = int(best["k"][j])
            ring_radius[i] = float(best["rbar"][j])
    return BoardEstimate(
        image_shape=(h, w), pixel_size_mm=ps, axis_angle=float(psi_f), centre_offset_mm=float(c_f),
        centre_point_px=(float(centre_pt[0]), float(centre_pt[1])),
        centre_visible=bool(wc.min() <= c_f <= wc.max()), axis_distance_mm=float(d_f), tilt=float(tilt),
        ring_scale_mm=float(s_f), ring_phase=(float(best["phi"][0]), float(best["phi"][1])), rotation=rotation,
        translation=translation, fit_rms_mm=float(best["rms"]), ring_index=ring_index,
        ring_radius_mm=ring_radius, ring_order=ring_order, neighbour_distances_mm=neighbour,
        rings=[np.array(p) for p in rings])


def _tilt_grid(max_tilt_deg):
    """Signed tilt angles (deg) of the brute-force search: 2° steps up to 20° (tangential boards, where the ring
    pattern is most sensitive to the tilt), 5° steps beyond, up to ``max_tilt_deg`` (90°: end grain)."""
    fine = np.linspace(0.0, min(max_tilt_deg, 20.0), int(round(min(max_tilt_deg, 20.0) / 2)) + 1)
    coarse = np.arange(25.0, max_tilt_deg + 1e-9, 5.0) if max_tilt_deg > 20 else np.zeros(0)
    pos = np.concatenate([fine[1:], coarse])
    return np.concatenate([-pos[::-1], [0.0], pos])


def _refine(p_mm, ring_of, counts, centre, psi, c, d0, g, s_r0, rounds=3, c_band=None):
    """Least-squares fit of (ψ, c, d0, γ, s_r, φ0±) with ring indices re-assigned between rounds (c kept inside
    ``c_band`` = (low, high) mm when given)."""
    n_rings = len(counts)
    present = counts > 0
    keep = present.copy()

    def geometry(x):
        ap, wp = _board_coords(p_mm, x[0], centre)
        return ap, wp, _radius(ap, wp, x[1], x[2], x[3])

    def ring_means(v):
        return np.bincount(ring_of, weights=v, minlength=n_rings) / np.maximum(counts, 1)

    x = np.array([psi, c, d0, g])
    ap, wp, r = geometry(x)
    rbar = ring_means(r)
    # spacing per side of the centre line: the traced level may sit half a ring apart on the two sides
    side_major = np.where(ring_means(np.where(wp >= x[1], 1.0, -1.0)) >= 0, 1, -1)
    # (the gaps of both sides are pooled: a side with only two rings must not weigh as much as one with ten)
    # (fragments of one ring traced separately sit closer than a fifth of the transversal ring spacing s_r0)
    found = np.concatenate([_spacing_gaps(rbar[present & (side_major == sgn)], 0.2 * s_r0) for sgn in (1, -1)])
    found = found[np.isfinite(found) & (found > 0)]
    if len(found) == 0:
        return None
    s_r = float(np.median(found))
    if s_r < 0.2 * s_r0:
        return None
    s_r = min(s_r, 3 * s_r0)
    out = None
    for _ in range(rounds):
        side_pt = np.where(wp >= x[1], 1.0, -1.0)
        side_major = np.where(ring_means(side_pt) >= 0, 1, -1)
        phi = _fit_phase_offsets(rbar, counts * keep, side_major, s_r)
        k = _assign_rings(rbar, side_major, s_r, phi)
        side_idx = (side_pt < 0).astype(np.int64)
        pt_keep = keep[ring_of]

        def residuals(y):
            _, _, rr = geometry(y[:4])
            ph = y[5:7][side_idx]
            # in ring widths (phase units): a residual in mm would favour ever flatter geometries (axis far away,
            # tiny s_r, large φ0) that shrink all radius differences together
            return (rr / y[4] - k[ring_of] - ph)[pt_keep]

        y0 = np.concatenate([x, [s_r], phi])
        lower = np.array([-np.inf, -np.inf, -np.inf, -1.0, 0.2 * s_r0, -1.0, -1.0])
        upper = np.array([np.inf, np.inf, np.inf, 1.0, 5.0 * s_r0, 2.0, 2.0])
        if c_band is not None:
            lower[1], upper[1] = c_band
        y0 = np.clip(y0, lower + 1e-9, upper - 1e-9)
        try:
            sol = optimize.least_squares(residuals, y0, loss="soft_l1", f_scale=0.1, x_scale="jac", max_nfev=100,
                                         bounds=(lower, upper))
        except (ValueError, np.linalg.LinAlgError):
            return out
        y = sol.x
        if y[4] < 0.2 * s_r0:
            return out
        x, s_r, phi = y[:4], float(y[4]), y[5:7]
        ap, wp, r = geometry(x)
        rbar = ring_means(r)
        # per-ring RMS; a ring far off its circle (mis-traced) is dropped from the next round
        res = r - s_r * (k[ring_of] + phi[(np.where(wp >= x[1], 0, 1))])
        ring_rms = np.sqrt(ring_means(res ** 2))
        keep = present & (ring_rms < max(0.25 * s_r, 3 * np.median(ring_rms[present])))
        rms = float(np.sqrt(np.mean(res[keep[ring_of]] ** 2)))
        # shift k so that φ0 lies in [0, 1)
        shift = np.floor(phi)
        phi = phi - shift
        k_out = k + shift[np.where(side_major > 0, 0, 1)].astype(np.int64)
        out = {"psi": float(x[0]), "c": float(x[1]), "d0": float(x[2]), "gamma": float(x[3]), "s_r": s_r,
               "phi": phi, "k": k_out.astype(np.int64), "rbar": rbar, "keep": keep, "rms": rms,
               "cost": rms / s_r + 0.02 * (~keep).mean()}
    return out
