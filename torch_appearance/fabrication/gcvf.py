"""GrabCAD Voxel Print packages (``.gcvf``) for Stratasys PolyJet printers, written layer by layer, and read back.

A ``.gcvf`` file is a zip archive of one PNG per printer layer and a ``ConfigFile.xml``. The layout below is the
one that public converters write and GrabCAD Print opens (e.g. the open-source ``buildGCVF.js`` converters on
GitHub, which normalise slices to 24-bit PNGs named ``layer_<k>.png`` numbered from 0 without gaps or zero
padding, and write ``ConfigFile.xml`` with ``Version`` 2, the x/y DPI, the slice thickness in nanometres,
``BitDepth``, ``MaxNumberOfColors``, ``DataSemantics`` "Materials", ``ImageFilePrefix`` and a ``MaterialList`` of
``Name`` / ``RGBA`` / ``VoxelCount`` entries after the ``BackGroundMaterialRGBA``)::

    layer_0.png ... layer_{Dz-1}.png   8-bit RGB, bottom layer first, row j ↔ y index j, column i ↔ x index i;
                                        each pixel is the RGB of its voxel's material, or the background's
    ConfigFile.xml                      <GCVF><Version>2</Version>
                                          <Resolution><XDpi/><YDpi/><SliceThicknessNanoMeter/></Resolution>
                                          <SliceDimensions><SliceWidth/><SliceHeight/></SliceDimensions>
                                          <SliceRange><StartIndex>0</StartIndex><NumberOfSlices/></SliceRange>
                                          <BitDepth/><MaxNumberOfColors/><DataSemantics>Materials</DataSemantics>
                                          <CreationMode>MODEL_ONLY</CreationMode><ImageFilePrefix>layer_</...>
                                          <MaterialList><BackGroundMaterialRGBA/>
                                            <Material><Name/><RGBA/><VoxelCount/></Material>...</MaterialList>
                                        </GCVF>

Material names, colours, resolution, layer thickness and bit depth come from a :class:`.PrinterProfile`. The
archive is written to a temporary file beside ``path`` one layer at a time (peak memory: one layer) and renamed at
the end, so a failed export leaves nothing.
"""
import os
import re
import xml.etree.ElementTree as ET
import zipfile

import cv2
import numpy as np

from ..checks import check_path, describe
from ..io import atomic_output
from .export import palette_decoder
from .printer import load_printer

__all__ = ["write_gcvf", "read_gcvf", "CONFIG_FILE", "LAYER_PREFIX"]

CONFIG_FILE = "ConfigFile.xml"
LAYER_PREFIX = "layer_"
_VOID = 255
_LAYER_RE = re.compile(r"^layer_(0|[1-9]\d*)\.png$")


def check_layers(layers, name="layers"):
    """``(shape, iterable)`` of a layer source: a uint8 ``(Dz, Hy, Wx)`` ndarray or an object with ``shape`` and
    iteration over its ``Dz`` layers (e.g. :class:`~torch_appearance.fabrication.export.IndexVolumeLayers`)."""
    shape = getattr(layers, "shape", None)
    if shape is None or len(shape) != 3 or not all(int(v) >= 1 for v in shape):
        raise TypeError(f"{name}: expected a (Dz, Hy, Wx) uint8 volume or a layer source with a shape, got "
                        f"{describe(layers)}")
    return tuple(int(v) for v in shape), layers


def _material_table(printer, ink_names):
    """The materials the inks print with (each once, in ink order) and the ink → that list's index table."""
    per_ink = printer.material_indices(ink_names)
    used = list(dict.fromkeys(per_ink))
    lut = np.full(256, _VOID, dtype=np.uint8)
    lut[:len(per_ink)] = [used.index(m) for m in per_ink]
    return [printer.materials[m] for m in used], lut


def _xml_text(parent, tag, text):
    ET.SubElement(parent, tag).text = str(text)


def _config_xml(printer, shape, materials, counts):
    dz, hy, wx = shape
    root = ET.Element("GCVF")
    _xml_text(root, "Version", 2)
    res = ET.SubElement(root, "Resolution")
    _xml_text(res, "XDpi", f"{printer.dpi_xy[0]:g}")
    _xml_text(res, "YDpi", f"{printer.dpi_xy[1]:g}")
    _xml_text(res, "SliceThicknessNanoMeter", f"{printer.layer_thickness_nm:g}")
    dims = ET.SubElement(root, "SliceDimensions")
    _xml_text(dims, "SliceWidth", wx)
    _xml_text(dims, "SliceHeight", hy)
    rng = ET.SubElement(root, "SliceRange")
    _xml_text(rng, "StartIndex", 0)
    _xml_text(rng, "NumberOfSlices", dz)
    _xml_text(root, "BitDepth", printer.bit_depth)
    _xml_text(root, "MaxNumberOfColors", len(printer.materials))
    _xml_text(root, "DataSemantics", "Materials")
    _xml_text(root, "CreationMode", "MODEL_ONLY")
    _xml_text(root, "ImageFilePrefix", LAYER_PREFIX)
    mats = ET.SubElement(root, "MaterialList")
    _xml_text(mats, "BackGroundMaterialRGBA", " ".join(str(v) for v in printer.background_rgba))
    for (name, rgba), count in zip(materials, counts):
        m = ET.SubElement(mats, "Material")
        _xml_text(m, "Name", name)
        _xml_text(m, "RGBA", " ".join(str(v) for v in rgba))
        _xml_text(m, "VoxelCount", int(count))
    ET.indent(root, space="    ")
    body = ET.tostring(root, encoding="unicode")
    return ('<?xml version="1.0" encoding="UTF-8"?>\n<!-- GCVF - GrabCAD Voxel Print File, written by '
            'torch_appearance -->\n' + body + "\n").encode("utf-8")


