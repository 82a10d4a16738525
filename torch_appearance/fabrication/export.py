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
import zipfile

import cv2
import numpy as np

from .. import io as _io
from ..checks import check_path, describe
from .inks import InkSet, ink_from_dict
from .quantize import PRINTER_DPI, _check_dpi

__all__ = ["export_slices", "read_slices", "save_index_volume", "load_index_volume", "IndexVolumeLayers", "VOID",
           "VOID_RGB"]

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


def palette_decoder(colours, values, unknown):
    """A function ``decode(image, where)`` mapping an (H, W, 3) uint8 RGB image whose pixels are exactly the
    ``colours`` (K, 3) to ``values`` (K,) uint8; a pixel of another colour raises ValueError naming ``where``, the
    pixel and its colour, "which is ``unknown``"."""
    codes = _codes(np.asarray(colours))
    order = np.argsort(codes)
    sorted_codes, sorted_values = codes[order], np.asarray(values, np.uint8)[order]

    def decode(image, where):
        pixel = _codes(image)
        pos = np.clip(np.searchsorted(sorted_codes, pixel), 0, len(sorted_codes) - 1)
        known = sorted_codes[pos] == pixel
        if not known.all():
            j, i = np.argwhere(~known)[0]
            raise ValueError(f"{where}: pixel (row {j}, column {i}) has colour {image[j, i].tolist()}, which is "
                             f"{unknown}")
        return sorted_values[pos]

    return decode


def export_slices(indices, inks, folder, *, dpi=PRINTER_DPI, progress=None):
    """Write one RGB PNG per printer layer plus ``palette.json`` (see the module docstring for the format).

    Args:
        indices: (Dz, Hy, Wx) ``uint8`` material indices (e.g. from
            :func:`~torch_appearance.fabrication.quantize_mixture`), layer 0 at the bottom; or a layer source with
            ``shape`` that yields the (Hy, Wx) layers in order (e.g. :class:`IndexVolumeLayers`): it is read once,
            one layer at a time.
        inks: the :class:`InkSet` the indices refer to; palette colours must be distinct after 8-bit rounding.
        folder: output folder (created if missing). Stale ``slice_*.png`` files from an earlier, thicker export
            are removed.
        dpi: printer resolution ``(x, y, z)``, recorded in the palette (layer thickness 25.4 / dpi_z mm).
        progress: optional callable ``progress(k)`` after layer k.

    Returns:
        The palette dict that was written.

    Raises:
        TypeError, ValueError: naming the argument (wrong dtype/shape, an index without an ink, two inks
            sharing a palette colour).
    """
    inks = _check_inks(inks)
    if isinstance(indices, np.ndarray):
        indices = _check_indices(indices, len(inks))
        void = bool((indices == VOID).any())
    else:
        void = None                                             # found out layer by layer
    shape = getattr(indices, "shape", None)
    if shape is None or len(shape) != 3:
        raise TypeError(f"indices: expected a (Dz, Hy, Wx) uint8 ndarray or a layer source, got {describe(indices)}")
    folder = _check_folder(folder)
    dpi = _check_dpi(dpi, "dpi")
    rgb = inks.display_rgb()                                    # (N, 3) uint8
    codes = _codes(rgb)
    if len(np.unique(codes)) != len(codes):
        clashes = [f"{inks.names[i]}/{inks.names[j]}" for i in range(len(inks)) for j in range(i + 1, len(inks))
                   if codes[i] == codes[j]]
        raise ValueError(f"inks: slice colours must be distinct to be read back, but these inks share a "
                         f"display_rgb (after 8-bit rounding): {clashes}")
    void_clash = _codes(np.array(VOID_RGB)) in set(codes.tolist())
    if void and void_clash:
        raise ValueError(f"inks: an ink's display_rgb equals the void colour {VOID_RGB}; change the ink's colour")
    os.makedirs(folder, exist_ok=True)
    # Remove the palette first: a folder with stale slices but no palette is recognisably incomplete.
    if os.path.exists(os.path.join(folder, _PALETTE)):
        os.remove(os.path.join(folder, _PALETTE))
    bgr_palette = np.zeros((256, 3), dtype=np.uint8)
    bgr_palette[:len(rgb)] = rgb[:, ::-1]                       # OpenCV stores B, G, R
    bgr_palette[VOID] = VOID_RGB[::-1]
    dz, hy, wx = (int(v) for v in shape)
    seen_void = False
    z = -1
    for z, layer in enumerate(indices):
        if z >= dz:
            raise ValueError(f"indices: expected {dz} layers, got more")
        layer = _check_indices(np.asarray(layer)[None], len(inks))[0] if void is None else layer
        if layer.shape != (hy, wx):
            raise ValueError(f"indices: layer {z}: expected shape {(hy, wx)}, got {layer.shape}")
        if void is None and not seen_void and (layer == VOID).any():
            seen_void = True
            if void_clash:
                raise ValueError(f"inks: an ink's display_rgb equals the void colour {VOID_RGB}; change the ink's "
                                 f"colour")
        ok, encoded = cv2.imencode(".png", bgr_palette[layer])
        if not ok:
            raise RuntimeError(f"OpenCV failed to encode slice {z} of shape {(hy, wx)}")
        _io.atomic_write_bytes(os.path.join(folder, f"slice_{z:04d}.png"), encoded.tobytes())
        if progress is not None:
            progress(z)
    if z + 1 != dz:
        raise ValueError(f"indices: expected {dz} layers, got {z + 1}")
    palette = {
        "inks": [dict(index=i, name=ink.name, rgb=[int(v) for v in rgb[i]], sigma_t=list(ink.sigma_t),
                      albedo=list(ink.albedo), g=ink.g) for i, ink in enumerate(inks)],
        "layer_thickness_mm": 25.4 / dpi[2],
        "dpi": [int(v) if float(v).is_integer() else v for v in dpi],
        "order": "bottom_to_top",
        "layers": dz,
        "shape": [dz, hy, wx],
        "file_pattern": "slice_{:04d}.png",
    }
    if void or seen_void:
        palette["void"] = {"index": VOID, "rgb": list(VOID_RGB)}
    for name in os.listdir(folder):
        match = _SLICE_RE.match(name)
        if match and int(match.group(1)) >= dz:
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
    decode = palette_decoder(colours, index_of, f"not in the palette {colours.tolist()}")
    indices = np.empty(shape, dtype=np.uint8)
    for z in range(shape[0]):
        path = os.path.join(folder, f"slice_{z:04d}.png")
        image, info = _io.decode_image(path, name="slice")  # RGB as stored; truncated/corrupt files refused
        if info["format"] != "PNG" or image.dtype != np.uint8 or image.shape[2] != 3:
            raise ValueError(f"{path!r}: expected an 8-bit RGB PNG, got {info['bits']}-bit {info['format']} with "
                             f"{image.shape[2]} channel(s)")
        if image.shape[:2] != shape[1:]:
            raise ValueError(f"{path!r}: expected size (H, W) = {shape[1:]}, got {image.shape[:2]}")
        indices[z] = decode(image, repr(path))
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


