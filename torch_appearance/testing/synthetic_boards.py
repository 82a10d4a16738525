"""A second generator of wood boards with known growth phase, written apart from :mod:`torch_appearance.rings.synthetic`
so that the wood fit is not judged only by the generator it was designed with (issue 48).

:func:`torch_appearance.rings.synthetic_board` renders a :class:`~torch_appearance.nn.WoodModel`: equal ring widths
distorted by a smooth (z, r) texture, one sigmoid colour ramp per ring. This module shares nothing with it: numpy
only, the stem axis given as a line in the board's own frame, and a growth field built from

* rings of unequal width (juvenile wide rings near the pith, lognormal year-to-year variation), the ring count G
  interpolated between the cumulative ring radii, so G is an integer at every ring boundary;
* lobes: the innermost rings bulge into ``lobe_order`` lobes, r_w = r / (1 + A·e^(−r/ρ)·cos(mθ + φ)), the
  bulge decaying outwards over ``lobe_decay_rings`` ring widths;
* waves: ring surfaces displaced along the stem and round it, Σ a·sin(2π z/λ + nθ + φ), faded at the pith;
* knots: branches leaving the pith; the rings bulge round each, and where the board cuts the branch it shows
  the branch's own dark rings (those pixels have no stem phase and are marked invalid);
* ring profiles other than a sigmoid: ``"abrupt"`` (a sharp earlywood → latewood step), ``"gradual"`` (ℓ^p),
  ``"porous"`` (a dark pore band at the start of each ring) with per-ring latewood fractions, fibre streaks along
  the stem, uneven light, blur and noise.

The true phase is 2π·frac(G) (G = 0 at the pith, integers at the latewood → earlywood boundaries), as the model's.

Example:
    >>> from torch_appearance.testing.synthetic_boards import independent_board
    >>> b = independent_board("lobed_pith", 64, 64, seed=1)
    >>> b["image"].shape, b["phase"].shape, bool(b["valid"].all())
    ((64, 64, 3), (64, 64), True)
"""
from __future__ import annotations

import dataclasses
import math
import numbers

import numpy as np

from ..checks import check_int, check_positive

__all__ = ["BoardRecipe", "RECIPES", "independent_board", "phase_scores"]

_PROFILES = ("abrupt", "gradual", "porous")
_PALETTES = {  # (earlywood, latewood) linear RGB
    "pine": ((0.70, 0.52, 0.30), (0.36, 0.20, 0.08)),
    "oak": ((0.55, 0.40, 0.24), (0.30, 0.19, 0.10)),
    "pale": ((0.78, 0.66, 0.48), (0.52, 0.38, 0.22)),
}


@dataclasses.dataclass(frozen=True)
class BoardRecipe:
    """What one kind of independent board varies (lengths in mm, angles in degrees).

    Attributes:
        ring_width_mm: mean ring width.
        juvenile: extra relative width of the first rings (width × (1 + juvenile·e^(−k/3))).
        width_jitter: lognormal σ of the year-to-year ring width.
        distance_mm: distance of the stem axis below the board at the image centre (0: the pith in the surface).
        tilt_deg: inclination of the axis out of the board plane (the axis pierces the board where the distance
            reaches 0).
        in_plane_deg: angle of the projected axis from the image rows' direction (down the image).
        offset_frac: offset of the projected axis from the centre column, as a fraction of the width.
        lobe_order: number of lobes m of the innermost rings (0: none). lobe_amplitude: A (< 0.8).
        lobe_decay_rings: ρ in ring widths.
        wave_mm: amplitude of the ring waves (0: none). wave_length_mm: their wavelength along the stem.
        knots: number of knots.
        profile: one of ``"abrupt"``, ``"gradual"``, ``"porous"``. latewood: (low, high) latewood fraction per ring.
        palette: ``"pine"``, ``"oak"`` or ``"pale"``.
    """

    ring_width_mm: float = 2.5
    juvenile: float = 0.4
    width_jitter: float = 0.15
    distance_mm: float = 8.0
    tilt_deg: float = 6.0
    in_plane_deg: float = 4.0
    offset_frac: float = 0.1
    lobe_order: int = 0
    lobe_amplitude: float = 0.0
    lobe_decay_rings: float = 1.5
    wave_mm: float = 0.0
    wave_length_mm: float = 12.0
    knots: int = 0
    profile: str = "abrupt"
    latewood: tuple = (0.2, 0.35)
    palette: str = "pine"


