"""The phase sign and the growth direction of a board (Nindel et al., thesis ch. 2, §3.5–3.6).

Phase sign: the Gabor phase is ``±(2π G + const)`` with a sign that depends on the (mod π) normal chosen per
pixel; beyond the projected centre the sign flips. :func:`resolve_phase_sign` makes it agree with the model's
``phase = 2π·frac(G)`` (increasing outwards); stage-1 fitting compares ``wrap(resolved − model phase)``. Where
the projected centre line sits decides which side gets flipped, and the ring-based estimate
(:func:`~torch_appearance.rings.board_estimate.estimate_board`) can put it in the
wrong gap (few traced rings on one side): the fit then follows the rings there with latewood on the pith side
(mirrored growth). :func:`choose_pith_side` scores the sign hypotheses of candidate centre lines by how well one
lateness profile explains the photo (:func:`lateness_profile_score`; a ring's profile is asymmetric) and re-fits
the board around the best line. :func:`unwrap_phase` (weighted least squares) serves the initial distortion, which
is fitted to the unwrapped phase residual so that it holds no 2π steps. :func:`split_at_pith_line` filters the
two sides of the projected centre line apart where the rings run along it (the pith line of a board cut through the
pith), where the symmetric profile otherwise bends the phase of the innermost rings.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np
from scipy import ndimage, sparse
from scipy.sparse import linalg as sparse_linalg

from .board_estimate import BoardEstimate, _board_coords, _image_centre_mm, _transform, estimate_board
from .tracing import wrap_angle

__all__ = ["resolve_phase_sign", "lateness_profile_score", "unwrap_phase", "choose_pith_side", "split_at_pith_line"]

_TWO_PI = 2.0 * math.pi


def resolve_phase_sign(phase, estimate: BoardEstimate, *, sigma_px=None, method="gradient"):
    """Flip the Gabor phase so that it increases outwards like the model phase 2π·frac(G).

    Args:
        phase: ``(H, W)`` Gabor phase I_φ (rad).
        estimate: board estimate (gives the ideal radius field r).
        sigma_px: smoothing (pixels) of the per-pixel sign vote; default ¼ of the median ring spacing in pixels.
        method: ``"gradient"``: sign of the (smoothed) agreement of ∇I_φ (wrapped differences) with ∇r, robust to
            any per-region sign convention of the Gabor filter; ``"side"``: +1/−1 on the two sides of the
            projected tree centre, with the global sign from the gradient vote.

    Returns:
        ``(resolved, sign)``: ``(H, W)`` phase in [0, 2π) and the ``(H, W)`` ±1 sign applied.
    """
    from .tracing import _as_field

    phase = _as_field("phase", phase)
    if phase.shape != tuple(estimate.image_shape):
        raise ValueError(f"phase must have the estimate's image shape {tuple(estimate.image_shape)}, "
                         f"got {phase.shape}")
    if method not in ("gradient", "side"):
        raise ValueError(f"method must be 'gradient' or 'side', got {method!r}")
    r = estimate.radius_map()
    gy_r, gx_r = np.gradient(r)
    gx = np.zeros_like(phase)
    gy = np.zeros_like(phase)
    gx[:, 1:-1] = wrap_angle(phase[:, 2:] - phase[:, :-2]) / 2
    gy[1:-1] = wrap_angle(phase[2:] - phase[:-2]) / 2
    vote = gx * gx_r + gy * gy_r
    if sigma_px is None:
        sigma_px = max(1.0, 0.25 * estimate.ring_scale_mm / estimate.pixel_size_mm)
    if method == "gradient":
        sign = np.where(ndimage.gaussian_filter(vote, float(sigma_px)) >= 0, 1.0, -1.0)
    else:
        side = estimate.side_map()
        sign = side * (1.0 if (vote * side).sum() >= 0 else -1.0)
    return (sign * phase) % _TWO_PI, sign


def lateness_profile_score(resolved_phase, gray, weight=None, bins=24):
    """How well ONE lateness profile explains the photo: the weighted R² of the luminance predicted by its mean
    per phase bin (the colour stage of the fit with one colour map shared by all rings).

    The growth direction is what tells the two sign hypotheses of the Gabor phase apart: a ring's profile is
    asymmetric (gradual early → late wood, then the sharp ring boundary), so where the resolved phase runs against
    the growth (latewood on the pith side of its ring) the profile is mirrored and one shared profile explains the
    photo less well. A global sign flip leaves the score unchanged; it only compares sign fields.

    Args:
        resolved_phase: ``(H, W)`` sign-resolved phase (rad, any range; taken mod 2π).
        gray: ``(H, W)`` luminance of the photo.
        weight: optional ``(H, W)`` non-negative weights (e.g. the Gabor magnitude); default uniform.
        bins: number of phase bins (>= 2).

    Returns:
        float R² in (−∞, 1]: 1 − Σw(I − P(bin))² / Σw(I − Ī)².
    """
    from .tracing import _as_field

    ph = _as_field("resolved_phase", resolved_phase)
    g = _as_field("gray", gray, ph.shape)
    w = np.ones_like(g) if weight is None else np.maximum(_as_field("weight", weight, ph.shape), 0.0)
    if isinstance(bins, bool) or not isinstance(bins, (int, np.integer)) or bins < 2:
        raise ValueError(f"bins: expected an integer >= 2, got {bins!r}")
    b = np.minimum((np.mod(ph, _TWO_PI) / _TWO_PI * bins).astype(np.int64), bins - 1).ravel()
    wr, gr = w.ravel(), g.ravel()
    n = np.bincount(b, wr, bins)
    prof = np.bincount(b, wr * gr, bins) / np.maximum(n, 1e-300)
    mean = (wr * gr).sum() / max(wr.sum(), 1e-300)
    total = (wr * (gr - mean) ** 2).sum()
    return float(1.0 - (wr * (gr - prof[b]) ** 2).sum() / max(total, 1e-300))


def unwrap_phase(wrapped, weight=None):
    """Weighted least-squares phase unwrapping (Ghiglia & Romero 1994): the smooth field whose neighbour
    differences match the wrapped differences of ``wrapped``.

    Solves min Σ w_ij (u_i − u_j − wrap(φ_i − φ_j))² over 4-neighbour pairs (w_ij = min of the two pixel weights)
    (plus a tiny ridge term); the free constant is the weighted circular mean of the input minus the solution, so
    wrap(result) ≈ wrapped. Where the wrapped field is smooth this is
    exact unwrapping; at residues (true phase singularities) the error is spread smoothly instead of left as
    2π cuts.

    Args:
        wrapped: ``(H, W)`` phase (rad). weight: optional ``(H, W)`` non-negative confidence (default uniform).

    Returns:
        ``(H, W)`` float64 unwrapped phase (rad).
    """
    from .tracing import _as_field

    phi = _as_field("wrapped", wrapped).astype(np.float64)
    h, w = phi.shape
    wt = np.ones_like(phi) if weight is None else np.maximum(_as_field("weight", weight, phi.shape), 0.0)
    wt = wt / max(float(wt.mean()), 1e-300) + 1e-3
    idx = np.arange(h * w).reshape(h, w)
    rows_i, rows_j, vals, ws = [], [], [], []
    for a, b, da in ((idx[:, :-1], idx[:, 1:], phi[:, 1:] - phi[:, :-1]),
                     (idx[:-1, :], idx[1:, :], phi[1:, :] - phi[:-1, :])):
        rows_i.append(a.ravel())
        rows_j.append(b.ravel())
        vals.append(wrap_angle(da).ravel())
        ws.append(np.minimum(wt.ravel()[a.ravel()], wt.ravel()[b.ravel()]))
    i, j, d, we = (np.concatenate(x) for x in (rows_i, rows_j, vals, ws))
    m = len(i)
    dmat = sparse.csr_matrix((np.concatenate([-np.ones(m), np.ones(m)]),
                              (np.concatenate([np.arange(m)] * 2), np.concatenate([i, j]))), shape=(m, h * w))
    eps = 1e-8
    lhs = (dmat.T @ sparse.diags(we) @ dmat + eps * sparse.identity(h * w)).tocsc()
    u = sparse_linalg.spsolve(lhs, dmat.T @ (we * d)).reshape(h, w)
    return u + np.angle((wt * np.exp(1j * (phi - u))).sum())


def _with_centre(estimate, c):
    """The estimate with its projected centre line moved to offset ``c`` (mm), other geometry kept."""
    h, w = estimate.image_shape
    ps = estimate.pixel_size_mm
    rotation, translation = _transform(estimate.axis_angle, c, estimate.axis_distance_mm, estimate.tilt, (h, w), ps)
    b = np.array([-math.sin(estimate.axis_angle), math.cos(estimate.axis_angle)])
    centre_pt = (_image_centre_mm((h, w), ps) + c * b) / ps
    return dataclasses.replace(estimate, centre_offset_mm=float(c), rotation=rotation, translation=translation,
                               centre_point_px=(float(centre_pt[0]), float(centre_pt[1])))


def _ring_fit_cost(estimate):
    """RMS distance of the traced ring points from the estimate's circles, in ring widths."""
    return estimate.fit_rms_mm / estimate.ring_scale_mm


