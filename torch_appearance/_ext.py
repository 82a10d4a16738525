"""Loads the compiled core ``torch_appearance._C`` and refuses a missing or stale build with the fix; calls its tracer
entry points so that Ctrl-C interrupts them (:func:`call_tracer`)."""
import os

import torch

from ._buildinfo import source_hash

_FIX = ("Build it from the repository root with `make build` (or: pip install -e . --no-build-isolation; "
        "python setup.py build_ext --inplace).")


def _load():
    try:
        from . import _C  # noqa: WPS433 - the compiled extension
    except ImportError as exc:
        raise ImportError(f"torch_appearance: the C++ extension torch_appearance._C is missing or does not load "
                          f"({exc}). {_FIX}") from exc
    check_build(_C.source_hash, _C.torch_version)
    return _C


def check_build(built_hash, built_torch, csrc_dir=None):
    """Raise ImportError if the extension was built from other sources or against another torch.

    Args:
        built_hash: the source hash recorded in the extension at build time.
        built_torch: ``torch.__version__`` at build time.
        csrc_dir: the C++ source folder to compare with (default: ``csrc/`` beside the package, present in a
            source checkout; an installed wheel has none and only the torch version is checked).
    """
    if os.environ.get("TORCH_APPEARANCE_ALLOW_STALE_BUILD") == "1":
        return
    if built_torch != torch.__version__:
        raise ImportError(f"torch_appearance: the C++ extension was built against torch {built_torch} but torch "
                          f"{torch.__version__} is installed. Rebuild it: {_FIX}")
    if csrc_dir is None:
        csrc_dir = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "csrc")
    if os.path.isdir(csrc_dir):
        current = source_hash(csrc_dir)
        if current != built_hash:
            raise ImportError(f"torch_appearance: the C++ extension is stale: csrc/ changed since it was built "
                              f"(built from sources {built_hash}, checkout has {current}). Rebuild it: {_FIX} "
                              f"(set TORCH_APPEARANCE_ALLOW_STALE_BUILD=1 to import anyway).")


_INTERRUPTED = "interrupted (SIGINT)"


def call_tracer(entry, *args):
    """``entry(*args)`` for a C++ entry point of the tracer, with Ctrl-C: the tracer polls SIGINT between sensor
    elements (csrc/volpath/interrupt.h), stops within moments instead of finishing a render of minutes, and its
    "interrupted" error becomes the ``KeyboardInterrupt`` Python code expects."""
    try:
        return entry(*args)
    except RuntimeError as error:
        if _INTERRUPTED in str(error):
            raise KeyboardInterrupt(f"{_INTERRUPTED} during a render") from None
        raise


_C = _load()
