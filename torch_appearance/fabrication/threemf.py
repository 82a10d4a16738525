"""3MF files of a printed object: the mesh with viewer colours, and the per-voxel material volume.

:func:`write_3mf` writes, through lib3mf (the 3MF Consortium's library, ``lib3mf >= 2.5``; imported on first use):

* **Mesh** — one mesh object at its printed size, in millimetres by default (``unit`` picks another 3MF unit; the
  arguments stay in mm and are converted), placed by one build item with the identity transform.
* **Viewer colours** (3MF Materials extension) — one ``<m:colorgroup>`` that holds each distinct sRGB colour once;
  every triangle refers to it with ``pid`` and ``p1 p2 p3`` (one colour per corner for ``vertex_rgb``, the same
  colour three times for ``face_rgb``). Any 3MF viewer shows these.
* **Material volume** (3MF Volumetric extension) — one ``<basematerials>`` entry per material (name and display
  colour), and per material ``k``:

  - an ``<v:image3d>`` image stack named ``material_k`` with one sheet per printer layer (sheet ``z`` = layer ``z``,
    bottom to top), part ``/3D/volumetric/material_k/sheet_zzzzz.png``: a **1-bit greyscale PNG** of ``Hy × Wx``
    pixels, 1 where the voxel holds material ``k`` and 0 elsewhere (zlib level 1). 1-bit sheets are smaller and
    faster to encode than 8-bit ones (a 472 × 945 sheet of random material: 44 kB in 4 ms, against 60 kB in 36 ms
    for 8 bits at level 6, 85 kB at OpenCV's default); the volumetric specification normalises an N-bit sample by
    ``2**N - 1``, so 1 reads as 1.0 either way, and lib3mf stores the PNG bytes as they are;
  - a ``<v:functionfromimage3d>`` on that stack with ``filter="nearest"`` and ``clamp`` tiling on u, v and w;
  - a ``<v:property name="material_k" channel="red" required="true">`` in the mesh's ``<v:volumedata>`` whose
    ``transform`` maps object coordinates to the function's normalised (u, v, w) coordinates:
    ``u = x / (Wx·sx)``, ``v = y / (Hy·sy)``, ``w = z / (Dz·sz)`` (a diagonal matrix, no offset, in file units).

  Orientation: the volumetric specification puts image column ``j`` at ``u = (j + ½) / columncount``, image row
  ``i`` at ``v = 1 − (i + ½) / rowcount`` (row 0 at the top, as in 2D textures) and sheet ``k`` at
  ``w = (k + ½) / sheetcount``. A sheet is therefore the layer as seen from above with +y up (``layer[::-1]``: PNG
  row 0 is the layer's last row, the largest y), and voxel ``(k, j, i)``, centred at
  ``((i + ½)·sx, (j + ½)·sy, (k + ½)·sz)``, samples exactly its own pixel. Void voxels (index 255) are 0 in every
  sheet.

  Namespaced metadata (``urn:torch-appearance:3mf:1``) records the exact ``pitch_mm``, ``grid_shape`` and which
  colour argument was given, since the XML ``transform`` keeps only 6 significant digits (still < 0.001 pixel of
  error on a 1024-voxel axis). Core metadata: ``Title`` (the file name) and ``Application`` (``torch_appearance``).

What lib3mf 2.5.0 does not support, and how this module works around it:

* **Volumetric composites**: ``VolumeDataComposite`` (``SetBaseMaterialGroup``, ``AddMaterialMapping``,
  ``GetMaterialMapping`` ...) raises "functionality not implemented", so no ``<v:composite>`` with
  ``<v:materialmapping>`` elements can be written (or read). Each material mask is written as a volumetric
  ``<v:property>`` named ``material_k`` instead, and the base materials are written as a resource of their own;
  the link property ``material_k`` ↔ ``<base>`` number ``k`` is this module's convention, not part of the 3MF
  specification. A consumer that reads composites will not find the material mixing. lib3mf gives no way to declare
  an XML namespace prefix for a property name, so the names carry none (the specification asks for one).
* lib3mf marks the volumetric *and* implicit extensions as ``requiredextensions="v i"`` as soon as a
  ``functionfromimage3d`` exists, so a consumer without the Volumetric extension must refuse a file with a volume
  (the specification allows non-required ``property`` elements). Files without ``layers`` carry no such mark.
* ``Model.AddImageStack(ColumnCount, RowCount, SheetCount)`` swaps rows and columns; the counts are set again with
  ``SetRowCount`` / ``SetColumnCount``.
* lib3mf's reader warns "Invalid Element in namespace" on its own ``image3d`` and ``functionfromimage3d``
  elements but reads them completely; the warnings are ignored.
* Bulk data (vertices, triangles, triangle properties, PNG sheets) goes through the binding's C functions with
  NumPy buffers: the binding's Python methods copy element by element (2.5 s instead of 0.01 s for 200 000
  vertices).

lib3mf builds the model (mesh, colours, materials, functions, volume data) with one placeholder sheet per image
stack, because it keeps buffers for every package part until the whole package is written (hundreds of kB per
sheet: 11 GB for 5 materials × 2873 layers of 524 × 467). The package is then copied with the real sheets streamed
in, one layer at a time, and each ``<v:imagesheet>`` and relationship pointed at its own part; the materials of a
layer are encoded in parallel threads. Memory thus stays at the mesh and one layer, whatever the number of layers.

:func:`~torch_appearance.fabrication.threemf_read.read_3mf` (in :mod:`.threemf_read`, also read from here) reads
such a file back (geometry, colours, materials, index volume);
:func:`~torch_appearance.fabrication.threemf_read.iter_3mf_layers` yields its index volume one layer at a time.
"""
import ctypes
import functools
import locale
import os
from concurrent.futures import ThreadPoolExecutor

