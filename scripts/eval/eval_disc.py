#!/usr/bin/env python
"""Evaluate disc mode (detect_rings.py --pith) on the UruDendro disc F02b against CS-TRD's ring polygons.

Not part of the test suite: the image and the labels are read from DATA/disc_urudendro_F02b/ (default
../shared/data next to the checkout) and never copied (image licence unclear, labels AGPL). The labels are CS-TRD's
*automatic* detection (labelme JSON: 22 closed polygons of 360 vertices, one per ray of its 360-ray web; "center"
is the pith as [row, col]) - a weak label, CS-TRD itself scores P 0.95 R 0.86 F 0.89 against humans on UruDendro.

For each transect angle the labelled boundaries are the radii where the ray from the pith crosses each polygon
(first crossing); CS-TRD's innermost polygon (radius ~6 px) outlines the pith and is left out unless
--keep-pith-polygon (a CooRecorder measurement also starts at the pith, which is not a boundary). Detections and
labels are matched one-to-one by radius along the transect (torch_appearance.rings.dendro.match_boundaries) at
each tolerance. Prints a table per transect and the pooled
sensitivity / precision / F1, writes them as JSON and (with --overlay) a PNG of the disc with the labels (green
ticks) and the detections (red ticks) along every transect.

Example:
    python scripts/eval/eval_disc.py --angles 0,45,90,135,180,225,270,315 --out /tmp/disc_eval.json --overlay /tmp/d.png
"""
import argparse
import json
import math
import os
import sys
import time

import cv2
import numpy as np

from torch_appearance.io import atomic_write_bytes, read_image
from torch_appearance.rings.dendro import match_boundaries
from torch_appearance.rings.disc import detect_disc_boundaries
from torch_appearance.rings.pith import detect_pith

PROG = "eval_disc.py"
DEFAULT_DATA = os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "..", "shared", "data")
DISC = ("disc_urudendro_F02b", "F02b.png", "F02b_cstrd_detection.json")


def polygon_radii(polygons, pith, angle_deg):
    """Sorted radii (px) where the ray from ``pith`` at ``angle_deg`` first crosses each closed polygon."""
    th = math.radians(angle_deg)
    u = np.array([math.cos(th), math.sin(th)])
    n = np.array([-u[1], u[0]])
    out = []
    for poly in polygons:
        q = np.vstack([poly, poly[:1]]) - pith
        sd, t = q @ n, q @ u
        i = np.nonzero(np.sign(sd[:-1]) * np.sign(sd[1:]) <= 0)[0]
        i = i[sd[i] != sd[i + 1]]
        tt = t[i] + sd[i] / (sd[i] - sd[i + 1]) * (t[i + 1] - t[i])
        tt = tt[tt > 0]
        if len(tt):
            out.append(float(tt.min()))
    return np.sort(np.array(out))


def load_labels(path):
    """``(pith (2,) x, y, [polygon (360, 2) x, y])`` of a CS-TRD labelme JSON."""
    with open(path) as f:
        j = json.load(f)
    try:
        row, col = j["center"]
        polys = [np.asarray(s["points"], dtype=np.float64).reshape(-1, 2) for s in j["shapes"]]
    except (KeyError, TypeError, ValueError) as e:
        raise ValueError(f"{path!r} is not a CS-TRD labelme JSON with 'center' and polygon 'shapes': {e}") from None
    return np.array([col, row], dtype=np.float64), polys


