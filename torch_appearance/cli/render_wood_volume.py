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
import sys

from torch_appearance.pipelines.wood_volume_render import LampshadeGeometry, WoodVolumeConfig, render_wood_volume

from .command import (CommandParser, add_device_argument, check_output_folder, fail, interrupted,
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
    args.device = str(resolve_device(p, args.device, log=print))
    return args


def main(argv=None):
    args = parse_args(argv)
    try:
        shade = LampshadeGeometry(*args.shade, voxel_mm=args.shade_voxel_mm)
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
        return fail(PROG, error)
    except KeyboardInterrupt as stop:
        return interrupted(PROG, interrupted_message(stop))
    return 0


if __name__ == "__main__":
    sys.exit(main())
