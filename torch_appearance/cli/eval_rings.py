"""Evaluate detected ring boundaries against labels: one-to-one matching within a tolerance (pixels).

Prints sensitivity (matched / labelled), precision (matched / detected), F1 and the mean position error of the
matches. Both CSVs need an x_px column; when both also have y_px the distance is Euclidean in (x, y), otherwise
only x is compared (e.g. MtreeRing label tables: year,x_px,ring_width_mm, measured along one horizontal path).

Labels may also be a CooRecorder .pos file (torch_appearance.rings.coorecorder: points in mm with a #DPI line,
converted to pixels; points on the file's PithCoordinates are not boundaries, and without that header the first
point is taken as the pith, unless --pos-keep-first). Disc-mode CSVs
(detect_rings.py --pith) have a transect column: --transect K keeps only transect K of the detections, and of the
labels when they have a transect column too (a .pos file measures one path); when both CSVs have a transect column,
each transect is matched separately and the counts are pooled. Labels of several transects against detections of one
path (no transect column), an empty or header-only label file, and non-finite coordinates are refused in one line.

Examples:
    ta-eval-rings rings.csv labels.csv --tolerance-px 3
    ta-eval-rings disc.csv disc_radius_a.pos --transect 0 --tolerance-px 5
"""
import csv
import math
import sys

import numpy as np

from torch_appearance.rings.coorecorder import read_pos
from torch_appearance.rings.dendro import match_boundaries

from .command import CommandParser, fail

PROG = "ta-eval-rings"


def read_points(path, what):
    """``{column: float array}`` of a boundary CSV (``x_px``, and ``y_px``, ``transect`` where it has them; a UTF-8
    byte-order mark, as spreadsheets write it, is skipped); raises ValueError naming ``what`` (the argument,
    ``detected_csv`` or ``labels_csv``), the file and what is wrong in it."""
    try:
        with open(path, newline="", encoding="utf-8-sig") as f:
            reader = csv.DictReader(f)
            cols = [c.strip() for c in (reader.fieldnames or [])]
            rows = [{k.strip(): v for k, v in r.items() if k is not None} for r in reader]
    except IsADirectoryError:
        raise ValueError(f"{what}: expected a CSV file, got the folder {str(path)!r}") from None
    except FileNotFoundError:
        raise ValueError(f"{what}: no such file {str(path)!r}") from None
    except (OSError, UnicodeDecodeError, csv.Error) as e:
        raise ValueError(f"{what}: cannot read {str(path)!r} as a CSV file ({e})") from None
    if not cols:
        raise ValueError(f"{what}: {str(path)!r} is empty; expected a CSV with an x_px column")
    if "x_px" not in cols:
        raise ValueError(f"{what}: {str(path)!r} has no x_px column (columns: {', '.join(cols)}); expected a CSV "
                         f"with x_px[,y_px][,transect], comma-separated")
    out = {}
    if "transect" in cols:
        try:
            out["transect"] = np.array([int(r["transect"]) for r in rows], dtype=np.int64)
        except (TypeError, ValueError):
            raise ValueError(f"{what}: {str(path)!r}: column transect holds a non-integer value") from None
    for c in ("x_px", "y_px"):
        if c in cols:
            try:
                out[c] = np.array([float(r[c]) for r in rows], dtype=np.float64)
            except (TypeError, ValueError):
                raise ValueError(f"{what}: {str(path)!r}: column {c} holds a non-numeric value") from None
            bad = np.flatnonzero(~np.isfinite(out[c]))
            if len(bad):
                raise ValueError(f"{what}: {str(path)!r}: column {c} holds {out[c][bad[0]]} in data row {bad[0] + 1}; "
                                 f"expected finite pixel coordinates")
    return out


def read_labels(path, keep_first=False):
    """Labels as ``{column: array}``: a CSV (see :func:`read_points`) or a CooRecorder ``.pos`` file (pixels)."""
    if str(path).lower().endswith(".pos"):
        try:
            pos = read_pos(path)
        except ValueError as error:
            raise ValueError(f"labels_csv: {error}") from None
        b = pos.boundaries_px(first_is_pith=False if keep_first else None)
        return {"x_px": b[:, 0], "y_px": b[:, 1]}
    return read_points(path, "labels_csv")


