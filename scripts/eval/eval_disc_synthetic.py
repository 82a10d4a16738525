#!/usr/bin/env python
"""Disc mode on the synthetic disc suite of :mod:`torch_appearance.rings.synthetic_discs` (a generator written apart
from the detector's own ``rings.synthetic``): radial F1 at 3 and 5 px per condition, with the true pith and with
the automatic one.

Every condition is one 560 x 560 disc of 20 rings whose widths shrink 10x from the pith to the bark; each adds one
thing real discs vary (``CONDITIONS``: faint outer latewood, blur, JPEG, uneven light, dark / light bark, a crack,
an off-centre pith). Four transects (``--angles``) run from the pith; the true boundaries are where the rings cross
them (all 20, the last one the wood's edge at the bark, as a CooRecorder user marks it). Detections and truth are
matched one-to-one by radius (:func:`~torch_appearance.rings.evaluation.match_boundaries`).

Example:
    python scripts/eval/eval_disc_synthetic.py --out scripts/eval/measured/disc_synthetic.json
"""
import argparse
import json
import math
import sys
import time

import numpy as np

from torch_appearance.io import atomic_write_bytes
from torch_appearance.rings.disc import detect_disc_boundaries
from torch_appearance.rings.evaluation import match_boundaries
from torch_appearance.rings.synthetic_discs import CONDITIONS, suite

PROG = "eval_disc_synthetic.py"
TOLERANCES = (3.0, 5.0)


def score_disc(disc, pith, angles, **kw):
    """Pooled radial matching of one synthetic disc: ``dict(tol3=..., tol5=..., seconds, pith_error_px)``."""
    t0 = time.perf_counter()
    res = detect_disc_boundaries(disc.rgb, pith, angles_deg=angles, **kw)
    seconds = time.perf_counter() - t0
    out = dict(seconds=seconds, pith_error_px=float(np.linalg.norm(res.pith - disc.pith)))
    for tol in TOLERANCES:
        m = d = n = 0
        for tr, deg in zip(res.transects, res.angles_deg):
            # truth along the transect's ray from the pith used (the detector's), read off the true ring curves
            u = np.array([math.cos(math.radians(deg)), math.sin(math.radians(deg))])
            truth = _crossings(disc, res.pith, u)
            det = np.asarray(tr.info["radius_px"], np.float64)
            r = match_boundaries(det, truth, tol)
            m, d, n = m + r["matched"], d + r["detected"], n + r["labelled"]
        s, p = m / max(n, 1), m / max(d, 1)
        out[f"tol{tol:g}"] = dict(sensitivity=s, precision=p, f1=2 * s * p / (s + p) if s + p else 0.0, matched=m,
                                  detected=d, labelled=n)
    return out


def _crossings(disc, origin, u, step=0.25):
    """Radii from ``origin`` along unit ``u`` where the ray crosses each true ring boundary (first crossing)."""
    t = np.arange(0.0, 2 * max(disc.rgb.shape[:2]), step)
    xy = origin[None, :] + t[:, None] * u[None, :]
    d = xy - disc.pith[None, :]
    r = np.hypot(d[:, 0], d[:, 1])
    phi = np.arctan2(d[:, 1], d[:, 0]) % (2 * math.pi)
    out = []
    for ring in disc.radii:
        b = np.interp(phi, disc.phis, ring, period=2 * math.pi)
        k = np.nonzero(r >= b)[0]
        if len(k):
            out.append(t[k[0]])
    return np.array(out)


def main(argv=None):
    p = argparse.ArgumentParser(prog=PROG, description=__doc__.split("\n\n")[0], epilog=__doc__.split("\n\n", 1)[1],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--conditions", default=",".join(CONDITIONS), help="comma-separated (default: all)")
    p.add_argument("--angles", default="20,110,200,290", help="transect angles in degrees (default: %(default)s)")
    p.add_argument("--seed", type=int, default=0, help="generator seed (default: %(default)s)")
    p.add_argument("--pith", choices=("true", "auto", "both"), default="both", help="pith used (default: both)")
    p.add_argument("--no-edge", action="store_true", help="do not report the wood's edge as the last boundary")
    p.add_argument("--no-whole-rings", action="store_true",
                   help="do not trace the rings round the disc (detect_disc_boundaries(whole_rings=False))")
    p.add_argument("--bark-gaps", type=int, default=0,
                   help="search this many gaps before the bark for skipped narrow rings "
                        "(detect_disc_boundaries(bark_gaps=...); default: %(default)s)")
    p.add_argument("--pith-edge", action="store_true",
                   help="put the pith's own edge on every transect (detect_disc_boundaries(pith_edge=True))")
    p.add_argument("--out", default="disc_synthetic.json", help="output JSON (default: %(default)s)")
    args = p.parse_args(argv)
    try:
        angles = [float(a) for a in args.angles.split(",")]
        discs = suite(args.conditions.split(","), seed=args.seed)
    except ValueError as e:
        p.error(str(e))
    modes = ("true", "auto") if args.pith == "both" else (args.pith,)
    rows = []
    print(f"{'condition':14s} {'pith':5s} {'F1@3':>5s} {'F1@5':>5s} {'S@5':>5s} {'P@5':>5s} {'pith err':>8s} {'s':>5s}")
    for name, disc in discs.items():
        for mode in modes:
            r = score_disc(disc, disc.pith if mode == "true" else "auto", angles, include_edge=not args.no_edge,
                           whole_rings=not args.no_whole_rings, pith_edge=args.pith_edge, bark_gaps=args.bark_gaps)
            rows.append(dict(condition=name, pith=mode, **r))
            print(f"{name:14s} {mode:5s} {r['tol3']['f1']:5.2f} {r['tol5']['f1']:5.2f} {r['tol5']['sensitivity']:5.2f} "
                  f"{r['tol5']['precision']:5.2f} {r['pith_error_px']:8.1f} {r['seconds']:5.1f}", flush=True)
    blob = dict(command="python scripts/eval/eval_disc_synthetic.py " + " ".join(argv or sys.argv[1:]),
                angles=angles, seed=args.seed, include_edge=not args.no_edge, whole_rings=not args.no_whole_rings,
                pith_edge=args.pith_edge, bark_gaps=args.bark_gaps, rows=rows)
    atomic_write_bytes(args.out, json.dumps(blob, indent=1).encode())
    print(f"-> {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
