"""The settings of one wood fit (:class:`WoodFitConfig`) and the thresholds its summary reports against."""
import math
from dataclasses import dataclass
from typing import Optional

import torch

__all__ = ["WoodFitConfig", "LOG_FIELDS", "POOR_FIT_PHASE_RMS", "MIN_RINGS_FOR_SCALE", "MIN_PHOTO_SIDE", "MIN_EPOCH_S",
           "MAX_JOB_S"]

LOG_FIELDS = ["stage", "epoch", "wall_s", "phase_loss", "color_loss", "phase_rms", "photometric_loss"]
POOR_FIT_PHASE_RMS = 0.8  # rad; fits above it are flagged (summary["fit_ok"] = False) and warned about
# Fewer distinct rings than this on the board leave the ring scale poorly determined (the number of rings between
# the pith and the board trades against the axis distance); measured on synthetic boards (eval_wood_synthetic.py):
# s_r errors of 8-127 % with 2-4 visible rings, 3-7 % with 6-9.
MIN_RINGS_FOR_SCALE = 6
#: the least side of a photo the fit takes, in pixels (after --max-size's downscaling too)
MIN_PHOTO_SIDE = 8
#: the least time an epoch takes (one render of the board and an Adam step; 96² px take ~3 ms) and the longest job
#: admitted: epochs that cannot end within a year even at that pace are refused before any work
MIN_EPOCH_S = 1e-3
MAX_JOB_S = 365.25 * 86400
#: the pixel pitches admitted, mm: a ring is found only when it is at least ~4 px wide, so above 10 mm per pixel the
#: rings would be 4 cm and wider (wider than trees grow); below 0.1 µm the photo is a micrograph of cell walls
PIXEL_SIZE_MM_RANGE = (1e-4, 10.0)
#: the lobes are of the innermost rings (default 4): beyond this many ring widths they would cover the whole board
MAX_LOBE_RADIUS_RINGS = 50.0


