"""Fabrication: ink library, probabilistic quantisation to printer resolution (with optional blue-noise halftoning),
printer profiles, and printer output: PNG slice stacks, GrabCAD Voxel Print packages and 3MF files."""
from .inks import DEFAULT_INKS, INKS, Ink, InkSet, ink_from_dict
from .quantize import (HALFTONES, PRINTER_DPI, index_volume_to_weights, iter_quantized, micro_grid_pitch,
                       micro_grid_shape, micro_voxel_size, quantize_mixture, resample_nearest, source_index,
                       hold_fixed_fractions)
from .export import IndexVolumeLayers, export_slices, load_index_volume, read_slices, save_index_volume
from .printer import PrinterProfile, builtin_printers, load_printer
from .gcvf import read_gcvf, write_gcvf
from .threemf import write_3mf
from .threemf_read import iter_3mf_layers, read_3mf

__all__ = [
    "Ink", "InkSet", "INKS", "DEFAULT_INKS", "ink_from_dict",
    "PRINTER_DPI", "micro_voxel_size", "micro_grid_shape", "micro_grid_pitch", "source_index", "resample_nearest",
    "quantize_mixture", "iter_quantized", "HALFTONES", "hold_fixed_fractions", "index_volume_to_weights",
    "export_slices", "read_slices", "save_index_volume", "load_index_volume", "IndexVolumeLayers",
    "PrinterProfile", "load_printer", "builtin_printers", "write_gcvf", "read_gcvf", "write_3mf", "read_3mf",
    "iter_3mf_layers",
]
