"""Meshes as they arrive (geometry/mesh.py, geometry/surface.py, geometry/voxelize.py): texture atlases without seam
bleeding, glTF base-colour factors, open, duplicated, flipped, non-manifold and multi-shell meshes, units, a texture
attached to an OBJ without material, and bad input. Every expected value is computed independently of the code under
test (analytic shapes, brute-force closest points from trimesh.triangles, trimesh's barycentrics, a float64 bilinear
lookup and sRGB decoding written here)."""
import math
import os

import numpy as np
import pytest
import torch
import trimesh
from PIL import Image

from torch_appearance.geometry import load_mesh, voxelize

DATA = os.path.join(os.path.dirname(__file__), "data", "meshes")
SPOT = os.path.join(DATA, "spot")

# one sRGB colour per box side, side = 2·axis + (normal > 0): −x, +x, −y, +y, −z, +z
SIDE_SRGB = np.array([[200, 40, 40], [40, 180, 60], [50, 70, 220], [230, 210, 40], [40, 200, 210], [190, 60, 200]],
                     dtype=np.uint8)


def srgb_decode(x):
    """sRGB-encoded values in [0, 1] → linear (IEC 61966-2-1), float64."""
    x = np.asarray(x, dtype=np.float64)
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)


SIDE_LIN = srgb_decode(SIDE_SRGB / 255.0)


def bilinear(image, uv):
    """Bilinear lookup in an (h, w, 3) float64 image at uv (N, 2): v up, texel centres at ((i + ½)/w,
    1 − (j + ½)/h), repeat wrap — an independent float64 implementation for the checks."""
    h, w = image.shape[:2]
    x = np.mod(uv[:, 0], 1.0) * w - 0.5
    y = (1.0 - np.mod(uv[:, 1], 1.0)) * h - 0.5
    xf, yf = np.floor(x), np.floor(y)
    ax, ay = (x - xf)[:, None], (y - yf)[:, None]
    i0, j0 = xf.astype(int) % w, yf.astype(int) % h
    i1, j1 = (i0 + 1) % w, (j0 + 1) % h
    top = image[j0, i0] * (1 - ax) + image[j0, i1] * ax
    bottom = image[j1, i0] * (1 - ax) + image[j1, i1] * ax
    return top * (1 - ay) + bottom * ay


def atlas_cube(size=4.0, px=16, inset_px=0.5):
    """A box with one UV island per side in a 3×2 atlas of px×px squares, each square one colour (SIDE_SRGB), each
    island inset by ``inset_px`` pixels in its square. With half a pixel, a bilinear lookup with texel centres at
    (i + ½)/w reads only its own square's pixels anywhere on the island (at the island's border the neighbour's
    weight is exactly 0), so every surface point has exactly its side's colour; a lookup off by half a texel, or
    with v not flipped, or sampling across the seam, mixes in a neighbour's colour.
    Returns (mesh with unmerged vertices and TextureVisuals, PIL image, side of each face (F,))."""
    mesh = trimesh.creation.box((size, size, size))
    mesh.unmerge_vertices()
    fn = mesh.face_normals
    axis = np.abs(fn).argmax(1)
    side = 2 * axis + (fn[np.arange(len(fn)), axis] > 0)
    image = np.zeros((2 * px, 3 * px, 3), dtype=np.uint8)
    for s in range(6):
        row, col = divmod(s, 3)
        image[row * px:(row + 1) * px, col * px:(col + 1) * px] = SIDE_SRGB[s]
    uv = np.zeros((len(mesh.vertices), 2))
    for f in range(len(mesh.faces)):
        row, col = divmod(int(side[f]), 3)
        b, c = [a for a in range(3) if a != axis[f]]
        for v in mesh.faces[f]:
            t = (mesh.vertices[v] + size / 2) / size  # 0..1 across the side
            x = col * px + inset_px + t[b] * (px - 2 * inset_px)  # pixels from the left
            y = row * px + inset_px + (1 - t[c]) * (px - 2 * inset_px)  # pixels from the top
            uv[v] = (x / (3 * px), 1 - y / (2 * px))
    pil = Image.fromarray(image)
    mesh.visual = trimesh.visual.TextureVisuals(uv=uv, image=pil)
    return mesh, pil, side