RECIPES = {
    # the issue-48 cases: wavy rings with the pith along the board's middle, and a pith whose innermost rings bulge
    "wavy_pith_middle": BoardRecipe(ring_width_mm=2.5, distance_mm=0.6, tilt_deg=2.0, in_plane_deg=3.0,
                                    offset_frac=0.0, wave_mm=0.5, wave_length_mm=14.0, profile="abrupt",
                                    latewood=(0.25, 0.4), palette="pine"),
    "lobed_pith": BoardRecipe(ring_width_mm=2.5, juvenile=0.3, distance_mm=2.5, tilt_deg=14.0, in_plane_deg=-5.0,
                              offset_frac=0.0, lobe_order=4, lobe_amplitude=0.45, lobe_decay_rings=1.5,
                              profile="gradual", latewood=(0.3, 0.45), palette="oak"),
    # other profiles and proportions, pith outside the board
    "porous_flat": BoardRecipe(ring_width_mm=3.0, juvenile=0.0, width_jitter=0.25, distance_mm=14.0, tilt_deg=8.0,
                               in_plane_deg=-6.0, offset_frac=0.15, wave_mm=0.3, wave_length_mm=20.0,
                               profile="porous", latewood=(0.15, 0.3), palette="pale"),
    "knotty": BoardRecipe(ring_width_mm=2.5, distance_mm=6.0, tilt_deg=9.0, in_plane_deg=5.0, offset_frac=-0.1,
                          wave_mm=0.2, knots=1, profile="abrupt", latewood=(0.2, 0.35), palette="pine"),
}


def _check_recipe(recipe):
    if isinstance(recipe, str):
        if recipe not in RECIPES:
            raise ValueError(f"recipe: expected a BoardRecipe or one of {sorted(RECIPES)}, got {recipe!r}")
        return RECIPES[recipe]
    if not isinstance(recipe, BoardRecipe):
        raise TypeError(f"recipe: expected a BoardRecipe or a name, got {type(recipe).__name__}")
    for name in ("ring_width_mm", "wave_length_mm", "lobe_decay_rings"):
        check_positive(f"recipe.{name}", getattr(recipe, name))
    for name in ("juvenile", "width_jitter", "distance_mm", "wave_mm", "lobe_amplitude"):
        v = getattr(recipe, name)
        if isinstance(v, bool) or not isinstance(v, numbers.Real) or not math.isfinite(v) or v < 0:
            raise ValueError(f"recipe.{name}: expected a finite number >= 0, got {v!r}")
    if recipe.lobe_amplitude >= 0.8:
        raise ValueError(f"recipe.lobe_amplitude: expected < 0.8 (rings must not fold), got {recipe.lobe_amplitude}")
    if recipe.wave_mm > 0.4 * recipe.ring_width_mm * 2:
        raise ValueError(f"recipe.wave_mm: expected <= 0.8 ring widths ({0.8 * recipe.ring_width_mm:g} mm), got "
                         f"{recipe.wave_mm}")
    check_int("recipe.lobe_order", recipe.lobe_order, lo=0)
    check_int("recipe.knots", recipe.knots, lo=0)
    if recipe.profile not in _PROFILES:
        raise ValueError(f"recipe.profile: expected one of {_PROFILES}, got {recipe.profile!r}")
    if recipe.palette not in _PALETTES:
        raise ValueError(f"recipe.palette: expected one of {sorted(_PALETTES)}, got {recipe.palette!r}")
    lo, hi = recipe.latewood
    if not 0.02 <= lo <= hi <= 0.8:
        raise ValueError(f"recipe.latewood: expected 0.02 <= low <= high <= 0.8, got {recipe.latewood!r}")
    return recipe


