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

:func:`read_3mf` reads such a file back (geometry, colours, materials, index volume); :func:`iter_3mf_layers` yields
its index volume one layer at a time.
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

__all__ = ["write_3mf", "read_3mf", "iter_3mf_layers", "UNITS_MM"]

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


# --------------------------------------------------------------------------------------------------------------
# reading
# --------------------------------------------------------------------------------------------------------------
def _read_model(path):
    """Check ``path`` and read it with lib3mf; ValueError naming the file when it is not a readable 3MF."""
    path = check_path("path", path)
    if not os.path.exists(path):
        raise _MissingFileError(f"path: no such file {path!r}")
    if os.path.isdir(path):
        raise ValueError(f"path: expected a 3MF file, got the folder {path!r}")
    lib3mf, wrapper = _lib3mf()
    model = wrapper.CreateModel()
    try:
        model.QueryReader("3mf").ReadFromFile(path)
    except lib3mf.ELib3MFException as error:
        raise ValueError(f"path: cannot read {path!r} as a 3MF file (missing, truncated or not 3MF): "
                         f"{error}") from None
    return path, model


def _resources(iterator, getter):
    items = []
    while iterator.MoveNext():
        items.append(getattr(iterator, getter)())
    return items


def _metadata(model):
    group = model.GetMetaDataGroup()
    entries = {}
    for index in range(group.GetMetaDataCount()):
        entry = group.GetMetaData(index)
        entries[(entry.GetNameSpace(), entry.GetName())] = entry.GetValue()
    return entries


def _mesh_arrays(path, mesh):
    lib3mf, _ = _lib3mf()
    n_vertices, n_faces = mesh.GetVertexCount(), mesh.GetTriangleCount()
    if n_vertices < 3 or n_faces < 1:
        raise ValueError(f"path: {path!r} holds an empty mesh ({n_vertices} vertices, {n_faces} triangles)")
    positions = np.empty((n_vertices, 3), dtype=np.float32)
    triangles = np.empty((n_faces, 3), dtype=np.uint32)
    properties = np.empty((n_faces, 4), dtype=np.uint32)
    needed = ctypes.c_uint64()
    _call(mesh, "meshobject_getvertices", ctypes.c_uint64(n_vertices), needed, _pointer(positions, lib3mf.Position))
    _call(mesh, "meshobject_gettriangleindices", ctypes.c_uint64(n_faces), needed,
          _pointer(triangles, lib3mf.Triangle))
    _call(mesh, "meshobject_getalltriangleproperties", ctypes.c_uint64(n_faces), needed,
          _pointer(properties, lib3mf.TriangleProperties))
    return positions, triangles.astype(np.int64), properties


def _corner_colours(model, properties):
    """(F, 3, 3) uint8 sRGB per triangle corner, or None unless every triangle refers to a colour group."""
    lib3mf, wrapper = _lib3mf()
    corner = np.empty((len(properties), 3, 3), dtype=np.uint8)
    for resource in np.unique(properties[:, 0]).tolist():
        if resource == 0 or model.GetPropertyTypeByID(resource) != lib3mf.PropertyType.Colors:
            return None
        group = model.GetColorGroupByID(resource)
        ids = np.array(group.GetAllPropertyIDs(), dtype=np.int64)
        if not len(ids):
            return None
        rgb = np.array([wrapper.ColorToRGBA(group.GetColor(i))[:3] for i in ids.tolist()], dtype=np.uint8)
        order = np.argsort(ids)
        rows = properties[:, 0] == resource
        wanted = properties[rows, 1:].astype(np.int64)
        pos = np.clip(np.searchsorted(ids[order], wanted), 0, len(ids) - 1)
        if not (ids[order][pos] == wanted).all():
            return None
        corner[rows] = rgb[order][pos]
    return corner


def _split_colours(corner, faces, n_vertices, kind):
    """``(vertex_rgb, face_rgb)`` from per-corner colours (see :func:`read_3mf`)."""
    if corner is None:
        return None, None
    vertex_rgb = np.zeros((n_vertices, 3), dtype=np.uint8)
    vertex_rgb[faces.reshape(-1)] = corner.reshape(-1, 3)
    per_vertex = bool(np.array_equal(vertex_rgb[faces], corner))
    per_face = bool((corner == corner[:, :1]).all())
    if per_face and (kind == "face" or not per_vertex):
        return None, corner[:, 0].copy()
    if per_vertex:
        return vertex_rgb, None
    return None, None


