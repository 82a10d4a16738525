#!/usr/bin/env python
"""Wood appearance matching on synthetic flat-sawn boards with known ground truth (not a test).

For every seed, torch_appearance.rings.synthetic_board(SIZE, SIZE, PIXEL_SIZE, seed) draws a board (random
ring scale, axis distance, tilt, in-plane angle, radial distortion and per-ring colours, pixel noise); its image is
written as ``OUT/seed_<NN>/board.png`` (8-bit sRGB) and the wood fit (fit_wood) runs into the same folder. Reported:

* rings traced by the detector; the true number of rings visible (distinct integer G levels on the board);
* ring scale s_r: true vs fitted and the relative error (fitted / true − 1). s_r alone is not identifiable (a radial
  distortion growing with r rescales the rings like s_r does), so the mean ring width over the board
  (effective_ring_width, on the true and on the fitted model) is reported too;
* phase RMS (rad) of the fitted phase against the true 2π·frac(G) after removing the best constant offset
  (circular mean of the wrapped difference; the Gabor phase is aligned with the rings' fundamental, not with G);
* mean ring-boundary distance (px) in both directions: fitted boundaries (G = k + boundary_lateness of the fitted
  model) → nearest true boundary point (Newton-refined iso-lines G ∈ ℤ), and true → fitted;
* growth direction: the fraction of the board where the fitted growth field increases the same way as the true
  one (∇G_fit · ∇G_true > 0, central differences): lateness must grow away from the pith on both sides of the
  projected tree centre (a fit that follows the rings but mirrors them beyond the centre scores ≈ the mirrored
  share less than 1);
* the fit's own phase RMS vs the photo's Gabor phase, wall time, and the true geometry (distance_mm, tilt_deg).

``--pith-inside`` draws the boards with ``synthetic_board(..., pith_inside=True)``: cut 1.5-4 mm from the pith at
12-20° tilt, so the pith and the closed oval rings around it lie in the photo.

Seeds where no board geometry can be fitted (fit_wood raises ValueError) get the status "refused: <message>".

Outputs (atomic writes): ``OUT/synthetic.json`` (settings, rows, summary), ``OUT/synthetic.md`` (markdown table +
summary line), ``OUT/ring_scale.png`` (true vs fitted s_r and mean ring width with a ±5 % band).

Examples:
    python scripts/eval/eval_wood_synthetic.py                                    # seeds 0-9, default fit settings
    python scripts/eval/eval_wood_synthetic.py --seeds 0,1 --epochs 20 --color-epochs 5 --out /tmp/wood_syn
    python scripts/eval/eval_wood_synthetic.py --seeds 0-4,7 --size 192 --pixel-size-mm 0.12
    python scripts/eval/eval_wood_synthetic.py --seeds 0-7 --pith-inside --out /tmp/wood_pith
"""
import argparse
import math
import os
import sys
import time

import numpy as np

from torch_appearance import io as ta_io
from torch_appearance.cli.fit_wood import add_fit_arguments, config_from_args

PROG = "eval_wood_synthetic.py"
BAND = 0.05  # relative ring-scale tolerance of the summary and the plot
GOOD_PHASE_RMS = 0.3  # rad