def write_gcvf(path, layers, printer, ink_names, *, progress=None):
    """Write a GrabCAD Voxel Print package of an ink-index volume.

    Args:
        path: the ``.gcvf`` file to write (its folder must exist; an existing file is replaced only when the
            whole package is written).
        layers: ``uint8`` ``(Dz, Hy, Wx)`` ink indices (255 = no material), layer 0 at the bottom, or a layer source
            with ``shape`` that yields those layers in order (it is consumed once: the volume is never held).
        printer: a :class:`.PrinterProfile` or its name/path; its resolution is written, not checked here.
        ink_names: the names of the inks the indices refer to (index n ↔ ``ink_names[n]``), mapped to the printer's
            materials by the profile's ``inks`` table.
        progress: optional callable ``progress(k)`` after layer k.

    Returns:
        dict: ``materials`` (the names written), ``voxel_counts``, ``layers``, ``bytes`` (the package size).

    Raises:
        TypeError, ValueError: naming the argument (an ink the printer lacks, an index without an ink, a layer of
            another shape or count); nothing is left at ``path`` or beside it.
    """
    path = check_path("path", path, (".gcvf",))
    printer = load_printer(printer)
    ink_names = [str(n) for n in ink_names]
    (dz, hy, wx), source = check_layers(layers)
    materials, lut = _material_table(printer, ink_names)
    colours = np.zeros((256, 3), dtype=np.uint8)                       # BGR for OpenCV, by ink index
    colours[:] = printer.background_rgba[2::-1]
    for i in range(len(ink_names)):
        colours[i] = materials[lut[i]][1][2::-1]
    counts = np.zeros(len(materials), dtype=np.int64)
    with atomic_output(path) as tmp, zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_STORED,
                                                     allowZip64=True) as archive:
        k = -1
        for k, layer in enumerate(source):
            if k >= dz:
                raise ValueError(f"layers: expected {dz} layers, got more")
            layer = np.asarray(layer)
            if layer.shape != (hy, wx) or layer.dtype != np.uint8:
                raise ValueError(f"layers: layer {k}: expected uint8 of shape {(hy, wx)}, got {layer.dtype} "
                                 f"{layer.shape}")
            hist = np.bincount(layer.reshape(-1), minlength=256)
            bad = np.flatnonzero(hist[len(ink_names):_VOID]) + len(ink_names)
            if len(bad):
                raise ValueError(f"layers: layer {k} holds ink index {int(bad[0])}, but only "
                                 f"{len(ink_names)} inks {ink_names} are given")
            np.add.at(counts, lut[:len(ink_names)], hist[:len(ink_names)])
            ok, png = cv2.imencode(".png", colours[layer])
            if not ok:
                raise RuntimeError(f"OpenCV failed to encode layer {k} of shape {(hy, wx)}")
            archive.writestr(f"{LAYER_PREFIX}{k}.png", png.tobytes())  # PNG is compressed already: stored
            if progress is not None:
                progress(k)
        if k + 1 != dz:
            raise ValueError(f"layers: expected {dz} layers, got {k + 1}")
        archive.writestr(zipfile.ZipInfo(CONFIG_FILE, date_time=(2020, 1, 1, 0, 0, 0)),
                         _config_xml(printer, (dz, hy, wx), materials, counts), compress_type=zipfile.ZIP_DEFLATED)
    return {"materials": [m[0] for m in materials], "voxel_counts": counts.tolist(), "layers": dz,
            "bytes": os.path.getsize(path)}


def _child(node, tag, where):
    found = node.find(tag)
    if found is None or found.text is None:
        raise ValueError(f"{where}: {CONFIG_FILE} lacks <{tag}>")
    return found.text.strip()


def _ints(text, n, where, tag):
    try:
        values = [int(v) for v in text.split()]
    except ValueError:
        values = []
    if len(values) != n:
        raise ValueError(f"{where}: <{tag}> expected {n} integers, got {text!r}")
    return values


