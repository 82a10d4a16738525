"""Loading textured meshes as artists and scanners deliver them (OBJ + MTL + texture, glTF/GLB, PLY, STL) via
trimesh, scaled to millimetres."""
import os
import re

import numpy as np

from ..checks import check_real

__all__ = ["load_mesh"]


def _obj_textures(path):
    """Texture files named by the MTL libraries of an OBJ (names may contain spaces): (missing names, {name as
    written in the MTL: path} of the existing ones)."""
    folder = os.path.dirname(os.path.abspath(path))
    missing, present = [], {}
    with open(path, "r", errors="replace") as handle:
        libs = [line.split(None, 1)[1].strip() for line in handle if line.startswith("mtllib ") and len(line.split()) > 1]
    for lib in libs:
        mtl = os.path.join(folder, lib)
        if not os.path.exists(mtl):
            missing.append(lib)
            continue
        with open(mtl, "r", errors="replace") as handle:
            for line in handle:
                m = re.match(r"\s*map_Kd\s+(?:-\S+\s+\S+\s+)*(.+?)\s*$", line)
                if m:
                    texture = os.path.join(os.path.dirname(mtl), m.group(1))
                    if os.path.exists(texture):
                        present[m.group(1)] = texture
                    else:
                        missing.append(m.group(1))
    return missing, present


def _ply_textures(path):
    """The texture a PLY names in its header (``comment TextureFile NAME``): (missing names, {NAME: path})."""
    with open(path, "rb") as handle:
        header = handle.read(65536).split(b"end_header", 1)[0].decode("ascii", errors="replace")
    missing, present = [], {}
    for line in header.splitlines():
        m = re.match(r"\s*comment\s+TextureFile\s+(.+?)\s*$", line)
        if m:
            texture = os.path.join(os.path.dirname(os.path.abspath(path)), m.group(1))
            if os.path.exists(texture):
                present[m.group(1)] = texture
            else:
                missing.append(m.group(1))
    return missing, present


def _read_texture(texture, name="texture"):
    """A base-colour image file read by :func:`torch_appearance.io.read_image` (decoded completely, so truncated or
    corrupt files fail here; sRGB kept, grey repeated over R, G, B, palette expanded, alpha dropped) as an 8-bit
    RGB PIL image, the form trimesh's materials hold. 16-bit textures are rounded to 8 bits."""
    from PIL import Image

    from .. import io as ta_io

    if not isinstance(texture, (str, os.PathLike)):
        raise TypeError(f"{name}: expected an image file path, got {type(texture).__name__}")
    texture = os.fspath(texture)
    if not os.path.isfile(texture):
        raise ValueError(f"{name}: no such file {texture!r}")
    srgb = ta_io.read_image(texture, space="srgb", name=name)
    return Image.fromarray(np.rint(np.clip(srgb, 0.0, 1.0) * 255.0).astype(np.uint8))


def _gltf_images(path):
    """The images a glTF/GLB file embeds or names, as ``(label, bytes or file path)``: buffer views (the GLB's BIN
    chunk or a buffer file), base64 data URIs and image files beside the glTF. ``[]`` when the file's JSON cannot be
    parsed (trimesh then reports the file)."""
    import base64
    import json
    import struct
    import urllib.parse

    folder = os.path.dirname(os.path.abspath(path))
    with open(path, "rb") as handle:
        data = handle.read()

    def from_uri(uri):
        if uri.startswith("data:"):
            return base64.b64decode(uri.split(",", 1)[1])
        return os.path.join(folder, urllib.parse.unquote(uri))

    try:
        binary = None
        if data[:4] == b"glTF":
            offset, doc = 12, None
            while offset + 8 <= len(data):
                length, kind = struct.unpack_from("<I4s", data, offset)
                chunk = data[offset + 8:offset + 8 + length]
                offset += 8 + length
                if kind == b"JSON":
                    doc = json.loads(chunk)
                elif kind == b"BIN\x00" and binary is None:
                    binary = chunk
        else:
            doc = json.loads(data)
        images = []
        for i, image in enumerate(doc.get("images", [])):
            label = image.get("name") or image.get("uri", "")[:40] or f"image {i}"
            if "bufferView" in image:
                view = doc["bufferViews"][image["bufferView"]]
                buffer = doc["buffers"][view["buffer"]]
                if "uri" in buffer:
                    blob = from_uri(buffer["uri"])
                    if not isinstance(blob, bytes):
                        with open(blob, "rb") as handle:
                            blob = handle.read()
                else:
                    blob = binary
                start = view.get("byteOffset", 0)
                images.append((f"embedded texture {label}", blob[start:start + view["byteLength"]]))
            elif "uri" in image:
                images.append((f"texture {label}", from_uri(image["uri"])))
        return images
    except (ValueError, KeyError, IndexError, TypeError, AttributeError, OSError, struct.error):
        return []


