"""What a mesh says at points on its surface: barycentric coordinates, smooth normals (crease-aware), texture
coordinates and linear-RGB colours (texture, vertex or face colours)."""
import math

import numpy as np
import torch

__all__ = ["surface_attributes", "barycentric"]


def barycentric(p, a, b, c):
    """Barycentric coordinates (N, 3) of points p (N, 3) in triangles (a, b, c), each (N, 3), clipped to the
    triangle (negative weights of points off it set to 0, renormalised)."""
    v0, v1, v2 = b - a, c - a, p - a
    d00, d01, d11 = (v0 * v0).sum(1), (v0 * v1).sum(1), (v1 * v1).sum(1)
    d20, d21 = (v2 * v0).sum(1), (v2 * v1).sum(1)
    den = d00 * d11 - d01 * d01
    den = np.where(np.abs(den) > 1e-300, den, 1.0)
    v = (d11 * d20 - d01 * d21) / den
    w = (d00 * d21 - d01 * d20) / den
    bary = np.clip(np.stack([1 - v - w, v, w], axis=1), 0, None)
    return bary / np.maximum(bary.sum(1, keepdims=True), 1e-300)


def _texture_lookup(image, uv):
    """Bilinear lookup of an (h, w, 3) linear-RGB texture at uv (N, 2): v up, texel centres at ((i + ½)/w,
    1 − (j + ½)/h), repeat wrap on both axes (glTF's default sampler)."""
    h, w = image.shape[:2]
    x = (uv[:, 0] % 1.0) * w - 0.5
    y = (1.0 - uv[:, 1] % 1.0) * h - 0.5
    x0 = np.floor(x).astype(np.int64)
    y0 = np.floor(y).astype(np.int64)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    x0, x1 = x0 % w, (x0 + 1) % w
    y0, y1 = y0 % h, (y0 + 1) % h
    return ((image[y0, x0] * (1 - fx) + image[y0, x1] * fx) * (1 - fy)
            + (image[y1, x0] * (1 - fx) + image[y1, x1] * fx) * fy)


def _is_placeholder_image(image):
    """True for the stand-in texture trimesh makes when a mesh has UVs but no image (``TextureVisuals(uv=...)``,
    e.g. an OBJ with ``vt`` lines and no MTL): a 2×2 image in its default grey, made in memory (no file format).
    Such a texture says nothing about the object's colour."""
    from trimesh.visual.material import color_image

    if image is None or getattr(image, "format", None) is not None or tuple(image.size) != (2, 2):
        return False
    return bool(np.array_equal(np.asarray(image.convert("RGBA")), np.asarray(color_image())))


def _base_colour(material):
    """The base colour a trimesh material gives: (image or None, factor (3,) float64 linear RGB or None).

    ``PBRMaterial`` (glTF): ``baseColorTexture`` and ``baseColorFactor`` (linear, RGBA uint8 in trimesh or float;
    alpha ignored); the colour is factor × texture, or the factor alone without a texture. ``SimpleMaterial``
    (OBJ/MTL, PLY): its ``image``, unless it is trimesh's placeholder (:func:`_is_placeholder_image`); its
    ``diffuse`` is not used, since trimesh fills in a default grey where a file gives none."""
    from trimesh.visual.color import to_float
    from trimesh.visual.material import PBRMaterial

    if isinstance(material, PBRMaterial):
        factor = material.baseColorFactor
        factor = None if factor is None else np.asarray(to_float(factor), dtype=np.float64).reshape(-1)[:3]
        return material.baseColorTexture, factor
    image = getattr(material, "image", None)
    return (None if _is_placeholder_image(image) else image), None


