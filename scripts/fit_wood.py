#!/usr/bin/env python
"""Fit an anatomically meaningful procedural solid-wood texture to one photograph of a board.

Curved Gabor filtering finds the growth rings and their phase, the board's location in the log is estimated from
the traced rings, then a WoodModel (tree axis, ring scale, radial distortion, colour map) is fitted with a cyclic
phase loss (stage 1) and a colour loss (stage 2); ``--photometric`` adds stage 3, geometry and colour map
refined against the photo's colours through the reparameterised render. Writes a run folder: fit.png, phase.npy,
fit_phase.npy, params.json, log.csv, convergence.png, orientation/magnitude/phase images, ring_overlay.png,
board_estimate.json, model.json + model.pt, fit_vs_photo.png, phase_error.png, cube_preview.png, summary.json (with
--photometric also fit_before_photometric.png and model_before_photometric.json + .pt).

Examples:
    python scripts/fit_wood.py board.png --pixel-size-mm 0.1 --out results/board
    python scripts/fit_wood.py board.jpg --dpi 600 --epochs 300 --out results/board600
    python scripts/fit_wood.py board.png --photometric --out results/board_photo
"""
import os
import sys

try:
    import torch_appearance  # noqa: F401
except ModuleNotFoundError as error:  # running from a checkout that is not installed
    if error.name != "torch_appearance":
        raise
    sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from torch_appearance.pipelines.wood.cli import main

if __name__ == "__main__":
    sys.exit(main())
