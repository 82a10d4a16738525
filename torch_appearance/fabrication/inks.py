"""Printing inks: optical properties per ink, the built-in ink library and ordered ink sets.

An ink is a homogeneous scattering medium described by its extinction coefficient μ_t (``sigma_t``, mm⁻¹, per
linear RGB channel), its single-scattering albedo α (per channel) and a Henyey–Greenstein mean cosine ``g``.
Scattering and absorption coefficients follow as σ_s = α μ_t and σ_a = (1 − α) μ_t; mixtures of inks mix these
linearly (:func:`torch_appearance.nn.mix_inks`, eq. 9 of Nindel et al. 2021).

The built-in table :data:`INKS` holds the Stratasys Vero opaque family measured by Elek et al. (2017) (cyan,
magenta, yellow, black, white) and the hypothetical inks of Nindel et al. (2021), Table 2; all with g = 0.4.

Example:
    >>> from torch_appearance.fabrication import InkSet
    >>> inks = InkSet.from_names(["Cyan", "magenta", "yellow", "black", "white"])
    >>> inks.names
    ('cyan', 'magenta', 'yellow', 'black', 'white')
    >>> inks.sigma_s().shape        # (N, 3), mm⁻¹
    torch.Size([5, 3])
"""
from collections.abc import Sequence
from dataclasses import dataclass
import json
import math
import numbers
import os
from typing import Optional, Tuple

import numpy as np
import torch

from .. import io as _io

__all__ = ["Ink", "InkSet", "INKS", "DEFAULT_INKS", "ink_from_dict"]

_INK_FIELDS = ("name", "sigma_t", "albedo", "g", "display_rgb")


def _triple(name, value, *, lo, hi=math.inf):
    """``value`` as a tuple of three finite floats in [lo, hi]; TypeError/ValueError naming ``name``."""
    if isinstance(value, torch.Tensor):
        value = value.detach().cpu().tolist()
    elif isinstance(value, np.ndarray):
        value = value.tolist()
    if isinstance(value, (str, bytes)) or not isinstance(value, Sequence):
        raise TypeError(f"{name}: expected a sequence of 3 real numbers, got {type(value).__name__}")
    if len(value) != 3:
        raise ValueError(f"{name}: expected 3 values (R, G, B), got {len(value)}: {list(value)!r}")
    out = []
    for v in value:
        if isinstance(v, bool) or not isinstance(v, numbers.Real):
            raise TypeError(f"{name}: expected real numbers, got an element of type {type(v).__name__}")
        out.append(float(v))
    if not all(math.isfinite(v) and lo <= v <= hi for v in out):
        hi_s = "inf)" if hi == math.inf else f"{hi:g}]"
        raise ValueError(f"{name}: expected finite values in [{lo:g}, {hi_s}, got {out!r}")
    return tuple(out)


def _default_display_rgb(albedo, g):
    """sRGB colour of a thick layer of the ink (van de Hulst's semi-infinite diffuse reflectance), in [0, 1]."""
    rgb = []
    for a in albedo:
        s = math.sqrt((1.0 - a) / (1.0 - g * a))
        r = (1.0 - s) * (1.0 - 0.139 * s) / (1.0 + 1.17 * s)
        r = min(max(r, 0.0), 1.0)
        rgb.append(12.92 * r if r <= 0.0031308 else 1.055 * r ** (1.0 / 2.4) - 0.055)
    return tuple(min(max(v, 0.0), 1.0) for v in rgb)