import cv2
import numpy as np
import torch

from ..checks import check_choice, check_path, check_real, check_vector3, describe, is_int
from ..io import atomic_output
from .export import VOID

__all__ = ["write_3mf", "UNITS_MM"]
#: the reader lives in :mod:`.threemf_read` (it shares this module's lib3mf access and conventions); its names are
#: still read from here (``from torch_appearance.fabrication.threemf import read_3mf``)
_READER = ("read_3mf", "iter_3mf_layers")

#: Millimetres per 3MF unit.
UNITS_MM = {"micron": 1e-3, "millimeter": 1.0, "centimeter": 10.0, "inch": 25.4, "foot": 304.8, "meter": 1000.0}
_UNIT_ENUM = {"micron": "MicroMeter", "millimeter": "MilliMeter", "centimeter": "CentiMeter", "inch": "Inch",
              "foot": "Foot", "meter": "Meter"}

#: Namespace of this module's metadata entries.
NAMESPACE = "urn:torch-appearance:3mf:1"
_PNG_PARAMS = [cv2.IMWRITE_PNG_BILEVEL, 1, cv2.IMWRITE_PNG_COMPRESSION, 1]   # level 6: +0.3 % smaller, 1.4x slower
_DECIMALS = 9                       # vertex coordinates: finer than float32 steps for coordinates >= 0.01 mm
_CV_CHANNEL = {"red": 2, "green": 1, "blue": 0, "alpha": 3}   # channel name -> index in OpenCV's BGR(A) order

class _MissingFileError(FileNotFoundError, ValueError):
    """A file to read does not exist: both a FileNotFoundError and a ValueError (like io.UnsupportedOperation)."""


# --------------------------------------------------------------------------------------------------------------
# lib3mf access
# --------------------------------------------------------------------------------------------------------------
def _keeps_locale(function):
    """Restore the process's locale after ``function``: lib3mf sets the C locale (LC_ALL) and leaves it, which made
    Python's text streams of later subprocesses ASCII (UnicodeDecodeError on a "µ" in another command's output)."""
    @functools.wraps(function)
    def wrapper(*args, **kwargs):
        saved = locale.setlocale(locale.LC_ALL)
        try:
            return function(*args, **kwargs)
        finally:
            locale.setlocale(locale.LC_ALL, saved)
    return wrapper


@functools.lru_cache(maxsize=1)
def _lib3mf():
    """``(module, wrapper)`` of lib3mf, loaded once."""
    try:
        import lib3mf
    except ImportError as error:
        raise ImportError("3MF files need lib3mf >= 2.5 (pip install lib3mf)") from error
    return lib3mf, lib3mf.get_wrapper()


def _call(obj, function, *args):
    """Call the C function ``lib3mf_<function>(obj handle, *args)``, raising lib3mf's exception on failure."""
    wrapper = obj._wrapper
    wrapper.checkError(obj, getattr(wrapper.lib, "lib3mf_" + function)(obj._handle, *args))


def _pointer(array, ctype):
    return array.ctypes.data_as(ctypes.POINTER(ctype))


