"""Ink-set selection (Nindel et al. 2021, Fig. 15): which k of the candidate inks print this target best?

Runs every combination of k inks out of --candidates, each together with the --always-inks (black and white by
default), as a short print optimisation (ta-optimize-print's loop: --iterations at --spp, the same --seed
for every set) on one shared target/voxelisation, then ranks the sets and plots their convergence.

The table is ordered by dE00_mean, the CIEDE2000 mean of each set's final *quantised* result (the printable
volume), free of the evaluation render's noise (four renders of --eval-spp/4 spp; dE00_mean_se its standard error:
sets closer than about two of them are not told apart). Next to it, loss_rank orders the sets by loss_final, the
appearance loss E of that same render. loss_last is the training loss (at --spp, averaged over the last 10% of iterations, at least one): at
low spp it is dominated by the render noise (its ΔE76² term measures noise as well as error, and the noise differs
between inks), so it shows convergence within a set but does not rank sets.

Output folder --out DIR:
    runs/<ink1+ink2+...>/   one optimize_print run folder per combination (+ inks.json, selection.json);
                            a combination whose summary.json exists is skipped, so rerunning the same command
                            resumes an interrupted selection (a half-done run continues from its checkpoint)
    ranking.csv, ranking.json   rank, inks, dE00_mean, dE00_mean_se, dE00_p95 (final quantised), dE00_continuous (the
                            continuous mixture), loss_final, loss_rank, loss_last, naive_dE00_mean (naive
                            extrusion, quantised), seconds (optimisation loop), run_seconds (the whole run with
                            baseline, quantisation and exports), folder
    convergence.png         CIEDE2000 against wall time and loss against iteration for every set (the best 3
                            highlighted), and the final quantised CIEDE2000 mean of every set, ranked
    summary.json            the settings, the best set, the timings
    inks.json               every candidate and fixed ink (optical properties)

Examples:
    # the quick ColorChecker selection: 35 sets of 3 out of the 7 coloured built-in inks, + black + white
    # (21 × 31 texels × 6 layers, 40 iterations each; a few minutes on 2 cores)
    ta-select-inks --target colorchecker --width-mm 5.25 --dpi 150 --out results/inksel
    # 2 of 4 inks for a photo, longer runs
    ta-select-inks --target photo.png --width-mm 10 -k 2 --candidates cyan,magenta,yellow,orange \\
        --iterations 100 --out results/inksel_photo
    # your own inks (a JSON list of {name, sigma_t, albedo, g?, display_rgb?}) next to built-in ones
    ta-select-inks --target colorchecker --user-inks my_inks.json \\
        --candidates cyan,magenta,yellow,my_teal --out results/inksel_mine
    # a textured object (the core ink must be one of --always-inks)
    ta-select-inks --mesh spot.obj --texture spot_texture.png --height-mm 20 --shell-mm 1 \\
        --out results/inksel_spot
    # rerun the same command to resume an interrupted selection
"""
import csv
import dataclasses
import itertools
import json
import math
import os
import re
import sys
import tempfile
import time

from torch_appearance import io as ta_io
from torch_appearance.fabrication.inks import INKS, InkSet
from torch_appearance.pipelines.print import PrintConfig, build_target, optimize_print
from torch_appearance.pipelines.runs import claim_run_folder
from torch_appearance.progress import LineProgress, progress_bar

from .command import CommandParser, check_output_folder, fail, interrupted
from .optimize_print import add_optimization_arguments, add_target_arguments, config_from_args

DEFAULT_CANDIDATES = ("cyan", "cyan2", "magenta", "magenta2", "yellow", "yellow2", "orange")
DEFAULT_FIXED = ("black", "white")
RANKING_FIELDS = ["rank", "inks", "dE00_mean", "dE00_mean_se", "dE00_p95", "dE00_continuous", "loss_final", "loss_rank",
                  "loss_last", "naive_dE00_mean", "seconds", "run_seconds", "folder"]
