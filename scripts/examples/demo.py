#!/usr/bin/env python
"""Render a built-in slab of Stratasys Vero inks with the differentiable volume path tracer.

The slab is ``--size`` x ``--size`` texels and ``--thickness`` mm thick at ``--voxel-size`` mm voxels
(defaults: 64 x 64 texels, 1 mm at 0.085 mm -> D = 12 layers). Its lower half is white ink; its upper half
carries a picture (black frame; top half: bars of cyan, magenta, yellow, black; bottom half: a
cyan -> magenta -> yellow -> cyan hue ramp that fades into white towards the bottom edge). Inks are mixed
linearly in sigma_a and sigma_s (the material-space parameterisation of Nindel et al. 2021).

Both faces are rendered (``face="both"``, smooth dielectric boundary, IOR 1.5, uniform white environment),
then a backward pass of ``loss = image.mean()`` is timed. The run folder receives, each written atomically:

    top.png, bottom.png      sRGB renders (8-bit by default)
    top.exr, bottom.exr      linear RGB renders (float32)
    timings.json             forward/backward seconds, scatter events, events per second, spp, texels,
                             torch threads, versions
    config.json              the arguments and the scene (inks, layout, grid size)

Usage::

    python scripts/examples/demo.py --out results/demo --spp 256 --seed 0
"""
import argparse
import importlib.metadata
import os
import platform
import sys
import time

import numpy as np
import torch

import torch_appearance
from torch_appearance import io as ta_io

# Stratasys "Vero Opaque Rigid" inks as measured by Elek et al. 2017 (Nindel et al. 2021, Table 2):
# extinction sigma_t (mm^-1) and single-scattering albedo per R, G, B channel; all with HG g = 0.4.
INKS = {
    "cyan": {"sigma_t": (9.0, 4.5, 7.5), "albedo": (0.05, 0.7, 0.98)},
    "magenta": {"sigma_t": (2.5, 3.0, 10.0), "albedo": (0.98, 0.1, 0.9)},
    "yellow": {"sigma_t": (2.25, 3.75, 19.0), "albedo": (0.997, 0.995, 0.15)},
    "black": {"sigma_t": (5.0, 5.5, 6.5), "albedo": (0.35, 0.35, 0.35)},
    "white": {"sigma_t": (6.0, 9.0, 24.0), "albedo": (0.9991, 0.9997, 0.999)},
}
INK_NAMES = tuple(INKS)  # order of the mixture weights: cyan, magenta, yellow, black, white


