#!/usr/bin/env python
"""Evaluate detected ring boundaries against labels: one-to-one matching within a tolerance (pixels).

Prints sensitivity (matched / labelled), precision (matched / detected), F1 and the mean position error of the
matches. Both CSVs need an x_px column; when both also have y_px the distance is Euclidean in (x, y), otherwise
only x is compared (e.g. MtreeRing label tables: year,x_px,ring_width_mm, measured along one horizontal path).

Example:
    python scripts/eval_rings.py rings.csv labels.csv --tolerance-px 3
"""
import argparse
import csv
import os
import sys

try:
    import torch_appearance  # noqa: F401
except ModuleNotFoundError as error:
    if error.name != "torch_appearance":
        raise
    sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
import numpy as np

from torch_appearance.rings.dendro import match_boundaries

PROG = "eval_rings.py"


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
    for c in ("x_px", "y_px"):
        if c in cols:
            try:
                out[c] = np.array([float(r[c]) for r in rows], dtype=np.float64)
            except (TypeError, ValueError):
                raise ValueError(f"{what} CSV {path!r}: column {c} holds a non-numeric value") from None
    return out


def evaluate(detected_csv, labels_csv, tolerance_px=3.0):
    if not tolerance_px > 0:
        raise ValueError(f"--tolerance-px must be > 0; got {tolerance_px}")
    d, l = read_points(detected_csv, "detected"), read_points(labels_csv, "labels")
    keys = ["x_px", "y_px"] if "y_px" in d and "y_px" in l else ["x_px"]
    return match_boundaries(np.stack([d[k] for k in keys], 1), np.stack([l[k] for k in keys], 1), tolerance_px)


def main(argv=None):
    p = argparse.ArgumentParser(prog=PROG, description=__doc__.split("\n\n")[0], epilog=__doc__.split("\n\n", 1)[1],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("detected_csv")
    p.add_argument("labels_csv")
    p.add_argument("--tolerance-px", type=float, default=3.0, help="match tolerance in pixels (default: %(default)s)")
    args = p.parse_args(argv)
    try:
        r = evaluate(args.detected_csv, args.labels_csv, args.tolerance_px)
    except ValueError as e:
        print(f"{PROG}: error: {e}", file=sys.stderr)
        return 2
    print(f"sensitivity {r['sensitivity']:.4f}  precision {r['precision']:.4f}  F1 {r['f1']:.4f}  "
          f"mean error {r['mean_error_px']:.3f} px  (matched {r['matched']}, detected {r['detected']}, "
          f"labelled {r['labelled']}, tolerance {args.tolerance_px:g} px)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
