"""``nn.Module`` models and losses."""
from .renderer import VolumeRenderer
from .mixture import FixedFraction, MaterialMixture, mix_inks

__all__ = ["VolumeRenderer", "MaterialMixture", "FixedFraction", "mix_inks"]
