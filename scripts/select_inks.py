#!/usr/bin/env python
"""Shim for the ``ta-select-inks`` command (torch_appearance/cli/select_inks.py): ``python scripts/select_inks.py ARGS`` = ``ta-select-inks ARGS``."""
import sys

from torch_appearance.cli.select_inks import main

if __name__ == "__main__":
    sys.exit(main())
