"""Detect tree-ring boundaries on an increment core scan (core mode), along a transect of a board photo, or along
several pith -> bark transects of a whole-disc photo (disc mode).

Core mode (default): rings cross the core's long axis; the bark (youngest rings) is at the side found from the rings'
shape (each ring's sharp latewood -> earlywood step faces the bark), or given by --bark (a warning when the rings
clearly say otherwise). Transect mode: --transect X0,Y0,X1,Y1 in pixels, drawn from
the pith towards the bark (filters the whole image; for discs use disc mode). The boundary is the sharp latewood ->
earlywood transition (torch_appearance.rings.dendro). Writes a CSV with columns index,x_px,y_px,width_px,width_mm
ordered pith -> bark (width to the previous boundary; empty for the first, width_mm empty without --dpi /
--pixel-size-mm).
Disc mode (--mode disc, implied by --pith, --angles or --edge): the pith is --pith X,Y, or found from the ring
orientation field (--pith auto, the default; its position and standard error are printed). Transects run from the
pith outwards, given as --angles A1,A2,... (degrees from the +x axis
towards +y, i.e. clockwise on screen: 0 = right, 90 = down, 180 = left, 270 = up; each runs to the disc edge or the
image border) and/or repeated --transect X,Y (the bark-side end point in pixels); default: --angles 0,90,180,270.
Only a narrow polar strip around each transect is resampled and filtered, once (torch_appearance.rings.disc).
Each ring boundary is then followed round the disc to the neighbouring transects (and to --helpers helper
transects between them); a ring that the curves from both neighbours agree on and that the transect missed is
added as inferred (torch_appearance.rings.consistency; --no-link to turn this off).
Writes one CSV with columns transect,angle_deg,index,kind,x_px,y_px,radius_px,width_px,width_mm (kind: ring,
inferred, pith_edge for the pith's own edge with --pith-edge, or edge for the disc edge with --edge), the whole rings
that close round the disc as labelme-style JSON polygons (--rings, default NAME_rings.json beside --out;
torch_appearance.rings.ring_polygons) and one overlay with all transects (inferred boundaries: a tick with a dot) and
the rings' polygons.
Section mode (--mode section): a stained microscopy cross-section; writes the boundary polyline (index,x_px,y_px,
about 1 px apart; header only if none was found); --cell-px is the typical cell diameter in pixels.

Examples:
    ta-detect-rings core.png --bark left --dpi 1200 --out rings.csv --overlay rings.png
    ta-detect-rings board.jpg --transect 512,500,980,130 --pixel-size-mm 0.05 --out board.csv
    ta-detect-rings disc.jpg --pith 1520,1610 --angles 0,90,180,270 --out disc.csv --overlay disc.png
    ta-detect-rings disc.jpg --pith 1520,1610 --transect 2900,1650 --transect 1480,40 --out disc.csv
    ta-detect-rings disc.jpg --mode disc --dpi 600 --out disc.csv --pos disc.pos --rwl disc.rwl --last-year 2019
    ta-detect-rings section.png --mode section --out boundary.csv --overlay boundary.png
"""
import math
import os
import re
import sys
import warnings

import cv2
import numpy as np

from torch_appearance.io import atomic_write_bytes, read_image, write_csv
from torch_appearance.rings.dendro import detect_core_boundaries, detect_transect_boundaries
from torch_appearance.rings.section import detect_section_boundaries
from torch_appearance.rings.coorecorder import write_pos
from torch_appearance.rings.disc import MAX_HALF_WIDTH, MAX_HELPERS, MIN_HALF_WIDTH, detect_disc_boundaries
from torch_appearance.rings.ring_polygons import draw_ring_polygons, labelme_json, ring_polygons
from torch_appearance.rings.tucson import RingSeries, write_rwl

from .command import CommandParser, check_output_file, fail

PROG = "ta-detect-rings"