def closest_on_mesh(mesh, points, chunk=128):
    """Brute force (trimesh.triangles.closest_point on every triangle whose bounding box is no farther than the
    nearest vertex; no spatial index): (closest points (N, 3), triangle ids (N,)), the lowest id among equally near
    triangles."""
    from trimesh.triangles import closest_point

    tris = np.asarray(mesh.triangles, dtype=np.float64)
    lo, hi = tris.min(1), tris.max(1)
    V = np.asarray(mesh.vertices, dtype=np.float64)
    out, ids = np.empty((len(points), 3)), np.empty(len(points), dtype=np.int64)
    for start in range(0, len(points), chunk):
        p = points[start:start + chunk]
        upper = np.sqrt(((p[:, None, :] - V[None]) ** 2).sum(2).min(1))  # a vertex is this near
        box = np.linalg.norm(np.maximum(np.maximum(lo[None] - p[:, None], p[:, None] - hi[None]), 0), axis=2)
        n, t = np.nonzero(box <= upper[:, None] * (1 + 1e-12) + 1e-12)
        q = closest_point(tris[t], p[n])
        d = ((q - p[n]) ** 2).sum(1)
        order = np.lexsort((t, d, n))  # per point: nearest first, then the lowest triangle id
        first = order[np.r_[True, n[order][1:] != n[order][:-1]]]
        out[start + n[first]] = q[first]
        ids[start + n[first]] = t[first]
    return out, ids


def texel_centres(obj):
    return np.asarray(obj.origin) + (obj.texel_voxels.numpy()[:, ::-1] + 0.5) * obj.voxel_size


def voxel_centres(obj):
    d, h, w = obj.grid_shape
    k, j, i = np.meshgrid(np.arange(d), np.arange(h), np.arange(w), indexing="ij")
    return np.asarray(obj.origin) + (np.stack([i, j, k], axis=-1) + 0.5) * obj.voxel_size


def sides_of_points(points, half):
    """(N, 6) bool: the box sides (−x, +x, −y, +y, −z, +z) each point lies on (several on edges and corners)."""
    on = np.zeros((len(points), 6), dtype=bool)
    for a in range(3):
        on[:, 2 * a] = np.abs(points[:, a] + half) < 1e-9
        on[:, 2 * a + 1] = np.abs(points[:, a] - half) < 1e-9
    return on


def nearest_sides(points, half):
    """(N, 6) bool: the box sides nearest to points inside the box (several where distances tie: texel centres
    next to an edge or a corner are equally near two or three sides, so their closest point is not unique)."""
    dist = np.concatenate([points + half, half - points], axis=1)[:, [0, 3, 1, 4, 2, 5]]
    return dist <= dist.min(1, keepdims=True) + 1e-9


def check_box_colours(obj, mesh, side, expected_lin, half):
    """Every texel's closest point is a closest point (brute force over all triangles), lies on one of the sides
    nearest to the texel centre, and the texel has exactly that side's colour: where one side is nearest, the side
    of the brute-force closest triangle; on edges and corners, the side its own closest point lies on (any blend
    of two sides' colours fails). Returns the mask of texels with a single nearest side."""
    centres = texel_centres(obj)
    closest, tri = closest_on_mesh(mesh, centres)
    points = obj.texel_points.numpy()
    assert np.abs(np.linalg.norm(points - centres, axis=1) - np.linalg.norm(closest - centres, axis=1)).max() < 1e-9
    near = nearest_sides(centres, half)
    on = sides_of_points(points, half) & near
    assert on.any(1).all()
    colours = obj.texel_colors.numpy().astype(np.float64)
    single = near.sum(1) == 1
    assert single.sum() > 0.5 * len(colours) and (near.sum(1) > 1).sum() > 0
    assert np.array_equal(side[tri[single]], near[single].argmax(1))
    assert np.abs(colours[single] - expected_lin[side[tri[single]]]).max() < 1e-6
    err = np.abs(colours[:, None, :] - expected_lin[None, :, :]).max(2)  # (N, 6)
    err = np.where(on, err, np.inf).min(1)
    assert err.max() < 1e-6, f"{int((err >= 1e-6).sum())} texels with a colour not of their side, worst {err.max():.3g}"
    return single