def _transform(lib3mf, scale):
    """A lib3mf Transform that scales x, y, z by ``scale`` (the 3 diagonal entries), no translation."""
    transform = lib3mf.Transform()
    for row in range(4):
        for col in range(3):
            transform.Fields[row][col] = scale[row] if row == col else 0.0
    return transform


# --------------------------------------------------------------------------------------------------------------
# argument checks
# --------------------------------------------------------------------------------------------------------------
def _as_numpy(name, value, shape_desc):
    if isinstance(value, torch.Tensor):
        return value.detach().cpu().numpy()
    if isinstance(value, np.ndarray):
        return value
    raise TypeError(f"{name}: expected a numpy.ndarray or torch.Tensor of shape {shape_desc}, got {describe(value)}")


def _check_vertices(vertices):
    array = _as_numpy("vertices", vertices, "(V, 3)")
    if not np.issubdtype(array.dtype, np.floating):
        raise TypeError(f"vertices: expected a floating-point dtype, got {array.dtype}")
    if array.ndim != 2 or array.shape[1] != 3 or array.shape[0] < 3:
        raise ValueError(f"vertices: expected shape (V, 3) with V >= 3, got {tuple(array.shape)}")
    if not np.isfinite(array).all():
        raise ValueError("vertices: expected finite coordinates, got NaN or inf")
    return array.astype(np.float64)


def _check_faces(faces, n_vertices):
    array = _as_numpy("faces", faces, "(F, 3)")
    if array.dtype == bool or not np.issubdtype(array.dtype, np.integer):
        raise TypeError(f"faces: expected an integer dtype, got {array.dtype}")
    if array.ndim != 2 or array.shape[1] != 3 or array.shape[0] < 1:
        raise ValueError(f"faces: expected shape (F, 3) with F >= 1, got {tuple(array.shape)}")
    low, high = int(array.min()), int(array.max())
    if low < 0 or high >= n_vertices:
        raise ValueError(f"faces: expected vertex indices in [0, {n_vertices}), got values in [{low}, {high}]")
    degenerate = (array[:, 0] == array[:, 1]) | (array[:, 1] == array[:, 2]) | (array[:, 0] == array[:, 2])
    if degenerate.any():
        f = int(np.flatnonzero(degenerate)[0])
        raise ValueError(f"faces: triangle {f} repeats a vertex ({array[f].tolist()}); 3MF refuses degenerate "
                         f"triangles")
    return array.astype(np.uint32)


def _check_rgb(name, rgb, count, what):
    array = _as_numpy(name, rgb, f"({what}, 3)")
    if array.dtype == bool or not np.issubdtype(array.dtype, np.integer):
        raise TypeError(f"{name}: expected uint8 sRGB values (an integer dtype), got {array.dtype}")
    if array.shape != (count, 3):
        raise ValueError(f"{name}: expected shape ({what}, 3) = ({count}, 3), got {tuple(array.shape)}")
    if array.size and (int(array.min()) < 0 or int(array.max()) > 255):
        raise ValueError(f"{name}: expected values in [0, 255], got values in [{int(array.min())}, "
                         f"{int(array.max())}]")
    return array.astype(np.uint8)


def _check_materials(materials):
    if not isinstance(materials, (list, tuple)):
        raise TypeError(f"materials: expected a list of (name, (r, g, b, a)), got {describe(materials)}")
    if not 1 <= len(materials) < VOID:
        raise ValueError(f"materials: expected 1 to {VOID - 1} materials (index {VOID} means void), got "
                         f"{len(materials)}")
    checked = []
    for m, entry in enumerate(materials):
        if not isinstance(entry, (list, tuple)) or len(entry) != 2:
            raise TypeError(f"materials[{m}]: expected a pair (name, (r, g, b, a)), got {describe(entry)}")
        name, rgba = entry
        if not isinstance(name, str):
            raise TypeError(f"materials[{m}]: expected a str name, got {describe(name)}")
        if not name.strip():
            raise ValueError(f"materials[{m}]: expected a non-empty name, got {name!r}")
        if isinstance(rgba, np.ndarray):
            rgba = rgba.tolist()
        if not isinstance(rgba, (list, tuple)) or len(rgba) != 4:
            raise ValueError(f"materials[{m}]: expected 4 colour values (r, g, b, a), got {rgba!r}")
        if not all(is_int(v) for v in rgba):
            raise TypeError(f"materials[{m}]: expected integer colour values 0..255, got {rgba!r}")
        if not all(0 <= int(v) <= 255 for v in rgba):
            raise ValueError(f"materials[{m}]: expected colour values in [0, 255], got {list(rgba)}")
        checked.append((name, tuple(int(v) for v in rgba)))
    return checked


