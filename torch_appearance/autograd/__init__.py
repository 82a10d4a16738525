"""Custom ``torch.autograd.Function`` wrappers around the C++ core."""
from .volpath import VolumePathTrace

__all__ = ["VolumePathTrace"]
