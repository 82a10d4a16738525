"""Mesh → voxel object (geometry/voxelize.py) against analytic shapes, and into the general-scene tracer."""
import math

import numpy as np
import pytest
import torch
import trimesh

import torch_appearance as ta
from torch_appearance.geometry import VoxelObject, voxelize
from torch_appearance.render import Scene, SDFBoundary, SurfaceTexels


def corner_points(obj):
    d, h, w = obj.grid_shape
    o, s = np.array(obj.origin), obj.voxel_size
    k, j, i = np.meshgrid(np.arange(d + 1), np.arange(h + 1), np.arange(w + 1), indexing="ij")
    return o + s * np.stack([i, j, k], axis=-1)


def box_distance(p, half):
    q = np.abs(p) - half
    return np.linalg.norm(np.maximum(q, 0), axis=-1) + np.minimum(q.max(-1), 0)


@pytest.mark.parametrize("pitch", [0.1, 0.07, 0.05])
def test_box_counts_sdf_and_slab_texels(pitch):
    """A slab-shaped box (faces on voxel planes): exactly the voxels inside, exactly its faces as texels, and the
    SDF equal to the analytic box distance in the band."""
    n = (40, 30, 8)  # voxels along x, y, z
    extents = tuple(m * pitch for m in n)
    obj = voxelize(trimesh.creation.box(extents), pitch)
    assert int(obj.occupancy.sum()) == n[0] * n[1] * n[2]
    inner = max(0, n[0] - 2) * max(0, n[1] - 2) * max(0, n[2] - 2)
    assert len(obj.texel_voxels) == n[0] * n[1] * n[2] - inner
    # the top layer of voxels is exactly the top face's texels (one per voxel column), normals +z away from edges
    d = obj.grid_shape[0]
    k_top = int(obj.texel_voxels[:, 0].max())
    top = obj.texel_voxels[:, 0] == k_top
    assert int(top.sum()) == n[0] * n[1] and k_top == d - 2  # one padding layer above
    interior = top & (obj.texel_points[:, 0].abs() < extents[0] / 2 - pitch) & \
        (obj.texel_points[:, 1].abs() < extents[1] / 2 - pitch)
    assert torch.allclose(obj.texel_normals[interior], torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64), atol=1e-9)
    assert torch.allclose(obj.texel_points[interior, 2], torch.tensor(extents[2] / 2, dtype=torch.float64))
    p = corner_points(obj)
    exact = box_distance(p, np.array(extents) / 2)
    band = np.abs(exact) < obj.band_mm - 1e-9
    assert np.abs(obj.sdf.numpy()[band] - exact[band]).max() < 1e-3  # the accuracy target (measured: 1.5e-4)
    assert (np.sign(obj.sdf.numpy()[~band]) == np.sign(exact[~band])).all()


def test_sphere_volume_normals_and_sdf():
    """Sphere (icosphere of 5 subdivisions, R = 2 mm) at 40+ voxels across: volume within 1 % of 4/3πR³, texel
    normals within 2° of the radial direction, SDF in the band within the mesh's own deviation from the sphere plus
    1e-3 mm, texel count consistent with the surface area: a 6-separating boundary layer holds max_a |n_a| voxels
    per h² of surface with normal n, so N·h² ≈ ∫ max_a |n_a| dA = 4πR²·E[max_a |n_a|] over uniform directions."""
    R, h = 2.0, 0.09
    mesh = trimesh.creation.icosphere(subdivisions=5, radius=R)
    obj = voxelize(mesh, h)
    volume = float(obj.occupancy.sum()) * h ** 3
    assert abs(volume / (4 / 3 * math.pi * R ** 3) - 1) < 0.01
    radial = obj.texel_points / obj.texel_points.norm(dim=1, keepdim=True)
    angle = torch.rad2deg(torch.acos((radial * obj.texel_normals).sum(1).clamp(-1, 1)))
    assert float(angle.max()) < 2.0
    p = corner_points(obj)
    exact = np.linalg.norm(p, axis=-1) - R
    band = np.abs(exact) < obj.band_mm - 2 * h
    sag = R * (1 - math.cos(math.radians(1.3)))  # icosphere(5): edge angle ≈ 1.2°, chord sag below this
    assert np.abs(obj.sdf.numpy()[band] - exact[band]).max() < sag + 1e-3
    dirs = np.random.default_rng(0).normal(size=(400000, 3))
    e_max = float((np.abs(dirs).max(1) / np.linalg.norm(dirs, axis=1)).mean())
    expected = 4 * math.pi * R ** 2 * e_max / h ** 2
    assert abs(len(obj.texel_voxels) / expected - 1) < 0.03, (len(obj.texel_voxels), expected)