def _stem_frame(recipe, height, width, ps, rng):
    """Pith point A (mm, board frame: u right, v down, w into the board) at the centre row, stem direction D and
    the two cross-section axes e1 (towards the board face), e2 = D × e1."""
    alpha = math.radians(recipe.in_plane_deg)
    beta = math.radians(recipe.tilt_deg) * (1 if rng.uniform() < 0.5 else -1)
    d = np.array([math.sin(alpha) * math.cos(beta), math.cos(alpha) * math.cos(beta), math.sin(beta)])
    centre = np.array([(width - 1) / 2 * ps + recipe.offset_frac * width * ps, (height - 1) / 2 * ps,
                       recipe.distance_mm])
    up = np.array([0.0, 0.0, -1.0])           # from the pith towards the face (w decreases)
    e1 = up - (up @ d) * d
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(d, e1)
    return centre, d, e1, e2


def _cylinder(points, a, d, e1, e2):
    """(z, r, θ) of points (N, 3) about the line through a with direction d."""
    rel = points - a
    z = rel @ d
    x, y = rel @ e1, rel @ e2
    return z, np.hypot(x, y), np.arctan2(y, x)


def _ring_radii(recipe, n, rng):
    """Cumulative radii C_0 = 0 < C_1 < … (mm) of n rings."""
    k = np.arange(n)
    w = recipe.ring_width_mm * (1 + recipe.juvenile * np.exp(-k / 3.0)) * np.exp(
        recipe.width_jitter * rng.standard_normal(n) - 0.5 * recipe.width_jitter ** 2)
    w = np.maximum(w, 0.25 * recipe.ring_width_mm)
    return np.concatenate([[0.0], np.cumsum(w)])


def _profile(recipe, lateness, ring, late_frac, power):
    """Latewood share L ∈ [0, 1] of a pixel at lateness ℓ of its ring."""
    f = late_frac[ring]
    if recipe.profile == "abrupt":
        edge = 1.0 - f
        return 1.0 / (1.0 + np.exp(-(lateness - edge) / 0.025))
    if recipe.profile == "gradual":
        return np.clip(lateness, 0, 1) ** power[ring] * (0.35 + 0.65 * (f / 0.45))
    # porous: a dark pore band at the ring's start, light earlywood, then the latewood
    pores = 0.55 * np.exp(-0.5 * (lateness / 0.035) ** 2)
    late = 1.0 / (1.0 + np.exp(-(lateness - (1.0 - f)) / 0.05))
    return np.maximum(pores, late)


