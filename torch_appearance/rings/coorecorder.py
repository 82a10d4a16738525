"""CooRecorder ``.pos`` coordinate files (Cybis Elektronik & Data AB) as ring-boundary labels.

A ``.pos`` file is plain text; header lines start with ``#`` (or are ``SCALE ...``), every other non-empty line holds
one measured point ``x,y`` in millimetres on the image (origin at the top-left corner, x right, y down; pixel =
mm * DPI / 25.4), optionally followed by `` #label``::

    #DENDRO (Cybis Dendro program compatible format) Coordinate file written as C:\\data\\disc1_a.pos
    #Imagefile disc1.jpg
    #DPI 1200.0
    #All coordinates in millimeters (mm)
    SCALE 1
    #C DATED 2019
    #C PithCoordinates=10.160,12.700; DistanceToPith=0.0; YearsToPith=0;
    10.160,12.700
    11.430,12.700
    13.970,12.700  14.100,13.200
    D15.240,12.700#%gap

The points are in measurement order, one per ring boundary. Two orders occur: pith first, then the boundaries
towards the bark (the example above, whose first point is the pith); or the outermost boundary first, inwards, with
the pith only in the ``PithCoordinates`` header (the order that public .pos readers, e.g. an R ``read_pos``,
assign calendar years in: the first point gets the outer date). :meth:`PosFile.boundaries_px` tells them apart by
the pith. Text lines before the first point (holding letters: some files start with the path they were written to)
are kept in ``header["preamble"]``; any other line must be a point. A line with
two points is a *jump* (a "double point": the path continues elsewhere, e.g. around a crack); both mark the same
ring boundary, the first where the path arrives, which is kept as the boundary (the second is in ``jumps``).
Lines starting with ``D`` (gaps, season-wood marks ``#W#``) are not ring boundaries and are skipped; a ``#ZERO``
suffix (missing rings of zero width) is ignored (the position is counted once). The header line
``#C PithCoordinates=x,y;`` gives the pith when the first point is not on it.
"""
from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass, field

import numpy as np

from ..io import atomic_write_bytes

__all__ = ["PosFile", "read_pos", "write_pos"]

_POINT = re.compile(r"^\s*(-?\d+(?:\.\d*)?|-?\.\d+)\s*,\s*(-?\d+(?:\.\d*)?|-?\.\d+)\s*$")


@dataclass
class PosFile:
    """A parsed CooRecorder ``.pos`` file.

    Attributes:
        dpi: the ``#DPI`` value (pixels per inch).
        points_mm: ``(N, 2)`` float64 ``(x, y)`` in mm, in file order (the first point of each double point).
        points_px: ``points_mm * dpi / 25.4``.
        pith_px: ``(2,)`` pith in pixels from ``#C PithCoordinates``, or None.
        jumps_px: ``(J, 2)`` the second points of double points, in pixels.
        header: dict of ``#C key=value;`` entries and ``Imagefile``.
    """

    dpi: float
    points_mm: np.ndarray
    points_px: np.ndarray
    pith_px: np.ndarray | None
    jumps_px: np.ndarray
    header: dict = field(default_factory=dict)

    def boundaries_px(self, first_is_pith: bool | None = None) -> np.ndarray:
        """``(K, 2)`` ring boundaries in pixels, ordered pith -> bark.

        Args:
            first_is_pith: None (automatic): with a ``PithCoordinates`` header, every point is a boundary except
                points on the pith (within 1 px), and the list is reversed when it starts at the bark end (its first
                point farther from the pith than its last); without the header the first point is taken as the pith
                (the pith-first convention). True: drop the first point; False: every point, in file order.
        """
        if first_is_pith is True:
            return self.points_px[1:].copy()
        if first_is_pith is False:
            return self.points_px.copy()
        if self.pith_px is None:
            return self.points_px[1:].copy()
        d = np.hypot(*(self.points_px - self.pith_px).T)
        b, d = self.points_px[d > 1.0], d[d > 1.0]
        if len(b) > 1 and d[0] > d[-1]:
            b = b[::-1]
        return b.copy()


def _xy(text, path, lineno):
    m = _POINT.match(text)
    if not m:
        raise ValueError(f"{path!r} line {lineno}: expected a point 'x,y' in mm; got {text.strip()!r}")
    x, y = float(m.group(1)), float(m.group(2))
    if not (math.isfinite(x) and math.isfinite(y)):
        raise ValueError(f"{path!r} line {lineno}: non-finite coordinate {text.strip()!r}")
    return x, y