def test_torus_volume():
    R, r, h = 2.0, 0.7, 0.06
    obj = voxelize(trimesh.creation.torus(major_radius=R, minor_radius=r, major_sections=256, minor_sections=128), h)
    volume = float(obj.occupancy.sum()) * h ** 3
    assert abs(volume / (2 * math.pi ** 2 * R * r * r) - 1) < 0.01


def test_shell_depth_and_texels_to_grid():
    obj = voxelize(trimesh.creation.box((2.0, 2.0, 2.0)), 0.1, shell_mm=0.3)
    # depth of a voxel centre = distance to the nearest face; the shell is the voxels within 0.3 mm
    k, j, i = 5, 11, 11  # one padding layer: centre z = -1.1 + 5.5·0.1 = -0.55, depth 0.45
    assert float(obj.depth[k, j, i]) == pytest.approx(0.45, abs=1e-5)
    assert int(obj.shell.sum()) == 20 ** 3 - 14 ** 3
    grid = obj.texels_to_grid(torch.ones(len(obj.texel_voxels), 2))
    assert grid.shape == (2, 22, 22, 22) and int(grid[0].sum()) == len(obj.texel_voxels)
    with pytest.raises(ValueError, match="values: expected a tensor of shape"):
        obj.texels_to_grid(torch.ones(3, 2))