def _check_gltf_textures(path):
    """Read every image of a glTF/GLB (:func:`_gltf_images`) through :func:`torch_appearance.io.read_image`, so that
    a truncated or corrupt texture is refused with its name (trimesh drops one it cannot open without a word)."""
    from .. import io as ta_io

    for label, source in _gltf_images(path):
        try:
            if isinstance(source, bytes):
                ta_io.read_image_bytes(source, source=f"{path} ({label})", name="texture")
            else:
                ta_io.decode_image(source, name="texture")
        except (ValueError, FileNotFoundError) as error:
            raise ValueError(f"path: {path!r} holds a texture that cannot be read: {error}") from None


def _load_strictly(mesh, path):
    """Decode, with truncated loading off (:func:`torch_appearance.io.strict_pillow`), a base-colour image that
    trimesh opened lazily from a format whose textures are not read beforehand (PLY, DAE, ...), so that a truncated
    or corrupt one is refused here (``ValueError`` naming ``path``) rather than filled in later."""
    from trimesh.visual.material import PBRMaterial

    from .. import io as ta_io

    material = getattr(mesh.visual, "material", None)
    image = getattr(material, "baseColorTexture" if isinstance(material, PBRMaterial) else "image", None)
    if image is None or not hasattr(image, "load"):
        return
    try:
        with ta_io.strict_pillow():
            image.load()
    except Exception as error:  # Pillow raises OSError, SyntaxError, ... for broken data
        raise ValueError(f"path: {path!r} holds a texture that cannot be decoded completely (truncated or corrupt: "
                         f"{type(error).__name__}: {error})") from None


def _use_checked_textures(mesh, textures, ply=False):
    """Replace an OBJ's (or PLY's) base-colour image that trimesh opened itself (from the MTL's ``map_Kd``, the PLY's
    ``TextureFile``) with the same file
    as read by :func:`_read_texture` (``textures``: MTL name → that PIL image), so that its colours are converted as
    documented there (16-bit and grey images included) rather than by PIL's ``convert``. (Several textures packed
    by trimesh into one atlas keep trimesh's packing; each was read and checked before.)"""
    material = getattr(mesh.visual, "material", None)
    image = getattr(material, "image", None)
    name = getattr(image, "info", {}).get("file_path") if image is not None else None
    if ply and name is None and len(textures) == 1:
        name = next(iter(textures))  # a PLY names one texture; trimesh does not record its name
    if image is not None and name in textures:
        material.image = textures[name]