class _Volume:
    """The material volume of a mesh as written by :func:`write_3mf`: stacks, orientation, pitch, materials."""

    def __init__(self, path, model, mesh, metadata, to_mm):
        self.path = path
        volume = mesh.GetVolumeData()
        self.present = volume is not None and volume.GetPropertyCount() > 0
        groups = _resources(model.GetBaseMaterialGroups(), "GetCurrentBaseMaterialGroup")
        self.materials = []
        _, wrapper = _lib3mf()
        for group in groups:
            for pid in group.GetAllPropertyIDs():
                rgba = wrapper.ColorToRGBA(group.GetDisplayColor(pid))
                self.materials.append((group.GetName(pid), tuple(int(v) for v in rgba)))
        if not self.present:
            return
        if len(groups) > 1:
            raise ValueError(f"path: {path!r} holds {len(groups)} base material groups; expected one with a volume")
        n = len(self.materials)
        if n == 0:
            raise ValueError(f"path: {path!r}: the mesh has volume data but the file has no base materials")
        by_index = {}
        for p in range(volume.GetPropertyCount()):
            prop = volume.GetProperty(p)
            name = prop.GetName()
            index = name[len("material_"):] if name.startswith("material_") else ""
            if not index.isdigit() or int(index) in by_index:
                raise ValueError(f"path: {path!r}: volumetric property {name!r} is not one of material_0 .. "
                                 f"material_{n - 1} (a volume not written by torch_appearance)")
            by_index[int(index)] = prop
        if sorted(by_index) != list(range(n)):
            raise ValueError(f"path: {path!r}: expected volumetric properties material_0 .. material_{n - 1} for "
                             f"{n} base materials, got {sorted(by_index)}")
        self.stacks, self.channels, transforms = [], [], []
        for m in range(n):
            prop = by_index[m]
            function = model.GetResourceByID(prop.GetFunctionResourceID())
            image = function.GetImage3D() if hasattr(function, "GetImage3D") else None
            if image is None or not image.IsImageStack():
                raise ValueError(f"path: {path!r}: material_{m} does not refer to a function of an image stack")
            self.stacks.append(model.GetImageStackByID(image.GetResourceID()))
            channel = prop.GetChannelName()
            if channel not in _CV_CHANNEL:
                raise ValueError(f"path: {path!r}: material_{m} samples channel {channel!r}; expected one of "
                                 f"{tuple(_CV_CHANNEL)}")
            self.channels.append(channel)
            transforms.append(np.array([list(row) for row in prop.GetTransform().Fields], dtype=np.float64))
        dims = {(s.GetSheetCount(), s.GetRowCount(), s.GetColumnCount()) for s in self.stacks}
        if len(dims) != 1:
            raise ValueError(f"path: {path!r}: the material image stacks differ in size: {sorted(dims)}")
        self.shape = dims.pop()
        transform = transforms[0]
        if any(not np.allclose(t, transform, rtol=1e-6, atol=0) for t in transforms):
            raise ValueError(f"path: {path!r}: the material properties have different transforms")
        linear, offset = transform[:3], transform[3]
        if np.abs(linear - np.diag(np.diag(linear))).max() > 0 or (np.diag(linear) == 0).any():
            raise ValueError(f"path: {path!r}: expected an axis-aligned scaling transform, got "
                             f"{transform.tolist()}")
        # reversed[a]: coordinate a decreases along the image axis a (negative scale, offset 1).
        reversed_axes = []
        for a, name in enumerate("uvw"):
            scale = linear[a, a]
            if scale > 0 and abs(offset[a]) < 1e-5:
                reversed_axes.append(False)
            elif scale < 0 and abs(offset[a] - 1) < 1e-5:
                reversed_axes.append(True)
            else:
                raise ValueError(f"path: {path!r}: unsupported {name} mapping {name} = {scale:g}·x + {offset[a]:g}; "
                                 f"expected the voxel grid to start at the origin")
        counts = (self.shape[2], self.shape[1], self.shape[0])               # x, y, z
        pitch = tuple(to_mm / (counts[a] * abs(linear[a, a])) for a in range(3))
        recorded = metadata.get((NAMESPACE, "pitch_mm"))
        try:
            exact = tuple(float(v) for v in recorded.split()) if recorded else None
        except ValueError:
            exact = None
        if exact is not None and len(exact) == 3 and np.allclose(exact, pitch, rtol=1e-5, atol=0):
            pitch = exact
        self.pitch_mm = pitch
        # Spec: image row i sits at v = 1 - (i + 1/2) / rows, so a direct v axis stores rows top-down (y flipped).
        self.flip_columns, self.flip_rows, self.flip_sheets = reversed_axes[0], not reversed_axes[1], reversed_axes[2]

    def _sheet(self, m, k):
        stack = self.stacks[m]
        sheet = stack.GetSheet(k)
        size = sheet.GetStreamSize()
        data = np.empty(size, dtype=np.uint8)
        needed = ctypes.c_uint64()
        _call(sheet, "attachment_writetobuffer", ctypes.c_uint64(size), needed, _pointer(data, ctypes.c_uint8))
        image = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if size else None
        where = f"path: {self.path!r}: material_{m} sheet {k} ({sheet.GetPath()})"
        if image is None:
            raise ValueError(f"{where}: not a decodable PNG")
        if image.shape[:2] != self.shape[1:]:
            raise ValueError(f"{where}: expected {self.shape[1]} rows × {self.shape[2]} columns, got "
                             f"{image.shape[0]} × {image.shape[1]}")
        if image.ndim == 2:
            values = image if self.channels[m] != "alpha" else np.full_like(image, np.iinfo(image.dtype).max)
        else:
            channel = _CV_CHANNEL[self.channels[m]]
            values = image[..., channel] if channel < image.shape[2] else \
                np.full(image.shape[:2], np.iinfo(image.dtype).max, image.dtype)
        full = np.iinfo(values.dtype).max
        mask = values == full
        if np.count_nonzero(mask) + np.count_nonzero(values == 0) != mask.size:
            raise ValueError(f"{where}: expected a binary mask (0 or {full}), got intermediate values (mixing "
                             f"ratios cannot be read as material indices)")
        return mask

    def layer(self, k):
        """(Hy, Wx) uint8 material indices of printer layer k (255 = void)."""
        lib3mf, _ = _lib3mf()
        try:
            return self._layer(k)
        except lib3mf.ELib3MFException as error:
            raise ValueError(f"path: cannot read layer {k} of {self.path!r}: {error}") from None

    def _layer(self, k):
        sheet = self.shape[0] - 1 - k if self.flip_sheets else k
        plus_one = np.zeros(self.shape[1:], dtype=np.uint8)      # material + 1 where set (at most 255 materials)
        count = np.zeros(self.shape[1:], dtype=np.uint8)
        masks = []
        for m in range(len(self.stacks)):
            masks.append(self._sheet(m, sheet))
            ones = masks[-1].view(np.uint8)
            count += ones
            plus_one += ones * np.uint8(m + 1)
        layer = plus_one - np.uint8(1)                              # no material: 0 - 1 wraps to VOID = 255
        if int(count.max()) > 1:
            i, j = np.argwhere(count > 1)[0]
            both = [m for m, mask in enumerate(masks) if mask[i, j]][:2]
            raise ValueError(f"path: {self.path!r}: layer {k}, image row {i}, column {j} is set in the sheets of "
                             f"material {both[0]} and material {both[1]}; expected one material per voxel")
        if self.flip_rows:
            layer = layer[::-1]
        if self.flip_columns:
            layer = layer[:, ::-1]
        return np.ascontiguousarray(layer)


