#!/usr/bin/env python
"""Benchmark one print-optimisation iteration of a textured object (default Spot) at several heights, end to end.

The mesh is scaled to each ``--heights-mm``, voxelised at ``--dpi`` with a ``--shell-mm`` shell (as
``ta-optimize-print --mesh`` does: the shell voxels carry the optimised mixture, the core holds white), the mixture
starts at 97 % white (MaterialMixture's initialisation, the paper's start and the longest paths), and one iteration
is timed in its parts, after an untimed warm-up iteration at 1 spp:

* ``mix_s``: the mixture → dense (3, D, H, W) σ_t and albedo of the bounding box (``MaterialMixture.forward``);
* ``forward_s``: the tracer's forward (surface texels, smooth dielectric SDF boundary, ``--spp`` per texel);
* ``loss_s``: the appearance loss on the texels (sparse texel path) against a target of the texture's colours;
* ``backward_s``: ``loss.backward()``, of which ``replay_s`` is the tracer's path replay (its own timer; gradients
  only in the shell, ``grad_support``, as the print loop asks) and the
  rest the gradient of the loss and of the dense scatter back to the shell's logits;
* ``step_s``: the Adagrad step; ``iteration_s``: their sum;
* ``events_per_path`` (scattering events of the forward per path; a path is one texel sample of one channel for the
  per-channel estimator, of all three for hero), ``voxel_steps_per_path`` and ``outside_steps_per_path`` (voxels
  visited by the flights inside the object, and cells visited outside it, where empty bricks are crossed in one
  move each), ``core_event_share`` (the share of the scattering events in the homogeneous white core, crossed in
  bricks; ``--shortcuts off,on`` times each height without and with the two brick shortcuts), ``peak_rss_mb`` (VmHWM
  growth over the iteration); ``--walks two,one`` times the iteration with a forward and a replay, and as the
  ``ema`` estimator runs it from its second iteration on (the loss's gradient at the running mean first, here the
  warm-up's render, then one walk for the render and its gradient: ``replay_s`` is then 0), ``--simd scalar,avx2``
  times it with the scalar walk and with the SIMD object walk (csrc/volpath/object_simd.h) at each width,
  with ``--depth-bin-mm`` > 0, ``by_depth``: one more, untimed forward at ``--spp`` whose walk counts its scattering
  events and voxel moves by the depth of their voxel below the surface, in bins of that width (``[depth_from_mm,
  share of the events, share of the moves]`` per bin; the last bin holds everything deeper), and ``events_per_mm3``
  per bin (events per path per mm³ of that bin's volume inside the object);
  and, with ``--ref-mult`` > 0, ``image_rmse`` against a render at ``ref-mult × spp`` with another seed (corrected
  for the reference's own noise) and ``efficiency`` = 1 / (RMSE² · (forward_s + replay_s)).

With ``--baseline REV`` each height is also timed on the extension built from git revision REV (built once into
build/baseline-<sha>/, as ``bench_volpath.py --baseline`` does): the tracer's raw forward and replay of the
iteration above (the same grids, options and adjoint; the new build gets ``grad_support`` as the print loop passes
it, an old build without that option replays every voxel), old and new alternating in worker processes
``--reps`` times, with the medians and new / old ratios in a ``"compare": "new/old"`` line.

One JSON line per height and estimator (``--chromatic per_channel,hero``); all lines are also written atomically
to ``--out``. Numbers go to docs/bench_log.md with the date and the command.

Usage::

    python scripts/bench/bench_objects.py --heights-mm 10,20 --spp 8 --threads 2
    python scripts/bench/bench_objects.py --heights-mm 25 --spp 32 --chromatic per_channel,hero --ref-mult 4
    python scripts/bench/bench_objects.py --heights-mm 25 --spp 8 --walks two,one
    python scripts/bench/bench_objects.py --heights-mm 25,40 --spp 8 --simd scalar,avx2
    python scripts/bench/bench_objects.py --heights-mm 25 --spp 8 --baseline c845e46 --reps 2
"""
import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time

