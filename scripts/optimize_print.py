#!/usr/bin/env python
"""Optimise the ink arrangement of a printed slab or textured object so that its rendered look matches a target.

Runs torch_appearance.pipelines.optimize_print: ink mixtures → C++ path tracer (radiative backpropagation) →
perceptual appearance loss (ΔE76², 3D SSIM, 3D Sobel) → Adagrad/Adam; then probabilistic quantisation to the
printer's native resolution, slice export, and an evaluation of the quantised volume against the target and
against the naive-extrusion baseline (CIEDE2000). Writes a run folder (see --help of --out) and can resume.

With --mesh (OBJ + MTL + texture, GLB/GLTF, PLY with vertex colours, ...) the object is scaled to --height-mm,
voxelised at --dpi, and only a shell of --shell-mm below its surface is optimised (deeper voxels hold --core-ink);
the surface is a smooth dielectric (--ior), the texels shoot inward from the surface.

Examples:
    python scripts/optimize_print.py --target colorchecker --iterations 200 --out results/colorchecker
    python scripts/optimize_print.py --target zebra --gamma 1,3,1 --out results/zebra
    python scripts/optimize_print.py --target photo.png --bottom-target back.exr --width-mm 20 --out results/mine
    python scripts/optimize_print.py --mesh spot.obj --texture spot_texture.png --height-mm 20 --out results/spot
    python scripts/optimize_print.py --out results/mine --resume     # continue an interrupted run
"""
import argparse
import os
import sys

try:
    import torch_appearance  # noqa: F401
except ModuleNotFoundError as error:  # running from a checkout that is not installed
    if error.name != "torch_appearance":
        raise
    sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from torch_appearance.fabrication.inks import DEFAULT_INKS
from torch_appearance.pipelines.print_cli import (add_optimization_arguments, add_target_arguments, config_from_args,
                                                  ink_names_help)
from torch_appearance.pipelines.print_optimization import PrintConfig, optimize_print


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], epilog=__doc__.split("\n\n", 1)[1],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    add_target_arguments(p)
    p.add_argument("--inks", default=",".join(DEFAULT_INKS), help=f"{ink_names_help()} (default: %(default)s)")
    add_optimization_arguments(p)
    p.add_argument("--no-naive-baseline", dest="naive_baseline", action="store_false",
                   help="skip the naive-extrusion baseline (a table of homogeneous renders and a quantised render)")
    p.add_argument("--remap-baseline", action="store_true",
                   help="objects: also score the 2.5D remapped baseline (a slab optimised in the mesh's UV space with "
                        "the same settings, wrapped around the object by UV and depth; costs a second optimisation)")
    p.add_argument("--views", type=int, default=PrintConfig.views,
                   help="objects: camera renders of the quantised print (default: %(default)s)")
    p.add_argument("--view-size", type=int, default=PrintConfig.view_size,
                   help="objects: pixels per side of those renders (default: %(default)s)")
    p.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's choice)")
    p.add_argument("--out", default=PrintConfig.out,
                   help="run folder: config.json, log.csv, convergence.png, target/baseline/initial/optimized/final "
                        "images (slabs: .exr+.png; objects: .npy, .ply and _uv.png), views.png (objects), "
                        "ink_usage_by_depth.png, mixture.npz, quantized.npz, slices/, checkpoint.pt, summary.json "
                        "(default: %(default)s)")
    p.add_argument("--resume", action="store_true", help="continue the run in --out from its checkpoint")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p.parse_args(argv)


def main(argv=None):
    args = parse_args(argv)
    if args.threads is not None:
        import torch
        if args.threads < 1:
            raise SystemExit(f"--threads: expected >= 1, got {args.threads}")
        torch.set_num_threads(args.threads)
    cfg = config_from_args(args)
    distributed = int(os.environ.get("WORLD_SIZE", "1")) > 1  # started by torchrun: data-parallel rendering
    if distributed:
        import torch.distributed as dist
        dist.init_process_group("gloo")
    try:
        optimize_print(cfg, progress=not args.quiet)
    except (ValueError, TypeError) as error:
        print(f"optimize_print.py: error: {error}", file=sys.stderr)
        return 2
    finally:
        if distributed:
            dist.destroy_process_group()
    return 0


if __name__ == "__main__":
    sys.exit(main())