def npy_header(handle, where):
    """``(shape, fortran_order, dtype)`` of the ``.npy`` array that the open binary ``handle`` (e.g. a member of an
    ``.npz`` opened with :mod:`zipfile`) starts with; the handle is left at the first byte of the data, which is not
    read. ValueError naming ``where`` for a file that is not ``.npy`` version 1 or 2."""
    version = np.lib.format.read_magic(handle)
    read = {(1, 0): np.lib.format.read_array_header_1_0, (2, 0): np.lib.format.read_array_header_2_0}.get(version)
    if read is None:
        raise ValueError(f"{where}: unsupported .npy version {version}")
    return read(handle)


class IndexVolumeLayers:
    """The layers of a volume written by :func:`save_index_volume`, read one at a time (never the whole volume).

    ``shape`` (Dz, Hy, Wx), ``inks`` and ``dpi`` come from the archive; iterating yields the ``uint8`` (Hy, Wx)
    layers bottom to top, decompressed from the archive as they are read, so memory stays at one layer whatever the
    number of layers (a 40 mm object at printer resolution holds ~660 M voxels). Each iteration re-reads the file.

    Raises:
        FileNotFoundError: no such file.
        ValueError: not an index volume, a volume that is not uint8 (Dz, Hy, Wx) in C order, a truncated file.

    Example:
        >>> import tempfile, numpy as np
        >>> from torch_appearance.fabrication import InkSet
        >>> path = tempfile.mkdtemp() + "/q.npz"
        >>> save_index_volume(path, np.arange(24, dtype=np.uint8).reshape(2, 3, 4) % 5, InkSet.from_names())
        >>> layers = IndexVolumeLayers(path)
        >>> layers.shape, [int(layer.sum()) for layer in layers]
        ((2, 3, 4), [21, 25])
    """

    def __init__(self, path):
        self.path = check_path("path", path)
        if not os.path.isfile(self.path):
            raise FileNotFoundError(f"path: no such file {self.path!r}")
        try:
            with zipfile.ZipFile(self.path) as archive:
                missing = [k for k in ("indices.npy", "dpi.npy", "inks_json.npy") if k not in archive.namelist()]
                if missing:
                    raise ValueError(f"{self.path!r}: not an index volume, missing entries {missing}")
                with np.load(self.path, allow_pickle=False) as small:
                    dpi, inks_json = small["dpi"], str(small["inks_json"])
                with archive.open("indices.npy") as handle:
                    self._header(handle)
        except zipfile.BadZipFile as error:
            raise ValueError(f"{self.path!r}: not an index volume (not a zip archive: {error})") from None
        self.inks = InkSet([ink_from_dict(e, where=f"{self.path}: inks[{i}]")
                            for i, e in enumerate(json.loads(inks_json))])
        self.dpi = _check_dpi(tuple(dpi.tolist()), "dpi")

    def _header(self, handle):
        shape, fortran, dtype = npy_header(handle, repr(self.path))
        if dtype != np.uint8 or fortran or len(shape) != 3 or min(shape) < 1:
            raise ValueError(f"{self.path!r}: expected uint8 indices (Dz, Hy, Wx) in C order, got {dtype} "
                             f"{shape}{' (Fortran order)' if fortran else ''}")
        self.shape = tuple(int(v) for v in shape)

    def __len__(self):
        return self.shape[0]

    def __iter__(self):
        _, hy, wx = self.shape
        with zipfile.ZipFile(self.path) as archive, archive.open("indices.npy") as handle:
            self._header(handle)
            for k in range(self.shape[0]):
                data = handle.read(hy * wx)
                if len(data) != hy * wx:
                    raise ValueError(f"{self.path!r}: truncated at layer {k} of {self.shape[0]}")
                yield np.frombuffer(data, np.uint8).reshape(hy, wx)
