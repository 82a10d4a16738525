"""The 2.5D remapped baseline (pipelines/print/remap25d.py, pipelines/print/loop.py remap_baseline): a slab optimised in UV space wrapped around an object."""
import os

import numpy as np
import pytest
import torch
import trimesh

from torch_appearance.fabrication import InkSet
from torch_appearance.geometry import load_mesh, voxelize
from torch_appearance.pipelines import PrintConfig
from torch_appearance.pipelines.print import ObjectTarget, remap_baseline
from torch_appearance.pipelines.print.remap25d import _slab_fixed, slab_size, uv_target_image, wrap_slab_weights

QUIET = dict(log=lambda *_: None)
GLB = os.path.join(os.path.dirname(__file__), "data", "meshes", "BoxTextured.glb")


def box_with_top_uv(extent):
    """A box whose top face (+z) maps (x, y) linearly onto (u, v) ∈ [0, 1]²; every other face sits in the
    corner (0.02, 0.02) of UV space."""
    mesh = trimesh.creation.box(extent)
    mesh.unmerge_vertices()
    v = np.asarray(mesh.vertices)
    uv = np.full((len(v), 2), 0.02)
    top = np.unique(np.asarray(mesh.faces)[np.isclose(mesh.face_normals[:, 2], 1.0)])
    lo, hi = v.min(0), v.max(0)
    uv[top] = (v[top, :2] - lo[:2]) / (hi[:2] - lo[:2])
    mesh.visual = trimesh.visual.TextureVisuals(uv=uv)
    return mesh


def object_target(mesh, h, shell_mm):
    obj = voxelize(mesh, h, shell_mm=shell_mm)
    obj.texel_colors = torch.rand(len(obj.texel_voxels), 3)
    target = ObjectTarget(obj)
    target.mesh = mesh
    return target


def test_slab_columns_map_onto_a_flat_face_identically():
    """Under the top face, away from the sides, voxel (k, j, i) holds slab[:, layer, row, col] with col = i − i0,
    row = H_s − 1 − (j − j0) (v up: image row 0 is v = 1) and layer = D_s − 1 − (layers below the top face);
    every voxel outside the shell holds the core ink."""
    h, shell_mm = 0.2, 0.6                       # 3 slab layers; box faces on voxel boundaries
    nx, ny, nz = 12, 10, 10
    target = object_target(box_with_top_uv((nx * h, ny * h, nz * h)), h, shell_mm)
    inks = InkSet.from_names()
    cfg = PrintConfig(shell_mm=shell_mm, dpi=25.4 / h)
    ds = 3                                       # round(shell_mm / h) layers: depths 0.1, 0.3, 0.5 mm
    rng = np.random.default_rng(1)
    slab = rng.random((len(inks), ds, ny, nx)).astype(np.float32)
    slab /= slab.sum(0, keepdims=True)
    weights, info = wrap_slab_weights(target, slab, inks, cfg.core_ink, **QUIET)
    d, hh, w = target.shape
    assert weights.shape == (len(inks), d, hh, w) and weights.dtype == torch.float32
    assert info["slab_hw"] == [ny, nx] and info["slab_depth"] == ds
    i0, j0, k_top = 1, 1, d - 2                  # one voxel of padding around the box
    assert bool(target.obj.occupancy[k_top, j0, i0]) and not bool(target.obj.occupancy[k_top + 1, j0, i0])
    margin = int(np.ceil(shell_mm / h))          # columns more than the shell depth away from the sides
    checked = 0
    for m in range(ds):
        for j in range(j0 + margin, j0 + ny - margin):
            for i in range(i0 + margin, i0 + nx - margin):
                assert bool(target.support[k_top - m, j, i])
                expected = slab[:, ds - 1 - m, ny - 1 - (j - j0), i - i0]
                assert np.array_equal(weights[:, k_top - m, j, i].numpy(), expected), (m, j, i)
                checked += 1
    assert checked == ds * (ny - 2 * margin) * (nx - 2 * margin)
    core = np.zeros(len(inks), np.float32)
    core[inks.index("white")] = 1
    outside = ~target.support
    assert bool((weights[:, outside] == torch.from_numpy(core)[:, None]).all())
    assert torch.allclose(weights.sum(0), torch.ones(d, hh, w))