import torch

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(os.path.dirname(HERE))
SPOT = os.path.join(ROOT, "tests", "data", "meshes", "spot")

from torch_appearance import io as ta_io  # noqa: E402
from torch_appearance.testing import reset_peak_rss, status_kb  # noqa: E402


def build(args, height):
    """The object target, its mixture (97 % white shell, white core) and the loss, for ``height`` mm."""
    from torch_appearance.nn.losses import AppearanceLoss
    from torch_appearance.nn.mixture import MaterialMixture
    from torch_appearance.pipelines.print import PrintConfig
    from torch_appearance.pipelines.print.config import load_inks
    from torch_appearance.pipelines.print.object_target import ObjectTarget
    cfg = PrintConfig(mesh=args.mesh, texture=args.texture, height_mm=height, dpi=args.dpi, shell_mm=args.shell_mm,
                      out="unused")
    inks = load_inks(cfg.inks)
    t0 = time.perf_counter()
    target = ObjectTarget.from_config(cfg, inks, log=lambda *a: None)
    prepare_s = time.perf_counter() - t0
    model = MaterialMixture(inks, tuple(target.shape), support=target.support, core_ink="white")
    return target, model, AppearanceLoss(gamma=(1.0, 3.0, 1.0)), prepare_s


def iteration(target, model, criterion, optimizer, spp, seed, chromatic, primal=None):
    """One timed iteration; returns the timings and the tracer's statistics. With ``primal`` (texel colours, as the
    print loop's running mean) the iteration is the ``ema`` estimator's: the loss's gradient at ``primal`` first
    (``loss_s``), then one walk for the render and its gradient (``forward_s``; render_scene's ``adjoint``)."""
    from torch_appearance.render.volpath import render_scene
    stats, parts = {}, {}
    clock = [time.perf_counter()]

    def lap(name):
        clock.append(time.perf_counter())
        parts[name] = clock[-1] - clock[-2]

    sigma_t, albedo = model()
    lap("mix_s")
    kw = dict(spp=spp, seed=seed, stats=stats, chromatic=chromatic, grad_support=target.support)
    if primal is None:
        image = render_scene(target.scene, sigma_t, albedo, **kw)
        lap("forward_s")
        loss, _ = target.appearance(criterion, image)
        lap("loss_s")
    else:
        x = primal.clone().requires_grad_(True)
        value, _ = target.appearance(criterion, x)
        (adjoint,) = torch.autograd.grad(value, x)
        lap("loss_s")
        image = render_scene(target.scene, sigma_t, albedo, adjoint=adjoint, **kw)
        lap("forward_s")
        loss = (adjoint * image).sum()
    optimizer.zero_grad(set_to_none=True)
    loss.backward()
    lap("backward_s")
    optimizer.step()
    lap("step_s")
    return parts, stats, image.detach()


