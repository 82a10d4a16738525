#!/usr/bin/env python
"""Detect tree-ring boundaries on an increment core scan (core mode) or along a transect of a disc / board photo.

Core mode (default): rings cross the core's long axis; the bark (youngest rings) is at the side given by --bark
(default: right for wide images, bottom for tall ones). Transect mode: --transect X0,Y0,X1,Y1 in pixels, drawn from
the pith towards the bark. The boundary is the sharp latewood -> earlywood transition
(torch_appearance.rings.dendro). Writes a CSV with columns index,x_px,y_px,width_px,width_mm ordered pith -> bark
(width to the previous boundary; empty for the first, width_mm empty without --dpi / --pixel-size-mm).
Section mode (--mode section): a stained microscopy cross-section; writes the boundary polyline (index,x_px,y_px,
about 1 px apart; header only if none was found); --cell-px is the typical cell diameter in pixels.

Examples:
    python scripts/detect_rings.py core.png --bark left --dpi 1200 --out rings.csv --overlay rings.png
    python scripts/detect_rings.py disc.jpg --transect 512,500,980,130 --pixel-size-mm 0.05 --out disc.csv
    python scripts/detect_rings.py section.png --mode section --out boundary.csv --overlay boundary.png
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
import cv2
import numpy as np

from torch_appearance.io import atomic_write_bytes, read_image, write_csv
from torch_appearance.rings.dendro import (detect_core_boundaries, detect_section_boundaries,
                                           detect_transect_boundaries)

PROG = "detect_rings.py"


def parse_args(argv=None):
    p = argparse.ArgumentParser(prog=PROG, description=__doc__.split("\n\n")[0], epilog=__doc__.split("\n\n", 1)[1],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("image", help="core scan or photo (sRGB PNG/JPEG/TIFF/BMP/WebP or linear EXR; truncated or corrupt "
                                  "files are refused)")
    p.add_argument("--out", required=True, help="output CSV")
    p.add_argument("--overlay", default=None, help="optional overlay PNG with the detected boundaries")
    p.add_argument("--bark", choices=("left", "right", "top", "bottom"), default=None,
                   help="core mode: side with the bark (default: right for wide, bottom for tall images)")
    p.add_argument("--transect", default=None, help="transect mode: X0,Y0,X1,Y1 in pixels, pith -> bark")
    size = p.add_mutually_exclusive_group()
    size.add_argument("--dpi", type=float, default=None, help="scan resolution (pixel size 25.4 / dpi mm)")
    size.add_argument("--pixel-size-mm", type=float, default=None, help="pixel size in mm")
    p.add_argument("--width-px", type=int, default=32, help="core mode: uniform core width (default: %(default)s)")
    p.add_argument("--mode", choices=("core", "section"), default="core",
                   help="core (also transect with --transect) or section (microscopy); default: %(default)s")
    p.add_argument("--cell-px", type=float, default=8.0, help="section mode: cell diameter in px (default: %(default)s)")
    return p.parse_args(argv)


def _fail(msg):
    print(f"{PROG}: error: {msg}", file=sys.stderr)
    return 2


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


def main(argv=None):
    args = parse_args(argv)
    for name, path in (("--out", args.out), ("--overlay", args.overlay)):
        if path is not None and not os.path.isdir(os.path.dirname(os.path.abspath(path))):
            return _fail(f"{name}: folder of {path!r} does not exist")
    if args.dpi is not None and not args.dpi > 0:
        return _fail(f"--dpi must be > 0; got {args.dpi}")
    if args.pixel_size_mm is not None and not args.pixel_size_mm > 0:
        return _fail(f"--pixel-size-mm must be > 0; got {args.pixel_size_mm}")
    try:
        rgb = read_image(args.image, space="srgb", name="image")  # decoded fully: truncated files are refused
    except (OSError, ValueError) as e:
        return _fail(f"cannot read image {args.image!r}: {e}")
    transect = None
    if args.transect is not None:
        try:
            transect = tuple(float(t) for t in args.transect.split(","))
            if len(transect) != 4:
                raise ValueError
        except ValueError:
            return _fail(f"--transect must be X0,Y0,X1,Y1 (four numbers); got {args.transect!r}")
    if args.mode == "section" and (transect is not None or args.bark is not None):
        return _fail("--transect / --bark do not apply to --mode section")
    try:
        if args.mode == "section":
            sec = detect_section_boundaries(rgb, cell_px=args.cell_px)
            rows = [dict(index=i, x_px=f"{x:.2f}", y_px=f"{y:.2f}") for i, (x, y) in enumerate(sec.points)]
            png = overlay_png(rgb, sec.points, polyline=True) if args.overlay else None
    except ValueError as e:
        return _fail(str(e))
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
            h, w = rgb.shape[:2]
            bark = args.bark or ("right" if w >= h else "bottom")
            res = detect_core_boundaries(rgb, bark=bark, width_px=args.width_px, dpi=args.dpi,
                                         pixel_size_mm=args.pixel_size_mm)
        rows = [dict(index=i, x_px=f"{x:.2f}", y_px=f"{y:.2f}",
                     width_px="" if not np.isfinite(wp) else f"{wp:.2f}",
                     width_mm="" if not np.isfinite(wm) else f"{wm:.4f}")
                for i, ((x, y), wp, wm) in enumerate(zip(res.points, res.widths_px, res.widths_mm))]
        png = overlay_png(rgb, res.points, transect) if args.overlay else None
    except ValueError as e:
        return _fail(str(e))
    write_csv(args.out, rows, ["index", "x_px", "y_px", "width_px", "width_mm"])
    if png is not None:
        atomic_write_bytes(args.overlay, png)
    print(f"{len(rows)} boundaries -> {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
