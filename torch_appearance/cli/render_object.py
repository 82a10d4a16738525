"""Render a built-in translucent object (a torus or a sphere given as an SDF grid) with the general-scene tracer.

The object is a smooth dielectric (``--ior``, default 1.5; 0 = index matched) filled with a heterogeneous ink
medium: white ink with a band of cyan, magenta or yellow depending on the height and the azimuth, so the picture
shows refraction, subsurface scattering and colour bleeding. It is lit by a distant disc light (``--light-deg``
angular radius) plus an ambient term, or by a lat-long environment map (``--envmap file.exr``), and seen by a
perspective camera. A backward pass of ``image.mean()`` is timed too.

The run folder receives (each written atomically): ``render.png`` (sRGB), ``render.exr`` (linear RGB),
``timings.json`` (forward/backward seconds, scatter events per second) and ``config.json``, the four together once
the render is done, and ``tool.json`` (naming this command; another tool's folder is refused). A second
``ta-render-object`` on the same ``--out`` while one renders is refused; Ctrl-C ends it with one line and exit 130,
and writes nothing (or, when it comes while the files are written, all four).

Examples:
    ta-render-object --shape torus --size 256 --spp 64 --out results/render-object
    ta-render-object --shape sphere --device cuda --out results/render-object-gpu
"""
import json
import math
import os
import sys
import time

import torch

import torch_appearance
from torch_appearance import io as ta_io
from torch_appearance.geometry import corner_points, sphere_sdf, torus_sdf
from torch_appearance.pipelines.runs import (check_memory, check_run_folder_owner, lock_output, mark_run_folder,
                                             sigint_deferred)
from torch_appearance.render import (BoxBoundary, DiscLight, EnvironmentMap, PerspectiveCamera, Scene,
                                     SDFBoundary)

from .command import (CommandParser, add_device_argument, check_output_folder, fail, flag_names, interrupted,
                      resolve_device)

PROG = "ta-render-object"

#: peak memory per voxel of the n³ grid (its corner points and SDF, the ink medium, the gradient): 143 bytes
#: measured between n = 104 and n = 204 (peak RSS 1.00 and 2.05 GB at 8×8 pixels, 1 spp), with a margin
BYTES_PER_VOXEL = 160

WHITE = ((6.0, 9.0, 24.0), (0.9991, 0.9997, 0.999))  # Vero white: σ_t (mm⁻¹), albedo
COLOURS = [((9.0, 4.5, 7.5), (0.05, 0.7, 0.98)),       # cyan
           ((2.5, 3.0, 10.0), (0.98, 0.1, 0.9)),       # magenta
           ((2.25, 3.75, 19.0), (0.997, 0.995, 0.15))]  # yellow


def ink_medium(points, extent):
    """σ_t, albedo (3, D, H, W) at the voxel centres: white, with a coloured band around the middle height whose
    ink changes with the azimuth."""
    centres = (points[:-1, :-1, :-1] + points[1:, 1:, 1:]) / 2
    x, y, z = centres.unbind(-1)
    band = (z.abs() < 0.12 * extent).double()
    which = ((torch.atan2(y, x) + math.pi) / (2 * math.pi) * 3).long().clamp(0, 2)
    sigma = torch.tensor(WHITE[0]).view(3, 1, 1, 1).expand(3, *x.shape).clone().double()
    albedo = torch.tensor(WHITE[1]).view(3, 1, 1, 1).expand(3, *x.shape).clone().double()
    for k, (s, a) in enumerate(COLOURS):
        m = (band * (which == k)).bool()
        for c in range(3):
            sigma[c][m] = s[c]
            albedo[c][m] = a[c]
    return sigma.float().contiguous(), albedo.float().contiguous()


