#!/usr/bin/env python
"""Benchmark the appearance loss (eq. 18) on an object's texels: dense grid path against sparse texel path.

The mesh (default: Spot, ``tests/data/meshes/spot``) is scaled to each ``--heights-mm`` and voxelised at ``--dpi``
as ``ta-voxelize`` does; its texel positions and colours are cached in ``--out``'s folder
(``texels_<H>mm.npz``). For every height and variant a fresh worker process loads them, makes a prediction
``clamp(target + N(0, 0.05²))`` (fixed seed) and times

* ``setup_s``: what the variant needs before the loss — dense: the target grid and mask
  (``VoxelObject.texels_to_grid``); sparse: nothing (the matrices are built in the first call);
* ``first_s``: the first forward + backward of ``AppearanceLoss((1, 3, 1))`` with respect to the (N, 3)
  prediction — dense: ``forward_parts(texels_to_grid(pred), target_grid, mask)``; sparse:
  ``forward_parts_texels(pred, target, positions)``, including the construction of the CSR matrices;
* ``forward_s``, ``backward_s``: a second call (the sparse matrices cached, as in every later iteration);
* ``peak_rss_mb``: the peak resident memory of the worker (VmHWM, reset after the texels were loaded) minus the
  resident memory at that point: the memory the loss itself needs;

and records E1, E2, E3 (so that dense and sparse can be compared; ``--f64`` adds their float64 values) and, for
the sparse path, the number of stored matrix entries and their bytes. One JSON line per run is printed and all of them are written atomically to
``--out``. ``--dense-max-mm`` skips the dense path above that height (it needs 3 floats per bounding-box voxel
for every filtered volume).

Usage::

    python scripts/bench/bench_texel_loss.py --heights-mm 10 --out results/bench_texel_loss/bench.json
    python scripts/bench/bench_texel_loss.py --heights-mm 10,25,40 --dense-max-mm 10 --threads 1
"""
import argparse
import json
import os
import subprocess
import sys
import time

import numpy as np
import torch

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(os.path.dirname(HERE))
SPOT = os.path.join(ROOT, "tests", "data", "meshes", "spot")

from torch_appearance.testing import reset_peak_rss as _reset_peak_rss, status_kb as _status_kb  # noqa: E402


def _texels(args, height):
    """Voxelise (or load the cached) texels at ``height`` mm: ``(path of the npz, info dict)``."""
    from torch_appearance import io as ta_io
    folder = os.path.dirname(os.path.abspath(args.out))
    path = os.path.join(folder, f"texels_{height:g}mm_{args.dpi:g}dpi.npz")
    if os.path.exists(path):
        with np.load(path) as data:
            return path, json.loads(str(data["info_json"]))
    from torch_appearance.geometry import load_mesh, voxelize
    t0 = time.perf_counter()
    mesh, _ = load_mesh(args.mesh, height_mm=height, **({"texture": args.texture} if args.texture else {}))
    obj = voxelize(mesh, 25.4 / args.dpi)
    info = {"height_mm": height, "dpi": args.dpi, "grid_dhw": list(obj.grid_shape),
            "grid_voxels": int(np.prod(obj.grid_shape)), "texels": int(len(obj.texel_voxels)),
            "voxelize_s": time.perf_counter() - t0}
    if obj.texel_colors is None:
        raise ValueError(f"--mesh: {args.mesh!r} has no colours (give --texture)")
    import io as _io
    buffer = _io.BytesIO()
    np.savez(buffer, positions=obj.texel_voxels.numpy(), colors=obj.texel_colors.float().numpy(),
             grid_dhw=np.array(obj.grid_shape), info_json=np.array(json.dumps(info)))
    ta_io.atomic_write_bytes(path, buffer.getvalue())
    return path, info


