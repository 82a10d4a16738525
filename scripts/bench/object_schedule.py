#!/usr/bin/env python
"""Error against time for print runs with different schedules: the figure and table that choose the defaults.

Reads finished ``ta-optimize-print`` run folders (``config.json``, ``log.csv``, ``summary.json``) and plots each run's
evaluation CIEDE2000 (mean, continuous mixture) against its *optimisation* time, the evaluation renders taken out
(each evaluation's cost is its row's time step less the run's median iteration time), so that runs evaluated at
different intervals compare fairly; the final quantised result is a marker at the run's end, the naive extrusion a
horizontal line. Prints a Markdown table (spp, lr, estimator, s/iteration, ΔE00 at each evaluation, final quantised,
the whole job's wall time when the summary has it).

Runs to compare are plain commands, e.g. Spot at 25 mm (``docs/bench_log.md``, "Object schedule"):

    ta-optimize-print --mesh tests/data/meshes/spot/spot_triangulated.obj \\
        --texture tests/data/meshes/spot/spot_texture.png --height-mm 25 --spp 4 --iterations 100 \\
        --eval-every 25 --eval-spp 32 --views 0 --threads 2 --out /tmp/sched/spp4

Example:
    python scripts/bench/object_schedule.py /tmp/sched/* --out /tmp/sched/schedule.png
"""
import argparse
import csv
import json
import os
import sys

import numpy as np


def read_run(folder):
    """``{"name", "config", "rows", "summary"}`` of a run folder; ValueError naming the folder if it is not one."""
    paths = {name: os.path.join(folder, name) for name in ("config.json", "log.csv", "summary.json")}
    missing = [name for name, path in paths.items() if not os.path.isfile(path)]
    if missing:
        raise ValueError(f"{folder}: not a finished ta-optimize-print run (no {', '.join(missing)})")
    with open(paths["config.json"]) as f:
        config = json.load(f)
    with open(paths["summary.json"]) as f:
        summary = json.load(f)
    with open(paths["log.csv"], newline="") as f:
        rows = [{k: (float(v) if v not in ("", None) else None) for k, v in row.items()} for row in csv.DictReader(f)]
    return {"name": os.path.basename(os.path.normpath(folder)), "config": config, "rows": rows, "summary": summary}


def optimisation_curve(rows):
    """(seconds per iteration, [(optimisation seconds, iteration, dE00 mean)]) of a run's log rows: wall time less
    the evaluation renders before each point."""
    steps = [b["wall_s"] - a["wall_s"] for a, b in zip(rows, rows[1:])
             if b["iteration"] > 1 and b.get("dE00_mean") is None]
    per_it = float(np.median(steps)) if steps else float("nan")
    eval_s, points = 0.0, []
    for a, b in zip([None] + rows, rows):
        if b.get("dE00_mean") is None:
            continue
        if a is not None and b["iteration"] > 1:
            eval_s += max(0.0, b["wall_s"] - a["wall_s"] - per_it)
        points.append((b["wall_s"] - eval_s, int(b["iteration"]), b["dE00_mean"]))
    return per_it, points


def label(run):
    c = run["config"]
    return f"{run['name']}: {c['spp']} spp, lr {c['lr']:g}, {c['estimator']}, {c['iterations']} it"


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                epilog=__doc__.split("\n\n", 1)[1], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("runs", nargs="+", help="finished ta-optimize-print run folders")
    p.add_argument("--out", default="schedule.png", help="figure (default: %(default)s)")
    p.add_argument("--budget-min", type=float, default=30.0, help="a vertical line at this many minutes of the whole "
                   "job (default: %(default)s)")
    args = p.parse_args(argv)
    try:
        runs = [read_run(folder) for folder in args.runs]
    except ValueError as error:
        p.error(str(error))

    from matplotlib.figure import Figure
    fig = Figure(figsize=(7.5, 4.5))
    ax = fig.subplots()
    print("| run | spp | lr | estimator | s/it | ΔE00 at evaluations (iteration: mean) | final quantised mean/p95 "
          "| loop s | job min |")
    print("|---|---|---|---|---|---|---|---|---|")
    naive = None
    for k, run in enumerate(runs):
        c, s = run["config"], run["summary"]
        per_it, points = optimisation_curve(run["rows"])
        t = np.array([pt[0] for pt in points]) / 60.0
        ax.plot(t, [pt[2] for pt in points], "o-", ms=3, color=f"C{k}", label=label(run))
        final = s.get("final_quantized") or {}
        if final:
            ax.plot([t[-1]], [final["dE00_mean"]], "*", ms=10, color=f"C{k}")
        naive = naive or s.get("baseline_naive_extrusion")
        evals = ", ".join(f"{it}: {de:.2f}" for _, it, de in points)
        job = s.get("job_s")
        print(f"| {run['name']} | {c['spp']} | {c['lr']:g} | {c['estimator']} | {per_it:.1f} | {evals} | "
              f"{final.get('dE00_mean', float('nan')):.2f}/{final.get('dE00_p95', float('nan')):.2f} | "
              f"{s['wall_s']:.0f} | {'' if job is None else f'{job / 60:.1f}'} |")
    if naive is not None:
        ax.axhline(naive["dE00_mean"], color="k", ls=":", label=f"naive extrusion {naive['dE00_mean']:.2f}")
    ax.axvline(args.budget_min, color="0.6", ls="--", lw=0.8)
    ax.set(xlabel="optimisation time [min] (evaluations taken out)", ylabel="mean CIEDE2000 (eval spp)",
           title="error against time; ★ final quantised")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(args.out, dpi=120)
    print(f"wrote {args.out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