PHOTOMETRIC_FIELDS = [  # with --photometric: the same fit before and after stage 3
    ("seed", "seed", "{}"),
    ("phase_rms_vs_true_before", "phase RMS vs true before", "{:.3f}"),
    ("phase_rms_vs_true", "after", "{:.3f}"),
    ("direction_correct_before", "growth dir ok before", "{:.1%}"),
    ("direction_correct", "after", "{:.1%}"),
    ("ssim_before", "SSIM before", "{:.3f}"),
    ("ssim_fit_vs_photo", "after", "{:.3f}"),
    ("contrast_before", "contrast before", "{:.2f}"),
    ("contrast_after", "after", "{:.2f}"),
    ("stage3_s", "stage 3 s", "{:.1f}"),
]
FIELDS = [  # (key, header, format)
    ("seed", "seed", "{}"),
    ("status", "status", "{}"),
    ("rings_visible", "rings true", "{}"),
    ("rings_traced", "traced", "{}"),
    ("scale_reliable", "scale flagged reliable", "{}"),
    ("distance_mm", "dist mm", "{:.1f}"),
    ("tilt_deg", "tilt °", "{:+.1f}"),
    ("ring_scale_true_mm", "s_r true", "{:.3f}"),
    ("ring_scale_fit_mm", "s_r fit", "{:.3f}"),
    ("ring_scale_rel_error", "s_r err", "{:+.1%}"),
    ("ring_width_true_mm", "width true", "{:.3f}"),
    ("ring_width_fit_mm", "width fit", "{:.3f}"),
    ("ring_width_rel_error", "width err", "{:+.1%}"),
    ("phase_rms_vs_true", "phase RMS vs true", "{:.3f}"),
    ("phase_rms_inner", "phase RMS, 2 innermost rings", "{:.3f}"),
    ("direction_correct", "growth dir ok", "{:.1%}"),
    ("boundary_fit_to_true_px", "bnd fit→true px", "{:.2f}"),
    ("boundary_true_to_fit_px", "bnd true→fit px", "{:.2f}"),
    ("wall_s", "wall s", "{:.1f}"),
]


def parse_seeds(text):
    """``"0-9"``, ``"1,4,7"``, ``"0-3,8"`` → sorted unique list of ints >= 0."""
    seeds = []
    for part in str(text).split(","):
        part = part.strip()
        if not part:
            continue
        try:
            if "-" in part[1:]:
                lo, hi = (int(x) for x in part.split("-", 1))
                if hi < lo:
                    raise ValueError
                seeds.extend(range(lo, hi + 1))
            else:
                seeds.append(int(part))
        except ValueError:
            raise ValueError(f"--seeds: cannot read {part!r}; expected e.g. 0-9 or 1,4,7 or 0-3,8") from None
    if not seeds or min(seeds) < 0:
        raise ValueError(f"--seeds: expected one or more integers >= 0, got {text!r}")
    return sorted(set(seeds))


def phase_rms_vs_true(fit_phase, G_true):
    """RMS (rad) of wrap(fitted phase − 2π·frac(G)) after removing its circular mean (tests/test_wood_fit.py)."""
    true_phase = 2 * math.pi * (G_true - np.floor(G_true))
    d = np.angle(np.exp(1j * (np.asarray(fit_phase, np.float64) - true_phase)))
    offset = np.angle(np.exp(1j * d).mean())
    return float(np.sqrt((np.angle(np.exp(1j * (d - offset))) ** 2).mean())), float(offset)


def phase_rms_inner(fit_phase, G_true, offset, rings=2.0):
    """The same RMS (rad, the whole board's offset removed) over the pixels of the ``rings`` innermost rings (true
    G < rings): where the pith lies in the photo, the closed ovals around it; None when the board holds none."""
    inner = np.asarray(G_true) < rings
    if not inner.any():
        return None
    true_phase = 2 * math.pi * (G_true - np.floor(G_true))
    d = np.angle(np.exp(1j * (np.asarray(fit_phase, np.float64) - true_phase - offset)))
    return float(np.sqrt((d[inner] ** 2).mean()))


def direction_correct(G_fit, G_true):
    """Fraction of pixels where ∇G_fit · ∇G_true > 0 (central differences; G increases away from the pith)."""
    fy, fx = np.gradient(np.asarray(G_fit, np.float64))
    ty, tx = np.gradient(np.asarray(G_true, np.float64))
    return float(((fx * tx + fy * ty) > 0).mean())


