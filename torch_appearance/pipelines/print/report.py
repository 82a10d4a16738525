"""The figures of a print run folder, built on :class:`matplotlib.figure.Figure` (no pyplot state, no backend
switch): ``convergence.png`` (loss and CIEDE2000 against wall time), ``ink_usage_by_depth.png`` and, for a slab,
``dE00_heatmap.png`` (the target's ``figures``)."""
import os

import numpy as np
import torch

from ... import io as ta_io
from ...metrics import delta_e_2000

__all__ = ["convergence_figure", "ink_usage_figure", "heatmap_figure", "write_figures"]


def convergence_figure(rows, spp, eval_spp, baseline=None, remap=None, final=None):
    """Training loss and evaluation CIEDE2000 against wall-clock time, with the baselines' and the final result's
    means as horizontal lines.

    Args:
        rows: the run's log rows (``iteration``, ``wall_s``, ``loss``, optional ``dE00_mean``/``dE00_p95``).
        spp, eval_spp: samples per texel of training and evaluation renders (titles).
        baseline, remap, final: dicts with ``dE00_mean`` or None.

    Returns:
        a :class:`matplotlib.figure.Figure`.
    """
    from matplotlib.figure import Figure

    # row 0 is scored at eval_spp, the others at spp: only the training rows share a noise level
    train = [r for r in rows if r["iteration"] > 0]
    fig = Figure(figsize=(10, 3.8))
    ax = fig.subplots(1, 2)
    ax[0].plot([r["wall_s"] for r in train], [r["loss"] for r in train], lw=1)
    ax[0].set(xlabel="wall-clock time [s]", ylabel="appearance loss E", yscale="log",
              title=f"training loss at {spp} spp (includes render noise)")
    ev = [r for r in rows if r.get("dE00_mean") is not None]
    ax[1].plot([r["wall_s"] for r in ev], [r["dE00_mean"] for r in ev], "o-", ms=3, label="mean ΔE00 (continuous)")
    ax[1].plot([r["wall_s"] for r in ev], [r["dE00_p95"] for r in ev], "s--", ms=3, label="p95 ΔE00")
    if baseline is not None:
        ax[1].axhline(baseline["dE00_mean"], color="k", ls=":", label="naive extrusion (mean)")
    if remap is not None:
        ax[1].axhline(remap["dE00_mean"], color="C2", ls="--", label="2.5D remapped (mean)")
    if final is not None:
        ax[1].axhline(final["dE00_mean"], color="C3", ls="-.", label="final quantised (mean)")
    ax[1].set(xlabel="wall-clock time [s]", ylabel="CIEDE2000", title=f"evaluation at {eval_spp} spp")
    ax[1].legend(fontsize=7)
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


def heatmap_figure(image, target):
    """CIEDE2000 of an (H, W, 3) linear RGB image against the target, as a map with its mean and p95."""
    from matplotlib.figure import Figure

    de = np.asarray(delta_e_2000(torch.as_tensor(image), target), np.float64)
    fig = Figure(figsize=(5, 4))
    ax = fig.subplots()
    im = ax.imshow(de, cmap="magma", vmin=0)
    fig.colorbar(im, ax=ax, label="CIEDE2000")
    ax.set(title=f"final (quantised) vs target: mean {de.mean():.2f}, p95 {np.percentile(de, 95):.2f}")
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
    for name, fig in target.figures(final["image"]):
        ta_io.save_figure(fig, os.path.join(folder, name))
