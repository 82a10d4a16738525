#!/usr/bin/env python
"""Shim for the ``ta-render-wood-volume`` command (torch_appearance/cli/render_wood_volume.py): ``python scripts/render_wood_volume.py ARGS`` = ``ta-render-wood-volume ARGS``."""
import sys

from torch_appearance.cli.render_wood_volume import main

if __name__ == "__main__":
    sys.exit(main())
