"""Texel values baked into a mesh's UV layout (geometry/bake.py)."""
import numpy as np
import pytest
import trimesh

from torch_appearance.geometry import voxelize
from torch_appearance.geometry.bake import bake_texels, uv_face_image


def plate(size=4.0, thickness=1.0):
    """A box whose top face (+z) maps (x, y) ∈ [−s/2, s/2]² linearly onto (u, v) ∈ [0.1, 0.9]²; the other faces
    share one small corner of UV space."""
    mesh = trimesh.creation.box((size, size, thickness))
    mesh.unmerge_vertices()
    v = np.asarray(mesh.vertices)
    uv = np.full((len(v), 2), 0.02)
    top = np.isclose(mesh.face_normals[:, 2], 1.0)
    top_vertices = np.unique(np.asarray(mesh.faces)[top])
    uv[top_vertices] = 0.1 + 0.8 * (v[top_vertices, :2] + size / 2) / size
    mesh.visual = trimesh.visual.TextureVisuals(uv=uv)
    return mesh, size


def test_bake_follows_the_uv_map_of_a_flat_face():
    """Baking the texels' own x, y: every covered pixel of the top face's island holds the (x, y) its UV maps to,
    to within the texel spacing; uncovered pixels are filled from covered ones."""
    mesh, size = plate()
    h = 0.1
    obj = voxelize(mesh, h)
    points = obj.texel_points.numpy()
    image, covered = bake_texels(mesh, points, points[:, :2], size=(128, 128))
    rows, cols = np.nonzero(covered)
    u, v = (cols + 0.5) / 128, 1 - (rows + 0.5) / 128
    island = (u > 0.1 + 2 / 128) & (u < 0.9 - 2 / 128) & (v > 0.1 + 2 / 128) & (v < 0.9 - 2 / 128)
    expected = np.stack([(u - 0.1) / 0.8 * size - size / 2, (v - 0.1) / 0.8 * size - size / 2], axis=1)
    err = np.abs(image[rows, cols] - expected)[island]
    assert island.sum() > 0.5 * 0.8 ** 2 * 128 ** 2
    assert err.max() <= h  # the nearest texel's point lies within about half a texel pitch
    assert np.isfinite(image).all() and covered.mean() < 0.7
    far = image[0, -1]  # top-right pixel lies outside every island: it takes a covered neighbour's value
    assert np.any(np.all(np.isclose(image[covered], far), axis=1))


def test_uv_face_image_and_refusals():
    mesh, _ = plate()
    faces = uv_face_image(mesh, (64, 64))
    top = np.flatnonzero(np.isclose(mesh.face_normals[:, 2], 1.0))
    assert set(np.unique(faces[20:44, 20:44])) <= set(top.tolist())
    with pytest.raises(ValueError, match="texture coordinates"):
        uv_face_image(trimesh.creation.box(), (8, 8))
    with pytest.raises(ValueError, match="values: expected shape"):
        bake_texels(mesh, np.zeros((5, 3)), np.zeros((4, 3)), size=(8, 8))