def test_checker_atlas_cube_has_no_seam_bleeding():
    """4 mm cube, 3×2 atlas of one colour per side (islands inset by half a pixel), 0.25 mm voxels (faces on voxel
    planes): 16³ − 14³ texels, each coloured exactly like the side of its closest point, including the texels on
    edges and corners (their closest points lie on the edges, i.e. on the islands' borders), and each side's texels
    inside its own UV island."""
    mesh, _, side = atlas_cube(4.0, px=16, inset_px=0.5)
    obj = voxelize(mesh, 0.25)
    assert int(obj.occupancy.sum()) == 16 ** 3 and len(obj.texel_voxels) == 16 ** 3 - 14 ** 3
    single = check_box_colours(obj, mesh, side, SIDE_LIN, 2.0)
    # every side is seen, and the texel uv of a single-side texel lies in that side's island
    _, tri = closest_on_mesh(mesh, texel_centres(obj))
    assert set(side[tri[single]].tolist()) == set(range(6))
    uv = obj.texel_uv.numpy().astype(np.float64)
    row, col = np.divmod(side[tri[single]], 3)
    x = uv[single, 0] * 48 - col * 16  # pixels inside the square
    y = (1 - uv[single, 1]) * 32 - row * 16
    assert x.min() >= 0.5 - 1e-4 and x.max() <= 15.5 + 1e-4 and y.min() >= 0.5 - 1e-4 and y.max() <= 15.5 + 1e-4


def test_gltf_base_color_factor_multiplies_texture(tmp_path):
    """A GLB written by trimesh: PBRMaterial with baseColorFactor (230, 128, 64) and the atlas texture → texel
    colours = factor/255 (linear, not decoded) × the texture's decoded colour; without a texture → the factor
    alone, reported as colour 'material'."""
    from trimesh.visual.material import PBRMaterial

    mesh, image, side = atlas_cube(4.0, px=8, inset_px=0.5)
    factor = np.array([230, 128, 64], dtype=np.float64) / 255.0
    mesh.visual = trimesh.visual.TextureVisuals(uv=mesh.visual.uv, material=PBRMaterial(
        baseColorFactor=[230, 128, 64, 255], baseColorTexture=image))
    path = tmp_path / "box.glb"
    mesh.export(str(path))
    loaded, report = load_mesh(str(path))
    assert report["colour"] == "texture" and report["texture_size"] == (24, 16) and report["watertight"]
    obj = voxelize(loaded, 0.5)
    check_box_colours(obj, loaded, side, SIDE_LIN * factor, 2.0)
    assert float(obj.texel_colors[:, 0].max()) == pytest.approx(factor[0] * SIDE_LIN[:, 0].max(), abs=1e-6)

    plain = trimesh.creation.box((4.0, 4.0, 4.0))
    plain.visual = trimesh.visual.TextureVisuals(uv=np.zeros((8, 2)), material=PBRMaterial(
        baseColorFactor=[230, 128, 64, 255]))
    path = tmp_path / "plain.glb"
    plain.export(str(path))
    loaded, report = load_mesh(str(path))
    assert report["colour"] == "material" and report["texture_size"] is None
    obj = voxelize(loaded, 0.5)
    assert np.abs(obj.texel_colors.numpy() - factor).max() < 1e-7


def test_mesh_with_a_hole(tmp_path):
    """An icosphere (R = 2 mm) without its top cap (faces above z = 1.8, 5 % of the solid angle), saved as PLY:
    load_mesh says not watertight; voxelised at 0.1 mm it has the closed sphere's voxels except in the cap
    (z > 1.5 mm), at most the cap's volume (π·0.2²·(3R − 0.2)/3 = 0.24 mm³) fewer; texels are everywhere."""
    R, h = 2.0, 0.1
    closed = trimesh.creation.icosphere(subdivisions=3, radius=R)
    keep = closed.triangles_center[:, 2] < 1.8
    assert 40 < (~keep).sum() < 80
    holey = trimesh.Trimesh(closed.vertices, closed.faces[keep], process=False)  # same vertices: the same grid
    path = tmp_path / "holey.ply"
    holey.export(str(path))
    loaded, report = load_mesh(str(path))
    assert not report["watertight"] and report["triangles"] == int(keep.sum())
    ref = voxelize(closed, h)
    obj = voxelize(holey, h)
    assert obj.grid_shape == ref.grid_shape
    diff = obj.occupancy.numpy() != ref.occupancy.numpy()
    z = voxel_centres(obj)[..., 2]
    assert not diff[z < 1.5].any(), f"{int(diff[z < 1.5].sum())} voxels differ away from the hole"
    lost = (int(ref.occupancy.sum()) - int(obj.occupancy.sum())) * h ** 3
    cap = math.pi * 0.2 ** 2 * (3 * R - 0.2) / 3
    assert -1e-9 <= lost <= cap + 0.05
    assert abs(float(obj.occupancy.sum()) * h ** 3 / closed.volume - 1) < 0.02
    assert len(obj.texel_voxels) > 0.95 * len(ref.texel_voxels)