ORDERED_BY = "dE00_mean (CIEDE2000 mean of the final quantised result), ties by loss_final"
HIGHLIGHT = ("tab:red", "tab:blue", "tab:green")
# settings that must agree between a finished run and this selection for the run to be reused
_NOT_COMPARED = {"out", "resume", "inks"}


class SelectionError(ValueError):
    """Bad input, reported as ``ta-select-inks: error: ...`` with exit code 2."""


PROG = "ta-select-inks"


# ------------------------------------------------------------------------------------------------ arguments
def parse_args(argv=None):
    # short runs; evaluations of 4 × 32 spp every 10 iterations: at 4 × 8 spp (every 5) the ranked quantised figure
    # read 0.21 low with an SE of 0.17 and the continuous one 1.15 high on the ColorChecker example; at 4 × 32 spp
    # 0.08 low (SE 0.085) and 0.26 low (docs/bench_log.md, "Ink selection, free of render noise")
    d = PrintConfig(iterations=40, spp=4, eval_spp=128, eval_every=10, table_steps=3)
    p = CommandParser(PROG, __doc__)
    g = p.add_argument_group("target (as ta-optimize-print)")
    add_target_arguments(g, d, fixed=False)

    g = p.add_argument_group("ink sets")
    g.add_argument("--candidates", default=None,
                   help=f"comma-separated candidate inks to choose k from: built-in {sorted(INKS)} or names from "
                        f"--user-inks (default: {','.join(DEFAULT_CANDIDATES)}, plus every --user-inks ink)")
    g.add_argument("--user-inks", default=None, metavar="JSON",
                   help="extra inks: a JSON list of {name, sigma_t, albedo, g?, display_rgb?} (InkSet.load_json); "
                        "their names must differ from the built-in ones")
    g.add_argument("-k", type=int, default=3, help="inks chosen per set from the candidates (default: %(default)s)")
    g.add_argument("--always-inks", default=",".join(DEFAULT_FIXED),
                   help="comma-separated inks in every set, '' for none (default: %(default)s)")

    g = p.add_argument_group("each run (short, at low spp; the same seed for every set)")
    add_optimization_arguments(g, d)

    g = p.add_argument_group("output")
    g.add_argument("--out", default="results/select_inks", help="output folder (default: %(default)s)")
    g.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's choice)")
    g.add_argument("--quiet", action="store_true", help="no progress bar and no per-run lines; only the result")
    args = p.parse_args(argv)
    check_output_folder(p, "--out", args.out)
    return args


# ------------------------------------------------------------------------------------------------ inks
def _names(text, flag):
    """Comma list → names (stripped); empty items and duplicates are errors."""
    names = [n.strip() for n in text.split(",")] if text.strip() else []
    if any(not n for n in names):
        raise SelectionError(f"{flag}: empty ink name in {text!r}")
    keys = [n.lower() for n in names]
    dup = sorted({n for n in keys if keys.count(n) > 1})
    if dup:
        raise SelectionError(f"{flag}: duplicate ink(s) {dup} in {text!r}")
    return names


def _library(user_inks):
    """Built-in + user inks by lower-case name, and the user inks' names."""
    library = dict(INKS)
    if user_inks is None:
        return library, []
    try:
        user = InkSet.load_json(user_inks)
    except FileNotFoundError:
        raise SelectionError(f"--user-inks: no such file {user_inks!r}") from None
    except (TypeError, ValueError) as error:
        raise SelectionError(f"--user-inks: {error}") from None
    clash = [ink.name for ink in user if ink.name.lower() in INKS]
    if clash:
        raise SelectionError(f"--user-inks: ink name(s) {clash} are built-in inks; rename them in {user_inks!r}")
    for ink in user:
        library[ink.name.lower()] = ink
    return library, list(user.names)


def _resolve(names, library, flag):
    unknown = [n for n in names if n.lower() not in library]
    if unknown:
        known = sorted(INKS) + sorted(set(library) - set(INKS))
        raise SelectionError(f"{flag}: unknown ink(s) {unknown}; known inks are {known}")
    return [library[n.lower()] for n in names]