def read_pos(path) -> PosFile:
    """Parse a CooRecorder ``.pos`` file (module docstring).

    Raises:
        ValueError: the file cannot be read, has no (or a non-positive) ``#DPI`` line, a malformed point line, or no
            point at all.
    """
    try:
        with open(path, encoding="utf-8", errors="replace") as f:
            lines = f.read().splitlines()
    except OSError as e:
        raise ValueError(f"cannot read .pos file {str(path)!r}: {e}") from None
    dpi, header, pts, jumps, preamble = None, {}, [], [], []
    for lineno, raw in enumerate(lines, 1):
        line = raw.strip()
        if not line:
            continue
        if line.startswith("#"):
            m = re.match(r"#DPI\s+(\S+)", line, re.IGNORECASE)
            if m:
                try:
                    dpi = float(m.group(1))
                except ValueError:
                    raise ValueError(f"{str(path)!r} line {lineno}: #DPI must be a number; "
                                     f"got {m.group(1)!r}") from None
            elif line.lower().startswith("#imagefile"):
                header["Imagefile"] = line[len("#imagefile"):].strip()
            elif line.startswith("#C"):
                for key, val in re.findall(r"(\w+)\s*=\s*([^;]*)", line[2:]):
                    header[key] = val.strip()
            continue
        if line.upper().startswith("SCALE") or line.startswith("D"):
            continue  # the scale line; gaps and season-wood marks are not ring boundaries
        body = line.split("#", 1)[0].strip()
        parts = body.split()
        if not pts and re.search(r"[A-Za-z]", body) and not all(_POINT.match(p) for p in parts):
            preamble.append(line)  # header text before the first point (e.g. the path the file was written to)
            continue
        if not parts or len(parts) > 2:
            raise ValueError(f"{str(path)!r} line {lineno}: expected 'x,y' or a double point 'x1,y1  x2,y2'; got "
                             f"{line!r}")
        pts.append(_xy(parts[0], str(path), lineno))
        if len(parts) == 2:
            jumps.append(_xy(parts[1], str(path), lineno))
    if dpi is None:
        raise ValueError(f".pos file {str(path)!r} has no '#DPI' line (needed to convert mm to pixels)")
    if not (math.isfinite(dpi) and dpi > 0):
        raise ValueError(f".pos file {str(path)!r}: #DPI must be > 0; got {dpi}")
    if not pts:
        raise ValueError(f".pos file {str(path)!r} holds no points")
    if preamble:
        header["preamble"] = preamble
    scale = dpi / 25.4
    pmm = np.array(pts, dtype=np.float64).reshape(-1, 2)
    pith = None
    if "PithCoordinates" in header:
        try:
            pith = np.array([float(t) for t in header["PithCoordinates"].split(",")], dtype=np.float64) * scale
            if pith.shape != (2,):
                raise ValueError
        except ValueError:
            raise ValueError(f".pos file {str(path)!r}: PithCoordinates must be 'x,y' in mm; got "
                             f"{header['PithCoordinates']!r}") from None
    return PosFile(dpi=dpi, points_mm=pmm, points_px=pmm * scale, pith_px=pith,
                   jumps_px=np.array(jumps, dtype=np.float64).reshape(-1, 2) * scale, header=header)


def write_pos(path, boundaries_px, dpi, pith_px=None, image_file=None, last_year=None, program="torch_appearance"):
    """Write ring boundaries as a CooRecorder ``.pos`` file (atomically), in the order CooRecorder itself writes a
    radial transect: the pith first (when known, also as ``#C PithCoordinates``), then the boundaries outwards; mm
    from the image's top-left corner with three decimals; CRLF line ends. :func:`read_pos` reads it back.

    Args:
        path: the file. boundaries_px: ``(K, 2)`` boundaries ``(x, y)`` in pixels, pith → bark. dpi: the image's
            resolution (pixels per inch, > 0). pith_px: optional ``(2,)`` pith in pixels. image_file: the image's
            name for ``#Imagefile``. last_year: the calendar year of the outermost ring (``#C DATED``), or None.
    """
    pts = np.asarray(boundaries_px, np.float64)
    if pts.ndim != 2 or pts.shape[1] != 2 or len(pts) == 0 or not np.all(np.isfinite(pts)):
        raise ValueError(f"boundaries_px: expected finite (K, 2) pixel coordinates with K >= 1, got shape "
                         f"{pts.shape}")
    if isinstance(dpi, bool) or not isinstance(dpi, (int, float)) or not (math.isfinite(dpi) and dpi > 0):
        raise ValueError(f"dpi: expected a number > 0, got {dpi!r}")
    mm = 25.4 / float(dpi)
    lines = [f"#DENDRO (Cybis Dendro program compatible format) Coordinate file written as {os.path.basename(path)} "
             f"by {program}"]
    if image_file:
        lines.append(f"#Imagefile {os.path.basename(image_file)}")
    lines += [f"#DPI {float(dpi):.1f}", "#All coordinates in millimeters (mm)", "SCALE 1",
              "#C DATED" + ("" if last_year is None else f" {int(last_year)}")]
    if pith_px is not None:
        pith = np.asarray(pith_px, np.float64).ravel()
        if pith.shape != (2,) or not np.all(np.isfinite(pith)):
            raise ValueError(f"pith_px: expected finite (x, y) in pixels, got {pith_px!r}")
        lines.append(f"#C PithCoordinates={pith[0] * mm:.3f},{pith[1] * mm:.3f}; DistanceToPith=0.0; YearsToPith=0;")
        pts = np.concatenate([pith[None], pts])
    lines += [f"{x * mm:.3f},{y * mm:.3f}" for x, y in pts]
    atomic_write_bytes(path, ("\r\n".join(lines) + "\r\n").encode("ascii"))
