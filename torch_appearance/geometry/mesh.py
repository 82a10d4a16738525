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


def load_mesh(path, *, height_mm=None, scale=None):
    """Load a triangle mesh and scale it to millimetres.

    Args:
        path: OBJ (+ MTL + texture), GLB/GLTF, PLY or STL file. Multi-object files are concatenated.
        height_mm: scale uniformly so that the z extent is this many mm (> 0); or
        scale: a factor from file units to mm (> 0), e.g. 1000 for a model in metres. Neither: file units are mm.

    Returns:
        (mesh, report): a ``trimesh.Trimesh`` in mm that keeps its UVs and texture (or vertex/face colours), and a
        dict with ``triangles``, ``vertices``, ``watertight`` (after merging seam-split vertices), ``colour``
        (``texture``/``vertex``/``face``/``none``), ``texture_size`` (w, h) or None, ``extent_file_units``,
        ``units_guess`` (what the extent suggests the file's units were) and ``scale_to_mm``.

    Raises:
        ValueError: unreadable or missing file, no triangles, a texture file named by the MTL that is missing,
            bad height or scale, both height_mm and scale given.
    """
    import trimesh

    if not isinstance(path, (str, os.PathLike)):
        raise TypeError(f"path: expected a file path, got {type(path).__name__}")
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise ValueError(f"path: no such file {path!r}")
    if height_mm is not None and scale is not None:
        raise ValueError("height_mm, scale: expected at most one of them, got both")
    if path.lower().endswith(".obj"):
        missing = _obj_missing_textures(path)
        if missing:
            raise ValueError(f"path: {path!r} names texture/material files that are missing: {missing}")
    try:
        mesh = trimesh.load(path, force="mesh")
    except Exception as error:  # trimesh raises many kinds for unreadable input
        raise ValueError(f"path: could not read {path!r} as a mesh ({type(error).__name__}: {error})") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise ValueError(f"path: {path!r} holds no triangles")
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
    mesh.apply_scale(factor)
    biggest = float(extent.max())
    guess = "m" if biggest < 2.0 else ("cm" if biggest < 20.0 else "mm")
    merged = mesh.copy()
    merged.merge_vertices(merge_tex=True, merge_norm=True)
    visual = mesh.visual
    kind = getattr(visual, "kind", None) or "none"
    size = None
    if kind == "texture":
        material = visual.material
        image = getattr(material, "image", None)
        if image is None:
            image = getattr(material, "baseColorTexture", None)
        size = None if image is None else tuple(image.size)
    report = {"triangles": int(len(mesh.faces)), "vertices": int(len(mesh.vertices)),
              "watertight": bool(merged.is_watertight), "colour": kind, "texture_size": size,
              "extent_file_units": extent.tolist(), "units_guess": guess, "scale_to_mm": float(factor)}
    return mesh, report