def independent_board(recipe="lobed_pith", height=256, width=256, pixel_size_mm=0.1, seed=0, noise=0.02) -> dict:
    """Render one board of an independent recipe with its true growth phase.

    Args:
        recipe: a :class:`BoardRecipe` or one of :data:`RECIPES` (``"wavy_pith_middle"``, ``"lobed_pith"``,
            ``"porous_flat"``, ``"knotty"``).
        height, width: image size (px, >= 16).
        pixel_size_mm: pixel pitch (mm, > 0); pixel (row y, column x) is the board point (x, y)·pixel_size_mm.
        seed: integer seed of the random draws (ring widths, colours, lobe and wave phases, knot places, noise).
        noise: standard deviation of the additive pixel noise (linear RGB, >= 0).

    Returns:
        dict: ``image`` (H, W, 3) float32 linear RGB in [0, 1]; ``clean`` without noise and blur;
        ``G`` (H, W) float64 true ring count (integers at ring boundaries, 0 at the pith); ``phase`` (H, W)
        float64 2π·frac(G); ``valid`` (H, W) bool (False on knots, where the stem has no phase);
        ``recipe`` the :class:`BoardRecipe`; ``params`` dict (``pith_point_mm``, ``stem_direction``,
        ``ring_radii_mm``, ``knots``, ``pixel_size_mm``).

    Raises:
        TypeError, ValueError: a bad recipe, size, pixel size, seed or noise (the message names the argument).
    """
    recipe = _check_recipe(recipe)
    height = check_int("height", height, lo=16)
    width = check_int("width", width, lo=16)
    ps = check_positive("pixel_size_mm", pixel_size_mm)
    if isinstance(seed, bool) or not isinstance(seed, numbers.Integral) or seed < 0:
        raise ValueError(f"seed: expected an integer >= 0, got {seed!r}")
    if isinstance(noise, bool) or not isinstance(noise, numbers.Real) or not math.isfinite(noise) or noise < 0:
        raise ValueError(f"noise: expected a finite number >= 0, got {noise!r}")
    rng = np.random.default_rng([int(seed), 4848])

    a, d, e1, e2 = _stem_frame(recipe, height, width, ps, rng)
    yy, xx = np.mgrid[0:height, 0:width].astype(np.float64)
    pts = np.stack([xx.ravel() * ps, yy.ravel() * ps, np.zeros(xx.size)], 1)
    z, r, theta = _cylinder(pts, a, d, e1, e2)
    s = recipe.ring_width_mm

    # warped radius: lobes (multiplicative, decaying outwards), waves (faded at the pith), knots (bulges)
    rw = r.copy()
    if recipe.lobe_order > 0 and recipe.lobe_amplitude > 0:
        rho = recipe.lobe_decay_rings * s
        phi = rng.uniform(0, 2 * math.pi)
        twist = rng.uniform(-1, 1) * 2 * math.pi / 200.0          # lobes turn slowly along the stem (rad/mm)
        lobe = recipe.lobe_amplitude * np.exp(-r / rho) * np.cos(recipe.lobe_order * theta + phi + twist * z)
        # a second, weaker harmonic so the lobes are not all alike
        lobe += 0.3 * recipe.lobe_amplitude * np.exp(-r / rho) * np.cos(
            (recipe.lobe_order + 1) * theta + rng.uniform(0, 2 * math.pi))
        rw = rw / (1.0 + lobe)
    if recipe.wave_mm > 0:
        wave = np.zeros_like(r)
        for n_theta, share in ((0, 0.5), (1, 0.3), (2, 0.2)):
            lam = recipe.wave_length_mm * rng.uniform(0.7, 1.4)
            wave += share * np.sin(2 * math.pi * z / lam + n_theta * theta + rng.uniform(0, 2 * math.pi))
        fade = 1.0 - np.exp(-(r / (2.0 * s)) ** 2)
        rw = rw - recipe.wave_mm * wave * fade
    knots = []
    valid = np.ones(r.shape, bool)
    knot_dark = np.zeros(r.shape)
    for _ in range(recipe.knots):
        # a branch leaving the pith at height zk towards the face side (θ near 0), rising 30-50° along the stem
        zk = rng.uniform(-0.25, 0.25) * height * ps
        tk = rng.uniform(-0.5, 0.5)
        rise = math.radians(rng.uniform(30, 50))
        radius = rng.uniform(1.2, 2.0) * s / 2
        bdir = math.cos(rise) * (math.cos(tk) * e1 + math.sin(tk) * e2) + math.sin(rise) * d
        # distance of each pixel from the branch axis (a ray from the pith point at zk)
        origin = a + zk * d
        rel = pts - origin
        along = np.maximum(rel @ bdir, 0.0)
        dist = np.linalg.norm(rel - along[:, None] * bdir, axis=1)
        bump = 0.8 * s * np.exp(-0.5 * (dist / (2.5 * radius)) ** 2) * (1 - np.exp(-(r / s) ** 2))
        rw = rw - bump
        inside = dist < radius
        valid &= dist > 1.3 * radius
        knot_dark = np.maximum(knot_dark, np.where(inside, 0.6 + 0.4 * np.cos(2 * math.pi * dist / (0.3 * s)), 0.0))
        knots.append({"height_mm": float(zk), "angle_rad": float(tk), "radius_mm": float(radius)})
    rw = np.maximum(rw, 0.0)

    radii = _ring_radii(recipe, int(rw.max() / (0.25 * s)) + 4, rng)
    G = np.interp(rw, radii, np.arange(len(radii), dtype=np.float64))
    ring = np.floor(G).astype(np.int64)
    lateness = G - ring
    n = len(radii)
    late_frac = rng.uniform(*recipe.latewood, size=n)
    power = rng.uniform(2.0, 4.0, size=n)
    L = _profile(recipe, lateness, ring, late_frac, power)
    early, late = (np.asarray(c) for c in _PALETTES[recipe.palette])
    jitter = 1 + 0.06 * rng.standard_normal((n, 3))
    rgb = (early[None] * (1 - L[:, None]) + late[None] * L[:, None]) * jitter[ring]

    # fibre streaks along the projected stem, uneven light, knots
    from scipy import ndimage

    streak = ndimage.gaussian_filter(rng.standard_normal((height, width)), (6.0, 0.7))
    streak = (streak / max(streak.std(), 1e-12)).ravel()
    rgb = rgb * (1 + 0.03 * streak[:, None])
    light = 1 + 0.08 * ((xx.ravel() / width - 0.5) * rng.uniform(-1, 1) + (yy.ravel() / height - 0.5)
                        * rng.uniform(-1, 1))
    rgb = rgb * light[:, None]
    rgb = rgb * (1 - 0.7 * knot_dark[:, None])
    clean = np.clip(rgb.reshape(height, width, 3), 0, 1)
    image = ndimage.gaussian_filter(clean, (0.6, 0.6, 0))
    image = np.clip(image + noise * rng.standard_normal(image.shape), 0, 1)
    G = G.reshape(height, width)
    return {"image": image.astype(np.float32), "clean": clean.astype(np.float32), "G": G,
            "phase": 2 * math.pi * (G - np.floor(G)), "valid": valid.reshape(height, width), "recipe": recipe,
            "params": {"pith_point_mm": a, "stem_direction": d, "ring_radii_mm": radii, "knots": knots,
                       "pixel_size_mm": ps}}