def choose_pith_side(estimate: BoardEstimate, phase, gray, *, magnitude=None, rings=None, n_candidates=49,
                     min_gain=0.01):
    """Place the projected tree centre (the line where the phase sign flips) where the growth direction is
    consistent on both sides of it, re-fitting the board geometry there if the ring-based estimate put it
    elsewhere.

    The ring-based estimate (widest monotone gap, §3.4) can put the centre line in the wrong gap when few rings
    are traced; the phase is then resolved the wrong way between the true and the estimated line, and a fit
    follows the rings there with latewood on the wrong side (mirrored growth). Here the sign hypotheses are
    scored by the fit itself: for every candidate line (``n_candidates`` offsets c across the board and beyond
    its edges, the estimate's axis direction, distance and tilt kept) the phase is resolved
    (:func:`resolve_phase_sign`) and scored by :func:`lateness_profile_score`. If the best candidate beats the
    estimate and lies more than half a ring away, :func:`estimate_board` is run again with the centre restricted
    to one ring spacing around it, and the best-scoring of the estimate and the re-fit is returned. The ring fit
    supports the move where the re-fit's line lies more than half a ring from the estimate's and the traced rings
    fit it better (lower RMS in ring widths); then the re-fit with its line moved to the best candidate is a third
    option, where the ring fit shifted the line by more than half a ring within its band. A gain below
    ``min_gain`` (a symmetric ring profile, e.g. an abrupt latewood band, scores both growth directions nearly
    alike) moves the line only where the ring fit supports it: the ring search scores lines off the photo too well
    on a board cut near the pith, and can miss the geometry of a board whose rings bulge round a knot.

    Args:
        estimate: :class:`BoardEstimate` from :func:`estimate_board`.
        phase: ``(H, W)`` Gabor phase (rad). gray: ``(H, W)`` luminance of the photo.
        magnitude: optional ``(H, W)`` Gabor magnitude (score weights).
        rings: the ring polylines of ``estimate`` (default ``estimate.rings``), for the re-fit.
        n_candidates: number of candidate offsets (>= 3). min_gain: R² gain that moves the line on the lateness
            score alone (a smaller gain needs a better ring fit as well).

    Returns:
        ``(estimate, info)``: the chosen :class:`BoardEstimate` and a dict with ``score_initial``,
        ``score_chosen`` (R²), ``moved`` (bool), ``candidates_mm`` and ``candidate_scores``.
    """
    from .tracing import _as_field

    if not isinstance(estimate, BoardEstimate):
        raise TypeError(f"estimate: expected a BoardEstimate, got {type(estimate).__name__}")
    phase = _as_field("phase", phase, tuple(estimate.image_shape))
    gray = _as_field("gray", gray, phase.shape)
    mag = None if magnitude is None else _as_field("magnitude", magnitude, phase.shape)
    if isinstance(n_candidates, bool) or not isinstance(n_candidates, (int, np.integer)) or n_candidates < 3:
        raise ValueError(f"n_candidates: expected an integer >= 3, got {n_candidates!r}")

    def score(est):
        return lateness_profile_score(resolve_phase_sign(phase, est)[0], gray, mag)

    h, w = estimate.image_shape
    ps, s_r = estimate.pixel_size_mm, estimate.ring_scale_mm
    corners = np.array([[0, 0], [w - 1, 0], [0, h - 1], [w - 1, h - 1]], dtype=np.float64) * ps
    _, wc = _board_coords(corners, estimate.axis_angle, _image_centre_mm((h, w), ps))
    cands = np.linspace(wc.min() - s_r, wc.max() + s_r, int(n_candidates))
    scores = np.array([score(_with_centre(estimate, c)) for c in cands])
    s0 = score(estimate)
    info = {"score_initial": s0, "score_chosen": s0, "moved": False, "candidates_mm": cands.tolist(),
            "candidate_scores": scores.tolist()}
    i = int(np.argmax(scores))
    if scores[i] <= s0 or abs(cands[i] - estimate.centre_offset_mm) <= 0.5 * s_r:
        return estimate, info
    # a gain below min_gain moves the line only where the rings fit the re-fitted geometry better too
    weak = scores[i] < s0 + min_gain
    hint = _with_centre(estimate, cands[i]).centre_point_px
    tol = max(s_r, float(cands[1] - cands[0]))
    rings = estimate.rings if rings is None else rings
    try:
        refit = estimate_board(rings, (h, w), ps, centre_hint_px=hint, centre_tolerance_mm=tol)
    except ValueError:
        refit = None
    options = [(s0, estimate)]
    # the ring fit itself supports the move: near the candidate it finds a line more than half a ring from the
    # estimate's, with the traced rings closer to its circles (a re-fit that returns to the estimate's line, as
    # it can when the band holds it, does not)
    better_rings = (refit is not None and abs(refit.centre_offset_mm - estimate.centre_offset_mm) > 0.5 * s_r
                    and _ring_fit_cost(refit) < _ring_fit_cost(estimate))
    if refit is not None and (better_rings or not weak):
        options.append((score(refit), refit))
    if better_rings and abs(refit.centre_offset_mm - cands[i]) > 0.5 * s_r:
        # the rings fit better away from the estimate, but the ring fit shifted the line by more than half a ring
        # within its band (e.g. towards a ring traced along the pith line): the re-fitted geometry with the line
        # where the lateness profile put it is a third option (nearer, the score does not place it better)
        moved = _with_centre(refit, cands[i])
        options.append((score(moved), moved))
    best_s, best = max(options, key=lambda t: t[0])
    info.update(score_chosen=best_s, moved=best is not estimate)
    return best, info


