"""Printer input: per-layer slice PNGs with a palette, and compressed material-index volumes (.npz).

Slices (the form voxel-print workflows take): ``slice_0000.png`` is the bottom layer (z index 0), numbering
upward; each is an 8-bit RGB PNG with row j ↔ y index j and column i ↔ x index i (the layout of
:func:`torch_appearance.render_texels` images), every pixel exactly the palette colour of its ink
(``round(255 · Ink.display_rgb)``, sRGB). ``palette.json`` beside them maps colours to inks::

    {"inks": [{"index": 0, "name": "cyan", "rgb": [0, 255, 255], "sigma_t": [...], "albedo": [...], "g": 0.4},
              ...],
     "layer_thickness_mm": 0.0270..., "dpi": [600, 300, 940], "order": "bottom_to_top",
     "layers": Dz, "shape": [Dz, Hy, Wx], "file_pattern": "slice_{:04d}.png"}

Objects: micro-voxels outside the object hold :data:`VOID` (255, "no material"); their pixels take the colour
``palette["void"]["rgb"]`` (not an ink's colour), and :func:`read_slices` maps it back to 255.

Every file is written atomically (temporary file + :func:`os.replace`); ``palette.json`` is written last.
"""
import io as _stdio
import json
import os
import re

import cv2
import numpy as np

from .. import io as _io
from ..checks import check_path, describe
from .inks import InkSet, ink_from_dict
from .quantize import PRINTER_DPI, _check_dpi

__all__ = ["export_slices", "read_slices", "save_index_volume", "load_index_volume", "VOID", "VOID_RGB"]

#: Material index of "no material" (outside an object) in index volumes.
VOID = 255
#: Slice colour of VOID micro-voxels (sRGB bytes), distinct from the built-in inks' colours.
VOID_RGB = (0, 96, 0)

_SLICE_RE = re.compile(r"^slice_(\d{4,})\.png$")
_PALETTE = "palette.json"


def _check_indices(indices, n_inks=None):
    if not isinstance(indices, np.ndarray):
        raise TypeError(f"indices: expected a numpy.ndarray of dtype uint8 and shape (Dz, Hy, Wx), "
                        f"got {type(indices).__name__}")
    if indices.dtype != np.uint8:
        raise TypeError(f"indices: expected dtype uint8, got {indices.dtype}")
    if indices.ndim != 3 or min(indices.shape) < 1:
        raise ValueError(f"indices: expected shape (Dz, Hy, Wx) with all sizes >= 1, got {indices.shape}")
    if n_inks is not None:
        bad = (indices >= n_inks) & (indices != VOID)
        if bad.any():
            raise ValueError(f"indices: expected values in [0, {n_inks}) (one per ink) or {VOID} (void), got "
                             f"{int(indices[bad][0])}")
    return indices


def _check_inks(inks):
    if not isinstance(inks, InkSet):
        raise TypeError(f"inks: expected an InkSet, got {describe(inks)}")
    return inks


def _check_folder(folder):
    return check_path("folder", folder)


def _codes(rgb):
    """(..., 3) uint8 → (...) int64 colour codes r·65536 + g·256 + b."""
    rgb = rgb.astype(np.int64)
    return (rgb[..., 0] << 16) | (rgb[..., 1] << 8) | rgb[..., 2]


