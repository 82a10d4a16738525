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
  bricks; ``--shortcuts off,on`` times each height without and with the two brick shortcuts), ``peak_rss_mb`` (VmHWM growth over the iteration),
  with ``--depth-bin-mm`` > 0, ``by_depth``: one more, untimed forward at ``--spp`` whose walk counts its scattering
  events and voxel moves by the depth of their voxel below the surface, in bins of that width (``[depth_from_mm,
  share of the events, share of the moves]`` per bin; the last bin holds everything deeper), and ``events_per_mm3``
  per bin (events per path per mm³ of that bin's volume inside the object);
  and, with ``--ref-mult`` > 0, ``image_rmse`` against a render at ``ref-mult × spp`` with another seed (corrected
  for the reference's own noise) and ``efficiency`` = 1 / (RMSE² · (forward_s + replay_s)).

One JSON line per height and estimator (``--chromatic per_channel,hero``); all lines are also written atomically
to ``--out``. Numbers go to scripts/bench/README.md with the date and the command.

Usage::

    python scripts/bench/bench_objects.py --heights-mm 10,20 --spp 8 --threads 2
    python scripts/bench/bench_objects.py --heights-mm 25 --spp 32 --chromatic per_channel,hero --ref-mult 4
"""
import argparse
import json
import os
import sys
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


def iteration(target, model, criterion, optimizer, spp, seed, chromatic):
    """One timed iteration; returns the timings and the tracer's statistics."""
    from torch_appearance.render.volpath import render_scene
    stats = {}
    t = [time.perf_counter()]
    sigma_t, albedo = model()
    t.append(time.perf_counter())
    image = render_scene(target.scene, sigma_t, albedo, spp=spp, seed=seed, stats=stats, chromatic=chromatic,
                         grad_support=target.support)
    t.append(time.perf_counter())
    loss, _ = target.appearance(criterion, image)
    t.append(time.perf_counter())
    optimizer.zero_grad(set_to_none=True)
    loss.backward()
    t.append(time.perf_counter())
    optimizer.step()
    t.append(time.perf_counter())
    parts = dict(zip(("mix_s", "forward_s", "loss_s", "backward_s", "step_s"), (b - a for a, b in zip(t, t[1:]))))
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
    iteration(target, model, criterion, optimizer, 1, args.seed + 1, chromatic)  # warm-up (filter matrices, pages)
    model.load_state_dict(start)
    optimizer = torch.optim.Adagrad(model.parameters(), lr=1.0)
    base = status_kb("VmRSS")
    reset_peak_rss()
    parts, stats, image = iteration(target, model, criterion, optimizer, args.spp, args.seed, chromatic)
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
           "voxel_steps_per_path": round(stats["voxel_steps"] / paths, 2),
           "outside_steps_per_path": round(stats["outside_steps"] / paths, 2),
           "core_event_share": round(stats["core_events"] / max(1, stats["scatter_events"]), 4),
           "shortcuts": args.shortcuts_now,
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
    p.add_argument("--depth-bin-mm", type=float, default=0.0, help="> 0: also count the events and voxel moves by "
                   "depth below the surface in bins of this width, in one more forward (default: off)")
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
    if not args.depth_bin_mm >= 0:
        p.error(f"--depth-bin-mm: expected a width >= 0 (0: off), got {args.depth_bin_mm}")
    if args.spp < 1 or args.threads < 1 or args.ref_mult < 0:
        p.error("--spp and --threads: expected >= 1; --ref-mult: expected >= 0")
    torch.set_num_threads(args.threads)
    rows = []
    from torch_appearance import _C
    for height in heights:
        for c in chromatic:
            for mode in shortcuts:
                args.shortcuts_now = mode
                _C._set_empty_space_skipping(mode == "on")
                _C._set_core_walk(mode == "on")
                row = run(args, height, c)
                print(json.dumps(row), flush=True)
                rows.append(row)
    _C._set_empty_space_skipping(True)
    _C._set_core_walk(True)
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    ta_io.atomic_write_bytes(args.out, "".join(json.dumps(r) + "\n" for r in rows).encode())
    return 0


if __name__ == "__main__":
    sys.exit(main())
