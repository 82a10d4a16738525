"""The baselines a print optimisation is scored against, and the quantised render every result is scored by.

* **Naive extrusion** (TOG 2021 §6): the best homogeneous mixture per texel, from a table of rendered homogeneous
  slabs (:func:`homogeneous_table`, :func:`naive_extrusion`), extruded through the slab or, for an object, into the
  shell (the target's ``naive_weights``).
* **2.5D remap** (thesis part II §3.2): :mod:`.remap25d` prepares a slab in the mesh's UV space and wraps the slab's
  optimised weights around the object; the loop runs that slab (:func:`.loop.remap_baseline`).
* **Quantised render**: probabilistic quantisation to the printer's native resolution (:func:`quantize`) and a
  render of the printer-resolution volume (:func:`render_quantized` for a slab; an object's ``render_quantized``).
"""
import numpy as np
import torch

from ...color import rgb_to_lab
from ...fabrication.quantize import hold_fixed_fractions, micro_grid_pitch, quantize_mixture, source_index
from ...nn.mixture import mix_inks
from .rendering import render, render_indexed, replay_seed, slab_scene

__all__ = ["homogeneous_table", "naive_extrusion", "quantize", "render_quantized", "render_slab"]

_MATCH_BLOCK = 1 << 14  # texels per block of the naive extrusion's table matching


def render_slab(sigma_t, albedo, cfg, inks, faces, spp, seed, voxel_size=None, adjoint=None):
    """Face texels (F, H, W, 3) linear RGB of a slab medium (3, D, H, W) rendered with the run's settings: its
    voxel pitch (or ``voxel_size``, e.g. the printer's micro-voxel edges), IOR, the inks' common g unless ``cfg.g``
    overrides it, and its gradient replay seed (``cfg.gradient_seed``); F = ``faces`` (1: top, 2: top and bottom).
    ``adjoint``: the texels' (F, H, W, 3) gradient when known before the render (see :func:`.rendering.render`)."""
    scene = slab_scene(cfg.voxel_size if voxel_size is None else voxel_size, faces=faces, g=cfg.phase_g(inks),
                       ior=cfg.ior)
    if adjoint is not None and faces != 2:
        adjoint = adjoint[0]  # the tracer's image of one face is (H, W, 3)
    image = render(scene, sigma_t, albedo, spp=spp, seed=seed, seed_grad=replay_seed(seed, cfg.gradient_seed),
                   adjoint=adjoint)
    return image if faces == 2 else image.unsqueeze(0)


def _compositions(n_inks, steps):
    """All mixtures of ``n_inks`` inks in multiples of 1/steps, (M, n_inks)."""
    out = []

    def rec(prefix, left, k):
        if k == n_inks - 1:
            out.append(prefix + [left])
            return
        for v in range(left + 1):
            rec(prefix + [v], left - v, k + 1)

    rec([], steps, 0)
    return np.array(out, np.float64) / steps


def homogeneous_table(inks, mixtures, cfg, spp=64, lateral=16, seed=12345):
    """Rendered top-face colour (linear RGB) of homogeneous slabs, one per mixture.

    Each slab is ``lateral`` × ``lateral`` voxels of the run's thickness; the centre half of its texels is averaged
    (edge texels lose light through the sides).

    Args:
        inks: InkSet of N inks. mixtures: (M, N) weights summing to 1.

    Returns:
        (M, 3) float64 linear RGB.
    """
    colours = []
    c0, c1 = lateral // 4, lateral - lateral // 4
    for m in np.asarray(mixtures, np.float64):
        w = torch.tensor(m, dtype=torch.float32).view(-1, 1, 1, 1).expand(-1, cfg.depth, lateral, lateral)
        sigma_t, albedo = mix_inks(w.contiguous(), inks)
        img = render_slab(sigma_t.detach(), albedo.detach(), cfg, inks, 1, spp, seed)[0]
        colours.append(img[c0:c1, c0:c1].double().mean((0, 1)).numpy())
    return np.stack(colours)


