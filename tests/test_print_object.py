"""Print optimisation of a voxelised textured object (issue 12): the loop, its run folder, resume, the shell,
the void outside the object and bad input."""
import csv
import os

import numpy as np
import pytest
import torch
import trimesh

from torch_appearance.fabrication import InkSet, load_index_volume, read_slices
from torch_appearance.fabrication.export import VOID
from torch_appearance.geometry import VoxelObject, voxelize
from torch_appearance.nn import AppearanceLoss
from torch_appearance.pipelines import PrintConfig, optimize_print
from torch_appearance.pipelines.print import ObjectTarget
from torch_appearance.pipelines.print.config import auto_eval_texels

QUIET = dict(progress=False, log=lambda *_: None)


@pytest.fixture(scope="module")
def sphere_ply(tmp_path_factory):
    """A sphere coloured by its normals (vertex colours), radius 1 in file units."""
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    rgb = np.clip(0.5 + 0.4 * mesh.vertex_normals, 0, 1)
    mesh.visual.vertex_colors = np.c_[(rgb * 255).astype(np.uint8), np.full(len(rgb), 255, np.uint8)]
    path = tmp_path_factory.mktemp("mesh") / "sphere.ply"
    mesh.export(path)
    return str(path)


def config(mesh_path, out, **kw):
    kw.setdefault("mesh", mesh_path)
    base = dict( height_mm=2.4, dpi=100.0, shell_mm=0.55, spp=2, eval_spp=8, eval_every=2, iterations=4,
                printer_dpi=(300.0, 300.0, 300.0), views=0, view_size=40, out=str(out))
    base.update(kw)
    return PrintConfig(**base)


def test_object_run_folder_shell_void_and_resume(sphere_ply, tmp_path):
    # from the paper's 97 % white start, four iterations must lower the error (the naive start is already close)
    summary = optimize_print(config(sphere_ply, tmp_path / "run", views=2, init="white"), **QUIET)
    folder = tmp_path / "run"
    for name in ("config.json", "log.csv", "convergence.png", "ink_usage_by_depth.png", "object.npz", "mixture.npz",
                 "quantized.npz", "summary.json", "checkpoint.pt", "slices/palette.json", "views.png",
                 "view_0.exr", "view_1.png"):
        assert (folder / name).exists(), name
    for stem in ("target", "baseline", "initial", "optimized", "final"):
        assert (folder / f"{stem}.ply").exists() and (folder / f"{stem}.npy").exists(), stem
    obj = VoxelObject.load(str(folder / "object.npz"))
    n_texels, shell = len(obj.texel_voxels), obj.shell
    assert summary["kind"] == "object" and summary["texels"] == n_texels
    # eval_texels "auto" (the object default): the subset the rule sizes by the training, here every texel
    resolved = config(sphere_ply, tmp_path / "run", views=2, init="white").resolved()
    assert resolved.eval_texels == "auto" and auto_eval_texels(n_texels, resolved) == 0
    assert summary["evaluation"]["texels"] == n_texels
    assert np.load(folder / "final.npy").shape == (n_texels, 3)
    # only the shell carries parameters; deeper voxels hold the core ink exactly
    inks = InkSet.from_names()
    assert summary["parameters"] == len(inks) * int(shell.sum())
    weights = torch.from_numpy(np.load(folder / "mixture.npz")["weights"])
    core = weights[:, obj.occupancy & ~shell]
    assert core.shape[1] > 0 and bool((core[inks.index("white")] == 1).all())
    # the quantised volume: void outside the object, inks inside, the slices read back the same
    indices, _, _ = load_index_volume(str(folder / "quantized.npz"))
    inside = obj.occupancy.float().mean().item()
    assert 0.5 * inside < float((indices != VOID).mean()) < 1.5 * inside
    assert np.array_equal(read_slices(str(folder / "slices"))[0], indices)
    # the colours move towards the target (same evaluation spp and seed at iteration 0 and at the end)
    rows = list(csv.DictReader(open(folder / "log.csv")))
    assert [int(r["iteration"]) for r in rows] == list(range(5))
    assert float(rows[-1]["dE00_mean"]) < 0.8 * float(rows[0]["dE00_mean"])
    # resume: 2 iterations, then continue to 4 = one run of 4 (same seeds per iteration)
    optimize_print(config(sphere_ply, tmp_path / "split", iterations=2, init="white"), **QUIET)
    with pytest.raises(ValueError, match="already holds a run"):
        optimize_print(config(sphere_ply, tmp_path / "split", init="white"), **QUIET)
    resumed = optimize_print(config(sphere_ply, tmp_path / "split", resume=True, init="white"), **QUIET)
    split_rows = list(csv.DictReader(open(tmp_path / "split" / "log.csv")))
    assert [r["loss"] for r in split_rows] == [r["loss"] for r in rows]
    assert resumed["final_quantized"] == summary["final_quantized"]


