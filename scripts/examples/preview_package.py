"""A picture of a printer package (ta-export-print): one GrabCAD layer as the printer receives it, and the 3MF as a
viewer shows it.

Reads the package's print.gcvf (one layer PNG, straight from the zip) and print.3mf (through lib3mf, the reader the
tests use), renders the 3MF's coloured mesh offscreen with pyvista from three sides, and writes one PNG.

Examples:
    python scripts/examples/preview_package.py results/spot/package-j750 --out docs/images/print_package.png
    python scripts/examples/preview_package.py results/spot/package-j750 --layer 400 --crop 160
"""
import argparse
import os
import sys
import zipfile

import cv2
import numpy as np


def render_views(mesh, size=360):
    """Three offscreen pyvista renders (front, side, above; z up) of the 3MF mesh with its vertex or face colours."""
    import pyvista as pv

    from torch_appearance.geometry.preview import offscreen_rendering

    ok, detail = offscreen_rendering()
    if not ok:
        raise RuntimeError(f"offscreen rendering is not available: {detail}")
    faces = np.c_[np.full(len(mesh["faces"]), 3), mesh["faces"]].reshape(-1)
    poly = pv.PolyData(mesh["vertices"], faces)
    if mesh.get("vertex_rgb") is not None:
        poly.point_data["rgb"] = mesh["vertex_rgb"]
    elif mesh.get("face_rgb") is not None:
        poly.cell_data["rgb"] = mesh["face_rgb"]
    images = []
    for direction in ((0.0, -1.0, 0.25), (1.0, 0.0, 0.25), (0.15, -0.3, 1.0)):
        plotter = pv.Plotter(off_screen=True, window_size=(size, size))
        plotter.set_background((0.85, 0.85, 0.85))
        plotter.add_mesh(poly, scalars="rgb" if "rgb" in poly.array_names else None, rgb=True, smooth_shading=True,
                         ambient=0.45, diffuse=0.65, specular=0.05)
        plotter.view_vector(direction, viewup=(0, 0, 1) if direction[2] < 0.9 else (0, 1, 0))
        plotter.enable_parallel_projection()
        plotter.reset_camera()
        images.append(plotter.screenshot(return_img=True))
        plotter.close()
    return images


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], epilog=__doc__.split("\n\n", 1)[1],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("package", help="a package folder of ta-export-print (print.gcvf and print.3mf)")
    p.add_argument("--layer", type=int, default=None, help="the GrabCAD layer to show (default: the middle one)")
    p.add_argument("--crop", type=int, default=120, help="side in pixels of the enlarged corner of the layer")
    p.add_argument("--out", default="package_preview.png")
    args = p.parse_args(argv)
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from torch_appearance.fabrication.threemf import read_3mf
    from torch_appearance.io import save_figure

    with zipfile.ZipFile(os.path.join(args.package, "print.gcvf")) as z:
        n = sum(1 for name in z.namelist() if name.startswith("layer_"))
        k = n // 2 if args.layer is None else args.layer
        if not 0 <= k < n:
            p.error(f"--layer: expected 0..{n - 1}, got {k}")
        layer = cv2.imdecode(np.frombuffer(z.read(f"layer_{k}.png"), np.uint8), cv2.IMREAD_COLOR)[..., ::-1]
        import xml.etree.ElementTree as ET
        config = ET.fromstring(z.read("ConfigFile.xml"))
        aspect = float(config.findtext("Resolution/XDpi")) / float(config.findtext("Resolution/YDpi"))
    mesh = read_3mf(os.path.join(args.package, "print.3mf"))
    views = render_views(mesh)
    fig = plt.figure(figsize=(15, 4.6))
    grid = fig.add_gridspec(1, 5, width_ratios=[1.3, 1, 1, 1, 1])
    ax = fig.add_subplot(grid[0])
    ax.imshow(layer, interpolation="nearest", aspect=aspect)        # 600 x 300 DPI: a y voxel is twice as long
    ax.set_title(f"print.gcvf: layer {k} of {n} ({layer.shape[1]} x {layer.shape[0]} px)", fontsize=9)
    ax.axis("off")
    # the enlarged corner: where the layer mixes the most materials (the two commonest and the background aside)
    codes = (layer[..., 0].astype(np.int64) << 16) | (layer[..., 1].astype(np.int64) << 8) | layer[..., 2]
    values, counts = np.unique(codes[codes != 0], return_counts=True)
    common = values[np.argsort(counts)[-2:]]
    mixed = cv2.blur(((codes != 0) & ~np.isin(codes, common)).astype(np.float32), (args.crop, args.crop // 2))
    cy, cx = np.unravel_index(np.argmax(mixed), mixed.shape)
    c = args.crop
    y0 = int(np.clip(cy - c // 4, 0, max(0, layer.shape[0] - c // 2)))
    x0 = int(np.clip(cx - c // 2, 0, max(0, layer.shape[1] - c)))
    ax = fig.add_subplot(grid[1])
    ax.imshow(layer[y0:y0 + c // 2, x0:x0 + c], interpolation="nearest", aspect=aspect)
    ax.set_title(f"a corner of it ({c} x {c // 2} voxels)", fontsize=9)
    ax.axis("off")
    for i, (image, name) in enumerate(zip(views, ("front", "side", "above"))):
        ax = fig.add_subplot(grid[2 + i])
        ax.imshow(image)
        ax.set_title(f"print.3mf ({len(mesh['faces'])} triangles), {name}" if i == 0 else name, fontsize=9)
        ax.axis("off")
    fig.tight_layout()
    save_figure(fig, args.out, dpi=110)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
