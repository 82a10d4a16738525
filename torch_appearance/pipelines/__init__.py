"""Optimisation loops as library functions (used by scripts/ and tests)."""
from .print_optimization import PrintConfig, optimize_print
from .targets import colorchecker_target, load_target, zebra_target

__all__ = ["PrintConfig", "optimize_print", "load_target", "zebra_target", "colorchecker_target"]
