"""Per-texel values baked back into a mesh's texture space (a PNG in the mesh's UV layout).

Every texture pixel covered by a UV triangle is mapped to its 3D point on that triangle (barycentric
interpolation of the triangle's corners) and takes the value of the nearest texel in 3D; so values never bleed
across UV seams (pixels on either side of a seam map to 3D points on their own side of the surface). Uncovered
pixels take the value of the nearest covered pixel, so bilinear filtering and mip-maps stay clean at the island
borders.
"""
import numpy as np

__all__ = ["uv_face_image", "bake_texels"]


def uv_face_image(mesh, size):
    """Which face covers each texture pixel (its centre lies in the face's UV triangle).

    Triangles are shifted by whole units towards the unit square (tiled layouts that repeat the texture cover it
    too); triangles without UV area (collapsed) are left out. cv2 rasterises conservatively (edge pixels whose
    centre lies outside are drawn too), so each drawn pixel's centre is tested against its triangle; a centre on an
    edge shared by two triangles may fail the test of the one drawn last and stay uncovered.

    Args:
        mesh: a ``trimesh.Trimesh`` with per-vertex UVs (``mesh.visual.uv``).
        size: (height, width) of the texture in pixels.

    Returns:
        (height, width) int32 face ids, −1 where no UV triangle covers the pixel centre (row 0 is v = 1).
    """
    import cv2

    uv = getattr(mesh.visual, "uv", None)
    if uv is None:
        raise ValueError("mesh: has no texture coordinates (UVs) to bake into")
    h, w = (int(s) for s in size)
    if h < 1 or w < 1:
        raise ValueError(f"size: expected (height, width) >= 1, got {size!r}")
    uv = np.asarray(uv, dtype=np.float64)[np.asarray(mesh.faces, dtype=np.int64)]      # (M, 3, 2)
    d1, d2 = uv[:, 1] - uv[:, 0], uv[:, 2] - uv[:, 0]
    area2 = 0.5 * np.abs(d1[:, 0] * d2[:, 1] - d2[:, 0] * d1[:, 1])
    ids = np.flatnonzero(area2 > 1e-12 * max(float(area2.max(initial=0.0)), 1e-300))
    uv = uv[ids] - np.floor(uv[ids].mean(1, keepdims=True))
    shift = 4  # 4 bits of sub-pixel precision (cv2 'shift'); pixel centres at integers
    xy = np.stack([uv[..., 0] * w - 0.5, (1.0 - uv[..., 1]) * h - 0.5], axis=-1)
    fixed = np.round(xy * (1 << shift)).astype(np.int32)
    drawn = np.full((h, w), -1, dtype=np.int32)
    hits = np.flatnonzero((fixed.max(1) >= 0).all(1) & (fixed.min(1)[:, 0] < w << shift)
                          & (fixed.min(1)[:, 1] < h << shift))
    for f in hits:
        cv2.fillConvexPoly(drawn, fixed[f], int(f), lineType=cv2.LINE_8, shift=shift)
    rows, cols = np.nonzero(drawn >= 0)
    tri = xy[drawn[rows, cols]]                                                          # (K, 3, 2)
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    e0 = np.stack([cols, rows], axis=1).astype(np.float64) - tri[:, 0]
    det = e1[:, 0] * e2[:, 1] - e2[:, 0] * e1[:, 1]
    b1 = (e0[:, 0] * e2[:, 1] - e2[:, 0] * e0[:, 1]) / det
    b2 = (e1[:, 0] * e0[:, 1] - e0[:, 0] * e1[:, 1]) / det
    eps = 1e-9
    inside = (b1 >= -eps) & (b2 >= -eps) & (b1 + b2 <= 1 + eps)
    image = np.full((h, w), -1, dtype=np.int32)
    image[rows[inside], cols[inside]] = ids[drawn[rows[inside], cols[inside]]]
    return image


def bake_texels(mesh, texel_points, values, size=(1024, 1024)):
    """Bake per-texel values into the mesh's UV layout.

    Args:
        mesh: a ``trimesh.Trimesh`` with UVs (mm, the mesh that was voxelised).
        texel_points: (N, 3) texel surface points, mm (``VoxelObject.texel_points``).
        values: (N, C) per-texel values (e.g. linear RGB).
        size: (height, width) of the texture.

    Returns:
        (height, width, C) float32 image (row 0 is v = 1, as image files store textures), and the (height, width)
        bool mask of the pixels covered by UV triangles.
    """
    from scipy import ndimage
    from scipy.spatial import cKDTree

    values = np.asarray(values, dtype=np.float32)
    points = np.asarray(texel_points, dtype=np.float64)
    if values.ndim != 2 or values.shape[0] != points.shape[0]:
        raise ValueError(f"values: expected shape ({points.shape[0]}, C), got {values.shape}")
    faces = uv_face_image(mesh, size)
    covered = faces >= 0
    if not covered.any():
        raise ValueError("mesh: its UV triangles cover no pixel centre of the texture")
    h, w = faces.shape
    rows, cols = np.nonzero(covered)
    fid = faces[rows, cols]
    uv = np.asarray(mesh.visual.uv, dtype=np.float64)
    tri_uv = uv[np.asarray(mesh.faces)[fid]]                       # (M, 3, 2)
    tri_uv = tri_uv - np.floor(tri_uv.mean(1, keepdims=True))      # the tiling shift of uv_face_image
    p = np.stack([(cols + 0.5) / w, 1.0 - (rows + 0.5) / h], axis=1)
    a, b, c = tri_uv[:, 0], tri_uv[:, 1], tri_uv[:, 2]
    v0, v1, v2 = b - a, c - a, p - a
    den = v0[:, 0] * v1[:, 1] - v1[:, 0] * v0[:, 1]
    den = np.where(np.abs(den) > 1e-300, den, 1.0)
    beta = (v2[:, 0] * v1[:, 1] - v1[:, 0] * v2[:, 1]) / den
    gamma = (v0[:, 0] * v2[:, 1] - v2[:, 0] * v0[:, 1]) / den
    bary = np.clip(np.stack([1 - beta - gamma, beta, gamma], axis=1), 0, None)
    bary /= np.maximum(bary.sum(1, keepdims=True), 1e-300)
    xyz = (np.asarray(mesh.vertices, dtype=np.float64)[np.asarray(mesh.faces)[fid]] * bary[:, :, None]).sum(1)
    _, nearest = cKDTree(points).query(xyz, workers=-1)
    out = np.zeros((h, w, values.shape[1]), dtype=np.float32)
    out[rows, cols] = values[nearest]
    _, (ri, ci) = ndimage.distance_transform_edt(~covered, return_indices=True)
    out = out[ri, ci]
    return out, covered