def export_slices(indices, inks, folder, *, dpi=PRINTER_DPI):
    """Write one RGB PNG per printer layer plus ``palette.json`` (see the module docstring for the format).

    Args:
        indices: (Dz, Hy, Wx) ``uint8`` material indices (e.g. from
            :func:`~torch_appearance.fabrication.quantize_mixture`), layer 0 at the bottom.
        inks: the :class:`InkSet` the indices refer to; palette colours must be distinct after 8-bit rounding.
        folder: output folder (created if missing). Stale ``slice_*.png`` files from an earlier, thicker export
            are removed.
        dpi: printer resolution ``(x, y, z)``, recorded in the palette (layer thickness 25.4 / dpi_z mm).

    Returns:
        The palette dict that was written.

    Raises:
        TypeError, ValueError: naming the argument (wrong dtype/shape, an index without an ink, two inks
            sharing a palette colour).
    """
    inks = _check_inks(inks)
    indices = _check_indices(indices, len(inks))
    folder = _check_folder(folder)
    dpi = _check_dpi(dpi, "dpi")
    rgb = inks.display_rgb()                                    # (N, 3) uint8
    codes = _codes(rgb)
    if len(np.unique(codes)) != len(codes):
        clashes = [f"{inks.names[i]}/{inks.names[j]}" for i in range(len(inks)) for j in range(i + 1, len(inks))
                   if codes[i] == codes[j]]
        raise ValueError(f"inks: slice colours must be distinct to be read back, but these inks share a "
                         f"display_rgb (after 8-bit rounding): {clashes}")
    void = bool((indices == VOID).any())
    if void and _codes(np.array(VOID_RGB)) in set(codes.tolist()):
        raise ValueError(f"inks: an ink's display_rgb equals the void colour {VOID_RGB}; change the ink's colour")
    os.makedirs(folder, exist_ok=True)
    palette = {
        "inks": [dict(index=i, name=ink.name, rgb=[int(v) for v in rgb[i]], sigma_t=list(ink.sigma_t),
                      albedo=list(ink.albedo), g=ink.g) for i, ink in enumerate(inks)],
        "layer_thickness_mm": 25.4 / dpi[2],
        "dpi": [int(v) if float(v).is_integer() else v for v in dpi],
        "order": "bottom_to_top",
        "layers": int(indices.shape[0]),
        "shape": [int(v) for v in indices.shape],
        "file_pattern": "slice_{:04d}.png",
    }
    if void:
        palette["void"] = {"index": VOID, "rgb": list(VOID_RGB)}
    # Remove the palette first: a folder with stale slices but no palette is recognisably incomplete.
    if os.path.exists(os.path.join(folder, _PALETTE)):
        os.remove(os.path.join(folder, _PALETTE))
    bgr_palette = np.zeros((256, 3), dtype=np.uint8)
    bgr_palette[:len(rgb)] = rgb[:, ::-1]                       # OpenCV stores B, G, R
    bgr_palette[VOID] = VOID_RGB[::-1]
    for z in range(indices.shape[0]):
        ok, encoded = cv2.imencode(".png", bgr_palette[indices[z]])
        if not ok:
            raise RuntimeError(f"OpenCV failed to encode slice {z} of shape {indices.shape[1:]}")
        _io.atomic_write_bytes(os.path.join(folder, f"slice_{z:04d}.png"), encoded.tobytes())
    for name in os.listdir(folder):
        match = _SLICE_RE.match(name)
        if match and int(match.group(1)) >= indices.shape[0]:
            os.remove(os.path.join(folder, name))
    _io.write_json(os.path.join(folder, _PALETTE), palette)
    return palette