def test_duplicated_faces_voxelise_like_the_clean_mesh():
    """Every face twice (as in a careless merge of two copies): the same occupancy, texels, closest points and
    normals as the clean mesh. The duplicate is not watertight (every edge has four faces), so its signs come from
    the winding number (2 inside, 0 outside: |w| > ½ is the same set) instead of pseudonormals; a difference could
    only appear at voxel centres on the surface itself, and this grid has none."""
    clean = trimesh.creation.icosphere(subdivisions=3, radius=2.0)
    double = trimesh.Trimesh(clean.vertices, np.vstack([clean.faces, clean.faces]), process=False)
    a, b = voxelize(clean, 0.1), voxelize(double, 0.1)
    assert torch.equal(a.occupancy, b.occupancy)
    assert torch.equal(a.texel_voxels, b.texel_voxels)
    assert torch.allclose(a.texel_points, b.texel_points, atol=1e-12)
    assert torch.allclose(a.texel_normals, b.texel_normals, atol=1e-9)
    band = a.sdf.abs() < a.band_mm
    assert torch.allclose(a.sdf[band], b.sdf[band], atol=1e-6)


def _outward(obj, centre=(0.0, 0.0, 0.0)):
    radial = obj.texel_points - torch.tensor(centre, dtype=torch.float64)
    radial = radial / radial.norm(dim=1, keepdim=True)
    return (radial * obj.texel_normals).sum(1)


def test_inverted_faces():
    """All faces wound inward (mesh.invert()): the same occupancy and texels as the clean sphere, normals still
    outward (cos to the radial direction > 0.99)."""
    clean = trimesh.creation.icosphere(subdivisions=3, radius=2.0)
    flipped = clean.copy()
    flipped.invert()
    assert flipped.volume < 0
    a, b = voxelize(clean, 0.1), voxelize(flipped, 0.1)
    assert torch.equal(a.occupancy, b.occupancy)
    assert torch.equal(a.texel_voxels, b.texel_voxels)
    assert float(_outward(b).min()) > 0.99
    assert torch.allclose(a.texel_normals, b.texel_normals, atol=1e-9)


def test_partly_flipped_faces():
    """A third of the faces wound the wrong way (a broken export; the mesh is watertight but not consistently
    wound): the same occupancy as the clean sphere and outward normals (cos > 0.99) on every texel."""
    clean = trimesh.creation.icosphere(subdivisions=3, radius=2.0)
    faces = clean.faces.copy()
    faces[::3] = faces[::3, ::-1]
    broken = trimesh.Trimesh(clean.vertices, faces, process=False)
    assert not broken.is_winding_consistent
    a, b = voxelize(clean, 0.1), voxelize(broken, 0.1)
    assert int(b.occupancy.sum()) == int(a.occupancy.sum()), (int(b.occupancy.sum()), int(a.occupancy.sum()))
    assert torch.equal(a.occupancy, b.occupancy)
    cos = _outward(b)
    assert float(cos.min()) > 0.99, f"{int((cos <= 0.99).sum())} of {len(cos)} texel normals point inward"


def test_two_cubes_sharing_an_edge():
    """Two 2 mm cubes touching along one edge (x = y = 0; a non-manifold edge with four faces), 0.25 mm voxels on
    the cubes' faces: occupancy is exactly the union (2·8³ voxels, 16 mm³), texels exactly both cubes' boundary
    layers (2·(8³ − 6³))."""
    a = trimesh.creation.box((2.0, 2.0, 2.0))
    a.apply_translation((-1.0, -1.0, 0.0))
    b = trimesh.creation.box((2.0, 2.0, 2.0))
    b.apply_translation((1.0, 1.0, 0.0))
    mesh = trimesh.util.concatenate([a, b])
    merged = mesh.copy()
    merged.merge_vertices()
    assert not merged.is_watertight  # the shared edge has four faces
    obj = voxelize(mesh, 0.25)
    p = voxel_centres(obj)
    truth = ((p[..., 0] < 0) & (p[..., 1] < 0) | (p[..., 0] > 0) & (p[..., 1] > 0)) & \
        (np.abs(p[..., 0]) < 2) & (np.abs(p[..., 1]) < 2) & (np.abs(p[..., 2]) < 1)
    assert truth.sum() == 2 * 8 ** 3
    assert np.array_equal(obj.occupancy.numpy(), truth)
    assert float(obj.occupancy.sum()) * 0.25 ** 3 == pytest.approx(16.0)
    assert len(obj.texel_voxels) == 2 * (8 ** 3 - 6 ** 3)