def test_slab_size_follows_the_uv_stretch_and_is_capped():
    """A 3 × 2 mm plate mapped onto u ∈ [0, 0.5], v ∈ [0, 1]: 6 mm per u, 2 mm per v → 60 × 20 texels at 0.1 mm;
    a cap of 300 texels coarsens both sides by the same factor."""
    mesh = trimesh.Trimesh(vertices=[[0, 0, 0], [3, 0, 0], [3, 2, 0], [0, 2, 0]], faces=[[0, 1, 2], [0, 2, 3]],
                           process=False)
    mesh.visual = trimesh.visual.TextureVisuals(uv=np.array([[0, 0], [0.5, 0], [0.5, 1], [0, 1]], float))
    (hs, ws), info = slab_size(mesh, 0.1)
    assert (hs, ws) == (20, 60)
    assert info["mm_per_u"] == pytest.approx(6.0) and info["mm_per_v"] == pytest.approx(2.0)
    assert info["surface_area_mm2"] == pytest.approx(6.0) and info["uv_area"] == pytest.approx(0.5)
    (hs, ws), info = slab_size(mesh, 0.1, max_texels=300)
    assert (hs, ws) == (10, 30) and info["scale"] == pytest.approx(0.5)


def test_vertex_coloured_mesh_without_uvs_is_refused(tmp_path):
    mesh = trimesh.creation.box((2.0, 2.0, 2.0))
    mesh.visual.vertex_colors = np.tile([200, 40, 40, 255], (len(mesh.vertices), 1)).astype(np.uint8)
    target = object_target(mesh, 0.25, 0.5)
    inks = InkSet.from_names()
    with pytest.raises(ValueError, match="vertex colours but no UV layout"):
        remap_baseline(target, inks, PrintConfig(shell_mm=0.5, dpi=25.4 / 0.25), work_dir=tmp_path, **QUIET)
    with pytest.raises(ValueError, match="no UV layout"):  # even with a slab given: there is nothing to look up
        wrap_slab_weights(target, np.full((len(inks), 2, 4, 4), 0.2, np.float32), inks, "white", **QUIET)
    assert not any(tmp_path.iterdir())


def test_end_to_end_on_a_textured_box(tmp_path):
    """BoxTextured.glb (every face maps the whole texture, u tiled over [0, 6]) at 2 mm: a short slab run in UV
    space (8 × 8 texels: one per voxel of a face; the run's fixed fraction in the top 0.2 mm carried over), then
    the remap; weights are mixtures on the object's grid and the slab's columns appear on the surface."""
    mesh, _ = load_mesh(GLB, height_mm=2.0)
    cfg = PrintConfig(mesh=GLB, height_mm=2.0, dpi=100.0, shell_mm=0.5, spp=2, eval_spp=4, eval_every=2,
                      iterations=2, table_steps=2, printer_dpi=(300.0, 300.0, 300.0), out=str(tmp_path / "run"),
                      fixed=("white=0.5:depth:0-0.2",))
    target = object_target(mesh, cfg.voxel_size, cfg.shell_mm)
    inks = InkSet.from_names()
    weights, info = remap_baseline(target, inks, cfg, work_dir=tmp_path / "remap", **QUIET)
    assert info["slab_hw"] == [8, 8] and info["slab_depth"] == round(cfg.shell_mm / cfg.voxel_size) == 2
    assert info["uv_area"] == pytest.approx(6.0) and info["covered_fraction"] == 1.0
    assert (tmp_path / "remap" / "uv_target.exr").exists()
    assert np.isfinite(info["slab_final_dE00_mean"])
    slab = np.load(tmp_path / "remap" / "slab" / "mixture.npz")["weights"]
    assert slab.shape == (len(inks), 2, 8, 8)
    white = inks.index("white")                                     # the fixed fraction reached the slab run
    assert np.allclose(slab[white, 1], 0.5) and not np.allclose(slab[white, 0], 0.5)
    assert weights.shape == (len(inks), *target.shape) and weights.dtype == torch.float32
    assert torch.allclose(weights.sum(0), torch.ones(target.shape), atol=1e-5)
    assert bool((weights >= 0).all())
    # every shell voxel holds one of the slab's (layer, row, col) mixtures; the top layer's columns are used
    shell_w = weights[:, target.support].numpy().T                  # (M, N)
    table = slab.transpose(1, 2, 3, 0).reshape(-1, len(inks))
    dist = np.abs(shell_w[:, None, :] - table[None]).max(2).min(1)
    assert dist.max() == 0.0
    texel_w = weights[:, target.obj.texel_voxels[:, 0], target.obj.texel_voxels[:, 1],
                      target.obj.texel_voxels[:, 2]].numpy().T
    top = slab[:, -1].reshape(len(inks), -1).T
    assert (np.abs(texel_w[:, None, :] - top[None]).max(2).min(1) == 0).mean() > 0.9


