#!/usr/bin/env python
"""Fit an anatomically meaningful procedural solid-wood texture to one photograph of a board.

Curved Gabor filtering finds the growth rings and their phase, the board's location in the log is estimated from
the traced rings, then a WoodModel (tree axis, ring scale, radial distortion, colour map) is fitted with a cyclic
phase loss (stage 1) and a colour loss (stage 2); ``--photometric`` adds stage 3, geometry and colour map
refined against the photo's colours through the reparameterised render. Writes a run folder: fit.png, phase.npy,
fit_phase.npy, params.json, log.csv, convergence.png, orientation/magnitude/phase images, ring_overlay.png,
board_estimate.json, model.json + model.pt, fit_vs_photo.png, phase_error.png, cube_preview.png, summary.json (with
--photometric also fit_before_photometric.png and model_before_photometric.json + .pt).

Examples:
    python scripts/fit_wood.py board.png --pixel-size-mm 0.1 --out results/board
    python scripts/fit_wood.py board.jpg --dpi 600 --epochs 300 --out results/board600
    python scripts/fit_wood.py board.png --photometric --out results/board_photo
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
from torch_appearance.pipelines.wood_fit import WoodFitConfig, fit_wood


def parse_args(argv=None):
    d = WoodFitConfig(photo="")
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], epilog=__doc__.split("\n\n", 1)[1],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("photo", help="photo of a planar board (PNG/JPG sRGB or linear EXR)")
    p.add_argument("--out", default=d.out, help="run folder (default: %(default)s)")
    size = p.add_mutually_exclusive_group()
    size.add_argument("--pixel-size-mm", type=float, default=None, help=f"pixel pitch in mm (default: {d.pixel_size_mm})")
    size.add_argument("--dpi", type=float, default=None, help="scan resolution (pixel size = 25.4 / dpi mm)")
    p.add_argument("--epochs", type=int, default=d.epochs, help="stage-1 (phase) epochs (default: %(default)s)")
    p.add_argument("--lr", type=float, default=d.lr, help="stage-1 Adam learning rate (default: %(default)s)")
    p.add_argument("--color-epochs", type=int, default=d.color_epochs, help="stage-2 epochs (default: %(default)s)")
    p.add_argument("--p", type=int, default=d.p, help="curved Gabor: contours across the rings, 2p+1 (default: %(default)s)")
    p.add_argument("--q", type=int, default=d.q, help="curved Gabor: points along each contour, 2q+1 (default: %(default)s)")
    p.add_argument("--distortion", choices=("radial", "azimuthal"), default=d.distortion, help="(default: %(default)s)")
    p.add_argument("--coarse-to-fine", type=int, default=d.coarse_to_fine,
                   help="stage-1 distortion levels, coarse first (1: full texture from the start; default: %(default)s)")
    p.add_argument("--color-bins", type=int, default=d.color_bins,
                   help="lateness samples of the colour map (default: %(default)s)")
    p.add_argument("--contrast-match", action="store_true",
                   help="after stage 2, remap the colour map's luminance so that the fit's luminance histogram is the "
                        "photo's (keeps latewood contrast that per-bin means wash out where the phase is slightly off)")
    p.add_argument("--photometric", action="store_true",
                   help="stage 3: refine geometry and colour map against the photo's colours (CIELAB L2) through the "
                        "reparameterised render (correct ring-boundary gradients), coarse to fine")
    p.add_argument("--photometric-epochs", type=int, default=d.photometric_epochs,
                   help="stage-3 Adam steps over all levels (default: %(default)s)")
    p.add_argument("--photometric-levels", type=int, nargs="+", default=list(d.photometric_levels), metavar="F",
                   help="stage-3 downsampling factors of the photo, coarse first (default: %(default)s)")
    p.add_argument("--photometric-spp", type=int, default=d.photometric_spp,
                   help="stage-3 filter samples per pixel and step (default: %(default)s)")
    p.add_argument("--photometric-weight", type=float, default=d.photometric_weight,
                   help="stage-3 weight of the CIELAB term, mean ΔE²/100 (default: %(default)s)")
    p.add_argument("--photometric-anchor", type=float, default=d.photometric_anchor,
                   help="stage-3 weight of the stage-1 phase loss kept as an anchor, 0 = colour only "
                        "(default: %(default)s)")
    p.add_argument("--photometric-lr", type=float, default=d.photometric_lr,
                   help="stage-3 geometry step, ring widths per step (default: %(default)s)")
    p.add_argument("--photometric-color-lr", type=float, default=d.photometric_color_lr,
                   help="stage-3 colour-map step, 0 = frozen (default: %(default)s)")
    p.add_argument("--photometric-estimator", choices=("reparam", "naive"), default=d.photometric_estimator,
                   help="stage-3 gradients: reparameterised (boundary term included) or naive fixed-sample autograd, "
                        "for comparison (default: %(default)s)")
    p.add_argument("--max-size", type=int, default=None, help="downscale photos larger than this many pixels")
    p.add_argument("--device", default=d.device, help="torch device for the fit: cpu or cuda (default: %(default)s)")
    p.add_argument("--seed", type=int, default=d.seed)
    p.add_argument("--no-preview", action="store_true", help="skip the pyvista cube preview")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p.parse_args(argv)


def main(argv=None):
    args = parse_args(argv)
    pixel = args.pixel_size_mm if args.pixel_size_mm is not None else (
        25.4 / args.dpi if args.dpi else WoodFitConfig(photo="").pixel_size_mm)
    if args.dpi is not None and args.dpi <= 0:
        print(f"fit_wood.py: error: --dpi: expected > 0, got {args.dpi}", file=sys.stderr)
        return 2
    cfg = WoodFitConfig(photo=args.photo, out=args.out, pixel_size_mm=pixel, epochs=args.epochs, lr=args.lr,
                        color_epochs=args.color_epochs, p=args.p, q=args.q, distortion=args.distortion,
                        device=args.device, max_size=args.max_size, seed=args.seed, preview=not args.no_preview,
                        coarse_to_fine=args.coarse_to_fine, color_bins=args.color_bins,
                        contrast_match=args.contrast_match,
                        photometric=args.photometric, photometric_epochs=args.photometric_epochs,
                        photometric_levels=tuple(args.photometric_levels), photometric_spp=args.photometric_spp,
                        photometric_weight=args.photometric_weight, photometric_anchor=args.photometric_anchor,
                        photometric_lr=args.photometric_lr, photometric_color_lr=args.photometric_color_lr,
                        photometric_estimator=args.photometric_estimator)
    try:
        fit_wood(cfg, progress=not args.quiet)
    except (ValueError, TypeError) as error:
        print(f"fit_wood.py: error: {error}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
