"""Phase function of the medium."""
from dataclasses import dataclass

from ..checks import check_real

__all__ = ["HenyeyGreenstein"]


@dataclass(frozen=True)
class HenyeyGreenstein:
    """Henyey–Greenstein phase function with mean cosine ``g`` in (−1, 1); sampled exactly."""
    g: float = 0.4

    def __post_init__(self):
        object.__setattr__(self, "g", check_real("g", self.g, lo=-1, hi=1, lo_open=True, hi_open=True))
