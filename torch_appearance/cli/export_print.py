"""``ta-export-print``: write the printer package of a finished print run, for any printer, without optimising again.

Reads a run folder of ta-optimize-print (its quantized.npz, and mixture.npz when the printer's resolution differs
from the run's) and writes a package folder: print.gcvf (GrabCAD Voxel Print, for Stratasys J-series printers),
print.3mf (the object at its printed size coloured by the rendered print, with the per-voxel material volume of
the 3MF Volumetric extension), slices/ (one PNG per layer + palette.json) and export.json. The volume is streamed
layer by layer: memory does not grow with the number of layers. A printer profile is a small JSON file (see
--list-printers and the README); the built-in ones are J750/J850-like at 27 um (j750) and 14 um (j750-hq) layers
and a generic 600 x 600 DPI, 20 um printer (generic).

An existing --out is refused without --force, and so is an --out that another ta-export-print is writing; a run that
ta-optimize-print is writing (or extending with --resume) is refused until it has written its results. export.json
records the run's iteration that was packaged.

Examples:
    ta-export-print results/spot --printer j750
    ta-export-print results/spot --printer j750-hq --format gcvf --out spot-hq --force
    ta-export-print results/colorchecker --printer my_printer.json --format 3mf,slices --halftone blue-noise
    ta-export-print --list-printers
"""
import os
import sys

from ..fabrication.printer import builtin_printers, load_printer
from ..fabrication.quantize import HALFTONES
from ..pipelines.print.package import FORMATS, export_run
from .command import CommandParser, check_output_folder, fail, flag_names, interrupted

__all__ = ["parser", "main"]

PROG = "ta-export-print"


def parser(prog=PROG):
    p = CommandParser(prog, __doc__)
    p.add_argument("run", nargs="?", help="the run folder (ta-optimize-print --out)")
    p.add_argument("--printer", default="j750",
                   help=f"a built-in profile ({', '.join(builtin_printers())}) or a profile JSON file "
                        f"(default: %(default)s)")
    p.add_argument("--format", default="gcvf,3mf",
                   help=f"comma-separated formats from {', '.join(FORMATS)} (default: %(default)s)")
    p.add_argument("--out", default=None, help="the package folder (default: RUN/package-PRINTER)")
    p.add_argument("--force", action="store_true", help="replace an existing package folder")
    p.add_argument("--halftone", choices=HALFTONES, default=None,
                   help="quantise the run's mixture again with this halftoning (default: the run's own volume)")
    p.add_argument("--list-printers", action="store_true", help="list the built-in printer profiles and exit")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    return p


def main(argv=None, prog=PROG):
    """Export with the flags in ``argv``; returns the exit status (2 for refused input, with one line on stderr)."""
    argv = sys.argv[1:] if argv is None else list(argv)
    p = parser(prog)
    args = p.parse_args(argv)
    if args.list_printers:
        for name in builtin_printers():
            profile = load_printer(name)
            print(f"{name:10s} {profile.dpi_xy[0]:g} x {profile.dpi_xy[1]:g} DPI, "
                  f"{profile.layer_thickness_nm / 1000:g} um layers, materials {', '.join(profile.material_names)}")
        return 0
    if args.run is None:
        p.error("run: expected a run folder (or --list-printers)")
    check_output_folder(p, "--out", args.out, writable=False)  # export_run checks it under the name's lock
    formats = [f.strip() for f in args.format.split(",") if f.strip()]
    unknown = [f for f in formats if f not in FORMATS]
    if unknown or not formats:
        p.error(f"--format: expected comma-separated formats from {', '.join(FORMATS)}, got {args.format!r}")
    printer = os.path.abspath(args.printer) if os.path.isfile(args.printer) else args.printer
    try:
        export_run(args.run, args.out, printer, formats, halftone=args.halftone, force=args.force,
                   progress=not args.quiet)
    except (ValueError, TypeError, FileNotFoundError) as error:
        return fail(prog, error, flag_names(p, formats="--format"), vars(args))
    except KeyboardInterrupt:  # the package is written under a temporary name, removed as the write unwinds
        return interrupted(prog, "nothing was written (an existing package is as it was)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
