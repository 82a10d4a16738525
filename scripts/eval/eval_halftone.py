"""Halftoning compared on finished print runs (issue 27): independent random draws against a 3D blue-noise threshold
volume, by the rendered colour error of the quantised print and by its visible grain.

For each run folder (a slab or an object of ta-optimize-print) the run's target is rebuilt from its config.json, its
optimised mixture (mixture.npz) rendered at --spp (the continuous optimum), then quantised with each halftoning at
the run's printer resolution and rendered with the same spp and seed. Reported per halftoning:

* ``dE00_vs_continuous``: mean CIEDE2000 of the quantised print's texels against the continuous optimum's, both
  free of render noise (:func:`torch_appearance.print_error.noise_free_error` on the two seeds of each: what the
  quantisation costs, grain included), ``dE00_vs_continuous_smoothed`` the raw figure after smoothing both (slabs: a
  Gaussian of σ = 3 texels; objects: the mean of each texel and its 8 nearest), which leaves the colour shift and
  takes out most noise and grain, and ``dE00_vs_target`` (the print's score, free of render noise); ``*_raw``: the
  figures of the two renders' means as they are;
* ``grain``: the high-frequency energy of the texels' lightness, mean (L* − local mean L*)² — for a slab the local
  mean is a Gaussian of σ = --sigma texels, for an object the mean of the 8 nearest texels on the surface — free of
  Monte Carlo noise: every volume is rendered with two seeds and the two high-pass images are multiplied (their
  noise is independent, so the product's mean estimates the energy of the noise-free image); ``grain_excess``, that
  energy minus the continuous optimum's (the image's own detail), is what the halftoning adds. The colour errors
  use the mean of the two renders.

Writes ``halftone.json``, the renders (``halftone_RUN_renders.npz``) and prints a Markdown table.

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
from torch_appearance.print_error import noise_free_error
from torch_appearance.nn.mixture import mix_inks
from torch_appearance.pipelines.print import PrintConfig
from torch_appearance.pipelines.print.baselines import quantize
from torch_appearance.pipelines.print.config import iteration_seed, load_inks
from torch_appearance.pipelines.print.loop import build_target


def lightness(texels):
    return rgb_to_lab(torch.as_tensor(np.asarray(texels), dtype=torch.float64))[..., 0].numpy()


def high_slab(texels, sigma):
    """L* minus its Gaussian blur (σ texels), per face, a border of 3σ left out: (F, H', W')."""
    import cv2

    b = int(np.ceil(3 * sigma))
    out = []
    for face in np.asarray(texels):
        L = lightness(face)
        out.append((L - cv2.GaussianBlur(L, (0, 0), sigma, borderType=cv2.BORDER_REFLECT))[b:-b, b:-b])
    return np.stack(out)


def high_object(texels, neighbours):
    """L* minus the mean L* of each texel's 8 nearest texels on the surface: (N,)."""
    L = lightness(texels)
    return L - L[neighbours].mean(1)


