"""Fixed ink fractions from the command line (translucency, paper §5.2 Fig. 16): ``INK=FRACTION:MASK``.

MASK selects voxels of the print target; terms joined by ``&`` intersect:

* ``all``: every optimised voxel;
* ``depth:A-B``: voxels whose centre lies between A and B mm below the surface (the top face of a slab);
* ``PATH.png``: a mask image, white = selected. For a slab it has the slab's texel size (H × W) and selects whole
  columns; for an object it is painted in the mesh's texture space (same size as the mesh's texture when it has
  one) and every shell voxel takes the mask value at the UV of its nearest surface texel;
* ``material:NAME``: objects only: shell voxels whose nearest surface texel lies on a face of the mesh's material
  NAME (``load_mesh``'s report lists the names: an OBJ's ``usemtl`` materials, a glTF's materials).

Example: ``transparent=0.8:depth:0-0.4`` makes the outer 0.4 mm 80 % clear.
"""
import os
import re

import numpy as np
import torch

from ...nn.mixture import FixedFraction

__all__ = ["parse_fixed", "fixed_fractions"]

_SPEC = re.compile(r"^\s*([A-Za-z0-9_\-]+)\s*=\s*([0-9.eE+\-]+)\s*:\s*(.+?)\s*$")
_DEPTH = re.compile(r"^depth:([0-9.eE+\-]+)-([0-9.eE+\-]+)$")


def parse_fixed(spec):
    """``"INK=FRACTION:MASK"`` → (ink, fraction, [mask terms]); ValueError naming what is wrong."""
    if not isinstance(spec, str):
        raise TypeError(f"fixed: expected strings INK=FRACTION:MASK, got {type(spec).__name__}")
    m = _SPEC.match(spec)
    if not m:
        raise ValueError(f"fixed: expected INK=FRACTION:MASK (e.g. transparent=0.8:depth:0-0.4), got {spec!r}")
    ink, fraction, mask = m.group(1), m.group(2), m.group(3)
    try:
        fraction = float(fraction)
    except ValueError:
        raise ValueError(f"fixed: {spec!r}: the fraction {fraction!r} is not a number") from None
    if not 0.0 <= fraction <= 1.0:
        raise ValueError(f"fixed: {spec!r}: expected a fraction in [0, 1], got {fraction}")
    terms = [t.strip() for t in mask.split("&") if t.strip()]
    for term in terms:
        if term == "all" or _DEPTH.match(term):
            continue
        if term.startswith("material:") and term[len("material:"):].strip():
            continue
        if term.lower().endswith(".png"):
            if not os.path.isfile(term):
                raise ValueError(f"fixed: {spec!r}: mask image {term!r} does not exist")
            continue
        raise ValueError(f"fixed: {spec!r}: unknown mask term {term!r} (expected all, depth:A-B, material:NAME or a .png image)")
    return ink, fraction, terms


def _read_mask(path):
    """(H, W) bool: the mask image's grey value > 0.5 (:func:`torch_appearance.io.read_mask`; truncated or corrupt
    files are refused)."""
    from ... import io as ta_io

    return ta_io.read_mask(path, name="fixed: mask image")


def _term_mask(target, term, spec):
    """(D, H, W) bool of one mask term (the target places depth ranges, mask images and materials: its
    ``voxel_depth``, ``image_mask`` and ``material_mask``)."""
    shape = tuple(target.shape)
    if term == "all":
        return np.ones(shape, dtype=bool)
    m = _DEPTH.match(term)
    if m:
        a, b = float(m.group(1)), float(m.group(2))
        if not 0 <= a < b:
            raise ValueError(f"fixed: {spec!r}: expected depth:A-B with 0 <= A < B (mm), got {term!r}")
        depth = target.voxel_depth()
        return (depth >= a) & (depth < b)
    if term.startswith("material:"):
        return target.material_mask(term[len("material:"):].strip(), spec)
    return target.image_mask(_read_mask(term), term, spec)


def fixed_fractions(target, specs, inks):
    """``FixedFraction`` constraints of a target from ``INK=FRACTION:MASK`` strings (see the module docstring).

    Returns:
        (list of FixedFraction, list of (ink index, fraction, (D, H, W) bool mask)) for the mixture and the
        quantisation.
    """
    constraints, raw = [], []
    support = None if target.support is None else target.support.numpy()
    for spec in specs:
        ink, fraction, terms = parse_fixed(spec)
        try:
            index = inks.index(ink)
        except ValueError:
            raise ValueError(f"fixed: {spec!r}: ink {ink!r} is not in the ink set {list(inks.names)}") from None
        mask = np.ones(tuple(target.shape), dtype=bool)
        for term in terms:
            mask &= _term_mask(target, term, spec)
        if support is not None:
            mask &= support
        if not mask.any():
            raise ValueError(f"fixed: {spec!r} selects no optimised voxel")
        constraints.append(FixedFraction(torch.from_numpy(np.ascontiguousarray(mask)), inks.names[index], fraction))
        raw.append((index, fraction, mask))
    return constraints, raw