@dataclass
class WoodFitConfig:
    """Settings of one wood fit (every field is a flag of ta-fit-wood)."""
    photo: str
    out: str = "results/wood"
    pixel_size_mm: float = 0.1
    epochs: int = 500
    lr: float = 0.03
    color_epochs: int = 200
    color_lr: float = 0.05
    p: int = 80
    q: int = 80
    distortion: str = "radial"
    distortion_shape: tuple = (32, 64)
    smoothness: float = 1.0  # weight of the distortion prior (squared texel-to-texel change, in ring widths)
    color_bins: int = 32  # lateness samples of the colour map (a thin latewood line needs a few of its own)
    coarse_to_fine: int = 3  # stage-1 distortion levels (1: the full texture from the start, as before)
    # lobes of the innermost rings: a (θ, r) texture of lobe_shape texels within lobe_radius_rings ring widths of the
    # pith (WoodModel(lobe_shape=...)); None: no lobe texture (the growth field is m_r(z, r) alone)
    lobe_shape: Optional[tuple] = (16, 8)
    lobe_radius_rings: float = 4.0
    # the photo's phase near the pith line: the two sides of the projected centre line filtered apart where the rings
    # run along it (rings.board.split_at_pith_line); False: the Gabor phase of the whole photo, as before
    pith_split: bool = True
    # after stage 2: remap the colour map's luminance so that the fit's luminance histogram is the photo's (the
    # per-bin photo means blur latewood into earlywood wherever the fitted phase is off by a fraction of a ring)
    contrast_match: bool = False
    # stage 3 (photometric): geometry + colour map against the photo's colours (CIELAB L2) through the
    # reparameterised render (correct boundary gradients), coarse to fine over photometric_levels (downsampling
    # factors of the photo), photometric_epochs Adam steps in all, split evenly over the levels
    photometric: bool = False
    photometric_epochs: int = 120
    photometric_lr: float = 0.005  # geometry, in ring widths per step (as lr)
    photometric_color_lr: float = 0.01  # colour map, linear RGB per step (0: frozen)
    photometric_spp: int = 4
    photometric_levels: tuple = (4, 2)
    photometric_weight: float = 10.0  # multiplies the CIELAB term (mean ΔE² / 100)
    photometric_anchor: float = 1.0  # weight of the stage-1 cyclic phase loss kept in stage 3 (0: colour only)
    photometric_estimator: str = "reparam"  # "naive": fixed-sample autograd, no boundary term (for comparison)
    device: str = "cpu"
    max_size: Optional[int] = None
    seed: int = 0
    preview: bool = True

    def validate(self):
        if not (isinstance(self.pixel_size_mm, (int, float)) and math.isfinite(self.pixel_size_mm)
                and self.pixel_size_mm > 0):
            raise ValueError(f"pixel_size_mm: expected a finite value > 0, got {self.pixel_size_mm!r}")
        low, high = PIXEL_SIZE_MM_RANGE
        if not low <= self.pixel_size_mm <= high:  # 1e12 was taken: a board of 1e11 m, its rings metres wide
            raise ValueError(f"pixel_size_mm: expected {low:g} ... {high:g} mm per pixel (a ring is at least ~4 px "
                             f"wide: above {high:g} mm per pixel it would be wider than trees grow), got "
                             f"{self.pixel_size_mm:g}")
        for name in ("epochs", "color_epochs", "photometric_epochs"):
            v = getattr(self, name)
            if not isinstance(v, int) or v < 0:
                raise ValueError(f"{name}: expected an int >= 0, got {v!r}")
            if v * MIN_EPOCH_S > MAX_JOB_S:
                raise ValueError(f"{name}: {v} epochs take at least {v * MIN_EPOCH_S / MAX_JOB_S:.3g} years (an epoch "
                                 f"takes at least {MIN_EPOCH_S * 1e3:g} ms); expected a job under a year, at most "
                                 f"{int(MAX_JOB_S / MIN_EPOCH_S)} epochs")
        for name in ("p", "q", "coarse_to_fine"):
            v = getattr(self, name)
            if not isinstance(v, int) or v < 1:
                raise ValueError(f"{name}: expected an int >= 1, got {v!r}")
        # the pyramid's levels halve the distortion texture down to 2 texels a side; further levels repeat the
        # coarsest (2 × 2) and add only work
        levels = max(1, int(math.log2(max(self.distortion_shape))))
        if self.coarse_to_fine > levels:
            raise ValueError(f"coarse_to_fine: expected at most {levels} (the {self.distortion_shape[0]} × "
                             f"{self.distortion_shape[1]}-texel distortion texture halves {levels - 1} times before it "
                             f"is 2 texels a side; more levels only repeat the coarsest), got {self.coarse_to_fine}")
        if self.max_size is not None and (isinstance(self.max_size, bool) or not isinstance(self.max_size, int)
                                          or self.max_size < MIN_PHOTO_SIDE):
            raise ValueError(f"max_size: expected an int >= {MIN_PHOTO_SIDE} (the photo's longest side after "
                             f"downscaling, in pixels), got {self.max_size!r}")
        for name in ("color_bins",):
            v = getattr(self, name)
            if not isinstance(v, int) or v < 2:
                raise ValueError(f"{name}: expected an int >= 2, got {v!r}")
        for name in ("photometric", "contrast_match", "pith_split"):
            if not isinstance(getattr(self, name), bool):
                raise TypeError(f"{name}: expected a bool, got {type(getattr(self, name)).__name__}")
        if not isinstance(self.photometric_spp, int) or self.photometric_spp < 2:
            raise ValueError(f"photometric_spp: expected an int >= 2, got {self.photometric_spp!r}")
        levels = self.photometric_levels
        if (not isinstance(levels, (tuple, list)) or not levels
                or any(isinstance(f, bool) or not isinstance(f, int) or f < 1 for f in levels)):
            raise ValueError(f"photometric_levels: expected a non-empty sequence of ints >= 1 (downsampling factors, "
                             f"coarse first), got {levels!r}")
        if self.photometric_estimator not in ("reparam", "naive"):
            raise ValueError(f"photometric_estimator: expected 'reparam' or 'naive', "
                             f"got {self.photometric_estimator!r}")
        for name in ("photometric_weight", "photometric_anchor"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v >= 0):
                raise ValueError(f"{name}: expected a finite value >= 0, got {v!r}")
        if not (isinstance(self.photometric_color_lr, (int, float)) and math.isfinite(self.photometric_color_lr)
                and self.photometric_color_lr >= 0):
            raise ValueError(f"photometric_color_lr: expected a finite value >= 0 (0: colour map frozen in stage 3), "
                             f"got {self.photometric_color_lr!r}")
        for name in ("lr", "color_lr", "photometric_lr"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v > 0):
                raise ValueError(f"{name}: expected a finite value > 0, got {v!r}")
        # Adam moves a parameter by about its rate per step: more than a ring width (the geometry's unit, which the
        # cyclic phase loss cannot tell from none) or than the whole colour range [0, 1] only throws the fit away
        # (--lr 1e12 ended in NaN parameters and an IndexError)
        for name, unit in (("lr", "ring width"), ("photometric_lr", "ring width"), ("color_lr", "colour range"),
                           ("photometric_color_lr", "colour range")):
            if getattr(self, name) > 1:
                raise ValueError(f"{name}: expected at most 1 (a {unit} per step), got {getattr(self, name)!r}")
        if self.lobe_shape is not None and (
                not isinstance(self.lobe_shape, (tuple, list)) or len(self.lobe_shape) != 2
                or any(isinstance(v, bool) or not isinstance(v, int) for v in self.lobe_shape)
                or self.lobe_shape[0] < 4 or self.lobe_shape[1] < 2):
            raise ValueError(f"lobe_shape: expected None or (Htheta >= 4, Hp >= 2), got {self.lobe_shape!r}")
        if not (isinstance(self.lobe_radius_rings, (int, float)) and not isinstance(self.lobe_radius_rings, bool)
                and math.isfinite(self.lobe_radius_rings) and self.lobe_radius_rings > 0):
            raise ValueError(f"lobe_radius_rings: expected a finite value > 0, got {self.lobe_radius_rings!r}")
        if self.lobe_radius_rings > MAX_LOBE_RADIUS_RINGS:
            raise ValueError(f"lobe_radius_rings: expected at most {MAX_LOBE_RADIUS_RINGS:g} ring widths (the lobes "
                             f"are of the innermost rings), got {self.lobe_radius_rings:g}")
        if self.distortion not in ("radial", "azimuthal"):
            raise ValueError(f"distortion: expected 'radial' or 'azimuthal', got {self.distortion!r}")
        if self.device not in ("cpu", "cuda") and not str(self.device).startswith("cuda:"):
            raise ValueError(f"device: expected 'cpu' or 'cuda[:N]', got {self.device!r}")
        if str(self.device).startswith("cuda") and not torch.cuda.is_available():
            raise ValueError(f"device: {self.device!r} requested but CUDA is not available")
