#!/usr/bin/env python
"""Gradient of a wood surface render with respect to any wood parameter (ring scale s_r, board rotation and
translation, a distortion texel): naive autograd vs reparameterisation (Loubet et al. 2019; thesis §2.4, Fig. 2.1)
against central finite differences.

The board face of a wood model (synthetic, with a smooth radial distortion texture, or a fit run folder) is seen
straight on by an orthographic camera with a Gaussian pixel filter. Naive autograd differentiates the filter samples
at fixed positions and misses the moving ring boundaries; the reparameterised render (reparam_render in
torch_appearance/nn/wood_reparam.py) warps the samples with the boundaries so that plain autograd of the image gives
the boundary term of every parameter. Both are compared per pixel block with central finite differences of the
image (common samples, high sample count): z-tests with a Bonferroni threshold, relative L1 error.

--param takes parameter specs: ring_scale (d/ds_r, per mm), rotation[i] (per rad), translation[i] (per mm),
m_r[row,col] (per mm of that distortion texel), color_map[ring,bin,channel]; several may be given.

With --cylinder-radius-mm R the face is bent into the lamp shade's curved surface instead: a
cylinder of radius R (axis along the image columns' direction, through the image centre) seen from the side,
Lambert-shaded from the camera on a black background; the warp follows the rings on the curved surface and vanishes
at its silhouette.

Writes --out/gradients.png (first parameter: render, FD, reparameterised, naive, z maps), one
--out/gradients_<param>.png per parameter and --out/summary.json (statistics per parameter and estimator).

Examples:
    python scripts/eval/wood_gradients.py --out results/wood_gradients
    python scripts/eval/wood_gradients.py --param ring_scale "rotation[0]" "translation[0]" "m_r[2,3]" --out results/wg
    python scripts/eval/wood_gradients.py --fit-dir results/board --out results/board_gradients --size 48 48
    python scripts/eval/wood_gradients.py --cylinder-radius-mm 6 --out results/wood_gradients_cylinder
"""
import argparse
import os
import sys
import time

import numpy as np
import torch

from torch_appearance import io as ta_io
from torch_appearance.nn import WoodModel
from torch_appearance.progress import progress_bar
from torch_appearance.nn.wood_reparam import (CylinderView, compare_parameter_gradients, parse_parameter,
                                              render_filtered)


def demo_model():
    """A flat-sawn board: stem 0.2 rad out of the board plane, axis 6 mm behind it, a smooth radial distortion
    (6×8 texels over r ∈ [0, 24] mm, z ∈ [−4, 20] mm, up to ~0.4 mm, fixed seed)."""
    m = WoodModel(ring_scale_mm=1.2, n_rings=8, distortion="radial", distortion_shape=(6, 8), r_max_mm=24.0,
                  z_range_mm=(-4.0, 20.0), dtype=torch.float64, color_bins=8)
    lat = torch.linspace(0, 1, 8, dtype=torch.float64)[:, None]
    ramp = 1 / (1 + torch.exp(-(lat - 0.7) / 0.06))
    early, late = torch.tensor([0.62, 0.44, 0.27]), torch.tensor([0.27, 0.14, 0.06])
    cmap = (early + (late - early) * ramp).to(torch.float64)
    # board (u, v, w) → tree: u → x, v → z (stem), w → −y, then tilted about u by 0.2 rad
    m_r = 0.2 * torch.randn(6, 8, dtype=torch.float64, generator=torch.Generator().manual_seed(3))
    m.set_parameters(rotation=torch.tensor([np.pi / 2 + 0.2, 0.0, 0.0]), translation=torch.tensor([-4.0, 6.0, 0.0]),
                     color_map=cmap.expand(8, 8, 3), m_r=m_r)
    return m.requires_grad_(False)


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], epilog=__doc__.split("\n\n", 1)[1],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default="results/wood_gradients", help="output folder (default: %(default)s)")
    p.add_argument("--fit-dir", default=None, help="a ta-fit-wood run folder instead of the demo board")
    p.add_argument("--param", nargs="+", default=["ring_scale"], metavar="SPEC",
                   help="parameters to differentiate: ring_scale, rotation[i], translation[i], m_r[row,col], "
                        "color_map[ring,bin,ch] (default: %(default)s)")
    p.add_argument("--size", type=int, nargs=2, default=(48, 64), metavar=("ROWS", "COLS"),
                   help="image size (default: %(default)s)")
    p.add_argument("--pixel-mm", type=float, default=0.25, help="pixel pitch on the board (default: %(default)s)")
    p.add_argument("--spp", type=int, default=16, help="samples per pixel per seed (default: %(default)s)")
    p.add_argument("--seeds", type=int, default=32, help="independent renders per estimator (default: %(default)s)")
    p.add_argument("--fd-spp", type=int, default=4096, help="finite-difference samples per pixel (default: %(default)s)")
    p.add_argument("--fd-h", type=float, default=None,
                   help="FD step: relative for ring_scale (0.002), else in the parameter's units (default: a step "
                        "that moves the ring boundaries by about 0.02 ring widths)")
    p.add_argument("--block", type=int, default=4, help="pixel block of the z-tests (default: %(default)s)")
    p.add_argument("--cylinder-radius-mm", type=float, default=None, metavar="R",
                   help="render the curved surface of a cylinder of radius R mm (axis through the image centre, "
                        "along the columns) instead of the flat face")
    p.add_argument("--quiet", action="store_true")
    return p.parse_args(argv)