def test_fixed_fractions_carry_over_to_the_slab(tmp_path):
    """Depth masks stay; a texture-space PNG mask is resampled (nearest) to the slab's texels."""
    import cv2

    mask = np.zeros((64, 32), np.uint8)
    mask[:32] = 255                                             # the upper half of UV space (v > 0.5)
    path = str(tmp_path / "mask.png")
    cv2.imwrite(path, mask)
    specs = _slab_fixed(["transparent=0.8:depth:0-0.4", f"black=0.1:{path}&depth:0.2-1"], (10, 6), str(tmp_path))
    assert specs[0] == "transparent=0.8:depth:0-0.4"
    ink, rest = specs[1].split(":", 1)
    png, depth = rest.split("&")
    assert ink == "black=0.1" and depth == "depth:0.2-1" and os.path.dirname(png) == str(tmp_path)
    slab_mask = cv2.imread(png, cv2.IMREAD_GRAYSCALE)
    assert slab_mask.shape == (10, 6)
    assert (slab_mask[:5] == 255).all() and (slab_mask[5:] == 0).all()


@pytest.mark.parametrize("shift", [0.0, 2.0])
def test_uv_target_fills_the_background_from_the_islands(shift):
    """A 4 mm plate whose top face maps onto u, v ∈ [0.1, 0.9] (shifted by whole units: tiled UVs land on the same
    pixels); the texture is red on the island and black around it. At 0.1 mm the island spans 4 mm per 0.8 UV →
    50 × 50 texels, 64 % covered; the black background takes the island's red."""
    from PIL import Image

    mesh = trimesh.creation.box((4.0, 4.0, 1.0))
    mesh.unmerge_vertices()
    v = np.asarray(mesh.vertices)
    uv = np.full((len(v), 2), 0.02)
    top = np.unique(np.asarray(mesh.faces)[np.isclose(mesh.face_normals[:, 2], 1.0)])
    uv[top] = 0.1 + 0.8 * (v[top, :2] + 2.0) / 4.0
    uv[top, 0] += shift
    texture = np.zeros((100, 100, 3), np.uint8)
    texture[10:90, 10:90] = (255, 0, 0)
    mesh.visual = trimesh.visual.TextureVisuals(uv=uv, image=Image.fromarray(texture))
    image, info = uv_target_image(mesh, 0.1)
    assert image.shape == (50, 50, 3)            # the sides and bottom collapse to a point of UV space: no area
    assert info["degenerate_area_fraction"] == pytest.approx(32.0 / 48.0)
    assert info["covered_fraction"] == pytest.approx(0.64, abs=0.005)  # 40 × 40 texel centres
    assert image[..., 0].min() > 0.9 and image[..., 1:].max() < 0.05


