"""Print appearance optimisation on slabs (Nindel et al., TOG 2021): the loop as a library function.

Given target texel images for the top (and optionally bottom) face of a slab, find per-voxel ink mixtures whose
rendered (= predicted printed) look matches them, quantise to the printer's native resolution, and write a run
folder (see :func:`optimize_print`). ``scripts/optimize_print.py`` is the command-line front end.

Data flow: ``MaterialMixture`` (learnable logits, N × D × H × W) → (σ_t, albedo) → ``render_texels`` (C++ path
tracer, radiative backpropagation) → texel colours placed on the voxel grid → ``AppearanceLoss`` (E1 ΔE76², E2 3D
SSIM, E3 3D Sobel) → ``loss.backward()`` → Adagrad/Adam step. Every ``eval_every`` iterations a render at
``eval_spp`` with a fixed seed is scored with CIEDE2000. After the loop: probabilistic quantisation (one ink per
printer micro-voxel) and an evaluation render of the *quantised* volume at the printer resolution.
"""
import dataclasses
import io as _io
import math
import os
import time
from dataclasses import dataclass
from typing import Optional, Sequence, Tuple

import numpy as np
import torch

from .. import distributed
from .. import io as ta_io
from ..color import rgb_to_lab
from ..fabrication.export import export_slices, save_index_volume
from ..fabrication.inks import DEFAULT_INKS, InkSet
from ..fabrication.quantize import (PRINTER_DPI, hold_fixed_fractions, micro_grid_pitch, quantize_mixture,
                                    source_index)
from ..metrics import color_report, delta_e_2000
from ..nn.losses import AppearanceLoss
from ..nn.mixture import MaterialMixture, mix_inks
from ..render.emitter import EnvironmentMap
from ..render.scene import derive_seed_grad
from ..render.volpath import render_texels
from .fixed_fractions import fixed_fractions, parse_fixed
from .targets import load_target

__all__ = ["PrintConfig", "optimize_print", "build_target", "SlabTarget", "slab_texel_grid", "homogeneous_table", "naive_extrusion",
           "render_quantized", "LOG_FIELDS"]

LOG_FIELDS = ["iteration", "wall_s", "loss", "E1", "E2", "E3", "dE00_mean", "dE00_p95", "dE76_mean", "seed"]
CHECKPOINT = "checkpoint.pt"
_MATCH_BLOCK = 1 << 14  # texels per block of the naive extrusion's table matching