def test_two_separate_shells():
    """Two spheres (R = 1 mm, centres x = ±2.5 mm) in one mesh: both filled (each within 2 % of its mesh volume),
    nothing between them, texels on both in equal numbers (the grid and the icosphere are mirror symmetric in x),
    normals outward from each sphere's own centre."""
    s = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    left, right = s.copy(), s.copy()
    left.apply_translation((-2.5, 0, 0))
    right.apply_translation((2.5, 0, 0))
    h = 0.1
    obj = voxelize(trimesh.util.concatenate([left, right]), h)
    p = voxel_centres(obj)
    occ = obj.occupancy.numpy()
    for sign in (-1, 1):
        half = occ & (np.sign(p[..., 0]) == sign)
        assert abs(half.sum() * h ** 3 / s.volume - 1) < 0.02
    assert not occ[np.abs(p[..., 0]) < 1.4].any()
    x = obj.texel_points[:, 0]
    n_left, n_right = int((x < 0).sum()), int((x > 0).sum())
    assert n_left == n_right and n_left > 500
    centre = torch.stack([torch.sign(x) * 2.5, torch.zeros_like(x), torch.zeros_like(x)], 1)
    radial = obj.texel_points - centre
    cos = (radial / radial.norm(dim=1, keepdim=True) * obj.texel_normals).sum(1)
    assert float(cos.min()) > 0.99


def test_metres_and_millimetres_give_the_same_object(tmp_path):
    """A torus 22 mm across saved in mm and in metres (PLY, float32): loaded raw and with scale=1000, both give
    the same voxels, texels and SDF (float32 storage: coordinates agree to ~1e-6 mm); units_guess says mm vs m."""
    mm = trimesh.creation.torus(major_radius=8.0, minor_radius=3.0, major_sections=48, minor_sections=24)
    mm.apply_transform(trimesh.transformations.rotation_matrix(0.3, (1.0, 0.5, 0.0)))
    m = mm.copy()
    m.apply_scale(1e-3)
    mm.export(str(tmp_path / "mm.ply"))
    m.export(str(tmp_path / "m.ply"))
    mesh_mm, rep_mm = load_mesh(str(tmp_path / "mm.ply"))
    mesh_m, rep_m = load_mesh(str(tmp_path / "m.ply"), scale=1000)
    assert rep_mm["units_guess"] == "mm" and rep_m["units_guess"] == "m"
    assert rep_mm["scale_to_mm"] == 1.0 and rep_m["scale_to_mm"] == 1000.0
    assert np.abs(mesh_mm.vertices - mesh_m.vertices).max() < 1e-5
    a, b = voxelize(mesh_mm, 0.5), voxelize(mesh_m, 0.5)
    assert a.grid_shape == b.grid_shape and np.allclose(a.origin, b.origin, atol=1e-5)
    assert torch.equal(a.occupancy, b.occupancy)
    assert torch.equal(a.texel_voxels, b.texel_voxels)
    assert float((a.sdf - b.sdf).abs().max()) < 1e-4
    assert float((a.texel_points - b.texel_points).abs().max()) < 1e-4


def test_obj_with_uvs_and_no_material_then_texture_argument():
    """Spot's OBJ has vt lines and no MTL: trimesh's 2×2 placeholder image is not taken for the object's colour
    (colour none, no texture size, a hint naming texture=, texel colours None but texel uvs kept); with
    texture= the PNG is attached (1024×1024, source 'argument')."""
    obj_path = os.path.join(SPOT, "spot_triangulated.obj")
    mesh, report = load_mesh(obj_path, height_mm=10.0)
    assert report["colour"] == "none" and report["texture_size"] is None and report["uv"]
    assert "texture=" in report["hint"]
    obj = voxelize(mesh, 0.5)
    assert obj.texel_colors is None and obj.texel_uv is not None and len(obj.texel_uv) == len(obj.texel_voxels)
    mesh, report = load_mesh(obj_path, height_mm=10.0, texture=os.path.join(SPOT, "spot_texture.png"))
    assert report["colour"] == "texture" and report["texture_size"] == (1024, 1024)
    assert report["texture_source"] == "argument" and report["hint"] is None
    assert report["triangles"] == 5856 and report["watertight"]


