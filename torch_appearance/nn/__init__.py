"""``nn.Module`` models and losses."""
from .renderer import VolumeRenderer

__all__ = ["VolumeRenderer"]
