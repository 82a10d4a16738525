"""torch_appearance: appearance matching and fabrication with differentiable material models.

The core is a differentiable heterogeneous-volume path tracer in C++ (``torch_appearance._C``) whose backward
pass is radiative backpropagation by path replay; see :func:`render_texels` (slabs) and :func:`render_scene`
(general scenes).

Importing the package imports only the standard library: torch, the compiled core and the subpackages load on first
use of a name (``torch_appearance.render_scene``, ``torch_appearance.nn``, PEP 562), and a missing or stale build is
refused then, with how to build it (:mod:`torch_appearance._ext`). The ``ta-…`` commands rely on it: their entry
points (:mod:`torch_appearance.cli.entry`) take over Ctrl-C before torch loads.
"""
import importlib

__version__ = "0.1.0"
__all__ = ["render_texels", "render_scene", "autograd", "geometry", "nn", "render", "__version__"]

#: name -> (module relative to the package, attribute of it or None for the module itself), loaded on first access
_LAZY = {
    "_C": ("._ext", "_C"),  # through _ext, which refuses a missing or stale build with the fix
    "render_texels": (".render", "render_texels"),
    "render_scene": (".render", "render_scene"),
    "autograd": (".autograd", None),
    "geometry": (".geometry", None),
    "nn": (".nn", None),
    "render": (".render", None),
}


def __getattr__(name):
    try:
        module, attribute = _LAZY[name]
    except KeyError:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}") from None
    value = importlib.import_module(module, __name__)
    if attribute is not None:
        value = getattr(value, attribute)
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(_LAZY))