def _worker(variant, path, threads, f64=False):
    """Run one measurement in this (fresh) process; return the JSON-able row."""
    torch.set_num_threads(threads)
    from torch_appearance.geometry.voxelize import VoxelObject
    from torch_appearance.nn import AppearanceLoss
    with np.load(path) as data:
        positions = torch.from_numpy(data["positions"]).long()
        target = torch.from_numpy(data["colors"]).float().clamp(0, 1)
        shape = tuple(int(v) for v in data["grid_dhw"])
    g = torch.Generator().manual_seed(0)
    pred0 = (target + 0.05 * torch.randn(target.shape, generator=g)).clamp(0, 1)
    # texels_to_grid without a whole VoxelObject: the same index_copy placement
    place = VoxelObject.texels_to_grid.__get__(type("T", (), {"texel_voxels": positions, "grid_shape": shape})())
    crit = AppearanceLoss(gamma=(1.0, 3.0, 1.0))
    peak_reset = _reset_peak_rss()
    base_kb = _status_kb("VmRSS")
    t0 = time.perf_counter()
    if variant == "dense":
        target_grid = place(target)
        mask = place(torch.ones(len(target), 1, dtype=torch.bool))[0]

        def loss(x):
            return crit.forward_parts(place(x), target_grid, mask)
    else:
        def loss(x):
            return crit.forward_parts_texels(x, target, positions)
    setup = time.perf_counter() - t0
    row = {"variant": variant, "texels": len(positions), "grid_dhw": list(shape), "threads": threads,
           "setup_s": setup}
    for name in ("first", "second"):
        x = pred0.clone().requires_grad_(True)
        t0 = time.perf_counter()
        total, parts = loss(x)
        t1 = time.perf_counter()
        total.backward()
        t2 = time.perf_counter()
        if name == "first":
            row["first_s"] = t2 - t0
        else:
            row.update(forward_s=t1 - t0, backward_s=t2 - t1)
        del total
    row.update({k: float(v) for k, v in parts.items()})
    row["grad_abs_sum"] = float(x.grad.abs().sum())
    if variant == "sparse":
        filters = crit.texel_filters(positions)
        row["gaussian_nnz"] = filters.gaussian_nnz(torch.float32)
        row["matrices_mb"] = filters.nbytes() / 2**20
    peak_kb = _status_kb("VmHWM")
    if peak_reset and peak_kb is not None and base_kb is not None:
        row["peak_rss_mb"] = (peak_kb - base_kb) / 1024.0
    if variant == "sparse" and f64:  # the float64 values (the sparse path equals the dense one there, see tests)
        with torch.no_grad():
            _, parts64 = AppearanceLoss(gamma=(1.0, 3.0, 1.0)).forward_parts_texels(
                pred0.double(), target.double(), positions)
        row.update({f"{k}_f64": float(v) for k, v in parts64.items()})
    return row


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    p.add_argument("--mesh", default=os.path.join(SPOT, "spot_triangulated.obj"), help="mesh file")
    p.add_argument("--texture", default=os.path.join(SPOT, "spot_texture.png"),
                   help="its colour image ('' for none)")
    p.add_argument("--heights-mm", default="10", help="comma-separated heights in mm (default: %(default)s)")
    p.add_argument("--dpi", type=float, default=300.0, help="voxel pitch in DPI (default: %(default)s)")
    p.add_argument("--variants", default="dense,sparse", help="comma-separated: dense, sparse")
    p.add_argument("--dense-max-mm", type=float, default=10.0,
                   help="run the dense path only up to this height (default: %(default)s)")
    p.add_argument("--threads", type=int, default=1, help="torch threads per worker (default: %(default)s)")
    p.add_argument("--out", default=os.path.join(ROOT, "results", "bench_texel_loss", "bench.json"),
                   help="JSON file of the rows (its folder also caches the voxelised texels)")
    p.add_argument("--f64", action="store_true",
                   help="also record E1/E2/E3 in float64 (sparse runs, after the timing): the reference for both")
    p.add_argument("--worker", nargs=2, metavar=("VARIANT", "NPZ"), help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.worker:
        print(json.dumps(_worker(args.worker[0], args.worker[1], args.threads, args.f64)))
        return 0
    try:
        heights = [float(h) for h in args.heights_mm.split(",") if h.strip()]
    except ValueError:
        p.error(f"--heights-mm: expected comma-separated numbers, got {args.heights_mm!r}")
    variants = [v.strip() for v in args.variants.split(",") if v.strip()]
    if not heights or any(h <= 0 for h in heights):
        p.error(f"--heights-mm: expected positive heights, got {args.heights_mm!r}")
    if not variants or any(v not in ("dense", "sparse") for v in variants):
        p.error(f"--variants: expected a comma-separated subset of dense,sparse, got {args.variants!r}")
    if not args.threads >= 1:
        p.error(f"--threads: expected >= 1, got {args.threads}")
    if not os.path.exists(args.mesh):
        p.error(f"--mesh: no such file {args.mesh!r}")
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    from torch_appearance.progress import progress_bar

    from torch_appearance import io as ta_io
    jobs = [(h, v) for h in heights for v in variants if not (v == "dense" and h > args.dense_max_mm)]
    rows = []
    env = dict(os.environ, OMP_NUM_THREADS=str(args.threads), PYTHONPATH=ROOT + os.pathsep
               + os.environ.get("PYTHONPATH", ""))
    bar = progress_bar(jobs, desc="bench_texel_loss", unit="run")
    for height, variant in bar:
        bar.set_postfix(height=f"{height:g}mm", variant=variant)
        path, info = _texels(args, height)
        command = [sys.executable, os.path.abspath(__file__), "--worker", variant, path, "--threads",
                   str(args.threads)] + (["--f64"] if args.f64 else [])
        proc = subprocess.run(command, capture_output=True, text=True, env=env)
        if proc.returncode != 0:
            tail = proc.stderr.strip().splitlines()[-1:] or [f"exit status {proc.returncode}"]
            row = {**info, "variant": variant, "error": tail[0]}
        else:
            row = {**info, **json.loads(proc.stdout.strip().splitlines()[-1])}
        rows.append(row)
        bar.write(json.dumps(row))
        ta_io.write_json(args.out, rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
