"""Printer profiles: what a printer holds and how the library's inks map onto it.

A profile is a small JSON file (the built-in ones live in ``torch_appearance/fabrication/printers/``; a user's own is
read from any path)::

    {
      "name": "j750",
      "description": "...",
      "dpi": [600, 300],                   # x, y in dots per inch
      "layer_thickness_nm": 27000,         # z: one printer layer, in nanometres
      "bit_depth": 4,                      # written to GrabCAD's ConfigFile.xml
      "background_rgba": [0, 0, 0, 255],   # the slice colour of "no material"
      "materials": [{"name": "VeroCY-V", "rgba": [0, 255, 255, 255]}, ...],
      "inks": {"cyan": "VeroCY-V", ...}    # library ink name -> the material it prints with
    }

The material names and colours are the printer's (they come from the profile, never from the code); the ``inks``
table says which material prints each of the library's inks (:class:`~torch_appearance.fabrication.Ink` names,
case-insensitive). Each material's RGB must differ from every other's and from the background's, because the
slices identify materials by their 24-bit colour.

The printer's resolution in the library's ``(x, y, z)`` DPI convention is :attr:`PrinterProfile.dpi`
(z = 25.4 mm / layer thickness).
"""
import dataclasses
import json
import math
import os
from typing import Dict, Tuple

from ..checks import describe

__all__ = ["PrinterProfile", "load_printer", "builtin_printers", "PRINTERS_DIR"]

#: Folder of the built-in profiles (``NAME.json``).
PRINTERS_DIR = os.path.join(os.path.dirname(os.path.abspath(__file__)), "printers")

_FIELDS = ("name", "description", "dpi", "layer_thickness_nm", "bit_depth", "background_rgba", "materials", "inks")


def builtin_printers():
    """Names of the built-in profiles, sorted."""
    return sorted(f[:-5] for f in os.listdir(PRINTERS_DIR) if f.endswith(".json"))


def _rgba(where, value):
    if (not isinstance(value, (list, tuple)) or len(value) != 4
            or not all(isinstance(v, int) and not isinstance(v, bool) and 0 <= v <= 255 for v in value)):
        raise ValueError(f"{where}: expected [r, g, b, a], four ints in 0..255, got {value!r}")
    return tuple(value)


