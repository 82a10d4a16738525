"""Tucson ``.rwl`` ring-width files (the decadal format of the ITRDB, read by dplR, CDendro, COFECHA, TSAP).

Each line holds one series' values for (part of) one decade, in fixed columns::

    columns  1-8   series ID (at most 8 characters, no spaces inside; left-justified)
    columns  9-12  year of the line's first value (right-justified)
    then up to ten values, 6 columns each, right-justified integers in units of the file's precision

A series' first line starts at its first year and ends at the decade's last year (a year ending in 9); each later line
starts at a year ending in 0. The value after a series' last year is the stop marker, which also gives the
precision: ``999`` for 0.01 mm units, ``-9999`` for 0.001 mm units. A file may hold several series, one after the
other. This module writes 0.001 mm units by default (a width of exactly 9.99 mm cannot be written in 0.01 mm units,
where 999 means "stop"), and reads both. Missing rings (zero width) are written as 0, as dplR does.

Reference: the ITRDB's Tucson format description (NOAA/WDS Paleoclimatology, "Tucson Format"), and dplR's
``read.tucson``/``write.tucson`` (Bunn 2008, Dendrochronologia 26:115).
"""
from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass

import numpy as np

from ..io import atomic_write_bytes

__all__ = ["RingSeries", "write_rwl", "read_rwl"]

_STOP = {0.01: 999, 0.001: -9999}
_ID = re.compile(r"^[^\s]{1,8}$")


@dataclass
class RingSeries:
    """One ring-width series: ``widths_mm[k]`` is the width of the ring of year ``first_year + k`` (pith → bark)."""

    id: str
    first_year: int
    widths_mm: np.ndarray

    @property
    def last_year(self):
        return self.first_year + len(self.widths_mm) - 1

    @classmethod
    def ending(cls, id, last_year, widths_mm):
        """The series whose last (outermost) ring grew in ``last_year``."""
        widths = np.asarray(widths_mm, np.float64).ravel()
        return cls(id, int(last_year) - len(widths) + 1, widths)


def _check_series(s, precision):
    if not isinstance(s, RingSeries):
        raise TypeError(f"series: expected RingSeries, got {type(s).__name__}")
    if not isinstance(s.id, str) or not _ID.match(s.id):
        raise ValueError(f"series id: expected 1 to 8 characters without spaces (Tucson columns 1-8), got {s.id!r}")
    widths = np.asarray(s.widths_mm, np.float64).ravel()
    if widths.size == 0:
        raise ValueError(f"series {s.id!r}: no ring widths")
    if not np.all(np.isfinite(widths)) or np.any(widths < 0):
        raise ValueError(f"series {s.id!r}: ring widths must be finite and >= 0 mm, got {widths.tolist()}")
    units = np.rint(widths / precision).astype(np.int64)
    if units.max() > 99999 or (precision == 0.01 and np.any(units == 999)):
        raise ValueError(f"series {s.id!r}: a width of {widths.max():.3f} mm does not fit 6 columns at precision "
                         f"{precision} mm")
    first, last = int(s.first_year), int(s.first_year) + widths.size  # `last`: the stop marker's year
    if first < -999 or last > 9999:
        raise ValueError(f"series {s.id!r}: years {first}..{last - 1} do not fit the 4-column year field")
    return units


def write_rwl(path, series, precision=0.001):
    """Write ring-width series (a :class:`RingSeries` or a sequence of them) to a Tucson ``.rwl`` file (atomically).

    Args:
        path: the file to write. series: RingSeries with distinct ids. precision: 0.001 (default, stop marker -9999)
            or 0.01 mm (stop marker 999).

    Raises:
        ValueError/TypeError: an id longer than 8 characters or with spaces, duplicate ids, negative or non-finite
            widths, a width too large for the format, a year outside -999..9999, another precision.
    """
    if precision not in _STOP:
        raise ValueError(f"precision: expected 0.01 or 0.001 (mm), got {precision!r}")
    series = [series] if isinstance(series, RingSeries) else list(series)
    if not series:
        raise ValueError("series: expected at least one series")
    ids = [getattr(s, "id", None) for s in series]
    if len(set(ids)) != len(ids):
        raise ValueError(f"series: ids must be distinct, got {ids}")
    lines = []
    for s in series:
        values = list(_check_series(s, precision)) + [_STOP[precision]]
        year = int(s.first_year)
        k = 0
        while k < len(values):
            n = 10 - (year % 10)  # to the end of the decade (Python's % is 9 for -1: a year -1 line ends at 0 - 1)
            chunk = values[k:k + n]
            lines.append(f"{s.id:<8}{year:>4}" + "".join(f"{v:>6}" for v in chunk))
            k += n
            year += n
    atomic_write_bytes(path, ("\r\n".join(lines) + "\r\n").encode("ascii"))


def read_rwl(path):
    """The series of a Tucson ``.rwl`` file, ``{id: RingSeries}`` in file order (precision from each stop marker).

    Header lines of the ITRDB's three-line header (a series id followed by text that is not a year and numbers) are
    skipped. Raises ValueError naming the file and line for a malformed data line, a year that does not continue the
    series, or a series without its stop marker (a truncated file).
    """
    try:
        with open(path, encoding="ascii", errors="replace") as f:
            text = f.read().splitlines()
    except OSError as e:
        raise ValueError(f"cannot read .rwl file {str(path)!r}: {e}") from None
    out, current, name = {}, None, os.fspath(path)
    for lineno, line in enumerate(text, 1):
        if not line.strip():
            continue
        sid, year_text, body = line[:8].strip(), line[8:12].strip(), line[12:]
        values = [body[6 * k:6 * k + 6] for k in range(math.ceil(len(body.rstrip()) / 6))]
        try:
            year = int(year_text)
            numbers = [int(v) for v in values]
        except ValueError:
            if current is None and sid not in out:
                continue  # a header line
            raise ValueError(f"{name!r} line {lineno}: expected a data line (id, year, up to ten 6-column values), "
                             f"got {line!r}") from None
        if not numbers or len(numbers) > 10:
            raise ValueError(f"{name!r} line {lineno}: expected 1 to 10 values, got {len(numbers)}")
        if current is None:
            if sid in out:
                raise ValueError(f"{name!r} line {lineno}: series {sid!r} appears twice")
            current = {"id": sid, "first": year, "next": year, "units": []}
        elif sid != current["id"] or year != current["next"]:
            raise ValueError(f"{name!r} line {lineno}: series {current['id']!r} ends without its stop marker "
                             f"(999 or -9999) before {sid!r} {year}")
        for v in numbers:
            if v in (999, -9999):
                precision = 0.01 if v == 999 else 0.001
                widths = np.array(current["units"], np.float64) * precision
                out[sid] = RingSeries(sid, current["first"], widths)
                current = None
                break
            current["units"].append(v)
        else:
            current["next"] = year + len(numbers)
    if current is not None:
        raise ValueError(f"{name!r}: series {current['id']!r} has no stop marker (a truncated file?)")
    if not out:
        raise ValueError(f"{name!r} holds no ring-width series")
    return out