def test_save_load_round_trip_and_refusals(tmp_path):
    obj = voxelize(trimesh.creation.box((1.0, 1.0, 0.5)), 0.1, shell_mm=0.2)
    path = str(tmp_path / "obj.npz")
    obj.save(path)
    back = VoxelObject.load(path)
    assert back.origin == obj.origin and back.voxel_size == obj.voxel_size
    for name in ("occupancy", "sdf", "texel_voxels", "texel_points", "texel_normals", "depth", "shell"):
        assert torch.equal(getattr(back, name), getattr(obj, name)), name
    data = open(path, "rb").read()
    (tmp_path / "cut.npz").write_bytes(data[: len(data) // 2])
    with pytest.raises(ValueError, match="not a readable voxel-object"):
        VoxelObject.load(str(tmp_path / "cut.npz"))
    np.savez(str(tmp_path / "other.npz"), a=np.zeros(3))
    with pytest.raises(ValueError, match="not a voxel object"):
        VoxelObject.load(str(tmp_path / "other.npz"))


def test_bad_input():
    box = trimesh.creation.box((1.0, 1.0, 1.0))
    with pytest.raises(TypeError, match="mesh: expected a trimesh.Trimesh"):
        voxelize("box.obj", 0.1)
    with pytest.raises(ValueError, match="mesh: expected triangles"):
        voxelize(trimesh.Trimesh(), 0.1)
    with pytest.raises(ValueError, match="voxel_size: expected"):
        voxelize(box, 0.0)
    with pytest.raises(ValueError, match=r"voxel_size: 1e-05 mm gives a .* grid that needs about .* GiB"):
        voxelize(box, 1e-5)
    with pytest.raises(ValueError, match="shell_mm: expected"):
        voxelize(box, 0.1, shell_mm=-1)


def test_vertex_colours_and_white_furnace_render():
    """Vertex colours become linear texel colours; the voxel object renders through the SDF boundary with its own
    texels as the sensor (white furnace: exactly 1)."""
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=0.5)
    mesh.visual.vertex_colors = np.tile(np.array([[188, 188, 188, 255]], dtype=np.uint8), (len(mesh.vertices), 1))
    obj = voxelize(mesh, 0.1)
    expected = ((188 / 255 + 0.055) / 1.055) ** 2.4
    assert torch.allclose(obj.texel_colors, torch.full_like(obj.texel_colors, expected), atol=1e-5)
    d, h, w = obj.grid_shape
    scene = Scene(voxel_size=obj.voxel_size, origin=obj.origin, boundary=SDFBoundary(obj.sdf, ior=1.5),
                  sensor=SurfaceTexels(obj.texel_points, obj.texel_normals, footprint_mm=obj.voxel_size / 2))
    image = ta.render_scene(scene, torch.full((3, d, h, w), 10.0), torch.ones(3, d, h, w), spp=8)
    assert image.shape == (len(obj.texel_voxels), 3)
    assert float((image - 1).abs().max()) < 1e-5


DATA = __import__("os").path.join(__import__("os").path.dirname(__file__), "data", "meshes")


def test_load_mesh_glb_texture_and_lookup():
    """BoxTextured.glb: scaled to 10 mm, texture kept; texel colours equal an independent lookup (trimesh's
    barycentric coordinates and its bilinear uv_to_interpolated_color) at the closest points."""
    from trimesh.triangles import points_to_barycentric
    from trimesh.visual.color import uv_to_interpolated_color
    from torch_appearance.geometry import load_mesh

    mesh, report = load_mesh(__import__("os").path.join(DATA, "BoxTextured.glb"), height_mm=10.0)
    assert report["colour"] == "texture" and report["texture_size"] == (256, 256) and report["watertight"]
    assert np.allclose(mesh.extents, 10.0)
    obj = voxelize(mesh, 0.5)
    pts = obj.texel_points.numpy()
    import igl  # the face of the closest point (the lookup below is what is checked independently)
    _, fid, _ = igl.point_mesh_squared_distance(pts, np.asarray(mesh.vertices, dtype=np.float64),
                                                np.asarray(mesh.faces, dtype=np.int64))
    bary = points_to_barycentric(mesh.triangles[fid], pts)
    uv = (mesh.visual.uv[mesh.faces[fid]] * bary[:, :, None]).sum(1)
    # where the closest point is unique (away from the cube's edges) the face and the uv must agree
    inner = (np.abs(pts).max(1) - np.sort(np.abs(pts), 1)[:, 1]) > 0.3
    assert inner.sum() > 500
    assert np.allclose(obj.texel_uv.numpy()[inner], uv[inner], atol=1e-5)
    # independent bilinear lookup (scipy, texel centres at (i + ½)/w, glTF's default REPEAT wrap, v up)
    from scipy.ndimage import map_coordinates
    tex = np.asarray(mesh.visual.material.baseColorTexture.convert("RGB"), dtype=np.float64) / 255.0
    tex = np.where(tex <= 0.04045, tex / 12.92, ((tex + 0.055) / 1.055) ** 2.4)
    h, w = tex.shape[:2]
    rows = (1 - uv[inner, 1] % 1.0) * h - 0.5
    cols = (uv[inner, 0] % 1.0) * w - 0.5
    linear = np.stack([map_coordinates(tex[..., c], [rows, cols], order=1, mode="grid-wrap") for c in range(3)], 1)
    assert float(np.ptp(linear)) > 0.3  # the sampled texels see the logo, not only the flat background
    assert np.abs(obj.texel_colors.numpy()[inner] - linear).max() < 1e-5


def test_load_mesh_bad_input(tmp_path):
    from torch_appearance.geometry import load_mesh
    with pytest.raises(ValueError, match="path: no such file"):
        load_mesh(str(tmp_path / "nothing.obj"))
    bad = tmp_path / "bad.ply"
    bad.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 99\n")
    with pytest.raises(ValueError, match="path: could not read|holds no triangles"):
        load_mesh(str(bad))
    obj = tmp_path / "m.obj"
    obj.write_text("mtllib m.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 0 1\nf 1/1 2/2 3/3\n")
    (tmp_path / "m.mtl").write_text("newmtl a\nmap_Kd missing texture.png\n")
    with pytest.raises(ValueError, match="missing"):
        load_mesh(str(obj))
    (tmp_path / "m.mtl").write_text("newmtl a\n")
    with pytest.raises(ValueError, match="height_mm: expected"):
        load_mesh(str(obj), height_mm=0.0)
    with pytest.raises(ValueError, match="at most one"):
        load_mesh(str(obj), height_mm=1.0, scale=2.0)
    mesh, report = load_mesh(str(obj), scale=1000.0)
    assert report["units_guess"] == "m" and np.allclose(mesh.extents[:2], 1000.0) and not report["watertight"]


def test_voxelize_cli(tmp_path):
    """ta-voxelize on an STL box: npz, summary and previews written; bad input → exit code 2."""
    import json
    from torch_appearance.cli import voxelize as cli
    stl = tmp_path / "box.stl"
    trimesh.creation.box((2.0, 3.0, 1.0)).export(str(stl))
    out = tmp_path / "out"
    assert cli.main([str(stl), "--height-mm", "1.0", "--dpi", "127", "--shell-mm", "0.4", "--out", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["inside_voxels"] == 10 * 15 * 5 and summary["watertight"]
    assert summary["max_texel_centre_to_surface_mm"] == pytest.approx(0.1, abs=1e-9)
    assert VoxelObject.load(str(out / "object.npz")).grid_shape == (7, 17, 12)  # one padding voxel per side
    for name in ("texels_normal.png", "sdf_slice.png"):
        assert (out / name).stat().st_size > 1000
    assert cli.main([str(tmp_path / "missing.obj"), "--out", str(out)]) == 2


@pytest.mark.parametrize("rays", ["embree", "none"])
def test_signs_match_brute_force_winding_number(rays, monkeypatch):
    """The fast paths (coarse pruning, pseudonormal signs in the band, ray parity beyond it, centre signs from
    decisive corners) agree with the winding number asked at every voxel centre and every corner, with embree rays
    and without embreex (far regions then signed by one winding-number query each)."""
    import sys

    import igl

    if rays == "none":
        monkeypatch.setitem(sys.modules, "trimesh.ray.ray_pyembree", None)  # the import fails
    mesh = trimesh.creation.torus(major_radius=2.0, minor_radius=0.7, major_sections=48, minor_sections=24)
    mesh.apply_transform(trimesh.transformations.random_rotation_matrix(np.random.default_rng(3).random(3)))
    obj = voxelize(mesh, 0.13)
    assert obj.info["closed"] and obj.info["ray_parity"] == (rays == "embree")
    assert obj.info["parity_fallback_columns"] == 0
    V, F = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    d, h, w = obj.grid_shape
    o, s = np.array(obj.origin), obj.voxel_size
    k, j, i = np.meshgrid(np.arange(d), np.arange(h), np.arange(w), indexing="ij")
    centres = o + s * (np.stack([i, j, k], axis=-1).reshape(-1, 3) + 0.5)
    truth = igl.fast_winding_number(V, F, centres) > 0.5
    assert np.array_equal(obj.occupancy.numpy().ravel(), truth)
    corners = corner_points(obj).reshape(-1, 3)
    wn = igl.fast_winding_number(V, F, corners)
    clear = np.abs(wn - 0.5) > 0.1  # corners on the surface itself have no sign to compare
    assert np.array_equal((obj.sdf.numpy().ravel() < 0)[clear], (wn > 0.5)[clear])
    # the band: every corner nearer than band_mm has its exact distance, every other one ±band_mm
    dist = np.sqrt(igl.point_mesh_squared_distance(corners, V, F)[0])
    sdf = np.abs(obj.sdf.numpy().ravel().astype(np.float64))
    inner = dist < obj.band_mm
    assert np.abs(sdf[inner] - dist[inner]).max() < 1e-5
    assert np.all(sdf[~inner] == np.float32(obj.band_mm))