def evaluate_seed(seed, args, log):
    import torch
    from scipy.spatial import cKDTree
    from torch_appearance.nn.wood import WoodModel
    from torch_appearance.pipelines.wood import effective_ring_width, fit_wood, model_boundaries
    from torch_appearance.rings.synthetic import synthetic_board

    n, ps = args.size, args.pixel_size_mm
    board = synthetic_board(n, n, ps, seed=seed, pith_inside=args.pith_inside)
    prm = board["params"]
    folder = os.path.join(args.out, f"seed_{seed:02d}")
    os.makedirs(folder, exist_ok=True)
    photo = os.path.join(folder, "board.png")
    ta_io.write_png(photo, board["image"])
    width_true = effective_ring_width(board["model"], n, n, ps)
    row = {"seed": seed, "run_folder": os.path.abspath(folder),
           "rings_visible": len(set(board["boundary_levels"])), "distance_mm": prm["distance_mm"],
           "tilt_deg": prm["tilt_deg"], "in_plane_deg": prm["in_plane_deg"], "distortion_mm": prm["distortion_mm"],
           "ring_scale_true_mm": prm["ring_scale"], "ring_width_true_mm": width_true}
    cfg = config_from_args(args, photo=photo, out=folder, pixel_size_mm=ps, preview=False, seed=0)
    t0 = time.perf_counter()
    try:
        summary = fit_wood(cfg, progress=False, log=log)
    except ValueError as exc:
        row.update(status=f"refused: {exc}", wall_s=time.perf_counter() - t0)
        return row
    wall = time.perf_counter() - t0
    model = WoodModel.load(os.path.join(folder, "model"))
    with torch.no_grad():
        out = model.render_board(n, n, ps)
    rms, offset = phase_rms_vs_true(out["phase"].numpy(), board["G"].astype(np.float64))
    lines = model_boundaries(out["G"].numpy(), summary["boundary_lateness"])
    truth = np.concatenate(board["boundaries"]) if board["boundaries"] else np.zeros((0, 2))
    if lines and len(truth):
        det = np.concatenate(lines)
        fit_to_true = float(cKDTree(truth).query(det)[0].mean())
        true_to_fit = float(cKDTree(det).query(truth)[0].mean())
    else:
        fit_to_true = true_to_fit = None
    s_fit, w_fit = summary["ring_scale_mm"], summary["mean_ring_width_mm"]
    row.update(status="ok" if summary["fit_ok"] else "poor fit", rings_traced=summary["rings_traced"],
               ring_scale_fit_mm=s_fit, ring_scale_rel_error=s_fit / prm["ring_scale"] - 1,
               ring_width_fit_mm=w_fit, ring_width_rel_error=w_fit / width_true - 1,
               phase_rms_vs_true=rms, phase_offset_rad=offset,
               phase_rms_inner=phase_rms_inner(out["phase"].numpy(), board["G"].astype(np.float64), offset),
               direction_correct=direction_correct(out["G"].numpy(), board["G"]),
               boundary_fit_to_true_px=fit_to_true, boundary_true_to_fit_px=true_to_fit,
               boundary_lateness=summary["boundary_lateness"], fit_phase_rms_initial=summary["initial_phase_rms"],
               fit_phase_rms_final=summary["final_phase_rms"], ssim_fit_vs_photo=summary["ssim_fit_vs_photo"],
               timings_s=summary["timings_s"], wall_s=wall, fit_ok=summary["fit_ok"],
               scale_reliable=summary["ring_scale_reliable"])
    if summary.get("photometric") is not None:   # the same fit before stage 3
        before = WoodModel.load(os.path.join(folder, "model_before_photometric"))
        with torch.no_grad():
            out_b = before.render_board(n, n, ps)
        row.update(phase_rms_vs_true_before=phase_rms_vs_true(out_b["phase"].numpy(), board["G"].astype(np.float64))[0],
                   direction_correct_before=direction_correct(out_b["G"].numpy(), board["G"]),
                   ssim_before=summary["photometric"]["before"]["ssim"],
                   contrast_before=summary["photometric"]["before"]["latewood_contrast"]["ratio"],
                   contrast_after=summary["photometric"]["after"]["latewood_contrast"]["ratio"],
                   stage3_s=summary["photometric"]["seconds"])
    return row


