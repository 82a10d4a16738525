#!/usr/bin/env python
"""Real-data evaluation of the dendrochronology detectors (not part of the test suite).

1. Core mode on the MtreeRing core 001.png (bark left, 1200 dpi) against 001_borders_mtreering_watershed.csv
   (x positions; one-to-one matching within the tolerance, torch_appearance.rings.dendro.match_boundaries).
2. Section mode on the five microscopy patches input_0000k_preview.png against mask_0000k.png (boundary F-measure
   within the tolerance: label centre-line pixels near the detected curve / detected samples near the label).

Prints a table (sensitivity, precision, F1, mean error in px, wall time in s) and writes it as JSON. The data are
read from DATA (default ../shared/data: rings_core_mtreering/ and rings_microscopy/), never copied.

Example:
    python scripts/eval/eval_dendro_real.py --out /tmp/dendro_real.json
"""
import argparse
import csv
import json
import os
import sys
import time

import numpy as np

from torch_appearance.io import atomic_write_bytes, read_image, read_mask
from torch_appearance.rings.dendro import detect_core_boundaries
from torch_appearance.rings.evaluation import boundary_f_measure, mask_centerline, match_boundaries
from torch_appearance.rings.section import detect_section_boundaries

PROG = "eval_dendro_real.py"
DEFAULT_DATA = os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "..", "shared", "data")
CORE = ("rings_core_mtreering", "001.png", "001_borders_mtreering_watershed.csv")
MICRO = ("rings_microscopy", [(f"input_0000{k}_preview.png", f"mask_0000{k}.png") for k in range(1, 6)])


def needed_files(data):
    files = [os.path.join(data, CORE[0], CORE[1]), os.path.join(data, CORE[0], CORE[2])]
    files += [os.path.join(data, MICRO[0], f) for pair in MICRO[1] for f in pair]
    return files


def evaluate(data, tolerance_px=3.0):
    rows = []
    rgb = read_image(os.path.join(data, CORE[0], CORE[1]), space="srgb", name="core image")
    with open(os.path.join(data, CORE[0], CORE[2]), newline="") as f:
        lab = np.array([float(r["x_px"]) for r in csv.DictReader(f)])
    t = time.perf_counter()
    res = detect_core_boundaries(rgb, bark="left", dpi=1200)
    dt = time.perf_counter() - t
    m = match_boundaries(res.points[:, 0], lab, tolerance_px)
    rows.append(dict(name="core 001 (vs MtreeRing watershed)", metric="one-to-one", detected=m["detected"],
                     labelled=m["labelled"], sensitivity=m["sensitivity"], precision=m["precision"], f1=m["f1"],
                     mean_error_px=m["mean_error_px"], seconds=dt))
    for img, mask in MICRO[1]:
        rgb = read_image(os.path.join(data, MICRO[0], img), space="srgb", name="image")
        msk = read_mask(os.path.join(data, MICRO[0], mask), threshold=0.0)  # nonzero = boundary
        t = time.perf_counter()
        res = detect_section_boundaries(rgb)
        dt = time.perf_counter() - t
        m = boundary_f_measure(res.points, mask_centerline(msk), tolerance_px)
        rows.append(dict(name=f"microscopy {img[:11]}", metric="boundary-F", detected=m["detected"],
                         labelled=m["labelled"], sensitivity=m["sensitivity"], precision=m["precision"], f1=m["f1"],
                         mean_error_px=m["mean_error_px"], seconds=dt))
    return rows


def main(argv=None):
    p = argparse.ArgumentParser(prog=PROG, description=__doc__.split("\n\n")[0], epilog=__doc__.split("\n\n", 1)[1],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", default=DEFAULT_DATA, help="folder holding rings_core_mtreering/ and rings_microscopy/ "
                                                        "(default: ../shared/data next to the checkout)")
    p.add_argument("--out", default="dendro_real.json", help="output JSON (default: %(default)s)")
    p.add_argument("--tolerance-px", type=float, default=3.0, help="match tolerance in px (default: %(default)s)")
    args = p.parse_args(argv)
    if not args.tolerance_px > 0:
        print(f"{PROG}: error: --tolerance-px must be > 0; got {args.tolerance_px}", file=sys.stderr)
        return 2
    missing = [f for f in needed_files(args.data) if not os.path.isfile(f)]
    if missing:
        print(f"{PROG}: error: data missing under {args.data!r}: {', '.join(missing)}", file=sys.stderr)
        return 2
    if not os.path.isdir(os.path.dirname(os.path.abspath(args.out))):
        print(f"{PROG}: error: --out: folder of {args.out!r} does not exist", file=sys.stderr)
        return 2
    try:
        rows = evaluate(args.data, args.tolerance_px)
    except (OSError, ValueError) as e:
        print(f"{PROG}: error: {e}", file=sys.stderr)
        return 2
    print(f"{'case':36s} {'metric':10s} {'sens':>5s} {'prec':>5s} {'F1':>5s} {'mean px':>7s} {'s':>5s}"
          f"   (tolerance {args.tolerance_px:g} px)")
    for r in rows:
        print(f"{r['name']:36s} {r['metric']:10s} {r['sensitivity']:5.2f} {r['precision']:5.2f} {r['f1']:5.2f} "
              f"{r['mean_error_px']:7.2f} {r['seconds']:5.2f}")
    blob = json.dumps(dict(tolerance_px=args.tolerance_px, data=os.path.abspath(args.data), results=rows), indent=1)
    atomic_write_bytes(args.out, blob.encode())
    print(f"-> {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
