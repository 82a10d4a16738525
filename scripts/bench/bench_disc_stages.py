#!/usr/bin/env python
"""Disc mode's cost per stage on one photo: four transects (0, 90, 180, 270 degrees), the automatic pith by default,
as ``ta-detect-rings DISC --mode disc`` runs them. Prints one JSON line: the total CPU and wall seconds, and per stage
(the pith, the strips' orientation, the curved Gabor filter and its parts, the linking, the whole rings) the CPU
seconds (all threads, ``time.process_time``), wall seconds and calls, inclusive: a stage's figure holds the stages
called inside it (indented names). The stages are timed by wrapping the module functions that run them; a function
an older commit lacks is left out.

The TRAS photos carry burned-in red lines: give the inpainted photo that ``scripts/eval/eval_disc_lodo.py`` caches
(``ta_lodo_<disc>_dots_inpainted.npy`` with ``--inpaint-dots``). To compare with an older commit, run this script
with ``PYTHONPATH`` on an export of that commit's package (``git archive <commit> torch_appearance | tar -x -C
/tmp/old`` plus the built ``_C`` extension copied beside it). On a shared machine compare CPU seconds of runs made
one after the other, not wall seconds.

Example:
    python scripts/bench/bench_disc_stages.py /tmp/ta_lodo_C13C_dots_inpainted.npy
    python scripts/bench/bench_disc_stages.py /tmp/ta_lodo_C13C_dots_inpainted.npy --pith 1417.07,1543.71
"""
import argparse
import functools
import json
import os
import sys
import time

import numpy as np

import torch_appearance.rings.consistency as consistency
import torch_appearance.rings.disc as disc
import torch_appearance.rings.gabor as gabor
import torch_appearance.rings.pith as pith_module
import torch_appearance.rings.ring_polygons as ring_polygons
from torch_appearance.io import read_image

PROG = "bench_disc_stages.py"

#: (module, function, label): the stages timed; indented labels run inside the one above them
STAGES = [
    (pith_module, "detect_pith", "detect_pith"),
    (disc, "_polar_sample", "_polar_sample"),
    (disc, "hsv_value", "hsv_value"),
    (disc, "_strip_orientation", "_strip_orientation"),
    (disc, "_strip_boundaries", "_strip_boundaries (Gabor included)"),
    (disc, "curved_gabor", "  curved_gabor"),
    (gabor, "orientation_from_phase", "    curved_gabor: orientation_from_phase"),
    (gabor, "_dominant_period", "    curved_gabor: _dominant_period"),
    (consistency, "blurred_value", "blurred_value"),
    (consistency, "link_transects", "link_transects"),
    (consistency, "closed_rings", "  link_transects: closed_rings"),
    (consistency, "trace_curves", "  trace_curves (linking and closed rings)"),
    (ring_polygons, "trace_whole_rings", "trace_whole_rings"),
    (ring_polygons, "_band_trace", "  trace_whole_rings: _band_trace"),
    # the edge maps: _sector_edges where it exists (sector_edges calls it), else sector_edges
    (consistency, "_sector_edges" if hasattr(consistency, "_sector_edges") else "sector_edges",
     "  sector edge maps (linking, closed and whole rings)"),
    (consistency, "_radial_derivative", "  rays' radial derivative (all)"),
]


def _timed(fn, label, acc):
    @functools.wraps(fn)
    def run(*args, **kwargs):
        c0, t0 = time.process_time(), time.perf_counter()
        try:
            return fn(*args, **kwargs)
        finally:
            e = acc.setdefault(label, [0.0, 0.0, 0])
            e[0] += time.process_time() - c0
            e[1] += time.perf_counter() - t0
            e[2] += 1
    return run


def main(argv=None):
    p = argparse.ArgumentParser(prog=PROG, description=__doc__.split("\n\n")[0], epilog=__doc__.split("\n\n", 1)[1],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("image", help="disc photo (or a .npy of an (H, W, 3) float image in [0, 1])")
    p.add_argument("--pith", default="auto", help="'auto' (default) or X,Y in pixels")
    args = p.parse_args(argv)
    if not os.path.isfile(args.image):
        p.error(f"image: {args.image!r} is not a file")
    if args.pith == "auto":
        pith = "auto"
    else:
        try:
            pith = tuple(float(v) for v in args.pith.split(","))
        except ValueError:
            pith = ()
        if len(pith) != 2:
            p.error(f"--pith: expected 'auto' or X,Y in pixels, got {args.pith!r}")
    rgb = np.load(args.image) if args.image.endswith(".npy") else read_image(args.image, space="srgb", name="image")
    acc = {}
    for module, name, label in STAGES:
        fn = getattr(module, name, None)
        if fn is not None:
            setattr(module, name, _timed(fn, label, acc))
    t0, c0 = time.perf_counter(), time.process_time()
    res = disc.detect_disc_boundaries(rgb, pith, angles_deg=[0, 90, 180, 270])
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    print(json.dumps(dict(image=os.path.basename(args.image), pith=args.pith,
                          package=os.path.dirname(os.path.dirname(disc.__file__)), cpu_s=round(cpu, 2), wall_s=round(wall, 2),
                          load=os.getloadavg(), boundaries=[len(t.points) for t in res.transects],
                          stages={label: dict(cpu_s=round(e[0], 2), wall_s=round(e[1], 2), calls=e[2])
                                  for label, e in acc.items()})))
    return 0


if __name__ == "__main__":
    sys.exit(main())
