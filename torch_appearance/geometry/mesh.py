"""Loading textured meshes as artists and scanners deliver them (OBJ + MTL + texture, glTF/GLB, PLY, STL) via
trimesh, scaled to millimetres."""
import os
import re

import numpy as np

from ..render.checks import check_real

__all__ = ["load_mesh"]


def _obj_missing_textures(path):
    """Texture files named by the MTL libraries of an OBJ that do not exist (names may contain spaces)."""
    folder = os.path.dirname(os.path.abspath(path))
    missing = []
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
                if m and not os.path.exists(os.path.join(os.path.dirname(mtl), m.group(1))):
                    missing.append(m.group(1))
    return missing


def _read_texture(texture):
    """A base-colour image file opened (and decoded, so unreadable files fail here) as a PIL image."""
    from PIL import Image

    if not isinstance(texture, (str, os.PathLike)):
        raise TypeError(f"texture: expected an image file path, got {type(texture).__name__}")
    texture = os.fspath(texture)
    if not os.path.isfile(texture):
        raise ValueError(f"texture: no such file {texture!r}")
    try:
        image = Image.open(texture)
        image.load()
    except Exception as error:  # PIL raises UnidentifiedImageError, OSError, SyntaxError, ... for bad files
        raise ValueError(f"texture: could not read {texture!r} as an image ({type(error).__name__}: {error})") \
            from None
    return image


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
        ValueError: unreadable or missing file, no triangles, a texture file named by the MTL that is missing,
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
    if path.lower().endswith(".obj"):
        missing = _obj_missing_textures(path)
        if missing:
            raise ValueError(f"path: {path!r} names texture/material files that are missing: {missing}")
    try:
        # what trimesh.load(force="mesh") does (scene → baked parts → one mesh), keeping each face's material
        parts = [g for g in trimesh.load_scene(path).dump() if isinstance(g, trimesh.Trimesh) and len(g.faces)]
        mesh = trimesh.util.concatenate(parts) if parts else None
    except Exception as error:  # trimesh raises many kinds for unreadable input
        raise ValueError(f"path: could not read {path!r} as a mesh ({type(error).__name__}: {error})") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise ValueError(f"path: {path!r} holds no triangles")
    names = [str(getattr(getattr(g.visual, "material", None), "name", None) or g.metadata.get("name") or f"part{i}")
             for i, g in enumerate(parts)]
    material_names = list(dict.fromkeys(names))
    mesh.metadata["material_names"] = material_names
    mesh.metadata["face_materials"] = np.repeat(np.array([material_names.index(n) for n in names], np.int32),
                                                [len(g.faces) for g in parts])
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
