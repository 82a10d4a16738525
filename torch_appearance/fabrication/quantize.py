"""Probabilistic ink quantisation (Nindel et al. 2021, §4.7): mixture volume → one ink per printer micro-voxel.

The optimisation grid (macro voxels, cubic, edge s mm) is resampled to the printer's native grid (default
600 × 300 × 940 DPI in x, y, z). Both grids cover the same physical box W·s × H·s × D·s mm (x ↔ W, y ↔ H,
z ↔ D, layer 0 at the bottom, as in :func:`torch_appearance.render_texels`). Each micro-voxel takes the macro
voxel that contains its centre (works for non-integer factors) and draws one ink from that voxel's mixture.
"""
import math
import numbers
from collections.abc import Sequence

import numpy as np
import torch

from ..checks import check_positive, is_real

__all__ = ["PRINTER_DPI", "micro_voxel_size", "micro_grid_shape", "micro_grid_pitch", "source_index",
           "resample_nearest", "quantize_mixture", "iter_quantized", "HALFTONES", "hold_fixed_fractions",
           "index_volume_to_weights"]

#: Native resolution of Stratasys PolyJet printers (J7/J8 family) in dots per inch along (x, y, z).
PRINTER_DPI = (600, 300, 940)

_MM_PER_INCH = 25.4
_CHUNK = 1 << 22  # micro-voxels per sampling chunk (bounds the temporaries to ~100 MB)


def _check_dpi(printer_dpi, name="printer_dpi"):
    if isinstance(printer_dpi, (str, bytes)) or not isinstance(printer_dpi, (Sequence, np.ndarray)):
        raise TypeError(f"{name}: expected three numbers (x, y, z) in dots per inch, got {type(printer_dpi).__name__}")
    values = list(printer_dpi)
    if len(values) != 3 or not all(is_real(v) for v in values):
        raise ValueError(f"{name}: expected three numbers (x, y, z) in dots per inch, got {printer_dpi!r}")
    values = tuple(float(v) for v in values)
    if not all(math.isfinite(v) and v > 0 for v in values):
        raise ValueError(f"{name}: expected finite values > 0, got {values!r}")
    return values


def _check_voxel_size(voxel_size_mm):
    return check_positive("voxel_size_mm", voxel_size_mm)


def micro_voxel_size(printer_dpi=PRINTER_DPI):
    """Nominal printer voxel edges ``(sx, sy, sz)`` in mm: 25.4 / dpi per axis (x, y, z)."""
    return tuple(_MM_PER_INCH / v for v in _check_dpi(printer_dpi))


def micro_grid_shape(shape, voxel_size_mm, printer_dpi=PRINTER_DPI):
    """Printer-grid counts ``(Dz, Hy, Wx)`` covering the box of a ``(D, H, W)`` grid of cubic voxels.

    Each count is ``round(extent_mm · dpi / 25.4)`` (halves round up), at least 1. The actual micro pitch per
    axis is ``extent / count``, within half a micro voxel of the nominal 25.4 / dpi over the whole extent.

    Args:
        shape: macro grid ``(D, H, W)``.
        voxel_size_mm: macro voxel edge s in mm.
        printer_dpi: ``(x, y, z)`` dots per inch.
    """
    if isinstance(shape, (str, bytes)) or not isinstance(shape, Sequence) or len(shape) != 3 or not all(
            isinstance(v, numbers.Integral) and not isinstance(v, bool) and v >= 1 for v in shape):
        raise ValueError(f"shape: expected (D, H, W), three ints >= 1, got {shape!r}")
    s = _check_voxel_size(voxel_size_mm)
    dx, dy, dz = _check_dpi(printer_dpi)
    d, h, w = (int(v) for v in shape)
    return tuple(max(1, int(math.floor(n * s * dpi / _MM_PER_INCH + 0.5))) for n, dpi in ((d, dz), (h, dy), (w, dx)))


