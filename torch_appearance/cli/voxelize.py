"""Voxelise a textured mesh for printing: occupancy, exact SDF band, surface texels with normals and colours.

Loads MODEL (OBJ + MTL + texture, GLB/GLTF, PLY, STL; ``--texture`` gives or replaces its colour image), scales it
to ``--height-mm`` (or by ``--scale``), voxelises it at ``--dpi`` (isotropic voxels of 25.4/dpi mm) and writes to
``--out``:

    object.npz          the VoxelObject (torch_appearance.geometry.VoxelObject.load reads it)
    summary.json        counts, timings, peak memory, watertightness, units guess, max texel-to-surface distance,
                        preview_backend
    texels_color.png    the texels from three sides (front-left above, back-right above, front-right below; z up,
                        front = -y), coloured by their target colour (sRGB); only when the mesh has colours
    texels_normal.png   the same, coloured by their normals (0.5 + 0.5 n)
    sdf_slice.png       the SDF through the middle of the object (xz plane), with its zero level

The texel pictures are rendered offscreen with pyvista/VTK (EGL or OSMesa where there is no X display); where that
is impossible they are matplotlib scatter plots instead, with a warning, and summary.json says which
("preview_backend": "pyvista" or "matplotlib"; TA_PREVIEW_BACKEND=matplotlib forces the fallback). Progress goes to
stderr (--quiet: none), the summary as one JSON line to stdout.

Examples:
    ta-voxelize model.obj --height-mm 30 --dpi 300 --shell-mm 2 --out results/voxelize
    ta-voxelize model.ply --texture albedo.png --scale 1000 --out results/voxelize
"""
import contextlib
import inspect
import json
import math
import os
import resource
import signal
import sys
import threading
import time

import numpy as np

from torch_appearance import io as ta_io
from torch_appearance.geometry import check_grid_size, load_mesh, voxelize
from torch_appearance.geometry.preview import write_previews

from torch_appearance.pipelines.runs import claim_run_folder

from .command import (INTERRUPTED, CommandParser, check_output_folder, fail, flag_names, folder_listing, in_flags,
                      interrupted, undo_partial)

#: the most voxels along the height the command admits before loading the mesh (88 m at 300 DPI: no grid of such an
#: object fits in memory, and the mesh scaled to it overflowed trimesh's vertex merging)
MAX_AXIS_VOXELS = 1 << 20
PROG = "ta-voxelize"
NOTHING_WRITTEN = "nothing written (object.npz was not finished)"


def _accepts_keyword(fn, name):
    try:
        parameters = inspect.signature(fn).parameters
    except (TypeError, ValueError):
        return True
    return name in parameters or any(p.kind is p.VAR_KEYWORD for p in parameters.values())


class Progress:
    """Step lines on stderr ("[voxelize 1.2 s] voxelising …"), unless quiet."""

    def __init__(self, quiet=False):
        self.quiet, self.t0 = quiet, time.perf_counter()

    def __call__(self, message):
        if not self.quiet:
            print(f"[voxelize {time.perf_counter() - self.t0:6.1f} s] {message}", file=sys.stderr, flush=True)


UNITS = {"m": ("metres", 1000), "cm": ("centimetres", 10)}


def units_refusal(report):
    """The one line for a model given without a scale whose size suggests other units than mm (``units_guess`` of
    :func:`~torch_appearance.geometry.load_mesh`): as trimesh, a guess is not applied silently; unlike a renderer,
    a printed size cannot be left unitless, so the command asks for the scale."""
    extent = " × ".join(f"{e:.3g}" for e in report["extent_file_units"])
    name, factor = UNITS[report["units_guess"]]
    return (f"--scale: the model is {extent} file units, which reads as {name} (in millimetres it would be a "
            f"{max(report['extent_file_units']):.3g} mm object); give --scale {factor} for {name}, --scale 1 if the "
            f"file is in millimetres, or --height-mm")