def ink_picture(size):
    """Mixture weights of the picture layer, shape ``(5, size, size)`` (inks in ``INK_NAMES`` order).

    Texel ``[j, i]``: row j (y), column i (x). Rows ``j < size/2``: four vertical bars C, M, Y, K.
    Rows ``j >= size/2``: a hue ramp along x (C -> M -> Y -> C, adjacent inks mixed linearly) whose ink
    coverage falls linearly from 1 to 0 towards the last row, the rest being white. A 2-texel black frame.
    """
    c, m, y, k, w = range(5)
    weights = np.zeros((5, size, size))
    half = size // 2
    cols = np.arange(size)
    bar = np.minimum(cols * 4 // size, 3)  # 0..3 -> C, M, Y, K
    for ink in (c, m, y, k):
        weights[ink, :half, :] = (bar == ink)[None, :]
    hue = cols / max(size - 1, 1) * 3.0  # 0..3 along x
    segment = np.minimum(hue.astype(int), 2)
    frac = hue - segment
    pairs = ((c, m), (m, y), (y, c))
    rows = size - half
    coverage = 1.0 - np.arange(rows) / max(rows - 1, 1)  # 1 at the middle row, 0 at the last row
    for seg, (a, b) in enumerate(pairs):
        sel = segment == seg
        weights[a][half:, sel] += coverage[:, None] * (1.0 - frac[sel])[None, :]
        weights[b][half:, sel] += coverage[:, None] * frac[sel][None, :]
    weights[w, half:, :] = 1.0 - coverage[:, None]
    frame = 2 if size >= 16 else 0
    if frame:
        border = np.zeros((size, size), dtype=bool)
        border[:frame, :] = border[-frame:, :] = border[:, :frame] = border[:, -frame:] = True
        weights[:, border] = 0.0
        weights[k, border] = 1.0
    return weights


def build_slab(size, depth, picture_layers, dtype=torch.float32):
    """Grids of the demo slab.

    Args:
        size: texels per side (H = W = size).
        depth: number of voxel layers D.
        picture_layers: number of top layers that carry the picture; the layers below are white.
        dtype: floating dtype of the grids.

    Returns:
        ``(sigma_t, albedo)``, each of shape ``(3, D, H, W)``; ``sigma_t`` in mm^-1.
    """
    picture = ink_picture(size)  # (5, H, W)
    weights = np.zeros((5, depth, size, size))
    weights[INK_NAMES.index("white")] = 1.0
    first = depth - picture_layers  # z grows with k: the top face sees layer D - 1 first
    weights[:, first:] = picture[:, None]
    sig = np.array([INKS[n]["sigma_t"] for n in INK_NAMES])  # (5, 3)
    alb = np.array([INKS[n]["albedo"] for n in INK_NAMES])
    sigma_s = np.einsum("nc,ndhw->cdhw", sig * alb, weights)
    sigma_a = np.einsum("nc,ndhw->cdhw", sig * (1.0 - alb), weights)
    sigma_t = sigma_s + sigma_a
    albedo = sigma_s / sigma_t
    return torch.from_numpy(sigma_t).to(dtype).contiguous(), torch.from_numpy(albedo).to(dtype).contiguous()


def _versions():
    out = {"python": platform.python_version(), "torch": torch.__version__, "numpy": np.__version__}
    for name in ("torch_appearance", "kornia", "opencv-contrib-python-headless", "OpenEXR"):
        try:
            out[name] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            out[name] = None
    out["platform"] = platform.platform()
    return out


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", default="results/demo", help="run folder (created if missing; default: %(default)s)")
    parser.add_argument("--size", type=int, default=64, help="texels per side (default: %(default)s)")
    parser.add_argument("--thickness", type=float, default=1.0, help="slab thickness in mm (default: %(default)s)")
    parser.add_argument("--voxel-size", type=float, default=0.085, help="voxel edge in mm (default: %(default)s)")
    parser.add_argument("--spp", type=int, default=256, help="samples per texel and face (default: %(default)s)")
    parser.add_argument("--seed", type=int, default=0, help="random seed of the tracer (default: %(default)s)")
    parser.add_argument("--g", type=float, default=0.4, help="Henyey-Greenstein parameter (default: %(default)s)")
    parser.add_argument("--ior", type=float, default=1.5, help="index of refraction of the slab (default: %(default)s)")
    parser.add_argument("--threads", type=int, default=None, help="torch intra-op threads (default: torch's choice)")
    parser.add_argument("--png-bits", type=int, default=8, choices=(8, 16), help="PNG bit depth (default: %(default)s)")
    parser.add_argument("--no-backward", action="store_true", help="skip the timed backward pass")
    args = parser.parse_args(argv)
    if args.size < 1:
        parser.error(f"--size must be >= 1, got {args.size}")
    if not args.voxel_size > 0:
        parser.error(f"--voxel-size must be > 0, got {args.voxel_size}")
    if not args.thickness >= args.voxel_size:
        parser.error(f"--thickness must be at least one voxel ({args.voxel_size} mm), got {args.thickness}")
    if args.spp < 1:
        parser.error(f"--spp must be >= 1, got {args.spp}")
    if args.threads is not None and args.threads < 1:
        parser.error(f"--threads must be >= 1, got {args.threads}")
    return args


def main(argv=None):
    args = parse_args(argv)
    if args.threads is not None:
        torch.set_num_threads(args.threads)
    depth = max(1, int(round(args.thickness / args.voxel_size)))
    picture_layers = max(1, depth // 2)
    sigma_t, albedo = build_slab(args.size, depth, picture_layers)
    sigma_t.requires_grad_(not args.no_backward)
    albedo.requires_grad_(not args.no_backward)
    os.makedirs(args.out, exist_ok=True)

    config = {
        "args": vars(args),
        "scene": {
            "grid_dhw": [depth, args.size, args.size],
            "voxel_size_mm": args.voxel_size,
            "thickness_mm": depth * args.voxel_size,
            "picture_layers": picture_layers,
            "white_base_layers": depth - picture_layers,
            "inks": INKS,
            "mixing": "sigma_a and sigma_s mixed linearly with the ink weights",
            "picture": "black 2-texel frame; top half bars C, M, Y, K; bottom half hue ramp C->M->Y->C fading to white",
            "faces": ["top", "bottom"],
            "environment": 1.0,
        },
        "render": {"face": "both", "g": args.g, "ior": args.ior, "spp": args.spp, "seed": args.seed},
    }
    ta_io.write_json(os.path.join(args.out, "config.json"), config)

    stats = {}
    start = time.perf_counter()
    image = torch_appearance.render_texels(
        sigma_t, albedo, voxel_size=args.voxel_size, face="both", g=args.g, ior=args.ior,
        environment=1.0, spp=args.spp, seed=args.seed, stats=stats,
    )  # (2, H, W, 3): 0 = top, 1 = bottom
    forward_s = time.perf_counter() - start

    backward_s = None
    if not args.no_backward:
        start = time.perf_counter()
        image.mean().backward()
        backward_s = time.perf_counter() - start

    rendered = image.detach().cpu().numpy()
    for index, face in enumerate(("top", "bottom")):
        ta_io.write_exr(os.path.join(args.out, f"{face}.exr"), rendered[index])
        ta_io.write_png(os.path.join(args.out, f"{face}.png"), rendered[index], bits=args.png_bits)

    events = stats.get("scatter_events")
    texels = 2 * args.size * args.size
    timings = {
        "forward_s": forward_s,
        "forward_tracer_s": stats.get("forward_s"),
        "scatter_events": events,
        "events_per_s": events / forward_s if events is not None and forward_s > 0 else None,
        "backward_s": backward_s,
        "backward_tracer_s": stats.get("backward_s"),
        "backward_scatter_events": stats.get("backward_scatter_events"),
        "backward_over_forward": backward_s / forward_s if backward_s is not None and forward_s > 0 else None,
        "spp": args.spp,
        "texels": texels,
        "faces": 2,
        "texel_samples": texels * args.spp,
        "lanes": stats.get("lanes"),
        "grid_dhw": [depth, args.size, args.size],
        "torch_threads": torch.get_num_threads(),
        "versions": _versions(),
    }
    ta_io.write_json(os.path.join(args.out, "timings.json"), timings)

    mean_top = rendered[0].reshape(-1, 3).mean(axis=0)
    mean_bottom = rendered[1].reshape(-1, 3).mean(axis=0)
    events_text = f", {events / 1e6:.2f} M scatter events, {timings['events_per_s'] / 1e6:.2f} M/s" if events else ""
    backward_text = f", backward {backward_s:.2f} s" if backward_s is not None else ""
    print(
        f"demo: {args.size}x{args.size} texels x 2 faces, D={depth} @ {args.voxel_size} mm, {args.spp} spp, "
        f"{torch.get_num_threads()} threads: forward {forward_s:.2f} s{events_text}{backward_text}; "
        f"mean linear RGB top ({mean_top[0]:.3f}, {mean_top[1]:.3f}, {mean_top[2]:.3f}) "
        f"bottom ({mean_bottom[0]:.3f}, {mean_bottom[1]:.3f}, {mean_bottom[2]:.3f}) -> {args.out}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
