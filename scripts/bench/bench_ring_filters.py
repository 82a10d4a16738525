#!/usr/bin/env python
"""Time the ring filters (orientation field, phase orientation, curved Gabor) and compare their outputs with a
saved run.

The image is a synthetic flat-sawn board (torch_appearance.rings.synthetic_board, seed 0) converted to grey with
Rec. 709 weights. Each filter is timed ``--repeat`` times with ``torch.set_num_threads(--threads)``; the minimum
wall time is printed (the machine may be shared). ``--save out.npz`` stores the outputs; ``--compare old.npz``
prints the largest absolute difference of every output against an earlier run (e.g. before a refactor).

Examples:
    python scripts/bench/bench_ring_filters.py --size 1000 --save before.npz
    python scripts/bench/bench_ring_filters.py --size 1000 --compare before.npz
"""
import argparse
import os
import sys
import time

import numpy as np
import torch

from torch_appearance.rings import curved_gabor, orientation_field, orientation_from_phase, synthetic_board

PROG = "bench_ring_filters.py"


def parse_args(argv=None):
    p = argparse.ArgumentParser(prog=PROG, description=__doc__.split("\n\n")[0], epilog=__doc__.split("\n\n", 1)[1],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--size", type=int, default=1000, help="image side in pixels (default 1000)")
    p.add_argument("--gabor-size", type=int, default=None,
                   help="image side for curved_gabor (default: --size); 0 skips curved_gabor")
    p.add_argument("--pq", type=int, default=80, help="curved Gabor half-lengths p = q (default 80)")
    p.add_argument("--repeat", type=int, default=3, help="timings per filter; the minimum is printed (default 3)")
    p.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    p.add_argument("--save", help="write the outputs to this .npz")
    p.add_argument("--compare", help="print max |difference| against the outputs in this .npz")
    args = p.parse_args(argv)
    for name in ("size", "pq", "repeat", "threads"):
        if getattr(args, name) < 1:
            p.error(f"--{name}: expected an integer >= 1, got {getattr(args, name)}")
    if args.compare and not os.path.isfile(args.compare):
        p.error(f"--compare: expected an existing .npz written by --save, got {args.compare!r}")
    if args.gabor_size is None:
        args.gabor_size = args.size
    if args.gabor_size < 0:
        p.error(f"--gabor-size: expected an integer >= 0, got {args.gabor_size}")
    return args


def _timed(fn, repeat):
    best, out = float("inf"), None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def main(argv=None):
    args = parse_args(argv)
    from torch_appearance.progress import progress_bar

    torch.set_num_threads(args.threads)
    weights = np.array([0.2126, 0.7152, 0.0722], np.float32)
    gray = synthetic_board(args.size, args.size, seed=0)["image"] @ weights
    outputs, rows = {}, []
    jobs = [("orientation_field (1, 15)", lambda: orientation_field(gray)),
            ("orientation_field (4, 61)", lambda: orientation_field(gray, 4.0, 61)),
            ("orientation_from_phase", lambda: orientation_from_phase(np.cos(gray * 40.0), 2.0, 31,
                                                                      magnitude=np.abs(gray)))]
    if args.gabor_size:
        g = gray if args.gabor_size == args.size else \
            synthetic_board(args.gabor_size, args.gabor_size, seed=0)["image"] @ weights
        jobs.append((f"curved_gabor {args.gabor_size}^2 p=q={args.pq}",
                     lambda: curved_gabor(g, p=args.pq, q=args.pq, num_workers=args.threads)))
    for name, fn in progress_bar(jobs, desc="filters", unit="filter"):
        seconds, out = _timed(fn, args.repeat if "curved" not in name else 1)
        fields = out if isinstance(out, tuple) else (out.magnitude, out.phase, out.frequency, out.orientation)
        for i, f in enumerate(fields):
            outputs[f"{name}/{i}"] = np.asarray(f)
        rows.append((name, seconds))
    print(f"threads={args.threads} size={args.size}")
    for name, seconds in rows:
        print(f"{name:40s} {seconds:9.3f} s")
    if args.compare:
        old = np.load(args.compare)
        for key, value in outputs.items():
            if key in old.files:
                diff = np.abs(value.astype(np.float64) - old[key].astype(np.float64))
                if "/1" in key and "curved" in key:  # phase: cyclic difference
                    diff = np.abs(np.angle(np.exp(1j * (value.astype(np.float64) - old[key]))))
                if (key.startswith("orientation") and key.endswith("/0")) or ("curved" in key and key.endswith("/3")):
                    # orientation mod pi
                    diff = np.abs(np.angle(np.exp(2j * (value.astype(np.float64) - old[key])))) / 2
                print(f"max |diff| {key:45s} {diff.max():.3e}   (99.9 %: {np.quantile(diff, 0.999):.3e})")
    if args.save:
        from torch_appearance.io import atomic_write_bytes
        import io
        buf = io.BytesIO()
        np.savez_compressed(buf, **outputs)
        atomic_write_bytes(args.save, buf.getvalue())


if __name__ == "__main__":
    main()