def parse_args(argv=None):
    p = CommandParser(PROG, __doc__)
    p.add_argument("image", help="core scan or photo (sRGB PNG/JPEG/TIFF/BMP/WebP or linear EXR; truncated or corrupt "
                                  "files are refused)")
    p.add_argument("--out", required=True, help="output CSV")
    p.add_argument("--overlay", default=None, help="optional overlay PNG with the detected boundaries")
    p.add_argument("--bark", choices=("left", "right", "top", "bottom"), default=None,
                   help="core mode: side with the bark (default: found from the rings' shape, the sharp latewood -> "
                        "earlywood steps facing the bark; a given side that the rings clearly contradict is warned of)")
    p.add_argument("--transect", action="append", default=None,
                   help="transect mode: X0,Y0,X1,Y1 in pixels, pith -> bark; disc mode (with --pith): X,Y, the "
                        "transect's bark-side end (repeat for several transects)")
    p.add_argument("--pith", default=None,
                   help="disc mode: pith position X,Y in pixels, or 'auto' (the default in disc mode): found from the "
                        "ring orientation field, with its uncertainty")
    p.add_argument("--angles", default=None,
                   help="disc mode: transect angles in degrees, comma-separated (from +x towards +y, clockwise on "
                        "screen: 0 right, 90 down); default 0,90,180,270 when no --transect is given")
    p.add_argument("--edge", action="store_true",
                   help="disc mode: report the disc edge (outer end of the last ring) as the last boundary")
    p.add_argument("--rings", default=None,
                   help="disc mode: the whole rings (closed curves chained round the disc from the linked transects) "
                        "as labelme-style JSON polygons (default: beside --out, NAME_rings.json); drawn on --overlay")
    p.add_argument("--pith-edge", action="store_true",
                   help="disc mode: find the pith's own edge as a closed curve round the pith and put it on every "
                        "transect as the innermost boundary (kind pith_edge), dropping boundaries inside it; off by "
                        "default (it gained on one human-labelled disc and lost on the other)")
    p.add_argument("--bark-gaps", type=int, default=0,
                   help="disc mode: look for a narrow ring the passes skipped in each of this many gaps before the "
                        "bark, where the profile rises sharply (default: %(default)s, none)")
    p.add_argument("--no-link", action="store_true",
                   help="disc mode: do not follow the rings between transects (no inferred rings)")
    p.add_argument("--helpers", type=int, default=1,
                   help="disc mode: helper transects between neighbouring transects, evidence for linking only "
                        "(default: %(default)s)")
    p.add_argument("--half-width", type=int, default=16,
                   help="disc mode: half-width of the strip filtered around each transect, px (default: %(default)s)")
    size = p.add_mutually_exclusive_group()
    size.add_argument("--dpi", type=float, default=None, help="scan resolution (pixel size 25.4 / dpi mm)")
    size.add_argument("--pixel-size-mm", type=float, default=None, help="pixel size in mm")
    p.add_argument("--width-px", type=int, default=32, help="core mode: uniform core width (default: %(default)s)")
    p.add_argument("--mode", choices=("core", "disc", "section"), default=None,
                   help="core (also transect with --transect), disc (also implied by --pith, --angles or --edge) or "
                        "section (microscopy); default: core")
    p.add_argument("--cell-px", type=float, default=8.0,
                   help="section mode: cell diameter in px (default: %(default)s)")
    files = p.add_argument_group("files for dendrochronology programs (need --dpi or --pixel-size-mm)")
    files.add_argument("--pos", default=None,
                       help="CooRecorder coordinate file (.pos, mm; the pith first in disc mode); disc mode writes one "
                            "per transect, NAME_t0.pos, NAME_t1.pos, ...")
    files.add_argument("--rwl", default=None,
                       help="Tucson ring-width file (.rwl, 0.001 mm) with one series per transect (or the core), for "
                            "dplR, CDendro, COFECHA; needs --last-year")
    files.add_argument("--last-year", type=int, default=None,
                       help="calendar year of the outermost measured ring (dates the .rwl series and the .pos file)")
    files.add_argument("--series-id", default=None,
                       help="Tucson series id, at most 6 characters in disc mode (the transect number is appended) and "
                            "8 otherwise (default: from the image file name)")
    args = p.parse_args(argv)
    check_output_file(p, "--out", args.out)
    check_output_file(p, "--overlay", args.overlay)
    check_output_file(p, "--pos", args.pos)
    check_output_file(p, "--rwl", args.rwl)
    check_output_file(p, "--rings", args.rings)
    return args


