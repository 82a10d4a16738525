#!/usr/bin/env python
"""Error against time of the chromatic estimators: one walk per channel ("per_channel") against one hero-channel
walk with spectral MIS ("hero"), on the scenes of ``scripts/bench/bench_volpath.py``.

For each scene, estimator and spp in ``--spp``: one forward + backward (``loss = (image * w).sum()`` with the
benchmark's fixed random weights), timed, and the RMSE of the image and of both gradients against one
per-channel reference at ``--ref-spp`` (independent seed, cached beside ``--out``). The reference's own noise is
removed from the raw MSE: its variance per element is estimated from the per-channel points (raw MSE at s spp =
σ²₁ (1/s + 1/R)), and subtracted from every point. Unbiased estimators fall on lines of slope −1/2 in log RMSE
against log seconds; the lower line gives less error for the same time (1/(RMSE²·s) is bench_volpath's
``efficiency``).

Writes ``--out`` (JSON, one object per point) and a PNG beside it (RMSE against seconds, log-log, one panel per
scene and quantity), atomically.

Usage::

    python scripts/bench/bench_chromatic_curve.py --scenes print-slab,ink-slab --spp 1,2,4,8,16 --threads 1 \\
        --slab-size 96 --out results/bench/chromatic_curve.json
"""
import argparse
import io
import math
import os
import sys
import zlib

import torch

# this folder is on the path when the script runs
from bench_volpath import SCENE_VOXEL, SCENES, VOXEL_SIZE, _int_list, _run_once, make_scene

KEYS = ("image", "grad_sigma_t", "grad_albedo")


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], epilog=__doc__.split("\n\n", 1)[1],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenes", default="print-slab,ink-slab",
                        help=f"comma-separated scenes from {','.join(SCENES)} (default: %(default)s)")
    parser.add_argument("--spp", type=_int_list, default=[1, 2, 4, 8, 16],
                        help="comma-separated samples per texel of the points (default: 1,2,4,8,16)")
    parser.add_argument("--chromatic", default="per_channel,hero",
                        help="comma-separated estimators; per_channel is needed (default: %(default)s)")
    parser.add_argument("--ref-spp", type=int, default=256, help="reference samples per texel (default: %(default)s)")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default: %(default)s)")
    parser.add_argument("--slab-size", type=int, default=96, help="print-slab texels per side (default: %(default)s)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the scenes and the tracer (default: %(default)s)")
    parser.add_argument("--ior", type=float, default=1.5, help="index of refraction (default: %(default)s)")
    parser.add_argument("--g", type=float, default=0.4, help="Henyey-Greenstein parameter (default: %(default)s)")
    parser.add_argument("--out", default="results/bench/chromatic_curve.json",
                        help="JSON result file; the plot goes beside it as .png (default: %(default)s)")
    args = parser.parse_args(argv)
    from torch_appearance.render.scene import CHROMATIC
    args.scenes = [s.strip() for s in args.scenes.split(",") if s.strip()]
    args.chromatic = [c.strip() for c in args.chromatic.split(",") if c.strip()]
    if not args.scenes or any(s not in SCENES for s in args.scenes):
        parser.error(f"--scenes: expected names from {', '.join(SCENES)}, got {args.scenes}")
    if "per_channel" not in args.chromatic or any(c not in CHROMATIC for c in args.chromatic):
        parser.error(f"--chromatic: expected names from {', '.join(CHROMATIC)} including per_channel, "
                     f"got {args.chromatic}")
    if args.ref_spp < 1 or args.threads < 1 or args.slab_size < 1:
        parser.error("--ref-spp, --threads and --slab-size must be >= 1")
    return args


def _setup(name, args):
    generator = torch.Generator().manual_seed(args.seed + zlib.crc32(name.encode()))
    sigma_t, albedo, _, scene = make_scene(name, generator, args)
    sigma_t = sigma_t.to(torch.float32).contiguous()
    albedo = albedo.to(torch.float32).contiguous()
    _, depth, height, width = sigma_t.shape
    out_shape = (height, width, 3) if scene is None else scene.output_shape((depth, height, width))
    weights = torch.rand(out_shape, generator=generator, dtype=torch.float64).to(torch.float32)
    return sigma_t, albedo, scene, weights, SCENE_VOXEL.get(name, VOXEL_SIZE)