def _open(path):
    """``(path, model, mesh, metadata, volume, mm per file unit)`` of a 3MF file with one mesh object."""
    lib3mf, _ = _lib3mf()
    path, model = _read_model(path)
    try:
        meshes = _resources(model.GetMeshObjects(), "GetCurrentMeshObject")
        if len(meshes) != 1:
            raise ValueError(f"path: {path!r} holds {len(meshes)} mesh objects; expected one")
        unit = {v: k for k, v in _UNIT_ENUM.items()}[model.GetUnit().name]
        metadata = _metadata(model)
        volume = _Volume(path, model, meshes[0], metadata, UNITS_MM[unit])
    except lib3mf.ELib3MFException as error:
        raise ValueError(f"path: cannot read {path!r}: {error}") from None
    return path, model, meshes[0], metadata, volume, unit


def iter_3mf_layers(path):
    """The material volume of a file written by :func:`write_3mf`, one layer at a time.

    The file is read (and checked) when this is called; the layers are decoded as they are asked for.

    Returns:
        An iterator of ``grid_shape[0]`` uint8 (Hy, Wx) arrays, printer layer 0 (bottom) first, row j ↔ y,
        column i ↔ x, material indices with 255 for void.

    Raises:
        ValueError: the file is missing, truncated or not 3MF, has no volume, or holds a volume in another
            encoding; while iterating: a sheet that is not a binary PNG of the stack's size, a voxel set in two
            materials' sheets.
    """
    path, _, _, _, volume, _ = _keeps_locale(_open)(path)
    if not volume.present:
        raise ValueError(f"path: {path!r} holds no volume data")
    layer = _keeps_locale(volume.layer)
    return (layer(k) for k in range(volume.shape[0]))