def micro_grid_pitch(shape, voxel_size_mm, printer_dpi=PRINTER_DPI):
    """Actual micro-voxel edges ``(sx, sy, sz)`` in mm of the grid of :func:`micro_grid_shape`: extent / count.

    Use these (not the nominal :func:`micro_voxel_size`) to render a quantised volume over exactly the macro box;
    they differ from 25.4 / dpi by the rounding of the counts (e.g. 12 layers of 25.4/300 mm: 38 layers of
    0.02675 mm instead of 0.02702 mm).
    """
    dz, hy, wx = micro_grid_shape(shape, voxel_size_mm, printer_dpi)
    d, h, w = (int(v) for v in shape)
    s = float(voxel_size_mm)
    return (w * s / wx, h * s / hy, d * s / dz)


def source_index(n_source, n_target):
    """For a target grid of ``n_target`` cells over the same interval as ``n_source`` cells: the source cell
    containing each target cell's centre, ``floor((i + ½) · n_source / n_target)``, computed in exact integers.

    Returns:
        ``int64`` array of shape ``(n_target,)`` with values in ``[0, n_source)``, non-decreasing.
    """
    for name, v in (("n_source", n_source), ("n_target", n_target)):
        if not isinstance(v, numbers.Integral) or isinstance(v, bool) or v < 1:
            raise ValueError(f"{name}: expected an int >= 1, got {v!r}")
    i = np.arange(int(n_target), dtype=np.int64)
    return ((2 * i + 1) * int(n_source)) // (2 * int(n_target))


def resample_nearest(volume, out_shape):
    """Nearest-cell resampling of the last three axes onto ``out_shape`` over the same box.

    Each output cell takes the input cell containing its centre (:func:`source_index` per axis). Useful to put
    an anisotropic printer-resolution index volume onto a cubic grid for rendering.

    Args:
        volume: ``(..., D, H, W)`` ndarray or tensor.
        out_shape: ``(D', H', W')``.

    Returns:
        ``(..., D', H', W')`` of the same type and dtype.
    """
    if not isinstance(volume, (np.ndarray, torch.Tensor)) or volume.ndim < 3:
        raise ValueError(f"volume: expected an ndarray or tensor with at least 3 dimensions (..., D, H, W), "
                         f"got {type(volume).__name__} {tuple(getattr(volume, 'shape', ()))}")
    if isinstance(out_shape, (str, bytes)) or not isinstance(out_shape, Sequence) or len(out_shape) != 3:
        raise ValueError(f"out_shape: expected (D', H', W'), got {out_shape!r}")
    iz, iy, ix = (source_index(n_in, n_out) for n_in, n_out in zip(volume.shape[-3:], out_shape))
    if isinstance(volume, torch.Tensor):
        iz, iy, ix = (torch.from_numpy(a).to(volume.device) for a in (iz, iy, ix))
    return volume[..., iz[:, None, None], iy[None, :, None], ix[None, None, :]]


def _weights_numpy(weights):
    """The checked (N, D, H, W) weights as one float64 ndarray (see :func:`_weight_layers`)."""
    layer, shape = _weight_layers(weights)
    return np.stack([layer(z) for z in range(shape[1])], axis=1)


