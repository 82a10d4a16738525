"""Fabrication: ink library, probabilistic quantisation to printer resolution, slice and volume export."""
from .inks import DEFAULT_INKS, INKS, Ink, InkSet, ink_from_dict
from .quantize import (PRINTER_DPI, index_volume_to_weights, micro_grid_pitch, micro_grid_shape, micro_voxel_size,
                       quantize_mixture, resample_nearest, source_index, hold_fixed_fractions)
from .export import export_slices, load_index_volume, read_slices, save_index_volume

__all__ = [
    "Ink", "InkSet", "INKS", "DEFAULT_INKS", "ink_from_dict",
    "PRINTER_DPI", "micro_voxel_size", "micro_grid_shape", "micro_grid_pitch", "source_index", "resample_nearest",
    "quantize_mixture", "hold_fixed_fractions", "index_volume_to_weights",
    "export_slices", "read_slices", "save_index_volume", "load_index_volume",
]