def _series_id(args, width):
    """The Tucson id stem: ``--series-id``, else the image's file name (letters and digits), at most ``width``."""
    if args.series_id is not None:
        if not re.fullmatch(r"[A-Za-z0-9_.-]{1,%d}" % width, args.series_id):
            raise ValueError(f"--series-id: expected 1 to {width} letters, digits, '_', '.' or '-'; got "
                             f"{args.series_id!r}")
        return args.series_id
    stem = re.sub(r"[^A-Za-z0-9]", "", os.path.splitext(os.path.basename(args.image))[0])
    return (stem or "series")[:width]


def check_ring_file_args(args):
    """ValueError for --pos / --rwl without a pixel size, --rwl without --last-year, or in section mode; for
    --last-year without either file (it dates them only: it was ignored without a word) or outside the Tucson
    format's 4-column year field."""
    if args.last_year is not None:
        if args.pos is None and args.rwl is None:
            raise ValueError("--last-year: it dates the ring files; give --pos or --rwl, or leave it out")
        if not -999 <= args.last_year <= 9999:
            raise ValueError(f"--last-year: expected a year in -999 ... 9999 (the 4-column year of the Tucson "
                             f"format), got {args.last_year}")
    if args.pos is None and args.rwl is None:
        return
    if args.mode == "section":
        raise ValueError("--pos / --rwl: a microscopy section has no ring series (drop them or --mode section)")
    if args.dpi is None and args.pixel_size_mm is None:
        raise ValueError("--pos / --rwl are in millimetres: give the image's --dpi or --pixel-size-mm")
    if args.rwl is not None and args.last_year is None:
        raise ValueError("--rwl: give --last-year, the calendar year of the outermost measured ring")
    _series_id(args, 6 if args.mode == "disc" else 8)


def write_ring_files(args, transects, pith=None):
    """Write ``--pos`` and ``--rwl`` for the ring boundaries of one or more transects (:class:`RingBoundaries`, pith →
    bark). With the pith (disc mode) each series starts with the ring around the pith; without it (a core or a
    board transect) with the ring after the first boundary. Returns the files written."""
    if args.pos is None and args.rwl is None:
        return []
    dpi = args.dpi if args.dpi is not None else 25.4 / args.pixel_size_mm
    mm = 25.4 / dpi
    disc = pith is not None
    written, series = [], []
    stem = _series_id(args, 6 if disc else 8)
    for k, tr in enumerate(transects):
        pts = np.asarray(tr.points, np.float64).reshape(-1, 2)
        if args.pos is not None and len(pts):
            base, ext = os.path.splitext(args.pos)
            path = f"{base}_t{k}{ext or '.pos'}" if disc else args.pos
            write_pos(path, pts, dpi, pith_px=pith, image_file=args.image, last_year=args.last_year,
                      program=PROG)
            written.append(path)
        if args.rwl is not None:
            if disc:
                widths = np.diff(np.r_[0.0, np.asarray(tr.info["radius_px"], np.float64)]) * mm
            else:
                widths = np.asarray(tr.widths_px, np.float64)[1:] * mm  # the CSV's widths
            if len(widths):
                series.append(RingSeries.ending(f"{stem}{k:02d}" if disc else stem, args.last_year, widths))
    if args.rwl is not None:
        if not series:
            raise ValueError("--rwl: no ring was found, so there is no ring-width series to write")
        write_rwl(args.rwl, series)
        written.append(args.rwl)
    return written


def overlay_png(rgb, points, transect=None, polyline=False):
    """uint8 BGR-encoded PNG bytes of the image with boundary ticks (red) and the transect (cyan), or the boundary
    polyline (red) when ``polyline``."""
    img = np.ascontiguousarray((np.clip(rgb, 0, 1) * 255 + 0.5).astype(np.uint8)[..., ::-1])
    h, w = img.shape[:2]
    if polyline:
        if len(points) >= 2:
            cv2.polylines(img, [np.round(np.asarray(points)).astype(np.int32)], False, (0, 0, 255), 1)
        points = []
    if transect is not None:
        x0, y0, x1, y1 = transect
        cv2.line(img, (int(round(x0)), int(round(y0))), (int(round(x1)), int(round(y1))), (255, 255, 0), 1)
    horizontal = w >= h
    for i, (x, y) in enumerate(points):
        if transect is None:
            a = (int(round(x)), 0) if horizontal else (0, int(round(y)))
            b = (int(round(x)), h - 1) if horizontal else (w - 1, int(round(y)))
            cv2.line(img, a, b, (0, 0, 255), 1)
        else:
            cv2.circle(img, (int(round(x)), int(round(y))), 3, (0, 0, 255), 1)
    ok, buf = cv2.imencode(".png", img)
    if not ok:
        raise ValueError("could not encode the overlay PNG")
    return buf.tobytes()