def test_cropped_slab_remaps_like_the_full_slab():
    """uv_target_image(crop=True) keeps the islands' bounding box only (a plate whose top face uses
    u, v ∈ [0.1, 0.9]: 40 × 40 of 50 × 50 texels), its pixels equal the full image's there, and remap_slab of the
    crop with its window gives the object exactly the weights that the full slab gives (full slab random outside
    the crop: unused); a window that does not fit is refused."""
    from torch_appearance.pipelines.print.remap25d import remap_slab

    h = 0.1
    mesh = trimesh.creation.box((4.0, 4.0, 1.0))
    mesh.unmerge_vertices()
    v = np.asarray(mesh.vertices)
    uv = np.full((len(v), 2), 0.5)
    top = np.unique(np.asarray(mesh.faces)[np.isclose(mesh.face_normals[:, 2], 1.0)])
    uv[top] = 0.1 + 0.8 * (v[top, :2] + 2.0) / 4.0
    from PIL import Image
    texture = (np.random.default_rng(0).random((100, 100, 3)) * 255).astype(np.uint8)
    mesh.visual = trimesh.visual.TextureVisuals(uv=uv, image=Image.fromarray(texture))
    full, info_full = uv_target_image(mesh, h)
    crop, info = uv_target_image(mesh, h, crop=True)
    r0, c0, hs, ws = info["window"]
    assert full.shape == (50, 50, 3) and (hs, ws) == (50, 50) and info_full["window"] == [0, 0, 50, 50]
    assert crop.shape == (40, 40, 3) and (r0, c0) == (5, 5) and info["covered_fraction"] == 1.0
    assert np.array_equal(crop, full[r0:r0 + 40, c0:c0 + 40])
    target = object_target(mesh, h, 0.3)
    inks = InkSet.from_names()
    core = np.zeros(len(inks), np.float32)
    core[inks.index("white")] = 1
    slab = np.random.default_rng(2).random((len(inks), 3, 50, 50)).astype(np.float32)
    expected, _ = remap_slab(target, slab, core)
    got, _ = remap_slab(target, np.ascontiguousarray(slab[:, :, r0:r0 + 40, c0:c0 + 40]), core, window=info["window"])
    assert torch.equal(got, expected)
    with pytest.raises(ValueError, match="window: a 40×40 slab at row 20"):
        remap_slab(target, slab[:, :, :40, :40], core, window=(20, 0, 50, 50))


def test_material_mask_becomes_a_slab_mask(tmp_path):
    """``material:NAME`` in the slab run: the slab texels inside the UV triangles of that material's faces."""
    import cv2

    mesh = box_with_top_uv((2.0, 2.0, 1.0))
    is_top = np.isclose(mesh.face_normals[:, 2], 1.0)
    mesh.metadata["material_names"] = ["sides", "top"]
    mesh.metadata["face_materials"] = is_top.astype(np.int32)
    (spec,) = _slab_fixed(["transparent=0.5:material:top&depth:0-0.2"], (10, 10), str(tmp_path), mesh=mesh)
    png, depth = spec.split(":", 1)[1].split("&")
    assert depth == "depth:0-0.2"
    assert (cv2.imread(png, cv2.IMREAD_GRAYSCALE) == 255).all()  # the top face spans the whole UV square
    mesh.metadata["face_materials"] = (~is_top).astype(np.int32)
    (spec,) = _slab_fixed(["transparent=0.5:material:top"], (10, 10), str(tmp_path), mesh=mesh)
    assert (cv2.imread(spec.split(":", 1)[1], cv2.IMREAD_GRAYSCALE) == 0).all()
    with pytest.raises(ValueError, match="no material 'lid'"):
        _slab_fixed(["transparent=0.5:material:lid"], (10, 10), str(tmp_path), mesh=mesh)