def naive_extrusion(target_rgb, inks, cfg, table_spp=64):
    """The naive baseline: the best homogeneous mixture per texel, extruded through the whole thickness.

    Grey targets (all |a*|, |b*| < 2) use black/white mixtures matched to lightness L* (41 levels of black,
    quadratically spaced: a little black darkens a lot, so the light end needs the finer steps); colour targets
    use the table of all mixtures in steps of 1/``cfg.table_steps`` matched by ΔE76.

    Args:
        target_rgb: (H, W, 3) linear RGB of the top face.

    Returns:
        (N, D, H, W) float32 mixture weights and a dict describing the table.
    """
    lab = rgb_to_lab(torch.as_tensor(target_rgb, dtype=torch.float64)).numpy()
    grey = bool(np.all(np.abs(lab[..., 1:]) < 2.0))
    names = [n.lower() for n in inks.names]
    if grey and "black" in names and "white" in names:
        k, wht = names.index("black"), names.index("white")
        levels = np.linspace(0.0, 1.0, 41) ** 2
        mixtures = np.zeros((len(levels), len(names)))
        mixtures[:, k], mixtures[:, wht] = levels, 1.0 - levels
        kind = "black/white by L*"
    else:
        mixtures = _compositions(len(names), cfg.table_steps)
        kind = f"all mixtures in steps of 1/{cfg.table_steps} by dE76"
    colours = homogeneous_table(inks, mixtures, cfg, spp=table_spp)
    table_lab = rgb_to_lab(torch.as_tensor(colours)).numpy()
    flat = lab.reshape(-1, 3)
    choice = np.empty(len(flat), np.int64)
    for a in range(0, len(flat), _MATCH_BLOCK):  # texels × table distances a block of texels at a time (Spot at
        f = flat[a:a + _MATCH_BLOCK]            # 40 mm: 375 k texels × 210 mixtures × 3 is 1.9 GB per temporary)
        if kind.startswith("black"):
            d = np.abs(f[:, None, 0] - table_lab[None, :, 0])
        else:
            d = np.linalg.norm(f[:, None, :] - table_lab[None, :, :], axis=2)
        choice[a:a + len(f)] = d.argmin(1)
    h, w = target_rgb.shape[:2]
    weights = mixtures[choice].reshape(h, w, -1).transpose(2, 0, 1)
    weights = np.broadcast_to(weights[:, None], (len(names), cfg.depth, h, w))
    return torch.tensor(np.ascontiguousarray(weights), dtype=torch.float32), {"kind": kind, "entries": len(mixtures)}


def render_quantized(indices, inks, cfg, macro_hw, faces, spp, seed):
    """Render a printer-resolution material-index volume and average its texels back to the macro texel grid.

    The tracer reads the uint8 volume and the ink tables (:func:`.rendering.render_indexed`): 1 byte per printer
    voxel, no dense one-hot or σ_t/albedo copy of the printer volume; the same image as those dense grids, bitwise.

    Args:
        indices: (Dz, Hy, Wx) uint8 ink indices at ``cfg.printer_dpi``.
        macro_hw: (H, W) of the optimisation texel grid.

    Returns:
        (F, H, W, 3) float32 linear RGB.
    """
    h, w = macro_hw
    edges = micro_grid_pitch((cfg.depth, h, w), cfg.voxel_size, cfg.printer_dpi)  # exact box, not nominal DPI
    scene = slab_scene(edges, faces=faces, g=cfg.phase_g(inks), ior=cfg.ior)
    micro = render_indexed(scene, np.ascontiguousarray(indices, np.uint8), inks, spp=spp, seed=seed)
    micro = micro if faces == 2 else micro.unsqueeze(0)
    _, hy, wx, _ = micro.shape
    jy, ix = source_index(h, hy), source_index(w, wx)  # the macro texel holding each micro texel's centre
    cell = torch.as_tensor((jy[:, None] * w + ix[None, :]).reshape(-1))
    out = torch.zeros(faces, h * w, 3, dtype=torch.float64)
    out.index_add_(1, cell, micro.reshape(faces, -1, 3).double())
    count = torch.zeros(h * w, dtype=torch.float64).index_add_(0, cell, torch.ones(cell.numel(), dtype=torch.float64))
    return (out / count.view(1, -1, 1)).reshape(faces, h, w, 3).float()


def quantize(target, weights, inks, cfg, seed, fixed=()):
    """Printer-resolution (Dz, Hy, Wx) uint8 ink indices of mixture ``weights`` (N, D, H, W) on ``target``'s grid:
    one ink per printer micro-voxel drawn with the mixture's probabilities (``seed``, ``cfg.halftone``), the target's void marked
    (VOID outside an object), fixed ink fractions (``fixed``, see :mod:`.fixed_fractions`) held exactly."""
    indices = target.quantized_void(quantize_mixture(weights, cfg.voxel_size, cfg.printer_dpi, seed=seed,
                                                     halftone=cfg.halftone))
    if fixed:
        indices = hold_fixed_fractions(indices, weights, cfg.voxel_size, fixed, cfg.printer_dpi, seed=seed)
    return indices
