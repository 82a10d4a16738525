"""Apparent surface colour ↔ single-scattering albedo of a thick homogeneous medium.

A semi-infinite homogeneous medium of single-scattering albedo α, seen along its normal under uniform white
illumination, shows the surface colour C(α): the fraction of light it returns, specular reflection included. C does
not depend on σ_t (the medium is scale free), only on α, the phase function and the boundary. Inverting C gives the
albedo that makes a volume look like a photographed surface (thesis §1.11: volumetric wood).

Two inverse mappings C → α:

- ``"elek"``: the polynomial of Elek et al. 2017 (thesis eq. 1.38), regressed on their own renderer,
  α(C) = Σ_k c_k·(1 − (1 − (C − C_s)/(1 − C_s))^{d_k}).
- ``"table"`` (default): C(α) measured with *this* tracer (thick slab, smooth dielectric boundary, HG phase) at
  the α values of a stored table (``_albedo_table.py``, written by ``scripts/eval/make_albedo_table.py``), joined by a
  monotone cubic (PCHIP) in s = √(1 − α) (C is close to linear in s near α = 1, diffusion theory) with the exact
  end point C(α = 1) = 1, and inverted on a dense grid. Tables exist for IOR 1.5 and the ``g`` values in :data:`TABLE_G`.

Round trip on our tracer (``scripts/eval/make_albedo_table.py`` prints it; tests/test_wood_volume.py checks it), g = 0.4,
IOR 1.5, ten colours (wood, greys, saturated): the polynomial gives CIEDE2000 mean 1.70, max 2.51 (too dark below
C ≈ 0.5, too bright above: C = 0.8 renders at 0.88); the table mean 0.17, max 0.52. The table is the default.
At g = 0 the polynomial misses by mean 3.9, max 5.9, at g = 0.8 by mean 10.3, max 14.7 (tables: 0.13/0.21 and
0.09/0.18): it holds only near g = 0.4.

Colours below C(0) (the specular reflection alone, 0.04 at IOR 1.5) are out of the gamut of any medium with this
boundary; both mappings return α = 0 for them (the table by definition; the polynomial is clamped at C_s) and
:func:`albedo_from_colour` reports how many entries were affected when asked (``return_gamut=True``).
"""
import functools

import numpy as np
import torch

from ..checks import check_int, check_real, check_seed

__all__ = ["ELEK_C", "ELEK_D", "ELEK_CS", "TABLE_G", "elek_albedo", "albedo_from_colour", "colour_from_albedo",
           "slab_colour"]

#: Elek et al. 2017 coefficients (thesis eq. 1.38).
ELEK_C = (0.163581, 0.391943, 0.029277, 0.316847, 0.098352)
ELEK_D = (3.969542, 15.94272, 46.26871, 59.95706, 206.5716)
ELEK_CS = 0.04526


def _tables():
    from ._albedo_table import TABLES
    return TABLES


#: Henyey–Greenstein g values with a stored table (IOR 1.5).
TABLE_G = tuple(sorted(g for (g, ior) in _tables()))


def _as_float_tensor(name, value):
    if isinstance(value, np.ndarray):
        value = torch.from_numpy(value)
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        value = torch.tensor(float(value), dtype=torch.float64)
    if not isinstance(value, torch.Tensor) or not value.is_floating_point():
        raise TypeError(f"{name}: expected a floating-point tensor or array, got "
                        f"{type(value).__name__ if not isinstance(value, torch.Tensor) else value.dtype}")
    if not bool(torch.isfinite(value).all()):
        raise ValueError(f"{name}: expected finite values, got {int((~torch.isfinite(value)).sum())} NaN/Inf entries")
    return value


def elek_albedo(colour):
    """Elek et al. 2017 (thesis eq. 1.38): single-scattering albedo from apparent surface colour.

    Args:
        colour: tensor (any shape) of linear surface reflectances in [0, 1].

    Returns:
        α of the same shape and dtype, in [0, 1]; colours below C_s = 0.04526 give 0.

    Example:
        >>> round(float(elek_albedo(torch.tensor(0.2))), 4)
        0.8955
    """
    c = _as_float_tensor("colour", colour)
    if bool((c < 0).any()) or bool((c > 1).any()):
        raise ValueError(f"colour: expected values in [0, 1], got range [{float(c.min()):g}, {float(c.max()):g}]")
    x = ((c - ELEK_CS) / (1 - ELEK_CS)).clamp(0.0, 1.0)
    return sum(ck * (1 - (1 - x) ** dk) for ck, dk in zip(ELEK_C, ELEK_D)).clamp(0.0, 1.0)


def _table(g, ior):
    g = check_real("g", g, lo=-1.0, hi=1.0, lo_open=True, hi_open=True)
    ior = check_real("ior", ior, lo=1.0)
    for (tg, tior), table in _tables().items():
        if abs(tg - g) < 1e-9 and abs(tior - ior) < 1e-9:
            return table
    raise ValueError(f"g, ior: expected a tabulated pair, one of {sorted(_tables())} (make more with "
                     f"scripts/eval/make_albedo_table.py), got ({g:g}, {ior:g})")


