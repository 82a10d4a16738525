#!/usr/bin/env python
"""Voxelise a textured mesh for printing: occupancy, exact SDF band, surface texels with normals and colours.

Loads MODEL (OBJ + MTL + texture, GLB/GLTF, PLY, STL), scales it to ``--height-mm`` (or by ``--scale``), voxelises
it at ``--dpi`` (isotropic voxels of 25.4/dpi mm) and writes to ``--out``:

    object.npz          the VoxelObject (torch_appearance.geometry.VoxelObject.load reads it)
    summary.json        counts, timings, peak memory, watertightness, units guess, max texel-to-surface distance
    texels_color.png    the texels seen from three sides, coloured by their target colour
    texels_normal.png   the same, coloured by their normals
    sdf_slice.png       the SDF through the middle of the object (xz plane), with its zero level

Usage::

    python scripts/voxelize.py model.obj --height-mm 30 --dpi 300 --shell-mm 2 --out results/voxelize
"""
import argparse
import json
import os
import resource
import sys
import time

import numpy as np

try:
    import torch_appearance  # noqa: F401
except ModuleNotFoundError as error:  # running from a checkout that is not installed
    if error.name != "torch_appearance":
        raise
    sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from torch_appearance import io as ta_io
from torch_appearance.geometry import load_mesh, voxelize


def previews(obj, folder):
    from matplotlib.figure import Figure

    pts = obj.texel_points.numpy()
    colours = {"color": None if obj.texel_colors is None else np.clip(obj.texel_colors.numpy(), 0, 1) ** (1 / 2.2),
               "normal": 0.5 + 0.5 * obj.texel_normals.numpy()}
    for name, c in colours.items():
        if c is None:
            continue
        fig = Figure(figsize=(12, 4))
        for k, (elev, azim) in enumerate([(20, -60), (20, 60), (80, 0)]):
            ax = fig.add_subplot(1, 3, k + 1, projection="3d")
            step = max(1, len(pts) // 60000)
            ax.scatter(pts[::step, 0], pts[::step, 1], pts[::step, 2], c=c[::step], s=1, depthshade=False)
            ax.view_init(elev=elev, azim=azim)
            ax.set_box_aspect(np.ptp(pts, axis=0) + 1e-9)
            ax.set_axis_off()
        fig.suptitle(f"{len(pts)} texels coloured by {name}")
        ta_io.save_figure(fig, os.path.join(folder, f"texels_{name}.png"))
    d, h, w = obj.grid_shape
    sdf = obj.sdf.numpy()[:, (h + 1) // 2, :]
    fig = Figure(figsize=(6, 6))
    ax = fig.add_subplot(1, 1, 1)
    x0, z0 = obj.origin[0], obj.origin[2]
    extent = (x0, x0 + w * obj.voxel_size, z0, z0 + d * obj.voxel_size)
    im = ax.imshow(sdf, origin="lower", extent=extent, cmap="RdBu", vmin=-obj.band_mm, vmax=obj.band_mm)
    ax.contour(sdf, levels=[0.0], colors="k", origin="lower", extent=extent, linewidths=0.8)
    fig.colorbar(im, ax=ax, label="signed distance [mm] (clamped to the band)")
    ax.set(xlabel="x [mm]", ylabel="z [mm]", title="SDF, middle xz slice")
    ta_io.save_figure(fig, os.path.join(folder, "sdf_slice.png"))


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], epilog=__doc__.split("\n\n", 1)[1],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("model", help="mesh file (OBJ + MTL + texture, GLB/GLTF, PLY, STL)")
    p.add_argument("--height-mm", type=float, default=None, help="scale to this z extent in mm")
    p.add_argument("--scale", type=float, default=None, help="factor from file units to mm (instead of --height-mm)")
    p.add_argument("--dpi", type=float, default=300.0, help="voxel pitch in DPI (default: %(default)s ≈ 0.0847 mm)")
    p.add_argument("--shell-mm", type=float, default=None, help="depth of the printable shell in mm")
    p.add_argument("--out", default="results/voxelize", help="output folder (default: %(default)s)")
    p.add_argument("--no-previews", action="store_true", help="skip the PNG previews")
    args = p.parse_args(argv)
    if not args.dpi > 0:
        p.error(f"--dpi: expected > 0, got {args.dpi}")
    try:
        t0 = time.perf_counter()
        mesh, report = load_mesh(args.model, height_mm=args.height_mm, scale=args.scale)
        t1 = time.perf_counter()
        obj = voxelize(mesh, 25.4 / args.dpi, shell_mm=args.shell_mm)
        t2 = time.perf_counter()
    except (ValueError, TypeError) as error:
        print(f"voxelize.py: error: {error}", file=sys.stderr)
        return 2
    os.makedirs(args.out, exist_ok=True)
    obj.save(os.path.join(args.out, "object.npz"))
    centres = (obj.texel_voxels.numpy()[:, ::-1] + 0.5) * obj.voxel_size + np.array(obj.origin)
    summary = {
        "model": os.path.abspath(args.model), **report, "voxel_size_mm": obj.voxel_size,
        "grid_dhw": list(obj.grid_shape), "inside_voxels": int(obj.occupancy.sum()),
        "texels": int(len(obj.texel_voxels)), "shell_voxels": None if obj.shell is None else int(obj.shell.sum()),
        "band_mm": obj.band_mm,
        "max_texel_centre_to_surface_mm": float(np.linalg.norm(centres - obj.texel_points.numpy(), axis=1).max()),
        "load_s": t1 - t0, "voxelize_s": t2 - t1,
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
    }
    ta_io.write_json(os.path.join(args.out, "summary.json"), summary)
    if not args.no_previews:
        previews(obj, args.out)
    print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    sys.exit(main())