def phase_scores(fit_phase, G_true, valid=None, *, boundary_band=0.05, inner_rings=2.0):
    """How well a fitted phase follows the true growth phase 2π·frac(G).

    The fitted phase may differ from the truth by a constant (the Gabor phase follows the rings' fundamental, not
    the boundary), so the difference d = wrap(fit − true) is scored after removing its circular mean.

    Args:
        fit_phase: ``(H, W)`` fitted phase (rad). G_true: ``(H, W)`` true ring count.
        valid: optional ``(H, W)`` bool mask of the pixels scored (default all).
        boundary_band: half width (rings) of the band round each true ring boundary (integer G) whose pixels give
            the boundary figure.
        inner_rings: the pixels with true G below this give ``phase_rms_inner``.

    Returns:
        dict: ``phase_rms`` (rad), ``offset`` (rad), ``fraction_above_1rad``, ``boundary_circular_std`` (rad:
        sqrt(−2 ln R) of d over the boundary band, the spread of the boundaries' misplacement across the
        board), ``boundary_pixels``, ``phase_rms_inner`` (None when no pixel has G < inner_rings).

    Raises:
        ValueError: shapes differ, non-finite values, or no valid pixel.
    """
    fit = np.asarray(fit_phase, np.float64)
    g = np.asarray(G_true, np.float64)
    if fit.ndim != 2 or fit.shape != g.shape:
        raise ValueError(f"fit_phase: expected the shape of G_true {g.shape}, got {fit.shape}")
    if not (np.isfinite(fit).all() and np.isfinite(g).all()):
        raise ValueError("fit_phase, G_true: expected finite values")
    v = np.ones(g.shape, bool) if valid is None else np.asarray(valid, bool)
    if v.shape != g.shape:
        raise ValueError(f"valid: expected shape {g.shape}, got {v.shape}")
    if not v.any():
        raise ValueError("valid: no pixel to score")
    d = np.angle(np.exp(1j * (fit - 2 * math.pi * (g - np.floor(g)))))[v]
    offset = float(np.angle(np.exp(1j * d).mean()))
    e = np.angle(np.exp(1j * (d - offset)))
    gv = g[v]
    band = np.abs(gv - np.rint(gv)) < boundary_band
    band &= np.rint(gv) >= 1
    if band.any():
        R = float(np.abs(np.exp(1j * d[band]).mean()))
        bstd = float(math.sqrt(max(-2.0 * math.log(max(R, 1e-300)), 0.0)))
    else:
        bstd = None
    inner = gv < inner_rings
    return {"phase_rms": float(np.sqrt((e ** 2).mean())), "offset": offset,
            "fraction_above_1rad": float((np.abs(e) > 1.0).mean()), "boundary_circular_std": bstd,
            "boundary_pixels": int(band.sum()),
            "phase_rms_inner": float(np.sqrt((e[inner] ** 2).mean())) if inner.any() else None}
