"""Evaluate detected ring boundaries against labels: one-to-one matching within a tolerance (pixels).

Prints sensitivity (matched / labelled), precision (matched / detected), F1 and the mean position error of the
matches. Both CSVs need an x_px column; when both also have y_px the distance is Euclidean in (x, y), otherwise
only x is compared (e.g. MtreeRing label tables: year,x_px,ring_width_mm, measured along one horizontal path).

Labels may also be a CooRecorder .pos file (torch_appearance.rings.coorecorder: points in mm with a #DPI line,
converted to pixels; points on the file's PithCoordinates are not boundaries, and without that header the first
point is taken as the pith, unless --pos-keep-first). Disc-mode CSVs
(detect_rings.py --pith) have a transect column: --transect K keeps only transect K of the detections (a .pos
file measures one path); when both CSVs have a transect column, each transect is matched separately and the
counts are pooled.

Examples:
    ta-eval-rings rings.csv labels.csv --tolerance-px 3
    ta-eval-rings disc.csv disc_radius_a.pos --transect 0 --tolerance-px 5
"""
import csv
import sys

import numpy as np

from torch_appearance.rings.coorecorder import read_pos
from torch_appearance.rings.dendro import match_boundaries

from .command import CommandParser, fail

PROG = "ta-eval-rings"


def read_points(path, what):
    """``(columns, {column: float array})`` of a boundary CSV; raises ValueError with a clear message."""
    try:
        with open(path, newline="") as f:
            reader = csv.DictReader(f)
            cols = [c.strip() for c in (reader.fieldnames or [])]
            rows = [{k.strip(): v for k, v in r.items() if k is not None} for r in reader]
    except (OSError, UnicodeDecodeError) as e:
        raise ValueError(f"cannot read {what} CSV {path!r}: {e}") from None
    if "x_px" not in cols:
        raise ValueError(f"{what} CSV {path!r} has no x_px column (columns: {', '.join(cols) or 'none'})")
    out = {}
    if "transect" in cols:
        try:
            out["transect"] = np.array([int(r["transect"]) for r in rows], dtype=np.int64)
        except (TypeError, ValueError):
            raise ValueError(f"{what} CSV {path!r}: column transect holds a non-integer value") from None
    for c in ("x_px", "y_px"):
        if c in cols:
            try:
                out[c] = np.array([float(r[c]) for r in rows], dtype=np.float64)
            except (TypeError, ValueError):
                raise ValueError(f"{what} CSV {path!r}: column {c} holds a non-numeric value") from None
    return out


def read_labels(path, keep_first=False):
    """Labels as ``{column: array}``: a CSV (see :func:`read_points`) or a CooRecorder ``.pos`` file (pixels)."""
    if str(path).lower().endswith(".pos"):
        pos = read_pos(path)
        b = pos.boundaries_px(first_is_pith=False if keep_first else None)
        return {"x_px": b[:, 0], "y_px": b[:, 1]}
    return read_points(path, "labels")


def evaluate(detected_csv, labels_csv, tolerance_px=3.0, transect=None, pos_keep_first=False):
    """Matching result (:func:`torch_appearance.rings.dendro.match_boundaries`; pooled over transects when both
    files have a transect column)."""
    if not tolerance_px > 0:
        raise ValueError(f"--tolerance-px must be > 0; got {tolerance_px}")
    d, l = read_points(detected_csv, "detected"), read_labels(labels_csv, pos_keep_first)
    if len(l["x_px"]) == 0:  # sensitivity and the mean error have nothing to count: no score, not a NaN
        raise ValueError(f"labels_csv: {str(labels_csv)!r} holds no labelled boundary (a header only); expected at "
                         f"least one")
    if transect is not None:
        if "transect" not in d:
            raise ValueError(f"--transect {transect}: detected CSV {detected_csv!r} has no transect column")
        if not (d["transect"] == transect).any():
            raise ValueError(f"--transect {transect}: detected CSV {detected_csv!r} has no transect {transect} "
                             f"(has {sorted(set(d['transect'].tolist()))})")
        d = {k: v[d["transect"] == transect] for k, v in d.items()}
    keys = ["x_px", "y_px"] if "y_px" in d and "y_px" in l else ["x_px"]
    pts = lambda a, sel: np.stack([a[k][sel] for k in keys], 1)  # noqa: E731
    if transect is None and "transect" in d and "transect" in l:
        ids = sorted(set(d["transect"].tolist()) | set(l["transect"].tolist()))
        parts = [match_boundaries(pts(d, d["transect"] == t), pts(l, l["transect"] == t), tolerance_px) for t in ids]
        m = sum(r["matched"] for r in parts)
        nd, nl = sum(r["detected"] for r in parts), sum(r["labelled"] for r in parts)
        sens, prec = (m / nl if nl else 0.0), (m / nd if nd else 0.0)
        err = [r["mean_error_px"] * r["matched"] for r in parts if r["matched"]]
        return dict(sensitivity=sens, precision=prec, f1=2 * sens * prec / (sens + prec) if sens + prec else 0.0,
                    mean_error_px=sum(err) / m if m else float("nan"), matched=m, detected=nd, labelled=nl)
    if transect is None and "transect" in d and len(set(d["transect"].tolist())) > 1:
        raise ValueError(f"detected CSV {detected_csv!r} holds several transects; choose one with --transect K "
                         f"(or give labels with a transect column)")
    all_ = lambda a: np.ones(len(a["x_px"]), bool)  # noqa: E731
    return match_boundaries(pts(d, all_(d)), pts(l, all_(l)), tolerance_px)


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
    print(f"sensitivity {r['sensitivity']:.4f}  precision {r['precision']:.4f}  F1 {r['f1']:.4f}  "
          f"mean error {error}  (matched {r['matched']}, detected {r['detected']}, "
          f"labelled {r['labelled']}, tolerance {args.tolerance_px:g} px)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