def evaluate(data, angles, tolerances=(3.0, 5.0), keep_pith_polygon=False, pith_offset=(0.0, 0.0),
             pith_mode="labels", **kw):
    """Run disc mode on F02b and match against the polygons. CS-TRD's innermost polygon (mean radius < 12 px)
    outlines the pith, not a ring boundary, and is left out unless ``keep_pith_polygon``. The detector gets the
    labels' pith plus ``pith_offset`` (px; a user's click error), or (``pith_mode="auto"``) the pith it finds
    itself (:func:`~torch_appearance.rings.pith.detect_pith`, timed with the detection); the labels are the polygon
    crossings of the transects actually analysed. Returns ``(rgb, res, labels, rows, pooled, seconds, pith_info)``
    with ``pith_info`` the pith used, the labels' pith and the distance between them."""
    rgb = read_image(os.path.join(data, DISC[0], DISC[1]), space="srgb", name="image")
    pith, polys = load_labels(os.path.join(data, DISC[0], DISC[2]))
    if not keep_pith_polygon:
        polys = [q for q in polys if np.linalg.norm(q - pith, axis=1).mean() >= 12.0]
    t0 = time.perf_counter()
    if pith_mode == "auto":
        given = detect_pith(rgb).xy
    else:
        given = pith + np.asarray(pith_offset, dtype=np.float64)
    res = detect_disc_boundaries(rgb, given, angles_deg=angles, **kw)
    seconds = time.perf_counter() - t0
    radius = max((float(np.linalg.norm(q - pith, axis=1).mean()) for q in polys), default=float("nan"))
    pith_info = dict(mode=pith_mode, xy=[float(v) for v in given], labels_xy=[float(v) for v in pith],
                     error_px=float(np.linalg.norm(given - pith)), radius_px=radius)
    rows, labels = [], []
    for deg, tr in zip(res.angles_deg, res.transects):
        lab = polygon_radii(polys, given, deg)  # the label polygons crossed by the transect actually analysed
        labels.append(lab)
        row = dict(angle_deg=float(deg), detected=len(tr.points), labelled=len(lab))
        for tol in tolerances:
            m = match_boundaries(tr.info["radius_px"], lab, tol)
            row[f"tol{tol:g}"] = {k: m[k] for k in ("sensitivity", "precision", "f1", "matched", "mean_error_px")}
            inf = [i for i, kind in enumerate(tr.info["kind"]) if kind == "inferred"]
            row[f"tol{tol:g}"]["inferred_on_label"] = len(set(inf) & {int(i) for i, _ in m["pairs"]})
        row["inferred"] = tr.info["kind"].count("inferred")
        rows.append(row)
    pooled = {}
    for tol in tolerances:
        m = sum(r[f"tol{tol:g}"]["matched"] for r in rows)
        nd, nl = sum(r["detected"] for r in rows), sum(r["labelled"] for r in rows)
        s, p = m / max(nl, 1), m / max(nd, 1)
        pooled[f"tol{tol:g}"] = dict(sensitivity=s, precision=p, f1=2 * s * p / (s + p) if s + p else 0.0,
                                     matched=m, detected=nd, labelled=nl)
    return rgb, res, labels, rows, pooled, seconds, pith_info


def overlay(rgb, res, labels):
    img = np.ascontiguousarray((np.clip(rgb, 0, 1) * 255 + 0.5).astype(np.uint8)[..., ::-1])
    c = res.pith
    for deg, tr, lab, end in zip(res.angles_deg, res.transects, labels, res.ends):
        th = math.radians(deg)
        u, n = np.array([math.cos(th), math.sin(th)]), np.array([-math.sin(th), math.cos(th)])
        cv2.line(img, tuple(np.round(c).astype(int)), tuple(np.round(end).astype(int)), (255, 255, 0), 1)
        for r in lab:  # labels on one side of the transect, detections on the other
            p = c + r * u
            cv2.line(img, tuple(np.round(p).astype(int)), tuple(np.round(p + 7 * n).astype(int)), (0, 160, 0), 2)
        for r, kind in zip(tr.info["radius_px"], tr.info["kind"]):  # inferred from the neighbours: orange
            p = c + r * u
            col = (0, 140, 255) if kind == "inferred" else (0, 0, 255)
            cv2.line(img, tuple(np.round(p).astype(int)), tuple(np.round(p - 7 * n).astype(int)), col, 2)
    ok, buf = cv2.imencode(".png", img)
    if not ok:
        raise ValueError("could not encode the overlay")
    return buf.tobytes()