def test_spot_texel_colours_match_an_independent_lookup():
    """Spot 20 mm tall with its texture, 0.4 mm voxels: on 200 random texels whose closest point lies inside a
    triangle (on an edge the triangle, and across a UV seam the uv, is not unique), the texel uv and colour equal
    the brute-force closest point → trimesh's barycentrics → uv → a float64 bilinear lookup (texel centres, v up) of the sRGB
    texture decoded here, to 1e-4."""
    from trimesh.triangles import points_to_barycentric

    mesh, report = load_mesh(os.path.join(SPOT, "spot_triangulated.obj"), height_mm=20.0,
                             texture=os.path.join(SPOT, "spot_texture.png"))
    assert abs(mesh.extents[2] - 20.0) < 1e-9 and report["colour"] == "texture"
    obj = voxelize(mesh, 0.4)
    rng = np.random.default_rng(0)
    sample = rng.choice(len(obj.texel_voxels), 400, replace=False)
    closest, tri = closest_on_mesh(mesh, texel_centres(obj)[sample])
    assert np.abs(closest - obj.texel_points.numpy()[sample]).max() < 1e-6
    bary = points_to_barycentric(mesh.triangles[tri], closest)
    interior = np.flatnonzero(bary.min(1) > 1e-6)
    assert len(interior) >= 200
    pick = sample[interior[:200]]
    uv = (np.asarray(mesh.visual.uv)[mesh.faces[tri[interior[:200]]]] * bary[interior[:200], :, None]).sum(1)
    assert np.abs(obj.texel_uv.numpy()[pick] - uv).max() < 1e-5
    with Image.open(os.path.join(SPOT, "spot_texture.png")) as im:
        tex = srgb_decode(np.asarray(im.convert("RGB"), dtype=np.float64) / 255.0)
    expected = bilinear(tex, uv)
    assert float(np.ptp(expected)) > 0.3  # the sample sees the texture's patches, not one flat colour
    assert np.abs(obj.texel_colors.numpy()[pick] - expected).max() < 1e-4


