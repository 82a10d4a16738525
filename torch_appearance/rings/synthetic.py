"""Synthetic flat-sawn boards with known ground truth, rendered from a :class:`~torch_appearance.nn.WoodModel`.

A flat-sawn (tangential) board has the stem axis roughly in the board plane: the growth cylinders cut the plane in
nested arches ("cathedrals") whose apexes point along the stem, which is slightly inclined to the board. The
generator draws a random board transform, ring width, smooth radial distortion and per-ring colours, renders
the board, adds pixel noise and returns the exact growth field, phase and ring boundaries (iso-lines G ∈ ℤ refined
with Newton steps on the model itself), for testing ring detection and board estimation.

Example:
    >>> from torch_appearance.rings import synthetic_board
    >>> board = synthetic_board(128, 160, pixel_size_mm=0.1, seed=3)
    >>> board["image"].shape, board["image"].dtype
    ((128, 160, 3), dtype('float32'))
"""
from __future__ import annotations

import copy
import math
import numbers

import numpy as np
import torch

from ..checks import check_int, check_positive
from ..nn.wood import WoodModel, matrix_to_axis_angle

__all__ = ["synthetic_board"]

_EARLY = np.array([0.62, 0.44, 0.27])
_LATE = np.array([0.27, 0.14, 0.06])


def _rotation(axis, angle):
    """Rotation matrix about a principal axis (0 = x, 1 = y, 2 = z) by ``angle`` rad."""
    c, s = math.cos(angle), math.sin(angle)
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    m = np.eye(3)
    m[i, i], m[i, j], m[j, i], m[j, j] = c, -s, s, c
    return m


def _range(name, value, rng, low, high):
    """``value`` if given (validated > 0), else uniform in [low, high]."""
    if value is None:
        return float(rng.uniform(low, high))
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(value):
        raise TypeError(f"{name}: expected a finite real number or None, got {value!r}")
    return float(value)


def _boundaries(model, G, pixel_size_mm, newton_steps=3):
    """Sub-pixel iso-lines of G at the integers, as (x, y) pixel polylines refined by Newton steps on the model."""
    import contourpy

    g = G.astype(np.float64)
    levels = np.arange(math.ceil(g.min()), math.floor(g.max()) + 1)
    gen = contourpy.contour_generator(z=g, line_type=contourpy.LineType.Separate)
    lines, owners = [], []
    for level in levels:
        for line in gen.lines(float(level)):
            if len(line) >= 2:
                lines.append(np.asarray(line, dtype=np.float64))
                owners.append(float(level))
    if not lines:
        return [], []
    sizes = [len(line) for line in lines]
    pts = torch.from_numpy(np.concatenate(lines))
    target = torch.from_numpy(np.repeat(np.asarray(owners), sizes))
    model64 = copy.deepcopy(model).to(torch.float64)
    for p in model64.parameters():
        p.requires_grad_(False)
    h, w = G.shape
    # Vertices on the image border only move along it (free coordinate mask).
    free = torch.ones_like(pts)
    free[:, 0] = ((pts[:, 0] > 1e-9) & (pts[:, 0] < w - 1 - 1e-9)).to(pts.dtype)
    free[:, 1] = ((pts[:, 1] > 1e-9) & (pts[:, 1] < h - 1 - 1e-9)).to(pts.dtype)
    for _ in range(newton_steps):
        pts = pts.detach().requires_grad_(True)
        value = model64.evaluate(pts * pixel_size_mm, board=True)["G"]
        (grad,) = torch.autograd.grad(value.sum(), pts)
        grad = grad * free
        step = (value.detach() - target) / (grad * grad).sum(-1).clamp_min(1e-30)
        pts = pts.detach() - step[:, None] * grad
        pts[:, 0].clamp_(0, w - 1)
        pts[:, 1].clamp_(0, h - 1)
    return [chunk.numpy() for chunk in torch.split(pts.detach(), sizes)], [int(v) for v in owners]