def summarise(rows):
    fitted = [r for r in rows if r.get("ring_scale_rel_error") is not None]
    s_err = np.abs([r["ring_scale_rel_error"] for r in fitted])
    w_err = np.abs([r["ring_width_rel_error"] for r in fitted])
    rms = np.array([r["phase_rms_vs_true"] for r in fitted])
    n = len(rows)
    return {
        "seeds": n, "fitted": len(fitted), "refused": n - len(fitted),
        "median_abs_ring_scale_rel_error": float(np.median(s_err)) if len(fitted) else None,
        "fraction_ring_scale_within_5pct": float((s_err <= BAND).sum() / n) if n else None,
        "median_abs_ring_width_rel_error": float(np.median(w_err)) if len(fitted) else None,
        "fraction_ring_width_within_5pct": float((w_err <= BAND).sum() / n) if n else None,
        "fraction_phase_rms_below_0.3": float((rms < GOOD_PHASE_RMS).sum() / n) if n else None,
        # the fit's own warning (summary["ring_scale_reliable"]: enough rings on the board): is it trustworthy?
        "flagged_reliable": int(sum(bool(r.get("scale_reliable")) for r in fitted)),
        "fraction_ring_scale_within_5pct_when_flagged_reliable": (
            float(np.mean([abs(r["ring_scale_rel_error"]) <= BAND for r in fitted if r.get("scale_reliable")]))
            if any(r.get("scale_reliable") for r in fitted) else None),
        "median_phase_rms_vs_true": float(np.median(rms)) if len(fitted) else None,
        "fraction_phase_rms_below_0.5": float((rms < 0.5).sum() / n) if n else None,
        "fraction_direction_correct_ge_95pct": (
            float(sum(r["direction_correct"] >= 0.95 for r in fitted) / n) if n else None),
    }


def summary_line(s):
    if not s["fitted"]:
        return f"{s['seeds']} seeds, none fitted"

    return (f"{s['seeds']} seeds, {s['fitted']} fitted: median |s_r error| {s['median_abs_ring_scale_rel_error']:.1%}, "
            f"s_r within 5 % {s['fraction_ring_scale_within_5pct']:.0%}; median |ring width error| "
            f"{s['median_abs_ring_width_rel_error']:.1%}, within 5 % {s['fraction_ring_width_within_5pct']:.0%}; "
            f"phase RMS vs true < 0.3 rad {s['fraction_phase_rms_below_0.3']:.0%} "
            f"(median {s['median_phase_rms_vs_true']:.3f} rad), < 0.5 rad {s['fraction_phase_rms_below_0.5']:.0%}; "
            f"growth direction right on >= 95 % of the board {s['fraction_direction_correct_ge_95pct']:.0%}; fractions over all seeds (refused count as misses); "
            f"{s['flagged_reliable']} flagged scale-reliable, of which within 5 %: "
            f"{s['fraction_ring_scale_within_5pct_when_flagged_reliable']}")


def scatter(rows, path):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 4.6))
    for ax, (t, f, name) in zip(axes, [("ring_scale_true_mm", "ring_scale_fit_mm", "ring scale s_r"),
                                       ("ring_width_true_mm", "ring_width_fit_mm", "mean ring width")]):
        ok = [r for r in rows if r.get(f) is not None]
        bad = [r for r in rows if r.get(f) is None]
        vals = [r[t] for r in rows] + [r[f] for r in ok]
        lo, hi = (min(vals) * 0.85, max(vals) * 1.15) if vals else (0.5, 5.0)
        x = np.linspace(lo, hi, 2)
        ax.fill_between(x, x * (1 - BAND), x * (1 + BAND), color="0.85", label="±5 %")
        ax.plot(x, x, "k-", lw=0.8)
        ax.scatter([r[t] for r in ok], [r[f] for r in ok], s=22, zorder=3, label="fitted")
        for r in ok:
            ax.annotate(str(r["seed"]), (r[t], r[f]), fontsize=7, xytext=(3, 3), textcoords="offset points")
        if bad:
            ax.scatter([r[t] for r in bad], [lo * 1.02] * len(bad), marker="x", color="C3", label="refused")
        ax.set(xlim=(lo, hi), ylim=(lo, hi), xlabel=f"true {name} [mm]", ylabel=f"fitted {name} [mm]", title=name)
        ax.set_aspect("equal")
        ax.legend(loc="upper left", fontsize=8)
    fig.tight_layout()
    ta_io.save_figure(fig, path, dpi=110)