def _folder_name(inks):
    """``cyan+magenta+yellow``; characters other than letters, digits, '.', '_' and '-' become '_'."""
    return "+".join(re.sub(r"[^A-Za-z0-9._-]", "_", ink.name) for ink in inks) or "none"


@dataclasses.dataclass
class Plan:
    cfg: PrintConfig
    library: list  # candidates then fixed (Ink)
    candidates: list
    fixed: list
    combinations: list  # [(folder name, [chosen Ink], InkSet of the run)]


def make_plan(args):
    """Validate the arguments and list the combinations (nothing is written)."""
    library, user_names = _library(args.user_inks)
    cand_names = _names(args.candidates, "--candidates") if args.candidates is not None \
        else list(DEFAULT_CANDIDATES) + user_names
    fixed_names = _names(args.always_inks, "--always-inks")
    candidates = _resolve(cand_names, library, "--candidates")
    fixed = _resolve(fixed_names, library, "--always-inks")
    both = sorted({i.name.lower() for i in candidates} & {i.name.lower() for i in fixed})
    if both:
        raise SelectionError(f"--candidates and --always-inks both name {both}; an ink is either chosen or always in")
    if not candidates:
        raise SelectionError("--candidates: expected at least one ink")
    if args.k < 1:
        raise SelectionError(f"-k: expected >= 1, got {args.k}")
    if args.k > len(candidates):
        raise SelectionError(f"-k: {args.k} inks per set but only {len(candidates)} candidate(s) "
                             f"{[i.name for i in candidates]}")
    if args.k + len(fixed) > 256:
        raise SelectionError(f"-k: a set holds at most 256 inks, got {args.k} + {len(fixed)} fixed")
    gs = sorted({ink.g for ink in candidates + fixed})
    if len(gs) != 1:
        by_g = {g_: [i.name for i in candidates + fixed if i.g == g_] for g_ in gs}
        raise SelectionError(f"inks: the tracer takes one Henyey–Greenstein g per run and the sets are compared "
                             f"under the same g, but the candidate and fixed inks have g = {by_g}")
    if args.mesh is not None and args.core_ink.lower() not in [i.name.lower() for i in fixed]:
        raise SelectionError(f"--core-ink: {args.core_ink!r} fills every object's core, so it must be one of "
                             f"--always-inks {[i.name for i in fixed]}")
    folders = {}
    for ink in candidates:
        folders.setdefault(_folder_name([ink]).lower(), []).append(ink.name)
    clash = [v for v in folders.values() if len(v) > 1]
    if clash:
        raise SelectionError(f"--candidates: ink names {clash} give the same folder name; rename them")
    if args.threads is not None and not 1 <= args.threads <= (os.cpu_count() or 1):
        raise SelectionError(f"--threads: expected 1 ... {os.cpu_count() or 1} (this machine's CPUs), got "
                             f"{args.threads}")
    if args.table_steps < 1:
        raise SelectionError(f"--table-steps: expected >= 1, got {args.table_steps}")

    try:
        cfg = config_from_args(args, resume=True, inks=tuple(i.name for i in candidates[:args.k] + fixed))
    except (TypeError, ValueError) as error:
        raise SelectionError(str(error)) from None
    try:
        cfg.validate()
    except (TypeError, ValueError) as error:
        raise SelectionError(str(error)) from None
    combinations = []
    for chosen in itertools.combinations(candidates, args.k):
        combinations.append((_folder_name(chosen), list(chosen), InkSet(list(chosen) + fixed)))
    return Plan(cfg, candidates + fixed, candidates, fixed, combinations)


# ------------------------------------------------------------------------------------------------ runs
def _jsonable(value):
    return json.loads(json.dumps(value, default=str))