def synthetic_board(height=256, width=256, pixel_size_mm=0.1, seed=0, noise=0.02, *, ring_scale_mm=None,
                    distance_mm=None, tilt_deg=None, in_plane_deg=None, distortion_mm=None, n_rings=64,
                    distortion_shape=(32, 64), color_bins=32, color_variation=0.08, pith_inside=False) -> dict:
    """Render a random flat-sawn board with known growth field.

    The stem axis lies roughly in the board plane: board columns (u) run across the rings, rows (v) along the
    stem; the axis is inclined out of the plane by ``tilt_deg`` (so rings form nested arches) and rotated in the
    plane by ``in_plane_deg``; it passes ``distance_mm`` below the board centre, its projection within ±20 % of
    the width from the centre column.

    Args:
        height: H, rows (>= 2).
        width: W, columns (>= 2).
        pixel_size_mm: pixel pitch (mm, > 0).
        seed: integer seed of all random choices (``numpy.random.default_rng``).
        noise: standard deviation of additive Gaussian pixel noise (linear RGB units, >= 0).
        ring_scale_mm: ring width s_r (mm); default uniform in [1, 4] mm intersected with [8, 40] px when possible.
        distance_mm: distance of the stem axis from the board centre (mm); default uniform in [5, 30].
        tilt_deg: inclination of the axis out of the board plane (deg); default ±[4, 12].
        in_plane_deg: rotation of the axis within the board plane w.r.t. the rows (deg); default uniform ±10.
        distortion_mm: amplitude of the smooth radial distortion (mm); default 0.15·s_r; 0 disables it.
        n_rings: ``WoodModel.n_rings`` (rings with their own colour).
        distortion_shape: ``(Hd, Wd)`` of the radial distortion texture.
        color_bins: lateness samples of the colour map.
        color_variation: relative per-ring colour jitter (>= 0).
        pith_inside: draw a board cut close to the pith, whose pith itself lies in the photo: default distance
            uniform in [1.5, 4] mm and tilt ±[12, 20]°, so the axis pierces the board plane inside the image and
            the innermost rings are closed ovals along the projected axis (the "cathedral" figure with its
            centre); the distortion is tapered to 0 at the pith (the model's ``pith_taper_mm = s_r``: factor
            1 − exp(−(r/s_r)²)) so that G >= 0.
            The random draws are the same as without it (same seed, same ring scale, colours and distortion
            shape).

    Returns:
        dict with
            ``image`` (H, W, 3) float32 linear RGB in [0, 1] (noisy); ``clean`` (H, W, 3) float32 without noise;
            ``phase`` (H, W) float32 2π·lateness in [0, 2π); ``G`` (H, W) float32 growth field;
            ``boundaries`` list of (K, 2) float64 (x, y) pixel polylines where G crosses an integer (sub-pixel,
            Newton-refined on the model, ~1e-9 px); ``boundary_levels`` list of the integer G of each polyline;
            ``model`` the :class:`WoodModel` (float32, ``requires_grad`` parameters);
            ``params`` dict: ``rotation`` (3,) rad, ``translation`` (3,) mm, ``ring_scale`` mm, ``distance_mm``,
            ``tilt_deg``, ``in_plane_deg``, ``distortion_mm``, ``pixel_size_mm``, ``axis_point_px`` (x, y) where
            the projection of the stem axis onto the board crosses the centre row, ``axis_direction_px`` (dx, dy)
            unit direction of that projection (dy >= 0).

    Raises:
        TypeError / ValueError: invalid sizes, pixel size, noise or overrides.
    """
    height = check_int("height", height, lo=2)
    width = check_int("width", width, lo=2)
    pixel_size_mm = check_positive("pixel_size_mm", pixel_size_mm)
    if isinstance(seed, bool) or not isinstance(seed, numbers.Integral):
        raise TypeError(f"seed: expected an integer, got {type(seed).__name__}")
    if isinstance(noise, bool) or not isinstance(noise, numbers.Real) or not math.isfinite(noise) or noise < 0:
        raise ValueError(f"noise: expected a finite real number >= 0, got {noise!r}")
    if (isinstance(color_variation, bool) or not isinstance(color_variation, numbers.Real)
            or not math.isfinite(color_variation) or color_variation < 0):
        raise ValueError(f"color_variation: expected a finite real number >= 0, got {color_variation!r}")
    if not isinstance(pith_inside, bool):
        raise TypeError(f"pith_inside: expected a bool, got {type(pith_inside).__name__}")
    rng = np.random.default_rng(int(seed))

    if ring_scale_mm is None:
        lo, hi = max(1.0, 8 * pixel_size_mm), min(4.0, 40 * pixel_size_mm)
        ring_scale_mm = float(rng.uniform(lo, hi)) if lo < hi else float(rng.uniform(1.0, 4.0))
    s_r = check_positive("ring_scale_mm", ring_scale_mm)
    d_lo, d_hi, t_lo, t_hi = (1.5, 4.0, 12.0, 20.0) if pith_inside else (5.0, 30.0, 4.0, 12.0)
    distance = check_positive("distance_mm", _range("distance_mm", distance_mm, rng, d_lo, d_hi))
    tilt = _range("tilt_deg", tilt_deg, rng, t_lo, t_hi) * (1 if tilt_deg is not None else rng.choice([-1, 1]))
    in_plane = _range("in_plane_deg", in_plane_deg, rng, -10.0, 10.0)
    amp = 0.15 * s_r if distortion_mm is None else _range("distortion_mm", distortion_mm, rng, 0.0, 0.0)
    if amp < 0:
        raise ValueError(f"distortion_mm: expected >= 0, got {amp}")

    # Board → tree: u → x̂ (across rings), v → ẑ (stem), w → −ŷ; then tilt about u and turn about w.
    rot = _rotation(0, math.pi / 2) @ _rotation(0, math.radians(tilt)) @ _rotation(2, math.radians(in_plane))
    centre_b = np.array([(width - 1) / 2 * pixel_size_mm, (height - 1) / 2 * pixel_size_mm, 0.0])
    offset = rng.uniform(-0.2, 0.2) * width * pixel_size_mm   # axis projection left/right of the centre column
    z_centre = rng.uniform(-5.0, 5.0)
    q_centre = np.array([offset, distance, z_centre])            # r(centre) ≈ hypot(offset, distance)
    translation = q_centre - rot @ centre_b

    corners = np.array([[u, v, 0.0] for u in (0.0, (width - 1) * pixel_size_mm)
                        for v in (0.0, (height - 1) * pixel_size_mm)])
    q_corners = corners @ rot.T + translation
    r_max = 1.25 * float(np.hypot(q_corners[:, 0], q_corners[:, 1]).max()) + 2 * s_r
    z_lo, z_hi = float(q_corners[:, 2].min()) - 5.0, float(q_corners[:, 2].max()) + 5.0

    model = WoodModel(ring_scale_mm=s_r, n_rings=n_rings, distortion="radial", distortion_shape=distortion_shape,
                      r_max_mm=r_max, z_range_mm=(z_lo, z_hi), tangential=False, dtype=torch.float32,
                      color_bins=color_bins, pith_taper_mm=s_r if pith_inside else 0.0)
    rotvec = matrix_to_axis_angle(rot)

    # Smooth radial distortion: a few random plane waves over (z, r), rescaled so that ∂m/∂r > −0.5 (no fold-over).
    texels = model.texel_coordinates().double().numpy()
    zz, rr = texels[..., 0], texels[..., 1]
    field = np.zeros_like(zz)
    d_dr = np.zeros_like(zz)
    for _ in range(4):
        kz = rng.uniform(0.5, 2.0) * 2 * math.pi / (z_hi - z_lo) * rng.choice([-1, 1])
        kr = rng.uniform(0.5, 3.0) * 2 * math.pi / r_max
        phi = rng.uniform(0, 2 * math.pi)
        a = rng.uniform(0.5, 1.0)
        field += a * np.sin(kz * zz + kr * rr + phi)
        d_dr += a * kr * np.cos(kz * zz + kr * rr + phi)
    scale = amp / max(np.abs(field).max(), 1e-12)
    if scale * max(-d_dr.min(), 0.0) > 0.5:
        scale = 0.5 / -d_dr.min()
    m_r = field * scale  # with pith_inside the model tapers it to 0 at the pith (G = 0 there, never negative)

    # Per-ring colours: early → late wood with a jittered transition position and colours.
    lat = np.linspace(0.0, 1.0, color_bins)
    trans = rng.uniform(0.55, 0.8, size=(n_rings, 1))
    width_t = rng.uniform(0.04, 0.1, size=(n_rings, 1))
    ramp = 1.0 / (1.0 + np.exp(-(lat[None, :] - trans) / width_t))              # (n_rings, K)
    early = _EARLY * (1 + color_variation * rng.standard_normal((n_rings, 1, 3)))
    late = _LATE * (1 + 1.5 * color_variation * rng.standard_normal((n_rings, 1, 3)))
    cmap = np.clip(early + (late - early) * ramp[..., None], 0.0, 1.0)

    model.set_parameters(rotation=rotvec, translation=translation, m_r=m_r, color_map=cmap)

    with torch.no_grad():
        out = model.render_board(height, width, pixel_size_mm)
    clean = out["image"].numpy().astype(np.float32)
    image = np.clip(clean + noise * rng.standard_normal(clean.shape), 0.0, 1.0).astype(np.float32)
    G = out["G"].numpy().astype(np.float32)

    # Projection of the stem axis onto the board plane, as a pixel-space line through the centre row.
    a_b = rot.T @ np.array([0.0, 0.0, 1.0])
    p_b = rot.T @ (np.array([0.0, 0.0, 0.0]) - translation)
    direction = a_b[:2] / np.linalg.norm(a_b[:2])
    if direction[1] < 0:
        direction = -direction
    t = (centre_b[1] - p_b[1]) / direction[1]
    axis_point = (p_b[:2] + t * direction) / pixel_size_mm

    boundaries, levels = _boundaries(model, out["G"].double().numpy(), pixel_size_mm)
    return {"image": image, "clean": clean, "phase": out["phase"].numpy().astype(np.float32), "G": G,
            "boundaries": boundaries, "boundary_levels": levels, "model": model,
            "params": {"rotation": rotvec, "translation": translation, "ring_scale": s_r, "distance_mm": distance,
                       "tilt_deg": float(tilt), "in_plane_deg": in_plane, "distortion_mm": float(np.abs(m_r).max()),
                       "pixel_size_mm": pixel_size_mm, "axis_point_px": axis_point,
                       "axis_direction_px": direction}}