def _reference(name, setup, args):
    from torch_appearance import io as ta_io
    sigma_t, albedo, scene, weights, voxel = setup
    size = "x".join(str(n) for n in sigma_t.shape[1:])
    folder = os.path.join(os.path.dirname(os.path.abspath(args.out)), "reference")
    path = os.path.join(folder, f"{name}-{size}-spp{args.ref_spp}-ior{args.ior}-g{args.g}-seed{args.seed}.pt")
    if os.path.exists(path):
        return torch.load(path)
    *_, ref = _run_once(sigma_t, albedo, weights, args.ref_spp, args.seed + 7919, args.ior, args.g, scene, voxel,
                        keep=True)
    os.makedirs(folder, exist_ok=True)
    buffer = io.BytesIO()
    torch.save(ref, buffer)
    ta_io.atomic_write_bytes(path, buffer.getvalue())
    return ref


def plot(rows, path):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker
    from torch_appearance import io as ta_io
    scenes = list(dict.fromkeys(r["scene"] for r in rows))
    fig, axes = plt.subplots(len(scenes), len(KEYS), figsize=(4.2 * len(KEYS), 3.4 * len(scenes)), squeeze=False)
    for i, scene in enumerate(scenes):
        for j, key in enumerate(KEYS):
            ax = axes[i][j]
            for chromatic in dict.fromkeys(r["chromatic"] for r in rows):
                pts = [r for r in rows if r["scene"] == scene and r["chromatic"] == chromatic]
                ax.loglog([r["seconds"] for r in pts], [r[f"{key}_rmse"] for r in pts], "o-", label=chromatic)
                for r in pts:
                    ax.annotate(str(r["spp"]), (r["seconds"], r[f"{key}_rmse"]), fontsize=6)
            ax.set_title(f"{scene}: {key}", fontsize=9)
            ax.set_xlabel("forward + backward seconds")
            ax.set_ylabel("RMSE")
            ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())  # (overlapping labels otherwise)
            ax.grid(True, which="both", alpha=0.3)
            ax.legend(fontsize=7)
    fig.tight_layout()
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=110)
    plt.close(fig)
    ta_io.atomic_write_bytes(path, buffer.getvalue())


def main(argv=None):
    args = parse_args(argv)
    from torch_appearance.progress import progress_bar
    from torch_appearance import io as ta_io
    torch.set_num_threads(args.threads)
    rows = []
    jobs = [(n, c, s) for n in args.scenes for c in args.chromatic for s in args.spp]
    bar = progress_bar(total=len(jobs) + len(args.scenes), desc="bench_chromatic_curve", unit="run")
    for name in args.scenes:
        setup = _setup(name, args)
        sigma_t, albedo, scene, weights, voxel = setup
        ref = _reference(name, setup, args)
        bar.update(1)
        raw = []
        for chromatic, spp in ((c, s) for n, c, s in jobs if n == name):
            _run_once(sigma_t, albedo, weights, spp, args.seed, args.ior, args.g, scene, voxel,
                      chromatic=chromatic)  # warm-up
            fwd, bwd, stats, est = _run_once(sigma_t, albedo, weights, spp, args.seed, args.ior, args.g, scene,
                                             voxel, keep=True, chromatic=chromatic)
            mse = {k: float(((e.double() - r.double()) ** 2).mean()) for k, e, r in zip(KEYS, est, ref)}
            raw.append((chromatic, spp, fwd, bwd, mse))
            bar.update(1)
        # the reference's noise variance per element, from the per-channel points: raw = σ²₁ (1/s + 1/R)
        ref_var = {k: sum(m[k] / (1 / s + 1 / args.ref_spp) for c, s, _, _, m in raw if c == "per_channel")
                   / sum(1 for c, *_ in raw if c == "per_channel") / args.ref_spp for k in KEYS}
        for chromatic, spp, fwd, bwd, mse in raw:
            row = {"scene": name, "chromatic": chromatic, "spp": spp, "threads": args.threads,
                   "forward_s": round(fwd, 5), "backward_s": round(bwd, 5), "seconds": round(fwd + bwd, 5),
                   "ref_spp": args.ref_spp}
            for k in KEYS:
                rmse = math.sqrt(max(mse[k] - ref_var[k], 0.0))
                row[f"{k}_rmse"] = float(f"{rmse:.6g}")
                row[f"efficiency_{k}"] = float(f"{1 / (rmse * rmse * (fwd + bwd)):.6g}") if rmse > 0 else None
            rows.append(row)
            bar.write(str(row))
    bar.close()
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    ta_io.write_json(args.out, rows)
    plot(rows, os.path.splitext(args.out)[0] + ".png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
