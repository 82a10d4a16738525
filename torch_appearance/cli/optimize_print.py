"""``ta-optimize-print``: the print optimisation's command line (:func:`main`), and the pieces other print tools
share (``ta-select-inks``): the target and optimisation flags of :class:`PrintConfig`, and the config built from
them.

Optimise the ink arrangement of a printed slab or textured object so that its rendered look matches a target:
ink mixtures → C++ path tracer (radiative backpropagation) → perceptual appearance loss (ΔE76², 3D SSIM, 3D Sobel)
→ Adagrad/Adam; then probabilistic quantisation to the printer's native resolution, slice export, and an
evaluation of the quantised volume against the target and against the naive-extrusion baseline (CIEDE2000). Writes
a run folder (see --help of --out) and can resume.

With --mesh (OBJ + MTL + texture, GLB/GLTF, PLY with vertex colours, ...) the object is scaled to --height-mm,
voxelised at --dpi, and only a shell of --shell-mm below its surface is optimised (deeper voxels hold --core-ink);
the surface is a smooth dielectric (--ior), the texels shoot inward from the surface.

--device cuda runs the iterations on a GPU (the mixture, the renders, the loss and the optimiser's state; one read
back per iteration, the log row); evaluations render there and are scored on the CPU; quantisation, its renders and
the files stay on the CPU. A run resumes on either device.

Examples:
    ta-optimize-print --target colorchecker --iterations 200 --out results/colorchecker
    ta-optimize-print --target zebra --gamma 1,3,1 --out results/zebra
    ta-optimize-print --target zebra --device cuda --out results/zebra-gpu
    ta-optimize-print --target photo.png --bottom-target back.exr --width-mm 20 --out results/mine
    ta-optimize-print --mesh spot.obj --texture spot_texture.png --height-mm 20 --out results/spot
    ta-optimize-print --out results/mine --resume     # continue an interrupted run
"""
import argparse
import dataclasses
import os
import shlex
import sys

from .. import io as ta_io
from ..fabrication.inks import DEFAULT_INKS, INKS
from ..fabrication.printer import builtin_printers
from ..fabrication.quantize import HALFTONES
from ..pipelines.print.config import RESUME_MAY_CHANGE, SCHEDULES, PrintConfig, config_conflicts
from ..pipelines.print.loop import TOOL, optimize_print
from ..pipelines.print.slab_target import MIN_SLAB_TEXELS, slab_texels
from ..pipelines.print.target_images import load_target
from ..pipelines.runs import (TRACE_BATCH, RunInterrupted, check_checkpoint, check_memory, check_run_folder_owner,
                              trace_buffer_bytes)
from .command import (CommandParser, add_device_argument, check_output_folder, fail, flag_names, in_flags,
                      resolve_device)

__all__ = ["float_tuple", "add_target_arguments", "add_optimization_arguments", "config_from_args", "ink_names_help",
           "check_slab_size", "check_render_memory", "parser", "main", "MIN_SLAB_TEXELS"]

PROG = "ta-optimize-print"

def float_tuple(n, name=None):
    """An argparse type: ``n`` comma-separated numbers → tuple of floats (argparse names the flag in the message;
    ``name`` is kept for callers that pass it)."""
    def parse(text):
        try:
            values = tuple(float(v) for v in text.split(","))
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {n} comma-separated numbers, got {text!r}") from None
        if len(values) != n:
            raise argparse.ArgumentTypeError(f"expected {n} comma-separated numbers, got {text!r}")
        return values
    return parse


def _eval_texels(text):
    """``--eval-texels``: 'auto' or an int."""
    if text.strip().lower() == "auto":
        return "auto"
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected 'auto', 0 (every texel) or an int >= 1024, got {text!r}") from None