@dataclass
class PrintConfig:
    """Settings of one print optimisation run (every field is a flag of scripts/optimize_print.py).

    Lengths in mm; ``dpi`` is the optimisation voxel pitch (300 DPI ≈ 0.0847 mm cubic voxels).
    """
    target: str = "colorchecker"
    bottom_target: Optional[str] = None
    thickness_mm: float = 1.0
    dpi: float = 300.0
    width_mm: Optional[float] = None
    height_mm: Optional[float] = None
    inks: Sequence[str] = DEFAULT_INKS
    gamma: Tuple[float, float, float] = (1.0, 3.0, 1.0)
    spp: int = 32
    eval_spp: int = 256
    eval_every: int = 25
    iterations: int = 300
    optimizer: str = "adagrad"
    lr: float = 1.0
    parameterization: str = "sigmoid"
    seed: int = 0
    gradient_seed: str = "same"  # "same": the replay retraces the forward's paths; "independent": seed_grad
    ior: Optional[float] = 1.5
    g: Optional[float] = None  # HG parameter; default: the inks' common g (0.4 for the built-in inks)
    printer_dpi: Tuple[float, float, float] = PRINTER_DPI
    table_steps: int = 6
    mesh: Optional[str] = None  # a textured mesh: optimise the object instead of a slab (height_mm: its z extent)
    texture: Optional[str] = None  # base-colour image for a mesh with UVs but no material
    shell_mm: float = 2.0  # objects: optimised depth below the surface; deeper voxels hold core_ink
    core_ink: str = "white"
    init: str = "naive"  # "naive": start from the naive extrusion; "white": 97 % white everywhere (the paper)
    estimator: str = "ema"  # "ema": loss gradient at the running mean of past renders; "plain": at this render
    ema_beta: float = 0.98  # decay of that running mean (about 1/(1 − β) renders)
    naive_baseline: bool = True  # score the naive extrusion (costs a table of homogeneous renders)
    remap_baseline: bool = False  # objects: also the 2.5D remapped baseline (a slab optimised in UV space)
    views: int = 3  # objects: camera renders of the quantised print from this many directions (0: none)
    view_size: int = 192  # objects: pixels per side of those renders
    fixed: Sequence[str] = ()  # "INK=FRACTION:MASK" constraints (see pipelines.fixed_fractions)
    envmap: Optional[str] = None  # objects: a lat-long linear EXR (z up) lighting the print instead of uniform white
    out: str = "results/print"
    resume: bool = False

    def validate(self):
        """Raise ValueError/TypeError naming the field for anything out of range."""
        def positive(name, value, integer=False):
            ok = isinstance(value, int) if integer else isinstance(value, (int, float))
            if not ok or isinstance(value, bool):
                raise TypeError(f"{name}: expected {'an int' if integer else 'a number'}, got {type(value).__name__}")
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name}: expected > 0, got {value}")

        for name in ("thickness_mm", "dpi", "lr", "shell_mm"):
            positive(name, getattr(self, name))
        for name in ("spp", "eval_spp", "eval_every", "iterations", "table_steps", "view_size"):
            positive(name, getattr(self, name), integer=True)
        if isinstance(self.views, bool) or not isinstance(self.views, int) or self.views < 0:
            raise ValueError(f"views: expected an int >= 0, got {self.views!r}")
        for name in ("width_mm", "height_mm"):
            if getattr(self, name) is not None:
                positive(name, getattr(self, name))
        if self.gradient_seed not in ("same", "independent"):
            raise ValueError(f"gradient_seed: expected 'same' or 'independent', got {self.gradient_seed!r}")
        if self.init not in ("white", "naive"):
            raise ValueError(f"init: expected 'white' or 'naive', got {self.init!r}")
        if self.estimator not in ("ema", "plain"):
            raise ValueError(f"estimator: expected 'ema' or 'plain', got {self.estimator!r}")
        if isinstance(self.ema_beta, bool) or not isinstance(self.ema_beta, (int, float)) or \
                not 0.0 <= self.ema_beta < 1.0:
            raise ValueError(f"ema_beta: expected a number in [0, 1), got {self.ema_beta!r}")
        if self.optimizer not in ("adagrad", "adam"):
            raise ValueError(f"optimizer: expected 'adagrad' or 'adam', got {self.optimizer!r}")
        if len(tuple(self.gamma)) != 3 or min(self.gamma) < 0 or sum(self.gamma) <= 0:
            raise ValueError(f"gamma: expected three weights >= 0 with a positive sum, got {self.gamma!r}")
        if len(tuple(self.printer_dpi)) != 3 or min(self.printer_dpi) <= 0:
            raise ValueError(f"printer_dpi: expected three positive DPI values (x, y, z), got {self.printer_dpi!r}")
        if self.remap_baseline and self.mesh is None:
            raise ValueError("remap_baseline: the 2.5D remapped baseline is for objects (--mesh)")
        if self.mesh is not None:
            if self.height_mm is None:
                raise ValueError("height_mm: an object print needs the object's height in mm (--height-mm)")
            if self.envmap is not None and not os.path.isfile(self.envmap):
                raise ValueError(f"envmap: no such file {self.envmap!r}")
            if self.bottom_target is not None or self.width_mm is not None:
                raise ValueError("mesh: bottom_target and width_mm are slab settings; an object takes its colours "
                                 "from the mesh and its size from height_mm")
        if isinstance(self.fixed, str) or not isinstance(self.fixed, Sequence):
            raise TypeError(f"fixed: expected a sequence of INK=FRACTION:MASK strings, got {self.fixed!r}")
        for spec in self.fixed:
            parse_fixed(spec)
        if self.mesh is None and self.envmap is not None:
            raise ValueError("envmap: environment maps light object prints (--mesh); slabs use uniform light")
        if self.voxel_size > self.thickness_mm * 1.0001:
            raise ValueError(f"thickness_mm: expected at least one voxel ({self.voxel_size:.4f} mm), "
                             f"got {self.thickness_mm}")

    @property
    def voxel_size(self):
        return 25.4 / self.dpi

    @property
    def depth(self):
        return max(1, int(round(self.thickness_mm / self.voxel_size)))


# ------------------------------------------------------------------------------------------------ geometry
def slab_texel_grid(faces_rgb, depth):
    """Place face texel images on the voxel grid for the appearance losses.

    Args:
        faces_rgb: (F, H, W, 3) texel colours, F = 1 (top) or 2 (top, bottom).
        depth: D, voxel layers of the slab (top face = layer D − 1, bottom face = layer 0).

    Returns:
        (3, D, H, W) grid (zeros off the faces) and the (D, H, W) bool texel mask.
    """
    f, h, w, _ = faces_rgb.shape
    if f == 2 and depth < 2:
        raise ValueError(f"thickness_mm: a two-sided target needs at least 2 voxel layers, got {depth}")
    grid = faces_rgb.new_zeros(3, depth, h, w)
    mask = torch.zeros(depth, h, w, dtype=torch.bool, device=faces_rgb.device)
    layers = [depth - 1, 0][:f]
    for k, layer in enumerate(layers):
        grid = grid.index_copy(1, torch.tensor([layer]), faces_rgb[k].permute(2, 0, 1).unsqueeze(1))
        mask[layer] = True
    return grid, mask


