#!/usr/bin/env python
"""Shim for the ``ta-voxelize`` command (torch_appearance/cli/voxelize.py): ``python scripts/voxelize.py ARGS`` = ``ta-voxelize ARGS``."""
import sys

from torch_appearance.cli.voxelize import main

if __name__ == "__main__":
    sys.exit(main())
