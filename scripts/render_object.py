#!/usr/bin/env python
"""Shim for the ``ta-render-object`` command (torch_appearance/cli/render_object.py): ``python scripts/render_object.py ARGS`` = ``ta-render-object ARGS``."""
import sys

from torch_appearance.cli.render_object import main

if __name__ == "__main__":
    sys.exit(main())