def evaluate(folder, spp, sigma, seed, log=print, mesh=None, texture=None):
    """Rows of the continuous optimum and each halftoning (see the module docstring). Each volume is rendered with
    two seeds; ``grain`` is the mean product of the two renders' high-pass L*, whose expectation is the high-pass
    energy of the noise-free image (the renders' Monte Carlo noise is independent and cancels)."""
    cfg = PrintConfig.from_record(ta_io.read_json(os.path.join(folder, "config.json"))).resolved()
    if mesh is not None:                      # the run's mesh moved: the same mesh from another place
        cfg = PrintConfig(**{**cfg.__dict__, "mesh": mesh, "texture": texture or cfg.texture})
    inks = load_inks(cfg.inks)
    t0 = time.perf_counter()
    target = build_target(cfg, log=lambda *a: None)
    target.use(inks, cfg)
    with np.load(os.path.join(folder, "mixture.npz")) as data:
        weights = torch.from_numpy(data["weights"])
    if target.kind == "object":
        from scipy.spatial import cKDTree

        points = target.obj.texel_points.numpy()
        near = cKDTree(points).query(points, k=9)[1]
        neighbours = near[:, 1:]
        high = lambda t: high_object(t, neighbours)            # noqa: E731
        smooth = lambda t: np.asarray(t)[near].mean(1)          # noqa: E731
    else:
        import cv2

        high = lambda t: high_slab(t, sigma)                    # noqa: E731
        smooth = lambda t: np.stack([cv2.GaussianBlur(np.asarray(f, np.float32), (0, 0), 3.0,   # noqa: E731
                                                      borderType=cv2.BORDER_REFLECT) for f in t])
    seeds = (iteration_seed(seed, -1), iteration_seed(seed, -3))
    with torch.no_grad():
        sigma_t, albedo = mix_inks(weights, inks)
        continuous = [target.render(sigma_t, albedo, spp, s).detach().numpy() for s in seeds]
        del sigma_t, albedo
    log(f"{folder}: continuous renders at {spp} spp after {time.perf_counter() - t0:.0f} s")
    reference = torch.as_tensor((continuous[0] + continuous[1]) / 2).reshape(-1, 3).double()
    goal = torch.as_tensor(target.target).reshape(-1, 3).double()
    name = os.path.basename(folder.rstrip("/"))

    smooth_reference = torch.as_tensor(smooth((continuous[0] + continuous[1]) / 2)).reshape(-1, 3).double()
    saved = {"continuous": np.stack(continuous)}

    def row(halftone, renders, seconds):
        saved[halftone] = np.stack(renders)
        mean = torch.as_tensor((renders[0] + renders[1]) / 2).reshape(-1, 3).double()
        smoothed = torch.as_tensor(smooth((renders[0] + renders[1]) / 2)).reshape(-1, 3).double()
        pair = torch.as_tensor(np.stack(renders)).reshape(2, -1, 3).double()
        pair_continuous = torch.as_tensor(np.stack(continuous)).reshape(2, -1, 3).double()
        return {"run": name, "kind": target.kind, "texels": int(len(goal)), "halftone": halftone,
                "dE00_vs_continuous": noise_free_error(pair, pair_continuous)["dE00_mean"],
                "dE00_vs_continuous_raw": float(delta_e_2000(mean, reference).mean()),
                "dE00_vs_continuous_smoothed": float(delta_e_2000(smoothed, smooth_reference).mean()),
                "dE00_vs_target": noise_free_error(pair, goal)["dE00_mean"],
                "dE00_vs_target_raw": float(delta_e_2000(mean, goal).mean()),
                "grain": float(np.mean(high(renders[0]) * high(renders[1]))), "seconds": seconds}

    rows = [row("continuous", continuous, 0.0)]
    for halftone in ("random", "blue-noise"):
        t = time.perf_counter()
        run_cfg = PrintConfig(**{**cfg.__dict__, "halftone": halftone})
        indices = target.prepare_quantized(quantize(target, weights, inks, run_cfg, iteration_seed(cfg.seed, -2)),
                                           cfg.printer_dpi)  # prepared once for all its renders
        renders = [target.render_quantized(indices, inks, cfg.printer_dpi, spp, s).numpy() for s in seeds]
        del indices
        rows.append(row(halftone, renders, time.perf_counter() - t))
        rows[-1]["grain_excess"] = rows[-1]["grain"] - rows[0]["grain"]
        log(f"  {halftone}: {rows[-1]}")
    rows[0]["grain_excess"] = 0.0
    return rows, saved


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], epilog=__doc__.split("\n\n", 1)[1],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("runs", nargs="+", help="finished run folders of ta-optimize-print")
    p.add_argument("--spp", type=int, default=64, help="samples per texel of every render (default: %(default)s)")
    p.add_argument("--sigma", type=float, default=1.5, help="slabs: the local mean's Gaussian σ in texels")
    p.add_argument("--seed", type=int, default=1, help="render seed (default: %(default)s)")
    p.add_argument("--mesh", default=None, help="objects: the run's mesh, where it is now (default: config.json's)")
    p.add_argument("--texture", default=None, help="objects: the run's texture, where it is now")
    p.add_argument("--out", default="results/halftone.json")
    args = p.parse_args(argv)
    rows = []
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    for run in args.runs:
        more, renders = evaluate(run, args.spp, args.sigma, args.seed, mesh=args.mesh, texture=args.texture)
        rows += more
        np.savez_compressed(os.path.splitext(args.out)[0] + f"_{more[0]['run']}_renders.npz", **renders)
    with open(args.out, "w") as handle:
        json.dump({"spp": args.spp, "sigma": args.sigma, "rows": rows}, handle, indent=2)
    fields = ["run", "kind", "texels", "halftone", "dE00_vs_continuous", "dE00_vs_continuous_raw",
              "dE00_vs_continuous_smoothed", "dE00_vs_target", "dE00_vs_target_raw", "grain", "grain_excess", "seconds"]
    print("| " + " | ".join(fields) + " |\n|" + "---|" * len(fields))
    for r in rows:
        print("| " + " | ".join(f"{r[k]:.3f}" if isinstance(r[k], float) else str(r[k]) for k in fields) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
