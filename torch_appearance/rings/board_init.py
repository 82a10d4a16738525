"""The initial WoodModel of a board: ring scale, transform and radial distortion from the board estimate and the
sign-resolved Gabor phase (Nindel et al., thesis ch. 2, §3.5–3.6): the traced rings' offsets from their ideal
circles, then the dense (unwrapped) phase residual, fitted as the model's distortion texture by sparse least
squares with a Laplacian smoothness prior, so that the local phase error starts well below π/2.
"""
from __future__ import annotations

import math

import numpy as np
from scipy import sparse
from scipy.sparse import linalg as sparse_linalg

from .board_estimate import BoardEstimate, _board_coords, _check_rings, _image_centre_mm, _resample
from .board_phase import resolve_phase_sign, unwrap_phase
from .tracing import wrap_angle

__all__ = ["initial_wood_model"]

_TWO_PI = 2.0 * math.pi


def _texture_weights(model, q):
    """Sparse (N, Hd·Wd) weights of the model's m_r texture at tree points q (N, 3): its bilinear
    grid_sample(align_corners=True, padding_mode='border') lookup times its taper at the pith."""
    hd, wd = model.distortion_shape
    z0, z1 = model.z_range_mm
    ix = np.clip((q[:, 2] - z0) / (z1 - z0) * (wd - 1), 0, wd - 1)
    r = np.hypot(q[:, 0], q[:, 1])
    if model.distortion == "radial":
        iy = np.clip(r / model.r_max_mm * (hd - 1), 0, hd - 1)
        periodic = False
    else:
        iy = (np.arctan2(q[:, 1], q[:, 0]) + math.pi) * (hd / _TWO_PI)
        periodic = True
    x0 = np.minimum(np.floor(ix).astype(np.int64), wd - 2)
    fx = ix - x0
    if periodic:
        y0 = np.floor(iy).astype(np.int64)
        fy = iy - y0
        y0 %= hd
        y1 = (y0 + 1) % hd
    else:
        y0 = np.minimum(np.floor(iy).astype(np.int64), hd - 2)
        fy = iy - y0
        y1 = y0 + 1
    n = len(q)
    rows = np.repeat(np.arange(n), 4)
    cols = np.stack([y0 * wd + x0, y0 * wd + x0 + 1, y1 * wd + x0, y1 * wd + x0 + 1], 1).ravel()
    # the model's taper at the pith (WoodModel pith_taper_mm): the displacement there is tau(r) times the lookup
    tau = 1.0 - np.exp(-(r / model.pith_taper_mm) ** 2) if model.pith_taper_mm > 0 else np.ones(n)
    vals = (np.stack([(1 - fy) * (1 - fx), (1 - fy) * fx, fy * (1 - fx), fy * fx], 1) * tau[:, None]).ravel()
    return sparse.csr_matrix((vals, (rows, cols)), shape=(n, hd * wd))


def _lobe_weights(model, q):
    """Sparse (N, Hθ·Hp) weights of the model's lobe texture m_p at tree points q (N, 3): its bilinear lookup over
    (θ_t periodic, r ∈ [0, R_p]) times the window ω(r) (WoodModel._lobes)."""
    ht, hp = model.lobe_shape
    big = model.lobe_radius_mm
    r = np.hypot(q[:, 0], q[:, 1])
    ix = np.clip(r / big, 0, 1) * (hp - 1)
    iy = (np.arctan2(q[:, 1], q[:, 0]) + math.pi) * (ht / _TWO_PI)
    x0 = np.minimum(np.floor(ix).astype(np.int64), hp - 2)
    fx = ix - x0
    y0 = np.floor(iy).astype(np.int64)
    fy = iy - y0
    y0 %= ht
    y1 = (y0 + 1) % ht
    x = np.minimum(r / big, 1.0)
    omega = (1.0 - np.exp(-r / (big / 4.0))) * (1.0 - x * x) ** 2
    n = len(q)
    rows = np.repeat(np.arange(n), 4)
    cols = np.stack([y0 * hp + x0, y0 * hp + x0 + 1, y1 * hp + x0, y1 * hp + x0 + 1], 1).ravel()
    vals = (np.stack([(1 - fy) * (1 - fx), (1 - fy) * fx, fy * (1 - fx), fy * fx], 1) * omega[:, None]).ravel()
    return sparse.csr_matrix((vals, (rows, cols)), shape=(n, ht * hp))