def main(argv=None):
    """Run the command with the flags in ``argv`` (default ``sys.argv[1:]``); returns the exit status (2 for refused
    input, 130 after Ctrl-C, with one line saying what was written)."""
    state = {"out": None, "object": False}
    try:
        return _main(argv, state)
    except KeyboardInterrupt:  # the folder's claim has removed the folder (or its mark) when nothing was written
        if not state["object"]:
            return interrupted(PROG, NOTHING_WRITTEN)
        return interrupted(PROG, f"object.npz in {state['out']} is complete, the previews are not (--no-previews "
                                 f"skips them)")


def _main(argv, state):
    p = CommandParser(PROG, __doc__)
    p.add_argument("model", help="mesh file (OBJ + MTL + texture, GLB/GLTF, PLY, STL)")
    p.add_argument("--texture", default=None, metavar="PATH",
                   help="base-colour image (sRGB PNG/JPEG) for a mesh with UVs, e.g. an OBJ with vt lines but no "
                        "MTL; it replaces any material the file has")
    p.add_argument("--height-mm", type=float, default=None, help="scale to this z extent in mm")
    p.add_argument("--scale", type=float, default=None, help="factor from file units to mm (instead of --height-mm)")
    p.add_argument("--dpi", type=float, default=300.0, help="voxel pitch in DPI (default: %(default)s ≈ 0.0847 mm)")
    p.add_argument("--shell-mm", type=float, default=None, help="depth of the printable shell in mm")
    p.add_argument("--out", default="results/voxelize", help="output folder (default: %(default)s)")
    p.add_argument("--no-previews", action="store_true", help="skip the PNG previews")
    p.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    args = p.parse_args(argv)
    check_output_folder(p, "--out", args.out)
    if not (math.isfinite(args.dpi) and args.dpi > 0):
        p.error(f"--dpi: expected a finite value > 0, got {args.dpi}")
    if args.height_mm is not None and not (math.isfinite(args.height_mm) and args.height_mm > 0):
        p.error(f"--height-mm: expected a finite value > 0, got {args.height_mm}")
    if args.height_mm is not None and args.height_mm * args.dpi / 25.4 > MAX_AXIS_VOXELS:
        # before loading: the mesh scaled to it overflowed trimesh's vertex merging (a RuntimeWarning on stderr)
        p.error(f"--height-mm: {args.height_mm:g} mm at {args.dpi:g} DPI is {args.height_mm * args.dpi / 25.4:.3g} "
                f"voxels tall; expected at most {MAX_AXIS_VOXELS} ({MAX_AXIS_VOXELS * 25.4 / args.dpi:g} mm at "
                f"--dpi {args.dpi:g})")
    load_kwargs = dict(height_mm=args.height_mm, scale=args.scale)
    if args.texture is not None:
        if not _accepts_keyword(load_mesh, "texture"):
            p.error("--texture: this version of torch_appearance.geometry.load_mesh takes no texture= yet")
        load_kwargs["texture"] = args.texture
    progress = Progress(args.quiet)
    flags = flag_names(p, voxel_size="--dpi")  # the library's voxel edge is 25.4 / --dpi mm
    before = folder_listing(args.out)
    with contextlib.ExitStack() as stack:
        try:  # the folder is this command's from here: another tool's, or one another process writes, is refused
            stack.enter_context(claim_run_folder(args.out, PROG, "--out"))
        except ValueError as error:
            return fail(PROG, error, flags)
        state["out"] = args.out
        return _voxelize_and_write(args, load_kwargs, progress, flags, state, before)