class SlabTarget:
    """Face texel images of a slab as the optimisation target (the loop's other kind is
    :class:`~torch_appearance.pipelines.object_target.ObjectTarget`).

    Attributes:
        shape: (D, H, W). support: None (every voxel optimised). target: (F, H, W, 3) linear RGB, F = 1 (top) or
        2 (top, bottom). target_grid, mask: the faces on the voxel grid for the losses.
    """
    kind = "slab"
    support = None

    def __init__(self, cfg, inks, faces_target):
        self.cfg, self.inks = cfg, inks
        self.target = torch.tensor(np.stack(faces_target))  # (F, H, W, 3)
        self.faces = self.target.shape[0]
        self.shape = (cfg.depth, *self.target.shape[1:3])
        self.target_grid, self.mask = slab_texel_grid(self.target, cfg.depth)

    def render(self, sigma_t, albedo, spp, seed):
        return _render_faces(sigma_t, albedo, self.cfg, self.inks, self.faces, spp, seed)

    def to_grid(self, texels):
        return slab_texel_grid(texels, self.cfg.depth)[0]

    def appearance(self, criterion, texels):
        """``(E, {"E1", "E2", "E3"})`` of the face texels (F, H, W, 3) on the voxel grid (dense path: the faces
        are whole layers, which the grid path filters with per-axis matrices)."""
        return criterion.forward_parts(self.to_grid(texels), self.target_grid, self.mask)

    def scored(self, texels):
        """The top face is scored (the bottom face is reported separately)."""
        return texels[0], self.target[0]

    def voxel_depth(self):
        """(D, H, W) depth of the voxel centres below the top face, mm."""
        d, h, w = self.shape
        depth = (d - 1 - np.arange(d) + 0.5) * self.cfg.voxel_size
        return np.broadcast_to(depth[:, None, None], (d, h, w))

    def describe(self):
        return {"grid_dhw": list(self.shape), "faces": self.faces, "texels": self.faces * self.shape[1] * self.shape[2]}


def _render_faces(sigma_t, albedo, cfg, inks, faces, spp, seed, voxel_size=None):
    g = inks.g if cfg.g is None else cfg.g  # the inks' common HG g unless the run overrides it
    seed_grad = derive_seed_grad(seed) if cfg.gradient_seed == "independent" else None
    image = distributed.render(render_texels, sigma_t=sigma_t, albedo=albedo,
                               voxel_size=cfg.voxel_size if voxel_size is None else voxel_size,
                               face="both" if faces == 2 else "top", g=g, ior=cfg.ior, spp=spp, seed=seed,
                               seed_grad=seed_grad)
    return image if faces == 2 else image.unsqueeze(0)


# ------------------------------------------------------------------------------------------------ baselines
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
        img = _render_faces(sigma_t.detach(), albedo.detach(), cfg, inks, 1, spp, seed)[0]
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


# ------------------------------------------------------------------------------------------------ quantisation
def render_quantized(indices, inks, cfg, macro_hw, faces, spp, seed):
    """Render a printer-resolution material-index volume and average its texels back to the macro texel grid.

    Args:
        indices: (Dz, Hy, Wx) uint8 ink indices at ``cfg.printer_dpi``.
        macro_hw: (H, W) of the optimisation texel grid.

    Returns:
        (F, H, W, 3) float32 linear RGB.
    """
    h, w = macro_hw
    edges = micro_grid_pitch((cfg.depth, h, w), cfg.voxel_size, cfg.printer_dpi)  # exact box, not nominal DPI
    idx = torch.as_tensor(indices.astype(np.int64))
    onehot = torch.nn.functional.one_hot(idx, len(inks)).permute(3, 0, 1, 2).float().contiguous()
    sigma_t, albedo = mix_inks(onehot, inks)
    micro = _render_faces(sigma_t.detach().contiguous(), albedo.detach().contiguous(), cfg, inks, faces, spp, seed,
                          voxel_size=edges)
    _, hy, wx, _ = micro.shape
    jy, ix = source_index(h, hy), source_index(w, wx)  # the macro texel holding each micro texel's centre
    cell = torch.as_tensor((jy[:, None] * w + ix[None, :]).reshape(-1))
    out = torch.zeros(faces, h * w, 3, dtype=torch.float64)
    out.index_add_(1, cell, micro.reshape(faces, -1, 3).double())
    count = torch.zeros(h * w, dtype=torch.float64).index_add_(0, cell, torch.ones(cell.numel(), dtype=torch.float64))
    return (out / count.view(1, -1, 1)).reshape(faces, h, w, 3).float()


# ------------------------------------------------------------------------------------------------ run folder I/O
def _save_image(folder, stem, rgb):
    rgb = np.ascontiguousarray(np.asarray(rgb, np.float32))
    ta_io.write_exr(os.path.join(folder, f"{stem}.exr"), rgb)
    ta_io.write_png(os.path.join(folder, f"{stem}.png"), np.clip(rgb, 0, 1))




def _atomic_torch_save(obj, path):
    buffer = _io.BytesIO()
    torch.save(obj, buffer)
    ta_io.atomic_write_bytes(path, buffer.getvalue())


