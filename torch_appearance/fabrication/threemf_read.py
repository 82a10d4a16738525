"""Reading back the 3MF files of :mod:`.threemf`: :func:`read_3mf` (geometry, viewer colours, materials and the
index volume) and :func:`iter_3mf_layers` (the index volume one layer at a time, memory of one layer), through
lib3mf, with the conventions :mod:`.threemf` documents (one ``material_k`` volumetric property per base material,
1-bit sheets, the exact pitch and grid shape in ``urn:torch-appearance:3mf:1`` metadata).
"""
import ctypes
import os

import cv2
import numpy as np

from ..checks import check_path
from .threemf import (_CV_CHANNEL, _UNIT_ENUM, NAMESPACE, UNITS_MM, _call, _keeps_locale, _lib3mf, _MissingFileError,
                      _pointer)

__all__ = ["read_3mf", "iter_3mf_layers"]

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
