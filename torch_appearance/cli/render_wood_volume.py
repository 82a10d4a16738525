"""Render a fitted (or synthetic) wood model as a translucent volume: a backlit veneer sheet, fitted vs extruded,
and a lamp shade cut from the model (wood paper §4.2, Figs. 6 and 7).

σ_t follows the lateness of growth between early- and latewood density (default 6.5 and 16.0 mm⁻¹), the albedo per
RGB channel comes from the model's colour map through the surface colour → albedo mapping measured with our tracer
(``--mapping elek``: the Elek et al. 2017 polynomial instead). The veneer (default 1.8 mm) is lit by a distant disc
light behind it and seen from the front and from its edge; the "extruded" volume repeats the surface pattern along
the normal into the depth. The lamp shade is an open conical shell lit through its lower opening (the tracer has
only distant lights; see torch_appearance/pipelines/wood_volume_render.py).

Writes to --out: veneer_fit.exr/.png, veneer_extruded.exr/.png, veneer_side_fit/extruded.exr/.png,
lampshade.exr/.png, figure.png (side by side) and summary.json (settings, volume statistics, timings).

Examples:
    ta-render-wood-volume --synthetic 3 --out results/wood_volume
    ta-render-wood-volume results/board --out results/board_volume --spp 64 --passes 8
    ta-render-wood-volume --synthetic 3 --device cuda --out results/wood_volume_gpu
"""
import math
import sys

from torch_appearance.pipelines.wood_volume_render import LampshadeGeometry, WoodVolumeConfig, render_wood_volume

from .command import (CommandParser, add_device_argument, check_output_folder, fail, flag_names, interrupted,
                      interrupted_message, owned_folder, resolve_device)

PROG = "ta-render-wood-volume"