@dataclass(frozen=True)
class Ink:
    """One printing material, homogeneous, with linear-RGB optical properties.

    Args:
        name: non-empty name (matched case-insensitively by :class:`InkSet`).
        sigma_t: extinction coefficient μ_t per channel (R, G, B) in mm⁻¹, finite, >= 0.
        albedo: single-scattering albedo α per channel, in [0, 1].
        g: Henyey–Greenstein mean cosine in (−1, 1) (0.4 for all built-in inks).
        display_rgb: sRGB colour in [0, 1] used for palettes and slice images. ``None`` derives one from the
            albedo (the approximate colour of a thick layer, van de Hulst's semi-infinite reflectance).

    Raises:
        TypeError, ValueError: naming the field, what was expected and what was received.

    Example:
        >>> Ink("grey", sigma_t=(5.0, 5.0, 5.0), albedo=(0.6, 0.6, 0.6)).sigma_s
        (3.0, 3.0, 3.0)
    """
    name: str
    sigma_t: Tuple[float, float, float]
    albedo: Tuple[float, float, float]
    g: float = 0.4
    display_rgb: Optional[Tuple[float, float, float]] = None

    def __post_init__(self):
        if not isinstance(self.name, str):
            raise TypeError(f"name: expected a str, got {type(self.name).__name__}")
        if not self.name.strip():
            raise ValueError(f"name: expected a non-empty string, got {self.name!r}")
        where = f"ink {self.name!r}: "
        object.__setattr__(self, "sigma_t", _triple(where + "sigma_t (mm⁻¹)", self.sigma_t, lo=0.0))
        object.__setattr__(self, "albedo", _triple(where + "albedo", self.albedo, lo=0.0, hi=1.0))
        g = self.g
        if isinstance(g, bool) or not isinstance(g, numbers.Real):
            raise TypeError(f"{where}g: expected a real number, got {type(g).__name__}")
        if not (math.isfinite(g) and -1.0 < g < 1.0):
            raise ValueError(f"{where}g: expected a finite value in (-1, 1), got {g!r}")
        object.__setattr__(self, "g", float(g))
        if self.display_rgb is None:
            object.__setattr__(self, "display_rgb", _default_display_rgb(self.albedo, self.g))
        else:
            object.__setattr__(self, "display_rgb",
                               _triple(where + "display_rgb (sRGB)", self.display_rgb, lo=0.0, hi=1.0))

    @property
    def sigma_s(self):
        """Scattering coefficient σ_s = α μ_t per channel, mm⁻¹."""
        return tuple(a * m for a, m in zip(self.albedo, self.sigma_t))

    @property
    def sigma_a(self):
        """Absorption coefficient σ_a = (1 − α) μ_t per channel, mm⁻¹."""
        return tuple((1.0 - a) * m for a, m in zip(self.albedo, self.sigma_t))

    def to_dict(self):
        """JSON-ready dict ``{name, sigma_t, albedo, g, display_rgb}`` (the format :meth:`InkSet.load_json` reads)."""
        return {"name": self.name, "sigma_t": list(self.sigma_t), "albedo": list(self.albedo), "g": self.g,
                "display_rgb": list(self.display_rgb)}


def ink_from_dict(entry, where="ink"):
    """Build an :class:`Ink` from ``{name, sigma_t, albedo, g?, display_rgb?}``; unknown or missing keys raise.

    Args:
        entry: the dict (e.g. one element of an ink JSON file).
        where: prefix of error messages (e.g. ``"inks.json[2]"``).
    """
    if not isinstance(entry, dict):
        raise TypeError(f"{where}: expected an object {{name, sigma_t, albedo, g?, display_rgb?}}, "
                        f"got {type(entry).__name__}")
    unknown = sorted(set(entry) - set(_INK_FIELDS))
    if unknown:
        raise ValueError(f"{where}: unknown key(s) {unknown}; allowed keys are {list(_INK_FIELDS)}")
    missing = [k for k in ("name", "sigma_t", "albedo") if k not in entry]
    if missing:
        raise ValueError(f"{where}: missing key(s) {missing}; an ink needs name, sigma_t and albedo")
    try:
        return Ink(**entry)
    except (TypeError, ValueError) as error:
        raise type(error)(f"{where}: {error}") from None


def _rgb8(r, g, b):
    return (r / 255.0, g / 255.0, b / 255.0)


#: Built-in inks by lower-case name: Vero opaque (Elek et al. 2017) and the hypothetical inks of Nindel et al.
#: (2021), Table 2. μ_t in mm⁻¹, linear RGB; HG g = 0.4. ``display_rgb`` are distinct, saturated palette colours.
INKS = {
    ink.name: ink
    for ink in (
        Ink("cyan", (9.0, 4.5, 7.5), (0.05, 0.7, 0.98), 0.4, _rgb8(0, 255, 255)),
        Ink("cyan2", (6.0, 3.0, 5.0), (0.05, 0.95, 0.98), 0.4, _rgb8(0, 128, 255)),
        Ink("magenta", (2.5, 3.0, 10.0), (0.98, 0.1, 0.9), 0.4, _rgb8(255, 0, 255)),
        Ink("magenta2", (1.7, 2.0, 6.7), (0.98, 0.05, 0.97), 0.4, _rgb8(255, 0, 128)),
        Ink("yellow", (2.25, 3.75, 19.0), (0.997, 0.995, 0.15), 0.4, _rgb8(255, 255, 0)),
        Ink("yellow2", (3.0, 5.0, 19.0), (0.92, 0.92, 0.15), 0.4, _rgb8(192, 192, 0)),
        Ink("orange", (3.0, 4.0, 15.0), (0.98, 0.32, 0.114), 0.4, _rgb8(255, 128, 0)),
        Ink("black", (5.0, 5.5, 6.5), (0.35, 0.35, 0.35), 0.4, _rgb8(0, 0, 0)),
        Ink("white", (6.0, 9.0, 24.0), (0.9991, 0.9997, 0.999), 0.4, _rgb8(255, 255, 255)),
        Ink("transparent", (1e-4, 1e-4, 1e-4), (1.0, 1.0, 1.0), 0.4, _rgb8(128, 128, 128)),
    )
}