def _iteration_seed(seed, iteration):
    """A distinct 63-bit seed per iteration (SplitMix64 of the run seed and the iteration)."""
    z = (int(seed) * 0x9E3779B97F4A7C15 + int(iteration) + 1) & 0xFFFFFFFFFFFFFFFF
    z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & 0xFFFFFFFFFFFFFFFF
    z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & 0xFFFFFFFFFFFFFFFF
    return (z ^ (z >> 31)) >> 1


def _plots(folder, rows, baseline, weights, inks, cfg, target, final, remap=None):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    # row 0 is scored at eval_spp, the others at spp: only the training rows share a noise level
    train = [r for r in rows if r["iteration"] > 0]
    fig, ax = plt.subplots(1, 2, figsize=(10, 3.8))
    ax[0].plot([r["wall_s"] for r in train], [r["loss"] for r in train], lw=1)
    ax[0].set(xlabel="wall-clock time [s]", ylabel="appearance loss E", yscale="log",
              title=f"training loss at {cfg.spp} spp (includes render noise)")
    ev = [r for r in rows if r.get("dE00_mean") is not None]
    ax[1].plot([r["wall_s"] for r in ev], [r["dE00_mean"] for r in ev], "o-", ms=3, label="mean ΔE00 (continuous)")
    ax[1].plot([r["wall_s"] for r in ev], [r["dE00_p95"] for r in ev], "s--", ms=3, label="p95 ΔE00")
    if baseline is not None:
        ax[1].axhline(baseline["dE00_mean"], color="k", ls=":", label="naive extrusion (mean)")
    if remap is not None:
        ax[1].axhline(remap["dE00_mean"], color="C2", ls="--", label="2.5D remapped (mean)")
    ax[1].axhline(final["dE00_mean"], color="C3", ls="-.", label="final quantised (mean)")
    ax[1].set(xlabel="wall-clock time [s]", ylabel="CIEDE2000", title=f"evaluation at {cfg.eval_spp} spp")
    ax[1].legend(fontsize=7)
    fig.tight_layout()
    ta_io.save_figure(fig, os.path.join(folder, "convergence.png"))

    # ink usage by depth: mean mixture per layer from the top face down (slab), or per depth bin below the
    # surface over the shell (object)
    if target.kind == "slab":
        w = weights.detach().double().mean((2, 3)).numpy()[:, ::-1]  # (N, D), depth 0 = top layer
        depth_mm = (np.arange(w.shape[1]) + 0.5) * cfg.voxel_size
        where = "the top face"
    else:
        w, depth_mm = target.ink_usage_by_depth(weights)
        where = "the surface (shell voxels)"
    fig, ax = plt.subplots(figsize=(5, 3.5))
    ax.stackplot(depth_mm, w, labels=inks.names, edgecolor="0.3", linewidth=0.4,
                 colors=[np.clip(np.asarray(ink.display_rgb, float), 0, 1) for ink in inks])
    ax.set(xlabel=f"depth below {where} [mm]", ylabel="mean ink fraction",
           xlim=(depth_mm[0], max(depth_mm[-1], depth_mm[0] + 1e-6)), ylim=(0, 1), title="ink usage by depth")
    ax.legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    ta_io.save_figure(fig, os.path.join(folder, "ink_usage_by_depth.png"))

    if target.kind != "slab":
        return
    de = delta_e_2000(torch.as_tensor(final["image"][0]), target.target[0])
    de = np.asarray(de, np.float64)
    fig, ax = plt.subplots(figsize=(5, 4))
    im = ax.imshow(de, cmap="magma", vmin=0)
    fig.colorbar(im, ax=ax, label="CIEDE2000")
    ax.set(title=f"final (quantised) vs target: mean {de.mean():.2f}, p95 {np.percentile(de, 95):.2f}")
    ax.axis("off")
    fig.tight_layout()
    ta_io.save_figure(fig, os.path.join(folder, "dE00_heatmap.png"))




def _score(image, target):
    """CIEDE2000 mean/p95 and ΔE76 of (H, W, 3) linear images."""
    rep = color_report(torch.as_tensor(image).reshape(-1, 3).double(), torch.as_tensor(target).reshape(-1, 3).double())
    return {k: float(v) for k, v in rep.items()}


# ------------------------------------------------------------------------------------------------ the loop
def _slab_target(cfg, inks):
    """The slab target: top (and bottom) images sized by the image at the voxel pitch or by width/height."""
    top = load_target(cfg.target, name="target")
    size = None
    if cfg.width_mm is not None or cfg.height_mm is not None:
        h0, w0 = top.shape[:2]
        width = cfg.width_mm if cfg.width_mm is not None else cfg.height_mm * w0 / h0
        height = cfg.height_mm if cfg.height_mm is not None else cfg.width_mm * h0 / w0
        size = (max(1, round(height / cfg.voxel_size)), max(1, round(width / cfg.voxel_size)))
        top = load_target(cfg.target, size=size, name="target")
    faces_target = [top]
    if cfg.bottom_target is not None:
        bottom = load_target(cfg.bottom_target, size=size, name="bottom_target")
        if bottom.shape != top.shape:
            raise ValueError(f"bottom_target: expected the size of the top target {top.shape[:2]}, "
                             f"got {bottom.shape[:2]} (pass width_mm/height_mm to resample both)")
        faces_target.append(bottom)
    return SlabTarget(cfg, inks, faces_target)


