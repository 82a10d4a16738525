#!/usr/bin/env python
"""Disc mode against HUMAN ring measurements: the TRAS discs C13C and C17C (CooRecorder .pos, 4 radial transects each).

Not part of the test suite: the photos and .pos files are read from DATA/disc_tras_coorecorder_dev/ (MIT, see its
README). The photos carry TRAS's automatic ring lines burned in red; they are masked (R > 120, R - G > 60,
R - B > 60, dilated by 1 px) and inpainted (OpenCV Telea) first, as the README asks.

For every disc: the pith is found automatically (``--pith auto``, the default) or taken from the human files
(``--pith human``: the mean of the four files' first points); the error of the automatic pith against the human one
is reported in px and in % of the disc radius (the mean distance of the human transects' last points). Each human
transect becomes a detector transect from the pith used towards the transect's last point, run on to the disc edge
(``detect_disc_boundaries(..., angles_deg=...)``). Detections and human points are matched one-to-one in 2D
(:func:`~torch_appearance.rings.dendro.match_boundaries`) at 3 and 5 px (``--match 2d``, the default), or by
their distances from the pith (``--match radial``: the distance from a human point to the ring boundary through
the detection, taking rings as circles about the pith). The human transects are not straight rays from the pith:
on C17C their inner points lie up to 8 px beside the ray to their last point, so a detection on the right ring
can be more than 5 px from the click in 2D; the radial match does not count that as a miss. Both pooled figures
are always printed. Prints per transect and pooled
sensitivity, precision and F1, the misses by ring index counted from the pith and from the bark, the signed offset
of matched boundaries along the transect (positive: on the bark side of the human point), the detection time, and
writes JSON plus one overlay PNG per disc (human points green on one side of the transect, detections red on the
other, the pith as a white cross, the human pith as a green one, the whole rings that close round the disc as
yellow and magenta polygons).

Example:
    python scripts/eval/eval_disc_human.py --out /tmp/human.json --overlay-dir /tmp/human
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
from torch_appearance.rings.coorecorder import read_pos
from torch_appearance.rings.dendro import match_boundaries
from torch_appearance.rings.disc import detect_disc_boundaries
from torch_appearance.rings.ring_polygons import draw_ring_polygons, ring_polygons

PROG = "eval_disc_human.py"
DEFAULT_DATA = os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "..",
                            "shared", "data")
FOLDER = "disc_tras_coorecorder_dev"
DISCS = ("C13C", "C17C")
SIDES = ("east", "north", "south", "west")
TOLERANCES = (3.0, 5.0)


def inpaint_red_lines(rgb):
    """The photo with TRAS's burned-in red lines masked and inpainted (the dataset README's recipe)."""
    u8 = (np.clip(rgb, 0, 1) * 255 + 0.5).astype(np.uint8)
    r, g, b = (u8[..., k].astype(np.int16) for k in range(3))
    mask = ((r > 120) & (r - g > 60) & (r - b > 60)).astype(np.uint8)
    mask = cv2.dilate(mask, np.ones((3, 3), np.uint8))
    bgr = cv2.inpaint(np.ascontiguousarray(u8[..., ::-1]), mask, 3, cv2.INPAINT_TELEA)
    return bgr[..., ::-1].astype(np.float32) / 255.0, int(mask.sum())


def inpaint_dark_dots(rgb, *, level=60, max_area=150, around=120):
    """The photo with small near-black blobs on the wood inpainted: max(R, G, B) < ``level`` of 255, at most
    ``max_area`` px, their 4 px surroundings brighter than ``around`` on average (the dark cloth is left alone),
    dilated by 1 px. The photos are the east transect's copies, which carry CooRecorder's measurement points as black
    dots of about 3 px exactly on the human boundaries, and a black dot of about 5 px radius on the pith."""
    from scipy import ndimage
    u8 = (np.clip(rgb, 0, 1) * 255 + 0.5).astype(np.uint8)
    v = u8.max(axis=2)
    n, lab, stats, _ = cv2.connectedComponentsWithStats((v < level).astype(np.uint8), connectivity=8)
    small = np.zeros(n, bool)
    small[1:] = stats[1:, cv2.CC_STAT_AREA] <= max_area
    near = ndimage.grey_dilation(np.where(small[lab], lab, 0), size=9)
    ring = (near > 0) & (lab == 0)
    mean = np.bincount(near[ring], weights=v[ring].astype(np.float64), minlength=n) / np.maximum(
        np.bincount(near[ring], minlength=n), 1)
    keep = small & (mean > around)
    mask = cv2.dilate(keep[lab].astype(np.uint8), np.ones((3, 3), np.uint8))
    bgr = cv2.inpaint(np.ascontiguousarray(u8[..., ::-1]), mask, 3, cv2.INPAINT_TELEA)
    return bgr[..., ::-1].astype(np.float32) / 255.0, int(mask.sum())


def load_disc(data, disc, dots=False):
    """``(rgb inpainted, {side: (pith (2,), boundaries (K, 2))})`` in pixels (``dots``: the black measurement dots
    inpainted too, :func:`inpaint_dark_dots`)."""
    folder = os.path.join(data, FOLDER)
    rgb, _ = inpaint_red_lines(read_image(os.path.join(folder, disc + ".jpg"), space="srgb", name="image"))
    if dots:
        rgb, _ = inpaint_dark_dots(rgb)
    labels = {}
    for side in SIDES:
        pos = read_pos(os.path.join(folder, f"{disc}_{side}.pos"))
        labels[side] = (pos.points_px[0].copy(), pos.points_px[1:].copy())  # point 0 is the pith (README)
    return rgb, labels


def pooled(rows, tol):
    m = sum(r[f"tol{tol:g}"]["matched"] for r in rows)
    nd, nl = sum(r["detected"] for r in rows), sum(r["labelled"] for r in rows)
    s, p = m / max(nl, 1), m / max(nd, 1)
    return dict(sensitivity=s, precision=p, f1=2 * s * p / (s + p) if s + p else 0.0, matched=m, detected=nd,
                labelled=nl)


def _match(det, lab, tol, pith, mode):
    """One-to-one matching of detections ``(N, 2)`` and human points ``(K, 2)``: in 2D, or by radius from the pith."""
    if mode == "radial":
        rd, rl = np.linalg.norm(det - pith, axis=1), np.linalg.norm(lab - pith, axis=1)
        det, lab = np.c_[rd, np.zeros_like(rd)], np.c_[rl, np.zeros_like(rl)]
    return match_boundaries(det, lab, tol)


def evaluate_disc(data, disc, pith_mode="auto", match="2d", dots=False, **kw):
    rgb, labels = load_disc(data, disc, dots)
    human_pith = np.mean([p for p, _ in labels.values()], axis=0)
    radius = float(np.mean([np.linalg.norm(b[-1] - human_pith) for _, b in labels.values()]))
    t0 = time.perf_counter()
    if pith_mode == "auto":
        from torch_appearance.rings.pith import detect_pith
        est = detect_pith(rgb)
        pith, sigma = est.xy, est.sigma_px
    else:
        pith, sigma = human_pith, float("nan")
    t_pith = time.perf_counter() - t0
    angles = [math.degrees(math.atan2(*(b[-1] - pith)[::-1])) % 360.0 for _, b in labels.values()]
    res = detect_disc_boundaries(rgb, pith, angles_deg=angles, **kw)
    seconds = time.perf_counter() - t0
    rings = ring_polygons(res)
    rows = []
    for side, tr, deg in zip(SIDES, res.transects, angles):
        lab = labels[side][1]
        det = np.asarray(tr.points, np.float64).reshape(-1, 2)
        u = np.array([math.cos(math.radians(deg)), math.sin(math.radians(deg))])
        row = dict(disc=disc, side=side, angle_deg=deg, detected=len(det), labelled=len(lab))
        for tol in TOLERANCES:
            other = "radial" if match == "2d" else "2d"
            mo = _match(det, lab, tol, pith, other)
            row[f"{other}_tol{tol:g}"] = dict(matched=mo["matched"])
            m = _match(det, lab, tol, pith, match)
            pairs = np.asarray(m["pairs"], int).reshape(-1, 2)
            missed = sorted(set(range(len(lab))) - set(pairs[:, 1].tolist()))
            row[f"tol{tol:g}"] = dict(sensitivity=m["sensitivity"], precision=m["precision"], f1=m["f1"],
                                      matched=m["matched"], missed_from_pith=missed,
                                      missed_from_bark=[len(lab) - 1 - i for i in missed],
                                      false=sorted(set(range(len(det))) - set(pairs[:, 0].tolist())),
                                      offset_px=[float((det[i] - lab[j]) @ u) for i, j in pairs])
            if tol == 5.0:  # the boundaries inferred from the neighbouring transects, and the human ring each is on
                ring_of = {int(i): int(j) for i, j in pairs}
                kinds = tr.info["kind"]
                row["inferred"] = [dict(radius_px=float(tr.info["radius_px"][i]), human_ring=ring_of.get(i),
                                        closed=bool(tr.info["closed"][i]))
                                   for i in range(len(kinds)) if kinds[i] == "inferred"]
                rl = np.linalg.norm(lab - pith, axis=1)  # dropped between closed rings: the human ring within 5 px
                row["dropped"] = [dict(radius_px=float(x), human_ring=int(np.argmin(np.abs(rl - x)))
                                       if np.abs(rl - x).min() <= tol else None)
                                  for x in tr.info.get("dropped_px", [])]
                row["moved_px"] = [list(map(float, m)) for m in tr.info.get("moved_px", [])]
        rows.append(row)
    return dict(disc=disc, rgb=rgb, res=res, labels=labels, rows=rows, pith=pith, pith_sigma_px=sigma, rings=rings,
                n_rings_closed=len(rings),
                human_pith=human_pith, pith_error_px=float(np.linalg.norm(pith - human_pith)), radius_px=radius,
                seconds=seconds, pith_seconds=t_pith)


def overlay(ev):
    img = np.ascontiguousarray((np.clip(ev["rgb"], 0, 1) * 255 + 0.5).astype(np.uint8)[..., ::-1])
    res, c = ev["res"], ev["res"].pith
    draw_ring_polygons(img, ev["rings"])
    t = max(1, round(max(img.shape[:2]) / 1200))
    for side, tr, end, deg in zip(SIDES, res.transects, res.ends, res.angles_deg):
        th = math.radians(deg)
        n = np.array([-math.sin(th), math.cos(th)])
        cv2.line(img, tuple(np.round(c).astype(int)), tuple(np.round(end).astype(int)), (255, 255, 0), t)
        for q in ev["labels"][side][1]:
            cv2.line(img, tuple(np.round(q).astype(int)), tuple(np.round(q + 14 * n).astype(int)), (0, 170, 0), 2 * t)
        for q in tr.points:
            cv2.line(img, tuple(np.round(q).astype(int)), tuple(np.round(q - 14 * n).astype(int)), (0, 0, 255), 2 * t)
    cv2.drawMarker(img, tuple(np.round(ev["human_pith"]).astype(int)), (0, 170, 0), cv2.MARKER_CROSS, 40, 2 * t)
    cv2.drawMarker(img, tuple(np.round(c).astype(int)), (255, 255, 255), cv2.MARKER_CROSS, 40, t)
    ok, buf = cv2.imencode(".png", img)
    if not ok:
        raise ValueError("could not encode the overlay")
    return buf.tobytes()


def main(argv=None):
    p = argparse.ArgumentParser(prog=PROG, description=__doc__.split("\n\n")[0], epilog=__doc__.split("\n\n", 1)[1],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", default=DEFAULT_DATA, help=f"folder holding {FOLDER}/ (default: ../shared/data next to "
                                                        "the checkout)")
    p.add_argument("--pith", choices=("auto", "human"), default="auto", help="pith used (default: %(default)s)")
    p.add_argument("--half-width", type=int, default=16, help="strip half-width in px (default: %(default)s)")
    p.add_argument("--edge-level", type=float, default=1.0,
                   help="boundary where dV/dt has fallen to this fraction of its peak on the latewood side; 1 = the "
                        "steepest point (default: %(default)s)")
    p.add_argument("--include-edge", action="store_true",
                   help="count the wood's edge at the bark as the outermost boundary (CooRecorder's last point is the "
                        "outer edge of the last ring, at the bark)")
    p.add_argument("--no-link", action="store_true",
                   help="do not link the transects (no rings inferred from the neighbouring transects)")
    p.add_argument("--inpaint-dots", action="store_true",
                   help="also inpaint the black measurement dots burned into the photos on the east transect's human "
                        "points and on the pith (a label leak; inpaint_dark_dots)")
    p.add_argument("--no-closed", action="store_true",
                   help="do not trace the rings near the pith as closed curves (detect_disc_boundaries(closed=False))")
    p.add_argument("--no-whole-rings", action="store_true",
                   help="do not trace the rings round the disc (detect_disc_boundaries(whole_rings=False))")
    p.add_argument("--pith-edge", action="store_true",
                   help="put the pith's own edge on every transect (detect_disc_boundaries(pith_edge=True))")
    p.add_argument("--helpers", type=int, default=1,
                   help="helper transects between neighbouring transects when linking (default: %(default)s)")
    p.add_argument("--match", choices=("2d", "radial"), default="2d",
                   help="match detections and human points in 2D, or by their distance from the pith (the ring "
                        "through the detection; docstring) (default: %(default)s)")
    p.add_argument("--out", default="disc_human_eval.json", help="output JSON (default: %(default)s)")
    p.add_argument("--overlay-dir", default=None, help="folder for one overlay PNG per disc")
    args = p.parse_args(argv)
    missing = [os.path.join(args.data, FOLDER, f) for d in DISCS for f in [d + ".jpg"] + [f"{d}_{s}.pos" for s in SIDES]
               if not os.path.isfile(os.path.join(args.data, FOLDER, f))]
    if missing:
        p.error(f"data missing: {', '.join(missing)}")
    if args.overlay_dir is not None and not os.path.isdir(args.overlay_dir):
        p.error(f"--overlay-dir: {args.overlay_dir!r} is not a folder")
    evs = []
    for disc in DISCS:
        try:
            evs.append(evaluate_disc(args.data, disc, args.pith, args.match, args.inpaint_dots,
                                     half_width=args.half_width,
                                     edge_level=args.edge_level, include_edge=args.include_edge,
                                     link=not args.no_link, helpers=args.helpers, closed=not args.no_closed,
                                     whole_rings=not args.no_whole_rings, pith_edge=args.pith_edge))
        except (OSError, ValueError) as e:
            print(f"{PROG}: error: {disc}: {e}", file=sys.stderr)
            return 2
    head = f"{'transect':14s} {'det':>4s} {'lab':>4s}   {'S@3':>5s} {'P@3':>5s} {'F1@3':>5s}   {'S@5':>5s} {'P@5':>5s} " \
           f"{'F1@5':>5s}  missed @5 (from pith)"
    print(head)
    rows = [r for ev in evs for r in ev["rows"]]
    for r in rows:
        a, b = r["tol3"], r["tol5"]
        print(f"{r['disc'] + ' ' + r['side']:14s} {r['detected']:4d} {r['labelled']:4d}   {a['sensitivity']:5.2f} "
              f"{a['precision']:5.2f} {a['f1']:5.2f}   {b['sensitivity']:5.2f} {b['precision']:5.2f} {b['f1']:5.2f}  "
              f"{b['missed_from_pith']}")
    total = {f"tol{t:g}": pooled(rows, t) for t in TOLERANCES}
    a, b = total["tol3"], total["tol5"]
    print(f"{'pooled':14s} {b['detected']:4d} {b['labelled']:4d}   {a['sensitivity']:5.2f} {a['precision']:5.2f} "
          f"{a['f1']:5.2f}   {b['sensitivity']:5.2f} {b['precision']:5.2f} {b['f1']:5.2f}")
    other = "radial" if args.match == "2d" else "2d"
    total_other = {}
    for t in TOLERANCES:
        key = f"{other}_tol{t:g}"
        total_other[f"tol{t:g}"] = pooled([dict(r, **{f"tol{t:g}": r[key]}) for r in rows], t)
    a, b = total_other["tol3"], total_other["tol5"]
    print(f"{'pooled, ' + other:14s} {b['detected']:4d} {b['labelled']:4d}   {a['sensitivity']:5.2f} "
          f"{a['precision']:5.2f} {a['f1']:5.2f}   {b['sensitivity']:5.2f} {b['precision']:5.2f} {b['f1']:5.2f}")
    from_pith, from_bark = np.zeros(40, int), np.zeros(40, int)
    for r in rows:
        for i in r["tol5"]["missed_from_pith"]:
            from_pith[min(i, 39)] += 1
        for i in r["tol5"]["missed_from_bark"]:
            from_bark[min(i, 39)] += 1
    print("misses @5 px by ring index from the pith (0 = innermost):",
          {i: int(v) for i, v in enumerate(from_pith) if v})
    print("misses @5 px by ring index from the bark (0 = outermost):",
          {i: int(v) for i, v in enumerate(from_bark) if v})
    linked = [(r, x) for r in rows for x in r["inferred"]]
    if not args.no_link:
        on = sum(x["human_ring"] is not None for _, x in linked)
        print(f"inferred from the neighbouring transects: {len(linked)}, {on} on a human ring at 5 px; moved onto "
              f"their ring's curve: {sum(len(r['moved_px']) for r in rows)}")
        def ring(x):
            return "no human ring" if x["human_ring"] is None else f"human ring {x['human_ring']}"
        for r in rows:
            if r["inferred"]:
                print(f"  {r['disc']} {r['side']}: " + ", ".join(
                    f"r {x['radius_px']:.0f} px ({ring(x)}{', closed ring' if x['closed'] else ''})"
                    for x in r["inferred"]))
        dropped = [(r, x) for r in rows for x in r["dropped"]]
        print(f"dropped between closed rings: {len(dropped)}, {sum(x['human_ring'] is not None for _, x in dropped)} "
              f"within 5 px (radially) of a human ring" + "".join(
                  f"\n  {r['disc']} {r['side']}: r {x['radius_px']:.0f} px ({ring(x)})" for r, x in dropped))
    offsets = np.array([o for r in rows for o in r["tol5"]["offset_px"]])
    if len(offsets):
        print(f"matched offset along the transect (+: bark side of the human point): median {np.median(offsets):+.2f} "
              f"px, mean {offsets.mean():+.2f} px")
    for ev in evs:
        print(f"{ev['disc']}: pith {ev['pith'][0]:.1f},{ev['pith'][1]:.1f} ({args.pith}; standard error "
              f"{ev['pith_sigma_px']:.1f} px), human {ev['human_pith'][0]:.1f},{ev['human_pith'][1]:.1f}: error "
              f"{ev['pith_error_px']:.1f} px = {100 * ev['pith_error_px'] / ev['radius_px']:.2f} % of the radius "
              f"{ev['radius_px']:.0f} px; {ev['seconds']:.1f} s for 4 transects (pith {ev['pith_seconds']:.1f} s); "
              f"{ev['n_rings_closed']} whole rings closed round the disc")
        if args.overlay_dir is not None:
            atomic_write_bytes(os.path.join(args.overlay_dir, f"{ev['disc']}_overlay.png"), overlay(ev))
    blob = dict(pith=args.pith, match=args.match, inpaint_dots=args.inpaint_dots, pooled_other={other: total_other},
                half_width=args.half_width,
                edge_level=args.edge_level, include_edge=args.include_edge,
                pooled=total, transects=rows,
                discs=[{k: ev[k] for k in ("disc", "pith", "pith_sigma_px", "human_pith", "pith_error_px", "radius_px",
                                           "seconds", "pith_seconds", "n_rings_closed")} for ev in evs])
    atomic_write_bytes(args.out, json.dumps(blob, indent=1, default=lambda o: np.asarray(o).tolist()).encode())
    print(f"-> {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