#: The measured Vero CMYKW set, the default ink set of print optimisation.
DEFAULT_INKS = ("cyan", "magenta", "yellow", "black", "white")


class InkSet(Sequence):
    """An ordered, immutable set of inks with unique (case-insensitive) names; ink ``n`` is material index ``n``.

    Args:
        inks: a non-empty sequence of :class:`Ink` (at most 256, so that material indices fit ``uint8``).

    Raises:
        TypeError: an element is not an :class:`Ink`.
        ValueError: empty, more than 256 inks, or duplicate names.

    Example:
        >>> inks = InkSet.from_names("cyan,magenta,yellow,black,white")
        >>> inks.index("WHITE"), len(inks)
        (4, 5)
    """

    def __init__(self, inks):
        if isinstance(inks, (str, bytes, Ink)) or not isinstance(inks, (Sequence, InkSet)):
            raise TypeError(f"inks: expected a sequence of Ink, got {type(inks).__name__}")
        inks = tuple(inks)
        for i, ink in enumerate(inks):
            if not isinstance(ink, Ink):
                raise TypeError(f"inks[{i}]: expected an Ink, got {type(ink).__name__} "
                                f"(use InkSet.from_names for names)")
        if not 1 <= len(inks) <= 256:
            raise ValueError(f"inks: expected 1 to 256 inks (uint8 material indices), got {len(inks)}")
        keys = [ink.name.lower() for ink in inks]
        duplicates = sorted({k for k in keys if keys.count(k) > 1})
        if duplicates:
            raise ValueError(f"inks: ink names must be unique (case-insensitive), got duplicates {duplicates}")
        self._inks = inks
        self._lookup = {k: i for i, k in enumerate(keys)}

    # ------------------------------------------------------------------------------------------------------------
    # construction and files
    # ------------------------------------------------------------------------------------------------------------
    @classmethod
    def from_names(cls, names=DEFAULT_INKS):
        """The built-in inks ``names`` (case-insensitive), in that order.

        Args:
            names: a sequence of names, or one string of comma-separated names (``"cyan,magenta,white"``).

        Raises:
            ValueError: an unknown name (the message lists the known ones), duplicates, or no names.
        """
        if isinstance(names, str):
            names = [n.strip() for n in names.split(",")]
        if not isinstance(names, Sequence):
            raise TypeError(f"names: expected a sequence of ink names or a comma-separated str, "
                            f"got {type(names).__name__}")
        inks = []
        for i, name in enumerate(names):
            if not isinstance(name, str):
                raise TypeError(f"names[{i}]: expected a str, got {type(name).__name__}")
            key = name.strip().lower()
            if key not in INKS:
                raise ValueError(f"names[{i}]: unknown ink {name!r}; known inks are {sorted(INKS)}")
            inks.append(INKS[key])
        return cls(inks)

    @classmethod
    def load_json(cls, path):
        """Read inks from JSON: a list of ``{name, sigma_t, albedo, g?, display_rgb?}`` (or ``{"inks": [...]}``).

        ``sigma_t`` in mm⁻¹ (3 values >= 0), ``albedo`` (3 values in [0, 1]), ``g`` default 0.4, ``display_rgb``
        sRGB in [0, 1] (derived from the albedo when absent).

        Raises:
            FileNotFoundError: ``path`` does not exist.
            ValueError: not valid JSON, not a list of ink objects, an invalid ink (the message names the entry
                and the field), unknown keys or duplicate names.
        """
        if not isinstance(path, (str, os.PathLike)):
            raise TypeError(f"path: expected a str or os.PathLike, got {type(path).__name__}")
        path = os.fspath(path)
        with open(path, "r", encoding="utf-8") as handle:
            try:
                data = json.load(handle)
            except json.JSONDecodeError as error:
                raise ValueError(f"path {path!r}: not valid JSON: {error}") from None
        if isinstance(data, dict) and set(data) == {"inks"}:
            data = data["inks"]
        if not isinstance(data, list):
            raise ValueError(f"path {path!r}: expected a JSON list of inks "
                             f"[{{name, sigma_t, albedo, g?, display_rgb?}}, ...], got {type(data).__name__}")
        inks = [ink_from_dict(entry, where=f"{os.path.basename(path)}[{i}]") for i, entry in enumerate(data)]
        try:
            return cls(inks)
        except ValueError as error:
            raise ValueError(f"path {path!r}: {error}") from None

    def save_json(self, path):
        """Write the inks as a JSON list readable by :meth:`load_json` (atomic write; floats round-trip exactly)."""
        _io.write_json(path, [ink.to_dict() for ink in self._inks])

    # ------------------------------------------------------------------------------------------------------------
    # sequence protocol and lookup
    # ------------------------------------------------------------------------------------------------------------
    def __len__(self):
        return len(self._inks)

    def __getitem__(self, item):
        if isinstance(item, slice):
            return InkSet(self._inks[item])
        return self._inks[item]

    def __iter__(self):
        return iter(self._inks)

    def __contains__(self, item):
        if isinstance(item, str):
            return item.strip().lower() in self._lookup
        return item in self._inks

    def __eq__(self, other):
        return isinstance(other, InkSet) and self._inks == other._inks

    def __hash__(self):
        return hash(self._inks)

    def __repr__(self):
        return f"InkSet({list(self.names)!r})"

    def index(self, name):
        """Material index of the ink called ``name`` (case-insensitive; an :class:`Ink` is also accepted).

        Raises:
            ValueError: no such ink in this set (the message lists the set's names).
        """
        if isinstance(name, Ink):
            name = name.name
        if not isinstance(name, str):
            raise TypeError(f"name: expected an ink name (str), got {type(name).__name__}")
        key = name.strip().lower()
        if key not in self._lookup:
            raise ValueError(f"name: ink {name!r} is not in this ink set {list(self.names)}")
        return self._lookup[key]

    @property
    def names(self):
        """Ink names in material-index order, as given."""
        return tuple(ink.name for ink in self._inks)

    @property
    def g(self):
        """The common Henyey–Greenstein g of all inks (the tracer takes one g).

        Raises:
            ValueError: the inks have different g (their mixture is not a Henyey–Greenstein medium).
        """
        values = sorted({ink.g for ink in self._inks})
        if len(values) != 1:
            raise ValueError(f"inks: the tracer takes one Henyey–Greenstein g, but these inks have g = {values}")
        return values[0]

    # ------------------------------------------------------------------------------------------------------------
    # optical properties as tensors
    # ------------------------------------------------------------------------------------------------------------
    def _table(self, values, dtype, device):
        return torch.tensor(values, dtype=torch.float64).to(dtype=dtype, device=device)

    def sigma_t(self, dtype=torch.float32, device=None):
        """(N, 3) extinction coefficients μ_t in mm⁻¹."""
        return self._table([ink.sigma_t for ink in self._inks], dtype, device)

    def albedo(self, dtype=torch.float32, device=None):
        """(N, 3) single-scattering albedos α."""
        return self._table([ink.albedo for ink in self._inks], dtype, device)

    def sigma_s(self, dtype=torch.float32, device=None):
        """(N, 3) scattering coefficients σ_s = α μ_t in mm⁻¹ (computed in float64, then cast)."""
        return self._table([ink.sigma_s for ink in self._inks], dtype, device)

    def sigma_a(self, dtype=torch.float32, device=None):
        """(N, 3) absorption coefficients σ_a = (1 − α) μ_t in mm⁻¹ (computed in float64, then cast)."""
        return self._table([ink.sigma_a for ink in self._inks], dtype, device)

    def display_rgb(self):
        """(N, 3) uint8 NumPy array of the palette colours (sRGB, ``round(255 · display_rgb)``)."""
        return np.array([[int(round(255.0 * v)) for v in ink.display_rgb] for ink in self._inks], dtype=np.uint8)
