#!/usr/bin/env python
"""The wood fit scored against the TRUE phase on boards of two generators (issue 48 item 1; not a test).

Boards: the project's own (``torch_appearance.rings.synthetic_board``: ``own:<seed>`` and ``own-pith:<seed>`` with
the pith inside) and the independent generator (``torch_appearance.testing.synthetic_boards.independent_board``:
``<recipe>:<seed>``, recipes wavy_pith_middle, lobed_pith, porous_flat, knotty). Each board's image is written as
``OUT/<case>/board.png`` and ``fit_wood`` runs into the same folder; the fitted model's phase is scored by
``phase_scores`` against 2π·frac(G_true): phase RMS (constant offset removed), the share of pixels off by more than
1 rad, the ring-boundary circular std (the fit's phase error over the pixels within 0.05 ring of a true boundary:
how much the boundaries' misplacement varies across the board) and the RMS over the two innermost rings. Knot
pixels (no stem phase) are left out.

Each run folder also gets ``overlay.png``: the photo with the true ring boundaries (white) and the fitted ones
(red dashed: integer levels of the fitted G less the constant phase offset), beside the fit's phase error against
the truth. ``--redraw`` rescores and redraws run folders that already hold a fitted model, without fitting.

Outputs: ``OUT/generators.json`` (settings, rows, per-generator medians) and the table on stdout; ``--measured
PATH`` also writes the JSON there (e.g. scripts/eval/measured/wood_generators.json).

Examples:
    python scripts/eval/eval_wood_generators.py --out /tmp/wood_gen
    python scripts/eval/eval_wood_generators.py --cases lobed_pith:0,own-pith:10 --epochs 200 --out /tmp/g
"""
import argparse
import os
import subprocess
import sys
import time

import numpy as np

from torch_appearance import io as ta_io
from torch_appearance.cli.fit_wood import add_fit_arguments, config_from_args

PROG = "eval_wood_generators.py"
DEFAULT_CASES = ("own:0,own:1,own-pith:10,own-pith:11,wavy_pith_middle:0,wavy_pith_middle:1,lobed_pith:0,"
                 "lobed_pith:1,porous_flat:0,knotty:0")
FIELDS = [("case", "board", "{}"), ("generator", "generator", "{}"), ("status", "status", "{}"),
          ("phase_rms", "phase RMS rad", "{:.3f}"), ("boundary_circular_std", "boundary circ. std rad", "{:.3f}"),
          ("fraction_above_1rad", "> 1 rad", "{:.1%}"), ("phase_rms_inner", "RMS 2 inner rings", "{:.3f}"),
          ("wall_s", "wall s", "{:.0f}")]


def parse_cases(text):
    from torch_appearance.testing.synthetic_boards import RECIPES

    cases = []
    for part in str(text).split(","):
        part = part.strip()
        if not part:
            continue
        kind, _, seed = part.partition(":")
        if kind not in ("own", "own-pith") + tuple(RECIPES) or not seed.isdigit():
            raise ValueError(f"--cases: cannot read {part!r}; expected KIND:SEED with KIND one of own, own-pith, "
                             f"{', '.join(RECIPES)}")
        cases.append((kind, int(seed)))
    if not cases:
        raise ValueError(f"--cases: expected one or more KIND:SEED, got {text!r}")
    return cases


def make_board(kind, seed, size, ps):
    """(image, true G, valid mask, generator name) of one case."""
    if kind.startswith("own"):
        from torch_appearance.rings.synthetic import synthetic_board

        b = synthetic_board(size, size, ps, seed=seed, pith_inside=kind == "own-pith")
        return b["image"], b["G"].astype(np.float64), None, "project (rings.synthetic)"
    from torch_appearance.testing.synthetic_boards import independent_board

    b = independent_board(kind, size, size, ps, seed=seed)
    return b["image"], b["G"], b["valid"], "independent (testing.synthetic_boards)"


def overlay(folder, image, G_true, G_fit, offset, valid, title):
    """``overlay.png``: true (white) and fitted (red dashed) ring boundaries on the photo, and |phase error|."""
    import math

    from matplotlib.figure import Figure

    h, w = G_true.shape
    fit_levels = G_fit - offset / (2 * math.pi)
    err = np.angle(np.exp(1j * (2 * math.pi * (fit_levels - G_true))))
    if valid is not None:
        err = np.where(valid, err, np.nan)
    fig = Figure(figsize=(11, 0.9 + 5.0 * h / w), layout="constrained")
    ax = fig.subplots(1, 2)
    ax[0].imshow(np.clip(image, 0, 1) ** (1 / 2.2))
    ax[0].contour(G_true, levels=np.arange(np.ceil(G_true.min()), G_true.max() + 1), colors="white", linewidths=1.0)
    ax[0].contour(fit_levels, levels=np.arange(np.ceil(fit_levels.min()), fit_levels.max() + 1), colors="red",
                  linewidths=1.0, linestyles="--")
    ax[0].set_title(f"{title}: true (white) and fitted (red) boundaries")
    im = ax[1].imshow(np.abs(err), cmap="magma", vmin=0, vmax=math.pi)
    ax[1].set_title("|fitted − true phase| (constant offset removed) [rad]")
    fig.colorbar(im, ax=ax[1], fraction=0.046)
    for a in ax:
        a.axis("off")
    ta_io.save_figure(fig, os.path.join(folder, "overlay.png"), dpi=110)