def main(argv=None):
    p = CommandParser(PROG, __doc__)
    p.add_argument("--shape", choices=("torus", "sphere"), default="torus", help="(default: %(default)s)")
    p.add_argument("--radius-mm", type=float, default=5.0, help="outer radius of the object (default: %(default)s)")
    p.add_argument("--voxel-size", type=float, default=0.2, help="mm (default: %(default)s)")
    p.add_argument("--ior", type=float, default=1.5, help="refractive index; 0 = index matched (default: %(default)s)")
    p.add_argument("--size", type=int, default=160, help="image height = width in pixels (default: %(default)s)")
    p.add_argument("--spp", type=int, default=64, help="samples per pixel (default: %(default)s)")
    p.add_argument("--seed", type=int, default=0, help="(default: %(default)s)")
    p.add_argument("--light-deg", type=float, default=25.0, help="angular radius of the disc light (default: %(default)s)")
    p.add_argument("--envmap", default=None, help="a lat-long linear EXR (z up) instead of the disc light")
    p.add_argument("--out", default="results/render-object", help="run folder (default: %(default)s)")
    add_device_argument(p)
    args = p.parse_args(argv)
    check_output_folder(p, "--out", args.out)
    try:  # another tool's folder: refused before any work (again when the files are written)
        check_run_folder_owner(args.out, PROG, "--out")
    except ValueError as error:
        return fail(PROG, error)
    args.device = str(resolve_device(p, args.device, log=print))
    for name in ("radius_mm", "voxel_size", "size", "spp"):
        if not getattr(args, name) > 0:
            p.error(f"--{name.replace('_', '-')}: expected > 0, got {getattr(args, name)}")
    # the library's checks of the light, the surface and the environment map before any work, in this command's
    # words (a damaged map costs nothing and writes nothing)
    flags = flag_names(p, angular_radius_deg="--light-deg")
    try:
        envmap = EnvironmentMap.from_exr(args.envmap) if args.envmap else None
        emitter = envmap if envmap is not None else DiscLight((0.4, -0.6, 1.0), args.light_deg, 40.0, ambient=0.35)
    except (OSError, ValueError) as error:
        return fail(PROG, error, flags, {"envmap": args.envmap})
    try:
        BoxBoundary(args.ior or None)
    except ValueError as error:
        return fail(PROG, f"{error}, or 0 for an index-matched surface", flags)
    r, h = args.radius_mm, args.voxel_size
    n = int(math.ceil(2 * r / h)) + 4
    try:  # a grid that cannot fit is refused before it is allocated
        check_memory("voxel_size", n ** 3 * BYTES_PER_VOXEL, f"a {n}³-voxel grid ({2 * r:g} mm across at {h:g} mm)",
                     "raise --voxel-size or lower --radius-mm")
    except ValueError as error:
        return fail(PROG, error, flags)
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)  # the lock file lies beside --out
    written = []
    try:
        with lock_output(args.out, "--out", advice="wait for the other ta-render-object to end or choose another "
                                                   "folder"):
            timings = _render(args, n, emitter, written)
    except ValueError as error:
        return fail(PROG, error, flags)
    except KeyboardInterrupt:
        if written:
            return interrupted(PROG, f"the render in {args.out!r} is complete")
        return interrupted(PROG, "nothing was written (start it again)")
    print(json.dumps(timings))
    return 0


def _render(args, n, emitter, written):
    """Render, time the backward pass, and write the run folder (Ctrl-C held back while it is written; ``written``
    gets True once it is); returns the timings."""
    r, h = args.radius_mm, args.voxel_size
    origin = (-n * h / 2,) * 3
    if args.shape == "torus":
        sdf = torus_sdf((n,) * 3, h, origin, (0, 0, 0), 0.68 * r, 0.32 * r)
    else:
        sdf = sphere_sdf((n,) * 3, h, origin, (0, 0, 0), r)
    sigma_t, albedo = ink_medium(corner_points((n,) * 3, h, origin), r)
    cam = PerspectiveCamera(origin=(3.2 * r, -2.4 * r, 2.6 * r), target=(0, 0, 0), up=(0, 0, 1), fov_y_deg=30,
                            resolution=(args.size, args.size))
    scene = Scene(voxel_size=h, origin=origin, boundary=SDFBoundary(sdf, ior=args.ior or None), sensor=cam,
                  emitter=emitter, g=0.4)
    sigma_t = sigma_t.to(args.device).requires_grad_()
    albedo = albedo.to(args.device)
    stats = {}
    start = time.perf_counter()
    image = torch_appearance.render_scene(scene, sigma_t, albedo, spp=args.spp, seed=args.seed, stats=stats)
    forward_s = time.perf_counter() - start
    image.mean().backward()
    image = image.cpu()
    timings = {"forward_s": forward_s, "backward_s": stats.get("backward_s"), "grid_dhw": [n, n, n],
               "pixels": args.size ** 2, "spp": args.spp, "scatter_events": stats["scatter_events"],
               "events_per_s": stats["scatter_events"] / forward_s, "threads": torch.get_num_threads(),
               "device": args.device}
    with sigint_deferred():
        check_run_folder_owner(args.out, PROG, "--out")  # under --out's lock, as the files are written
        os.makedirs(args.out, exist_ok=True)
        mark_run_folder(args.out, PROG)
        ta_io.write_png(os.path.join(args.out, "render.png"), image.detach())
        ta_io.write_exr(os.path.join(args.out, "render.exr"), image.detach())
        ta_io.write_json(os.path.join(args.out, "timings.json"), timings)
        ta_io.write_json(os.path.join(args.out, "config.json"), vars(args))
        written.append(True)
    return timings


if __name__ == "__main__":
    sys.exit(main())
