"""A slab as the print target: images of its top (and bottom) face, texel [j, i] = voxel column (j, i)."""
import dataclasses
import os

import numpy as np
import torch

from ... import io as ta_io
from ..runs import check_memory
from .baselines import naive_extrusion, render_quantized, render_slab
from .rendering import on_device
from .report import heatmap_figure
from .run_folder import save_image, score
from .target_images import load_target

__all__ = ["SlabTarget", "slab_texel_grid", "slab_texels", "slab_memory_bytes", "MIN_SLAB_TEXELS"]


def slab_texel_grid(faces_rgb, depth):
    """Place face texel images on the voxel grid for the appearance losses.

    Args:
        faces_rgb: (F, H, W, 3) texel colours, F = 1 (top) or 2 (top, bottom).
        depth: D, voxel layers of the slab (top face = layer D − 1, bottom face = layer 0).

    Returns:
        (3, D, H, W) grid (zeros off the faces) and the (D, H, W) bool texel mask.

    Example:
        >>> grid, mask = slab_texel_grid(torch.ones(2, 4, 5, 3), depth=3)
        >>> grid.shape, mask.sum(dim=(1, 2)).tolist()
        (torch.Size([3, 3, 4, 5]), [20, 0, 20])
    """
    f, h, w, _ = faces_rgb.shape
    if f == 2 and depth < 2:
        raise ValueError(f"thickness_mm: a two-sided target needs at least 2 voxel layers, got {depth}")
    grid = faces_rgb.new_zeros(3, depth, h, w)
    mask = torch.zeros(depth, h, w, dtype=torch.bool, device=faces_rgb.device)
    layers = [depth - 1, 0][:f]
    for k, layer in enumerate(layers):
        grid = grid.index_copy(1, torch.tensor([layer], device=faces_rgb.device),
                               faces_rgb[k].permute(2, 0, 1).unsqueeze(1))
        mask[layer] = True
    return grid, mask


#: peak memory of a slab run (the naive baseline, the optimisation and the quantised render), measured on slabs of
#: 128² to 640² × 12 voxels with 5 inks: about 0.35 GiB + (300 + 16 × inks) bytes per voxel (381 at 5 inks; the
#: mixture's logits, their gradient, optimiser state and weights take 16 bytes per ink and voxel)
SLAB_FIXED_BYTES = 0.35 * 2 ** 30
SLAB_BYTES_PER_VOXEL = 300
SLAB_BYTES_PER_INK_VOXEL = 16


#: the fewest texels a side of a slab may have (its losses compare neighbourhoods: SSIM, Sobel): a size that rounds
#: to fewer is refused, not optimised as a 1-texel slab
MIN_SLAB_TEXELS = 4