def _check_grid_shape(grid_shape):
    if not isinstance(grid_shape, (list, tuple, np.ndarray)) or len(grid_shape) != 3:
        raise TypeError(f"grid_shape: expected 3 ints (Dz, Hy, Wx), got {describe(grid_shape)}")
    if not all(is_int(v) for v in grid_shape):
        raise TypeError(f"grid_shape: expected 3 ints (Dz, Hy, Wx), got {tuple(grid_shape)}")
    shape = tuple(int(v) for v in grid_shape)
    if min(shape) < 1 or max(shape) > 1024 ** 3:
        raise ValueError(f"grid_shape: expected sizes in [1, 1024**3] (3MF image stack limits), got {shape}")
    return shape


def _check_pitch(pitch_mm):
    return tuple(check_real("pitch_mm", v, lo=0.0, lo_open=True) for v in check_vector3("pitch_mm", pitch_mm))


def _check_layer(k, layer, shape, n_materials):
    if not isinstance(layer, np.ndarray):
        raise TypeError(f"layers[{k}]: expected a numpy.ndarray of dtype uint8 and shape (Hy, Wx) = {shape}, got "
                        f"{describe(layer)}")
    if layer.dtype != np.uint8:
        raise TypeError(f"layers[{k}]: expected dtype uint8, got {layer.dtype}")
    if layer.shape != shape:
        raise ValueError(f"layers[{k}]: expected shape (Hy, Wx) = {shape}, got {layer.shape}")
    if int(layer.max()) >= n_materials:
        bad = (layer >= n_materials) & (layer != VOID)
        if bad.any():
            j, i = np.argwhere(bad)[0]
            raise ValueError(f"layers[{k}]: expected material indices in [0, {n_materials}) or {VOID} (void), got "
                             f"{int(layer[j, i])} at row {j}, column {i}")
    return layer


# --------------------------------------------------------------------------------------------------------------
# writing
# --------------------------------------------------------------------------------------------------------------
def _encode_mask(mask):
    ok, encoded = cv2.imencode(".png", mask.view(np.uint8), _PNG_PARAMS)
    if not ok:
        raise RuntimeError(f"OpenCV failed to encode a 1-bit PNG of shape {mask.shape}")
    return encoded


def _add_sheet(stack, index, part, png):
    """Add sheet ``index`` (PNG bytes as a uint8 array) to ``stack`` under the package part ``part``."""
    lib3mf, _ = _lib3mf()
    handle = ctypes.c_void_p()
    _call(stack, "imagestack_createsheetfrombuffer", ctypes.c_uint32(index), ctypes.c_char_p(part.encode()),
          ctypes.c_uint64(png.size), _pointer(png, ctypes.c_uint8), handle)
    if handle:
        lib3mf.Base(handle, stack._wrapper)            # releases lib3mf's reference when dropped


def _add_mesh(model, vertices_file, faces):
    """One mesh object with the given vertices (file units) and triangles."""
    lib3mf, _ = _lib3mf()
    mesh = model.AddMeshObject()
    mesh.SetName("object")
    positions = np.ascontiguousarray(vertices_file, dtype=np.float32)
    triangles = np.ascontiguousarray(faces, dtype=np.uint32)
    _call(mesh, "meshobject_setgeometry", ctypes.c_uint64(len(positions)), _pointer(positions, lib3mf.Position),
          ctypes.c_uint64(len(triangles)), _pointer(triangles, lib3mf.Triangle))
    return mesh


def _add_colours(model, mesh, faces, vertex_rgb, face_rgb):
    """One colour group with each distinct colour once; every triangle gets a colour per corner."""
    lib3mf, wrapper = _lib3mf()
    rgb = vertex_rgb if vertex_rgb is not None else face_rgb
    codes = (rgb[:, 0].astype(np.int64) << 16) | (rgb[:, 1].astype(np.int64) << 8) | rgb[:, 2]
    unique, inverse = np.unique(codes, return_inverse=True)
    group = model.AddColorGroup()
    ids = np.array([group.AddColor(wrapper.RGBAToColor(int(c >> 16), int((c >> 8) & 255), int(c & 255), 255))
                    for c in unique.tolist()], dtype=np.uint32)
    property_ids = ids[inverse.reshape(-1)]
    properties = np.empty((len(faces), 4), dtype=np.uint32)
    properties[:, 0] = group.GetResourceID()
    properties[:, 1:] = property_ids[faces] if vertex_rgb is not None else property_ids[:, None]
    _call(mesh, "meshobject_setalltriangleproperties", ctypes.c_uint64(len(properties)),
          _pointer(properties, lib3mf.TriangleProperties))


