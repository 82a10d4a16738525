#!/usr/bin/env python
"""Full stiff-case sweep of the tracer: σ_t ∈ {0, 1e-6, 1e-2, 1, 1e2, 1e4} mm⁻¹ × albedo ∈ {0, 1e-3, 0.5, 0.9997, 1}
× g ∈ {−0.99, 0, 0.99} × ior ∈ {None, 1 + 1e-6, 1.5, 3.0} × thickness ∈ {1 voxel, 2.5 mm} (720 cases).

Each case renders a uniform 3×3-texel slab forward and backward and checks: finite image and gradients, radiance in
[0, environment], the white furnace (deficit exactly explained by paths cut at max_depth), Beer–Lambert for albedo 0
(5σ), ∂L/∂σ_t <= 0 for albedo 0 and ∂L/∂albedo >= 0. Prints one JSON line per case and a summary; exits 1 if any
case failed. tests/test_stiff_sweep.py runs the part that fits the test budget.
"""
import argparse
import itertools
import json
import sys
import time

from torch_appearance.testing import ALBEDOS, GS, IORS, SIGMAS, THICKNESS, run_stiff_case as run_case


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], epilog=__doc__.split("\n\n", 1)[1],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--spp", type=int, default=64, help="samples per texel (default: %(default)s)")
    p.add_argument("--max-depth", type=int, default=65536, help="(default: %(default)s)")
    p.add_argument("--quiet", action="store_true", help="print only failing cases and the summary")
    args = p.parse_args(argv)
    start, failed, n = time.perf_counter(), 0, 0
    for sigma, albedo, g, ior, thickness in itertools.product(SIGMAS, ALBEDOS, GS, IORS, THICKNESS):
        r = run_case(sigma, albedo, g, ior, thickness, spp=args.spp, max_depth=args.max_depth)
        n += 1
        failed += bool(r["failed"])
        if r["failed"] or not args.quiet:
            print(json.dumps(r), flush=True)
    print(json.dumps({"cases": n, "failed": failed, "wall_s": round(time.perf_counter() - start, 2)}))
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
