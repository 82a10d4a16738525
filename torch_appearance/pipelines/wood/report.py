"""The images and figures of a wood fit's run folder, built on :class:`matplotlib.figure.Figure` and
:data:`matplotlib.colormaps` (no pyplot state, no backend switch)."""
import math
import os

import numpy as np
import torch

from ... import io as ta_io
from ...color import srgb_to_linear

__all__ = ["save_png", "save_gray", "ring_overlay", "cube_preview", "figures"]


def save_png(path, rgb_linear):
    """A linear RGB image (H, W, 3) as an sRGB PNG, clipped to [0, 1]."""
    ta_io.write_png(path, np.clip(np.asarray(rgb_linear, np.float32), 0, 1))


def save_gray(path, x, lo=None, hi=None, cmap="gray"):
    """A scalar image (H, W) mapped through the colormap ``cmap`` over [lo, hi] (default: its range) as a PNG."""
    import matplotlib

    x = np.asarray(x, np.float64)
    lo = np.nanmin(x) if lo is None else lo
    hi = np.nanmax(x) if hi is None else hi
    rgb = matplotlib.colormaps[cmap](np.clip((x - lo) / max(hi - lo, 1e-12), 0, 1))[..., :3]
    ta_io.write_png(path, srgb_to_linear(torch.from_numpy(rgb.astype(np.float32))).numpy())


def ring_overlay(folder, rgb, rings, estimate):
    """``ring_overlay.png``: the traced ring lines (and the projected tree axis of ``estimate``) over the photo."""
    import matplotlib
    from matplotlib.figure import Figure

    fig = Figure(figsize=(6, 6 * rgb.shape[0] / rgb.shape[1]))
    ax = fig.subplots()
    ax.imshow(np.clip(rgb, 0, 1) ** (1 / 2.2))
    for k, ring in enumerate(rings):
        ax.plot(ring[:, 0], ring[:, 1], lw=0.8, color=matplotlib.colormaps["tab10"](k % 10))
    if estimate is not None:
        cx, cy = estimate.centre_point_px
        psi = estimate.axis_angle
        L = max(rgb.shape)
        ax.plot([cx - L * math.cos(psi), cx + L * math.cos(psi)], [cy - L * math.sin(psi), cy + L * math.sin(psi)],
                "w--", lw=1, label="projected tree axis")
        ax.legend(loc="lower right", fontsize=7)
    ax.set(xlim=(0, rgb.shape[1]), ylim=(rgb.shape[0], 0), title=f"{len(rings)} traced rings")
    ax.axis("off")
    fig.tight_layout()
    ta_io.save_figure(fig, os.path.join(folder, "ring_overlay.png"), dpi=110)


def cube_preview(model, shape, pixel_size, path, resolution=96):
    """Offscreen pyvista render of the fitted texture carved onto a cube (edge = the board's shorter side)."""
    import pyvista as pv

    h, w = shape
    edge = min(h, w) * pixel_size
    faces = []
    n = resolution
    a = np.linspace(0, edge, n)
    uu, vv = np.meshgrid(a, a)
    # board-space cube [0, edge]² × [−edge, 0] (w < 0 goes into the board): top, front and side faces
    for pts in (np.stack([uu, vv, np.zeros_like(uu)], -1),
                np.stack([uu, np.full_like(uu, edge), -vv], -1),
                np.stack([np.full_like(uu, edge), uu, -vv], -1)):
        with torch.no_grad():
            out = model.evaluate(torch.as_tensor(pts.reshape(-1, 3), dtype=model.rotation.dtype), board=True)
        rgb = out["rgb"].clamp(0, 1).numpy() ** (1 / 2.2)
        grid = pv.StructuredGrid(pts[..., 0], pts[..., 1], pts[..., 2])
        grid.point_data["rgb"] = (rgb * 255).astype(np.uint8)
        faces.append(grid)
    pv.OFF_SCREEN = True
    plotter = pv.Plotter(off_screen=True, window_size=(480, 480))
    for f in faces:
        plotter.add_mesh(f, scalars="rgb", rgb=True, lighting=False)
    plotter.camera_position = [(2.2 * edge, 1.6 * edge, 1.8 * edge), (edge / 2, edge / 2, -edge / 2), (0, 0, 1)]
    image = plotter.screenshot(return_img=True)
    plotter.close()
    ta_io.write_png(path, srgb_to_linear(torch.from_numpy(image[..., :3].astype(np.float32) / 255)).numpy())


def figures(folder, rows, rgb, fit_rgb, err):
    """``convergence.png`` (each stage's loss against wall time), ``fit_vs_photo.png`` and ``phase_error.png``."""
    from matplotlib.figure import Figure

    s1 = [r for r in rows if r["stage"] == 1]
    s2 = [r for r in rows if r["stage"] == 2]
    s3 = [r for r in rows if r["stage"] == 3]
    fig = Figure(figsize=(15 if s3 else 10, 3.6), layout="constrained")
    ax = fig.subplots(1, 3 if s3 else 2)
    ax[0].plot([r["wall_s"] for r in s1], [r["phase_loss"] for r in s1])
    ax[0].set(xlabel="wall-clock time [s]", ylabel="cyclic phase loss [rad²]", yscale="log", title="stage 1: geometry")
    ax[1].plot([r["wall_s"] for r in s2], [r["color_loss"] for r in s2], color="C1")
    ax[1].set(xlabel="wall-clock time [s]", ylabel="colour MSE (linear RGB)", yscale="log", title="stage 2: colour map")
    if s3:
        ax[2].plot([r["wall_s"] for r in s3], [r["photometric_loss"] for r in s3], color="C2")
        ax[2].set(xlabel="wall-clock time [s]", ylabel="weighted ΔE²/100 + phase anchor + prior", yscale="log",
                  title="stage 3: photometric (reparameterised)")
    ta_io.save_figure(fig, os.path.join(folder, "convergence.png"), dpi=110)

    # constrained layout places the titles after the images' aspect is applied (tight_layout left them clipped at
    # the top edge); the height follows the photo's aspect
    aspect = rgb.shape[0] / max(rgb.shape[1], 1)
    fig = Figure(figsize=(12, 0.8 + 3.6 * min(max(aspect, 0.3), 3.0)), layout="constrained")
    ax = fig.subplots(1, 3)
    ax[0].imshow(np.clip(rgb, 0, 1) ** (1 / 2.2))
    ax[0].set_title("photo")
    ax[1].imshow(np.clip(fit_rgb, 0, 1) ** (1 / 2.2))
    ax[1].set_title("fitted procedural wood")
    im = ax[2].imshow(np.abs(err), cmap="magma", vmin=0, vmax=math.pi)
    ax[2].set_title(f"|wrapped phase error|, mean {np.abs(err).mean():.2f} rad")
    fig.colorbar(im, ax=ax[2], fraction=0.046)
    for a in ax:
        a.axis("off")
    ta_io.save_figure(fig, os.path.join(folder, "fit_vs_photo.png"), dpi=110)
    save_gray(os.path.join(folder, "phase_error.png"), np.abs(err), 0, math.pi, cmap="magma")