@functools.lru_cache(maxsize=8)
def _table_arrays(g, ior):
    """(s, C) of the table on a dense grid of s = √(1 − α) ∈ [0, 1], C falling with s: the measured points joined
    by the monotone cubic (PCHIP) in s, end point C(s = 0) = 1; dense enough (20001 points) that linear
    interpolation between them is exact to ~1e-8 in both directions."""
    from scipy.interpolate import PchipInterpolator

    t = _table(g, ior)
    alpha = np.asarray(t["albedo"], dtype=np.float64)
    colour = np.asarray(t["colour"], dtype=np.float64)
    s = np.concatenate([[0.0], np.sqrt(1.0 - alpha)[::-1]])
    colour = np.concatenate([[1.0], colour[::-1]])      # ascending s ↔ descending colour
    s_dense = np.linspace(0.0, 1.0, 20001)
    c_dense = PchipInterpolator(s, colour)(s_dense)
    if not np.all(np.diff(c_dense) < 0):
        raise ValueError(f"g, ior: the table for ({g:g}, {ior:g}) is not strictly monotone; remake it")
    return s_dense, c_dense


def colour_from_albedo(albedo, *, g=0.4, ior=1.5):
    """Apparent surface colour C(α) of a thick homogeneous medium, from the stored table of our tracer.

    Args:
        albedo: tensor (any shape) in [0, 1].
        g, ior: phase function and boundary of the table (see :data:`TABLE_G`).

    Returns:
        C of the same shape and dtype (linear reflectance, specular reflection included).
    """
    a = _as_float_tensor("albedo", albedo)
    if bool((a < 0).any()) or bool((a > 1).any()):
        raise ValueError(f"albedo: expected values in [0, 1], got range [{float(a.min()):g}, {float(a.max()):g}]")
    s_tab, c_tab = _table_arrays(g, ior)
    s = np.sqrt(1.0 - a.detach().cpu().double().numpy())
    return torch.from_numpy(np.asarray(np.interp(s, s_tab, c_tab), dtype=np.float64)).to(a)


def albedo_from_colour(colour, *, mapping="table", g=0.4, ior=1.5, return_gamut=False):
    """Single-scattering albedo whose thick homogeneous medium shows the surface colour ``colour``.

    Args:
        colour: tensor (any shape, e.g. (..., 3) linear RGB) of surface reflectances in [0, 1].
        mapping: ``"table"`` (our tracer, default) or ``"elek"`` (the polynomial of eq. 1.38).
        g, ior: phase function and boundary the table was measured with (``"table"`` only).
        return_gamut: also return the number of entries below the gamut (darker than C(0)), mapped to α = 0.

    Returns:
        α, same shape and dtype as ``colour``, in [0, 1] (and the count with ``return_gamut``).

    Example:
        >>> a = albedo_from_colour(torch.tensor([0.1, 0.3, 0.6]))
        >>> bool((a > 0.5).all() and (a < 1).all() and (a.diff() > 0).all())
        True
    """
    c = _as_float_tensor("colour", colour)
    if bool((c < 0).any()) or bool((c > 1).any()):
        raise ValueError(f"colour: expected values in [0, 1], got range [{float(c.min()):g}, {float(c.max()):g}]")
    if mapping == "elek":
        alpha = elek_albedo(c)
        below = int((c < ELEK_CS).sum())
    elif mapping == "table":
        s_tab, c_tab = _table_arrays(g, ior)
        cn = c.detach().cpu().double().numpy()
        # np.interp needs ascending abscissae: colour falls as s grows
        s = np.interp(cn, c_tab[::-1], s_tab[::-1])
        alpha = torch.from_numpy(np.asarray(1.0 - s * s, dtype=np.float64)).clamp(0.0, 1.0).to(c)
        below = int((cn < c_tab[-1]).sum())
    else:
        raise ValueError(f"mapping: expected 'table' or 'elek', got {mapping!r}")
    return (alpha, below) if return_gamut else alpha


def slab_colour(albedo, *, g=0.4, ior=1.5, spp=100000, seed=0, thickness_mfp=1.0e4, max_depth=1 << 20):
    """Render the apparent colour of a thick homogeneous slab with our tracer (the measurement behind the table).

    The slab is one voxel with σ_t = 1 mm⁻¹ and edges ``thickness_mfp`` mm (that many mean free paths in depth
    and width), smooth dielectric boundary of index ``ior`` (``None``: index matched), HG phase ``g``, uniform white
    environment; its top face texel (radiance leaving along the normal, specular reflection included) is the
    directional reflectance C.

    Args:
        albedo: (3,) or scalar albedo in [0, 1] (three channels are traced at once).
        spp: paths per channel (>= 1). The estimate is a mean of Bernoulli-like path weights: its standard error
            is at most 0.5/√spp.
        seed: tracer seed; a fixed seed makes C(α) monotone in α (common random numbers).

    Returns:
        (3,) float64 tensor C.
    """
    from .volpath import render_texels

    a = _as_float_tensor("albedo", albedo).double().flatten()
    if a.numel() == 1:
        a = a.expand(3)
    if a.numel() != 3:
        raise ValueError(f"albedo: expected a scalar or 3 values, got {a.numel()}")
    spp = check_int("spp", spp, lo=1)
    thickness = check_real("thickness_mfp", thickness_mfp, lo=0.0, lo_open=True)
    check_seed("seed", seed)
    sigma = torch.ones(3, 1, 1, 1, dtype=torch.float64)
    out = render_texels(sigma, a.reshape(3, 1, 1, 1).clone(), voxel_size=thickness, g=g, ior=ior, spp=spp,
                        seed=seed, max_depth=max_depth)
    return out.reshape(3)

