#!/usr/bin/env python
"""Optimise the ink arrangement of a printed slab or textured object so that its rendered look matches a target.

The command line is :func:`torch_appearance.pipelines.print.cli.main` (``--help`` lists the flags and examples).
"""
import os
import sys

try:
    import torch_appearance  # noqa: F401
except ModuleNotFoundError as error:  # running from a checkout that is not installed
    if error.name != "torch_appearance":
        raise
    sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from torch_appearance.pipelines.print.cli import main

if __name__ == "__main__":
    sys.exit(main())