def _object_target(cfg, inks, log):
    """The object target: the mesh loaded, scaled to height_mm and voxelised with a shell of shell_mm."""
    from ..geometry import load_mesh, voxelize
    from .object_target import ObjectTarget

    mesh, report = load_mesh(cfg.mesh, height_mm=cfg.height_mm, texture=cfg.texture)
    t0 = time.perf_counter()
    obj = voxelize(mesh, cfg.voxel_size, shell_mm=cfg.shell_mm)
    inside, shell = int(obj.occupancy.sum()), int(obj.shell.sum())
    if shell >= inside:
        raise ValueError(f"shell_mm: a {cfg.shell_mm} mm shell takes every one of the object's {inside} voxels (it "
                         f"is thicker than half the object's thickness); use a thinner shell")
    log(f"optimize_print: {cfg.mesh}: {report['triangles']} triangles, grid {obj.grid_shape}, {inside} inside "
        f"voxels, {shell} in the {cfg.shell_mm} mm shell, {len(obj.texel_voxels)} texels "
        f"({time.perf_counter() - t0:.1f} s)")
    g = inks.g if cfg.g is None else cfg.g
    emitter = None if cfg.envmap is None else EnvironmentMap.from_exr(cfg.envmap)
    target = ObjectTarget(obj, ior=cfg.ior, g=g, gradient_seed=cfg.gradient_seed, emitter=emitter)
    target.mesh, target.mesh_report = mesh, report
    return target


def _naive_baseline(target, inks, cfg):
    """Naive extrusion weights (N, D, H, W) and the table's description, for either kind of target."""
    if target.kind == "slab":
        return naive_extrusion(target.target[0].numpy(), inks, cfg)
    # objects: the same table (homogeneous slabs as thick as the shell) per texel, extruded to the nearest texel
    table_cfg = dataclasses.replace(cfg, thickness_mm=cfg.shell_mm)
    column, table = naive_extrusion(target.target.numpy()[:, None, :], inks, table_cfg)
    core = np.zeros(len(inks))
    core[inks.index(cfg.core_ink)] = 1.0
    return target.extrude(column[:, 0, :, 0].numpy(), core), table


def _quantize_and_render(target, weights, inks, cfg, spp, seed, quant_seed, fixed=()):
    """Printer-resolution indices of ``weights`` (VOID outside an object, fixed fractions exact) and their
    rendered texels."""
    indices = quantize_mixture(weights, cfg.voxel_size, cfg.printer_dpi, seed=quant_seed)
    if target.kind == "object":
        indices = target.quantized_void(indices)
    if fixed:
        indices = hold_fixed_fractions(indices, weights, cfg.voxel_size, fixed, cfg.printer_dpi, seed=quant_seed)
    if target.kind == "slab":
        h, w = target.shape[1:]
        return indices, render_quantized(indices, inks, cfg, (h, w), target.faces, spp, seed)
    return indices, target.render_quantized(indices, inks, cfg.printer_dpi, spp, seed)


def _object_views(folder, target, indices, inks, cfg, seed, log, texel_de=None):
    """Camera renders of the quantised object (``view_k.exr``/``.png``) and ``views.png`` beside the target
    texture on the mesh; returns the seconds spent."""
    if cfg.views == 0:
        return 0.0
    from .object_figures import views_figure

    t0 = time.perf_counter()
    cams = target.camera_views(cfg.views, cfg.view_size)
    renders = []
    for k, cam in enumerate(cams):
        image = target.render_quantized(indices, inks, cfg.printer_dpi, cfg.eval_spp, _iteration_seed(seed, -10 - k),
                                        sensor=cam)
        _save_image(folder, f"view_{k}", image.numpy())
        renders.append(image.numpy())
    views_figure(os.path.join(folder, "views.png"), target, cams, renders, texel_de=texel_de, log=log)
    return time.perf_counter() - t0


def _save_texels(target, folder, stem, texels):
    texels = texels.numpy() if isinstance(texels, torch.Tensor) else np.asarray(texels)
    if target.kind == "object":
        target.save_texels(folder, stem, texels)
        return
    _save_image(folder, stem, texels[0])
    if target.faces == 2:
        _save_image(folder, f"{stem}_bottom", texels[1])


# ------------------------------------------------------------------------------------------------ the loop
def build_target(cfg: PrintConfig, log=print):
    """The print target of ``cfg`` (a :class:`SlabTarget`, or with ``cfg.mesh`` an
    :class:`~torch_appearance.pipelines.object_target.ObjectTarget`), to share between runs that differ only in
    inks or optimiser settings (``optimize_print(cfg, target=...)``)."""
    cfg.validate()
    inks = _load_inks(cfg.inks)
    if cfg.mesh is not None and cfg.core_ink.lower() not in [n.lower() for n in inks.names]:
        raise ValueError(f"core_ink: {cfg.core_ink!r} is not in the ink set {list(inks.names)}")
    return _object_target(cfg, inks, log) if cfg.mesh is not None else _slab_target(cfg, inks)


