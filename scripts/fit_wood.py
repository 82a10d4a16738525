#!/usr/bin/env python
"""Shim for the ``ta-fit-wood`` command (torch_appearance/cli/fit_wood.py): ``python scripts/fit_wood.py ARGS`` = ``ta-fit-wood ARGS``."""
import sys

from torch_appearance.cli.fit_wood import main

if __name__ == "__main__":
    sys.exit(main())
