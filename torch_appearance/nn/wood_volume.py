"""Procedural wood as a participating medium: σ_t and albedo grids from a :class:`~torch_appearance.nn.WoodModel`.

Thesis §1.11 and the wood paper §4.2: the density follows the lateness of growth ℓ = frac(G) (early wood light and
thin-walled, late wood dense), σ_t = σ_early + (σ_late − σ_early)·ℓ, the same in every channel (defaults
6.5 and 16.0 mm⁻¹, from Inverse Adding-Doubling on Sugi wood); the single-scattering albedo per RGB channel comes
from the model's colour map (the fitted surface colour at that point of the tree) through the surface-colour →
albedo mapping of :mod:`torch_appearance.render.albedo_mapping` (our tracer's table by default, or the
Elek et al. 2017 polynomial).

``extruded=True`` gives the naive comparison of the paper's Fig. 6: every voxel takes the value of the board surface
point above it (u, v, 0), i.e. the surface pattern extruded along the board normal into the depth, instead of
following the growth surfaces below the surface.

World → board: a voxel centre x (world mm) is evaluated at the board-frame point b = R·x + t (``world_to_board``,
default identity: world = board frame (u, v, w), w pointing into the board away from the photographer).

Example:
    >>> import torch
    >>> from torch_appearance.nn import WoodModel
    >>> from torch_appearance.nn.wood_volume import wood_volume
    >>> vol = wood_volume(WoodModel(ring_scale_mm=2.0), (4, 8, 8), 0.25)
    >>> vol.sigma_t.shape, bool(vol.sigma_t.min() >= 6.5), bool(vol.sigma_t.max() <= 16.0)
    (torch.Size([3, 4, 8, 8]), True, True)
"""
from __future__ import annotations

from dataclasses import dataclass, field
import json
import math
import os

import numpy as np
import torch

from ..render.albedo_mapping import albedo_from_colour
from ..checks import check_int, check_real, check_vector3
from ..render.scene import voxel_edges

__all__ = ["WoodVolume", "wood_volume", "load_wood_fit", "FIT_FILES", "SIGMA_EARLY", "SIGMA_LATE"]

#: Extinction of early and late wood (mm⁻¹), the wood paper §4.2.
SIGMA_EARLY = 6.5
SIGMA_LATE = 16.0
#: Files of a ``ta-fit-wood`` run folder that :func:`load_wood_fit` needs.
FIT_FILES = ("model.json", "model.pt", "params.json")


@dataclass
class WoodVolume:
    """The medium grids of a wood volume and what they were made from.

    Attributes:
        sigma_t: (3, D, H, W) extinction, mm⁻¹, equal in the three channels.
        albedo: (3, D, H, W) single-scattering albedo in [0, 1].
        lateness: (D, H, W) mean lateness ℓ of the voxel's samples in [0, 1).
        colour: (3, D, H, W) surface colour (linear RGB) the albedo was mapped from.
        info: settings and counts (``out_of_gamut``: colour entries darker than the mapping's C(0), mapped to 0).
    """
    sigma_t: torch.Tensor
    albedo: torch.Tensor
    lateness: torch.Tensor
    colour: torch.Tensor
    info: dict = field(default_factory=dict)


def _grid_shape(grid_shape):
    if not isinstance(grid_shape, (tuple, list)) or len(grid_shape) != 3:
        raise ValueError(f"grid_shape: expected (D, H, W), got {grid_shape!r}")
    return tuple(check_int("grid_shape", n, lo=1) for n in grid_shape)


def _world_to_board(world_to_board, dtype):
    if world_to_board is None:
        return torch.eye(3, dtype=dtype), torch.zeros(3, dtype=dtype)
    if not isinstance(world_to_board, (tuple, list)) or len(world_to_board) != 2:
        raise TypeError(f"world_to_board: expected a pair (R (3, 3), t (3,)) or None, got {type(world_to_board).__name__}")
    rot = torch.as_tensor(np.asarray(world_to_board[0], dtype=np.float64))
    if rot.shape != (3, 3):
        raise ValueError(f"world_to_board: expected R of shape (3, 3), got {tuple(rot.shape)}")
    if not torch.allclose(rot.T @ rot, torch.eye(3, dtype=rot.dtype), atol=1e-6) or abs(float(torch.det(rot)) - 1) > 1e-6:
        raise ValueError("world_to_board: expected R a proper rotation (RᵀR = I, det R = 1)")
    t = torch.tensor(check_vector3("world_to_board", world_to_board[1]), dtype=torch.float64)
    return rot.to(dtype), t.to(dtype)