_END = object()
_PLACEHOLDER = "/3D/volumetric/material_{m}/sheets.png"
_SHEET = "3D/volumetric/material_{m}/sheet_{k:05d}.png"
_MODEL, _MODEL_RELS = "3D/3dmodel.model", "3D/_rels/3dmodel.model.rels"
_TEXTURE_REL = "http://schemas.microsoft.com/3dmanufacturing/2013/01/3dtexture"


def _add_volume(model, mesh, shape, pitch_file, materials):
    """Base materials, and one image stack + function + volumetric property per material. Every sheet of a stack
    refers to one placeholder part (a blank sheet): the real sheets are streamed into the package afterwards by
    :func:`_stream_sheets`. (lib3mf 2.5 keeps per-part buffers until the whole package is written, hundreds of kB
    per sheet: 11 GB for 5 materials × 2873 layers of 524 × 467; one part per stack costs nothing.)"""
    lib3mf, wrapper = _lib3mf()
    depth, height, width = shape
    group = model.AddBaseMaterialGroup()
    for name, rgba in materials:
        group.AddMaterial(name, wrapper.RGBAToColor(*rgba))
    blank = _encode_mask(np.zeros((height, width), dtype=bool))
    stacks = []
    for m in range(len(materials)):
        stack = model.AddImageStack(width, height, depth)
        stack.SetColumnCount(width)      # lib3mf 2.5 swaps the two counts of AddImageStack
        stack.SetRowCount(height)
        if (stack.GetColumnCount(), stack.GetRowCount(), stack.GetSheetCount()) != (width, height, depth):
            raise RuntimeError(f"lib3mf made an image stack of {stack.GetColumnCount()} columns, "
                               f"{stack.GetRowCount()} rows, {stack.GetSheetCount()} sheets instead of "
                               f"{width}, {height}, {depth}")
        stack.SetName(f"material_{m}")
        _add_sheet(stack, 0, _PLACEHOLDER.format(m=m), blank)
        sheet = stack.GetSheet(0)
        for k in range(1, depth):
            stack.SetSheet(k, sheet)
        stacks.append(stack)
    volume = model.AddVolumeData()
    scale = [1.0 / (n * s) for n, s in zip((width, height, depth), pitch_file)]
    for m, stack in enumerate(stacks):
        function = model.AddFunctionFromImage3D(stack)
        function.SetDisplayName(f"material {m}: {materials[m][0]}")
        function.SetFilter(lib3mf.TextureFilter.Nearest)
        clamp = lib3mf.TextureTileStyle.Clamp
        function.SetTileStyles(clamp, clamp, clamp)
        prop = volume.AddPropertyFromFunction(f"material_{m}", function)
        prop.SetTransform(_transform(lib3mf, scale))
        prop.SetChannelName("red")
        prop.SetIsRequired(True)
    mesh.SetVolumeData(volume)