def optimize_print(cfg: PrintConfig, progress=True, log=print, target=None):
    """Run one print optimisation of a slab or, with ``cfg.mesh``, of a textured object, and write ``cfg.out``.

    Run folder (fixed names other tools rely on): ``config.json``; ``log.csv`` (iteration, wall_s, loss, E1, E2,
    E3, dE00_mean, dE00_p95, dE76_mean, seed); ``convergence.png``; ``ink_usage_by_depth.png``; the texel colours
    of ``target``, ``baseline`` (naive extrusion, quantised), ``initial``, ``optimized`` (continuous mixture) and
    ``final`` (quantised result): for a slab linear-RGB ``.exr`` images of the top face with PNG previews (and
    ``*_bottom`` for two-sided targets) and ``dE00_heatmap.png``; for an object ``.npy`` (N, 3) linear RGB and a
    coloured point cloud ``.ply`` at the texels' surface points, and ``object.npz`` (the voxelisation);
    ``mixture.npz`` (weights N×D×H×W, ink names, voxel size); ``quantized.npz`` (uint8 material indices at the
    printer resolution, 255 = void outside an object); ``slices/`` (one PNG per printer layer +
    ``palette.json``); ``checkpoint.pt`` (written atomically at every evaluation; ``cfg.resume`` continues from
    it); ``summary.json``.

    Args:
        cfg: the settings. progress: show a tqdm bar. log: where one-line messages go.
        target: optional prebuilt target from :func:`build_target` for the same geometry settings (a run with
            other inks or optimiser settings reuses the voxelisation and the scene).

    Returns:
        The summary dict (also written to ``summary.json``).
    """
    cfg.validate()
    rank, world = distributed.rank_and_world()
    folder = cfg.out
    ckpt_path = os.path.join(folder, CHECKPOINT)
    if os.path.exists(ckpt_path) and not cfg.resume:
        raise ValueError(f"out: {folder!r} already holds a run (checkpoint.pt); pass resume=True (--resume) to "
                         f"continue it or choose another folder")
    inks = _load_inks(cfg.inks)
    if cfg.g is None:
        inks.g  # noqa: B018 - raises ValueError if the inks disagree on g
    if target is None:
        target = build_target(cfg, log)
    elif cfg.mesh is not None and cfg.core_ink.lower() not in [n.lower() for n in inks.names]:
        raise ValueError(f"core_ink: {cfg.core_ink!r} is not in the ink set {list(inks.names)}")
    if target.kind == "slab":
        target.inks = inks  # the slab renders with the run's inks (their g)
    else:
        target.use_g(inks.g if cfg.g is None else cfg.g)
    shape = tuple(target.shape)
    constraints, fixed = fixed_fractions(target, cfg.fixed, inks)
    if rank != 0:
        # under torchrun every rank runs the same loop (the renders are collective); only rank 0 writes the run
        # folder, the others write to a private temporary one that is removed at the end
        import tempfile
        folder = tempfile.mkdtemp(prefix=f"optimize_print_rank{rank}_")
        progress, log = False, (lambda *args, **kwargs: None)
    os.makedirs(folder, exist_ok=True)  # only once the inputs are known to be good: no partial run folder
    try:
        return _optimize(cfg, target, inks, shape, constraints, fixed, folder, ckpt_path, progress, log, world)
    finally:
        if rank != 0:
            import shutil
            shutil.rmtree(folder, ignore_errors=True)


