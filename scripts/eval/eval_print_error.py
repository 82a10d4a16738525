"""The print evaluator against a high-spp reference (issue 46): bias and standard error of the noise-free CIEDE2000
(:func:`torch_appearance.print_error.noise_free_error`) at several evaluation budgets, on a slab and on an object.

A print (the naive extrusion of a target, quantised as a run quantises it, or the ``quantized.npz`` of a finished
run) is rendered ``--renders`` times at ``--spp`` with independent seeds. The reference is the estimator on all of
them (``renders × spp`` samples per texel, four groups), beside the raw figure of their mean. Disjoint groups of them
make evaluations at the budgets 4 × spp, 8 × spp, …: per budget the mean over groups of the raw figure and of the
estimate, its bias against the reference, the spread over groups (sd) and the mean reported standard error (se).
With ``--texels M`` every group scores its own random subset of M texels, as an object run's evaluations do
(``eval_texels``): the reported SE then includes the sampling error over texels, and the spread over groups shows
whether it should.

Writes ``print_error.json`` and prints a Markdown table.

Examples:
    python scripts/eval/eval_print_error.py --target colorchecker --spp 16 --renders 256 --out /tmp/pe_slab
    python scripts/eval/eval_print_error.py --mesh-height-mm 10 --spp 16 --renders 64 --out /tmp/pe_spot10
    python scripts/eval/eval_print_error.py --run results/demo --spp 16 --renders 256 --out /tmp/pe_demo
    python scripts/eval/eval_print_error.py --mesh-height-mm 10 --spp 8 --renders 128 --texels 12288 --out /tmp/pe_sub
"""
import argparse
import json
import os
import time

import numpy as np
import torch

from torch_appearance.fabrication.export import load_index_volume
from torch_appearance.pipelines.print import PrintConfig
from torch_appearance.pipelines.print.baselines import quantize
from torch_appearance.pipelines.print.config import iteration_seed, load_inks
from torch_appearance.pipelines.print.loop import build_target
from torch_appearance.print_error import noise_free_error
from torch_appearance.progress import progress_bar

SPOT = ("tests/data/meshes/spot/spot_triangulated.obj", "tests/data/meshes/spot/spot_texture.png")


