"""The figures of a print run folder, built on :class:`matplotlib.figure.Figure` (no pyplot state, no backend
switch): ``convergence.png`` (loss and the print's CIEDE2000, free of render noise, against wall time),
``ink_usage_by_depth.png`` and, for a slab, ``dE00_heatmap.png`` (the target's ``figures``)."""
import os

import numpy as np

from ... import io as ta_io

__all__ = ["convergence_figure", "ink_usage_figure", "heatmap_figure", "write_figures"]


def convergence_figure(rows, spp, eval_spp, baseline=None, remap=None, final=None):
    """Training loss and the print's CIEDE2000 (free of render noise, ± 2 standard errors) against wall-clock time,
    with the raw figure of the evaluation renders for comparison and the baselines' and the final result's means as
    horizontal lines.

    Args:
        rows: the run's log rows (``iteration``, ``wall_s``, ``loss``; at evaluations ``dE00_mean``,
            ``dE00_mean_se``, ``dE00_p95``, ``dE00_mean_raw``).
        spp, eval_spp: samples per texel of training and evaluation renders (titles).
        baseline, remap, final: dicts with ``dE00_mean`` (and ``dE00_mean_se``) or None.

    Returns:
        a :class:`matplotlib.figure.Figure`.
    """
    from matplotlib.figure import Figure

    # row 0 is scored at eval_spp, the others at spp: only the training rows share a noise level
    train = [r for r in rows if r["iteration"] > 0]
    fig = Figure(figsize=(13, 4.2))
    ax = fig.subplots(1, 2, gridspec_kw={"width_ratios": [1, 1.1]})
    ax[0].plot([r["wall_s"] for r in train], [r["loss"] for r in train], lw=1)
    ax[0].set(xlabel="wall-clock time [s]", ylabel="appearance loss E", yscale="log")
    ax[0].set_title(f"training loss at {spp} spp\n(includes render noise)", fontsize=10)
    ev = [r for r in rows if r.get("dE00_mean") not in (None, "")]
    t = [r["wall_s"] for r in ev]

    def se(r, key):
        value = r.get(key)
        return 0.0 if value is None or value != value else 2.0 * value

    ax[1].errorbar(t, [r["dE00_mean"] for r in ev], yerr=[se(r, "dE00_mean_se") for r in ev], fmt="o-", ms=3,
                   capsize=3, label="mean ΔE00 of the print (continuous), ± 2 SE")
    ax[1].errorbar(t, [r["dE00_p95"] for r in ev], yerr=[se(r, "dE00_p95_se") for r in ev], fmt="s--", ms=3,
                   capsize=3, label="p95 ΔE00, ± 2 SE")
    raw = [(r["wall_s"], r["dE00_mean_raw"]) for r in ev if r.get("dE00_mean_raw") not in (None, "")]
    if raw:
        ax[1].plot(*zip(*raw), "x:", color="0.55", ms=4, label=f"mean ΔE00 of the {eval_spp}-spp render as it is")
    for scores, style, name in ((baseline, dict(color="k", ls=":"), "naive extrusion"),
                                (remap, dict(color="C2", ls="--"), "2.5D remapped"),
                                (final, dict(color="C3", ls="-."), "final quantised")):
        if scores is not None:
            ax[1].axhline(scores["dE00_mean"], label=f"{name} (mean {scores['dE00_mean']:.2f})", **style)
    ax[1].set(xlabel="wall-clock time [s]", ylabel="CIEDE2000")
    ax[1].set_title(f"the print's error, render noise taken out\n({eval_spp} spp in 4 renders per evaluation)",
                    fontsize=10)
    ax[1].legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.02, 1.0), borderaxespad=0.0)
    fig.tight_layout()
    return fig


def ink_usage_figure(usage, depth_mm, where, inks):
    """Stacked mean ink fractions (N, K) against depth (K,) mm below ``where`` (e.g. "the top face")."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(5, 3.5))
    ax = fig.subplots()
    ax.stackplot(depth_mm, usage, labels=inks.names, edgecolor="0.3", linewidth=0.4,
                 colors=[np.clip(np.asarray(ink.display_rgb, float), 0, 1) for ink in inks])
    ax.set(xlabel=f"depth below {where} [mm]", ylabel="mean ink fraction",
           xlim=(depth_mm[0], max(depth_mm[-1], depth_mm[0] + 1e-6)), ylim=(0, 1), title="ink usage by depth")
    ax.legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    return fig


def heatmap_figure(texel_de, scores):
    """The final print's CIEDE2000 per texel (an (H, W) map, free of render noise on average, as
    :func:`~torch_appearance.print_error.noise_free_error` gives it) titled with its ``scores`` (mean ± SE, p95)."""
    from matplotlib.figure import Figure

    de = np.asarray(texel_de, np.float64)
    fig = Figure(figsize=(5.2, 4.4))
    ax = fig.subplots()
    im = ax.imshow(de, cmap="magma", vmin=0, vmax=max(1.0, float(np.percentile(de, 99))))
    fig.colorbar(im, ax=ax, label="CIEDE2000 (render noise taken out)")
    se = scores.get("dE00_mean_se")
    se_text = "" if se is None or se != se else f" ± {se:.2f}"
    ax.set_title(f"final (quantised) print against the target\nmean {scores['dE00_mean']:.2f}{se_text}, "
                 f"p95 {scores['dE00_p95']:.2f} (raw render: {scores['dE00_mean_raw']:.2f})", fontsize=9)
    ax.axis("off")
    fig.tight_layout()
    return fig


def write_figures(folder, rows, cfg, target, inks, weights, final, baseline=None, remap=None):
    """``convergence.png``, ``ink_usage_by_depth.png`` and the target's own figures (``target.figures``) in
    ``folder``."""
    ta_io.save_figure(convergence_figure(rows, cfg.spp, cfg.eval_spp, baseline, remap, final),
                      os.path.join(folder, "convergence.png"))
    usage, depth_mm = target.ink_usage_by_depth(weights)
    ta_io.save_figure(ink_usage_figure(usage, depth_mm, target.depth_reference, inks),
                      os.path.join(folder, "ink_usage_by_depth.png"))
    for name, fig in target.figures(final):
        ta_io.save_figure(fig, os.path.join(folder, name))