def _voxelize_and_write(args, load_kwargs, progress, flags, state, before):
    """Load and voxelise the mesh, then write the folder (claimed by the caller); returns the exit status."""
    # nothing is written while the mesh loads and is voxelised: Ctrl-C then removes the claimed folder (or its mark)
    with _exit_on_sigint(lambda: undo_partial(args.out, before, "voxelisation")):
        loaded = _load_and_voxelize(args, load_kwargs, progress, flags)
    if isinstance(loaded, int):
        return loaded
    obj, report, t0, t1, t2 = loaded
    progress(f"voxelised in {t2 - t1:.1f} s: grid {' × '.join(map(str, obj.grid_shape))} (D×H×W), "
             f"{len(obj.texel_voxels)} texels; writing object.npz …")
    obj.save(os.path.join(args.out, "object.npz"))  # atomically: whole or not at all
    state["object"] = True
    centres = (obj.texel_voxels.numpy()[:, ::-1] + 0.5) * obj.voxel_size + np.array(obj.origin)
    summary = {
        "model": os.path.abspath(args.model), **report, "voxel_size_mm": obj.voxel_size,
        "grid_dhw": list(obj.grid_shape), "inside_voxels": int(obj.occupancy.sum()),
        "texels": int(len(obj.texel_voxels)), "shell_voxels": None if obj.shell is None else int(obj.shell.sum()),
        "band_mm": obj.band_mm,
        "max_texel_centre_to_surface_mm": float(np.linalg.norm(centres - obj.texel_points.numpy(), axis=1).max())
        if len(centres) else None,
        "load_s": t1 - t0, "voxelize_s": t2 - t1, "voxelize_info": obj.info,
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        "preview_backend": None,
    }
    if args.texture is not None:
        summary["texture"] = os.path.abspath(args.texture)
    summary_path = os.path.join(args.out, "summary.json")
    ta_io.write_json(summary_path, summary)  # written now, so a failing preview leaves it behind
    if not args.no_previews:
        t3 = time.perf_counter()
        result = write_previews(obj, args.out, progress=progress)
        summary["preview_backend"] = result["backend"]
        summary["preview_s"] = time.perf_counter() - t3
        summary["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
        ta_io.write_json(summary_path, summary)
    progress(f"done: {args.out}")
    print(json.dumps(summary))
    return 0


def _load_and_voxelize(args, load_kwargs, progress, flags):
    """(object, load report, t0, t1, t2) of the mesh of ``args``, or the exit status of a refusal."""
    try:
        t0 = time.perf_counter()  # no line before the refusals below: a refused model gets the one line only
        mesh, report = load_mesh(args.model, **load_kwargs)
        t1 = time.perf_counter()
        if args.height_mm is None and args.scale is None and report["units_guess"] != "mm":
            return fail(PROG, units_refusal(report))
        size = 25.4 / args.dpi
        check_grid_size(mesh, size)  # a grid too large is refused before any line (it was after two)
        if report.get("hint"):
            progress(f"hint: {in_flags(report['hint'], flags)}")
        extent = mesh.bounds[1] - mesh.bounds[0]
        dims = " × ".join(str(int(round(e / size))) for e in extent)
        progress(f"loaded {args.model}" + (f" with texture {args.texture}" if args.texture else "") +
                 f" in {t1 - t0:.1f} s: {report.get('triangles')} triangles, colour {report.get('colour')}, "
                 f"{extent[0]:.1f} × {extent[1]:.1f} × {extent[2]:.1f} mm (x × y × z); voxelising at {size:.4g} mm "
                 f"(about {dims} voxels) …")
        obj = voxelize(mesh, size, shell_mm=args.shell_mm)
        t2 = time.perf_counter()
    except (ValueError, TypeError) as error:
        return fail(PROG, error, flags, vars(args))
    return obj, report, t0, t1, t2


@contextlib.contextmanager
def _exit_on_sigint(undo):
    """Ctrl-C while nothing is written ends the process at once, after ``undo()``, with the one line and exit 130,
    instead of a ``KeyboardInterrupt`` raised inside the mesh and voxel libraries (trimesh swallows one raised during
    its lazy imports, and one raised while a native module loads can abort the process). Only in the main thread."""
    previous = signal.getsignal(signal.SIGINT)
    if threading.current_thread() is not threading.main_thread() or not callable(previous):
        yield
        return

    def exit_now(signum, frame):
        undo()
        print(f"{PROG}: interrupted; {NOTHING_WRITTEN}", file=sys.stderr, flush=True)
        os._exit(INTERRUPTED)

    signal.signal(signal.SIGINT, exit_now)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


if __name__ == "__main__":
    sys.exit(main())
