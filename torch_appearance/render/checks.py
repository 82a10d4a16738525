"""Moved to :mod:`torch_appearance.checks`; this name stays only for ``pipelines/wood_volume_render.py``'s import
while the pipelines are restructured (drop it once nothing imports ``render.checks``)."""
from ..checks import *  # noqa: F401,F403
from ..checks import __all__  # noqa: F401