@_keeps_locale
def read_3mf(path):
    """Read a 3MF file written by :func:`write_3mf` (and the mesh and colours of other single-mesh 3MF files).

    Returns:
        dict with

        - ``vertices``: (V, 3) float64, mm (float32 precision, as 3MF stores them);
        - ``faces``: (F, 3) int64;
        - ``vertex_rgb``: (V, 3) uint8 sRGB when every vertex has one colour across its triangles, else None
          (unused vertices get 0);
        - ``face_rgb``: (F, 3) uint8 sRGB when the file holds one colour per triangle (and the writer said so,
          or the colours are not per vertex), else None;
        - ``corner_rgb``: (F, 3, 3) uint8 sRGB, the colour of each triangle corner as stored, or None when not
          every triangle has a colour;
        - ``materials``: list of ``(name, (r, g, b, a))`` from the base materials ([] when none);
        - ``indices``: (Dz, Hy, Wx) uint8 material indices (255 = void), layer 0 at the bottom, or None when
          the mesh has no volume data;
        - ``pitch_mm``: (sx, sy, sz) floats, mm, or None;
        - ``grid_shape``: (Dz, Hy, Wx) ints, or None;
        - ``unit``: the file's 3MF unit (all lengths above are converted to mm).

    Raises:
        ValueError: naming the file: missing (also a FileNotFoundError), truncated or not 3MF; not exactly one
            mesh object; a volume in another encoding (e.g. mixing ratios, non-axis-aligned transforms); a voxel
            set in two materials' sheets.
    """
    path, model, mesh, metadata, volume, unit = _open(path)
    lib3mf, _ = _lib3mf()
    try:
        positions, faces, properties = _mesh_arrays(path, mesh)
        corner = _corner_colours(model, properties)
    except lib3mf.ELib3MFException as error:
        raise ValueError(f"path: cannot read {path!r}: {error}") from None
    kind = metadata.get((NAMESPACE, "colours"))
    vertex_rgb, face_rgb = _split_colours(corner, faces, len(positions), kind)
    result = {"vertices": positions.astype(np.float64) * UNITS_MM[unit], "faces": faces, "vertex_rgb": vertex_rgb,
              "face_rgb": face_rgb, "corner_rgb": corner, "materials": volume.materials, "indices": None,
              "pitch_mm": None, "grid_shape": None, "unit": unit}
    if volume.present:
        indices = np.empty(volume.shape, dtype=np.uint8)
        for k in range(volume.shape[0]):
            indices[k] = volume.layer(k)
        result.update(indices=indices, pitch_mm=volume.pitch_mm, grid_shape=tuple(int(v) for v in volume.shape))
    return result
