"""Scene description and rendering entry points."""
from .scene import (ConstantEnvironment, Dielectric, HenyeyGreenstein, IndexMatched, PathSettings, SlabScene,
                    TexelSensor, default_max_depth, default_rr_depth)
from .volpath import render_texels

__all__ = ["render_texels", "SlabScene", "HenyeyGreenstein", "Dielectric", "IndexMatched", "ConstantEnvironment",
           "TexelSensor", "PathSettings", "default_max_depth", "default_rr_depth"]
