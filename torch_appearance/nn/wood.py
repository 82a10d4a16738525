"""Procedural solid wood: the growth-field model of Liu et al. (2016) as a differentiable ``nn.Module``.

Thesis ch. 2 (Nindel et al., "Automatic inference of an anatomically meaningful solid wood texture from a single
photograph"), §3.5–3.6. A board (a plane in the log) is placed in *tree space* — a cylindrical system whose z axis
is the stem — by a rigid transform; every point q of tree space has a radius r = |q_xy|, an azimuth
θ_t = atan2(q_y, q_x) and a height z. Growth is distorted by a learnable radial field m_r (and optionally a
tangential one, m_t), eq. 5:

    q' = q + m_r(q)·r̂ + m_t(q)·t̂,      r' = |q'_xy| = sqrt((r + m_r)² + m_t²)     (= r + m_r without m_t)

With ``pith_taper_mm = t > 0`` both displacements fade at the pith, m ← m·(1 − exp(−(r/t)²)): a ring a fraction of
a millimetre round cannot be displaced by a millimetre, so the pith stays at G = 0 and the innermost rings stay
closed ovals (the wood fit uses one ring width).

Lobes (``lobe_shape=(Hθ, Hp)``, ``lobe_radius_mm = R_p``): the innermost rings of a stem are rarely circles; they bulge
into lobes that fade within a few rings. m_r over (z, r) cannot draw them (it has no azimuth), so a third texture
``m_p`` over (θ_t, r ∈ [0, R_p]) (rows periodic in θ_t as the azimuthal texture, columns over r, constant along the
stem) adds the radial displacement ω(r)·m_p(θ_t, r), with the window ω(r) = (1 − exp(−r/t_p))·(1 − (r/R_p)²)²
for r < R_p (0 beyond; t_p = R_p/4): 0 at the pith, where the rings stay closed, and 0 from R_p outwards. Unlike
the pith taper of m_r (quadratic at the pith, so the first ring keeps the width s_r), ω grows linearly from the
pith: the innermost ring may be wider or narrower than s_r, and differently so in every direction (a lobed cone).

The *growth field* G = r' / s_r counts rings from the pith (s_r: mean ring width, mm). Its integer part is the ring
index (the year), its fractional part the *lateness* ℓ ∈ [0, 1) (early wood → late wood) and φ = 2π·ℓ the phase
that the phase loss of §3.6 compares against the curved-Gabor phase of a photograph. Colour comes from a per-ring
colour map c(ring mod n_rings, ℓ).

Conventions (shared with :mod:`torch_appearance.rings`): lengths in mm, angles in radians; the board-plane point
of image pixel (row y, column x) is (u, v) = (x·pixel_size_mm, y·pixel_size_mm), w = 0 on the surface, so
(u, v, w) is a right-handed frame with w pointing into the image (x right, y down). The board→tree transform is
q = R(rotation)·(u, v, w) + translation, R from the axis-angle vector ``rotation`` (Rodrigues).

Distortion textures (``m_r``, ``m_t``: ``(1, 1, Hd, Wd)``, mm) are sampled bilinearly with
``torch.nn.functional.grid_sample(align_corners=True, padding_mode="border")``. Texture *columns* (x, width Wd)
span z ∈ ``z_range_mm``; texture *rows* (y, height Hd) span r ∈ [0, r_max] (``distortion="radial"``) or the
azimuth θ_t ∈ [−π, π) (``"azimuthal"``, periodic: row i sits at θ_t = −π + 2π·i/Hd and the first row is repeated
after the last before sampling, so θ_t = π wraps onto row 0). Outside the ranges the border texel is used.

The fibre direction is the stem direction ẑ projected onto the local growth surface G = const (its tangent plane
has normal ∇G), i.e. ẑ tilted by ∂m/∂z (and ∂m/∂θ_t): for a radial field f ∝ (1 + ∂m_r/∂r)·ẑ − (∂m_r/∂z)·r̂. It is
returned in tree space and in the board frame (R^T f).

Example:
    >>> from torch_appearance.nn import WoodModel
    >>> model = WoodModel(ring_scale_mm=2.0)
    >>> out = model.render_board(64, 96, pixel_size_mm=0.1)
    >>> out["image"].shape, out["G"].shape, out["ring_index"].dtype
    (torch.Size([64, 96, 3]), torch.Size([64, 96]), torch.int64)
"""
from __future__ import annotations

import json
import math
import numbers
import pathlib

import numpy as np
import torch
from torch import nn
import torch.nn.functional as F

from ..checks import check_finite, check_int, check_positive, check_tensor

__all__ = ["WoodModel", "axis_angle_to_matrix", "matrix_to_axis_angle"]

_DISTORTIONS = ("radial", "azimuthal")
_FORMAT = "torch_appearance.WoodModel"
_FORMAT_VERSION = 1
_DTYPES = {"float32": torch.float32, "float64": torch.float64, "float16": torch.float16, "bfloat16": torch.bfloat16}