def parse_args(argv=None):
    d = WoodVolumeConfig()
    s = d.shade
    p = CommandParser(PROG, __doc__)
    p.add_argument("fit_dir", nargs="?", default=None, help="run folder of ta-fit-wood (model.json, "
                   "model.pt, params.json)")
    p.add_argument("--synthetic", type=int, metavar="SEED", default=None,
                   help="use the synthetic board of this seed (rings.synthetic_board) instead of a fit")
    p.add_argument("--synthetic-size", type=int, nargs=2, default=d.synthetic_hw, metavar=("ROWS", "COLS"),
                   help="synthetic board size in pixels (default: %(default)s)")
    p.add_argument("--synthetic-pixel-mm", type=float, default=d.synthetic_pixel_mm,
                   help="synthetic board pixel size (default: %(default)s)")
    p.add_argument("--out", default=d.out, help="output folder (default: %(default)s)")
    p.add_argument("--thickness-mm", type=float, default=d.thickness_mm, help="veneer thickness (default: %(default)s)")
    p.add_argument("--veneer-voxel-mm", type=float, nargs=2, default=d.veneer_voxel_mm, metavar=("LATERAL", "DEPTH"),
                   help="veneer voxel edges (default: %(default)s)")
    p.add_argument("--veneer-max-mm", type=float, default=d.veneer_max_extent_mm,
                   help="largest veneer side; the board's centre is used (default: %(default)s)")
    p.add_argument("--pixel-mm", type=float, default=d.veneer_resolution_mm,
                   help="veneer image pixel pitch (default: %(default)s)")
    p.add_argument("--shade", type=float, nargs=4, default=(s.bottom_radius_mm, s.top_radius_mm, s.height_mm,
                   s.thickness_mm), metavar=("R_BOTTOM", "R_TOP", "HEIGHT", "WALL"),
                   help="lamp shade in mm (default: %(default)s)")
    p.add_argument("--shade-voxel-mm", type=float, default=s.voxel_mm, help="(default: %(default)s)")
    p.add_argument("--shade-light-deg", type=float, default=None,
                   help="angular radius of the light below the shade (default: 0.9 × the wall's tilt)")
    p.add_argument("--shade-resolution", type=int, nargs=2, default=d.shade_resolution, metavar=("ROWS", "COLS"),
                   help="(default: %(default)s)")
    p.add_argument("--sigma-early", type=float, default=d.sigma_early, help="mm⁻¹ (default: %(default)s)")
    p.add_argument("--sigma-late", type=float, default=d.sigma_late, help="mm⁻¹ (default: %(default)s)")
    p.add_argument("--mapping", choices=("table", "elek"), default=d.mapping,
                   help="surface colour → albedo (default: %(default)s)")
    p.add_argument("--spp", type=int, default=d.spp, help="samples per pixel and pass (default: %(default)s)")
    p.add_argument("--shade-spp", type=int, default=d.shade_spp,
                   help="lamp-shade samples per pixel and pass (default: %(default)s)")
    p.add_argument("--passes", type=int, default=d.passes, help="passes per image (default: %(default)s)")
    p.add_argument("--seed", type=int, default=d.seed)
    p.add_argument("--threads", type=int, default=d.threads, help="torch threads (0: torch's default)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    add_device_argument(p)
    args = p.parse_args(argv)
    if (args.fit_dir is None) == (args.synthetic is None):
        p.error("give either FIT_DIR or --synthetic SEED (exactly one)")
    check_output_folder(p, "--out", args.out)
    check_sizes(p, args)
    args.device = str(resolve_device(p, args.device, log=print))
    args.flags = flag_names(p, height="--synthetic-size", width="--synthetic-size",
                            pixel_size_mm="--synthetic-pixel-mm", voxel_mm="--veneer-voxel-mm",
                            extent_mm="--veneer-max-mm", resolution="--shade-resolution",
                            synthetic_seed="--synthetic", fit_dir="fit_dir", angular_radius_deg="--shade-light-deg")
    return args


#: bytes per pixel of a synthetic board while it is drawn (250-420 measured at 1024² and 256², peak RSS)
SYNTHETIC_BYTES_PER_PIXEL = 512
#: the narrowest ring of a synthetic board (mm; rings.synthetic_board draws 1-4 mm): a pixel should not be wider
SYNTHETIC_RING_MM = 1.0
#: the least time a pass takes (one render of the smallest image) and the longest job admitted, as ta-optimize-print
MIN_PASS_S = 1e-3
MAX_JOB_S = 365.25 * 86400


def check_sizes(p, args):
    """Refuse (one line, exit 2, before any work) sizes that are not finite and > 0, a synthetic board that does not
    fit in memory or whose pixels are wider than its rings, a veneer image or volume under a few pixels or voxels
    (they became 1 pixel or voxel without a word), passes that cannot end within a year, and more threads than the
    machine has CPUs (an overflow from torch)."""
    import os

    from ..pipelines.runs import check_memory

    def positive(flag, values):
        values = values if isinstance(values, (list, tuple)) else [values]
        if not all(math.isfinite(v) and v > 0 for v in values):
            p.error(f"{flag}: expected finite values > 0, got {' '.join(f'{v:g}' for v in values)}")

    positive("--synthetic-pixel-mm", args.synthetic_pixel_mm)
    positive("--thickness-mm", args.thickness_mm)
    positive("--veneer-voxel-mm", args.veneer_voxel_mm)
    positive("--veneer-max-mm", args.veneer_max_mm)
    positive("--pixel-mm", args.pixel_mm)
    positive("--shade", args.shade)
    positive("--shade-voxel-mm", args.shade_voxel_mm)
    if args.shade_voxel_mm > args.shade[3]:
        p.error(f"--shade-voxel-mm: expected at most the shade's wall, {args.shade[3]:g} mm (a coarser grid holds no "
                f"wall), got {args.shade_voxel_mm:g}")
    if args.synthetic is not None:
        if args.synthetic < 0:
            p.error(f"--synthetic: expected a seed >= 0, got {args.synthetic}")
        rows, cols = args.synthetic_size
        if min(rows, cols) < 8:
            p.error(f"--synthetic-size: expected at least 8 × 8 px, got {rows} × {cols}")
        if args.synthetic_pixel_mm > SYNTHETIC_RING_MM:
            p.error(f"--synthetic-pixel-mm: expected at most {SYNTHETIC_RING_MM:g} mm (the narrowest synthetic ring: "
                    f"a wider pixel draws no rings), got {args.synthetic_pixel_mm:g}")
        try:
            check_memory("--synthetic-size", rows * cols * SYNTHETIC_BYTES_PER_PIXEL, f"a {rows} × {cols} px "
                         f"synthetic board", "draw a smaller one")
        except ValueError as error:
            p.error(str(error))
    side = args.veneer_max_mm
    if side / args.pixel_mm < 2:  # the image was silently 1 pixel wide
        p.error(f"--pixel-mm: expected at most {side / 2:g} mm (2 pixels across the --veneer-max-mm {side:g} mm "
                f"veneer), got {args.pixel_mm:g}")
    lateral, depth = args.veneer_voxel_mm
    if side / lateral < 4 or args.thickness_mm / depth < 2:
        p.error(f"--veneer-voxel-mm: expected at most {side / 4:g} {args.thickness_mm / 2:g} mm (4 voxels across the "
                f"{side:g} mm veneer, 2 through its {args.thickness_mm:g} mm), got {lateral:g} {depth:g}")
    if args.passes * MIN_PASS_S > MAX_JOB_S:
        p.error(f"--passes: {args.passes} passes take at least {args.passes * MIN_PASS_S / MAX_JOB_S:.3g} years (a "
                f"pass takes at least {MIN_PASS_S * 1e3:g} ms); expected at most {int(MAX_JOB_S / MIN_PASS_S)}")
    cpus = os.cpu_count() or 1
    if args.threads > cpus:
        p.error(f"--threads: expected at most {cpus} (this machine's CPUs; 0: torch's default), got {args.threads}")


def main(argv=None):
    args = parse_args(argv)
    try:  # the shade's own names: its radii, height and wall are --shade, its voxel --shade-voxel-mm
        shade = LampshadeGeometry(*args.shade, voxel_mm=args.shade_voxel_mm)
    except (ValueError, TypeError) as error:
        return fail(PROG, error, dict(args.flags, bottom_radius_mm="--shade", top_radius_mm="--shade",
                                      height_mm="--shade", thickness_mm="--shade", voxel_mm="--shade-voxel-mm"))
    try:
        cfg = WoodVolumeConfig(out=args.out, fit_dir=args.fit_dir, synthetic_seed=args.synthetic,
                               synthetic_hw=tuple(args.synthetic_size), synthetic_pixel_mm=args.synthetic_pixel_mm,
                               thickness_mm=args.thickness_mm, veneer_voxel_mm=tuple(args.veneer_voxel_mm),
                               veneer_max_extent_mm=args.veneer_max_mm, veneer_resolution_mm=args.pixel_mm,
                               shade=shade, shade_light_deg=args.shade_light_deg,
                               shade_resolution=tuple(args.shade_resolution),
                               sigma_early=args.sigma_early, sigma_late=args.sigma_late, mapping=args.mapping,
                               spp=args.spp, shade_spp=args.shade_spp, passes=args.passes, seed=args.seed,
                               threads=args.threads, device=args.device)
        with owned_folder(PROG, args.out, "render"):  # another tool's folder or one being written: refused
            render_wood_volume(cfg, progress=not args.quiet)
    except (ValueError, TypeError) as error:
        return fail(PROG, error, args.flags, vars(args))
    except KeyboardInterrupt as stop:
        return interrupted(PROG, interrupted_message(stop))
    return 0


if __name__ == "__main__":
    sys.exit(main())