def add_target_arguments(p, d=None, *, fixed=True):
    """What is printed: a slab target image or a textured mesh, its size, shell, core ink, lighting (and, with
    ``fixed``, the ``--fixed INK=FRACTION:MASK`` constraints). ``d``: the PrintConfig giving the defaults."""
    d = PrintConfig() if d is None else d
    p.add_argument("--target", default=d.target,
                   help="top-face target: 'zebra', 'colorchecker', or an sRGB PNG/JPG or linear EXR (default: %(default)s)")
    p.add_argument("--bottom-target", default=None, help="optional bottom-face target (same size as the top)")
    p.add_argument("--thickness-mm", type=float, default=d.thickness_mm, help="slab thickness (default: %(default)s)")
    p.add_argument("--dpi", type=float, default=d.dpi, help="optimisation voxel pitch (default: %(default)s ≈ 0.0847 mm)")
    p.add_argument("--width-mm", type=float, default=None, help="slab width; default: target width × voxel pitch")
    p.add_argument("--height-mm", type=float, default=None, help="slab height (default: target height × voxel "
                   "pitch), or with --mesh the object's z extent in mm")
    p.add_argument("--mesh", default=None, help="a textured mesh to print as an object instead of a slab "
                   "(--height-mm is then its z extent in mm)")
    p.add_argument("--texture", default=None, help="base-colour image for a mesh with UVs but no material")
    p.add_argument("--shell-mm", type=float, default=d.shell_mm,
                   help="objects: optimised depth below the surface in mm (default: %(default)s)")
    p.add_argument("--core-ink", default=d.core_ink, help="objects: ink of the voxels below the shell "
                   "(default: %(default)s)")
    if fixed:
        p.add_argument("--fixed", action="append", default=[], metavar="INK=FRACTION:MASK",
                       help="hold an ink at a fixed fraction (translucency), repeatable; MASK: all, depth:A-B (mm "
                       "below the surface), a mask PNG (slab texel size, or an object's texture space), "
                       "material:NAME (objects: the faces of one of the mesh's materials), terms joined by &; e.g. "
                       "transparent=0.8:depth:0-0.4")
    p.add_argument("--envmap", default=None, help="objects: a lat-long linear EXR (z up) lighting the print, "
                   "baked into the optimisation (default: uniform white)")


def add_optimization_arguments(p, d=None):
    """How it is optimised: spp, iterations, optimiser, loss weights, quantisation, seeds. ``d``: defaults."""
    d = PrintConfig() if d is None else d
    p.add_argument("--gamma", type=float_tuple(3, "--gamma"), default=d.gamma,
                   help="weights γ1,γ2,γ3 of ΔE76², SSIM, Sobel (default: 1,3,1)")
    def default(name):  # a field left at None takes the schedule of the target's kind
        value = getattr(d, name)
        if value is None and SCHEDULES["slab"][name] == SCHEDULES["object"][name]:
            value = SCHEDULES["slab"][name]
        if value is not None:
            return f"(default: {value})"
        return f"(default: {SCHEDULES['slab'][name]} for a slab, {SCHEDULES['object'][name]} for an object)"

    p.add_argument("--spp", type=int, default=d.spp, help=f"samples per texel per iteration {default('spp')}")
    p.add_argument("--eval-spp", type=int, default=d.eval_spp,
                   help=f"samples per texel of evaluation renders {default('eval_spp')}")
    p.add_argument("--eval-every", type=int, default=d.eval_every,
                   help=f"evaluate every k iterations {default('eval_every')}")
    p.add_argument("--eval-texels", type=_eval_texels, default=d.eval_texels,
                   help=f"texels an evaluation scores, a random subset fixed for the run; 0: all; 'auto': a "
                        f"quarter of the iterations' texel samples, 2048 to 8192 {default('eval_texels')}")
    p.add_argument("--iterations", type=int, default=d.iterations, help=default("iterations"))
    p.add_argument("--table-steps", type=int, default=d.table_steps,
                   help="naive-extrusion baseline: mixtures in steps of 1/N (default: %(default)s)")
    p.add_argument("--init", choices=("white", "naive"), default=d.init,
                   help="starting mixture: 97 %% white everywhere (the paper), or the naive extrusion (each "
                        "voxel the best homogeneous mixture for its texel) (default: %(default)s)")
    p.add_argument("--estimator", choices=("ema", "plain"), default=d.estimator,
                   help="ema: the loss gradient with respect to the texel colours at the running mean of past renders, "
                        "applied to this render (unbiased by this render's noise); plain: at this render "
                        "(default: %(default)s)")
    p.add_argument("--ema-beta", type=float, default=d.ema_beta, help="decay of that mean (default: %(default)s)")
    p.add_argument("--optimizer", choices=("adagrad", "adam"), default=d.optimizer, help="(default: %(default)s)")
    p.add_argument("--lr", type=float, default=d.lr, help="learning rate (default: %(default)s)")
    p.add_argument("--parameterization", choices=("sigmoid", "softmax"), default=d.parameterization,
                   help="mixture parameterisation (default: %(default)s, as in the paper)")
    p.add_argument("--printer-dpi", type=float_tuple(3, "--printer-dpi"), default=d.printer_dpi,
                   help="native printer resolution x,y,z for quantisation (default: 600,300,940, or --printer's)")
    p.add_argument("--printer", default=d.printer,
                   help=f"a printer profile, built-in ({', '.join(builtin_printers())}) or a JSON file: quantise at its "
                        f"resolution and write its package (package-NAME/: print.gcvf, print.3mf) into the run "
                        f"folder; ta-export-print exports a run again for another printer")
    p.add_argument("--halftone", choices=HALFTONES, default=d.halftone,
                   help="how each printer voxel's ink is drawn from its voxel's mixture: by a 3D blue-noise threshold "
                        "volume (inks evenly spread: less grain at the same colour on Spot and the ColorChecker), or "
                        "independently at random (the paper) (default: %(default)s)")
    p.add_argument("--ior", type=float, default=d.ior, help="refractive index of the print (default: %(default)s)")
    p.add_argument("--seed", type=int, default=d.seed, help="(default: %(default)s)")
    p.add_argument("--gradient-seed", choices=("same", "independent"), default=d.gradient_seed,
                   help="gradient replay: retrace the forward's paths ('same') or draw independent ones with "
                        "seed_grad ('independent', as Mitsuba's render(seed, seed_grad)) (default: %(default)s)")