def _laplacian(hd, wd, periodic_rows):
    """Graph Laplacian of the texel grid (smoothness prior)."""
    idx = np.arange(hd * wd).reshape(hd, wd)
    pairs = [np.stack([idx[:, :-1].ravel(), idx[:, 1:].ravel()], 1)]
    if periodic_rows:
        pairs.append(np.stack([idx.ravel(), np.roll(idx, -1, axis=0).ravel()], 1))
    else:
        pairs.append(np.stack([idx[:-1].ravel(), idx[1:].ravel()], 1))
    e = np.concatenate(pairs)
    m = len(e)
    dmat = sparse.csr_matrix((np.concatenate([np.ones(m), -np.ones(m)]),
                              (np.concatenate([np.arange(m)] * 2), np.concatenate([e[:, 0], e[:, 1]]))),
                             shape=(m, hd * wd))
    return (dmat.T @ dmat).tocsr()


def initial_wood_model(estimate: BoardEstimate, phase, *, magnitude=None, rings=None, distortion="radial",
                       distortion_shape=(32, 64), n_rings=64, smoothness=1e-3, dense_refine=True,
                       dtype=None, return_info=False, color_bins=16, pith_taper_rings=1.0, lobe_shape=None,
                       lobe_radius_rings=4.0):
    """Initial WoodModel (board transform, ring scale, radial distortion) from a board estimate (paper §3.5).

    The distortion starts from the paper's recipe, the difference between the observed traced rings and their
    ideal undistorted circles r = s_r·(k + φ0) mapped to radial displacements, plus a global offset that makes
    the model phase 2π·frac(G) agree with the sign-resolved Gabor phase; with ``dense_refine`` the wrapped
    per-pixel phase residual is then added (it is small once the rings are in place). The texture is the
    least-squares fit (magnitude-weighted, with a small Laplacian smoothness prior) of these displacements at the
    pixels' tree-space (z, r) — or (z, θ_t) for ``distortion="azimuthal"`` — positions. The displacement fades
    within ``pith_taper_rings`` ring widths of the pith (``WoodModel(pith_taper_mm=...)``), and its median over the
    board, a constant that only shifts the phase, is moved into the target phase (``info["phase_offset"]``), so
    that G = 0 stays at the pith.

    Args:
        estimate: :class:`BoardEstimate` from :func:`estimate_board`.
        phase: ``(H, W)`` Gabor phase of the photograph (rad), as traced.
        magnitude: optional ``(H, W)`` Gabor magnitude (weights of the dense fit).
        rings: ring polylines; default ``estimate.rings`` (with ``estimate.ring_index``).
        distortion, distortion_shape, n_rings, color_bins: passed to ``WoodModel``.
        pith_taper_rings: the model's ``pith_taper_mm`` in ring widths (0: no taper).
        lobe_shape: ``(Hθ, Hp)`` of the model's lobe texture near the pith (``WoodModel(lobe_shape=...)``), fitted
            with the distortion in the dense refinement; ``None``: no lobes. lobe_radius_rings: its radius R_p in
            ring widths (> 0).
        smoothness: weight of the Laplacian prior relative to the mean data weight per texel.
        dense_refine: add the wrapped dense phase residual (recommended).
        dtype: torch dtype of the model (default float32).
        return_info: also return a dict with ``resolved_phase`` (H, W; the sign-resolved Gabor phase less
            ``phase_offset``, in [0, 2π): the target for the model's phase), ``phase_offset`` (rad: the constant
            displacement c taken out of the texture, 2π c / s_r), ``sign`` (H, W), ``phase_error`` (H, W) wrapped
            (resolved − model phase, rad), ``fraction_below_half_pi`` and ``rms_phase_error``.

    Returns:
        :class:`~torch_appearance.nn.wood.WoodModel` (and the info dict with ``return_info``).

    Raises:
        TypeError, ValueError: bad inputs (wrong shapes, unknown distortion, no usable rings).
    """
    import torch
    from ..nn.wood import WoodModel

    if not isinstance(estimate, BoardEstimate):
        raise TypeError(f"estimate must be a BoardEstimate, got {type(estimate).__name__}")
    if distortion not in ("radial", "azimuthal"):
        raise ValueError(f"distortion must be 'radial' or 'azimuthal' (the initial guess is a distortion), "
                         f"got {distortion!r}")
    from .tracing import _as_field

    phase = _as_field("phase", phase, tuple(estimate.image_shape))
    if lobe_shape is not None:
        from ..checks import check_positive

        lobe_radius_rings = check_positive("lobe_radius_rings", lobe_radius_rings)
    mag = None if magnitude is None else _as_field("magnitude", magnitude, phase.shape)
    dtype = torch.float32 if dtype is None else dtype
    h, w = estimate.image_shape
    ps = estimate.pixel_size_mm
    s_r = estimate.ring_scale_mm
    resolved, sign = resolve_phase_sign(phase, estimate)

    q = estimate.pixel_grid().reshape(-1, 3)
    r = np.hypot(q[:, 0], q[:, 1])
    z = q[:, 2]
    zspan = z.max() - z.min()
    z_range = (float(z.min() - 0.05 * zspan - 1e-3), float(z.max() + 0.05 * zspan + 1e-3))
    r_max = float(r.max() + 2 * s_r)
    model = WoodModel(ring_scale_mm=s_r, n_rings=n_rings, distortion=distortion, distortion_shape=distortion_shape,
                      r_max_mm=r_max, z_range_mm=z_range, dtype=dtype, color_bins=color_bins,
                      pith_taper_mm=pith_taper_rings * s_r, lobe_shape=lobe_shape,
                      lobe_radius_mm=None if lobe_shape is None else lobe_radius_rings * s_r)
    model.set_parameters(rotation=torch.as_tensor(estimate.rotation, dtype=torch.float64),
                         translation=torch.as_tensor(estimate.translation, dtype=torch.float64))

    # --- ring-based displacements: observed ring points vs. their ideal circles
    if rings is None:
        rings, ring_index = estimate.rings, estimate.ring_index
        rings = _check_rings(rings)
    else:
        rings = _check_rings(rings)
        ring_index = None
    rows, targets = [], []
    c = estimate.centre_offset_mm
    centre = _image_centre_mm((h, w), ps)
    for j, poly in enumerate(rings):
        if len(poly) < 2 or (ring_index is not None and ring_index[j] < 0):
            continue
        p = _resample(poly, 1.0)
        qq = estimate.tree_points(p)
        rr = np.hypot(qq[:, 0], qq[:, 1])
        _, wp = _board_coords(p * ps, estimate.axis_angle, centre)
        phi = np.where(wp >= c, estimate.ring_phase[0], estimate.ring_phase[1])
        k = ring_index[j] if ring_index is not None else int(np.rint(np.median(rr / s_r - phi)))
        rows.append(qq)
        targets.append(s_r * (k + phi) - rr)
    if not rows:
        raise ValueError("rings: no usable ring polylines for the initial distortion")
    q_ring = np.concatenate(rows)
    m_ring = np.concatenate(targets)

    hd, wd = model.distortion_shape
    lap = _laplacian(hd, wd, periodic_rows=distortion == "azimuthal")

    def solve(a_mat, values, weights, a_lobe=None):
        """Weighted least squares of the texture (and, with ``a_lobe``, the lobe texture beside it)."""
        lam = smoothness * max(float(weights.sum()) / (hd * wd), 1e-12)
        prior = lam * lap + 1e-9 * lam * sparse.identity(hd * wd)
        if a_lobe is not None:   # the lobes: the same smoothness per texel, and a ridge that keeps unseen ones at 0
            a_mat = sparse.hstack([a_mat, a_lobe]).tocsr()
            prior = sparse.block_diag([prior, lam * lap_lobe + 1e-3 * lam * sparse.identity(lap_lobe.shape[0])])
        wmat = sparse.diags(weights)
        lhs = (a_mat.T @ wmat @ a_mat).tocsr() + prior
        x = sparse_linalg.spsolve(lhs.tocsc(), a_mat.T @ (weights * values))
        return x if a_lobe is None else (x[: hd * wd], x[hd * wd:])

    # ring displacements are sparse in (z, r): fit them with a stronger smoothness so that texels between rings
    # interpolate; then add the offset that matches the dense resolved phase
    a_ring = _texture_weights(model, q_ring)
    tex = solve(a_ring, m_ring - np.median(m_ring), np.ones(len(m_ring))) + np.median(m_ring)
    a_pix = _texture_weights(model, q)
    weight = np.ones(len(q)) if mag is None else np.maximum(mag.ravel(), 0.0)
    m_pix = a_pix @ tex
    resid = wrap_angle(resolved.ravel() - _TWO_PI * (r + m_pix) / s_r)
    offset = np.angle((weight * np.exp(1j * resid)).sum())
    tex = tex + s_r * offset / _TWO_PI
    # the lobe texture takes part only where the pith region (r < R_p) is on the board
    a_lobe = lobe = None
    if lobe_shape is not None:
        a_lobe = _lobe_weights(model, q)
        lobe = np.zeros(a_lobe.shape[1])
        if a_lobe.nnz == 0 or not np.any(a_lobe.sum(axis=0) > 0):
            a_lobe = None
        else:
            lap_lobe = _laplacian(*model.lobe_shape, periodic_rows=True)

    def displacement():
        return a_pix @ tex + (0.0 if a_lobe is None else a_lobe @ lobe)

    if dense_refine:
        m_pix = displacement()
        resid = wrap_angle(resolved.ravel() - _TWO_PI * (r + m_pix) / s_r)
        # unwrapped: a wrapped residual jumps by 2π where it crosses ±π, and a texture fitted to it puts a whole
        # ring's displacement step there (the blocky 2π slips along texel cells that the cyclic loss cannot undo)
        resid = unwrap_phase(resid.reshape(h, w), weight.reshape(h, w)).ravel()
        if a_lobe is None:
            tex = solve(a_pix, m_pix + s_r * resid / _TWO_PI, weight + 1e-12)
        else:
            tex, lobe = solve(a_pix, m_pix + s_r * resid / _TWO_PI, weight + 1e-12, a_lobe)
        # then the small remainder the smooth texture could not follow, only where it is below π/2 (no 2π cut)
        m_pix = displacement()
        resid = wrap_angle(resolved.ravel() - _TWO_PI * (r + m_pix) / s_r)
        near = np.abs(resid) < math.pi / 2
        if a_lobe is None:
            tex = solve(a_pix, m_pix + s_r * np.where(near, resid, 0.0) / _TWO_PI, weight * near + 1e-12)
        else:
            tex, lobe = solve(a_pix, m_pix + s_r * np.where(near, resid, 0.0) / _TWO_PI, weight * near + 1e-12,
                              a_lobe)
    # A constant displacement c only shifts the model phase by 2π c / s_r away from the pith, so it is carried as a
    # shift of the target phase: left in the texture (about −0.35 ring on pith-inside boards) it made G negative at
    # the pith, and the taper there would fight it
    c = float(np.median(a_pix @ tex))
    tex = tex - c
    phase_offset = _TWO_PI * c / s_r
    resolved = np.mod(resolved - phase_offset, _TWO_PI)
    model.set_parameters(m_r=torch.as_tensor(tex.reshape(hd, wd), dtype=torch.float64))
    if lobe is not None:
        model.set_parameters(m_p=torch.as_tensor(lobe.reshape(model.lobe_shape), dtype=torch.float64))
    if not return_info:
        return model
    with torch.no_grad():
        out = model.render_board(h, w, ps)
    err = wrap_angle(resolved - out["phase"].double().cpu().numpy())
    wsum = weight.reshape(h, w)
    info = {"resolved_phase": resolved, "phase_offset": phase_offset, "sign": sign, "phase_error": err,
            "fraction_below_half_pi": float((wsum * (np.abs(err) < math.pi / 2)).sum() / wsum.sum()),
            "rms_phase_error": float(np.sqrt((wsum * err ** 2).sum() / wsum.sum()))}
    return model, info
