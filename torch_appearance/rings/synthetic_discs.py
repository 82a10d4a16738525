"""Synthetic disc photos with known ring boundaries, written independently of :mod:`~torch_appearance.rings.synthetic`
and of :func:`~torch_appearance.rings.disc.synthetic_disc`, so that the disc detector is not judged only by the
generator it was designed with (issue 48).

What differs from those generators, on purpose:

- **Rings as accumulated, angle-dependent widths.** Ring ``k`` has a width ``w_k(phi) = w_k (1 + m_k(phi))`` round
  the disc, ``m_k`` a smooth random modulation (a few low harmonics, drawn per ring, partly shared between rings so
  that a side of the tree grows faster for years), and its outer boundary is ``B_k(phi) = sum_{j <= k} w_j(phi)``
  from the pith. Rings are therefore not scaled copies of one curve (no single eccentricity), wider on one side
  (an off-centre pith) and wavy.
- **Widths shrink geometrically** from ``inner_width_px`` at the pith to ``outer_width_px`` at the bark (10x by
  default), as in a slowing tree; the latewood fraction varies per ring; the latewood *contrast* falls linearly
  from ``contrast_inner`` to ``contrast_outer`` (strong to faint).
- **Ring profile**: earlywood brightens slightly outwards, latewood comes in through a logistic transition of
  random softness; the boundary is the sharp latewood -> earlywood step (1 px ramp at the supersampled scale).
- **Wood texture**: radial fibre streaks (noise smoothed along the radius, not across it) and fine speckle.
- **Conditions** (:data:`CONDITIONS`): blur, JPEG compression, uneven light (a gradient and a vignette), a dark or a
  light bark band, a radial crack from the bark towards the pith (filled with the background), an off-centre pith
  with a one-sided growth.

Ground truth: :meth:`SyntheticDisc.boundaries_along` gives the boundary radii along any ray from the pith (all
``K`` ring boundaries; the last one is the wood's outer edge at the bark).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

__all__ = ["CONDITIONS", "SyntheticDisc", "make_disc", "suite"]

# name -> options of make_disc (on top of the defaults); "base" is the plain disc
CONDITIONS = {
    "base": {},
    "faint_outer": dict(contrast_outer=0.035),
    "blur": dict(blur_px=1.6),
    "jpeg": dict(jpeg_quality=25),
    "uneven_light": dict(light_gradient=0.5, vignette=0.35),
    "dark_bark": dict(bark="dark"),
    "light_bark": dict(bark="light"),
    "crack": dict(crack=True),
    "off_centre": dict(pith_frac=(0.43, 0.45), one_sided=0.3),
}


@dataclass
class SyntheticDisc:
    """A synthetic disc photo and its rings.

    Attributes:
        rgb: ``(H, W, 3)`` float32 in [0, 1].
        pith: ``(2,)`` ``(x, y)`` pixels.
        phis: ``(A,)`` angles (radians, from +x towards +y) at which the boundaries are tabulated.
        radii: ``(K, A)`` boundary ``k``'s distance from the pith at each angle (the last row: the wood's edge;
            with ``pith_px`` the first row the pith's edge).
        info: the options used.
    """

    rgb: np.ndarray
    pith: np.ndarray
    phis: np.ndarray
    radii: np.ndarray
    info: dict = field(default_factory=dict)

    def boundaries_along(self, angle_deg: float) -> np.ndarray:
        """``(K,)`` true boundary radii (px from the pith) along the ray at ``angle_deg`` (from +x towards +y)."""
        phi = math.radians(float(angle_deg)) % (2 * math.pi)
        return np.array([np.interp(phi, self.phis, r, period=2 * math.pi) for r in self.radii])


def _smooth_periodic(rng, A, harmonics, amplitude):
    """A smooth random periodic function on ``A`` angles: ``harmonics`` cosines with amplitudes ~ 1 / n."""
    phi = np.linspace(0, 2 * math.pi, A, endpoint=False)
    out = np.zeros(A)
    for n in range(1, harmonics + 1):
        out += rng.normal(0, amplitude / n) * np.cos(n * phi + rng.uniform(0, 2 * math.pi))
    return out


def make_disc(*, size=(560, 560), n_rings=20, inner_width_px=30.0, outer_width_px=3.0, contrast_inner=0.30,
              contrast_outer=0.10, pith_frac=(0.5, 0.5), one_sided=0.12, wobble=0.08, bark="none",
              bark_px=12.0, blur_px=0.0, jpeg_quality=None, light_gradient=0.0, vignette=0.0, crack=False,
              noise=0.015, background=(0.93, 0.93, 0.92), pith_px=0.0, seed=0, ss=2) -> SyntheticDisc:
    """One synthetic disc photo (module docstring).

    Args:
        size: ``(H, W)``.
        n_rings: number of rings (boundaries), pith -> bark.
        inner_width_px, outer_width_px: mean width of the first and the last ring; the widths in between are
            geometric.
        contrast_inner, contrast_outer: latewood darkening (fraction of the earlywood's value) of the first and
            last ring, linear in between.
        pith_frac: pith position as a fraction of ``(W, H)``.
        one_sided: relative amplitude of the growth modulation shared by all rings (one side grows faster).
        wobble: relative amplitude of each ring's own modulation.
        bark: ``"none"``, ``"dark"`` or ``"light"``: a bark band ``bark_px`` wide outside the last ring.
        blur_px: Gaussian blur sigma of the photo (0: none).
        jpeg_quality: JPEG-compress the photo at this quality (None: not).
        light_gradient: uneven light: brightness falls linearly by this fraction across the photo.
        vignette: brightness falls by this fraction at the photo's corners.
        crack: a radial crack (background colour) from the bark inwards to 35 % of the radius.
        noise: Gaussian pixel noise.
        background: colour around the disc.
        pith_px: a dark pith of about this radius (px; 0: none), as dark as the first ring's latewood and modulated
            round the disc like the rings; its edge (a sharp dark -> light step inside the first ring) is then the
            first boundary (``radii[0]``), and ``info["pith_radii"]`` holds it. At most half the first ring's width.
        seed: random seed.
        ss: supersampling per axis.

    Raises:
        ValueError: an argument out of range (named in the message).
    """
    H, W = (int(v) for v in size)
    if H < 32 or W < 32:
        raise ValueError(f"size: expected (H, W) >= 32, got {size!r}")
    if not (isinstance(n_rings, int) and n_rings >= 2):
        raise ValueError(f"n_rings: expected an integer >= 2, got {n_rings!r}")
    for name, v, lo in (("inner_width_px", inner_width_px, 1.0), ("outer_width_px", outer_width_px, 1.0),
                        ("contrast_inner", contrast_inner, 0.0), ("contrast_outer", contrast_outer, 0.0),
                        ("blur_px", blur_px, 0.0), ("noise", noise, 0.0), ("bark_px", bark_px, 0.0),
                        ("pith_px", pith_px, 0.0)):
        if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= lo):
            raise ValueError(f"{name}: expected a finite number >= {lo:g}, got {v!r}")
    if pith_px > 0.5 * inner_width_px:
        raise ValueError(f"pith_px: expected at most half of inner_width_px ({0.5 * inner_width_px:g}), got {pith_px!r}")
    if bark not in ("none", "dark", "light"):
        raise ValueError(f"bark: expected 'none', 'dark' or 'light', got {bark!r}")
    if jpeg_quality is not None and not (isinstance(jpeg_quality, int) and 1 <= jpeg_quality <= 100):
        raise ValueError(f"jpeg_quality: expected an integer in [1, 100] or None, got {jpeg_quality!r}")
    rng = np.random.default_rng(seed)
    A = 720
    phis = np.linspace(0, 2 * math.pi, A, endpoint=False)
    base_w = np.geomspace(inner_width_px, outer_width_px, n_rings)
    shared = _smooth_periodic(rng, A, 2, one_sided)
    widths = np.stack([w * np.clip(1 + shared + _smooth_periodic(rng, A, 4, wobble), 0.35, None) for w in base_w])
    radii = np.cumsum(widths, axis=0)                                   # (K, A) outer boundary of each ring
    pith = np.array([pith_frac[0] * (W - 1), pith_frac[1] * (H - 1)])
    late_frac = rng.uniform(0.2, 0.45, n_rings)
    softness = rng.uniform(0.04, 0.12, n_rings)
    contrast = np.linspace(contrast_inner, contrast_outer, n_rings)
    # supersampled pixel grid in polar coordinates about the pith
    o = (np.arange(ss) + 0.5) / ss - 0.5
    ys = (np.arange(H)[:, None] + o[None, :]).reshape(-1)
    xs = (np.arange(W)[:, None] + o[None, :]).reshape(-1)
    X, Y = np.meshgrid(xs, ys)
    dx, dy = X - pith[0], Y - pith[1]
    r = np.hypot(dx, dy)
    phi = np.arctan2(dy, dx) % (2 * math.pi)
    a = phi / (2 * math.pi) * A
    a0 = np.floor(a).astype(int) % A
    a1 = (a0 + 1) % A
    t = a - np.floor(a)
    Bp = radii[:, a0] * (1 - t) + radii[:, a1] * t                       # (K, N) boundaries along each pixel's ray
    Bp = Bp.reshape(n_rings, -1)
    rf = r.reshape(-1)
    k = (rf[None, :] >= Bp).sum(0)                                      # ring index of each sample (K: outside)
    inner = np.where(k > 0, Bp[np.maximum(k - 1, 0), np.arange(len(rf))], 0.0)
    outer = Bp[np.minimum(k, n_rings - 1), np.arange(len(rf))]
    f = np.clip((rf - inner) / np.maximum(outer - inner, 1e-6), 0, 1)  # position in the ring, 0 .. 1
    kk = np.minimum(k, n_rings - 1)
    lw = 1.0 / (1.0 + np.exp(-(f - (1 - late_frac[kk])) / softness[kk]))
    value = (0.80 + 0.06 * f) * (1 - contrast[kk] * lw)
    pith_radii = None
    if pith_px > 0:  # a dark pith, its edge modulated round the disc as the first ring is
        pith_radii = pith_px * widths[0] / base_w[0]
        pr = (pith_radii[a0] * (1 - t) + pith_radii[a1] * t).reshape(-1)
        value = np.where(rf < pr, 0.80 * (1 - contrast[0]), value)
    # fibre streaks along the radius and speckle (texture of the wood, not of the rings)
    n_streak = _smooth_periodic(rng, 2048, 200, 0.02)
    value = value * (1 + n_streak[(phi.reshape(-1) / (2 * math.pi) * 2048).astype(int) % 2048])
    value = value * (1 + rng.normal(0, 0.01, value.shape))
    tint = np.array([1.0, 0.78, 0.52])
    rgb = value[:, None] * tint[None, :]
    wood_end = Bp[-1]
    out = rf >= wood_end
    bgc = np.asarray(background, dtype=np.float64)
    if bark != "none":
        in_bark = out & (rf < wood_end + bark_px)
        col = np.array([0.22, 0.14, 0.09]) if bark == "dark" else np.array([0.72, 0.66, 0.58])
        rgb[in_bark] = col * (1 + rng.normal(0, 0.05, (int(in_bark.sum()), 1)))
        out = out & ~in_bark
    rgb[out] = bgc
    if crack:
        th = rng.uniform(0, 2 * math.pi)
        u = np.array([math.cos(th), math.sin(th)])
        along = dx.reshape(-1) * u[0] + dy.reshape(-1) * u[1]
        across = -dx.reshape(-1) * u[1] + dy.reshape(-1) * u[0]
        r_edge = np.interp(th, phis, radii[-1], period=2 * math.pi)
        width = 1.0 + 5.0 * np.clip((along - 0.35 * r_edge) / (0.65 * r_edge), 0, 1)
        rgb[(along > 0.35 * r_edge) & (np.abs(across) < width / 2) & (rf < wood_end)] = bgc * 0.35
    rgb = rgb.reshape(H, ss, W, ss, 3).mean((1, 3))
    if light_gradient or vignette:
        yy, xx = np.mgrid[0:H, 0:W]
        g = 1 - light_gradient * (0.7 * xx / (W - 1) + 0.3 * yy / (H - 1))
        g = g * (1 - vignette * (((xx - W / 2) / (W / 2)) ** 2 + ((yy - H / 2) / (H / 2)) ** 2) / 2)
        rgb = rgb * g[..., None]
    if blur_px > 0:
        rgb = ndimage.gaussian_filter(rgb, (blur_px, blur_px, 0))
    rgb = np.clip(rgb + rng.normal(0, noise, rgb.shape), 0, 1)
    if jpeg_quality is not None:
        import cv2
        u8 = (rgb * 255 + 0.5).astype(np.uint8)[..., ::-1]
        ok, buf = cv2.imencode(".jpg", np.ascontiguousarray(u8), [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality])
        rgb = cv2.imdecode(buf, cv2.IMREAD_COLOR)[..., ::-1].astype(np.float64) / 255.0
    info = dict(n_rings=n_rings, inner_width_px=inner_width_px, outer_width_px=outer_width_px,
                contrast_inner=contrast_inner, contrast_outer=contrast_outer, bark=bark, blur_px=blur_px,
                jpeg_quality=jpeg_quality, light_gradient=light_gradient, vignette=vignette, crack=crack, seed=seed,
                pith_px=pith_px, pith_radii=pith_radii)
    if pith_radii is not None:
        radii = np.concatenate([pith_radii[None], radii], 0)
    return SyntheticDisc(rgb=rgb.astype(np.float32), pith=pith, phis=phis, radii=radii, info=info)


def suite(conditions=None, seed=0, **common):
    """``{name: SyntheticDisc}`` for the named :data:`CONDITIONS` (default: all), ``common`` options on top."""
    names = list(CONDITIONS) if conditions is None else list(conditions)
    unknown = [n for n in names if n not in CONDITIONS]
    if unknown:
        raise ValueError(f"conditions: expected names from {sorted(CONDITIONS)}, got {unknown}")
    return {n: make_disc(seed=seed, **{**CONDITIONS[n], **common}) for n in names}