_COLOURS = [(0, 0, 255), (0, 200, 0), (255, 128, 0), (255, 0, 255), (0, 200, 255), (255, 255, 0), (128, 0, 255),
            (0, 128, 255)]


def disc_overlay_png(rgb, res, polygons=()):
    """PNG bytes of the disc with the whole rings' polygons (yellow and magenta in turn), each transect (its own
    colour), a tick across it at every boundary (with a dot when inferred from the neighbouring transects, a circle
    at the edge) and its number at the outer end; the pith is a white cross, the pith's edge (``--pith-edge``) a white
    curve round it."""
    img = np.ascontiguousarray((np.clip(rgb, 0, 1) * 255 + 0.5).astype(np.uint8)[..., ::-1])
    draw_ring_polygons(img, polygons)
    h, w = img.shape[:2]
    thick = max(1, int(round(max(h, w) / 1500)))
    tick = 4 * thick + 2
    c = res.pith
    for k, (tr, end) in enumerate(zip(res.transects, res.ends)):
        col = _COLOURS[k % len(_COLOURS)]
        cv2.line(img, (int(round(c[0])), int(round(c[1]))), (int(round(end[0])), int(round(end[1]))), col, thick)
        th = np.radians(res.angles_deg[k])
        n = np.array([-np.sin(th), np.cos(th)])
        for (x, y), kind in zip(tr.points, tr.info.get("kind", [])):
            if kind == "edge":
                cv2.circle(img, (int(round(x)), int(round(y))), tick, col, thick)
            else:
                a, b = np.array([x, y]) - tick * n, np.array([x, y]) + tick * n
                cv2.line(img, tuple(int(round(t)) for t in a), tuple(int(round(t)) for t in b), col, thick)
                if kind == "inferred":
                    cv2.circle(img, (int(round(x)), int(round(y))), thick + 1, col, -1)
        pos = (int(np.clip(end[0], 0, w - 30)), int(np.clip(end[1], 15, h - 5)))
        cv2.putText(img, str(k), pos, cv2.FONT_HERSHEY_SIMPLEX, 0.5 * thick, col, thick)
    pe = res.info.get("pith_edge")
    if pe is not None and pe["found"]:  # the pith's edge round the pith (--pith-edge), white
        pts = np.c_[c[0] + pe["radius"] * np.cos(pe["thetas"]), c[1] + pe["radius"] * np.sin(pe["thetas"])]
        cv2.polylines(img, [np.round(pts).astype(np.int32).reshape(-1, 1, 2)], True, (255, 255, 255), thick,
                      cv2.LINE_AA)
    cx, cy = int(round(c[0])), int(round(c[1]))
    cv2.drawMarker(img, (cx, cy), (255, 255, 255), cv2.MARKER_CROSS, 4 * tick, thick)
    ok, buf = cv2.imencode(".png", img)
    if not ok:
        raise ValueError("could not encode the overlay PNG")
    return buf.tobytes()


def _numbers(text, name, count=None):
    try:
        vals = [float(t) for t in text.split(",")]
    except ValueError:
        raise ValueError(f"{name} must be comma-separated numbers; got {text!r}") from None
    if count is not None and len(vals) != count:
        raise ValueError(f"{name} must be {count} numbers; got {text!r}")
    if not all(np.isfinite(vals)):
        raise ValueError(f"{name} must be finite numbers; got {text!r}")
    return vals


