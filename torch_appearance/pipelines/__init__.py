"""Optimisation loops as library functions (used by scripts/ and tests): the print optimisation
(:mod:`torch_appearance.pipelines.print`) and the wood fit (:mod:`torch_appearance.pipelines.wood`)."""
from .print import PrintConfig, colorchecker_target, load_target, optimize_print, zebra_target

__all__ = ["PrintConfig", "optimize_print", "load_target", "zebra_target", "colorchecker_target"]