def events_by_depth(target, model, start, args, chromatic, paths):
    """The forward's events and voxel moves by depth below the surface (the walk's tally, _C._set_tally)."""
    from torch_appearance import _C
    from torch_appearance.render.volpath import render_scene
    import numpy as np
    from scipy import ndimage
    sdf = target.scene.boundary.sdf  # (D+1, H+1, W+1) corner distances, mm, negative inside (a narrow band)
    centre = sum(sdf[k:k + sdf.shape[0] - 1, j:j + sdf.shape[1] - 1, i:i + sdf.shape[2] - 1]
                 for k in (0, 1) for j in (0, 1) for i in (0, 1))
    inside = (centre < 0).numpy()
    del centre
    sx, sy, sz = target.scene.voxel_size
    # depth of each inside voxel's centre: the distance to the nearest voxel centre outside (within half a voxel)
    depth = torch.from_numpy(ndimage.distance_transform_edt(inside, sampling=(sz, sy, sx)).astype(np.float32))
    last = 254
    bins = (depth / args.depth_bin_mm).floor().clamp(0, last).to(torch.uint8)
    bins[torch.from_numpy(~inside)] = 255  # outside (a walk's moves there are rounding at the surface)
    voxel_mm3 = sx * sy * sz
    model.load_state_dict(start)
    stats = {}
    with torch.no_grad():
        sigma_t, albedo = model()
        _C._set_tally(bins)
        try:
            render_scene(target.scene, sigma_t, albedo, spp=args.spp, seed=args.seed, stats=stats, chromatic=chromatic)
        finally:
            _C._set_tally(None)
    tally = stats["tally"].double()
    share = tally / tally.sum(0).clamp(min=1)
    counts = torch.bincount(bins.flatten().long(), minlength=256).double()
    rows, per_mm3 = [], []
    for b in range(last + 1):
        if tally[b].sum() == 0:
            continue
        rows.append([round(b * args.depth_bin_mm, 3), round(float(share[b, 0]), 4), round(float(share[b, 1]), 4)])
        per_mm3.append(round(float(tally[b, 0]) / paths / (float(counts[b]) * voxel_mm3), 5))
    return {"by_depth": rows, "events_per_mm3": per_mm3,
            "events_outside_share": round(float(share[255, 0]), 5)}


def run(args, height, chromatic):
    torch.manual_seed(args.seed)
    target, model, criterion, prepare_s = build(args, height)
    start = {k: v.clone() for k, v in model.state_dict().items()}  # 97 % white
    optimizer = torch.optim.Adagrad(model.parameters(), lr=1.0)
    _, _, warm = iteration(target, model, criterion, optimizer, 1, args.seed + 1, chromatic)  # warm-up (pages)
    model.load_state_dict(start)
    optimizer = torch.optim.Adagrad(model.parameters(), lr=1.0)
    base = status_kb("VmRSS")
    reset_peak_rss()
    primal = warm if args.walks_now == "one" else None  # the warm-up's render stands for the running mean
    parts, stats, image = iteration(target, model, criterion, optimizer, args.spp, args.seed, chromatic, primal)
    peak = status_kb("VmHWM")
    texels = image.shape[0]
    paths = texels * args.spp * (3 if stats.get("lanes", 1) == 1 and not stats.get("hero") else 1)
    row = {"mesh": os.path.basename(args.mesh), "height_mm": height, "dpi": args.dpi, "shell_mm": args.shell_mm,
           "grid_dhw": list(target.shape), "texels": texels, "shell_voxels": int(model.param_shape[0]),
           "chromatic": chromatic, "spp": args.spp, "threads": torch.get_num_threads(),
           "prepare_s": round(prepare_s, 3), **{k: round(v, 4) for k, v in parts.items()},
           "replay_s": round(stats.get("backward_s", float("nan")), 4),
           "iteration_s": round(sum(parts.values()), 4),
           "events_per_path": round(stats["scatter_events"] / paths, 2),
           # (the one walk counts its scattering events only)
           "voxel_steps_per_path": round(stats["voxel_steps"] / paths, 2) if "voxel_steps" in stats else None,
           "outside_steps_per_path": round(stats["outside_steps"] / paths, 2) if "outside_steps" in stats else None,
           "core_event_share": (round(stats["core_events"] / max(1, stats["scatter_events"]), 4)
                                if "core_events" in stats else None),
           "shortcuts": args.shortcuts_now, "walks": args.walks_now, "simd": args.simd_now,
           "peak_rss_mb": None if peak is None or base is None else round((peak - base) / 1024, 1)}
    if args.depth_bin_mm > 0:
        row.update(events_by_depth(target, model, start, args, chromatic, paths))
    if args.ref_mult > 0:
        from torch_appearance.render.volpath import render_scene
        model.load_state_dict(start)
        with torch.no_grad():
            sigma_t, albedo = model()
            ref = render_scene(target.scene, sigma_t, albedo, spp=args.spp * args.ref_mult, seed=args.seed + 7919)
        mse = float(((image.double() - ref.double()) ** 2).mean()) / (1.0 + 1.0 / args.ref_mult)
        row["image_rmse"] = mse ** 0.5
        row["efficiency"] = 1.0 / (mse * (parts["forward_s"] + row["replay_s"]))
    return row


