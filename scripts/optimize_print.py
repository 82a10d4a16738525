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
from torch_appearance.fabrication.inks import DEFAULT_INKS, INKS
from torch_appearance.pipelines.print_optimization import PrintConfig, optimize_print


def _floats(n, name):
    def parse(text):
        try:
            values = tuple(float(v) for v in text.split(","))
        except ValueError:
            raise argparse.ArgumentTypeError(f"{name}: expected {n} comma-separated numbers, got {text!r}")
        if len(values) != n:
            raise argparse.ArgumentTypeError(f"{name}: expected {n} comma-separated numbers, got {text!r}")
        return values
    return parse


def parse_args(argv=None):
    d = PrintConfig()
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], epilog=__doc__.split("\n\n", 1)[1],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--target", default=d.target,
                   help="top-face target: 'zebra', 'colorchecker', or an sRGB PNG/JPG or linear EXR (default: %(default)s)")
    p.add_argument("--bottom-target", default=None, help="optional bottom-face target (same size as the top)")
    p.add_argument("--thickness-mm", type=float, default=d.thickness_mm, help="slab thickness (default: %(default)s)")
    p.add_argument("--dpi", type=float, default=d.dpi, help="optimisation voxel pitch (default: %(default)s ≈ 0.0847 mm)")
    p.add_argument("--width-mm", type=float, default=None, help="slab width; default: target width × voxel pitch")
    p.add_argument("--height-mm", type=float, default=None, help="slab height (default: target height × voxel "
                   "pitch), or with --mesh the object's z extent in mm")
    p.add_argument("--mesh", default=None, help="a textured mesh to print as an object instead of a slab "
                   "(--height-mm is then its z extent in mm)")
    p.add_argument("--texture", default=None, help="base-colour image for a mesh with UVs but no material")
    p.add_argument("--shell-mm", type=float, default=d.shell_mm,
                   help="objects: optimised depth below the surface in mm (default: %(default)s)")
    p.add_argument("--core-ink", default=d.core_ink, help="objects: ink of the voxels below the shell "
                   "(default: %(default)s)")
    p.add_argument("--fixed", action="append", default=[], metavar="INK=FRACTION:MASK",
                   help="hold an ink at a fixed fraction (translucency), repeatable; MASK: all, depth:A-B (mm below "
                   "the surface), a mask PNG (slab texel size, or an object's texture space), terms joined by &; "
                   "e.g. transparent=0.8:depth:0-0.4")
    p.add_argument("--envmap", default=None, help="objects: a lat-long linear EXR (z up) lighting the print, "
                   "baked into the optimisation (default: uniform white)")
    p.add_argument("--inks", default=",".join(DEFAULT_INKS),
                   help=f"comma-separated ink names from {sorted(INKS)} or a JSON ink file (default: %(default)s)")
    p.add_argument("--gamma", type=_floats(3, "--gamma"), default=d.gamma,
                   help="weights γ1,γ2,γ3 of ΔE76², SSIM, Sobel (default: 1,3,1)")
    p.add_argument("--spp", type=int, default=d.spp, help="samples per texel per iteration (default: %(default)s)")
    p.add_argument("--eval-spp", type=int, default=d.eval_spp, help="samples per texel of evaluation renders (default: %(default)s)")
    p.add_argument("--eval-every", type=int, default=d.eval_every, help="evaluate every k iterations (default: %(default)s)")
    p.add_argument("--iterations", type=int, default=d.iterations, help="(default: %(default)s)")
    p.add_argument("--optimizer", choices=("adagrad", "adam"), default=d.optimizer, help="(default: %(default)s)")
    p.add_argument("--lr", type=float, default=d.lr, help="learning rate (default: %(default)s)")
    p.add_argument("--parameterization", choices=("sigmoid", "softmax"), default=d.parameterization,
                   help="mixture parameterisation (default: %(default)s, as in the paper)")
    p.add_argument("--printer-dpi", type=_floats(3, "--printer-dpi"), default=d.printer_dpi,
                   help="native printer resolution x,y,z for quantisation (default: 600,300,940)")
    p.add_argument("--ior", type=float, default=d.ior, help="refractive index of the print (default: %(default)s)")
    p.add_argument("--seed", type=int, default=d.seed, help="(default: %(default)s)")
    p.add_argument("--gradient-seed", choices=("same", "independent"), default=d.gradient_seed,
                   help="gradient replay: retrace the forward's paths ('same') or draw independent ones with "
                        "seed_grad ('independent', as Mitsuba's render(seed, seed_grad)) (default: %(default)s)")
    p.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's choice)")
    p.add_argument("--out", default=d.out,
                   help="run folder: config.json, log.csv, convergence.png, target/baseline/initial/optimized/final "
                        ".exr+.png, dE00_heatmap.png, ink_usage_by_depth.png, mixture.npz, quantized.npz, slices/, "
                        "checkpoint.pt, summary.json (default: %(default)s)")
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
    cfg = PrintConfig(target=args.target, bottom_target=args.bottom_target, thickness_mm=args.thickness_mm,
                      dpi=args.dpi, width_mm=args.width_mm, height_mm=args.height_mm, inks=args.inks,
                      gamma=args.gamma, spp=args.spp, eval_spp=args.eval_spp, eval_every=args.eval_every,
                      iterations=args.iterations, optimizer=args.optimizer, lr=args.lr,
                      parameterization=args.parameterization, printer_dpi=args.printer_dpi, ior=args.ior,
                      seed=args.seed, gradient_seed=args.gradient_seed, out=args.out, resume=args.resume,
                      mesh=args.mesh, texture=args.texture, shell_mm=args.shell_mm, core_ink=args.core_ink,
                      envmap=args.envmap, fixed=tuple(args.fixed))
    try:
        optimize_print(cfg, progress=not args.quiet)
    except (ValueError, TypeError) as error:
        print(f"optimize_print.py: error: {error}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
