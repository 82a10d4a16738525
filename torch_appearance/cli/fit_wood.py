"""``ta-fit-wood``: the wood fit's command line (:func:`main`), and the one settings block the wood
commands share (:func:`add_fit_arguments`, :func:`config_from_args`): every flag names a :class:`WoodFitConfig`
field, with its default.

Fit an anatomically meaningful procedural solid-wood texture to one photograph of a board.

Curved Gabor filtering finds the growth rings and their phase, the board's location in the log is estimated from
the traced rings, then a WoodModel (tree axis, ring scale, radial distortion, colour map) is fitted with a cyclic
phase loss (stage 1) and a colour loss (stage 2); ``--photometric`` adds stage 3, geometry and colour map
refined against the photo's colours through the reparameterised render. Writes a run folder: fit.png, phase.npy,
fit_phase.npy, params.json, log.csv, convergence.png, orientation/magnitude/phase images, ring_overlay.png,
board_estimate.json, model.json + model.pt, fit_vs_photo.png, phase_error.png, cube_preview.png, summary.json (with
--photometric also fit_before_photometric.png and model_before_photometric.json + .pt).

Examples:
    ta-fit-wood board.png --pixel-size-mm 0.1 --out results/board
    ta-fit-wood board.jpg --dpi 600 --epochs 300 --out results/board600
    ta-fit-wood board.png --photometric --out results/board_photo
"""
import argparse
import math
import sys

from ..pipelines.wood.config import PIXEL_SIZE_MM_RANGE, WoodFitConfig
from ..pipelines.wood.fit import fit_wood
from .command import (CommandParser, check_output_folder, fail, flag_names, interrupted, interrupted_message,
                      owned_folder)

__all__ = ["add_fit_arguments", "config_from_args", "parser", "main", "FIT_FLAGS", "stage3_flags_without_photometric"]

PROG = "ta-fit-wood"

#: The fit's flags: (flag, add_argument keywords, help); the defaults come from WoodFitConfig.
FIT_FLAGS = {
    "epochs": ("--epochs", dict(type=int), "stage-1 (phase) epochs (default: %(default)s)"),
    "lr": ("--lr", dict(type=float), "stage-1 Adam learning rate (default: %(default)s)"),
    "color_epochs": ("--color-epochs", dict(type=int), "stage-2 epochs (default: %(default)s)"),
    "p": ("--p", dict(type=int), "curved Gabor: contours across the rings, 2p+1 (default: %(default)s)"),
    "q": ("--q", dict(type=int), "curved Gabor: points along each contour, 2q+1 (default: %(default)s)"),
    "distortion": ("--distortion", dict(choices=("radial", "azimuthal")), "(default: %(default)s)"),
    "coarse_to_fine": ("--coarse-to-fine", dict(type=int),
                       "stage-1 distortion levels, coarse first (1: full texture from the start; "
                       "default: %(default)s)"),
    "lobe_shape": ("--lobe-shape", dict(type=int, nargs=2, metavar=("HTHETA", "HP")),
                   "texels (azimuth, radius) of the lobes of the innermost rings near the pith; 0 0: none "
                   "(default: %(default)s)"),
    "lobe_radius_rings": ("--lobe-radius-rings", dict(type=float),
                          "radius of the lobe texture round the pith, in ring widths (default: %(default)s)"),
    "pith_split": ("--pith-split", dict(action=argparse.BooleanOptionalAction),
                   "filter the two sides of the pith line apart where the rings run along it (the symmetric profile "
                   "there bends the innermost rings' phase; default: on)"),
    "color_bins": ("--color-bins", dict(type=int), "lateness samples of the colour map (default: %(default)s)"),
    "contrast_match": ("--contrast-match", dict(action="store_true"),
                       "after stage 2, remap the colour map's luminance so that the fit's luminance histogram is the "
                       "photo's (keeps latewood contrast that per-bin means wash out where the phase is slightly off)"),
    "photometric": ("--photometric", dict(action="store_true"),
                    "stage 3: refine geometry and colour map against the photo's colours (CIELAB L2) through the "
                    "reparameterised render (correct ring-boundary gradients), coarse to fine"),
    "photometric_epochs": ("--photometric-epochs", dict(type=int),
                           "stage-3 Adam steps over all levels (default: %(default)s)"),
    "photometric_levels": ("--photometric-levels", dict(type=int, nargs="+", metavar="F"),
                           "stage-3 downsampling factors of the photo, coarse first (default: %(default)s)"),
    "photometric_spp": ("--photometric-spp", dict(type=int),
                        "stage-3 filter samples per pixel and step (default: %(default)s)"),
    "photometric_weight": ("--photometric-weight", dict(type=float),
                           "stage-3 weight of the CIELAB term, mean ΔE²/100 (default: %(default)s)"),
    "photometric_anchor": ("--photometric-anchor", dict(type=float),
                           "stage-3 weight of the stage-1 phase loss kept as an anchor, 0 = colour only "
                           "(default: %(default)s)"),
    "photometric_lr": ("--photometric-lr", dict(type=float),
                       "stage-3 geometry step, ring widths per step (default: %(default)s)"),
    "photometric_color_lr": ("--photometric-color-lr", dict(type=float),
                             "stage-3 colour-map step, 0 = frozen (default: %(default)s)"),
    "photometric_estimator": ("--photometric-estimator", dict(choices=("reparam", "naive")),
                              "stage-3 gradients: reparameterised (boundary term included) or naive fixed-sample "
                              "autograd, for comparison (default: %(default)s)"),
    "max_size": ("--max-size", dict(type=int), "downscale photos larger than this many pixels"),
    "device": ("--device", dict(), "torch device for the fit: cpu or cuda (default: %(default)s)"),
    "seed": ("--seed", dict(type=int), None),
}


