"""torch_appearance: appearance matching and fabrication with differentiable material models.

The core is a differentiable heterogeneous-volume path tracer in C++ (``torch_appearance._C``) whose backward
pass is radiative backpropagation by path replay; see :func:`render_texels` (slabs) and :func:`render_scene`
(general scenes).
"""
from ._ext import _C  # noqa: F401  (fails with a message saying how to build, if missing or stale)
from . import autograd, geometry, nn, render
from .render import render_scene, render_texels

__version__ = "0.1.0"
__all__ = ["render_texels", "render_scene", "autograd", "geometry", "nn", "render", "__version__"]