def main(argv=None):
    p = argparse.ArgumentParser(prog=PROG, description=__doc__.split("\n\n")[0], epilog=__doc__.split("\n\n", 1)[1],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", default=DEFAULT_DATA, help="folder holding disc_urudendro_F02b/ (default: "
                                                        "../shared/data next to the checkout)")
    p.add_argument("--angles", default="0,45,90,135,180,225,270,315",
                   help="transect angles in degrees, from +x towards +y (default: %(default)s)")
    p.add_argument("--edge", action="store_true", help="report the disc edge as the last boundary")
    p.add_argument("--half-width", type=int, default=16, help="strip half-width in px (default: %(default)s)")
    p.add_argument("--edge-level", type=float, default=1.0,
                   help="boundary at this fraction of the steepest V rise on its latewood side; 1 = the steepest "
                        "point (default: %(default)s)")
    p.add_argument("--pith", choices=("labels", "auto"), default="labels",
                   help="pith given to the detector: the labels' (plus --pith-offset) or found automatically "
                        "(default: %(default)s)")
    p.add_argument("--no-link", action="store_true",
                   help="do not link the transects (no rings inferred from the neighbouring transects)")
    p.add_argument("--helpers", type=int, default=1,
                   help="helper transects between neighbouring transects when linking (default: %(default)s)")
    p.add_argument("--pith-offset", default="0,0",
                   help="DX,DY px added to the pith given to the detector (click error study; default: %(default)s)")
    p.add_argument("--keep-pith-polygon", action="store_true",
                   help="also count CS-TRD's innermost polygon (the outline of the pith) as a boundary")
    p.add_argument("--out", default="disc_eval.json", help="output JSON (default: %(default)s)")
    p.add_argument("--overlay", default=None,
                   help="optional overlay PNG (labels green, detections red, inferred from the neighbours orange)")
    args = p.parse_args(argv)
    try:
        angles = [float(a) for a in args.angles.split(",")]
    except ValueError:
        print(f"{PROG}: error: --angles must be comma-separated numbers; got {args.angles!r}", file=sys.stderr)
        return 2
    try:
        offset = [float(a) for a in args.pith_offset.split(",")]
        if len(offset) != 2:
            raise ValueError
        if args.pith == "auto" and any(offset):
            print(f"{PROG}: error: --pith-offset applies to --pith labels only", file=sys.stderr)
            return 2
    except ValueError:
        print(f"{PROG}: error: --pith-offset must be DX,DY; got {args.pith_offset!r}", file=sys.stderr)
        return 2
    missing = [f for f in (os.path.join(args.data, DISC[0], DISC[1]), os.path.join(args.data, DISC[0], DISC[2]))
               if not os.path.isfile(f)]
    if missing:
        print(f"{PROG}: error: data missing under {args.data!r}: {', '.join(missing)}", file=sys.stderr)
        return 2
    for name, path in (("--out", args.out), ("--overlay", args.overlay)):
        if path is not None and not os.path.isdir(os.path.dirname(os.path.abspath(path))):
            print(f"{PROG}: error: {name}: folder of {path!r} does not exist", file=sys.stderr)
            return 2
    from torch_appearance.progress import progress_bar

    def progress(k, n):
        bar.total = n
        bar.update(1)

    with progress_bar(total=len(angles), desc="transects", unit="transect") as bar:
        try:
            rgb, res, labels, rows, pooled, seconds, pith_info = evaluate(
                args.data, angles, keep_pith_polygon=args.keep_pith_polygon, pith_offset=offset,
                pith_mode=args.pith, include_edge=args.edge, half_width=args.half_width, edge_level=args.edge_level,
                link=not args.no_link, helpers=args.helpers, progress=progress)
        except (OSError, ValueError) as e:
            print(f"{PROG}: error: {e}", file=sys.stderr)
            return 2
    print(f"{'angle':>6s} {'det':>4s} {'lab':>4s}   {'S@3':>5s} {'P@3':>5s} {'F1@3':>5s}   {'S@5':>5s} {'P@5':>5s} "
          f"{'F1@5':>5s}")
    for r in rows + [dict(angle_deg="pooled", detected=pooled["tol3"]["detected"],
                          labelled=pooled["tol3"]["labelled"], **pooled)]:
        a, b = r["tol3"], r["tol5"]
        ang = f"{r['angle_deg']:6.1f}" if not isinstance(r["angle_deg"], str) else f"{r['angle_deg']:>6s}"
        print(f"{ang} {r['detected']:4d} {r['labelled']:4d}   {a['sensitivity']:5.2f} {a['precision']:5.2f} "
              f"{a['f1']:5.2f}   {b['sensitivity']:5.2f} {b['precision']:5.2f} {b['f1']:5.2f}")
    inferred = sum(tr.info["kind"].count("inferred") for tr in res.transects)
    moved = sum(len(tr.info.get("moved_px", [])) for tr in res.transects)
    closed = sum(sum(tr.info.get("closed", [])) for tr in res.transects)
    dropped = sum(len(tr.info.get("dropped_px", [])) for tr in res.transects)
    print(f"pith ({args.pith}) {pith_info['xy'][0]:.1f},{pith_info['xy'][1]:.1f}; labels' pith "
          f"{pith_info['labels_xy'][0]:.1f},{pith_info['labels_xy'][1]:.1f}: {pith_info['error_px']:.1f} px apart = "
          f"{100 * pith_info['error_px'] / pith_info['radius_px']:.2f} % of the outermost polygon's mean radius")
    on = sum(r["tol5"]["inferred_on_label"] for r in rows)
    linked = (f"{inferred} rings inferred ({on} on a label at 5 px; {closed} from closed rings round the pith), "
              f"{moved} moved, {dropped} dropped between closed rings")
    print(f"linked: {'no' if args.no_link else linked}")
    print(f"detection time {seconds:.1f} s for {len(angles)} transects (pith included); filtered "
          f"{res.info['filtered_px']} px ({100.0 * res.info['filtered_px'] / res.info['image_px']:.1f} % of the "
          f"image)")
    blob = dict(data=os.path.abspath(os.path.join(args.data, DISC[0])), label="CS-TRD automatic polygons (weak)",
                angles_deg=angles, edge=args.edge, half_width=args.half_width, edge_level=args.edge_level,
                keep_pith_polygon=args.keep_pith_polygon, pith_offset=offset, pith=pith_info, link=not args.no_link,
                helpers=args.helpers, inferred=inferred, moved=moved, closed=closed, dropped=dropped, seconds=seconds,
                transects=rows,
                pooled=pooled, filtered_px=res.info["filtered_px"], image_px=res.info["image_px"])
    atomic_write_bytes(args.out, json.dumps(blob, indent=1, default=float).encode())
    if args.overlay:
        atomic_write_bytes(args.overlay, overlay(rgb, res, labels))
    print(f"-> {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