def _check_settings(folder, cfg, inkset):
    """A run folder made with other settings or other ink properties cannot be reused (its numbers would not be
    comparable)."""
    path = os.path.join(folder, "config.json")
    if not os.path.exists(path):
        return
    with open(path, encoding="utf-8") as handle:
        stored = json.load(handle)
    mine = _jsonable(dataclasses.asdict(cfg.resolved()))  # as the run records it
    differ = [f"{k}: {stored[k]!r} there, {mine[k]!r} now" for k in sorted(mine)
              if k not in _NOT_COMPARED and k in stored and stored[k] != mine[k]]
    inks = _jsonable([dataclasses.asdict(i) for i in inkset])
    if "inks" in stored and stored["inks"] != inks:
        there = [i.get("name") for i in stored["inks"]] if isinstance(stored["inks"], list) else stored["inks"]
        what = "the same inks with other optical properties" if there == list(inkset.names) else repr(there)
        differ.append(f"inks: {what} there, {list(inkset.names)} now")
    if differ:
        raise SelectionError(f"--out: {folder} was run with other settings ({'; '.join(differ)}); use another "
                             f"--out or the same settings")


def _read_log(folder):
    with open(os.path.join(folder, "log.csv"), newline="", encoding="utf-8") as handle:
        rows = list(csv.DictReader(handle))

    def num(v):
        return float(v) if v not in ("", None) else math.nan

    return {k: [num(r[k]) for r in rows] for k in ("iteration", "wall_s", "loss", "dE00_mean")}


def _final_loss(folder, target, gamma):
    """Appearance loss E of the run's final quantised render (``final.exr`` / ``final.npy``, at eval spp)."""
    import torch
    from torch_appearance.nn.losses import AppearanceLoss

    texels = target.load_texels(folder, "final")
    with torch.no_grad():
        loss, _ = target.appearance(AppearanceLoss(gamma=tuple(gamma)), torch.as_tensor(texels, dtype=torch.float32))
    return float(loss)


def _result(name, chosen, folder, target, gamma):
    """One row of the ranking (before ranks) and the convergence curves of a finished run."""
    with open(os.path.join(folder, "summary.json"), encoding="utf-8") as handle:
        s = json.load(handle)
    log = _read_log(folder)
    opt = [(it, loss) for it, loss in zip(log["iteration"], log["loss"]) if it > 0]
    tail = [loss for _, loss in opt[-max(1, round(len(opt) / 10)):]] or [log["loss"][-1]]
    extra = {}
    if os.path.exists(os.path.join(folder, "selection.json")):
        with open(os.path.join(folder, "selection.json"), encoding="utf-8") as handle:
            extra = json.load(handle)
    final = s["final_quantized"]
    row = {"inks": name, "dE00_mean": final["dE00_mean"], "dE00_mean_se": final.get("dE00_mean_se"),
           "dE00_p95": final["dE00_p95"],
           "dE00_continuous": s["optimized_continuous"]["dE00_mean"],
           "loss_final": _final_loss(folder, target, gamma), "loss_last": sum(tail) / len(tail),
           "naive_dE00_mean": s["baseline_naive_extrusion"]["dE00_mean"], "seconds": s["wall_s"],
           "run_seconds": extra.get("run_seconds"), "folder": os.path.relpath(folder, os.path.dirname(os.path.dirname(folder)))}
    return row, {"inks": name, "colors": [tuple(i.display_rgb) for i in chosen], "log": log}


def rank(rows):
    """Sort by final quantised CIEDE2000 mean (ties: loss_final) and add rank and loss_rank (1 = best)."""
    rows = sorted(rows, key=lambda r: (r["dE00_mean"], r["loss_final"], r["inks"]))
    by_loss = sorted(range(len(rows)), key=lambda i: (rows[i]["loss_final"], rows[i]["dE00_mean"]))
    for r_, i in enumerate(by_loss):
        rows[i]["loss_rank"] = r_ + 1
    for i, r in enumerate(rows):
        r["rank"] = i + 1
    return [{k: r.get(k) for k in RANKING_FIELDS} for r in rows]


def _rounded(row):
    """A ranking row for the CSV: ΔE to 4 decimals, seconds to 3, the loss to 6 significant digits."""
    out = dict(row)
    for k in ("dE00_mean", "dE00_mean_se", "dE00_p95", "dE00_continuous", "naive_dE00_mean"):
        out[k] = None if out[k] is None else round(out[k], 4)
    for k in ("seconds", "run_seconds"):
        out[k] = None if out[k] is None else round(out[k], 3)
    for k in ("loss_final", "loss_last"):
        out[k] = float(f"{out[k]:.6g}")
    return out


