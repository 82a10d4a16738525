"""``nn.Module`` models and losses."""
from .renderer import SceneRenderer, VolumeRenderer
from .mixture import FixedFraction, MaterialMixture, mix_inks
from .wood import WoodModel
from .losses import (AppearanceLoss, ColorLoss, EdgeLoss3D, SSIMLoss3D, appearance_loss, color_loss, edge_loss_3d,
                     masked_ssim3d, ssim_loss_3d)
from .texel_losses import TexelFilters, texel_appearance_loss
from .gabor_loss import GaborPhaseLoss, gabor_phase_loss

__all__ = ["VolumeRenderer", "SceneRenderer", "MaterialMixture", "FixedFraction", "mix_inks",
           "AppearanceLoss", "ColorLoss", "SSIMLoss3D", "EdgeLoss3D", "appearance_loss", "color_loss",
           "ssim_loss_3d", "edge_loss_3d", "masked_ssim3d", "TexelFilters", "texel_appearance_loss", "WoodModel",
           "GaborPhaseLoss", "gabor_phase_loss"]