def slab_texels(cfg, target_hw, warn=None):
    """(H, W) texels of the slab that ``cfg.width_mm``/``cfg.height_mm`` ask for at the voxel pitch, the side not
    given from the target's ``target_hw`` aspect; None when neither is given (the target's own size).

    Args:
        cfg: the :class:`~torch_appearance.pipelines.print.PrintConfig`. target_hw: the target image's (H, W).
        warn: optional ``callable(str)``, told when both sides are given and change the target's aspect by more
            than 2 % (a 3:2 ColorChecker printed square: the slab is what was asked for, its patches are stretched).

    Raises:
        ValueError: naming ``width_mm`` or ``height_mm`` (the side given, or the one given that made the other)
            when a side rounds to fewer than :data:`MIN_SLAB_TEXELS` texels, or a size is not > 0.

    Example:
        >>> from torch_appearance.pipelines.print import PrintConfig
        >>> slab_texels(PrintConfig(width_mm=20.0), (42, 62))
        (160, 236)
        >>> slab_texels(PrintConfig(width_mm=0.01), (42, 62))
        Traceback (most recent call last):
        ...
        ValueError: width_mm: a slab 0.01 mm wide is 0 texels at 300 DPI (0.0847 mm); expected at least 4 texels (0.34 mm), or pass a higher dpi=DPI
    """
    if cfg.width_mm is None and cfg.height_mm is None:
        return None
    for name, value in (("width_mm", cfg.width_mm), ("height_mm", cfg.height_mm)):
        if value is not None and not value > 0:
            raise ValueError(f"{name}: expected > 0, got {value}")
    h0, w0 = (int(n) for n in target_hw)
    pitch = cfg.voxel_size
    width = cfg.width_mm if cfg.width_mm is not None else cfg.height_mm * w0 / h0
    height = cfg.height_mm if cfg.height_mm is not None else cfg.width_mm * h0 / w0
    sides = [("width", width, cfg.width_mm), ("height", height, cfg.height_mm)]
    for side, size, given in sorted(sides, key=lambda s: s[2] is None):  # a side given first, then one derived
        texels = round(size / pitch)
        if texels < MIN_SLAB_TEXELS:
            name = f"{side}_mm" if given is not None else ("height_mm" if side == "width" else "width_mm")
            how = "" if given is not None else f" (the {side} at the target's {w0}×{h0} aspect)"
            raise ValueError(f"{name}: a slab {size:.3g} mm {'wide' if side == 'width' else 'high'}{how} is {texels} "
                             f"texels at {cfg.dpi:g} DPI ({pitch:.4f} mm); expected at least {MIN_SLAB_TEXELS} "
                             f"texels ({MIN_SLAB_TEXELS * pitch:.2f} mm), or pass a higher dpi=DPI")
    if warn is not None and cfg.width_mm is not None and cfg.height_mm is not None:
        asked, own = cfg.width_mm / cfg.height_mm, w0 / h0
        if abs(asked / own - 1) > 0.02:
            warn(f"width_mm/height_mm: a {cfg.width_mm:g} × {cfg.height_mm:g} mm slab stretches the target's "
                 f"{w0}×{h0} texels (aspect {own:.2f}) to an aspect of {asked:.2f}; give only one of them to keep the "
                 f"target's aspect")
    return round(height / pitch), round(width / pitch)


def slab_memory_bytes(shape, n_inks):
    """Expected peak memory in bytes of a print run on a (D, H, W) slab with ``n_inks`` inks (see
    :data:`SLAB_BYTES_PER_VOXEL`).

    Example:
        >>> round(slab_memory_bytes((12, 1644, 1644), 5) / 2**30, 1)   # a 1644² photo at 300 DPI, 1 mm thick
        11.8
    """
    d, h, w = (int(n) for n in shape)
    return SLAB_FIXED_BYTES + d * h * w * (SLAB_BYTES_PER_VOXEL + SLAB_BYTES_PER_INK_VOXEL * n_inks)


