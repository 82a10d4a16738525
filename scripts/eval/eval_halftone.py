"""Halftoning compared on finished print runs (issue 27): independent random draws against a 3D blue-noise threshold
volume, by the rendered colour error of the quantised print and by its visible grain.

For each run folder (a slab or an object of ta-optimize-print) the run's target is rebuilt from its config.json, its
optimised mixture (mixture.npz) rendered at --spp (the continuous optimum), then quantised with each halftoning at
the run's printer resolution and rendered with the same spp and seed. Reported per halftoning:

* ``dE00_vs_continuous``: mean CIEDE2000 of the quantised print's texels against the continuous optimum's (what the
  quantisation costs), and ``dE00_vs_target`` (the print's score);
* ``grain``: the high-frequency energy of the texels' lightness, mean (L* − local mean L*)² — for a slab the local
  mean is a Gaussian of σ = --sigma texels, for an object the mean of the 8 nearest texels on the surface — and
  ``grain_excess``, that energy minus the continuous render's (whose high frequencies are Monte Carlo noise alone;
  the renders share spp and seed).

Writes ``halftone.json`` and prints a Markdown table.

Examples:
    python scripts/eval/eval_halftone.py results/demo /tmp/spot25 --spp 64
"""
import argparse
import json
import os
import sys
import time

import numpy as np
import torch

from torch_appearance import io as ta_io
from torch_appearance.color import rgb_to_lab
from torch_appearance.metrics import delta_e_2000
from torch_appearance.nn.mixture import mix_inks
from torch_appearance.pipelines.print import PrintConfig
from torch_appearance.pipelines.print.baselines import quantize
from torch_appearance.pipelines.print.config import iteration_seed, load_inks
from torch_appearance.pipelines.print.loop import build_target


def lightness(texels):
    return rgb_to_lab(torch.as_tensor(np.asarray(texels), dtype=torch.float64))[..., 0].numpy()


def grain_slab(texels, sigma):
    """Mean (L* − Gaussian-blurred L*)² over the faces' texels (a border of 3σ left out)."""
    import cv2

    out = []
    for face in np.asarray(texels):
        L = lightness(face)
        high = L - cv2.GaussianBlur(L, (0, 0), sigma, borderType=cv2.BORDER_REFLECT)
        b = int(np.ceil(3 * sigma))
        out.append(high[b:-b, b:-b] ** 2)
    return float(np.mean(out))


def grain_object(texels, neighbours):
    L = lightness(texels)
    return float(np.mean((L - L[neighbours].mean(1)) ** 2))


def evaluate(folder, spp, sigma, seed, log=print):
    cfg = PrintConfig.from_record(ta_io.read_json(os.path.join(folder, "config.json"))).resolved()
    inks = load_inks(cfg.inks)
    t0 = time.perf_counter()
    target = build_target(cfg, log=lambda *a: None)
    target.use(inks, cfg)
    with np.load(os.path.join(folder, "mixture.npz")) as data:
        weights = torch.from_numpy(data["weights"])
    if target.kind == "object":
        from scipy.spatial import cKDTree

        points = target.obj.texel_points.numpy()
        neighbours = cKDTree(points).query(points, k=9)[1][:, 1:]
        grain = lambda t: grain_object(t, neighbours)          # noqa: E731
    else:
        grain = lambda t: grain_slab(t, sigma)                  # noqa: E731
    render_seed = iteration_seed(seed, -1)
    with torch.no_grad():
        sigma_t, albedo = mix_inks(weights, inks)
        continuous = target.render(sigma_t, albedo, spp, render_seed).detach()
        del sigma_t, albedo
    log(f"{folder}: continuous render at {spp} spp after {time.perf_counter() - t0:.0f} s")
    reference = torch.as_tensor(continuous).reshape(-1, 3).double()
    goal = torch.as_tensor(target.target).reshape(-1, 3).double()
    rows = [{"run": os.path.basename(folder.rstrip("/")), "kind": target.kind, "halftone": "continuous",
             "dE00_vs_continuous": 0.0, "dE00_vs_target": float(delta_e_2000(reference, goal).mean()),
             "grain": grain(continuous.numpy()), "grain_excess": 0.0, "seconds": 0.0}]
    for halftone in ("random", "blue-noise"):
        t = time.perf_counter()
        run_cfg = PrintConfig(**{**cfg.__dict__, "halftone": halftone})
        indices = quantize(target, weights, inks, run_cfg, iteration_seed(cfg.seed, -2))
        image = target.render_quantized(indices, inks, cfg.printer_dpi, spp, render_seed)
        del indices
        flat = torch.as_tensor(image).reshape(-1, 3).double()
        g = grain(image.numpy())
        rows.append({"run": rows[0]["run"], "kind": target.kind, "halftone": halftone,
                     "dE00_vs_continuous": float(delta_e_2000(flat, reference).mean()),
                     "dE00_vs_target": float(delta_e_2000(flat, goal).mean()),
                     "grain": g, "grain_excess": g - rows[0]["grain"], "seconds": time.perf_counter() - t})
        log(f"  {halftone}: {rows[-1]}")
    return rows


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], epilog=__doc__.split("\n\n", 1)[1],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("runs", nargs="+", help="finished run folders of ta-optimize-print")
    p.add_argument("--spp", type=int, default=64, help="samples per texel of every render (default: %(default)s)")
    p.add_argument("--sigma", type=float, default=1.5, help="slabs: the local mean's Gaussian σ in texels")
    p.add_argument("--seed", type=int, default=1, help="render seed (default: %(default)s)")
    p.add_argument("--out", default="results/halftone.json")
    args = p.parse_args(argv)
    rows = []
    for run in args.runs:
        rows += evaluate(run, args.spp, args.sigma, args.seed)
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w") as handle:
        json.dump({"spp": args.spp, "sigma": args.sigma, "rows": rows}, handle, indent=2)
    fields = ["run", "kind", "halftone", "dE00_vs_continuous", "dE00_vs_target", "grain", "grain_excess", "seconds"]
    print("| " + " | ".join(fields) + " |\n|" + "---|" * len(fields))
    for r in rows:
        print("| " + " | ".join(f"{r[k]:.3f}" if isinstance(r[k], float) else str(r[k]) for k in fields) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