def test_object_naive_extrusion_takes_the_nearest_texel():
    """Every shell voxel of the baseline holds the mixture of the texel nearest to it; the core holds the core."""
    obj = voxelize(trimesh.creation.box((2.0, 1.6, 1.2)), 0.2, shell_mm=0.3)
    obj.texel_colors = torch.rand(len(obj.texel_voxels), 3)
    target = ObjectTarget(obj)
    n = len(obj.texel_voxels)
    texel_weights = np.random.default_rng(0).random((4, n))
    core = np.array([0.0, 0.0, 0.0, 1.0])
    w = target.extrude(texel_weights, core).numpy()
    tex = obj.texel_voxels.numpy()
    for k, j, i in np.argwhere(obj.shell.numpy())[::7]:
        d2 = ((tex - (k, j, i)) ** 2).sum(1)
        assert d2.min() == d2[np.argmin(d2)]
        candidates = np.flatnonzero(d2 == d2.min())
        assert any(np.allclose(w[:, k, j, i], texel_weights[:, c], atol=1e-7) for c in candidates)
    outside_shell = ~obj.shell.numpy()
    assert np.allclose(w[:, outside_shell], core[:, None])


def test_object_loss_is_the_sparse_texel_path():
    """The object loop's loss (ObjectTarget.appearance) needs no voxel grid and equals the grid path on the texels
    of a voxelised sphere (E1, E2, E3 and the gradient of E)."""
    obj = voxelize(trimesh.creation.icosphere(subdivisions=3, radius=1.0), 0.1, shell_mm=0.2)
    g = torch.Generator().manual_seed(0)
    obj.texel_colors = torch.rand(len(obj.texel_voxels), 3, generator=g)
    target = ObjectTarget(obj)
    criterion = AppearanceLoss(gamma=(1.0, 3.0, 1.0))
    x = torch.rand(len(obj.texel_voxels), 3, generator=g, requires_grad=True)
    total, parts = target.appearance(criterion, x)
    assert "target_grid" not in vars(target) and "mask" not in vars(target)  # no dense grid was built
    (grad,) = torch.autograd.grad(total, x)
    dense_total, dense_parts = criterion.forward_parts(target.to_grid(x), target.target_grid, target.mask)
    (dense_grad,) = torch.autograd.grad(dense_total, x)
    for k in ("E1", "E2", "E3"):
        torch.testing.assert_close(parts[k], dense_parts[k], rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(grad, dense_grad, rtol=1e-4, atol=1e-7 * float(dense_grad.abs().max()))


@pytest.mark.parametrize("overrides, match", [
    (dict(mesh="/nonexistent/missing.obj"), "no such file"),
    (dict(height_mm=0.0), "height_mm"),
    (dict(height_mm=None), "height_mm"),
    (dict(shell_mm=3.0), "shell_mm"),
    (dict(core_ink="gold"), "core_ink"),
    (dict(width_mm=3.0), "slab settings"),
])
def test_object_bad_input_leaves_no_run_folder(sphere_ply, tmp_path, overrides, match):
    out = tmp_path / "run"
    with pytest.raises(ValueError, match=match):
        optimize_print(config(sphere_ply, out, **overrides), **QUIET)
    assert not out.exists()


def test_object_without_colours_is_refused(tmp_path):
    path = tmp_path / "plain.stl"
    trimesh.creation.box((1.0, 1.0, 1.0)).export(path)
    out = tmp_path / "run"
    with pytest.raises(ValueError, match="neither a texture nor vertex/face colours"):
        optimize_print(config(str(path), out), **QUIET)
    assert not out.exists()


def test_textured_object_bakes_colours_into_its_uv_layout(tmp_path):
    """A glTF with a base-colour texture: the target and final texel colours are also written in the mesh's UV
    layout, and the baked target resembles the texture where the UV islands lie."""
    from PIL import Image

    glb = os.path.join(os.path.dirname(__file__), "data", "meshes", "BoxTextured.glb")
    optimize_print(config(glb, tmp_path / "run", height_mm=2.0, shell_mm=0.5, iterations=1, eval_every=1), **QUIET)
    baked = np.asarray(Image.open(tmp_path / "run" / "target_uv.png").convert("RGB"), dtype=np.float64)
    assert (tmp_path / "run" / "final_uv.png").exists() and (tmp_path / "run" / "baseline_uv.png").exists()
    texture = trimesh.load(glb, force="mesh").visual.material.baseColorTexture.convert("RGB")
    texture = np.asarray(texture.resize(baked.shape[1::-1]), dtype=np.float64)
    # texels sample the texture at 10 voxels per face: compare blurred versions
    from scipy.ndimage import uniform_filter
    diff = np.abs(uniform_filter(baked, (25, 25, 1)) - uniform_filter(texture, (25, 25, 1)))
    assert np.median(diff) < 20


def test_environment_map_lights_the_object(tmp_path):
    """A uniform lat-long map of radiance 1 lights the object exactly like the default uniform environment, a map
    of 2 doubles the texels (linear light transport); envmap is refused for slabs and when missing."""
    from torch_appearance import io as ta_io
    from torch_appearance.render import EnvironmentMap

    obj = voxelize(trimesh.creation.icosphere(radius=1.0), 0.15, shell_mm=0.4)
    obj.texel_colors = torch.full((len(obj.texel_voxels), 3), 0.5)
    sigma_t = torch.full((3, *obj.grid_shape), 8.0)
    albedo = torch.full((3, *obj.grid_shape), 0.9)
    plain = ObjectTarget(obj).render(sigma_t, albedo, 4, 7)
    ones = ObjectTarget(obj, emitter=EnvironmentMap(torch.ones(8, 16, 3))).render(sigma_t, albedo, 4, 7)
    twos = ObjectTarget(obj, emitter=EnvironmentMap(torch.ones(8, 16, 3), scale=2.0)).render(sigma_t, albedo, 4, 7)
    assert torch.allclose(ones, plain, rtol=1e-5, atol=1e-6)
    assert torch.allclose(twos, 2 * plain, rtol=1e-5, atol=1e-6)
    exr = tmp_path / "env.exr"
    ta_io.write_exr(str(exr), np.ones((8, 16, 3), np.float32))
    with pytest.raises(ValueError, match="envmap: environment maps light object prints"):
        optimize_print(PrintConfig(envmap=str(exr), out=str(tmp_path / "slab")), **QUIET)
    with pytest.raises(ValueError, match="envmap: no such file"):
        optimize_print(config("x.ply", tmp_path / "run", envmap=str(tmp_path / "none.exr")), **QUIET)


def test_fixed_fraction_is_exact_through_optimisation_and_quantisation(sphere_ply, tmp_path):
    """``transparent=0.8:depth:0-0.3``: every constrained voxel holds exactly 0.8 clear ink after optimisation,
    and the printer micro-voxels of the region hold exactly round(0.8·n) clear drops."""
    from torch_appearance.fabrication.quantize import source_index

    out = tmp_path / "run"
    inks = InkSet.from_names(["cyan", "magenta", "yellow", "black", "white", "transparent"])
    optimize_print(config(sphere_ply, out, iterations=2, inks=inks.names, table_steps=2,
                          fixed=("transparent=0.8:depth:0-0.3",)),
                   **QUIET)
    obj = VoxelObject.load(str(out / "object.npz"))
    k = inks.index("transparent")
    region = (obj.depth < 0.3) & obj.shell
    weights = np.load(out / "mixture.npz")["weights"]
    assert region.sum() > 50 and np.all(weights[k][region.numpy()] == np.float32(0.8))
    indices, _, _ = load_index_volume(str(out / "quantized.npz"))
    d, h, w = obj.grid_shape
    iz, iy, ix = (source_index(n, m) for n, m in zip((d, h, w), indices.shape))
    micro_region = region.numpy()[iz[:, None, None], iy[None, :, None], ix[None, None, :]] & (indices != VOID)
    n = int(micro_region.sum())
    assert int((indices[micro_region] == k).sum()) == round(0.8 * n)


def test_fixed_fraction_bad_specs(sphere_ply, tmp_path):
    out = tmp_path / "run"
    for spec, match in [("gold=0.5:all", "not in the ink set"), ("transparent=1.5:all", r"fraction in \[0, 1\]"),
                        ("transparent=0.5:elsewhere", "unknown mask term"), ("transparent", "INK=FRACTION:MASK"),
                        ("transparent=0.5:depth:5-6", "selects no optimised voxel")]:
        with pytest.raises(ValueError, match=match):
            optimize_print(config(sphere_ply, out, fixed=(spec,), inks=("cyan", "white", "transparent")), **QUIET)
        assert not out.exists()
    mask = tmp_path / "mask.png"
    import cv2
    cv2.imwrite(str(mask), np.full((5, 7), 255, np.uint8))
    with pytest.raises(ValueError, match="expected the same size"):
        optimize_print(PrintConfig(fixed=(f"white=0.5:{mask}",), out=str(out)), **QUIET)
    assert not out.exists()


def test_remap_baseline_is_scored_beside_ours(tmp_path):
    """--remap-baseline: the 2.5D remapped baseline (a slab optimised in UV space and wrapped around the object)
    is quantised, rendered and scored like the others, and kept through a resume."""
    glb = os.path.join(os.path.dirname(__file__), "data", "meshes", "BoxTextured.glb")
    out = tmp_path / "run"
    kw = dict(height_mm=2.0, shell_mm=0.5, eval_every=1, remap_baseline=True, table_steps=2)
    summary = optimize_print(config(glb, out, iterations=1, **kw), **QUIET)
    remap = summary["baseline_remap_25d"]
    assert remap is not None and remap["dE00_mean"] > 0 and (out / "remap25d" / "slab" / "mixture.npz").exists()
    assert np.load(out / "baseline_remap.npy").shape == (summary["texels"], 3)
    resumed = optimize_print(config(glb, out, iterations=2, resume=True, **kw), **QUIET)
    assert resumed["baseline_remap_25d"]["dE00_mean"] == remap["dE00_mean"]
    with pytest.raises(ValueError, match="remap_baseline"):
        optimize_print(PrintConfig(remap_baseline=True, out=str(tmp_path / "slab")), **QUIET)


def test_views_figure_without_offscreen_rendering(monkeypatch, tmp_path):
    """Where pyvista cannot render offscreen, views.png still shows the rendered print (no mesh pictures)."""
    import torch_appearance.geometry.preview as preview
    from torch_appearance.pipelines.print.object_figures import views_figure

    monkeypatch.setattr(preview, "_probe_result", (False, "test: no OpenGL"))
    obj = voxelize(trimesh.creation.icosphere(radius=1.0), 0.25, shell_mm=0.4)
    obj.texel_colors = torch.full((len(obj.texel_voxels), 3), 0.5)
    target = ObjectTarget(obj)
    target.mesh = trimesh.creation.icosphere(radius=1.0)
    cams = target.camera_views(2, 24)
    rows = views_figure(str(tmp_path / "views.png"), target, cams, [np.full((24, 24, 3), 0.5)] * 2,
                        texel_de=np.ones(len(obj.texel_voxels)), log=lambda *_: None)
    assert rows == 1 and (tmp_path / "views.png").exists()


def test_mesh_views_follow_each_camera():
    """The mesh pictures of a list of cameras equal those of each camera alone (no frame from the previous
    camera), and different cameras give different pictures."""
    from torch_appearance.geometry.preview import offscreen_rendering
    from torch_appearance.pipelines.print.object_figures import mesh_views

    if not offscreen_rendering()[0]:
        pytest.skip("no offscreen OpenGL here")
    mesh = trimesh.creation.box((1.0, 2.0, 3.0))
    mesh.visual.vertex_colors = np.c_[(np.abs(mesh.vertex_normals) * 255).astype(np.uint8),
                                      np.full(len(mesh.vertices), 255, np.uint8)]
    obj = voxelize(mesh, 0.25, shell_mm=0.3)
    obj.texel_colors = torch.full((len(obj.texel_voxels), 3), 0.5)
    cams = ObjectTarget(obj).camera_views(3, 48)
    together = mesh_views(mesh, cams)
    for k, cam in enumerate(cams):
        alone = mesh_views(mesh, [cam])[0]
        assert np.abs(together[k].astype(int) - alone.astype(int)).mean() < 1.0, k
    assert np.abs(together[0].astype(int) - together[1].astype(int)).mean() > 5.0


def test_naive_baseline_can_be_skipped(sphere_ply, tmp_path):
    summary = optimize_print(config(sphere_ply, tmp_path / "run", naive_baseline=False, iterations=2), **QUIET)
    assert summary["baseline_naive_extrusion"] is None and not (tmp_path / "run" / "baseline.npy").exists()
    assert (tmp_path / "run" / "convergence.png").exists()


def two_material_cube(folder):
    """A unit cube OBJ whose top face (z = 1) is material 'lid' (blue) and the other five 'body' (red)."""
    (folder / "cube.mtl").write_text("newmtl body\nKd 0.8 0.1 0.1\nnewmtl lid\nKd 0.1 0.1 0.8\n")
    corners = "".join(f"v {x} {y} {z}\n" for z in (0, 1) for y in (0, 1) for x in (0, 1))
    quads = {"body": [(1, 3, 4, 2), (1, 2, 6, 5), (2, 4, 8, 6), (4, 3, 7, 8), (3, 1, 5, 7)], "lid": [(5, 6, 8, 7)]}
    faces = "".join(f"usemtl {name}\n" + "".join(f"f {a} {b} {c}\nf {a} {c} {d}\n" for a, b, c, d in qs)
                    for name, qs in quads.items())
    path = folder / "cube.obj"
    path.write_text("mtllib cube.mtl\n" + corners + faces)
    return str(path)


def test_fixed_fraction_by_material_name(tmp_path):
    """``transparent=0.6:material:lid`` holds 60 % clear ink exactly in the shell voxels under the lid (their
    nearest texel is on the top face, told here from the texel normals), nowhere else; unknown names and
    material masks on a slab are refused."""
    from torch_appearance.geometry import load_mesh

    path = two_material_cube(tmp_path)
    mesh, report = load_mesh(path, height_mm=2.0)
    assert sorted(report["materials"]) == ["body", "lid"]
    lid = mesh.metadata["face_materials"] == report["materials"].index("lid")
    assert lid.sum() == 2 and np.allclose(mesh.face_normals[lid], [0, 0, 1])
    inks = ("cyan", "magenta", "yellow", "black", "white", "transparent")
    out = tmp_path / "run"
    optimize_print(config(path, out, height_mm=2.0, shell_mm=0.3, iterations=1, eval_every=1, inks=inks,
                          table_steps=2, fixed=("transparent=0.6:material:lid",)), **QUIET)
    obj = VoxelObject.load(str(out / "object.npz"))
    target = ObjectTarget(obj)
    shell = obj.shell.numpy()
    nearest = target.nearest_texel()
    top = obj.texel_normals.numpy()[:, 2] > 0.9
    expected = np.zeros(obj.grid_shape, dtype=bool)
    expected[shell] = top[nearest]
    side = obj.texel_normals.numpy()[:, 2] < 0.1  # side texels: the top rim's nearest face can be either
    clear_texels = np.abs(obj.texel_normals.numpy()[:, 2]) > 0.9
    decided = np.zeros(obj.grid_shape, dtype=bool)
    decided[shell] = clear_texels[nearest] | (side[nearest] & (obj.texel_points.numpy()[nearest, 2]
                                                                < obj.texel_points.numpy()[:, 2].max() - 0.2))
    weights = np.load(out / "mixture.npz")["weights"][inks.index("transparent")]
    held = weights == np.float32(0.6)
    assert expected.sum() > 20 and decided.sum() > 0.8 * shell.sum()
    assert np.array_equal(held[decided], expected[decided])
    with pytest.raises(ValueError, match=r"no material 'cap'; its materials are \[('body', 'lid'|'lid', 'body')\]"):
        optimize_print(config(path, tmp_path / "bad", height_mm=2.0, shell_mm=0.3, inks=inks,
                              fixed=("transparent=0.6:material:cap",)), **QUIET)
    with pytest.raises(ValueError, match="a slab has no materials"):
        optimize_print(PrintConfig(fixed=("white=0.5:material:lid",), out=str(tmp_path / "slab")), **QUIET)
    assert not (tmp_path / "bad").exists() and not (tmp_path / "slab").exists()


def test_quantised_white_object_renders_like_its_continuous_mixture():
    """A sphere printed in white only: the quantised micro-voxel volume is the same medium as the continuous one,
    so their texel colours agree in distribution. The micro-voxels whose centre is outside are VOID, but the
    smooth surface cuts some of them; light crosses those first, so they must hold the printed neighbour's ink
    (white), not a placeholder ink (cyan is ink 0 here: a cyan skin would take red out of every texel)."""
    from torch_appearance.testing import assert_z, seed_stats

    from torch_appearance.fabrication.quantize import quantize_mixture
    from torch_appearance.nn import mix_inks

    obj = voxelize(trimesh.creation.icosphere(subdivisions=3, radius=1.0), 0.125, shell_mm=0.3)
    obj.texel_colors = torch.full((len(obj.texel_voxels), 3), 0.5)
    target = ObjectTarget(obj)
    inks = InkSet.from_names(["cyan", "white"])
    weights = torch.zeros(2, *target.shape)
    weights[1] = 1.0
    indices = target.quantized_void(quantize_mixture(weights, obj.voxel_size, (609.6, 406.4, 609.6), seed=0))
    assert (indices == VOID).any() and set(np.unique(indices)) == {1, VOID}
    sigma_t, albedo = mix_inks(weights, inks)
    with torch.no_grad():
        cont, se_c = seed_stats(lambda k: target.render(sigma_t, albedo, 32, 100 + k), range(6))
    quant, se_q = seed_stats(lambda k: target.render_quantized(indices, inks, (609.6, 406.4, 609.6), 32, 200 + k),
                             range(6))
    assert_z(quant.mean(0) - cont.mean(0), (se_q.pow(2).mean(0) + se_c.pow(2).mean(0)).sqrt() / len(cont) ** 0.5,
             0.0, what="mean texel colour, quantised vs continuous")
    assert_z(quant - cont, (se_q ** 2 + se_c ** 2).sqrt(), 0.0, what="texel colours, quantised vs continuous")


def test_fill_void_at_surface_takes_the_inner_neighbour():
    from torch_appearance.pipelines.print.object_target import fill_void_at_surface

    # a 1-D column along x: printed inks 2, 0 then VOID; the surface (SDF 0) lies inside voxel 2 at x = 2.4
    indices = np.array([[[2, 0, VOID, VOID]]], dtype=np.uint8)
    sdf_x = np.array([-2.4, -1.4, -0.4, 0.6, 1.6], dtype=np.float32)
    sdf = torch.as_tensor(np.broadcast_to(sdf_x, (2, 2, 5)).copy())
    out = fill_void_at_surface(indices, sdf)
    assert out.tolist() == [[[2, 0, 0, VOID]]]      # the straddling voxel takes its printed neighbour; the outer stays
    assert indices[0, 0, 2] == VOID                  # the input is not modified
    with pytest.raises(ValueError, match="corner_sdf: expected shape"):
        fill_void_at_surface(indices, sdf[:, :, :4])


def test_object_evaluations_score_a_fixed_random_subset(sphere_ply, tmp_path, monkeypatch):
    """``eval_texels``: every evaluation renders and scores the same random subset of the texels (the sensor's rows
    and the target's rows agree: the subset's figure for the final print matches a render of all its texels within
    their standard errors); the pictures of the final print and the naive baseline cover every texel, the in-run
    ones only the subset."""
    from torch_appearance.pipelines.print.loop import build_target
    from torch_appearance.print_error import noise_free_error

    from torch_appearance.pipelines.print.object_target import ObjectTarget

    calls = {"prepare": 0, "render": 0}   # each print (naive, final) is prepared once for all its renders
    for name, key in (("prepare_quantized", "prepare"), ("render_quantized", "render")):
        def counted(self, *a, _f=getattr(ObjectTarget, name), _k=key, **kw):
            calls[_k] += 1
            return _f(self, *a, **kw)
        monkeypatch.setattr(ObjectTarget, name, counted)
    out = tmp_path / "run"
    cfg = config(sphere_ply, out, height_mm=3.6, dpi=200.0, iterations=2, eval_every=2, eval_spp=16,
                 eval_texels=1024, views=1)
    summary = optimize_print(cfg, **QUIET)
    # the evaluation's renders and the picture of each print, the final's view: 11 renders of 2 prepared prints
    from torch_appearance.print_error import EVAL_RENDERS
    assert calls == {"prepare": 2, "render": 2 * (EVAL_RENDERS + 1) + 1}
    monkeypatch.undo()
    n = summary["texels"]
    assert n > 1500 and summary["evaluation"]["texels"] == 1024
    rendered = [np.isfinite(np.load(out / f"{stem}.npy")).all(1) for stem in ("initial", "optimized")]
    assert rendered[0].sum() == 1024 and np.array_equal(rendered[0], rendered[1])
    for stem in ("final", "baseline"):
        assert np.isfinite(np.load(out / f"{stem}.npy")).all(), stem
    rows = list(csv.DictReader(open(out / "log.csv")))  # row 0's loss: the first iteration's, of the same state
    assert rows[0]["loss"] == rows[1]["loss"] != ""
    final = summary["final_quantized"]
    target = build_target(cfg.resolved(), log=lambda *_: None)
    target.use(InkSet.from_names(), cfg.resolved())
    indices = torch.as_tensor(load_index_volume(str(out / "quantized.npz"))[0])
    renders = torch.stack([target.render_quantized(indices, InkSet.from_names(), cfg.printer_dpi, 4, 900 + k)
                           for k in range(4)])
    whole = noise_free_error(renders, target.target)
    assert abs(final["dE00_mean"] - whole["dE00_mean"]) < 4 * np.hypot(final["dE00_mean_se"],
                                                                        whole["dE00_mean_se"]), (final, whole)
    # the whole population's SE has no sampling part: the subset's is larger
    assert final["dE00_mean_se"] > whole["dE00_mean_se"]