def score_folder(folder, case, image, G, valid, n, ps):
    """Scores and overlay of the fitted model in ``folder``."""
    import torch
    from torch_appearance.nn.wood import WoodModel
    from torch_appearance.testing.synthetic_boards import phase_scores

    model = WoodModel.load(os.path.join(folder, "model"))
    with torch.no_grad():
        out = model.render_board(n, n, ps)
    scores = phase_scores(out["phase"].double().numpy(), G, valid)
    overlay(folder, image, G, out["G"].double().numpy(), scores["offset"], valid, case)
    return scores


def evaluate(kind, seed, args, log):
    from torch_appearance.pipelines.wood import fit_wood

    n, ps = args.size, args.pixel_size_mm
    image, G, valid, generator = make_board(kind, seed, n, ps)
    case = f"{kind}:{seed}"
    folder = os.path.join(args.out, case.replace(":", "_"))
    os.makedirs(folder, exist_ok=True)
    photo = os.path.join(folder, "board.png")
    ta_io.write_png(photo, image)
    np.save(os.path.join(folder, "G_true.npy"), G)
    row = {"case": case, "generator": generator, "run_folder": os.path.abspath(folder)}
    if args.redraw:
        if not os.path.exists(os.path.join(folder, "model.json")):
            row.update(status="no fitted model")
            return row
        import json

        summary = json.load(open(os.path.join(folder, "summary.json"), encoding="utf-8"))
        timings = summary.get("timings_s", {})
        return dict(row, status="ok (redrawn)" if summary["fit_ok"] else "poor fit (redrawn)",
                    wall_s=sum(v for v in timings.values() if isinstance(v, (int, float))),
                    fit_phase_rms_vs_gabor=summary["final_phase_rms"], ssim_fit_vs_photo=summary["ssim_fit_vs_photo"],
                    **score_folder(folder, case, image, G, valid, n, ps))
    cfg = config_from_args(args, photo=photo, out=folder, pixel_size_mm=ps, preview=False, seed=0)
    t0 = time.perf_counter()
    try:
        summary = fit_wood(cfg, progress=False, log=log)
    except ValueError as exc:
        row.update(status=f"refused: {exc}", wall_s=time.perf_counter() - t0)
        return row
    row.update(score_folder(folder, case, image, G, valid, n, ps), status="ok" if summary["fit_ok"] else "poor fit",
               wall_s=time.perf_counter() - t0, fit_phase_rms_vs_gabor=summary["final_phase_rms"],
               ssim_fit_vs_photo=summary["ssim_fit_vs_photo"])
    return row


def medians(rows):
    out = {}
    for gen in sorted({r["generator"] for r in rows}):
        rs = [r for r in rows if r["generator"] == gen and r.get("phase_rms") is not None]
        out[gen] = {"boards": len([r for r in rows if r["generator"] == gen]), "fitted": len(rs)}
        for key in ("phase_rms", "boundary_circular_std", "fraction_above_1rad"):
            vals = [r[key] for r in rs if r.get(key) is not None]
            out[gen][f"median_{key}"] = float(np.median(vals)) if vals else None
            out[gen][f"max_{key}"] = float(np.max(vals)) if vals else None
    return out


def main(argv=None):
    p = argparse.ArgumentParser(prog=PROG, description=__doc__.split("\n\n")[0],
                                epilog=__doc__.split("\n\n", 1)[1], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--cases", default=DEFAULT_CASES, help="boards as KIND:SEED, comma separated (default: "
                                                          "%(default)s)")
    p.add_argument("--size", type=int, default=256, help="board size in px, square (default: %(default)s)")
    p.add_argument("--pixel-size-mm", type=float, default=0.1, help="pixel pitch in mm (default: %(default)s)")
    add_fit_arguments(p, ["epochs", "color_epochs", "lobe_shape", "lobe_radius_rings", "pith_split"])
    p.add_argument("--label", default="", help="a name for this run in the JSON (e.g. before, after)")
    p.add_argument("--redraw", action="store_true", help="rescore and redraw run folders that hold a fitted model")
    p.add_argument("--measured", default=None, help="also write the JSON here")
    p.add_argument("--out", default="results/wood_generators", help="output folder (default: %(default)s)")
    args = p.parse_args(argv)
    try:
        cases = parse_cases(args.cases)
    except ValueError as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return 2
    if args.size < 32 or not (args.pixel_size_mm > 0):
        print(f"{PROG}: error: --size must be >= 32 and --pixel-size-mm > 0; got {args.size}, "
              f"{args.pixel_size_mm}", file=sys.stderr)
        return 2
    os.makedirs(args.out, exist_ok=True)
    try:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                                cwd=os.path.dirname(os.path.abspath(__file__))).stdout.strip()
    except OSError:
        commit = ""
    rows = []
    for kind, seed in cases:
        rows.append(ta_io.nan_to_none(evaluate(kind, seed, args, log=print)))
        print(ta_io.markdown_table(rows[-1:], FIELDS).splitlines()[-1], flush=True)
        result = {"label": args.label, "commit": commit, "size": args.size, "pixel_size_mm": args.pixel_size_mm,
                  "epochs": args.epochs, "color_epochs": args.color_epochs, "cases": args.cases,
                  "lobe_shape": args.lobe_shape, "lobe_radius_rings": args.lobe_radius_rings,
                  "pith_split": args.pith_split,
                  "medians": medians(rows), "rows": rows}
        ta_io.write_json(os.path.join(args.out, "generators.json"), ta_io.nan_to_none(result))   # after every board
    print(ta_io.markdown_table(rows, FIELDS))
    for gen, m in result["medians"].items():
        print(f"{gen}: median phase RMS {m['median_phase_rms']}, boundary circ. std {m['median_boundary_circular_std']}")
    ta_io.write_json(os.path.join(args.out, "generators.json"), ta_io.nan_to_none(result))
    if args.measured:
        ta_io.write_json(args.measured, ta_io.nan_to_none(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