def test_bad_input(tmp_path):
    """What tests/test_voxelize.py does not already refuse: random bytes and empty files in each format, negative
    or non-numeric sizes, a missing MTL, texture= missing / not an image / truncated / not a path / on a mesh
    without UVs, a flat mesh scaled by height; and texture= over a file's own texture (replaced, said in the hint)."""
    rng = np.random.default_rng(0)
    for suffix in (".obj", ".ply", ".glb", ".stl"):
        noise = tmp_path / f"noise{suffix}"
        noise.write_bytes(rng.integers(0, 256, 4096, dtype=np.uint8).tobytes())
        with pytest.raises(ValueError, match="path: could not read|holds no triangles"):
            load_mesh(str(noise))
        empty = tmp_path / f"empty{suffix}"
        empty.write_bytes(b"")
        with pytest.raises(ValueError, match="path: could not read|holds no triangles"):
            load_mesh(str(empty))
    stl = tmp_path / "box.stl"
    trimesh.creation.box((1.0, 2.0, 3.0)).export(str(stl))
    with pytest.raises(ValueError, match=r"height_mm: expected a finite value in \(0, inf\], got -5.0"):
        load_mesh(str(stl), height_mm=-5.0)
    with pytest.raises(TypeError, match="height_mm: expected a real number, got str"):
        load_mesh(str(stl), height_mm="20")
    with pytest.raises(ValueError, match="scale: expected a finite value"):
        load_mesh(str(stl), scale=0.0)
    with pytest.raises(ValueError, match="scale: expected a finite value"):
        load_mesh(str(stl), scale=float("nan"))
    with pytest.raises(TypeError, match="path: expected a file path, got int"):
        load_mesh(3)
    box, _ = load_mesh(str(stl))
    with pytest.raises(ValueError, match=r"voxel_size: expected a finite value in \(0, inf\], got -0.1"):
        voxelize(box, -0.1)
    with pytest.raises(ValueError, match="voxel_size: expected a finite value"):
        voxelize(box, float("inf"))
    # a flat mesh cannot be scaled to a height
    flat = tmp_path / "flat.obj"
    flat.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    with pytest.raises(ValueError, match="height_mm: the mesh has no z extent"):
        load_mesh(str(flat), height_mm=10.0)
    # an OBJ whose mtllib is missing
    obj = tmp_path / "m.obj"
    obj.write_text("mtllib gone.mtl\nusemtl a\nv 0 0 0\nv 1 0 0\nv 0 1 1\nvt 0 0\nvt 1 0\nvt 0 1\nf 1/1 2/2 3/3\n")
    with pytest.raises(ValueError, match=r"names texture/material files that are missing: \['gone.mtl'\]"):
        load_mesh(str(obj))
    # texture=
    uv_obj = tmp_path / "uv.obj"
    uv_obj.write_text("v 0 0 0\nv 1 0 0\nv 0 1 1\nvt 0 0\nvt 1 0\nvt 0 1\nf 1/1 2/2 3/3\n")
    with pytest.raises(ValueError, match="texture: no such file"):
        load_mesh(str(uv_obj), texture=str(tmp_path / "nothing.png"))
    not_png = tmp_path / "noise.png"
    not_png.write_bytes(rng.integers(0, 256, 512, dtype=np.uint8).tobytes())
    with pytest.raises(ValueError, match="texture: cannot decode .*noise.png"):
        load_mesh(str(uv_obj), texture=str(not_png))
    cut = tmp_path / "cut.png"
    with open(os.path.join(SPOT, "spot_texture.png"), "rb") as handle:
        cut.write_bytes(handle.read()[:5000])  # a valid header, truncated data
    with pytest.raises(ValueError, match="texture: .*cut.png.* is a truncated or corrupt PNG file"):
        load_mesh(str(uv_obj), texture=str(cut))
    with pytest.raises(TypeError, match="texture: expected an image file path, got int"):
        load_mesh(str(uv_obj), texture=1)
    with pytest.raises(ValueError, match="texture: the mesh in .* has no texture coordinates"):
        load_mesh(str(stl), texture=os.path.join(SPOT, "spot_texture.png"))
    mesh, report = load_mesh(str(uv_obj), texture=os.path.join(SPOT, "spot_texture.png"))
    assert report["colour"] == "texture" and report["texture_size"] == (1024, 1024) and report["hint"] is None
    # a file with its own texture: texture= wins, and the report says what it replaced
    mesh, report = load_mesh(os.path.join(DATA, "BoxTextured.glb"), texture=os.path.join(SPOT, "spot_texture.png"))
    assert report["texture_size"] == (1024, 1024) and report["texture_source"] == "argument"
    assert report["hint"] == "texture= replaced the file's own 256x256 texture"
    assert mesh.visual.material.image.size == (1024, 1024)


@pytest.mark.parametrize("bad", ["nan", "inf"])
@pytest.mark.parametrize("suffix", [".obj", ".ply"])
def test_non_finite_vertex_is_refused_not_dropped(tmp_path, bad, suffix):
    """trimesh's processing drops the faces of a NaN/Inf vertex without a word, and the rest voxelised as if the
    mesh were whole; load_mesh refuses the file and says how many triangles are affected."""
    vertices = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [0.5, 0.5, 0.5]], dtype=np.float64)
    vertices[4, 0] = float(bad)
    faces = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3], [1, 2, 4]])
    path = tmp_path / f"tetra{suffix}"
    if suffix == ".obj":
        path.write_text("".join(f"v {x} {y} {z}\n" for x, y, z in vertices)
                        + "".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in faces))
    else:
        trimesh.Trimesh(vertices, faces, process=False).export(str(path))
    with pytest.raises(ValueError, match=r"path: .*non-finite \(NaN or Inf\) vertex coordinates in 1 of 5 triangles"):
        load_mesh(str(path), height_mm=5.0)
    vertices[4, 0] = 0.5  # the same file with a finite vertex loads
    path.unlink()
    trimesh.Trimesh(vertices, faces, process=False).export(str(path))
    mesh, _ = load_mesh(str(path), height_mm=5.0)
    assert len(mesh.faces) == 5