def _stream_sheets(source, target, layers, shape, n_materials, progress):
    """Copy the package ``source`` (written by lib3mf with placeholder sheets) to ``target``, streaming the real
    sheets from ``layers`` (consumed once, one layer at a time) and pointing each ``<v:imagesheet>`` of the model and
    its relationships at its own part."""
    import re
    import xml.etree.ElementTree as ET
    import zipfile

    depth, height, width = shape
    with zipfile.ZipFile(source) as old, zipfile.ZipFile(target, "w", zipfile.ZIP_DEFLATED, allowZip64=True) as new:
        placeholders = {_PLACEHOLDER.format(m=m).lstrip("/") for m in range(n_materials)}
        for info in old.infolist():
            if info.filename not in placeholders and info.filename not in (_MODEL, _MODEL_RELS):
                new.writestr(info.filename, old.read(info.filename))
        iterator = iter(layers)
        workers = max(1, min(n_materials, os.cpu_count() or 1, 8))
        with ThreadPoolExecutor(max_workers=workers) as pool:
            for k in range(depth):
                try:
                    layer = next(iterator)
                except StopIteration:
                    raise ValueError(f"layers: expected grid_shape[0] = {depth} layers, got {k}") from None
                layer = _check_layer(k, layer, (height, width), n_materials)
                top_view = layer[::-1]                       # PNG row 0 = largest y (the specification's v = 1)
                masks = [np.equal(top_view, m) for m in range(n_materials)]
                for m, png in enumerate(pool.map(_encode_mask, masks)):
                    new.writestr(zipfile.ZipInfo(_SHEET.format(m=m, k=k), date_time=(2020, 1, 1, 0, 0, 0)),
                                 png.tobytes(), compress_type=zipfile.ZIP_STORED)   # PNG is compressed already
                if progress is not None:
                    progress(k)
        if next(iterator, _END) is not _END:
            raise ValueError(f"layers: expected grid_shape[0] = {depth} layers, got more")
        model = old.read(_MODEL).decode("utf-8")
        for m in range(n_materials):
            counter = iter(range(depth))
            model = re.sub(re.escape(f'path="{_PLACEHOLDER.format(m=m)}"'),
                           lambda _: f'path="/{_SHEET.format(m=m, k=next(counter))}"', model)
            if next(counter, None) is not None:
                raise RuntimeError(f"lib3mf wrote fewer than {depth} sheets of material {m}")
        new.writestr(_MODEL, model.encode("utf-8"))
        rels = ET.fromstring(old.read(_MODEL_RELS))
        ns = rels.tag[:rels.tag.index("}") + 1] if rels.tag.startswith("{") else ""
        ET.register_namespace("", ns.strip("{}"))
        for rel in list(rels):
            if rel.get("Target", "").lstrip("/") in placeholders:
                rels.remove(rel)
        for m in range(n_materials):
            for k in range(depth):
                ET.SubElement(rels, f"{ns}Relationship", Type=_TEXTURE_REL, Target="/" + _SHEET.format(m=m, k=k),
                              Id=f"sheet{m}_{k}")
        new.writestr(_MODEL_RELS, b'<?xml version="1.0" encoding="utf-8"?>\n' + ET.tostring(rels))