def evaluate(detected_csv, labels_csv, tolerance_px=3.0, transect=None, pos_keep_first=False):
    """Matching result (:func:`torch_appearance.rings.dendro.match_boundaries`; pooled over transects when both
    files have a transect column; ``compared`` says which coordinates: ``"x, y"`` or ``"x"``).

    Raises:
        ValueError: a tolerance that is not a finite value > 0, a file that cannot be read or holds no boundary
        column, labels without a boundary, a ``transect`` that a file does not have, or labels of several transects
        for detections of one path (a file without a transect column).
    """
    if isinstance(tolerance_px, bool) or not (math.isfinite(tolerance_px) and tolerance_px > 0):
        raise ValueError(f"--tolerance-px: expected a finite value > 0 (pixels), got {tolerance_px}")
    d, l = read_points(detected_csv, "detected_csv"), read_labels(labels_csv, pos_keep_first)
    if len(l["x_px"]) == 0:  # sensitivity and the mean error have nothing to count: no score, not a NaN
        raise ValueError(f"labels_csv: {str(labels_csv)!r} holds no labelled boundary (a header only); expected at "
                         f"least one")
    if transect is not None:
        if "transect" not in d:
            raise ValueError(f"--transect {transect}: detected_csv {str(detected_csv)!r} has no transect column")
        if not (d["transect"] == transect).any():
            raise ValueError(f"--transect {transect}: detected_csv {str(detected_csv)!r} has no transect {transect} "
                             f"(has {sorted(set(d['transect'].tolist()))})")
        d = {k: v[d["transect"] == transect] for k, v in d.items()}
        if "transect" in l:  # the labels of that transect only (all of them were scored against it)
            if not (l["transect"] == transect).any():
                raise ValueError(f"--transect {transect}: labels_csv {str(labels_csv)!r} has no transect {transect} "
                                 f"(has {sorted(set(l['transect'].tolist()))})")
            l = {k: v[l["transect"] == transect] for k, v in l.items()}
    keys = ["x_px", "y_px"] if "y_px" in d and "y_px" in l else ["x_px"]
    compared = "x, y" if len(keys) == 2 else "x"
    pts = lambda a, sel: np.stack([a[k][sel] for k in keys], 1)  # noqa: E731
    if transect is None and "transect" in d and "transect" in l:
        ids = sorted(set(d["transect"].tolist()) | set(l["transect"].tolist()))
        parts = [match_boundaries(pts(d, d["transect"] == t), pts(l, l["transect"] == t), tolerance_px) for t in ids]
        m = sum(r["matched"] for r in parts)
        nd, nl = sum(r["detected"] for r in parts), sum(r["labelled"] for r in parts)
        sens, prec = (m / nl if nl else 0.0), (m / nd if nd else 0.0)
        err = [r["mean_error_px"] * r["matched"] for r in parts if r["matched"]]
        return dict(sensitivity=sens, precision=prec, f1=2 * sens * prec / (sens + prec) if sens + prec else 0.0,
                    mean_error_px=sum(err) / m if m else float("nan"), matched=m, detected=nd, labelled=nl,
                    compared=compared)
    if transect is None and "transect" in d and len(set(d["transect"].tolist())) > 1:
        raise ValueError(f"detected_csv: {str(detected_csv)!r} holds several transects; choose one with --transect K "
                         f"(or give labels with a transect column)")
    if transect is None and "transect" in l and len(set(l["transect"].tolist())) > 1:
        raise ValueError(f"labels_csv: {str(labels_csv)!r} holds several transects, while detected_csv "
                         f"{str(detected_csv)!r} has no transect column (one path); give detections with a transect "
                         f"column (disc mode) or the labels of one path")
    all_ = lambda a: np.ones(len(a["x_px"]), bool)  # noqa: E731
    return dict(match_boundaries(pts(d, all_(d)), pts(l, all_(l)), tolerance_px), compared=compared)


def main(argv=None):
    p = CommandParser(PROG, __doc__)
    p.add_argument("detected_csv")
    p.add_argument("labels_csv", help="labels: CSV with x_px[,y_px][,transect] or a CooRecorder .pos file")
    p.add_argument("--tolerance-px", type=float, default=3.0, help="match tolerance in pixels (default: %(default)s)")
    p.add_argument("--transect", type=int, default=None, help="use only this transect of a disc-mode CSV")
    p.add_argument("--pos-keep-first", action="store_true",
                   help="with .pos labels: count every point as a boundary (default: points on the PithCoordinates "
                        "header are not; without the header the first point is the pith)")
    args = p.parse_args(argv)
    try:
        r = evaluate(args.detected_csv, args.labels_csv, args.tolerance_px, args.transect, args.pos_keep_first)
    except ValueError as e:
        return fail(PROG, e)
    error = f"{r['mean_error_px']:.3f} px" if r["matched"] else "- (no match)"
    precision = f"{r['precision']:.4f}" if r["detected"] else "- (nothing detected)"
    compared = "" if r["compared"] == "x, y" else ", x only: a file has no y_px"
    print(f"sensitivity {r['sensitivity']:.4f}  precision {precision}  F1 {r['f1']:.4f}  "
          f"mean error {error}  (matched {r['matched']}, detected {r['detected']}, "
          f"labelled {r['labelled']}, tolerance {args.tolerance_px:g} px{compared})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