# Default colour map: early wood (light) → late wood (dark), linear RGB.
_EARLY_RGB = (0.60, 0.42, 0.25)
_LATE_RGB = (0.30, 0.17, 0.08)


# --------------------------------------------------------------------------------------------------------------
# Rotations
# --------------------------------------------------------------------------------------------------------------
def axis_angle_to_matrix(rotation: torch.Tensor) -> torch.Tensor:
    """Rotation matrices from axis-angle vectors (Rodrigues), differentiable everywhere including at zero.

    Args:
        rotation: ``(..., 3)`` axis-angle vectors ω (rad): rotation by |ω| about ω/|ω|.

    Returns:
        ``(..., 3, 3)`` rotation matrices R = I + A·K + B·K² with K = [ω]_×, A = sin θ/θ, B = (1 − cos θ)/θ²
        (Taylor series for θ² < 1e-6, so the gradient at ω = 0 is exact).

    Raises:
        TypeError: ``rotation`` is not a floating-point tensor.
        ValueError: its last dimension is not 3.
    """
    rotation = check_tensor("rotation", rotation, "(..., 3)", dtypes="floating", numpy=True)
    if rotation.dim() == 0 or rotation.shape[-1] != 3:
        raise ValueError(f"rotation: expected shape (..., 3), got {tuple(rotation.shape)}")
    wx, wy, wz = rotation.unbind(-1)
    t2 = wx * wx + wy * wy + wz * wz
    small = t2 < 1e-6
    t2_safe = torch.where(small, torch.ones_like(t2), t2)
    t = torch.sqrt(t2_safe)
    a = torch.where(small, 1.0 - t2 / 6.0 + t2 * t2 / 120.0, torch.sin(t) / t)
    b = torch.where(small, 0.5 - t2 / 24.0 + t2 * t2 / 720.0, (1.0 - torch.cos(t)) / t2_safe)
    zero = torch.zeros_like(wx)
    k = torch.stack([torch.stack([zero, -wz, wy], -1),
                     torch.stack([wz, zero, -wx], -1),
                     torch.stack([-wy, wx, zero], -1)], -2)
    eye = torch.eye(3, dtype=rotation.dtype, device=rotation.device).expand_as(k)
    return eye + a[..., None, None] * k + b[..., None, None] * (k @ k)


def matrix_to_axis_angle(matrix) -> np.ndarray:
    """Axis-angle vector of a rotation matrix (not differentiable; for initial guesses).

    Args:
        matrix: ``(3, 3)`` proper rotation matrix (array-like).

    Returns:
        ``(3,)`` float64 axis-angle vector (rad), angle in [0, π].

    Raises:
        ValueError: wrong shape, or not a rotation (RᵀR ≠ I or det R ≠ 1 to 1e-6).
    """
    from scipy.spatial.transform import Rotation

    m = np.asarray(matrix.detach().cpu() if isinstance(matrix, torch.Tensor) else matrix, dtype=np.float64)
    if m.shape != (3, 3):
        raise ValueError(f"matrix: expected shape (3, 3), got {m.shape}")
    if not np.allclose(m.T @ m, np.eye(3), atol=1e-6) or abs(np.linalg.det(m) - 1.0) > 1e-6:
        raise ValueError(f"matrix: expected a proper rotation (orthonormal, det = 1), got det {np.linalg.det(m):.6g}")
    return Rotation.from_matrix(m).as_rotvec()


# --------------------------------------------------------------------------------------------------------------
# Texture sampling
# --------------------------------------------------------------------------------------------------------------
def _bilinear_derivatives(tex, ix, iy):
    """Partial derivatives of the bilinear interpolant of ``tex`` (C, Ht, Wt) w.r.t. the continuous texel indices.

    ``ix``, ``iy``: (N,) continuous column / row indices (align_corners=True convention, texel i at index i).
    Returns (d/dix, d/diy), each (C, N); zero in a direction where the point lies outside the texture (the border
    padding of grid_sample is constant there). Differentiable w.r.t. ``tex`` and (inside a cell) the indices.
    """
    ht, wt = tex.shape[-2:]
    inside_x = (ix >= 0) & (ix <= wt - 1)
    inside_y = (iy >= 0) & (iy <= ht - 1)
    ixc = ix.clamp(0, wt - 1)
    iyc = iy.clamp(0, ht - 1)
    x0 = torch.floor(ixc.detach()).clamp(max=wt - 2).long()
    y0 = torch.floor(iyc.detach()).clamp(max=ht - 2).long()
    fx = ixc - x0.to(ixc.dtype)
    fy = iyc - y0.to(iyc.dtype)
    t00, t01 = tex[:, y0, x0], tex[:, y0, x0 + 1]
    t10, t11 = tex[:, y0 + 1, x0], tex[:, y0 + 1, x0 + 1]
    d_dx = (1 - fy) * (t01 - t00) + fy * (t11 - t10)
    d_dy = (1 - fx) * (t10 - t00) + fx * (t11 - t01)
    return d_dx * inside_x.to(tex.dtype), d_dy * inside_y.to(tex.dtype)


