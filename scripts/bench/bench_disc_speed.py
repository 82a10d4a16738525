#!/usr/bin/env python
"""Disc mode's cost on one photo: four transects (0, 90, 180, 270 degrees) with the automatic pith, as
``ta-detect-rings DISC --mode disc`` runs them. Prints one JSON line: wall seconds, CPU seconds of the process (all
threads; on a shared machine the steadier figure), the pixels passed to the Gabor filter (independent of the
machine's load) and the boundaries per transect.

The TRAS photos carry burned-in red lines: give the inpainted photo that ``scripts/eval/eval_disc_lodo.py`` caches
(``--cache DIR`` holds ``ta_lodo_<disc>_inpainted.npy``). To compare with an older commit, run this script with ``PYTHONPATH`` on an
export of that commit's package (``git archive <commit> torch_appearance | tar -x -C /tmp/old`` plus the built
``_C`` extension copied beside it).

Example:
    python scripts/bench/bench_disc_speed.py /tmp/ta_lodo_C13C_inpainted.npy
"""
import argparse
import json
import os
import sys
import time

import numpy as np

import torch_appearance
from torch_appearance.io import read_image
from torch_appearance.rings.disc import detect_disc_boundaries

PROG = "bench_disc_speed.py"


def main(argv=None):
    p = argparse.ArgumentParser(prog=PROG, description=__doc__.split("\n\n")[0], epilog=__doc__.split("\n\n", 1)[1],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("image", help="disc photo (or a .npy of an (H, W, 3) float image in [0, 1])")
    p.add_argument("--no-whole-rings", action="store_true",
                   help="do not trace the rings round the disc (detect_disc_boundaries(whole_rings=False))")
    args = p.parse_args(argv)
    if not os.path.isfile(args.image):
        p.error(f"image: {args.image!r} is not a file")
    if args.image.endswith(".npy"):
        rgb = np.load(args.image)
    else:
        rgb = read_image(args.image, space="srgb", name="image")
    t0, c0 = time.perf_counter(), time.process_time()
    res = detect_disc_boundaries(rgb, "auto", angles_deg=[0, 90, 180, 270], whole_rings=not args.no_whole_rings)
    print(json.dumps(dict(package=os.path.dirname(torch_appearance.__file__), wall_s=time.perf_counter() - t0,
                          cpu_s=time.process_time() - c0, filtered_px=res.info["filtered_px"],
                          filter_calls=res.info["filter_calls"], load=os.getloadavg(),
                          link_s=res.info["link_seconds"], whole_rings_s=res.info["whole_rings_seconds"],
                          boundaries=[len(t.points) for t in res.transects])))
    return 0


if __name__ == "__main__":
    sys.exit(main())