def main(argv=None):
    p = argparse.ArgumentParser(prog=PROG, description=__doc__.split("\n\n")[0],
                                epilog=__doc__.split("\n\n", 1)[1], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seeds", default="0-9", help="seeds: ranges and comma lists, e.g. 0-9 or 0,3,5-7 "
                                                  "(default: %(default)s)")
    p.add_argument("--size", type=int, default=256, help="board size in px, square (default: %(default)s)")
    p.add_argument("--pixel-size-mm", type=float, default=0.1, help="pixel pitch in mm (default: %(default)s)")
    p.add_argument("--pith-inside", action="store_true",
                   help="boards cut 1.5-4 mm from the pith (pith and closed oval rings in the photo)")
    # the fit's own flags (with --photometric: stage 3, reported before/after)
    add_fit_arguments(p, ["epochs", "color_epochs", "photometric", "photometric_weight", "photometric_estimator",
                          "photometric_anchor"])
    p.add_argument("--out", default="results/wood_synthetic", help="output folder (default: %(default)s)")
    args = p.parse_args(argv)
    try:
        seeds = parse_seeds(args.seeds)
    except ValueError as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return 2
    if args.size < 32:
        print(f"{PROG}: error: --size must be >= 32; got {args.size}", file=sys.stderr)
        return 2
    if not (math.isfinite(args.pixel_size_mm) and args.pixel_size_mm > 0):
        print(f"{PROG}: error: --pixel-size-mm must be > 0; got {args.pixel_size_mm}", file=sys.stderr)
        return 2
    if args.epochs < 0 or args.color_epochs < 0:
        print(f"{PROG}: error: --epochs and --color-epochs must be >= 0", file=sys.stderr)
        return 2
    os.makedirs(args.out, exist_ok=True)

    from torch_appearance.progress import progress_bar
    rows = []
    bar = progress_bar(seeds, desc="seeds", unit="board")
    for seed in bar:
        rows.append(ta_io.nan_to_none(evaluate_seed(seed, args, log=bar.write)))

    summ = summarise(rows)
    table = ta_io.markdown_table(rows, FIELDS)
    if args.photometric:
        table += "\n\nStage 3 (photometric), before → after:\n\n" + ta_io.markdown_table(rows, PHOTOMETRIC_FIELDS)
    line = summary_line(summ)
    settings = (f"{'pith-inside ' if args.pith_inside else ''}boards "
                f"{args.size}×{args.size} px at {args.pixel_size_mm:g} mm, epochs {args.epochs} + colour "
                f"{args.color_epochs}, seeds {args.seeds}")
    print(table)
    print(line)
    print(settings)
    ta_io.write_json(os.path.join(args.out, "synthetic.json"),
                     ta_io.nan_to_none({"size": args.size, "pith_inside": args.pith_inside, "pixel_size_mm": args.pixel_size_mm, "epochs": args.epochs,
                              "color_epochs": args.color_epochs, "seeds": seeds, "summary": summ, "rows": rows}))
    ta_io.atomic_write_bytes(os.path.join(args.out, "synthetic.md"),
                             f"# Wood fit on synthetic boards\n\n{settings}\n\n{table}\n\n{line}\n".encode())
    scatter(rows, os.path.join(args.out, "ring_scale.png"))
    print(f"-> {os.path.join(args.out, 'synthetic.json')}, synthetic.md, ring_scale.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