def split_at_pith_line(gray, estimate: BoardEstimate, gabor, *, p=80, q=80, device="cpu", parallel=0.5):
    """The Gabor response with the two sides of the projected tree centre line filtered apart where the rings run
    along it.

    On a board cut through the pith the rings on the two sides of the pith line are mirror images: the profile
    across them is symmetric there, so the Gabor response is real on the line (phase 0 or π, whatever the ring's
    phase is) and, over the filter's support (about a ring), the phase of the innermost ring on each side is bent
    towards it (0.4–1 rad on the independent boards; the fit then places the pith-line ring half a cycle off).
    Here the filter is run again with the centre line as a barrier
    (``curved_gabor(..., barrier=...)``) at the pixels whose rings run within ``acos(parallel)`` of the line's
    direction (across a ring that crosses the line, e.g. at an arch's tip, there is no mirror), and each pixel
    keeps the stronger of the two responses: a one-sided profile keeps its amplitude where the mirrored halves
    cancel, and where the line is misplaced (through a ring rather than along its symmetry axis) the unsplit
    response is usually the stronger one.

    Args:
        gray: ``(H, W)`` luminance of the photo. estimate: the :class:`BoardEstimate` (gives the centre line).
        gabor: the :class:`~torch_appearance.rings.gabor.GaborResult` of ``curved_gabor(gray, p=p, q=q)``.
        p, q, device: as for that call. parallel: |cos| of the angle between a pixel's ring normal and the line's
            normal above which the barrier applies (in (0, 1]).

    Returns:
        ``(gabor, info)``: a :class:`GaborResult` (``phase`` and ``magnitude`` replaced where the split response
        is stronger; the other fields of ``gabor``) and a dict with ``split`` (bool: the line crosses the photo)
        and ``fraction_split`` (share of pixels whose response changed by more than 1 % of the median magnitude).
    """
    from .gabor import curved_gabor
    from .tracing import _as_field

    gray = _as_field("gray", gray, tuple(estimate.image_shape))
    if not (isinstance(parallel, (int, float)) and 0 < parallel <= 1):
        raise ValueError(f"parallel: expected a value in (0, 1], got {parallel!r}")
    dist = estimate.centre_distance_map()
    if dist.min() >= 0 or dist.max() <= 0:  # the line misses the photo: nothing to split
        return gabor, {"split": False, "fraction_split": 0.0}
    th = gabor.theta.astype(np.float64)
    b = np.array([-math.sin(estimate.axis_angle), math.cos(estimate.axis_angle)])
    along = np.abs(-np.sin(th) * b[0] + np.cos(th) * b[1]) > parallel
    split = curved_gabor(gray, p=p, q=q, device=device, barrier=np.where(along, dist, 0.0))
    r0 = gabor.magnitude * np.exp(1j * gabor.phase)
    r1 = split.magnitude * np.exp(1j * split.phase)
    take = split.magnitude > gabor.magnitude
    changed = np.abs(r1 - r0) > 0.01 * max(float(np.median(gabor.magnitude)), 1e-12)
    out = dataclasses.replace(gabor, phase=np.where(take, split.phase, gabor.phase).astype(np.float32),
                              magnitude=np.where(take, split.magnitude, gabor.magnitude).astype(np.float32))
    return out, {"split": True, "fraction_split": float((take & changed).mean())}