# --------------------------------------------------------------------------------------------------------------
# old code against new code (--baseline)
# --------------------------------------------------------------------------------------------------------------
# Runs in a fresh interpreter after bench_volpath's WORKER_LOAD (one build of the extension per process), rebuilds the
# options from plain values (fields the build does not know are dropped and reported), times one forward and one
# replay after a 1-spp warm-up of both, prints JSON.
_WORKER = r"""
dropped = set()
def build(spec):
    o = getattr(C, spec["type"])()
    for k, v in spec["fields"].items():
        if not hasattr(o, k):
            dropped.add(spec["type"] + "." + k)
            continue
        setattr(o, k, build(v) if isinstance(v, dict) else v)
    return o
fwd, bwd = build(d["forward"]), build(d["backward"])
s, a, rs, ra, g = d["sigma_t"], d["albedo"], d["ref_sigma_t"], d["ref_albedo"], d["grad"]
spp = fwd.spp
fwd.spp = bwd.spp = 1
C.scene_forward(s, a, s, a, False, fwd)
C.scene_backward(g, s, a, rs, ra, True, True, bwd, d["sigma_t_floor"], d["albedo_floor"])
fwd.spp = bwd.spp = spp
t0 = time.perf_counter()
image, counts = C.scene_forward(s, a, s, a, False, fwd)
t1 = time.perf_counter()
gs, ga, _ = C.scene_backward(g, s, a, rs, ra, True, True, bwd, d["sigma_t_floor"], d["albedo_floor"])
t2 = time.perf_counter()
with open("/proc/self/status") as f:
    peak = [int(l.split()[1]) / 1024 for l in f if l.startswith("VmHWM:")]
print(json.dumps({"forward_s": t1 - t0, "replay_s": t2 - t1, "checksum": float(image.double().sum()),
                  "scatter_events": counts.scatter_events, "dropped": sorted(dropped),
                  "peak_rss_mb": peak[0] if peak else None}))
"""


def _plain(options):
    """A pybind options object as plain values: {"type": class name, "fields": {name: value}}, nested options
    (objects of the extension's own classes) likewise."""
    fields = {}
    for k in dir(options):
        v = getattr(options, k)
        if k.startswith("_") or callable(v) or v is None:  # None: an unset tensor, left at its default
            continue
        fields[k] = _plain(v) if type(v).__module__ == type(options).__module__ else v
    return {"type": type(options).__name__, "fields": fields}