# ------------------------------------------------------------------------------------------------ the plot
def _running_mean(iterations, values, window):
    """The training loss from iteration 1 on (iteration 0 is an evaluation render) as a trailing running mean."""
    pts = [(i, v) for i, v in zip(iterations, values) if i > 0 and not math.isnan(v)]
    out = []
    for k in range(len(pts)):
        chunk = [v for _, v in pts[max(0, k - window + 1):k + 1]]
        out.append(sum(chunk) / len(chunk))
    return [i for i, _ in pts], out


def plot(path, ranking, curves, plan, args):
    from matplotlib import colormaps
    from matplotlib.figure import Figure
    from matplotlib.lines import Line2D

    order = [r["inks"] for r in ranking]
    n = len(order)
    smooth_window = max(1, min(5, plan.cfg.iterations // 8))
    top = order[:min(3, n)]
    shown = order[:40]  # bars: the best 40 at most (the ranking files hold all)
    height = max(4.6, 0.2 * len(shown) + 1.6)
    fig = Figure(figsize=(16, height))
    ax = fig.subplots(1, 3, gridspec_kw={"width_ratios": [1.0, 1.0, 0.85]})
    grey = colormaps["Greys"]
    for pos in range(n - 1, -1, -1):  # worst first, so the best lie on top
        name = order[pos]
        c = curves[name]["log"]
        best = name in top
        if best:
            style = dict(color=HIGHLIGHT[top.index(name)], lw=2.2, alpha=1.0, zorder=10 + (3 - top.index(name)))
        else:  # the others in greys, darker = better rank
            frac = (pos - len(top)) / max(1, n - len(top) - 1)
            style = dict(color=grey(0.75 - 0.4 * (1 - frac)), lw=0.9, alpha=0.9, zorder=2)
        ev = [(t, e) for t, e in zip(c["wall_s"], c["dE00_mean"]) if not math.isnan(e)]
        ax[0].plot([t for t, _ in ev], [e for _, e in ev], marker="o" if best else None, ms=3, **style)
        its, smooth = _running_mean(c["iteration"], c["loss"], smooth_window)
        ax[1].plot(its, smooth, **style)
        if best:
            r = ranking[pos]
            ax[0].plot([ev[-1][0]], [r["dE00_mean"]], marker="D", ms=7, mec="k", mew=0.6, ls="none",
                       color=style["color"], zorder=20)
    handles = [Line2D([], [], color=HIGHLIGHT[i], lw=2.2,
                      label=f"{i + 1}. {top[i]}  (ΔE00 {ranking[i]['dE00_mean']:.2f})") for i in range(len(top))]
    if n > len(top):
        handles.append(Line2D([], [], color=grey(0.55), lw=0.9, label=f"the other {n - len(top)} sets "
                              f"(darker = better)"))
    handles.append(Line2D([], [], marker="D", ms=6, mec="k", color="0.8", ls="none", label="final quantised"))
    ax[0].legend(handles=handles, fontsize=8, loc="upper right", framealpha=0.9)
    ax[0].set(xlabel="wall-clock time [s]", ylabel="CIEDE2000 mean (continuous mixture)",
              title=f"CIEDE2000 at {plan.cfg.eval_spp} spp vs time")
    ax[1].set(xlabel="iteration", ylabel="appearance loss E (training)", yscale="log",
              title=f"training loss at {plan.cfg.spp} spp" + (f" (running mean of {smooth_window})"
                                                                  if smooth_window > 1 else ""))
    ax[1].text(0.02, 0.02, f"at {plan.cfg.spp} spp E also measures render noise; sets are ranked by the final\n"
               f"quantised render at {plan.cfg.eval_spp} spp (ΔE00, and E as loss_final)", transform=ax[1].transAxes,
               fontsize=7, color="0.3", va="bottom")
    for a in ax[:2]:
        a.grid(alpha=0.3)

    y = list(range(len(shown)))
    vals = [ranking[i]["dE00_mean"] for i in y]
    colors = [HIGHLIGHT[i] if i < len(top) else "0.45" for i in y]
    ax[2].hlines(y, min(vals), vals, color="0.85", lw=1, zorder=1)
    ax[2].scatter(vals, y, c=colors, s=[40 if i < len(top) else 18 for i in y], zorder=3)
    ax[2].set_yticks(y)
    ax[2].set_yticklabels([f"{i + 1}. {shown[i]}" for i in y], fontsize=7 if len(shown) > 20 else 8)
    for i in range(len(top)):
        ax[2].get_yticklabels()[i].set_color(HIGHLIGHT[i])
    ax[2].set_ylim(len(shown) - 0.5, -0.5)
    pad = 0.08 * max(0.1, max(vals) - min(vals))
    ax[2].set_xlim(min(vals) - pad, max(vals) + pad)
    ax[2].set(xlabel="CIEDE2000 mean, final quantised",
              title="ranking" + (f" (best {len(shown)} of {n})" if len(shown) < n else ""))
    ax[2].grid(axis="x", alpha=0.3)
    fixed = "+".join(i.name for i in plan.fixed) or "none"
    fig.suptitle(f"Ink-set selection on {os.path.basename(plan.cfg.mesh or plan.cfg.target)}: {n} sets of "
                 f"{args.k} from {len(plan.candidates)} candidates, fixed {fixed}; {plan.cfg.iterations} iterations "
                 f"at {plan.cfg.spp} spp, seed {plan.cfg.seed}", fontsize=10)
    fig.tight_layout()
    ta_io.save_figure(fig, path)


# ------------------------------------------------------------------------------------------------ main
def run(args):
    t_all = time.perf_counter()
    plan = make_plan(args)
    out = args.out
    runs_dir = os.path.join(out, "runs")
    for name, _, inkset in plan.combinations:  # before any work: refuse a folder made with other settings
        _check_settings(os.path.join(runs_dir, name), plan.cfg, inkset)

    quiet = args.quiet

    def say(msg):
        if not quiet:
            LineProgress.write(msg, file=sys.stderr)  # tqdm's write: above a terminal's bar, a line elsewhere

    # one target / voxelisation for every set (the slab's inks and the object's g are set per run)
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        first = os.path.join(tmp, "inks.json")
        plan.combinations[0][2].save_json(first)
        try:
            target = build_target(dataclasses.replace(plan.cfg, inks=first), log=say)
        except (TypeError, ValueError) as error:
            raise SelectionError(str(error)) from None
    target_seconds = time.perf_counter() - t0
    n = len(plan.combinations)
    say(f"select_inks: {n} sets of {args.k} from {[i.name for i in plan.candidates]} + fixed "
        f"{[i.name for i in plan.fixed]}; target {target.kind} {list(target.shape)} ({target_seconds:.1f} s)")

    os.makedirs(runs_dir, exist_ok=True)
    InkSet(plan.library).save_json(os.path.join(out, "inks.json"))
    bar = progress_bar(total=n, desc="select_inks", unit="set", disable=quiet)  # whole lines when not a terminal
    rows, curves, ran, skipped, run_seconds = [], {}, [], [], 0.0
    for name, chosen, inkset in plan.combinations:
        folder = os.path.join(runs_dir, name)
        if os.path.exists(os.path.join(folder, "summary.json")):
            say(f"select_inks: skipping {name} (done: {os.path.join(folder, 'summary.json')})")
            skipped.append(name)
        else:
            bar.set_postfix_str(name)
            os.makedirs(folder, exist_ok=True)
            inkset.save_json(os.path.join(folder, "inks.json"))
            cfg = dataclasses.replace(plan.cfg, inks=os.path.join(folder, "inks.json"), out=folder)
            t0 = time.perf_counter()
            try:
                optimize_print(cfg, progress=False, log=say, target=target)
            except (TypeError, ValueError) as error:
                raise SelectionError(f"set {name}: {error}") from None
            seconds = time.perf_counter() - t0
            run_seconds += seconds
            ta_io.write_json(os.path.join(folder, "selection.json"),
                             {"inks": list(inkset.names), "chosen": [i.name for i in chosen], "run_seconds": seconds})
            ran.append(name)
        row, curve = _result(name, chosen, folder, target, plan.cfg.gamma)
        rows.append(row)
        curves[name] = curve
        best = min(rows, key=lambda r: r["dE00_mean"])
        bar.set_postfix_str(f"best {best['inks']} ΔE00 {best['dE00_mean']:.2f}")
        bar.update(1)
    bar.close()

    ranking = rank(rows)
    ta_io.write_csv(os.path.join(out, "ranking.csv"), [_rounded(r) for r in ranking], RANKING_FIELDS)
    ta_io.write_json(os.path.join(out, "ranking.json"), ta_io.nan_to_none(
        {"ordered_by": ORDERED_BY, "fixed": [i.name for i in plan.fixed], "k": args.k, "rows": ranking}))
    t0 = time.perf_counter()
    plot(os.path.join(out, "convergence.png"), ranking, curves, plan, args)
    plot_seconds = time.perf_counter() - t0
    best = ranking[0]
    summary = {
        "ordered_by": ORDERED_BY,
        "best": {**best, "ink_set": [c[2].names for c in plan.combinations if c[0] == best["inks"]][0]},
        "best_by_loss": [r["inks"] for r in ranking if r["loss_rank"] == 1][0],
        "k": args.k, "candidates": [i.name for i in plan.candidates], "fixed": [i.name for i in plan.fixed],
        "combinations": n, "ran": ran, "skipped": skipped,
        "settings": {**_jsonable(dataclasses.asdict(plan.cfg)), "inks": None, "out": out},
        "target": {"kind": target.kind, **target.describe()},
        "timings": {"total_s": time.perf_counter() - t_all, "target_s": target_seconds,
                    "runs_s": run_seconds, "runs_ran": len(ran), "runs_skipped": len(skipped),
                    "mean_run_s": run_seconds / len(ran) if ran else None,
                    "plot_s": plot_seconds},
        "torch_threads": __import__("torch").get_num_threads(),
    }
    ta_io.write_json(os.path.join(out, "summary.json"), ta_io.nan_to_none(summary))
    if not quiet:
        print(ta_io.markdown_table(ranking[:10], [
            ("rank", "rank", "{}"), ("inks", "inks", "{}"), ("dE00_mean", "ΔE00 mean", "{:.2f}"),
            ("dE00_mean_se", "± SE", "{:.2f}"), ("dE00_p95", "ΔE00 p95", "{:.2f}"),
            ("dE00_continuous", "ΔE00 cont.", "{:.2f}"),
            ("loss_final", "loss", "{:.4g}"), ("loss_rank", "loss rank", "{}"), ("seconds", "s", "{:.1f}")]))
    print(f"select_inks: best set {best['inks']} + {'+'.join(i.name for i in plan.fixed) or 'nothing'} "
          f"(CIEDE2000 mean {best['dE00_mean']:.2f}, p95 {best['dE00_p95']:.2f}, loss rank {best['loss_rank']}); "
          f"{len(ran)} run, {len(skipped)} skipped, {summary['timings']['total_s']:.1f} s -> {out}")
    return summary


def main(argv=None):
    args = parse_args(argv)
    if args.threads is not None and 1 <= args.threads <= (os.cpu_count() or 1):  # else refused in run()
        import torch
        torch.set_num_threads(args.threads)
    try:  # the folder is this command's while it runs: another tool's, or one another selection writes, is refused
        with claim_run_folder(args.out, PROG, "--out"):
            run(args)
    except (SelectionError, ValueError) as error:
        return fail(PROG, error)
    except KeyboardInterrupt:  # finished sets keep their summary.json, the running one its checkpoint
        return interrupted(PROG, f"finished sets are kept; run the same command again to resume the selection in "
                                 f"{args.out!r}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