def figure(path, render, res, stats, param="ring_scale"):
    from matplotlib.figure import Figure
    from torch_appearance.color import linear_to_srgb

    lum = lambda x: x.mean(-1).numpy()  # noqa: E731
    fd = lum(res["fd"])
    lim = float(np.percentile(np.abs(fd), 99)) or 1.0
    fig = Figure(figsize=(15, 6.2))
    axes = fig.subplots(2, 4)
    axes[0, 0].imshow(linear_to_srgb(render.clamp(0, 1)).numpy(), interpolation="nearest")
    axes[0, 0].set_title("render (Gaussian pixel filter)", fontsize=9)
    for ax, key, title in ((axes[0, 1], "fd", "central finite differences"),
                           (axes[0, 2], "reparam", "reparameterised"), (axes[0, 3], "naive", "naive autograd")):
        im = ax.imshow(lum(res[key]), cmap="RdBu_r", vmin=-lim, vmax=lim, interpolation="nearest")
        extra = "" if key == "fd" else (f"\nrel. L1 error {stats[key]['relative_l1_error']:.3f}, blocks rejected "
                                        f"{100 * stats[key]['fraction_blocks_rejected']:.0f} %")
        ax.set_title(f"dI/d{'s_r' if param == 'ring_scale' else param} (grey): {title}{extra}", fontsize=9)
    fig.colorbar(im, ax=axes[0, 3], fraction=0.046)
    for ax, key in ((axes[1, 1], "reparam"), (axes[1, 2], "naive")):
        z = stats[key]["z"].abs().max(-1).values.numpy()
        thr = stats[key]["z_threshold"]
        im2 = ax.imshow(z, cmap="magma", vmin=0, vmax=max(2 * thr, 1.0), interpolation="nearest")
        ax.set_title(f"{key}: max |z| per block over RGB\n(threshold {thr:.2f}, max {z.max():.1f})", fontsize=9)
        fig.colorbar(im2, ax=ax, fraction=0.046)
    axes[1, 3].plot(lum(res["fd"])[lum(res["fd"]).shape[0] // 2], "k-", label="FD")
    axes[1, 3].plot(lum(res["reparam"])[lum(res["fd"]).shape[0] // 2], "b.-", label="reparam")
    axes[1, 3].plot(lum(res["naive"])[lum(res["fd"]).shape[0] // 2], "r.-", label="naive")
    axes[1, 3].set_title("middle row", fontsize=9)
    axes[1, 3].legend(fontsize=8)
    axes[1, 0].axis("off")
    for ax in list(axes[0]) + [axes[1, 1], axes[1, 2]]:
        ax.set_xticks([])
        ax.set_yticks([])
    fig.tight_layout()
    ta_io.save_figure(fig, path, dpi=100)


def main(argv=None):
    args = parse_args(argv)
    try:
        if args.fit_dir is not None:
            from torch_appearance.nn.wood_volume import load_wood_fit
            model, _ = load_wood_fit(args.fit_dir)
            model = model.double().requires_grad_(False)
        else:
            model = demo_model()
        for spec in args.param:
            parse_parameter(model, spec)                   # refuse a bad spec before any work
        h, w = args.size
        surface = None
        if args.cylinder_radius_mm is not None:
            surface = CylinderView(args.cylinder_radius_mm, 0.5 * w * args.pixel_mm)
        os.makedirs(args.out, exist_ok=True)
        results, seconds = {}, {}
        with progress_bar(total=len(args.param) * (1 + 2 * args.seeds), desc="wood_gradients", disable=args.quiet) as bar:
            for spec in args.param:
                t0 = time.perf_counter()
                results[spec] = compare_parameter_gradients(model, spec, h, w, args.pixel_mm, spp=args.spp,
                                                            seeds=args.seeds, fd_spp=args.fd_spp, h=args.fd_h,
                                                            block=args.block, progress=lambda: bar.update(1),
                                                            surface=surface)
                seconds[spec] = round(time.perf_counter() - t0, 1)
        render = render_filtered(model, h, w, args.pixel_mm, spp=64, surface=surface)
    except (ValueError, TypeError) as error:
        print(f"wood_gradients.py: error: {error}", file=sys.stderr)
        return 2
    for k, spec in enumerate(args.param):
        safe = "".join(ch if ch.isalnum() or ch == "_" else "_" for ch in spec).strip("_")
        figure(os.path.join(args.out, f"gradients_{safe}.png"), render, results[spec], results[spec]["stats"], spec)
        if k == 0:
            figure(os.path.join(args.out, "gradients.png"), render, results[spec], results[spec]["stats"], spec)
    summary = {"settings": {k: (list(v) if isinstance(v, tuple) else v) for k, v in vars(args).items()},
               "ring_scale_mm": float(model.ring_scale.detach()),
               "params": {spec: {"seconds": seconds[spec],
                                 "fd_max_abs": float(results[spec]["fd"].abs().max()),
                                 "estimators": {k: {kk: vv for kk, vv in v.items() if kk != "z"}
                                                for k, v in results[spec]["stats"].items()}}
                          for spec in args.param}}
    ta_io.write_json(os.path.join(args.out, "summary.json"), summary)
    for spec, entry in summary["params"].items():
        for k, v in entry["estimators"].items():
            print(f"{spec} {k}: max |z| {v['max_abs_z']:.2f} (threshold {v['z_threshold']:.2f}), blocks rejected "
                  f"{100 * v['fraction_blocks_rejected']:.1f} %, relative L1 error {v['relative_l1_error']:.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