@_keeps_locale
def write_3mf(path, vertices, faces, *, vertex_rgb=None, face_rgb=None, layers=None, grid_shape=None, pitch_mm=None,
              materials=None, unit="millimeter", progress=None):
    """Write a printed object as a 3MF file: its mesh, viewer colours, and material volume (atomic).

    See the module docstring for the file layout.

    Args:
        path: destination, ending with ``.3mf``; its folder must exist. Written atomically: a failed write leaves
            neither a partial ``path`` nor a temporary file, and an existing ``path`` keeps its old content.
        vertices: (V, 3) float, mm: the object at its printed size, in the coordinates of the voxel grid.
        faces: (F, 3) int vertex indices (no repeated vertex within a triangle).
        vertex_rgb: (V, 3) uint8 sRGB, one colour per vertex (each triangle gets its three corners' colours).
        face_rgb: (F, 3) uint8 sRGB, one colour per triangle. Give at most one of ``vertex_rgb`` and ``face_rgb``;
            neither: no colours.
        layers: iterable of ``grid_shape[0]`` uint8 (Hy, Wx) arrays, consumed once, one at a time (a generator
            is fine): printer layer k (bottom to top, k = 0 at z = 0), row j ↔ y, column i ↔ x; values are
            material indices in [0, len(materials)) or 255 (void, no material). None: no volume.
        grid_shape: (Dz, Hy, Wx) voxel counts, required with ``layers``.
        pitch_mm: (sx, sy, sz) voxel edges in mm, required with ``layers``: the grid covers
            [0, Wx·sx] × [0, Hy·sy] × [0, Dz·sz] in the coordinates of ``vertices``.
        materials: list of ``(name, (r, g, b, a))`` with ints 0..255 (display colour), one per material index,
            required with ``layers``.
        unit: the 3MF unit of the file, one of :data:`UNITS_MM` (arguments stay in mm and are converted).
        progress: optional callable, ``progress(k)`` is called after layer k has been added.

    Raises:
        TypeError, ValueError: naming the argument (wrong type, dtype or shape; an index out of range; a layer of
            the wrong shape; fewer or more layers than ``grid_shape[0]``; colours out of [0, 255]; both colour
            arguments; volume arguments without ``layers`` or the reverse). Layers are checked as they are read,
            so a bad layer is reported after the earlier ones were encoded, still before anything is written.
        RuntimeError: lib3mf failed.

    Example:
        >>> write_3mf("object.3mf", vertices, faces, vertex_rgb=rgb, layers=iter(volume),  # doctest: +SKIP
        ...           grid_shape=volume.shape, pitch_mm=(25.4 / 600, 25.4 / 300, 0.027),
        ...           materials=[("cyan", (0, 255, 255, 255)), ("white", (255, 255, 255, 255))])
    """
    path = check_path("path", path, (".3mf",))
    unit = check_choice("unit", unit, tuple(UNITS_MM), kind=str)
    vertices = _check_vertices(vertices)
    faces = _check_faces(faces, len(vertices))
    if vertex_rgb is not None and face_rgb is not None:
        raise ValueError("vertex_rgb, face_rgb: expected at most one of them, got both")
    if vertex_rgb is not None:
        vertex_rgb = _check_rgb("vertex_rgb", vertex_rgb, len(vertices), "V")
    if face_rgb is not None:
        face_rgb = _check_rgb("face_rgb", face_rgb, len(faces), "F")
    volume_args = {"grid_shape": grid_shape, "pitch_mm": pitch_mm, "materials": materials}
    if layers is None:
        given = [name for name, value in volume_args.items() if value is not None]
        if given:
            raise ValueError(f"{', '.join(given)}: given without layers; pass layers too, or none of them")
    else:
        missing = [name for name, value in volume_args.items() if value is None]
        if missing:
            raise ValueError(f"{', '.join(missing)}: required with layers")
        if isinstance(layers, (str, bytes)) or not hasattr(layers, "__iter__"):
            raise TypeError(f"layers: expected an iterable of (Hy, Wx) uint8 arrays, got {describe(layers)}")
        grid_shape = _check_grid_shape(grid_shape)
        pitch_mm = _check_pitch(pitch_mm)
        materials = _check_materials(materials)
    if progress is not None and not callable(progress):
        raise TypeError(f"progress: expected a callable or None, got {describe(progress)}")
    directory = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(directory):
        raise FileNotFoundError(f"path: the folder {directory!r} does not exist")

    lib3mf, wrapper = _lib3mf()
    to_file = 1.0 / UNITS_MM[unit]
    try:
        model = wrapper.CreateModel()
        model.SetUnit(getattr(lib3mf.ModelUnit, _UNIT_ENUM[unit]))
        metadata = model.GetMetaDataGroup()
        metadata.AddMetaData("", "Title", os.path.splitext(os.path.basename(path))[0], "string", False)
        metadata.AddMetaData("", "Application", "torch_appearance", "string", False)
        colours = "vertex" if vertex_rgb is not None else "face" if face_rgb is not None else "none"
        metadata.AddMetaData(NAMESPACE, "colours", colours, "string", True)
        mesh = _add_mesh(model, vertices * to_file, faces)
        if colours != "none":
            _add_colours(model, mesh, faces, vertex_rgb, face_rgb)
        if layers is not None:
            metadata.AddMetaData(NAMESPACE, "grid_shape", " ".join(str(v) for v in grid_shape), "string", True)
            metadata.AddMetaData(NAMESPACE, "pitch_mm", " ".join(repr(v) for v in pitch_mm), "string", True)
            _add_volume(model, mesh, grid_shape, [s * to_file for s in pitch_mm], materials)
        model.AddBuildItem(mesh, wrapper.GetIdentityTransform())
        writer = model.QueryWriter("3mf")
        writer.SetDecimalPrecision(_DECIMALS)
    except lib3mf.ELib3MFException as error:
        raise RuntimeError(f"lib3mf failed to build the 3MF model for {path!r}: {error}") from error
    with atomic_output(path) as tmp:
        try:
            writer.WriteToFile(tmp)
        except lib3mf.ELib3MFException as error:
            raise RuntimeError(f"lib3mf failed to write {path!r}: {error}") from error
        del writer, model
        if layers is not None:
            with atomic_output(tmp) as streamed:       # the package again, its sheets streamed in
                _stream_sheets(tmp, streamed, layers, grid_shape, len(materials), progress)


def __getattr__(name):
    """The reader's names, from :mod:`.threemf_read` (imported on first use: it imports this module)."""
    if name in _READER:
        from . import threemf_read
        return getattr(threemf_read, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