def _corner_normals(V, F, crease_deg=30.0):
    """Smooth normals at each face corner (F, 3, 3): the area-weighted normals of the faces around the corner's
    position (seams split for UVs do not split them) whose normal is within ``crease_deg`` of this face's, so
    curved surfaces are smooth and hard edges (a box) stay sharp."""
    _, pos = np.unique(V, axis=0, return_inverse=True)
    Fp = pos.reshape(-1)[F]                                   # faces in position ids
    tri = V[F]
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # length = 2·area
    unit = fn / np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-300)
    flat = Fp.reshape(-1)
    order = np.argsort(flat, kind="stable")
    faces_sorted = order // 3                                  # faces around each position, grouped
    starts = np.searchsorted(flat[order], np.arange(pos.max() + 1))
    counts = np.bincount(flat, minlength=pos.max() + 1)
    # expand every corner (f, c) to the faces g around its position
    corner_pos = flat
    n_per = counts[corner_pos]
    corner_id = np.repeat(np.arange(len(flat)), n_per)
    offset = np.arange(len(corner_id)) - np.repeat(np.cumsum(n_per) - n_per, n_per)
    g = faces_sorted[starts[corner_pos[corner_id]] + offset]
    f = corner_id // 3
    keep = (unit[f] * unit[g]).sum(1) >= math.cos(math.radians(crease_deg))
    out = np.zeros((len(flat), 3))
    np.add.at(out, corner_id[keep], fn[g[keep]])
    out /= np.maximum(np.linalg.norm(out, axis=1, keepdims=True), 1e-300)
    return out.reshape(len(F), 3, 3)


def _mesh_colours(mesh, faces, bary):
    """(colours (N, 3) float32 linear RGB or None, uv (N, 2) float32 or None) at points given by face ids (N,) and
    barycentrics (N, 3). Textures (sRGB 8-bit images) are decoded to linear and sampled bilinearly; a glTF
    ``baseColorFactor`` (linear) multiplies the texture, or is the colour where there is no texture (see
    :func:`_base_colour`); vertex colours are interpolated, face colours taken per face (both sRGB 8-bit)."""
    from ..color import srgb_to_linear
    visual = mesh.visual
    kind = getattr(visual, "kind", None)
    if kind == "texture":
        uv_v = getattr(visual, "uv", None)
        uv = None
        if uv_v is not None:
            uv = (np.asarray(uv_v, dtype=np.float64)[mesh.faces[faces]] * bary[:, :, None]).sum(1)
        image, factor = _base_colour(visual.material)
        colours = None
        if image is not None and uv is not None:
            tex = np.asarray(image.convert("RGB"), dtype=np.float64) / 255.0
            tex = np.asarray(srgb_to_linear(torch.from_numpy(tex)))
            colours = _texture_lookup(tex, uv)
            if factor is not None:
                colours = colours * factor
        elif factor is not None:
            colours = np.broadcast_to(factor, (len(faces), 3))
        return (None if colours is None else colours.astype(np.float32),
                None if uv is None else uv.astype(np.float32))
    if kind == "vertex":
        vc = np.asarray(visual.vertex_colors, dtype=np.float64)[:, :3] / 255.0
        rgb = (vc[mesh.faces[faces]] * bary[:, :, None]).sum(1)
        return np.asarray(srgb_to_linear(torch.from_numpy(rgb))).astype(np.float32), None
    if kind == "face":
        fc = np.asarray(visual.face_colors, dtype=np.float64)[faces, :3] / 255.0
        return np.asarray(srgb_to_linear(torch.from_numpy(fc))).astype(np.float32), None
    return None, None


def surface_attributes(mesh, faces, points):
    """Normals, colours and UVs of a mesh at points on its faces.

    Args:
        mesh: a ``trimesh.Trimesh`` (mm).
        faces: (N,) int face ids of the points.
        points: (N, 3) float points on those faces (e.g. closest points), mm.

    Returns:
        (normals (N, 3) float64 outward unit, colours (N, 3) float32 linear RGB or None, uv (N, 2) float32 or None).
    """
    V = np.asarray(mesh.vertices, dtype=np.float64)
    F = np.asarray(mesh.faces, dtype=np.int64)
    faces = np.asarray(faces, dtype=np.int64)
    tri = V[F[faces]]
    bary = barycentric(np.asarray(points, dtype=np.float64), tri[:, 0], tri[:, 1], tri[:, 2])
    normals = (_corner_normals(V, F)[faces] * bary[:, :, None]).sum(1)
    fn = np.asarray(mesh.face_normals, dtype=np.float64)[faces]
    bad = ~(np.linalg.norm(normals, axis=1) > 1e-12)
    normals[bad] = fn[bad]
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    colours, uv = _mesh_colours(mesh, faces, bary)
    return normals, colours, uv