def add_fit_arguments(p, names=None, **defaults):
    """Add the fit's flags (:data:`FIT_FLAGS`; only ``names`` when given) to the parser ``p``, their defaults from
    :class:`WoodFitConfig` unless ``defaults`` overrides them (e.g. a shorter evaluation)."""
    d = WoodFitConfig(photo="")
    for name in (FIT_FLAGS if names is None else names):
        flag, kwargs, help_text = FIT_FLAGS[name]
        kwargs = dict(kwargs)
        if kwargs.get("action") != "store_true":
            default = defaults.get(name, getattr(d, name))
            kwargs["default"] = list(default) if isinstance(default, tuple) else default
        if help_text is not None:
            kwargs["help"] = help_text
        p.add_argument(flag, **kwargs)


def config_from_args(args, **fields):
    """The :class:`WoodFitConfig` of the fit flags in ``args`` (those that it has), with ``fields`` on top."""
    values = {name: getattr(args, name) for name in FIT_FLAGS if hasattr(args, name)}
    if "photometric_levels" in values:
        values["photometric_levels"] = tuple(values["photometric_levels"])
    if "lobe_shape" in values and values["lobe_shape"] is not None:
        values["lobe_shape"] = None if list(values["lobe_shape"]) == [0, 0] else tuple(values["lobe_shape"])
    values.update(fields)
    return WoodFitConfig(**values)


def stage3_flags_without_photometric(parser, args):
    """The stage-3 flags (``--photometric-…``) that ``args`` sets to other than their defaults while stage 3 is off
    (no ``--photometric``): they would change nothing."""
    if getattr(args, "photometric", True):
        return []
    unused = []
    for name, (flag, _, _) in FIT_FLAGS.items():
        if name.startswith("photometric_") and hasattr(args, name) and getattr(args, name) != parser.get_default(name):
            unused.append(flag)
    return unused


def parser(prog=PROG):
    """The ``fit_wood`` argument parser."""
    d = WoodFitConfig(photo="")
    p = CommandParser(prog, __doc__.split("\n\n", 1)[1])
    p.add_argument("photo", help="photo of a planar board (PNG/JPG sRGB or linear EXR)")
    p.add_argument("--out", default=d.out, help="run folder (default: %(default)s)")
    size = p.add_mutually_exclusive_group()
    size.add_argument("--pixel-size-mm", type=float, default=None,
                      help=f"pixel pitch in mm (default: {d.pixel_size_mm})")
    size.add_argument("--dpi", type=float, default=None, help="scan resolution (pixel size = 25.4 / dpi mm)")
    add_fit_arguments(p)
    p.add_argument("--no-preview", action="store_true", help="skip the pyvista cube preview")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


def main(argv=None, prog=PROG):
    """Run :func:`fit_wood` with the flags in ``argv`` (default ``sys.argv[1:]``); returns the exit status (2 for
    refused input, with the message on stderr)."""
    p = parser(prog)
    args = p.parse_args(argv)
    check_output_folder(p, "--out", args.out)
    if args.dpi is not None and not (math.isfinite(args.dpi) and args.dpi > 0):
        p.error(f"--dpi: expected a finite value > 0, got {args.dpi}")
    if args.dpi is not None:  # the pixel pitch's range in the flag's own unit
        low, high = (25.4 / mm for mm in reversed(PIXEL_SIZE_MM_RANGE))
        if not low <= args.dpi <= high:
            p.error(f"--dpi: expected {low:g} ... {high:g} (pixels of {PIXEL_SIZE_MM_RANGE[1]:g} ... "
                    f"{PIXEL_SIZE_MM_RANGE[0]:g} mm: a ring is at least ~4 px wide), got {args.dpi:g}")
    shape = getattr(args, "lobe_shape", None)  # the library's message offers None; the command line gives 0 0
    if shape is not None and list(shape) != [0, 0] and (shape[0] < 4 or shape[1] < 2):
        p.error(f"--lobe-shape: expected 0 0 (no lobe texture) or HTHETA >= 4 and HP >= 2, got {shape[0]} {shape[1]}")
    unused = stage3_flags_without_photometric(p, args)
    if unused:
        p.error(f"{'/'.join(unused)}: set for stage 3, which runs only with --photometric; add --photometric or "
                f"leave {'them' if len(unused) > 1 else 'it'} out")
    pixel = args.pixel_size_mm if args.pixel_size_mm is not None else (
        25.4 / args.dpi if args.dpi else WoodFitConfig(photo="").pixel_size_mm)
    cfg = config_from_args(args, photo=args.photo, out=args.out, pixel_size_mm=pixel, preview=not args.no_preview)
    try:  # the folder is this command's while it fits: another tool's or one another fit writes is refused
        with owned_folder(PROG, args.out, "fit"):
            fit_wood(cfg, progress=not args.quiet)
    except (ValueError, TypeError) as error:
        return fail(prog, error, flag_names(p), vars(args))
    except KeyboardInterrupt as stop:
        return interrupted(prog, interrupted_message(stop))
    return 0


if __name__ == "__main__":
    sys.exit(main())