def _weight_layers(weights):
    """Check (N, D, H, W) mixture weights and return ``(layer, shape)``: ``layer(z)`` is macro layer z as a float64
    (N, H, W) ndarray. The checks and the conversion go one layer at a time, so the float64 copy of the whole
    volume (8 bytes per ink and voxel: 2.3 GB for 5 inks on 58 M voxels) is never held."""
    if isinstance(weights, torch.Tensor):
        if not weights.is_floating_point():
            raise TypeError(f"weights: expected a floating-point dtype, got {weights.dtype}")
        weights = weights.detach().cpu()

        def layer(z):
            return weights[:, z].to(torch.float64).numpy()
    elif isinstance(weights, np.ndarray):
        if not np.issubdtype(weights.dtype, np.floating):
            raise TypeError(f"weights: expected a floating-point dtype, got {weights.dtype}")

        def layer(z):
            return weights[:, z].astype(np.float64)
    else:
        raise TypeError(f"weights: expected a torch.Tensor or numpy.ndarray of shape (N, D, H, W), "
                        f"got {type(weights).__name__}")
    if weights.ndim != 4 or min(weights.shape) < 1:
        raise ValueError(f"weights: expected shape (N, D, H, W) with all sizes >= 1, got {tuple(weights.shape)}")
    if weights.shape[0] > 256:
        raise ValueError(f"weights: at most 256 inks fit uint8 material indices, got N = {weights.shape[0]}")
    n_bad = bad = 0
    low, high, minimum = math.inf, -math.inf, math.inf
    for z in range(weights.shape[1]):
        w = layer(z)
        n_bad += int(w.size - np.isfinite(w).sum())
        if n_bad:
            continue
        minimum = min(minimum, float(w.min()))
        total = w.sum(0)
        off = np.abs(total - 1.0) > 1e-3
        bad += int(off.sum())
        low, high = min(low, float(total.min())), max(high, float(total.max()))
    if n_bad:
        raise ValueError(f"weights: expected finite values, got {n_bad} NaN/Inf entries")
    if minimum < 0:
        raise ValueError(f"weights: expected weights >= 0, got minimum {minimum:g}")
    if bad:
        raise ValueError(f"weights: expected per-voxel sums of 1 (mixture weights, shape (N, D, H, W)), got sums in "
                         f"[{low:.6g}, {high:.6g}] ({bad} voxel(s) off by more than 1e-3)")
    return layer, tuple(weights.shape)


def quantize_mixture(weights, voxel_size_mm, printer_dpi=PRINTER_DPI, seed=0, halftone="random"):
    """Draw one ink per printer micro-voxel from the mixture of the macro voxel containing its centre.

    The micro grid covers the macro box (W·s × H·s × D·s mm) with ``micro_grid_shape`` cells; micro cell
    (k, j, i) maps to macro voxel ``(floor(z_k / s), floor(y_j / s), floor(x_i / s))`` of its centre, exact
    for non-integer factors. Its ink is the first n with ``u < c_n``, where c is the macro voxel's normalised
    cumulative mixture and u the micro-voxel's threshold in [0, 1):

    * ``halftone="random"`` (the paper's choice): u is one uniform draw of
      ``numpy.random.Generator(PCG64(seed)).random()`` per micro-voxel in C order, so ``P(ink n) = ρ_n / Σρ``
      exactly, independently per micro-voxel;
    * ``halftone="blue-noise"``: u is a tiled 3D blue-noise threshold volume (:func:`.halftone.blue_noise_thresholds`,
      shifted by ``seed``): each ink still takes its fraction ρ_n / Σρ of a region of constant mixture, but its
      micro-voxels are spread evenly instead of clumping by chance (less visible grain).

    Inks of weight 0 are never drawn. The volume is built layer block by layer block
    (:func:`iter_quantized`); the random stream is the same whatever the block size.

    Args:
        weights: (N, D, H, W) mixture weights (tensor or ndarray, floating point), >= 0, per-voxel sums within
            1e-3 of 1 (they are renormalised exactly). N <= 256.
        voxel_size_mm: macro voxel edge s in mm (cubic voxels, as in the optimisation).
        printer_dpi: ``(x, y, z)`` printer resolution in dots per inch.
        seed: int >= 0, the random seed (the pattern's shift for ``"blue-noise"``).
        halftone: ``"random"`` or ``"blue-noise"`` (:data:`HALFTONES`).

    Returns:
        ``numpy.ndarray`` ``uint8`` of shape ``(Dz, Hy, Wx)`` = ``micro_grid_shape((D, H, W), ...)``: ink
        (material) indices, layer 0 at the bottom (z = 0), row j ↔ y, column i ↔ x.

    Raises:
        TypeError, ValueError: naming the argument.

    Example:
        >>> from torch_appearance.fabrication import InkSet
        >>> from torch_appearance.nn import MaterialMixture
        >>> rho = MaterialMixture(InkSet.from_names(), (12, 16, 16)).weights()
        >>> quantize_mixture(rho, 25.4 / 300).shape     # at 600 × 300 × 940 DPI
        (38, 16, 32)
    """
    blocks = iter_quantized(weights, voxel_size_mm, printer_dpi, seed, halftone)
    out = np.empty(blocks.shape, dtype=np.uint8)
    for z0, block in blocks:
        out[z0:z0 + len(block)] = block
    return out