def run_disc(args, rgb):
    """Disc mode: returns the exit code (writes the CSV and the overlay)."""
    try:
        pith = "auto" if args.pith in (None, "auto") else _numbers(args.pith, "--pith (X,Y or auto)", 2)
        angles = _numbers(args.angles, "--angles") if args.angles is not None else None
        ends = [_numbers(t, "--transect in disc mode (the end point X,Y)", 2) for t in (args.transect or [])]
    except ValueError as e:
        return fail(PROG, str(e))
    from ..progress import progress_bar

    def progress(k, n):
        bar.total = n
        bar.update(1)

    with progress_bar(total=(len(angles or []) + len(ends)) or 4, desc="transects", unit="transect",
                      disable=None) as bar:
        try:
            res = detect_disc_boundaries(rgb, pith, angles_deg=angles, ends=ends or None, include_edge=args.edge,
                                         half_width=args.half_width, dpi=args.dpi, pixel_size_mm=args.pixel_size_mm,
                                         link=not args.no_link, helpers=args.helpers, pith_edge=args.pith_edge,
                                         bark_gaps=args.bark_gaps,
                                         progress=progress)
            polygons = ring_polygons(res)
            png = disc_overlay_png(rgb, res, polygons) if args.overlay else None
        except ValueError as e:
            return fail(PROG, str(e))
    found = res.info["pith"]
    if found["auto"]:
        print(f"pith (auto): {found['xy'][0]:.1f},{found['xy'][1]:.1f} px, standard error {found['sigma_px']:.1f} px "
              f"(give --pith X,Y to set it)", file=sys.stderr)
    rows = []
    for k, tr in enumerate(res.transects):
        for i, ((x, y), kind, r, wp, wm) in enumerate(zip(tr.points, tr.info["kind"], tr.info["radius_px"],
                                                          tr.widths_px, tr.widths_mm)):
            rows.append(dict(transect=k, angle_deg=f"{res.angles_deg[k]:.2f}", index=i, kind=kind, x_px=f"{x:.2f}",
                             y_px=f"{y:.2f}", radius_px=f"{r:.2f}",
                             width_px="" if not np.isfinite(wp) else f"{wp:.2f}",
                             width_mm="" if not np.isfinite(wm) else f"{wm:.4f}"))
    write_csv(args.out, rows, ["transect", "angle_deg", "index", "kind", "x_px", "y_px", "radius_px", "width_px",
                               "width_mm"])
    rings_path = args.rings if args.rings is not None else os.path.splitext(args.out)[0] + "_rings.json"
    atomic_write_bytes(rings_path, labelme_json(polygons, os.path.basename(args.image), rgb.shape,
                                                pith=res.pith).encode())
    if png is not None:
        atomic_write_bytes(args.overlay, png)
    try:
        extra = write_ring_files(args, res.transects, pith=res.pith)
    except ValueError as e:
        return fail(PROG, str(e))
    counts = ", ".join(str(len(tr.points)) for tr in res.transects)
    inferred = [[i for i, kind in enumerate(tr.info["kind"]) if kind == "inferred"] for tr in res.transects]
    if any(inferred):
        print("inferred from the neighbouring transects (boundary index from the pith): "
              + "; ".join(f"transect {k}: {v}" for k, v in enumerate(inferred) if v), file=sys.stderr)
    print(f"{len(rows)} boundaries on {len(res.transects)} transects ({counts}); filtered "
          f"{res.info['filtered_px']} px ({100.0 * res.info['filtered_px'] / res.info['image_px']:.1f} % of the "
          f"image); {len(polygons)} whole rings closed round the disc -> {', '.join([args.out, rings_path] + extra)}")
    return 0