# --------------------------------------------------------------------------------------------------------------
# The model
# --------------------------------------------------------------------------------------------------------------
class WoodModel(nn.Module):
    """Differentiable procedural wood (Liu et al. 2016 growth field) seen through a planar board.

    Args:
        ring_scale_mm: initial mean ring width s_r (mm, > 0); stored as ``log_ring_scale``.
        n_rings: number of rings with their own colours in ``color_map`` (ring index taken mod ``n_rings``).
        distortion: ``"radial"`` (m_r over (z, r)), ``"azimuthal"`` (m_r over (z, θ_t), periodic in θ_t) or
            ``None`` (no distortion texture).
        distortion_shape: ``(Hd, Wd)`` texel counts (each >= 2): rows over r (or θ_t), columns over z.
        r_max_mm: radius of the last texture row for ``"radial"`` (mm); default ``n_rings · ring_scale_mm``.
        z_range_mm: ``(z_min, z_max)`` heights of the first and last texture columns (mm), z_min < z_max.
        tangential: also learn a tangential displacement field ``m_t`` (same sampling as ``m_r``).
        dtype: floating dtype of all parameters.
        color_bins: K, number of lateness samples per ring in ``color_map`` (>= 2), at ℓ = k/(K − 1).
        pith_taper_mm: t (mm, >= 0): the displacements are multiplied by ``1 − exp(−(r/t)²)`` (0 at the pith,
            above 0.98 beyond 2 t); 0 (the default, and the models saved before it existed): no taper.
        lobe_shape: ``(Hθ, Hp)`` texels (Hθ >= 4, Hp >= 2) of the lobe texture ``m_p`` near the pith, or ``None``
            (the default: no lobes).
        lobe_radius_mm: R_p (mm, > 0), the radius within which lobes act; default 3 ring widths.

    Parameters (``nn.Parameter``):
        rotation: ``(3,)`` axis-angle (rad) of the board→tree rotation R.
        translation: ``(3,)`` mm, tree-space position of the board origin (pixel (0, 0)).
        log_ring_scale: ``()`` log of s_r in mm.
        m_r: ``(1, 1, Hd, Wd)`` mm, radial displacement texture (absent, ``None``, if ``distortion=None``).
        m_t: ``(1, 1, Hd, Wd)`` mm, tangential displacement texture (``None`` unless ``tangential=True``).
        m_p: ``(1, 1, Hθ, Hp)`` mm, lobe texture near the pith (``None`` unless ``lobe_shape`` is given).
        color_map: ``(n_rings, K, 3)`` linear RGB per ring and lateness sample.

    Raises:
        TypeError / ValueError: for invalid arguments (messages name the argument, expected and received values).
    """

    def __init__(self, ring_scale_mm=2.0, n_rings=64, distortion="radial", distortion_shape=(32, 64),
                 r_max_mm=None, z_range_mm=(-50.0, 50.0), tangential=False, dtype=torch.float32, *,
                 color_bins=16, pith_taper_mm=0.0, lobe_shape=None, lobe_radius_mm=None):
        super().__init__()
        ring_scale_mm = check_positive("ring_scale_mm", ring_scale_mm)
        n_rings = check_int("n_rings", n_rings, lo=1)
        if distortion is not None and distortion not in _DISTORTIONS:
            raise ValueError(f"distortion: expected one of {_DISTORTIONS} or None, got {distortion!r}")
        if (not isinstance(distortion_shape, (tuple, list)) or len(distortion_shape) != 2
                or any(isinstance(s, bool) or not isinstance(s, numbers.Integral) for s in distortion_shape)):
            raise TypeError(f"distortion_shape: expected a pair of integers (Hd, Wd), got {distortion_shape!r}")
        hd, wd = (int(s) for s in distortion_shape)
        if hd < 2 or wd < 2:
            raise ValueError(f"distortion_shape: expected (Hd, Wd) with both >= 2, got {(hd, wd)}")
        r_max_mm = n_rings * ring_scale_mm if r_max_mm is None else check_positive("r_max_mm", r_max_mm)
        if (not isinstance(z_range_mm, (tuple, list)) or len(z_range_mm) != 2
                or any(isinstance(z, bool) or not isinstance(z, numbers.Real) for z in z_range_mm)):
            raise TypeError(f"z_range_mm: expected a pair of real numbers (z_min, z_max), got {z_range_mm!r}")
        z0, z1 = float(z_range_mm[0]), float(z_range_mm[1])
        if not (math.isfinite(z0) and math.isfinite(z1) and z0 < z1):
            raise ValueError(f"z_range_mm: expected finite z_min < z_max, got {(z0, z1)}")
        if not isinstance(tangential, bool):
            raise TypeError(f"tangential: expected a bool, got {type(tangential).__name__}")
        if tangential and distortion is None:
            raise ValueError("tangential: expected False when distortion is None (m_t shares m_r's sampling), "
                             "got True")
        if not isinstance(dtype, torch.dtype) or not dtype.is_floating_point:
            raise TypeError(f"dtype: expected a floating-point torch.dtype, got {dtype!r}")
        color_bins = check_int("color_bins", color_bins, lo=2)
        if (isinstance(pith_taper_mm, bool) or not isinstance(pith_taper_mm, numbers.Real)
                or not math.isfinite(pith_taper_mm) or pith_taper_mm < 0):
            raise ValueError(f"pith_taper_mm: expected a finite number >= 0, got {pith_taper_mm!r}")

        if lobe_shape is not None:
            if (not isinstance(lobe_shape, (tuple, list)) or len(lobe_shape) != 2
                    or any(isinstance(v, bool) or not isinstance(v, numbers.Integral) for v in lobe_shape)):
                raise TypeError(f"lobe_shape: expected None or a pair of integers (Htheta, Hp), got {lobe_shape!r}")
            if int(lobe_shape[0]) < 4 or int(lobe_shape[1]) < 2:
                raise ValueError(f"lobe_shape: expected (Htheta, Hp) with Htheta >= 4 and Hp >= 2, "
                                 f"got {tuple(lobe_shape)}")
            lobe_shape = (int(lobe_shape[0]), int(lobe_shape[1]))
            lobe_radius_mm = (3.0 * ring_scale_mm if lobe_radius_mm is None
                              else check_positive("lobe_radius_mm", lobe_radius_mm))
        elif lobe_radius_mm is not None:
            lobe_radius_mm = check_positive("lobe_radius_mm", lobe_radius_mm)
        self.lobe_shape = lobe_shape
        self.lobe_radius_mm = None if lobe_radius_mm is None else float(lobe_radius_mm)
        self.n_rings = n_rings
        self.distortion = distortion
        self.distortion_shape = (hd, wd)
        self.r_max_mm = r_max_mm
        self.z_range_mm = (z0, z1)
        self.tangential = tangential
        self.color_bins = color_bins
        self.pith_taper_mm = float(pith_taper_mm)

        self.rotation = nn.Parameter(torch.zeros(3, dtype=dtype))
        self.translation = nn.Parameter(torch.zeros(3, dtype=dtype))
        self.log_ring_scale = nn.Parameter(torch.tensor(math.log(ring_scale_mm), dtype=dtype))
        if distortion is not None:
            self.m_r = nn.Parameter(torch.zeros(1, 1, hd, wd, dtype=dtype))
        else:
            self.register_parameter("m_r", None)
        if tangential:
            self.m_t = nn.Parameter(torch.zeros(1, 1, hd, wd, dtype=dtype))
        else:
            self.register_parameter("m_t", None)
        if lobe_shape is not None:
            self.m_p = nn.Parameter(torch.zeros((1, 1) + lobe_shape, dtype=dtype))
        else:
            self.register_parameter("m_p", None)
        late = torch.linspace(0.0, 1.0, color_bins, dtype=torch.float64)
        ramp = late * late * (3 - 2 * late)  # smoothstep: early wood → late wood
        early = torch.tensor(_EARLY_RGB, dtype=torch.float64)
        lat = torch.tensor(_LATE_RGB, dtype=torch.float64)
        cmap = early + (lat - early) * ramp[:, None]
        self.color_map = nn.Parameter(cmap.expand(n_rings, color_bins, 3).clone().to(dtype))

    # ----------------------------------------------------------------------------------------------------------
    # Small accessors
    # ----------------------------------------------------------------------------------------------------------
    @property
    def dtype(self) -> torch.dtype:
        """Floating dtype of the parameters."""
        return self.log_ring_scale.dtype

    @property
    def device(self) -> torch.device:
        """Device of the parameters."""
        return self.log_ring_scale.device

    @property
    def ring_scale(self) -> torch.Tensor:
        """``()`` tensor: mean ring width s_r = exp(log_ring_scale) in mm (differentiable)."""
        return torch.exp(self.log_ring_scale)

    def config(self) -> dict:
        """Constructor arguments (JSON-serialisable) that rebuild a model with this one's shapes."""
        return {"ring_scale_mm": float(self.ring_scale.detach()), "n_rings": self.n_rings,
                "distortion": self.distortion, "distortion_shape": list(self.distortion_shape),
                "r_max_mm": self.r_max_mm, "z_range_mm": list(self.z_range_mm), "tangential": self.tangential,
                "dtype": str(self.dtype).replace("torch.", ""), "color_bins": self.color_bins,
                "pith_taper_mm": self.pith_taper_mm,
                "lobe_shape": None if self.lobe_shape is None else list(self.lobe_shape),
                "lobe_radius_mm": self.lobe_radius_mm}

    def extra_repr(self) -> str:
        return (f"n_rings={self.n_rings}, distortion={self.distortion!r}, distortion_shape={self.distortion_shape}, "
                f"r_max_mm={self.r_max_mm:g}, z_range_mm={self.z_range_mm}, tangential={self.tangential}, "
                f"color_bins={self.color_bins}, pith_taper_mm={self.pith_taper_mm:g}, lobe_shape={self.lobe_shape}")

    def rotation_matrix(self) -> torch.Tensor:
        """``(3, 3)`` board→tree rotation R(rotation) (differentiable)."""
        return axis_angle_to_matrix(self.rotation)

    @torch.no_grad()
    def set_parameters(self, *, rotation=None, translation=None, ring_scale_mm=None, m_r=None, m_t=None,
                       color_map=None, m_p=None) -> "WoodModel":
        """Overwrite parameters in place (no gradient), with shape checks; returns ``self``.

        Args:
            rotation: ``(3,)`` axis-angle (rad).
            translation: ``(3,)`` mm.
            ring_scale_mm: s_r > 0 (mm).
            m_r: ``(Hd, Wd)`` or ``(1, 1, Hd, Wd)`` mm (requires a distortion texture).
            m_t: same for the tangential texture (requires ``tangential=True``).
            m_p: ``(Hθ, Hp)`` or ``(1, 1, Hθ, Hp)`` mm, the lobe texture (requires ``lobe_shape``).
            color_map: ``(n_rings, K, 3)`` linear RGB.

        Raises:
            TypeError / ValueError: wrong type, shape, non-finite values, or the texture does not exist.
        """
        def assign(name, param, value, shape):
            value = check_tensor(name, value, str(tuple(shape)), dtypes="floating", numpy=True)
            if len(shape) == 4 and tuple(value.shape) == tuple(shape[-2:]):
                value = value.reshape(shape)  # (Hd, Wd) texture given without the batch/channel axes
            if tuple(value.shape) != tuple(shape):
                raise ValueError(f"{name}: expected shape {tuple(shape)}, got {tuple(value.shape)}")
            check_finite(name, value)
            param.copy_(value.to(param))

        if rotation is not None:
            assign("rotation", self.rotation, rotation, (3,))
        if translation is not None:
            assign("translation", self.translation, translation, (3,))
        if ring_scale_mm is not None:
            if isinstance(ring_scale_mm, torch.Tensor):
                ring_scale_mm = float(ring_scale_mm.detach())
            self.log_ring_scale.fill_(math.log(check_positive("ring_scale_mm", ring_scale_mm)))
        for name in ("m_r", "m_t"):
            value = m_r if name == "m_r" else m_t
            if value is None:
                continue
            param = getattr(self, name)
            if param is None:
                raise ValueError(f"{name}: this model has no {name} texture (distortion={self.distortion!r}, "
                                 f"tangential={self.tangential}), got a value")
            assign(name, param, value, (1, 1) + self.distortion_shape)
        if m_p is not None:
            if self.m_p is None:
                raise ValueError("m_p: this model has no lobe texture (lobe_shape=None), got a value")
            assign("m_p", self.m_p, m_p, (1, 1) + self.lobe_shape)
        if color_map is not None:
            assign("color_map", self.color_map, color_map, tuple(self.color_map.shape))
        return self

    def texel_coordinates(self) -> torch.Tensor:
        """Tree-space sampling positions of the distortion texels.

        Returns:
            ``(Hd, Wd, 2)`` tensor: ``[..., 0]`` = z (mm) of each column, ``[..., 1]`` = r (mm) of each row for
            ``"radial"`` or θ_t (rad, in [−π, π)) for ``"azimuthal"``.

        Raises:
            ValueError: the model has no distortion texture.
        """
        if self.distortion is None:
            raise ValueError("distortion: expected 'radial' or 'azimuthal' for texel coordinates, got None")
        hd, wd = self.distortion_shape
        z = torch.linspace(self.z_range_mm[0], self.z_range_mm[1], wd, dtype=self.dtype, device=self.device)
        if self.distortion == "radial":
            y = torch.linspace(0.0, self.r_max_mm, hd, dtype=self.dtype, device=self.device)
        else:
            y = -math.pi + 2 * math.pi * torch.arange(hd, dtype=self.dtype, device=self.device) / hd
        zz, yy = torch.meshgrid(z, y, indexing="xy")
        return torch.stack([zz, yy], -1)

    # ----------------------------------------------------------------------------------------------------------
    # Geometry
    # ----------------------------------------------------------------------------------------------------------
    def _check_points(self, name, points, widths):
        points = check_tensor(name, points, f"(N, {' or '.join(map(str, widths))})", dtypes="floating", numpy=True)
        if points.dim() != 2 or points.shape[1] not in widths:
            raise ValueError(f"{name}: expected shape (N, {' or '.join(map(str, widths))}), "
                             f"got {tuple(points.shape)}")
        check_finite(name, points)
        return points.to(dtype=self.dtype, device=self.device)

    def board_to_tree(self, points: torch.Tensor) -> torch.Tensor:
        """Board-frame points → tree space, q = R·(u, v, w) + translation.

        Args:
            points: ``(N, 2)`` (u, v) on the surface (w = 0) or ``(N, 3)`` (u, v, w), mm.

        Returns:
            ``(N, 3)`` tree-space points (mm), differentiable w.r.t. points, rotation and translation.
        """
        points = self._check_points("points", points, (2, 3))
        rot = self.rotation_matrix()
        return points @ rot[:, : points.shape[1]].T + self.translation

    def tree_to_board(self, points: torch.Tensor) -> torch.Tensor:
        """Tree-space points → board frame (u, v, w) = Rᵀ(q − translation).

        Args:
            points: ``(N, 3)`` tree-space points (mm).

        Returns:
            ``(N, 3)`` board-frame points (mm); w is the signed distance from the board plane.
        """
        points = self._check_points("points", points, (3,))
        return (points - self.translation) @ self.rotation_matrix()

    def _sample(self, texture, gx, gy):
        """grid_sample of a (1, 1, Ht, Wt) texture at normalised coordinates (N,) → (N,)."""
        grid = torch.stack([gx, gy], -1)[None, None]  # (1, 1, N, 2)
        out = F.grid_sample(texture, grid, mode="bilinear", padding_mode="border", align_corners=True)
        return out[0, 0, 0]

    def _field(self, q):
        """Core evaluation for tree-space points q (N, 3): everything except the colour lookup."""
        x, y, z = q.unbind(-1)
        rho2 = x * x + y * y
        tiny = torch.finfo(q.dtype).tiny
        degenerate = rho2 <= tiny
        r = torch.sqrt(torch.where(degenerate, torch.full_like(rho2, tiny), rho2))
        xs = torch.where(degenerate, torch.ones_like(x), x)
        ys = torch.where(degenerate, torch.zeros_like(y), y)
        rs = torch.where(degenerate, torch.ones_like(r), r)
        cos_t, sin_t = xs / rs, ys / rs

        zero = torch.zeros_like(r)
        m_r = m_t = zero
        # ∇ of (r + m_r) and of m_t in the cylindrical basis (r̂, θ̂, ẑ)
        ga = [torch.ones_like(r), zero, zero]
        gb = [zero, zero, zero]
        if self.distortion is not None:
            hd, wd = self.distortion_shape
            z0, z1 = self.z_range_mm
            gx = 2.0 * (z - z0) / (z1 - z0) - 1.0
            ix = (gx + 1.0) * (0.5 * (wd - 1))
            dix_dz = (wd - 1) / (z1 - z0)
            if self.distortion == "radial":
                gy = 2.0 * r / self.r_max_mm - 1.0
                iy = r * ((hd - 1) / self.r_max_mm)
                diy = (hd - 1) / self.r_max_mm          # ∂iy/∂r
                pad = lambda t: t  # noqa: E731
            else:
                theta = torch.atan2(ys, xs)             # (−π, π]
                gy = theta / math.pi                    # padded texture: row 0 at θ = −π, row hd (copy) at π
                iy = (theta + math.pi) * (hd / (2 * math.pi))
                diy = hd / (2 * math.pi) / rs           # (1/r)·∂iy/∂θ
                pad = lambda t: torch.cat([t, t[:, :, :1]], dim=2)  # noqa: E731
            textures = {"m_r": self.m_r, "m_t": self.m_t}
            values, grads = {}, {}
            for name, tex in textures.items():
                if tex is None:
                    continue
                tex = pad(tex)
                values[name] = self._sample(tex, gx, gy)
                d_dx, d_dy = _bilinear_derivatives(tex[0], ix, iy)
                dz, dy = d_dx[0] * dix_dz, d_dy[0] * diy
                grads[name] = [dy, zero, dz] if self.distortion == "radial" else [zero, dy, dz]
            if self.pith_taper_mm > 0:  # m <- tau(r) m: grad(tau m) = tau grad m + tau'(r) m r_hat
                u = r / self.pith_taper_mm
                e = torch.exp(-u * u)
                tau, dtau = 1.0 - e, 2.0 * u / self.pith_taper_mm * e
                for name in values:
                    g0, g1, g2 = grads[name]
                    grads[name] = [tau * g0 + dtau * values[name], tau * g1, tau * g2]
                    values[name] = tau * values[name]
            m_r = values["m_r"]
            ga = [ga[0] + grads["m_r"][0], grads["m_r"][1], grads["m_r"][2]]
            if "m_t" in values:
                m_t = values["m_t"]
                gb = grads["m_t"]
        if self.m_p is not None:
            lobe, (d_r, d_t) = self._lobes(r, xs, ys, rs)
            m_r = m_r + lobe
            ga = [ga[0] + d_r, ga[1] + d_t, ga[2]]
        a = r + m_r
        if self.tangential:
            r2 = a * a + m_t * m_t
            r_dist = torch.sqrt(r2.clamp_min(tiny))
            inv = 1.0 / r_dist
            g = [(a * ga[i] + m_t * gb[i]) * inv for i in range(3)]
        else:
            r_dist = a
            g = ga
        G = r_dist / self.ring_scale

        # fibre: ẑ projected onto the tangent plane of the growth surface (normal ∝ g), normalised
        g_r, g_t, g_z = g
        h2 = g_r * g_r + g_t * g_t
        h = torch.sqrt(h2.clamp_min(tiny))
        norm_g = torch.sqrt((h2 + g_z * g_z).clamp_min(tiny))
        denom = h * norm_g
        f_r, f_t, f_z = -g_z * g_r / denom, -g_z * g_t / denom, h2 / denom
        fiber = torch.stack([f_r * cos_t - f_t * sin_t, f_r * sin_t + f_t * cos_t, f_z], -1)
        return G, m_r, fiber

    def _lobes(self, r, xs, ys, rs):
        """Lobe displacement ω(r)·m_p(θ_t, r) (N,) and its gradient's (r̂, θ̂) components."""
        hp_t, hp_r = self.lobe_shape
        big = self.lobe_radius_mm
        theta = torch.atan2(ys, xs)
        tex = torch.cat([self.m_p, self.m_p[:, :, :1]], dim=2)           # θ = π wraps onto row 0
        rc = r.clamp(max=big)
        gx = 2.0 * rc / big - 1.0                                         # columns over r ∈ [0, R_p]
        gy = theta / math.pi
        value = self._sample(tex, gx, gy)
        d_dx, d_dy = _bilinear_derivatives(tex[0], (gx + 1.0) * (0.5 * (hp_r - 1)),
                                           (theta + math.pi) * (hp_t / (2 * math.pi)))
        dv_dr, dv_dt = d_dx[0] * ((hp_r - 1) / big), d_dy[0] * (hp_t / (2 * math.pi)) / rs
        t = big / 4.0
        u = r / t
        e = torch.exp(-u)
        x = (r / big).clamp(max=1.0)
        win = (1.0 - x * x) ** 2
        omega = (1.0 - e) * win
        d_omega = e / t * win + (1.0 - e) * (-4.0 * x * (1.0 - x * x) / big)
        return omega * value, (d_omega * value + omega * dv_dr, omega * dv_dt)

    def evaluate(self, points: torch.Tensor, board: bool = False) -> dict:
        """Evaluate the growth field and colour at points.

        Args:
            points: ``(N, 3)`` tree-space points (mm), or with ``board=True`` board-frame points ``(N, 2)``
                (u, v; w = 0) or ``(N, 3)`` (u, v, w), mm.
            board: interpret ``points`` in the board frame.

        Returns:
            dict of tensors (N = number of points):
                ``G`` (N,) growth field r'/s_r (rings from the pith, unitless);
                ``phase`` (N,) 2π·lateness, rad in [0, 2π);
                ``lateness`` (N,) G − ⌊G⌋ in [0, 1);
                ``ring_index`` (N,) int64 ⌊G⌋ (not taken mod n_rings);
                ``rgb`` (N, 3) linear RGB from ``color_map``;
                ``fiber`` (N, 3) unit fibre direction in tree space; ``fiber_board`` (N, 3) the same in the
                board frame (u, v, w); ``m_r`` (N,) sampled radial displacement (mm); ``points_tree`` (N, 3) mm.
            All float outputs are differentiable w.r.t. every parameter and the points; ``lateness``, ``phase`` and
            ``rgb`` jump where G crosses an integer (ring boundaries) and are smooth elsewhere.

        Raises:
            TypeError / ValueError: ``points`` is not a floating tensor/array of the stated shape, or not finite.
        """
        if not isinstance(board, bool):
            raise TypeError(f"board: expected a bool, got {type(board).__name__}")
        q = self.board_to_tree(points) if board else self._check_points("points", points, (3,))
        G, m_r, fiber = self._field(q)
        floor_g = torch.floor(G.detach())
        lateness = G - floor_g
        ring_index = floor_g.long()
        rgb = self._colour(ring_index, lateness)
        return {"G": G, "phase": 2 * math.pi * lateness, "lateness": lateness, "ring_index": ring_index,
                "rgb": rgb, "fiber": fiber, "fiber_board": fiber @ self.rotation_matrix(), "m_r": m_r,
                "points_tree": q}

    def _colour(self, ring_index, lateness):
        """Colour-map lookup: ring (mod n_rings), linear interpolation along lateness samples ℓ_k = k/(K − 1)."""
        k = self.color_bins
        ring = torch.remainder(ring_index, self.n_rings)
        pos = lateness * (k - 1)
        k0 = torch.floor(pos.detach()).clamp(0, k - 2).long()
        w = (pos - k0.to(pos.dtype))[:, None]
        c0 = self.color_map[ring, k0]
        c1 = self.color_map[ring, k0 + 1]
        return c0 + w * (c1 - c0)

    def render_board(self, height: int, width: int, pixel_size_mm: float) -> dict:
        """Render the board surface (w = 0) on a pixel grid.

        Pixel (row y, column x) is the board point (u, v) = (x·pixel_size_mm, y·pixel_size_mm).

        Args:
            height: H, number of rows (>= 1).
            width: W, number of columns (>= 1).
            pixel_size_mm: pixel pitch (mm, > 0).

        Returns:
            dict: ``image`` (H, W, 3) linear RGB; ``phase`` (H, W) rad in [0, 2π); ``lateness`` (H, W) in [0, 1);
            ``ring_index`` (H, W) int64; ``G`` (H, W); ``fiber`` (H, W, 3) tree-space and ``fiber_board`` (H, W, 3)
            board-frame unit fibre directions; ``m_r`` (H, W) mm. Differentiable w.r.t. all continuous parameters
            (see :meth:`evaluate`).

        Raises:
            TypeError / ValueError: non-integer or non-positive ``height``/``width``, non-positive ``pixel_size_mm``.
        """
        height = check_int("height", height, lo=1)
        width = check_int("width", width, lo=1)
        pixel_size_mm = check_positive("pixel_size_mm", pixel_size_mm)
        ys = torch.arange(height, dtype=self.dtype, device=self.device) * pixel_size_mm
        xs = torch.arange(width, dtype=self.dtype, device=self.device) * pixel_size_mm
        vv, uu = torch.meshgrid(ys, xs, indexing="ij")
        out = self.evaluate(torch.stack([uu.reshape(-1), vv.reshape(-1)], -1), board=True)
        out["image"] = out.pop("rgb")
        out.pop("points_tree")
        return {key: value.reshape((height, width) + tuple(value.shape[1:])) for key, value in out.items()}

    def forward(self, height: int, width: int, pixel_size_mm: float) -> dict:
        """Alias of :meth:`render_board`."""
        return self.render_board(height, width, pixel_size_mm)

    # ----------------------------------------------------------------------------------------------------------
    # Persistence
    # ----------------------------------------------------------------------------------------------------------
    def save(self, path_prefix) -> tuple[pathlib.Path, pathlib.Path]:
        """Write ``<path_prefix>.json`` (format tag + constructor config) and ``<path_prefix>.pt`` (state dict).

        Args:
            path_prefix: str or path without extension; parent directories must exist.

        Returns:
            ``(json_path, pt_path)``.
        """
        from ..io import write_json

        if not isinstance(path_prefix, (str, pathlib.PurePath)) or str(path_prefix) == "":
            raise TypeError(f"path_prefix: expected a non-empty str or path, got {path_prefix!r}")
        prefix = pathlib.Path(path_prefix)
        json_path, pt_path = prefix.with_name(prefix.name + ".json"), prefix.with_name(prefix.name + ".pt")
        state = {k: v.detach().cpu().clone() for k, v in self.state_dict().items()}
        torch.save(state, pt_path)
        write_json(json_path, {"format": _FORMAT, "version": _FORMAT_VERSION, "config": self.config()})
        return json_path, pt_path

    @classmethod
    def load(cls, path_prefix, map_location="cpu") -> "WoodModel":
        """Rebuild a model written by :meth:`save`.

        Args:
            path_prefix: the prefix given to :meth:`save`.
            map_location: device for the parameters.

        Raises:
            FileNotFoundError: a file is missing. ValueError: wrong format tag/version or state mismatch.
        """
        if not isinstance(path_prefix, (str, pathlib.PurePath)) or str(path_prefix) == "":
            raise TypeError(f"path_prefix: expected a non-empty str or path, got {path_prefix!r}")
        prefix = pathlib.Path(path_prefix)
        json_path, pt_path = prefix.with_name(prefix.name + ".json"), prefix.with_name(prefix.name + ".pt")
        meta = json.loads(json_path.read_text(encoding="utf-8"))
        if meta.get("format") != _FORMAT or meta.get("version") != _FORMAT_VERSION:
            raise ValueError(f"path_prefix: expected {json_path} to hold format {_FORMAT!r} version "
                             f"{_FORMAT_VERSION}, got {meta.get('format')!r} version {meta.get('version')!r}")
        config = dict(meta["config"])
        dtype_name = config.pop("dtype")
        if dtype_name not in _DTYPES:
            raise ValueError(f"path_prefix: unknown dtype {dtype_name!r} in {json_path}")
        config["distortion_shape"] = tuple(config["distortion_shape"])
        config["z_range_mm"] = tuple(config["z_range_mm"])
        model = cls(dtype=_DTYPES[dtype_name], **config)
        state = torch.load(pt_path, map_location="cpu", weights_only=True)
        try:
            model.load_state_dict(state, strict=True)
        except RuntimeError as error:
            raise ValueError(f"path_prefix: state in {pt_path} does not match {json_path}: {error}") from None
        return model.to(map_location)