#: The halftoning options of :func:`quantize_mixture` and :func:`iter_quantized`.
HALFTONES = ("random", "blue-noise")


class iter_quantized:  # noqa: N801 - used like a generator function
    """The micro layers of :func:`quantize_mixture`, block by block, bottom to top, without the whole volume.

    Iterating yields ``(z0, block)``: ``block`` a ``uint8`` ``(k, Hy, Wx)`` array of micro layers ``z0 .. z0+k-1``
    (each block lies in one macro layer and holds at most ~4 M micro-voxels); the blocks cover every layer once,
    in order, and equal the slices of :func:`quantize_mixture`'s volume bit for bit. ``shape`` is the whole
    ``(Dz, Hy, Wx)``. Peak memory: one macro layer of the mixture in float64 and one block, whatever the number
    of layers. Arguments as for :func:`quantize_mixture`; they are checked when the object is made.
    """

    def __init__(self, weights, voxel_size_mm, printer_dpi=PRINTER_DPI, seed=0, halftone="random"):
        self._layer, (self._n, d, h, wd) = _weight_layers(weights)
        if isinstance(seed, bool) or not isinstance(seed, numbers.Integral) or seed < 0:
            raise ValueError(f"seed: expected an int >= 0, got {seed!r}")
        if halftone not in HALFTONES:
            raise ValueError(f"halftone: expected one of {HALFTONES}, got {halftone!r}")
        self.seed, self.halftone, self.macro_shape = int(seed), halftone, (d, h, wd)
        self.shape = micro_grid_shape((d, h, wd), voxel_size_mm, printer_dpi)

    def __len__(self):
        return self.shape[0]

    def __iter__(self):
        d, h, wd = self.macro_shape
        dz, hy, wx = self.shape
        iz, iy, ix = source_index(d, dz), source_index(h, hy), source_index(wd, wx)
        if self.halftone == "random":
            rng = np.random.Generator(np.random.PCG64(self.seed))
        else:
            from .halftone import blue_noise_thresholds
            thresholds_of = blue_noise_thresholds(self.shape, self.seed)
        layers = max(1, _CHUNK // (hy * wx))
        starts = np.searchsorted(iz, np.arange(d + 1))    # micro layers [starts[z], starts[z+1]) lie in macro layer z
        for z in range(d):                                # loop over macro layers, then blocks of micro layers
            if starts[z] == starts[z + 1]:
                continue
            # normalised cumulative weights of layer z, the thresholds c_0..c_{N-2} (c_{N-1} = 1 is implicit);
            # x / x = 1 exactly for trailing zeros. One layer at a time: the same numbers as over the whole volume.
            cdf = np.cumsum(self._layer(z), axis=0)
            cdf = cdf[:-1] / cdf[-1:]                                  # (N-1, H, W)
            cuts = cdf[:, iy[:, None], ix[None, :]]                    # (N-1, Hy, Wx): lateral upsampling of layer z
            for z0 in range(starts[z], starts[z + 1], layers):
                z1 = min(starts[z + 1], z0 + layers)
                if self.halftone == "random":
                    u = rng.random((z1 - z0, hy, wx))     # C order over the whole volume, block after block
                else:
                    u = thresholds_of(z0, z1)
                index = np.zeros(u.shape, dtype=np.uint8)
                for k in range(self._n - 1):              # loop over inks: count the thresholds u has passed
                    index += u >= cuts[k]
                yield int(z0), index


def hold_fixed_fractions(indices, weights, voxel_size_mm, fixed, printer_dpi=PRINTER_DPI, seed=0):
    """Make fixed ink fractions exact in a quantised volume (translucency constraints, paper §5.2).

    Independent draws give a fixed ink its fraction f only in expectation. For each constraint, the micro-voxels
    whose macro voxel lies in its mask get exactly ``round(f · n)`` of that ink (positions uniform at random); the
    others in the region that held it are drawn again from their macro voxel's mixture without it.

    Args:
        indices: (Dz, Hy, Wx) uint8 from :func:`quantize_mixture` (values 255 = void are left alone); modified
            copy returned.
        weights: the (N, D, H, W) mixture that was quantised.
        voxel_size_mm, printer_dpi: as for :func:`quantize_mixture`.
        fixed: sequence of (ink index, fraction, (D, H, W) bool mask).
        seed: int >= 0.

    Returns:
        The corrected (Dz, Hy, Wx) uint8 volume.
    """
    w = _weights_numpy(weights)
    n, d, h, wd = w.shape
    dz, hy, wx = indices.shape
    if (dz, hy, wx) != micro_grid_shape((d, h, wd), voxel_size_mm, printer_dpi):
        raise ValueError(f"indices: expected the micro grid {micro_grid_shape((d, h, wd), voxel_size_mm, printer_dpi)}"
                         f" of the weights, got {indices.shape}")
    iz, iy, ix = source_index(d, dz), source_index(h, hy), source_index(wd, wx)
    rng = np.random.Generator(np.random.PCG64(int(seed)))
    out = indices.copy()
    for ink, fraction, mask in fixed:
        mask = np.asarray(mask, dtype=bool)
        region = mask[iz[:, None, None], iy[None, :, None], ix[None, None, :]] & (out != 255)
        where = np.flatnonzero(region)
        want = int(round(fraction * len(where)))
        chosen = np.zeros(len(where), dtype=bool)
        chosen[rng.permutation(len(where))[:want]] = True
        flat = out.reshape(-1)
        redraw = where[~chosen & (flat[where] == ink)]
        flat[where[chosen]] = ink
        if len(redraw):
            k, j, i = np.unravel_index(redraw, out.shape)
            rest = w[:, iz[k], iy[j], ix[i]].T.copy()          # (R, N) mixtures of their macro voxels
            rest[:, ink] = 0.0
            total = rest.sum(1, keepdims=True)
            alone = total[:, 0] <= 0                           # only the fixed ink: keep it (f = 1 regions)
            cdf = np.cumsum(rest / np.where(total > 0, total, 1.0), axis=1)
            u = rng.random(len(redraw))
            draw = (u[:, None] >= cdf[:, :-1]).sum(1).astype(np.uint8)
            flat[redraw] = np.where(alone, ink, draw)
    return out


def index_volume_to_weights(indices, n_inks, dtype=torch.float32):
    """One-hot weights of a material-index volume (e.g. for :func:`torch_appearance.nn.mix_inks`).

    Args:
        indices: (Dz, Hy, Wx) integer ndarray or tensor, values in [0, n_inks).
        n_inks: number of inks N.
        dtype: floating dtype of the result.

    Returns:
        ``torch.Tensor`` (N, Dz, Hy, Wx) with exactly one 1 per voxel, the rest 0.
    """
    if isinstance(n_inks, bool) or not isinstance(n_inks, numbers.Integral) or n_inks < 1:
        raise ValueError(f"n_inks: expected an int >= 1, got {n_inks!r}")
    if isinstance(indices, np.ndarray):
        if not np.issubdtype(indices.dtype, np.integer):
            raise TypeError(f"indices: expected an integer dtype, got {indices.dtype}")
        indices = torch.from_numpy(indices.astype(np.int64))
    elif isinstance(indices, torch.Tensor):
        if indices.is_floating_point() or indices.is_complex() or indices.dtype == torch.bool:
            raise TypeError(f"indices: expected an integer dtype, got {indices.dtype}")
        indices = indices.long()
    else:
        raise TypeError(f"indices: expected an ndarray or tensor of shape (Dz, Hy, Wx), got {type(indices).__name__}")
    if indices.dim() != 3:
        raise ValueError(f"indices: expected shape (Dz, Hy, Wx), got {tuple(indices.shape)}")
    if indices.numel() and (int(indices.min()) < 0 or int(indices.max()) >= n_inks):
        raise ValueError(f"indices: expected values in [0, {n_inks}), got range "
                         f"[{int(indices.min())}, {int(indices.max())}]")
    return torch.nn.functional.one_hot(indices, int(n_inks)).permute(3, 0, 1, 2).to(dtype).contiguous()