def _optimize(cfg, target, inks, shape, constraints, fixed, folder, ckpt_path, progress, log, world):
    """The body of :func:`optimize_print` once the inputs are checked; writes to ``folder``, resumes from
    ``ckpt_path``."""
    ta_io.write_json(os.path.join(folder, "config.json"), {
        **dataclasses.asdict(cfg), "inks": [dataclasses.asdict(i) for i in inks], "voxel_size_mm": cfg.voxel_size,
        "kind": target.kind, **target.describe(), "torch": torch.__version__,
        "torch_threads": torch.get_num_threads(), "ranks": world, **({"mesh_report": target.mesh_report}
                                                     if target.kind == "object" else {})})
    if target.kind == "object":
        target.obj.save(os.path.join(folder, "object.npz"))
    _save_texels(target, folder, "target", target.target)

    model = MaterialMixture(inks, shape, parameterization=cfg.parameterization, support=target.support,
                            core_ink=cfg.core_ink if target.support is not None else None, fixed=constraints)
    optim_cls = torch.optim.Adagrad if cfg.optimizer == "adagrad" else torch.optim.Adam
    optimizer = optim_cls(model.parameters(), lr=cfg.lr)
    criterion = AppearanceLoss(gamma=tuple(cfg.gamma))
    rows, start, wall_offset = [], 0, 0.0
    ema = {"sum": None, "count": 0}  # estimator "ema": running mean of the renders (checkpointed)
    if cfg.resume and os.path.exists(ckpt_path):
        state = torch.load(ckpt_path, weights_only=False)
        if tuple(state["grid_dhw"]) != shape or state["inks"] != list(inks.names):
            raise ValueError(f"resume: the checkpoint in {folder!r} is for grid {state['grid_dhw']} and inks "
                             f"{state['inks']}, this run has {list(shape)} and {list(inks.names)}")
        model.load_state_dict(state["model"])
        optimizer.load_state_dict(state["optimizer"])
        rows, start, wall_offset = state["rows"], state["iteration"], state["wall_s"]
        ema = state.get("ema", ema)
        baseline, remap = state["baseline"], state.get("baseline_remap")
        log(f"optimize_print: resuming {folder} at iteration {start}")
    else:
        baseline, remap = None, None

    eval_seed = _iteration_seed(cfg.seed, -1)
    quant_seed = _iteration_seed(cfg.seed, -2)

    def evaluate(spp=cfg.eval_spp):
        with torch.no_grad():
            s, a = model()
            return target.render(s, a, spp, eval_seed)

    def score(texels):
        return _score(*target.scored(texels))

    def loss_row(texels):
        with torch.no_grad():
            loss, parts = target.appearance(criterion, texels)
        return {"loss": float(loss), **{k: float(v) for k, v in parts.items()}}

    if not rows:  # a fresh run: the naive extrusion, quantised and scored the same way as the result
        base_w = None
        if cfg.naive_baseline:
            t0 = time.perf_counter()
            base_w, table = _naive_baseline(target, inks, cfg)
            _, base_img = _quantize_and_render(target, base_w, inks, cfg, cfg.eval_spp, eval_seed, quant_seed)
            baseline = {"image": base_img.numpy(), **score(base_img), "table": table,
                        "seconds": time.perf_counter() - t0}
            _save_texels(target, folder, "baseline", baseline["image"])
        if cfg.init == "naive":  # warm start: the optimisation begins where the naive extrusion ends
            model.set_weights(_naive_baseline(target, inks, cfg)[0] if base_w is None else base_w)
        # the extrusion's (inks, D, H, W) weights are not kept through the optimisation (1.16 GB for Spot at 40 mm)
        del base_w
        initial = evaluate()
        _save_texels(target, folder, "initial", initial)
        rows.append({"iteration": 0, "wall_s": 0.0, **loss_row(initial), **score(initial), "seed": eval_seed})
    if target.kind == "object" and cfg.remap_baseline and remap is None:  # 2.5D: a slab in UV space, wrapped on
        from .remap25d import remap_baseline
        t0 = time.perf_counter()
        remap_w, remap_info = remap_baseline(target, inks, cfg, work_dir=os.path.join(folder, "remap25d"), log=log)
        _, remap_img = _quantize_and_render(target, remap_w, inks, cfg, cfg.eval_spp, eval_seed, quant_seed, fixed)
        remap = {"image": remap_img.numpy(), **score(remap_img), "info": remap_info,
                 "seconds": time.perf_counter() - t0}
        _save_texels(target, folder, "baseline_remap", remap["image"])

    # ---- optimisation
    try:
        from tqdm import tqdm
        bar = tqdm(total=cfg.iterations, initial=start, disable=not progress, desc="optimize_print", unit="it")
    except ImportError:  # pragma: no cover
        bar = None
    t_start = time.perf_counter() - wall_offset
    last_eval = rows[-1] if rows else {}
    for it in range(start, cfg.iterations):
        seed = _iteration_seed(cfg.seed, it)
        sigma_t, albedo = model()
        image = target.render(sigma_t, albedo, cfg.spp, seed)
        if cfg.estimator == "ema":
            # the loss's gradient with respect to the texel colours is taken at the running mean of the past
            # renders and applied to this render: the adjoint no longer shares this render's noise (that
            # correlation biases the plain estimator at low spp towards less noisy, not more accurate, media)
            now = image.detach()
            primal = now if ema["count"] == 0 else ema["sum"] / (1.0 - cfg.ema_beta ** ema["count"])
            x = primal.clone().requires_grad_(True)
            loss, parts = target.appearance(criterion, x)
            (adjoint,) = torch.autograd.grad(loss, x)
            ema["sum"] = (1.0 - cfg.ema_beta) * now + (0.0 if ema["sum"] is None else cfg.ema_beta * ema["sum"])
            ema["count"] += 1
            surrogate = (adjoint * image).sum()
        else:
            loss, parts = target.appearance(criterion, image)
            surrogate = loss
        optimizer.zero_grad(set_to_none=True)
        surrogate.backward()
        optimizer.step()
        # the full (3, D, H, W) grids of this iteration (1.4 GB for Spot at 40 mm) are not kept alive through the
        # evaluations, the quantisation and the next iteration's mixture
        del sigma_t, albedo, image, surrogate
        row = {"iteration": it + 1, "loss": loss.item(), **{k: v.item() for k, v in parts.items()}, "seed": seed}
        if (it + 1) % cfg.eval_every == 0 or it + 1 == cfg.iterations:
            row.update(score(evaluate()))
            last_eval = row
        row["wall_s"] = time.perf_counter() - t_start
        rows.append(row)
        if "dE00_mean" in row:
            _atomic_torch_save({"model": model.state_dict(), "optimizer": optimizer.state_dict(), "rows": rows,
                                "iteration": it + 1, "wall_s": row["wall_s"], "baseline": baseline,
                                "baseline_remap": remap, "ema": ema,
                                "grid_dhw": list(shape), "inks": list(inks.names)},
                               os.path.join(folder, CHECKPOINT))
            ta_io.write_csv(os.path.join(folder, "log.csv"), rows, LOG_FIELDS)
        if bar is not None:
            bar.update(1)
            bar.set_postfix(loss=f"{row['loss']:.4g}", dE00=f"{last_eval.get('dE00_mean', float('nan')):.2f}")
    if bar is not None:
        bar.close()
    ta_io.write_csv(os.path.join(folder, "log.csv"), rows, LOG_FIELDS)

    # ---- results: continuous, quantised, exports
    optimized = evaluate()  # before the (N, D, H, W) weights exist: the two are not held together
    _save_texels(target, folder, "optimized", optimized)
    weights = model.weights().detach()
    indices, final_img = _quantize_and_render(target, weights, inks, cfg, cfg.eval_spp, eval_seed, quant_seed,
                                              fixed)
    final = {"image": final_img.numpy(), **score(final_img)}
    _save_texels(target, folder, "final", final["image"])
    if target.kind == "slab" and target.faces == 2:
        final["bottom"] = _score(final_img[1], target.target[1])
    ta_io.atomic_write_bytes(os.path.join(folder, "mixture.npz"), _npz_bytes(
        weights=np.asarray(weights.numpy(), np.float32), inks=np.array(inks.names), voxel_size_mm=cfg.voxel_size))
    save_index_volume(os.path.join(folder, "quantized.npz"), indices, inks, cfg.printer_dpi)
    export_slices(indices, inks, os.path.join(folder, "slices"))
    _plots(folder, rows, baseline, weights, inks, cfg, target, final, remap)
    view_seconds = 0.0
    if target.kind == "object":
        texel_de = np.asarray(delta_e_2000(torch.as_tensor(final["image"]).double(), target.target.double()))
        view_seconds = _object_views(folder, target, indices, inks, cfg, eval_seed, log, texel_de)

    opt_rows = [r for r in rows if r["iteration"] > 0]
    summary = {
        "kind": target.kind,
        "iterations": cfg.iterations,
        "wall_s": rows[-1]["wall_s"],
        "seconds_per_iteration": (rows[-1]["wall_s"] / max(1, len(opt_rows))) if opt_rows else None,
        **target.describe(), "spp": cfg.spp, "eval_spp": cfg.eval_spp,
        "final_quantized": {k: v for k, v in final.items() if k != "image"},
        "optimized_continuous": score(optimized),
        "baseline_naive_extrusion": None if baseline is None else {k: v for k, v in baseline.items() if k != "image"},
        "baseline_remap_25d": None if remap is None else {k: v for k, v in remap.items() if k != "image"},
        "initial": {k: rows[0][k] for k in ("dE00_mean", "dE00_p95", "dE76_mean") if k in rows[0]},
        "loss_first_last": [rows[0]["loss"], rows[-1]["loss"]],
        "quantized_shape_dhw": list(indices.shape), "printer_dpi": list(cfg.printer_dpi),
        "parameters": int(model.logits.numel()), "views_s": view_seconds,
    }
    ta_io.write_json(os.path.join(folder, "summary.json"), summary)
    naive_text = "" if baseline is None else \
        f", naive extrusion {baseline['dE00_mean']:.2f}/{baseline['dE00_p95']:.2f}"
    remap_text = "" if remap is None else f", 2.5D remapped {remap['dE00_mean']:.2f}/{remap['dE00_p95']:.2f}"
    log(f"optimize_print: {cfg.iterations} iterations in {summary['wall_s']:.1f} s; CIEDE2000 mean/p95: "
        f"final (quantised) {final['dE00_mean']:.2f}/{final['dE00_p95']:.2f}{naive_text}{remap_text} -> {folder}")
    return summary


def _load_inks(spec):
    if isinstance(spec, str):
        if spec.lower().endswith(".json"):
            return InkSet.load_json(spec)
        spec = [s.strip() for s in spec.split(",") if s.strip()]
    return InkSet.from_names(list(spec))


def _npz_bytes(**arrays):
    buffer = _io.BytesIO()
    np.savez_compressed(buffer, **arrays)
    return buffer.getvalue()