def ink_names_help():
    return f"comma-separated ink names from {sorted(INKS)} or a JSON ink file"


def config_from_args(args, **overrides):
    """The :class:`PrintConfig` of parsed arguments (every flag named like a field), with ``overrides``."""
    values = {f.name: getattr(args, f.name) for f in dataclasses.fields(PrintConfig) if hasattr(args, f.name)}
    if "fixed" in values:
        values["fixed"] = tuple(values["fixed"])
    values.update(overrides)
    return PrintConfig(**values)


def parser(prog=PROG):
    """The ``optimize_print`` argument parser: every flag names a :class:`PrintConfig` field, plus ``--threads``
    and ``--quiet`` (``--device`` is ``auto`` until :func:`main` resolves it)."""
    p = CommandParser(prog, __doc__.split("\n\n", 1)[1])
    add_target_arguments(p)
    p.add_argument("--inks", default=",".join(DEFAULT_INKS), help=f"{ink_names_help()} (default: %(default)s)")
    add_optimization_arguments(p)
    p.add_argument("--no-naive-baseline", dest="naive_baseline", action="store_false",
                   help="skip the naive-extrusion baseline (a table of homogeneous renders and a quantised render)")
    p.add_argument("--remap-baseline", action="store_true",
                   help="objects: also score the 2.5D remapped baseline (a slab optimised in the mesh's UV space with "
                        "the same settings, wrapped around the object by UV and depth; costs a second optimisation)")
    p.add_argument("--views", type=int, default=PrintConfig.views,
                   help="objects: camera renders of the quantised print (default: %(default)s)")
    p.add_argument("--view-size", type=int, default=PrintConfig.view_size,
                   help="objects: pixels per side of those renders (default: %(default)s)")
    p.add_argument("--view-spp", type=int, default=PrintConfig.view_spp,
                   help="objects: samples per pixel of those renders (default: 32)")
    p.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's choice)")
    add_device_argument(p)
    p.add_argument("--out", default=PrintConfig.out,
                   help="run folder: config.json, log.csv, convergence.png, target/baseline/initial/optimized/final "
                        "images (slabs: .exr+.png; objects: .npy, .ply and _uv.png), views.png (objects), "
                        "ink_usage_by_depth.png, mixture.npz, quantized.npz, slices/, checkpoint.pt, summary.json "
                        "(default: %(default)s)")
    p.add_argument("--resume", action="store_true",
                   help="continue the run in --out from its checkpoint, with the settings of its config.json (a flag "
                        "that disagrees with them is refused; --iterations may be raised to extend the run)")
    p.add_argument("--checkpoint-s", type=float, default=PrintConfig.checkpoint_s,
                   help="write checkpoint.pt at least every this many seconds of wall time, besides at every "
                        "evaluation and on Ctrl-C (default: %(default)s)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


_PATH_FLAGS = ("target", "bottom_target", "mesh", "texture", "envmap", "printer")


def absolute_paths(args):
    """Input files named by absolute paths (config.json then names them wherever the run is resumed from): the
    target images, mesh, texture, environment map, a JSON ink file and the mask images of ``--fixed``."""
    def absolute(path):
        return os.path.abspath(path) if isinstance(path, str) and os.path.isfile(path) else path

    for name in _PATH_FLAGS:
        if hasattr(args, name):
            setattr(args, name, absolute(getattr(args, name)))
    if isinstance(getattr(args, "inks", None), str) and args.inks.lower().endswith(".json"):
        args.inks = absolute(args.inks)

    def absolute_masks(spec):  # INK=FRACTION:TERM&TERM...
        head, sep, mask = spec.partition(":")
        return head + sep + "&".join(absolute(term.strip()) for term in mask.split("&")) if sep else spec

    if getattr(args, "fixed", None):
        args.fixed = [absolute_masks(spec) for spec in args.fixed]


def given_flags(p, argv):
    """The destinations of the flags that ``argv`` gives (not left at their defaults)."""
    probe = parser(p.prog)
    for action in probe._actions:
        action.default = argparse.SUPPRESS
    return set(vars(probe.parse_args(argv)))


def resumed_config(p, args, argv):
    """The config of the run in ``--out`` (its config.json), with ``--iterations``/``--checkpoint-s`` if given and
    this call's (resolved) ``--device``; any other flag given must agree with it (exit 2 naming the flags
    otherwise)."""
    path = os.path.join(args.out, "config.json")
    if not os.path.isfile(path):
        p.error(f"--resume: {args.out!r} holds no run to resume (no config.json); start one without --resume")
    try:
        stored = PrintConfig.from_record(ta_io.read_json(path, name="--resume"))
    except (TypeError, ValueError) as error:
        p.error(f"--resume: {path} does not hold a run's settings ({error})")
    given = given_flags(p, argv)
    flag = {a.dest: a.option_strings[0] for a in p._actions if a.option_strings}
    differ = config_conflicts(stored, config_from_args(args), [n for n in sorted(given) if hasattr(stored, n) and
                                                                n not in RESUME_MAY_CHANGE])
    if differ:
        p.error(f"--resume: the run in {args.out!r} was made with other settings: " +
                "; ".join(f"{flag[name]} {_show(mine)} (the run has {_show(theirs)})" for name, mine, theirs in differ)
                + "; drop these flags to resume it, or start a new run in another --out")
    checkpoint = os.path.join(args.out, "checkpoint.pt")
    if os.path.exists(checkpoint):
        try:  # a truncated or damaged checkpoint: one line naming it, before any work
            check_checkpoint(checkpoint, name="--resume")
        except ValueError as error:
            p.error(str(error))
    keep = {name: getattr(args, name) for name in ("iterations", "checkpoint_s") if name in given}
    return dataclasses.replace(stored, out=args.out, resume=True, device=args.device, **keep)


def check_slab_size(cfg, warn):
    """A slab sized by ``--width-mm``/``--height-mm`` checked before any work the way the run sizes it
    (:func:`~torch_appearance.pipelines.print.slab_target.slab_texels`): a side of fewer than
    :data:`MIN_SLAB_TEXELS` texels refused (ValueError naming the flag), ``warn(line)`` for a changed aspect."""
    if cfg.mesh is not None or (cfg.width_mm is None and cfg.height_mm is None):
        return
    slab_texels(cfg, load_target(cfg.target, name="target").shape[:2], warn)


def check_render_memory(cfg, threads=None):
    """Refuse a ``spp`` or ``eval_spp`` whose tracer buffers (:func:`~torch_appearance.pipelines.runs
    .trace_buffer_bytes`) would not fit in the memory the process may use, before any render."""
    cfg = cfg.resolved()
    for name in ("spp", "eval_spp"):
        spp = getattr(cfg, name)
        check_memory(name, trace_buffer_bytes(spp, TRACE_BATCH, threads),
                     f"{spp} samples per texel (the tracer holds every sample of {TRACE_BATCH} texels per thread)",
                     f"lower --{name.replace('_', '-')}")


def _show(value):
    if isinstance(value, (list, tuple)):
        return ",".join(getattr(v, "name", None) or str(v) for v in value)
    return str(value)


def main(argv=None, prog=PROG):
    """Run :func:`optimize_print` with the flags in ``argv`` (default ``sys.argv[1:]``); under ``torchrun``
    (``WORLD_SIZE`` > 1) the renders are data-parallel over a process group (gloo; with ``--device cuda`` NCCL, each
    rank on the GPU ``cuda:LOCAL_RANK``: :func:`torch_appearance.distributed.init_process_group`). Returns the exit
    status (2 for refused input, with the message on stderr; 130 after Ctrl-C, with the checkpoint written and the
    command that resumes the run)."""
    import torch

    argv = sys.argv[1:] if argv is None else list(argv)
    p = parser(prog)
    args = p.parse_args(argv)
    device_lines = []  # which device and why: said once the input is known to be good (a refusal says only itself)
    args.device = str(resolve_device(p, args.device, log=device_lines.append))  # refused: exit 2, before any work
    check_output_folder(p, "--out", args.out)
    try:  # another tool's folder: refused before anything is read from it or done
        check_run_folder_owner(args.out, TOOL, "--out")
    except ValueError as error:
        return fail(prog, error)
    if args.threads is not None:
        if not 1 <= args.threads <= (os.cpu_count() or 1):  # torch overflowed on 10**12
            p.error(f"--threads: expected 1 ... {os.cpu_count() or 1} (this machine's CPUs), got {args.threads}")
        torch.set_num_threads(args.threads)
    absolute_paths(args)
    cfg = resumed_config(p, args, argv) if args.resume else config_from_args(args)
    flags = flag_names(p, names="--inks")

    def say(line):  # the library's lines in this command's words
        print(in_flags(line, flags))

    def warn(line):
        print(f"{prog}: warning: {in_flags(line, flags)}", file=sys.stderr)

    distributed = int(os.environ.get("WORLD_SIZE", "1")) > 1  # started by torchrun: data-parallel rendering
    try:
        cfg.validate()
        check_slab_size(cfg, warn)
        check_render_memory(cfg)
    except (ValueError, TypeError) as error:
        return fail(prog, error, flags, vars(args))
    given = {a.split("=", 1)[0] for a in argv if a.startswith("--")}
    ignored = [f for f in ("--views", "--view-size", "--view-spp") if f in given]
    if cfg.mesh is None and ignored:  # they were ignored without a word
        warn(f"{', '.join(ignored)}: camera views are made of objects (--mesh); a slab has none: ignored")
    if int(os.environ.get("RANK", "0")) == 0:  # under torchrun one rank says it
        for line in device_lines:
            print(line)
    if distributed:
        import torch.distributed as dist

        from ..distributed import init_process_group
        cfg = dataclasses.replace(cfg, device=str(init_process_group(cfg.device)))  # cuda: this rank's own GPU
    try:
        optimize_print(cfg, progress=not args.quiet, log=say)
    except (ValueError, TypeError) as error:
        return fail(prog, error, flags, vars(args))
    except RunInterrupted as stop:
        print(f"{prog}: {stop}; resume with: {prog} --out {shlex.quote(stop.folder)} --resume", file=sys.stderr)
        return 130
    except KeyboardInterrupt:
        if os.path.exists(os.path.join(cfg.out, "checkpoint.pt")):  # a resumed run, stopped before its first step
            print(f"{prog}: interrupted before the optimisation went on; its checkpoint is unchanged; resume with: "
                  f"{prog} --out {shlex.quote(cfg.out)} --resume", file=sys.stderr)
        else:
            print(f"{prog}: interrupted before the optimisation began; nothing to resume (start it again)",
                  file=sys.stderr)
        return 130
    finally:
        if distributed:
            dist.destroy_process_group()
    return 0


if __name__ == "__main__":
    sys.exit(main())