def read_slices(folder):
    """Read a folder written by :func:`export_slices`.

    Returns:
        (indices, palette): ``uint8`` (Dz, Hy, Wx) material indices (layer 0 at the bottom) and the parsed
        ``palette.json`` dict.

    Raises:
        FileNotFoundError: the folder, ``palette.json`` or a slice is missing.
        ValueError: a slice has another size, is not 8-bit RGB, or holds a colour that is not in the palette.
    """
    folder = _check_folder(folder)
    with open(os.path.join(folder, _PALETTE), "r", encoding="utf-8") as handle:
        try:
            palette = json.load(handle)
        except json.JSONDecodeError as error:
            raise ValueError(f"{os.path.join(folder, _PALETTE)!r}: not valid JSON: {error}") from None
    try:
        shape = tuple(int(v) for v in palette["shape"])
        entries = sorted(palette["inks"], key=lambda e: int(e["index"]))
        colours = np.array([e["rgb"] for e in entries], dtype=np.int64)
    except (KeyError, TypeError, ValueError) as error:
        raise ValueError(f"{os.path.join(folder, _PALETTE)!r}: malformed palette ({error!r})") from None
    if [int(e["index"]) for e in entries] != list(range(len(entries))) or colours.shape != (len(entries), 3):
        raise ValueError(f"{os.path.join(folder, _PALETTE)!r}: ink indices must be 0..N-1 with 3 rgb values each")
    index_of = np.arange(len(entries))
    if "void" in palette:
        colours = np.concatenate([colours, np.array([palette["void"]["rgb"]], dtype=np.int64)])
        index_of = np.append(index_of, VOID)
    codes = _codes(colours)
    order = np.argsort(codes)
    sorted_codes = codes[order]
    indices = np.empty(shape, dtype=np.uint8)
    for z in range(shape[0]):
        path = os.path.join(folder, f"slice_{z:04d}.png")
        image, info = _io.decode_image(path, name="slice")  # RGB as stored; truncated/corrupt files refused
        if info["format"] != "PNG" or image.dtype != np.uint8 or image.shape[2] != 3:
            raise ValueError(f"{path!r}: expected an 8-bit RGB PNG, got {info['bits']}-bit {info['format']} with "
                             f"{image.shape[2]} channel(s)")
        if image.shape[:2] != shape[1:]:
            raise ValueError(f"{path!r}: expected size (H, W) = {shape[1:]}, got {image.shape[:2]}")
        pixel = _codes(image)
        pos = np.clip(np.searchsorted(sorted_codes, pixel), 0, len(sorted_codes) - 1)
        known = sorted_codes[pos] == pixel
        if not known.all():
            j, i = np.argwhere(~known)[0]
            raise ValueError(f"{path!r}: pixel (row {j}, column {i}) has colour {image[j, i].tolist()}, "
                             f"which is not in the palette {colours.tolist()}")
        indices[z] = index_of[order[pos]]
    return indices, palette


def save_index_volume(path, indices, inks, dpi=PRINTER_DPI):
    """Save a material-index volume with its inks and printer resolution as a compressed ``.npz`` (atomic).

    The archive holds ``indices`` (uint8, (Dz, Hy, Wx), layer 0 at the bottom), ``dpi`` (float64 (3,), x, y, z)
    and ``inks_json`` (the ink list as JSON text); it loads with ``allow_pickle=False``.
    """
    path = check_path("path", path, (".npz",))
    inks = _check_inks(inks)
    indices = _check_indices(indices, len(inks))
    dpi = _check_dpi(dpi, "dpi")
    buffer = _stdio.BytesIO()
    np.savez_compressed(buffer, indices=indices, dpi=np.asarray(dpi, dtype=np.float64),
                        inks_json=np.asarray(json.dumps([ink.to_dict() for ink in inks])))
    _io.atomic_write_bytes(path, buffer.getvalue())


def load_index_volume(path):
    """Load a volume written by :func:`save_index_volume`.

    Returns:
        (indices, inks, dpi): ``uint8`` (Dz, Hy, Wx), the :class:`InkSet`, and ``(x, y, z)`` floats.

    Raises:
        FileNotFoundError: no such file.
        ValueError: the archive lacks an entry or holds invalid data.
    """
    path = check_path("path", path)
    with np.load(path, allow_pickle=False) as archive:
        missing = [k for k in ("indices", "dpi", "inks_json") if k not in archive.files]
        if missing:
            raise ValueError(f"{path!r}: not an index volume, missing entries {missing}")
        indices, dpi, inks_json = archive["indices"], archive["dpi"], str(archive["inks_json"])
    inks = InkSet([ink_from_dict(e, where=f"{path}: inks[{i}]") for i, e in enumerate(json.loads(inks_json))])
    return _check_indices(indices, len(inks)), inks, _check_dpi(tuple(dpi.tolist()), "dpi")