class SlabTarget:
    """Face texel images of a slab as the optimisation target; the same methods as
    :class:`~torch_appearance.pipelines.print.object_target.ObjectTarget`, so the loop never asks which it holds.

    Args:
        cfg: the run's :class:`~torch_appearance.pipelines.print.PrintConfig` (voxel pitch, thickness, IOR, g,
            gradient seed). inks: the :class:`~torch_appearance.fabrication.InkSet`.
        faces_target: one or two (H, W, 3) linear RGB images (top, bottom).

    Attributes:
        shape: (D, H, W). support: None (every voxel optimised). target: (F, H, W, 3) linear RGB, F = 1 (top) or
        2 (top, bottom). target_grid, mask: the faces on the voxel grid for the losses.
    """
    kind = "slab"
    support = None
    depth_reference = "the top face"

    def __init__(self, cfg, inks, faces_target):
        self.cfg, self.inks = cfg, inks
        self.target = torch.tensor(np.stack(faces_target))  # (F, H, W, 3)
        self.faces = self.target.shape[0]
        self.shape = (cfg.depth, *self.target.shape[1:3])
        self.target_grid, self.mask = slab_texel_grid(self.target, cfg.depth)

    @classmethod
    def from_config(cls, cfg, inks, log=print, available=None):
        """The slab of ``cfg``: top (and bottom) images sized by the image at the voxel pitch or by width/height.

        A slab that would not fit in memory (:func:`slab_memory_bytes` against ``available`` bytes, default what
        the process may use, and on a GPU ``cfg.device``'s free memory) is refused before any resampling or file;
        the log names its size and its memory (the seconds per iteration and the whole job's are logged once an
        iteration has been timed, by the loop)."""
        top = load_target(cfg.target, name="target")
        size = slab_texels(cfg, top.shape[:2])  # a side of fewer than MIN_SLAB_TEXELS texels is refused
        h, w = size or top.shape[:2]
        faces = 1 if cfg.bottom_target is None else 2
        what = (f"a {w}×{h}×{cfg.depth}-voxel slab ({w * cfg.voxel_size:.1f} × {h * cfg.voxel_size:.1f} × "
                f"{cfg.thickness_mm:g} mm at {cfg.dpi:g} DPI)")
        need = slab_memory_bytes((cfg.depth, h, w), len(inks))
        check_memory("target" if size is None else "width_mm/height_mm", need, what,
                     "print a smaller slab (width_mm/height_mm, --width-mm/--height-mm) or optimise at a lower dpi "
                     "(--dpi)", available, device=cfg.device)  # on a GPU its free memory too
        log(f"optimize_print: {what}, {faces * h * w} texels, about {need / 2**30:.1f} GiB of memory")
        if size is not None:
            top = load_target(cfg.target, size=size, name="target")
        faces_target = [top]
        if cfg.bottom_target is not None:
            bottom = load_target(cfg.bottom_target, size=size, name="bottom_target")
            if bottom.shape != top.shape:
                raise ValueError(f"bottom_target: expected the size of the top target {top.shape[:2]}, "
                                 f"got {bottom.shape[:2]} (pass width_mm/height_mm to resample both)")
            faces_target.append(bottom)
        return cls(cfg, inks, faces_target)

    def use(self, inks, cfg):
        """Render with the run's inks (their g) and settings (a target may be shared by runs with other inks)."""
        self.inks, self.cfg = inks, cfg

    # ------------------------------------------------------------------------------------------ rendering
    def render(self, sigma_t, albedo, spp, seed, adjoint=None):
        """(F, H, W, 3) face texel colours (linear RGB) of the medium (3, D, H, W), differentiable (``adjoint``: the
        texels' gradient when known before the render; see :func:`.rendering.render`)."""
        return render_slab(sigma_t, albedo, self.cfg, self.inks, self.faces, spp, seed, adjoint=adjoint)

    def to_grid(self, texels):
        return slab_texel_grid(texels, self.cfg.depth)[0]

    def appearance(self, criterion, texels):
        """``(E, {"E1", "E2", "E3"})`` of the face texels (F, H, W, 3) on the voxel grid (dense path: the faces
        are whole layers, which the grid path filters with per-axis matrices), on the texels' device (the target's
        grid and mask copied there once)."""
        return criterion.forward_parts(self.to_grid(texels), on_device(self, texels.device, "target_grid"),
                                       on_device(self, texels.device, "mask"))

    def evaluation_subset(self, count, seed):
        """A slab's evaluations score every texel of its top face: None."""
        return None

    def scored(self, texels, index=None):
        """The top face is scored (the bottom face is reported separately, :meth:`extra_scores`); a slab has no
        evaluation subset (``index`` None)."""
        if index is not None:
            raise ValueError("index: a slab is scored whole (evaluation_subset is None)")
        return texels[0], self.target[0]

    def extra_scores(self, renders):
        """``{"bottom": scores}`` of a two-sided target's bottom face from evaluation ``renders`` (K, F, H, W, 3),
        else nothing."""
        return {"bottom": score(renders[:, 1], self.target[1])} if self.faces == 2 else {}

    # ------------------------------------------------------------------------------------------ baselines
    def naive_weights(self, inks, cfg):
        """The naive extrusion (N, D, H, W) of the top face and the table's description."""
        return naive_extrusion(self.target[0].numpy(), inks, cfg)

    def quantized_void(self, indices):
        """A slab has no void: ``indices`` unchanged."""
        return indices

    def prepare_quantized(self, indices, printer_dpi):
        """A slab's renders need no preparation: ``indices`` as they are (the object's counterpart is
        :meth:`ObjectTarget.prepare_quantized`)."""
        return indices

    def render_quantized(self, indices, inks, printer_dpi, spp, seed):
        """(F, H, W, 3) face texels of a printer-resolution index volume averaged back to the slab's texels."""
        cfg = dataclasses.replace(self.cfg, printer_dpi=tuple(printer_dpi))
        return render_quantized(indices, inks, cfg, self.shape[1:], self.faces, spp, seed)

    # ------------------------------------------------------------------------------------------ masks
    def voxel_depth(self):
        """(D, H, W) depth of the voxel centres below the top face, mm."""
        d, h, w = self.shape
        depth = (d - 1 - np.arange(d) + 0.5) * self.cfg.voxel_size
        return np.broadcast_to(depth[:, None, None], (d, h, w))

    def image_mask(self, image, name, spec):
        """(D, H, W) bool: the columns of the white texels of an (H, W) mask image of the slab's size."""
        shape = tuple(self.shape)
        if image.shape != shape[1:]:
            raise ValueError(f"fixed: {spec!r}: the mask {name!r} is {image.shape[1]}×{image.shape[0]} pixels, the "
                             f"slab has {shape[2]}×{shape[1]} texels; expected the same size")
        return np.broadcast_to(image[None], shape)

    def material_mask(self, name, spec):
        raise ValueError(f"fixed: {spec!r}: material:NAME masks select parts of a mesh (--mesh); a slab has no "
                         f"materials")

    # ------------------------------------------------------------------------------------------ outputs
    def describe(self):
        return {"grid_dhw": list(self.shape), "faces": self.faces, "texels": self.faces * self.shape[1] * self.shape[2]}

    def inputs(self):
        """What config.json records of the inputs beyond :meth:`describe`: nothing for a slab."""
        return {}

    def save_inputs(self, folder):
        """A slab's inputs are its target images (:meth:`save_texels`): nothing more."""

    def save_texels(self, folder, stem, texels, index=None):
        """``stem.exr`` + ``.png`` of the top face and ``stem_bottom`` of a bottom face (whole faces: ``index``
        None)."""
        if index is not None:
            raise ValueError("index: a slab's faces are saved whole")
        texels = texels.numpy() if isinstance(texels, torch.Tensor) else np.asarray(texels)
        save_image(folder, stem, texels[0])
        if self.faces == 2:
            save_image(folder, f"{stem}_bottom", texels[1])

    def load_texels(self, folder, stem):
        """(F, H, W, 3) float32 texels that :meth:`save_texels` wrote (the ``.exr`` images)."""
        stems = [stem, f"{stem}_bottom"][:self.faces]
        return np.stack([ta_io.read_exr(os.path.join(folder, f"{s}.exr")) for s in stems])

    def ink_usage_by_depth(self, weights):
        """Mean ink fractions (N, D) per layer from the top face down; layer centres (D,) mm below it."""
        w = weights.detach().double().mean((2, 3)).numpy()[:, ::-1]  # (N, D), depth 0 = top layer
        return w, (np.arange(w.shape[1]) + 0.5) * self.cfg.voxel_size

    def figures(self, final):
        """``dE00_heatmap.png``: the final (quantised) top face's CIEDE2000 per texel, free of render noise on
        average (``final["texel_dE00"]``), with the scores of ``final``."""
        return [("dE00_heatmap.png", heatmap_figure(np.asarray(final["texel_dE00"]).reshape(self.target.shape[1:3]),
                                                    final))]

    def views(self, folder, indices, inks, cfg, seed, texel_de, log=print, texel_index=None):
        """A slab has no camera views (its faces are the images); seconds spent: 0."""
        return 0.0