@dataclasses.dataclass(frozen=True)
class PrinterProfile:
    """One printer: resolution, layer thickness, the materials it holds and the ink → material table.

    Attributes:
        name: the profile's name. description: one line for people.
        dpi_xy: ``(x, y)`` dots per inch. layer_thickness_nm: one layer in nm.
        bit_depth: GrabCAD's ``BitDepth``. background_rgba: the slice colour of empty voxels.
        materials: ``((name, (r, g, b, a)), ...)`` in the printer's order.
        inks: ``{ink name (lower case): material name}``.
        source: the file it was read from.
    """
    name: str
    description: str
    dpi_xy: Tuple[float, float]
    layer_thickness_nm: float
    bit_depth: int
    background_rgba: Tuple[int, int, int, int]
    materials: Tuple[Tuple[str, Tuple[int, int, int, int]], ...]
    inks: Dict[str, str]
    source: str = ""

    @property
    def dpi(self):
        """``(x, y, z)`` dots per inch, z = 25.4 mm / layer thickness (the library's ``printer_dpi``)."""
        return (float(self.dpi_xy[0]), float(self.dpi_xy[1]), 25.4e6 / self.layer_thickness_nm)

    @property
    def material_names(self):
        return [m[0] for m in self.materials]

    def material_indices(self, ink_names):
        """For each of ``ink_names`` (the run's inks, in order) the index of the printer material that prints it.

        Raises:
            ValueError: an ink the printer does not hold, naming the ink, the printer and what it holds.
        """
        names = self.material_names
        out = []
        for ink in ink_names:
            material = self.inks.get(str(ink).lower())
            if material is None:
                raise ValueError(f"printer {self.name!r}: no material for the ink {ink!r}; it prints the inks "
                                 f"{sorted(self.inks)} (edit the profile's \"inks\" table to add one)")
            out.append(names.index(material))
        return out

    def matches(self, dpi, tolerance=0.01):
        """Whether a volume quantised at ``dpi`` (x, y, z) has this printer's voxels, each axis within ``tolerance``
        (relative): the run's volume can then be printed as it is."""
        return all(abs(a / b - 1.0) <= tolerance for a, b in zip(dpi, self.dpi))

    def to_dict(self):
        return {"name": self.name, "description": self.description, "dpi": list(self.dpi_xy),
                "layer_thickness_nm": self.layer_thickness_nm, "bit_depth": self.bit_depth,
                "background_rgba": list(self.background_rgba),
                "materials": [{"name": n, "rgba": list(c)} for n, c in self.materials], "inks": dict(self.inks)}

    @classmethod
    def from_dict(cls, data, source=""):
        """A profile from its JSON dict; every field is checked, errors name the file and the field."""
        where = source or "printer profile"
        if not isinstance(data, dict):
            raise ValueError(f"{where}: expected a JSON object, got {describe(data)}")
        unknown = sorted(set(data) - set(_FIELDS))
        missing = [k for k in _FIELDS if k not in data and k != "description"]
        if unknown or missing:
            raise ValueError(f"{where}: " + "; ".join(
                ([f"unknown key(s) {unknown}"] if unknown else []) + ([f"missing key(s) {missing}"] if missing else []))
                + f" (a profile has {list(_FIELDS)})")
        name = data["name"]
        if not isinstance(name, str) or not name.strip():
            raise ValueError(f"{where}: name: expected a non-empty string, got {name!r}")
        dpi = data["dpi"]
        if (not isinstance(dpi, list) or len(dpi) != 2
                or not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v > 0
                           for v in dpi)):
            raise ValueError(f"{where}: dpi: expected [x, y], two numbers > 0 (dots per inch), got {dpi!r}")
        layer = data["layer_thickness_nm"]
        if not isinstance(layer, (int, float)) or isinstance(layer, bool) or not math.isfinite(layer) or layer <= 0:
            raise ValueError(f"{where}: layer_thickness_nm: expected a number > 0, got {layer!r}")
        bits = data["bit_depth"]
        if not isinstance(bits, int) or isinstance(bits, bool) or not 1 <= bits <= 16:
            raise ValueError(f"{where}: bit_depth: expected an int in 1..16, got {bits!r}")
        background = _rgba(f"{where}: background_rgba", data["background_rgba"])
        materials = data["materials"]
        if not isinstance(materials, list) or not materials:
            raise ValueError(f"{where}: materials: expected a non-empty list of {{name, rgba}}, got {materials!r}")
        parsed = []
        for i, m in enumerate(materials):
            if not isinstance(m, dict) or set(m) != {"name", "rgba"} or not isinstance(m["name"], str) \
                    or not m["name"]:
                raise ValueError(f"{where}: materials[{i}]: expected {{\"name\": str, \"rgba\": [r, g, b, a]}}, "
                                 f"got {m!r}")
            parsed.append((m["name"], _rgba(f"{where}: materials[{i}].rgba", m["rgba"])))
        names = [n for n, _ in parsed]
        if len(set(names)) != len(names):
            raise ValueError(f"{where}: materials: names must be unique, got {names}")
        if len(parsed) > 2 ** bits:
            raise ValueError(f"{where}: {len(parsed)} materials do not fit bit_depth {bits}")
        codes = [c[:3] for _, c in parsed] + [background[:3]]
        if len(set(codes)) != len(codes):
            raise ValueError(f"{where}: every material and the background need a distinct RGB (the slices identify "
                             f"materials by colour), got {[(n, c) for n, c in parsed]} and background {background}")
        inks = data["inks"]
        if not isinstance(inks, dict) or not inks:
            raise ValueError(f"{where}: inks: expected an object {{ink name: material name}}, got {inks!r}")
        for ink, material in inks.items():
            if material not in names:
                raise ValueError(f"{where}: inks: ink {ink!r} prints with {material!r}, which is not one of the "
                                 f"materials {names}")
        return cls(name=name, description=str(data.get("description", "")), dpi_xy=(float(dpi[0]), float(dpi[1])),
                   layer_thickness_nm=float(layer), bit_depth=bits, background_rgba=background,
                   materials=tuple(parsed), inks={str(k).lower(): v for k, v in inks.items()}, source=source)


def load_printer(printer):
    """A :class:`PrinterProfile` by built-in name (``"j750"``, ``"j750-hq"``, ``"generic"``; see
    :func:`builtin_printers`) or from a JSON file's path. A profile passes through unchanged.

    Raises:
        TypeError: not a str, path or profile.
        ValueError: an unknown name (listing the built-in ones), a file that is not a valid profile.

    Example:
        >>> p = load_printer("j750")
        >>> round(p.dpi[2], 2), p.material_names[0]
        (940.74, 'VeroCY-V')
    """
    if isinstance(printer, PrinterProfile):
        return printer
    if not isinstance(printer, (str, os.PathLike)):
        raise TypeError(f"printer: expected a profile name or a path to a profile's JSON, got {describe(printer)}")
    text = os.fspath(printer)
    if os.path.isfile(text):
        path = text
    elif text.lower() in builtin_printers():
        path = os.path.join(PRINTERS_DIR, text.lower() + ".json")
    else:
        raise ValueError(f"printer: {text!r} is neither a built-in profile {builtin_printers()} nor an existing "
                         f"JSON file")
    with open(path, "r", encoding="utf-8") as handle:
        try:
            data = json.load(handle)
        except json.JSONDecodeError as error:
            raise ValueError(f"printer: {path!r} is not valid JSON: {error}") from None
    return PrinterProfile.from_dict(data, source=path)
