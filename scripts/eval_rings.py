#!/usr/bin/env python
"""Shim for the ``ta-eval-rings`` command (torch_appearance/cli/eval_rings.py): ``python scripts/eval_rings.py ARGS`` = ``ta-eval-rings ARGS``."""
import sys

from torch_appearance.cli.eval_rings import main

if __name__ == "__main__":
    sys.exit(main())