def build(args):
    """(target, inks, cfg, indices, what): the print to evaluate."""
    if args.run is not None:
        with open(os.path.join(args.run, "config.json")) as f:
            cfg = PrintConfig.from_record(json.load(f))
        cfg = cfg.resolved()
    elif args.mesh_height_mm is not None:
        cfg = PrintConfig(mesh=SPOT[0], texture=SPOT[1], height_mm=args.mesh_height_mm).resolved()
    else:
        cfg = PrintConfig(target=args.target).resolved()
    inks = load_inks(cfg.inks)
    target = build_target(cfg, log=lambda *a, **k: None)
    target.use(inks, cfg)
    if args.run is not None:
        indices = torch.as_tensor(load_index_volume(os.path.join(args.run, "quantized.npz"))[0])
        what = f"the quantised print of {args.run}"
    else:
        weights = torch.as_tensor(target.naive_weights(inks, cfg)[0])
        indices = quantize(target, weights, inks, cfg, iteration_seed(cfg.seed, -2))
        what = "the naive extrusion, quantised, of " + (f"Spot at {args.mesh_height_mm:g} mm" if cfg.mesh else
                                                         f"the {cfg.target} slab")
    return target, inks, cfg, indices, what


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--target", default="colorchecker", help="a slab target (built-in name or image)")
    p.add_argument("--mesh-height-mm", type=float, default=None, help="Spot (tests/data) at this height instead")
    p.add_argument("--run", default=None, help="a finished ta-optimize-print run: its quantized.npz instead")
    p.add_argument("--spp", type=int, default=16, help="samples per texel of each render")
    p.add_argument("--renders", type=int, default=64, help="independent renders (a multiple of 16)")
    p.add_argument("--texels", type=int, default=0,
                   help="score each group on its own random subset of this many texels (0: all)")
    p.add_argument("--out", required=True, help="folder for print_error.json")
    args = p.parse_args(argv)
    if args.renders % 16 or args.renders < 16:
        p.error(f"--renders: expected a multiple of 16, got {args.renders}")
    os.makedirs(args.out, exist_ok=True)
    torch.manual_seed(0)
    target, inks, cfg, indices, what = build(args)
    renders = []
    t0 = time.perf_counter()
    indices = target.prepare_quantized(indices, cfg.printer_dpi)  # prepared once for all its renders
    for k in progress_bar(range(args.renders), desc="renders", unit="render"):
        image = target.render_quantized(indices, inks, cfg.printer_dpi, args.spp, 1000 + k)
        renders.append(np.asarray(target.scored(image)[0], np.float32).reshape(-1, 3))
    seconds = time.perf_counter() - t0
    renders = np.stack(renders).astype(np.float64)
    goal = np.asarray(target.scored(image)[1], np.float64).reshape(-1, 3)
    n, population = len(renders), goal.shape[0]
    if not 0 <= args.texels <= population:
        p.error(f"--texels: expected 0 (all) or at most the print's {population} texels, got {args.texels}")
    reference = noise_free_error(renders.reshape(4, n // 4, *renders.shape[1:]).mean(1), goal)
    pick = np.random.default_rng(7)

    def group(block):
        """The estimate of one group of renders (4 × per, texels, 3): all texels or a random subset of them."""
        if not args.texels:
            return noise_free_error(block.mean(1), goal)
        keep = np.sort(pick.choice(population, args.texels, replace=False))
        return noise_free_error(block[:, :, keep].mean(1), goal[keep], population=population)

    rows = []
    per = 1
    while 4 * per <= n // 4:
        groups = n // (4 * per)
        ests = [group(renders[g * 4 * per:(g + 1) * 4 * per].reshape(4, per, -1, 3)) for g in range(groups)]

        def stat(key):
            v = np.array([e[key] for e in ests])
            return float(v.mean()), float(v.std(ddof=1))

        row = {"budget_spp": 4 * per * args.spp, "groups": groups,
               "seconds_per_evaluation": seconds / n * 4 * per}
        for key in ("dE00_mean", "dE00_p95"):
            (m, sd), (raw, _) = stat(key), stat(key + "_raw")
            row[key] = {"raw": raw, "estimate": m, "bias": m - reference[key], "raw_bias": raw - reference[key],
                        "sd": sd, "se": stat(key + "_se")[0]}
        row["dE00_noise"] = stat("dE00_noise")[0]
        rows.append(row)
        per *= 2
    result = {"print": what, "texels": int(population), "scored_texels": args.texels or int(population),
              "spp_per_render": args.spp, "renders": n,
              "render_seconds": seconds, "reference_spp": n * args.spp, "reference": reference, "budgets": rows}
    with open(os.path.join(args.out, "print_error.json"), "w") as f:
        json.dump(result, f, indent=1)
    subset = f", groups scored on {args.texels} texels each" if args.texels else ""
    print(f"\n{what}: {goal.shape[0]} texels{subset}; reference at {n * args.spp} spp: mean {reference['dE00_mean']:.2f} "
          f"± {reference['dE00_mean_se']:.2f} (raw {reference['dE00_mean_raw']:.2f}), p95 {reference['dE00_p95']:.2f} "
          f"(raw {reference['dE00_p95_raw']:.2f})\n")
    print("| budget (spp) | s per evaluation | mean raw | mean estimate (bias) | sd / se | p95 raw "
          "| p95 estimate (bias) | sd / se | noise |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        m, q = r["dE00_mean"], r["dE00_p95"]
        print(f"| {r['budget_spp']} | {r['seconds_per_evaluation']:.1f} | {m['raw']:.2f} ({m['raw_bias']:+.2f}) | "
              f"{m['estimate']:.2f} ({m['bias']:+.2f}) | {m['sd']:.2f} / {m['se']:.2f} | {q['raw']:.2f} "
              f"({q['raw_bias']:+.2f}) | {q['estimate']:.2f} ({q['bias']:+.2f}) | {q['sd']:.2f} / {q['se']:.2f} | "
              f"{r['dE00_noise']:.2f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