def main(argv=None):
    args = parse_args(argv)
    for flag, value in (("--dpi", args.dpi), ("--pixel-size-mm", args.pixel_size_mm), ("--cell-px", args.cell_px)):
        if value is not None and not (math.isfinite(value) and value > 0):  # --dpi 1e12 is a size, nan is not
            return fail(PROG, f"{flag}: expected a finite value > 0, got {value}")
    # checked in every mode (they were accepted silently outside the one that reads them)
    if not 0 <= args.helpers <= MAX_HELPERS:
        return fail(PROG, f"--helpers: expected 0 ... {MAX_HELPERS} (helper transects between neighbours), got "
                          f"{args.helpers}")
    if not MIN_HALF_WIDTH <= args.half_width <= MAX_HALF_WIDTH:
        return fail(PROG, f"--half-width: expected {MIN_HALF_WIDTH} ... {MAX_HALF_WIDTH} (px of arc either side of a "
                          f"transect; the cost grows with it), got {args.half_width}")
    if not 0 <= args.bark_gaps <= 50:
        return fail(PROG, f"--bark-gaps: expected an int in [0, 50] (gaps before the bark), got {args.bark_gaps}")
    if args.width_px < 8:  # the library's message offers None, which the command line cannot give
        return fail(PROG, f"--width-px: expected an int >= 8 (px), got {args.width_px}")
    if args.rings is not None and args.mode in ("core", "section"):
        return fail(PROG, f"--rings is disc mode; it does not combine with --mode {args.mode}")
    implied = args.pith is not None or args.angles is not None or args.edge or args.rings is not None
    if implied and args.mode in ("core", "section"):
        return fail(PROG, f"--pith / --angles / --edge are disc mode; they do not combine with --mode {args.mode}")
    disc = implied or args.mode == "disc"
    args.mode = "disc" if disc else (args.mode or "core")
    if disc and args.bark is not None:
        return fail(PROG, "--bark is for cores; in disc mode (--pith, --angles, --edge or --mode disc) the transects run "
                          "from the pith outwards")
    if not disc and args.transect is not None and len(args.transect) > 1:
        return fail(PROG, "several --transect need disc mode (--mode disc, or --pith X,Y): each is a transect's end "
                          "X,Y")
    try:
        check_ring_file_args(args)
    except ValueError as e:
        return fail(PROG, str(e))
    try:
        rgb = read_image(args.image, space="srgb", name="image")  # decoded fully: truncated files are refused
    except (OSError, ValueError) as e:
        return fail(PROG, f"cannot read image {args.image!r}: {e}")
    if disc:
        return run_disc(args, rgb)
    transect = None
    if args.transect is not None:
        try:
            transect = tuple(float(t) for t in args.transect[0].split(","))
            if len(transect) != 4:
                raise ValueError
        except ValueError:
            return fail(PROG, f"--transect must be X0,Y0,X1,Y1 (four numbers); got {args.transect[0]!r}")
    if args.mode == "section" and (transect is not None or args.bark is not None):
        return fail(PROG, "--transect / --bark do not apply to --mode section")
    try:
        if args.mode == "section":
            sec = detect_section_boundaries(rgb, cell_px=args.cell_px)
            rows = [dict(index=i, x_px=f"{x:.2f}", y_px=f"{y:.2f}") for i, (x, y) in enumerate(sec.points)]
            png = overlay_png(rgb, sec.points, polyline=True) if args.overlay else None
    except ValueError as e:
        return fail(PROG, str(e))
    if args.mode == "section":
        write_csv(args.out, rows, ["index", "x_px", "y_px"])
        if png is not None:
            atomic_write_bytes(args.overlay, png)
        print(f"boundary polyline of {len(rows)} points -> {args.out}")
        return 0
    try:
        if transect is not None:
            res = detect_transect_boundaries(rgb, transect, dpi=args.dpi, pixel_size_mm=args.pixel_size_mm)
        else:
            with warnings.catch_warnings(record=True) as caught:  # a contradicted --bark: one line on stderr
                warnings.simplefilter("always")
                res = detect_core_boundaries(rgb, bark=args.bark, width_px=args.width_px, dpi=args.dpi,
                                             pixel_size_mm=args.pixel_size_mm)
            for w in caught:
                print(f"{PROG}: warning: {w.message}", file=sys.stderr)
            growth = res.info["growth"]
            if args.bark is None:
                print(f"bark on the {res.info['bark']} (from the rings' shape, z = {growth['z']:.1f}"
                      f"{'' if growth['confident'] else '; not confident: check it and give --bark'})",
                      file=sys.stderr)
        rows = [dict(index=i, x_px=f"{x:.2f}", y_px=f"{y:.2f}",
                     width_px="" if not np.isfinite(wp) else f"{wp:.2f}",
                     width_mm="" if not np.isfinite(wm) else f"{wm:.4f}")
                for i, ((x, y), wp, wm) in enumerate(zip(res.points, res.widths_px, res.widths_mm))]
        png = overlay_png(rgb, res.points, transect) if args.overlay else None
    except ValueError as e:
        return fail(PROG, e, flags={"width_px": "--width-px"})
    write_csv(args.out, rows, ["index", "x_px", "y_px", "width_px", "width_mm"])
    if png is not None:
        atomic_write_bytes(args.overlay, png)
    try:
        extra = write_ring_files(args, [res])
    except ValueError as e:
        return fail(PROG, str(e))
    print(f"{len(rows)} boundaries -> {', '.join([args.out] + extra)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