def read_gcvf(path):
    """Read a package written by :func:`write_gcvf` (or any GCVF of that layout) back.

    Returns:
        ``(indices, info)``: ``uint8`` ``(Dz, Hy, Wx)`` material indices into ``info["materials"]`` (255 where a
        pixel has the background colour), layer 0 at the bottom; ``info``: ``materials`` (names), ``rgba``,
        ``voxel_counts``, ``dpi_xy``, ``layer_thickness_nm``, ``bit_depth``, ``background_rgba``, ``layers``.

    Raises:
        FileNotFoundError: no such file.
        ValueError: not a zip, a truncated or corrupt archive or PNG, a missing or malformed ``ConfigFile.xml``,
            layers missing, extra, of another size, or holding a colour that is no material's.
    """
    path = check_path("path", path)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"path: no such file {path!r}")
    try:
        archive = zipfile.ZipFile(path)
    except (zipfile.BadZipFile, OSError) as error:
        raise ValueError(f"path: {path!r} is not a GCVF package (not a zip archive: {error})") from None
    with archive:
        names = set(archive.namelist())
        if CONFIG_FILE not in names:
            raise ValueError(f"path: {path!r} has no {CONFIG_FILE}")
        try:
            root = ET.fromstring(archive.read(CONFIG_FILE))
        except (ET.ParseError, zipfile.BadZipFile, OSError) as error:
            raise ValueError(f"path: {path!r}: {CONFIG_FILE} is not readable XML: {error}") from None
        where = f"path: {path!r}"
        if root.tag != "GCVF":
            raise ValueError(f"{where}: {CONFIG_FILE} has root <{root.tag}>, expected <GCVF>")
        dpi = (float(_child(root, "Resolution/XDpi", where)), float(_child(root, "Resolution/YDpi", where)))
        layer_nm = float(_child(root, "Resolution/SliceThicknessNanoMeter", where))
        wx = int(_child(root, "SliceDimensions/SliceWidth", where))
        hy = int(_child(root, "SliceDimensions/SliceHeight", where))
        start = int(_child(root, "SliceRange/StartIndex", where))
        dz = int(_child(root, "SliceRange/NumberOfSlices", where))
        prefix = _child(root, "ImageFilePrefix", where)
        background = _ints(_child(root, "MaterialList/BackGroundMaterialRGBA", where), 4, where,
                           "BackGroundMaterialRGBA")
        materials, rgba, declared = [], [], []
        for m in root.findall("MaterialList/Material"):
            materials.append(_child(m, "Name", where))
            rgba.append(_ints(_child(m, "RGBA", where), 4, where, "RGBA"))
            declared.append(int(_child(m, "VoxelCount", where)))
        layer_files = {n for n in names if n != CONFIG_FILE and n.lower().endswith(".png")}
        expected = {f"{prefix}{k}.png" for k in range(start, start + dz)}
        if layer_files != expected:
            missing = sorted(expected - layer_files, key=len)[:5]
            extra = sorted(layer_files - expected, key=len)[:5]
            raise ValueError(f"{where}: expected layers {prefix}{start}.png .. {prefix}{start + dz - 1}.png, "
                             f"missing {missing}, unexpected {extra}")
        colours = np.array([c[:3] for c in rgba + [background]], dtype=np.int64)
        if len({tuple(c) for c in colours.tolist()}) != len(colours):
            raise ValueError(f"{where}: two materials (or one and the background) share an RGB colour")
        decode = palette_decoder(colours, np.append(np.arange(len(materials)), _VOID), "no material's")
        indices = np.empty((dz, hy, wx), dtype=np.uint8)
        for k in range(dz):
            name = f"{prefix}{start + k}.png"
            try:
                data = archive.read(name)
            except (zipfile.BadZipFile, OSError, EOFError) as error:
                raise ValueError(f"{where}: {name} is corrupt: {error}") from None
            image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
            if image is None or image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3:
                raise ValueError(f"{where}: {name} is not an 8-bit RGB PNG")
            if image.shape[:2] != (hy, wx):
                raise ValueError(f"{where}: {name} is {image.shape[1]} x {image.shape[0]} pixels, the package "
                                 f"declares {wx} x {hy}")
            indices[k] = decode(np.ascontiguousarray(image[..., ::-1]), f"{where}: {name}")   # OpenCV's BGR
    counts = np.bincount(indices.reshape(-1), minlength=256)[:len(materials)]
    if counts.tolist() != declared:
        raise ValueError(f"{where}: the layers hold {counts.tolist()} voxels of {materials}, the package declares "
                         f"{declared}")
    return indices, {"materials": materials, "rgba": [tuple(c) for c in rgba], "voxel_counts": declared,
                     "dpi_xy": dpi, "layer_thickness_nm": layer_nm, "bit_depth": int(_child(root, "BitDepth", where)),
                     "background_rgba": tuple(background), "layers": dz}
