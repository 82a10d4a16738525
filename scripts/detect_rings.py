#!/usr/bin/env python
"""Shim for the ``ta-detect-rings`` command (torch_appearance/cli/detect_rings.py): ``python scripts/detect_rings.py ARGS`` = ``ta-detect-rings ARGS``."""
import sys

from torch_appearance.cli.detect_rings import main

if __name__ == "__main__":
    sys.exit(main())