def compare_baseline(args, height, chromatic, old_so, sha):
    """new / old times of the tracer's forward and replay of one Spot iteration, in alternating worker processes."""
    from bench_volpath import WORKER_LOAD  # this folder is on the path when the script runs
    from torch_appearance import _C
    from torch_appearance.autograd.volpath import _gradient_walks, walk_options
    from torch_appearance.render import TraceJob
    torch.manual_seed(args.seed)
    target, model, _, _ = build(args, height)
    with torch.no_grad():
        sigma_t, albedo = (x.contiguous() for x in model())
    job = TraceJob(target.scene, spp=args.spp, seed=args.seed, chromatic=chromatic, grad_support=target.support)
    grid = tuple(sigma_t.shape[1:])
    forward = walk_options(job, sigma_t, job.seed, grid, sigma_t.dtype)
    ref_s, floor_s, ref_a, floor_a, backward = _gradient_walks(job, sigma_t, albedo, None, None)
    image, _ = _C.scene_forward(sigma_t, albedo, sigma_t, albedo, False, forward)
    grad = torch.rand(image.shape, generator=torch.Generator().manual_seed(args.seed), dtype=torch.float64)
    grad = (grad - 0.5).to(image.dtype).contiguous()  # a fixed adjoint of both signs
    del image
    new_so = _C.__file__
    with tempfile.TemporaryDirectory() as tmp:
        data = os.path.join(tmp, "scene.pt")
        torch.save(dict(sigma_t=sigma_t, albedo=albedo, ref_sigma_t=ref_s, ref_albedo=ref_a, grad=grad,
                        sigma_t_floor=floor_s, albedo_floor=floor_a, forward=_plain(forward),
                        backward=_plain(backward)), data)
        del target, model, sigma_t, albedo, ref_s, ref_a
        runs = {"old": [], "new": []}
        for _ in range(args.reps):
            for which, so in (("old", old_so), ("new", new_so)):
                out = subprocess.run([sys.executable, "-c", WORKER_LOAD + _WORKER, so, data, str(args.threads)],
                                     check=True, capture_output=True, text=True).stdout
                runs[which].append(json.loads(out.strip().splitlines()[-1]))
    med = {w: {k: statistics.median(r[k] for r in runs[w]) for k in ("forward_s", "replay_s")} for w in runs}
    return {
        "compare": "new/old", "baseline": sha[:12], "height_mm": height, "chromatic": chromatic, "spp": args.spp,
        "threads": args.threads, "reps": args.reps,
        **{f"{w}_{k}": round(med[w][k], 4) for w in ("old", "new") for k in ("forward_s", "replay_s")},
        "ratio_forward": round(med["new"]["forward_s"] / med["old"]["forward_s"], 4),
        "ratio_replay": round(med["new"]["replay_s"] / med["old"]["replay_s"], 4),
        "ratio_iteration": round(sum(med["new"].values()) / sum(med["old"].values()), 4),
        "old_peak_rss_mb": max(r["peak_rss_mb"] or 0 for r in runs["old"]),
        "new_peak_rss_mb": max(r["peak_rss_mb"] or 0 for r in runs["new"]),
        "same_image": runs["old"][0]["checksum"] == runs["new"][0]["checksum"],
        "same_scatter_events": runs["old"][0]["scatter_events"] == runs["new"][0]["scatter_events"],
        "old_dropped_options": runs["old"][0]["dropped"],
    }


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], epilog=__doc__.split("Usage::")[1],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--mesh", default=os.path.join(SPOT, "spot_triangulated.obj"), help="(default: Spot)")
    p.add_argument("--texture", default=os.path.join(SPOT, "spot_texture.png"), help="(default: Spot's)")
    p.add_argument("--heights-mm", default="20,25", help="comma-separated object heights (default: %(default)s)")
    p.add_argument("--dpi", type=float, default=300.0, help="(default: %(default)s)")
    p.add_argument("--shell-mm", type=float, default=2.0, help="(default: %(default)s)")
    p.add_argument("--spp", type=int, default=32, help="samples per texel (default: %(default)s)")
    p.add_argument("--chromatic", default="per_channel", help="comma-separated estimators: per_channel, hero "
                   "(default: %(default)s)")
    p.add_argument("--ref-mult", type=int, default=0, help="reference spp = this × spp for image_rmse; 0: none "
                   "(default: %(default)s)")
    p.add_argument("--shortcuts", default="on", help="comma-separated: on, off: the walk's brick shortcuts (empty space "
                   "outside the object, its homogeneous core) for before/after figures in one run (default: "
                   "%(default)s)")
    p.add_argument("--walks", default="two", help="comma-separated: two (a forward, then the replay of the loss's "
                   "gradient), one (the ema estimator's adjoint known first: one walk for the render and its "
                   "gradient) (default: %(default)s)")
    p.add_argument("--simd", default="auto", help="comma-separated walks: auto (the CPU's widest, TA_SIMD), scalar, "
                   "avx2, avx512: the scalar walk and the SIMD object walk at each width in one run (default: "
                   "%(default)s)")
    p.add_argument("--depth-bin-mm", type=float, default=0.0, help="> 0: also count the events and voxel moves by "
                   "depth below the surface in bins of this width, in one more forward (default: off)")
    p.add_argument("--baseline", metavar="REV", default=None,
                   help="also time the tracer's forward and replay on the extension of git revision REV, old and new "
                        "alternating in worker processes, and print new/old ratios")
    p.add_argument("--reps", type=int, default=2, help="--baseline: rounds of old and new (default: %(default)s)")
    p.add_argument("--threads", type=int, default=torch.get_num_threads(), help="(default: torch's)")
    p.add_argument("--seed", type=int, default=0, help="(default: %(default)s)")
    p.add_argument("--out", default="results/bench/objects.jsonl", help="(default: %(default)s)")
    args = p.parse_args(argv)
    try:
        heights = [float(h) for h in args.heights_mm.split(",")]
    except ValueError:
        p.error(f"--heights-mm: expected comma-separated numbers, got {args.heights_mm!r}")
    chromatic = [c.strip() for c in args.chromatic.split(",")]
    if any(c not in ("per_channel", "hero") for c in chromatic):
        p.error(f"--chromatic: expected per_channel and/or hero, got {args.chromatic!r}")
    shortcuts = [c.strip() for c in args.shortcuts.split(",")]
    if any(c not in ("on", "off") for c in shortcuts):
        p.error(f"--shortcuts: expected on and/or off, got {args.shortcuts!r}")
    walks = [w.strip() for w in args.walks.split(",")]
    if any(w not in ("one", "two") for w in walks):
        p.error(f"--walks: expected one and/or two, got {args.walks!r}")
    simd_modes = {"auto": -1, "scalar": 0, "avx2": 1, "avx512": 2}
    simds = [w.strip() for w in args.simd.split(",")]
    if any(w not in simd_modes for w in simds):
        p.error(f"--simd: expected auto, scalar, avx2 and/or avx512, got {args.simd!r}")
    if not args.depth_bin_mm >= 0:
        p.error(f"--depth-bin-mm: expected a width >= 0 (0: off), got {args.depth_bin_mm}")
    if args.spp < 1 or args.threads < 1 or args.ref_mult < 0 or args.reps < 1:
        p.error("--spp, --threads and --reps: expected >= 1; --ref-mult: expected >= 0")
    torch.set_num_threads(args.threads)
    rows = []
    from torch_appearance import _C
    if args.baseline is not None:
        from bench_volpath import build_baseline  # this folder is on the path when the script runs
        old_so, sha = build_baseline(args.baseline)
    for height in heights:
        for c in chromatic:
            for mode in shortcuts:
                for w in walks:
                    for simd in simds:
                        args.shortcuts_now, args.walks_now, args.simd_now = mode, w, simd
                        _C._set_empty_space_skipping(mode == "on")
                        _C._set_core_walk(mode == "on")
                        try:
                            _C._set_simd(simd_modes[simd])
                        except RuntimeError as e:
                            p.error(f"--simd {simd}: {e}")
                        row = run(args, height, c)
                        print(json.dumps(row), flush=True)
                        rows.append(row)
                    _C._set_simd(-1)
            if args.baseline is not None:
                _C._set_empty_space_skipping(True)
                _C._set_core_walk(True)
                row = compare_baseline(args, height, c, old_so, sha)
                print(json.dumps(row), flush=True)
                rows.append(row)
    _C._set_empty_space_skipping(True)
    _C._set_core_walk(True)
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    ta_io.atomic_write_bytes(args.out, "".join(json.dumps(r) + "\n" for r in rows).encode())
    return 0


if __name__ == "__main__":
    sys.exit(main())