def wood_volume(model, grid_shape, voxel_size, origin=(0.0, 0.0, 0.0), *, world_to_board=None, extruded=False,
                sigma_early=SIGMA_EARLY, sigma_late=SIGMA_LATE, mapping="table", g=0.4, ior=1.5, supersample=1,
                dtype=torch.float32, chunk=1 << 20):
    """σ_t and albedo grids of a wood model over a voxel domain.

    Args:
        model: a :class:`~torch_appearance.nn.WoodModel` (fitted or synthetic); evaluated without gradients.
        grid_shape: (D, H, W) voxels; voxel (k, j, i) has its centre at origin + ((i+½)·sx, (j+½)·sy, (k+½)·sz).
        voxel_size: edge in mm, or the three edges (x, y, z).
        origin: world position (mm) of the grid corner.
        world_to_board: optional (R, t): board-frame point b = R·x + t of a world point x (R a rotation).
        extruded: evaluate every voxel at its board-surface point (u, v, 0) instead of (u, v, w).
        sigma_early, sigma_late: extinction (mm⁻¹) at lateness 0 and 1; 0 <= sigma_early, sigma_late.
        mapping: surface colour → albedo: ``"table"`` (our tracer, needs a table for (g, ior)) or ``"elek"``.
        g, ior: the phase function and boundary the volume will be rendered with (they select the table).
        supersample: n samples per axis in each voxel (n³ in all); σ_t is their mean, albedo the σ_t-weighted
            mean (scattering over extinction of the voxel).
        dtype: float32 or float64 grids.
        chunk: points evaluated at once (memory).

    Returns:
        :class:`WoodVolume`.

    Raises:
        TypeError / ValueError: bad arguments (name, expectation and value in the message).
    """
    if not all(hasattr(model, name) for name in ("evaluate", "color_map")):
        raise TypeError(f"model: expected a WoodModel, got {type(model).__name__}")
    shape = _grid_shape(grid_shape)
    sx, sy, sz = voxel_edges(voxel_size)
    ox, oy, oz = check_vector3("origin", origin)
    s_early = check_real("sigma_early", sigma_early, lo=0.0)
    s_late = check_real("sigma_late", sigma_late, lo=0.0)
    n = check_int("supersample", supersample, lo=1)
    chunk = check_int("chunk", chunk, lo=1)
    if not isinstance(extruded, bool):
        raise TypeError(f"extruded: expected a bool, got {type(extruded).__name__}")
    if dtype not in (torch.float32, torch.float64):
        raise TypeError(f"dtype: expected torch.float32 or torch.float64, got {dtype!r}")
    if mapping not in ("table", "elek"):
        raise ValueError(f"mapping: expected 'table' or 'elek', got {mapping!r}")
    rot, trans = _world_to_board(world_to_board, torch.float64)

    d, h, w = shape
    sub = (torch.arange(n, dtype=torch.float64) + 0.5) / n                      # sample offsets in a voxel
    zs = oz + sz * (torch.arange(d, dtype=torch.float64)[:, None] + sub).reshape(-1)
    ys = oy + sy * (torch.arange(h, dtype=torch.float64)[:, None] + sub).reshape(-1)
    xs = ox + sx * (torch.arange(w, dtype=torch.float64)[:, None] + sub).reshape(-1)
    lateness = torch.empty(d * n, h * n, w * n, dtype=torch.float64)
    colour = torch.empty(3, d * n, h * n, w * n, dtype=torch.float64)
    plane = h * n * w * n
    yy, xx = torch.meshgrid(ys, xs, indexing="ij")
    rows = max(1, chunk // plane)
    mdtype = model.color_map.dtype
    with torch.no_grad():
        for k0 in range(0, d * n, rows):
            zz = zs[k0:k0 + rows]
            pts = torch.stack([xx.expand(len(zz), -1, -1), yy.expand(len(zz), -1, -1),
                               zz[:, None, None].expand(-1, h * n, w * n)], -1).reshape(-1, 3)
            board = pts @ rot.T + trans
            if extruded:
                board = board[:, :2]
            out = model.evaluate(board.to(mdtype), board=True)
            lateness[k0:k0 + rows] = out["lateness"].double().reshape(len(zz), h * n, w * n)
            colour[:, k0:k0 + rows] = out["rgb"].double().T.reshape(3, len(zz), h * n, w * n)
    lo, hi = float(colour.min()), float(colour.max())
    if lo < 0 or hi > 1:
        raise ValueError(f"model: expected colour-map values in [0, 1] (surface reflectances), got range "
                         f"[{lo:g}, {hi:g}]")
    sigma = s_early + (s_late - s_early) * lateness                              # (D·n, H·n, W·n)
    alpha, out_of_gamut = albedo_from_colour(colour.permute(1, 2, 3, 0), mapping=mapping, g=g, ior=ior,
                                             return_gamut=True)
    alpha = alpha.permute(3, 0, 1, 2)

    def pool(x):  # mean over the n³ samples of each voxel: (..., D·n, H·n, W·n) → (..., D, H, W)
        lead = x.shape[:-3]
        return x.reshape(*lead, d, n, h, n, w, n).mean(dim=(-5, -3, -1))

    sigma_v = pool(sigma)
    scatter_v = pool(sigma[None] * alpha)
    albedo_v = torch.where(sigma_v[None] > 0, scatter_v / sigma_v[None].clamp_min(1e-300), pool(alpha))
    info = {"grid_shape": list(shape), "voxel_size_mm": [sx, sy, sz], "origin_mm": [ox, oy, oz],
            "extruded": extruded, "sigma_early": s_early, "sigma_late": s_late, "mapping": mapping, "g": g,
            "ior": ior, "supersample": n, "out_of_gamut": int(out_of_gamut),
            "colour_range": [lo, hi], "albedo_range": [float(albedo_v.min()), float(albedo_v.max())],
            "sigma_t_range": [float(sigma_v.min()), float(sigma_v.max())]}
    return WoodVolume(sigma_t=sigma_v.expand(3, -1, -1, -1).to(dtype).contiguous(),
                      albedo=albedo_v.clamp(0.0, 1.0).to(dtype).contiguous(),
                      lateness=pool(lateness).to(dtype), colour=pool(colour).to(dtype), info=info)


def load_wood_fit(fit_dir):
    """Load the fitted model of a ``ta-fit-wood`` run folder.

    Args:
        fit_dir: the run folder; it must hold ``model.json``, ``model.pt`` (:meth:`WoodModel.save`) and
            ``params.json`` (``pixel_size_mm``, ``image_hw``).

    Returns:
        (model, board) where board = {"pixel_size_mm", "height", "width", "extent_mm": (u, v) size of the photo}.

    Raises:
        ValueError: not a folder, files missing or unreadable parameters (the message lists what is missing).
    """
    from .wood import WoodModel

    if not isinstance(fit_dir, (str, os.PathLike)) or str(fit_dir) == "":
        raise TypeError(f"fit_dir: expected a path to a ta-fit-wood run folder, got {fit_dir!r}")
    if not os.path.isdir(fit_dir):
        raise ValueError(f"fit_dir: expected a run folder of ta-fit-wood, got {str(fit_dir)!r}, which is not "
                         f"a folder")
    missing = [f for f in FIT_FILES if not os.path.isfile(os.path.join(fit_dir, f))]
    if missing:
        raise ValueError(f"fit_dir: expected a run folder of ta-fit-wood holding {', '.join(FIT_FILES)}, "
                         f"got {str(fit_dir)!r} without {', '.join(missing)}")
    try:
        with open(os.path.join(fit_dir, "params.json"), encoding="utf-8") as fh:
            params = json.load(fh)
        pixel = float(params["pixel_size_mm"])
        height, width = (int(v) for v in params["image_hw"])
    except (ValueError, KeyError, TypeError) as error:
        raise ValueError(f"fit_dir: expected params.json with pixel_size_mm and image_hw in {str(fit_dir)!r}, "
                         f"got an unreadable file ({type(error).__name__}: {error})") from None
    if not (math.isfinite(pixel) and pixel > 0 and height > 0 and width > 0):
        raise ValueError(f"fit_dir: expected pixel_size_mm > 0 and image_hw > 0 in params.json, got "
                         f"{pixel}, {[height, width]}")
    model = WoodModel.load(os.path.join(fit_dir, "model"))
    return model, {"pixel_size_mm": pixel, "height": height, "width": width,
                   "extent_mm": (width * pixel, height * pixel)}
