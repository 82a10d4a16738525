#!/usr/bin/env python
"""Shim for the ``ta-optimize-print`` command (torch_appearance/cli/optimize_print.py): ``python scripts/optimize_print.py ARGS`` = ``ta-optimize-print ARGS``."""
import sys

from torch_appearance.cli.optimize_print import main

if __name__ == "__main__":
    sys.exit(main())