def load_mesh(path, *, height_mm=None, scale=None, texture=None):
    """Load a triangle mesh and scale it to millimetres.

    Args:
        path: OBJ (+ MTL + texture), GLB/GLTF, PLY or STL file. Multi-object files are concatenated.
        height_mm: scale uniformly so that the z extent is this many mm (> 0); or
        scale: a factor from file units to mm (> 0), e.g. 1000 for a model in metres. Neither: file units are mm.
        texture: optional path of a base-colour image (sRGB, e.g. PNG) for a mesh with UVs, e.g. an OBJ with ``vt``
            lines but no MTL; it replaces any material the file has (``hint`` says so when the file had a texture).

    Returns:
        (mesh, report): a ``trimesh.Trimesh`` in mm that keeps its UVs and texture (or vertex/face colours), and a
        dict with ``triangles``, ``vertices``, ``watertight`` (after merging seam-split vertices), ``colour``
        (``texture``: an image; ``material``: a uniform glTF ``baseColorFactor``; ``vertex``/``face`` colours;
        ``none``), ``texture_size`` (w, h) or None, ``texture_source`` (``file``, ``argument`` or None), ``uv``
        (whether the mesh has texture coordinates), ``extent_file_units``, ``units_guess`` (what the extent
        suggests the file's units were), ``scale_to_mm``, ``hint`` (a suggestion, or None) and ``materials`` (the
        names of the file's materials, or of its parts where they have none). ``mesh.metadata`` holds the same
        ``material_names`` and ``face_materials``, (F,) int32 indices into them. An OBJ with UVs and
        no texture gets a placeholder image from trimesh; it is removed (the material keeps no image), so the
        mesh reports, and voxelises with, no colour.

    Raises:
        ValueError: unreadable or missing file, no triangles, a texture file named by the MTL (or a glTF/GLB texture)
            that is missing, truncated or corrupt (read by :func:`torch_appearance.io.read_image`),
            bad height or scale, both height_mm and scale given, a ``texture`` file that is missing or not an
            image, a ``texture`` for a mesh without UVs.
        TypeError: ``path`` or ``texture`` not a file path.
    """
    import trimesh

    from .surface import _base_colour, _is_placeholder_image

    if not isinstance(path, (str, os.PathLike)):
        raise TypeError(f"path: expected a file path, got {type(path).__name__}")
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise ValueError(f"path: no such file {path!r}")
    if height_mm is not None and scale is not None:
        raise ValueError("height_mm, scale: expected at most one of them, got both")
    image = None if texture is None else _read_texture(texture)
    lower = path.lower()
    if lower.endswith((".obj", ".ply")):
        missing, present = (_obj_textures if lower.endswith(".obj") else _ply_textures)(path)
        if missing:
            raise ValueError(f"path: {path!r} names texture/material files that are missing: {missing}")
        for key, texture_path in present.items():  # trimesh drops a texture it cannot open without a word: read
            try:                                       # each through the reader first
                present[key] = _read_texture(texture_path)
            except ValueError as error:
                raise ValueError(f"path: {path!r} names a texture that cannot be read: {error}") from None
    elif lower.endswith((".glb", ".gltf")):
        _check_gltf_textures(path)
    try:
        # what trimesh.load(force="mesh") does (scene → baked parts → one mesh), keeping each face's material
        # read unprocessed first: trimesh's processing silently drops faces with NaN/Inf vertices
        parts = [g for g in trimesh.load_scene(path, process=False).dump()
                 if isinstance(g, trimesh.Trimesh) and len(g.faces)]
    except Exception as error:  # trimesh raises many kinds for unreadable input
        raise ValueError(f"path: could not read {path!r} as a mesh ({type(error).__name__}: {error})") from None
    bad = sum(int((~np.isfinite(np.asarray(g.vertices, dtype=np.float64)[g.faces])).any(axis=(1, 2)).sum())
              for g in parts)
    if bad:
        raise ValueError(f"path: {path!r} has non-finite (NaN or Inf) vertex coordinates in {bad} of "
                         f"{sum(len(g.faces) for g in parts)} triangles; repair or remove them in the mesh")
    try:
        for g in parts:
            g.process()  # what loading with process=True does: merge vertices, drop degenerate data
        mesh = trimesh.util.concatenate(parts) if parts else None
    except Exception as error:
        raise ValueError(f"path: could not read {path!r} as a mesh ({type(error).__name__}: {error})") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise ValueError(f"path: {path!r} holds no triangles")
    names = [str(getattr(getattr(g.visual, "material", None), "name", None) or g.metadata.get("name") or f"part{i}")
             for i, g in enumerate(parts)]
    material_names = list(dict.fromkeys(names))
    mesh.metadata["material_names"] = material_names
    mesh.metadata["face_materials"] = np.repeat(np.array([material_names.index(n) for n in names], np.int32),
                                                [len(g.faces) for g in parts])
    if image is None and lower.endswith((".obj", ".ply")):
        _use_checked_textures(mesh, present, ply=lower.endswith(".ply"))
    elif image is None and not lower.endswith((".glb", ".gltf")):
        _load_strictly(mesh, path)
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    if not np.isfinite(vertices).all():
        raise ValueError(f"path: {path!r} has non-finite vertex coordinates")
    extent = vertices.max(0) - vertices.min(0)
    if height_mm is not None:
        height_mm = check_real("height_mm", height_mm, lo=0.0, lo_open=True)
        if not extent[2] > 0:
            raise ValueError(f"height_mm: the mesh has no z extent to scale ({extent.tolist()})")
        factor = height_mm / extent[2]
    elif scale is not None:
        factor = check_real("scale", scale, lo=0.0, lo_open=True)
    else:
        factor = 1.0
    uv = getattr(mesh.visual, "uv", None) if getattr(mesh.visual, "kind", None) == "texture" else None
    replaced = None
    if image is not None:
        if uv is None or len(uv) != len(mesh.vertices):
            raise ValueError(f"texture: the mesh in {path!r} has no texture coordinates (UVs) to map an image with")
        own = _base_colour(mesh.visual.material)[0]
        replaced = None if own is None else tuple(int(n) for n in own.size)
        mesh.visual = trimesh.visual.TextureVisuals(uv=np.asarray(uv), image=image)
    elif uv is not None and _is_placeholder_image(getattr(mesh.visual.material, "image", None)):
        mesh.visual.material.image = None  # trimesh's stand-in for "no image", not the file's colour
    mesh.apply_scale(factor)
    biggest = float(extent.max())
    guess = "m" if biggest < 2.0 else ("cm" if biggest < 20.0 else "mm")
    merged = mesh.copy()
    merged.merge_vertices(merge_tex=True, merge_norm=True)
    kind = getattr(mesh.visual, "kind", None) or "none"
    size = None
    hint = None
    if kind == "texture":
        tex, base = _base_colour(mesh.visual.material)
        if tex is not None and uv is not None:
            size = tuple(int(n) for n in tex.size)
        else:
            kind = "material" if base is not None else "none"
        if kind == "none":
            hint = ("the mesh has texture coordinates but no texture image: pass texture=PATH (the base-colour "
                    "image) to attach one" if uv is not None else None)
    if replaced is not None:
        hint = f"texture= replaced the file's own {replaced[0]}x{replaced[1]} texture"
    report = {"triangles": int(len(mesh.faces)), "vertices": int(len(mesh.vertices)),
              "watertight": bool(merged.is_watertight), "colour": kind, "texture_size": size,
              "texture_source": None if size is None else ("argument" if image is not None else "file"),
              "uv": uv is not None, "extent_file_units": extent.tolist(), "units_guess": guess,
              "scale_to_mm": float(factor), "hint": hint, "materials": material_names}
    return mesh, report
