"""Command-line pieces shared by the print scripts (scripts/optimize_print.py, scripts/select_inks.py): the target
and optimisation flags of :class:`~torch_appearance.pipelines.PrintConfig`, and the config built from them."""
import argparse
import dataclasses

from ..fabrication.inks import INKS
from .print_optimization import PrintConfig

__all__ = ["float_tuple", "add_target_arguments", "add_optimization_arguments", "config_from_args"]


def float_tuple(n, name):
    """An argparse type: ``n`` comma-separated numbers → tuple of floats (``name`` in the message)."""
    def parse(text):
        try:
            values = tuple(float(v) for v in text.split(","))
        except ValueError:
            raise argparse.ArgumentTypeError(f"{name}: expected {n} comma-separated numbers, got {text!r}") from None
        if len(values) != n:
            raise argparse.ArgumentTypeError(f"{name}: expected {n} comma-separated numbers, got {text!r}")
        return values
    return parse


def add_target_arguments(p, d=None, *, fixed=True):
    """What is printed: a slab target image or a textured mesh, its size, shell, core ink, lighting (and, with
    ``fixed``, the ``--fixed INK=FRACTION:MASK`` constraints). ``d``: the PrintConfig giving the defaults."""
    d = PrintConfig() if d is None else d
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
    if fixed:
        p.add_argument("--fixed", action="append", default=[], metavar="INK=FRACTION:MASK",
                       help="hold an ink at a fixed fraction (translucency), repeatable; MASK: all, depth:A-B (mm "
                       "below the surface), a mask PNG (slab texel size, or an object's texture space), "
                       "material:NAME (objects: the faces of one of the mesh's materials), terms joined by &; e.g. "
                       "transparent=0.8:depth:0-0.4")
    p.add_argument("--envmap", default=None, help="objects: a lat-long linear EXR (z up) lighting the print, "
                   "baked into the optimisation (default: uniform white)")


def add_optimization_arguments(p, d=None):
    """How it is optimised: spp, iterations, optimiser, loss weights, quantisation, seeds. ``d``: defaults."""
    d = PrintConfig() if d is None else d
    p.add_argument("--gamma", type=float_tuple(3, "--gamma"), default=d.gamma,
                   help="weights γ1,γ2,γ3 of ΔE76², SSIM, Sobel (default: 1,3,1)")
    p.add_argument("--spp", type=int, default=d.spp, help="samples per texel per iteration (default: %(default)s)")
    p.add_argument("--eval-spp", type=int, default=d.eval_spp,
                   help="samples per texel of evaluation renders (default: %(default)s)")
    p.add_argument("--eval-every", type=int, default=d.eval_every, help="evaluate every k iterations (default: %(default)s)")
    p.add_argument("--iterations", type=int, default=d.iterations, help="(default: %(default)s)")
    p.add_argument("--table-steps", type=int, default=d.table_steps,
                   help="naive-extrusion baseline: mixtures in steps of 1/N (default: %(default)s)")
    p.add_argument("--init", choices=("white", "naive"), default=d.init,
                   help="starting mixture: 97 %% white everywhere (the paper), or the naive extrusion (each "
                        "voxel the best homogeneous mixture for its texel) (default: %(default)s)")
    p.add_argument("--estimator", choices=("ema", "plain"), default=d.estimator,
                   help="ema: the loss gradient with respect to the texel colours at the running mean of past renders, "
                        "applied to this render (unbiased by this render's noise); plain: at this render "
                        "(default: %(default)s)")
    p.add_argument("--ema-beta", type=float, default=d.ema_beta, help="decay of that mean (default: %(default)s)")
    p.add_argument("--optimizer", choices=("adagrad", "adam"), default=d.optimizer, help="(default: %(default)s)")
    p.add_argument("--lr", type=float, default=d.lr, help="learning rate (default: %(default)s)")
    p.add_argument("--parameterization", choices=("sigmoid", "softmax"), default=d.parameterization,
                   help="mixture parameterisation (default: %(default)s, as in the paper)")
    p.add_argument("--printer-dpi", type=float_tuple(3, "--printer-dpi"), default=d.printer_dpi,
                   help="native printer resolution x,y,z for quantisation (default: 600,300,940)")
    p.add_argument("--ior", type=float, default=d.ior, help="refractive index of the print (default: %(default)s)")
    p.add_argument("--seed", type=int, default=d.seed, help="(default: %(default)s)")
    p.add_argument("--gradient-seed", choices=("same", "independent"), default=d.gradient_seed,
                   help="gradient replay: retrace the forward's paths ('same') or draw independent ones with "
                        "seed_grad ('independent', as Mitsuba's render(seed, seed_grad)) (default: %(default)s)")


def ink_names_help():
    return f"comma-separated ink names from {sorted(INKS)} or a JSON ink file"


def config_from_args(args, **overrides):
    """The :class:`PrintConfig` of parsed arguments (every flag named like a field), with ``overrides``."""
    values = {f.name: getattr(args, f.name) for f in dataclasses.fields(PrintConfig) if hasattr(args, f.name)}
    if "fixed" in values:
        values["fixed"] = tuple(values["fixed"])
    values.update(overrides)
    return PrintConfig(**values)
