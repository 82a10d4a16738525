"""Memory of the object pipeline (issue 13: Spot at 40 mm within 8 GB). Each saving keeps the results exact:
quantisation, void marking, the printer-resolution medium and the naive extrusion's matching work in chunks; the
quantised volume renders as a palette medium (uint8 index + ink table) bitwise like the dense one; the replay's
sampling floors are applied inside the tracer bitwise like the floored copies; an unconstrained mixture skips its
masking with the same weights and gradients."""
import math
import tracemalloc

import numpy as np
import pytest
import torch
import trimesh

from torch_appearance.fabrication import InkSet, quantize_mixture
from torch_appearance.fabrication.export import VOID
from torch_appearance.geometry import voxelize
from torch_appearance.pipelines.print import ObjectTarget, object_target


def test_quantize_holds_no_float64_copy_of_the_volume():
    """tracemalloc (numpy allocations): the peak stays below the uint8 result plus a small part of one float64
    copy of the weights; the whole-volume cumulative sum held 2–3 such copies."""
    rng = np.random.default_rng(0)
    w = rng.random((5, 40, 48, 48)).astype(np.float32)
    w /= w.sum(0)
    voxel = 25.4 / 300
    tracemalloc.start()
    try:
        out = quantize_mixture(w, voxel, seed=3)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    float64_copy = w.size * 8
    assert peak < out.nbytes + 0.25 * float64_copy, (peak, out.nbytes, float64_copy)
    # the same draws as the whole-volume computation: thresholds from the float64 cumulative sum of each voxel
    cdf = np.cumsum(w.astype(np.float64), axis=0)
    cdf = cdf[:-1] / cdf[-1:]
    from torch_appearance.fabrication.quantize import micro_grid_shape, source_index
    dz, hy, wx = micro_grid_shape(w.shape[1:], voxel)
    u = np.random.Generator(np.random.PCG64(3)).random((dz, hy, wx))
    iz, iy, ix = source_index(40, dz), source_index(48, hy), source_index(48, wx)
    thresholds = cdf[:, iz[:, None, None], iy[None, :, None], ix[None, None, :]]
    assert np.array_equal(out, (u[None] >= thresholds).sum(0).astype(np.uint8))


@pytest.fixture(scope="module")
def sphere_target():
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    mesh.visual.vertex_colors = np.tile([200, 120, 60, 255], (len(mesh.vertices), 1))
    obj = voxelize(mesh, 0.12, shell_mm=0.4)
    return ObjectTarget(obj, ior=1.5, g=0.4)


def test_chunked_void_and_medium_equal_the_whole_volume(sphere_target, monkeypatch):
    """quantized_void, fill_void_at_surface and quantized_medium in chunks of one micro layer give bitwise the
    whole-volume computation (the trilinear SDF at the micro-voxel centres; the ink table looked up per voxel)."""
    target, inks = sphere_target, InkSet.from_names()
    rng = np.random.default_rng(1)
    dz, hy, wx = 13, 9, 10
    indices = rng.integers(0, len(inks), size=(dz, hy, wx)).astype(np.uint8)
    monkeypatch.setattr(object_target, "_CHUNK", 1)  # one micro layer (at least) per chunk
    void = target.quantized_void(indices)
    sdf = target.micro_sdf((dz, hy, wx))
    centre = (sdf[:-1, :-1, :-1] + sdf[1:, 1:, 1:] + sdf[1:, :-1, :-1] + sdf[:-1, 1:, :-1] + sdf[:-1, :-1, 1:]
              + sdf[1:, 1:, :-1] + sdf[1:, :-1, 1:] + sdf[:-1, 1:, 1:]) / 8
    want = np.where(centre.numpy() > 0, VOID, indices)
    assert np.array_equal(void, want) and 0 < int((void == VOID).sum()) < void.size
    sigma_t, albedo, _, _ = target.quantized_medium(void, inks, (600, 300, 940))
    filled = object_target.fill_void_at_surface(void, sdf)              # straddling VOID voxels take an ink
    monkeypatch.setattr(object_target, "_CHUNK", 1 << 30)
    assert np.array_equal(filled, object_target.fill_void_at_surface(void, sdf))
    assert 0 < int((filled == VOID).sum()) < int((void == VOID).sum())
    idx = torch.as_tensor(np.where(filled == VOID, 0, filled).astype(np.int64)).reshape(-1)
    assert torch.equal(sigma_t, inks.sigma_t(torch.float32).index_select(0, idx).t().reshape(3, dz, hy, wx))
    assert torch.equal(albedo, inks.albedo(torch.float32).index_select(0, idx).t().reshape(3, dz, hy, wx))


def _palette_scene(target):
    from torch_appearance.render import Scene, SDFBoundary
    obj = target.obj
    return Scene(voxel_size=obj.voxel_size, origin=obj.origin, boundary=SDFBoundary(obj.sdf.float(), ior=1.5),
                 sensor=target.scene.sensor, g=0.4)


@pytest.mark.parametrize("grey", [False, True])
def test_palette_medium_renders_the_dense_medium_bitwise(sphere_target, grey):
    """render_scene_indexed (uint8 index + ink table) gives bitwise the image of render_scene on the dense grids
    table[index], whole and as partition shares; chromatic (one walk per channel) and grey (one walk for all)."""
    from torch_appearance.render import render_scene, render_scene_indexed
    target = sphere_target
    scene = _palette_scene(target)
    d, h, w = target.shape
    rng = np.random.default_rng(2)
    table_s = torch.tensor(rng.uniform(2.0, 20.0, size=(4, 3)), dtype=torch.float32)
    table_a = torch.tensor(rng.uniform(0.5, 0.99, size=(4, 3)), dtype=torch.float32)
    if grey:
        table_s[:] = table_s[:, :1]
    index = torch.from_numpy(rng.integers(0, 3, size=(d, h, w)).astype(np.uint8))  # entry 3 unused
    dense_s = table_s[index.long()].permute(3, 0, 1, 2).contiguous()
    dense_a = table_a[index.long()].permute(3, 0, 1, 2).contiguous()
    want = render_scene(scene, dense_s, dense_a, spp=2, seed=7)
    got = render_scene_indexed(scene, index, table_s, table_a, spp=2, seed=7)
    assert got.dtype == torch.float32 and torch.equal(got, want) and float(want.mean()) > 0.05
    shares = [render_scene_indexed(scene, index.numpy(), table_s, table_a, spp=2, seed=7, partition=(r, 2))
              for r in range(2)]
    assert torch.equal(shares[0] + shares[1], want)


def test_palette_medium_refusals(sphere_target):
    from torch_appearance.render import render_scene_indexed
    scene = _palette_scene(sphere_target)
    index = torch.zeros(sphere_target.shape, dtype=torch.uint8)
    table = torch.full((2, 3), 5.0)
    with pytest.raises(ValueError, match=r"index: expected entries < P = 2"):
        render_scene_indexed(scene, index + 2, table, table.clamp(max=1))
    with pytest.raises(TypeError, match=r"index: expected a \(D, H, W\) uint8"):
        render_scene_indexed(scene, index.long(), table, table.clamp(max=1))
    with pytest.raises(ValueError, match=r"sigma_t_table: expected shape \(P, 3\)"):
        render_scene_indexed(scene, index, table.t(), table.clamp(max=1))
    with pytest.raises(ValueError, match=r"albedo_table: expected finite values in \[0, 1"):
        render_scene_indexed(scene, index, table, table)
    with pytest.raises(ValueError, match=r"sdf: expected shape"):
        render_scene_indexed(scene, index[:-1], table, table.clamp(max=1))


def test_quantized_render_equals_the_dense_medium(sphere_target):
    """ObjectTarget.render_quantized (palette medium) gives bitwise the image of the dense quantised medium."""
    from torch_appearance.render import Scene, SDFBoundary, render_scene
    target, inks = sphere_target, InkSet.from_names()
    dpi = (600, 300, 940)
    from torch_appearance.fabrication.quantize import micro_grid_shape
    shape = micro_grid_shape(target.shape, target.obj.voxel_size, dpi)
    rng = np.random.default_rng(4)
    indices = target.quantized_void(rng.integers(0, len(inks), size=shape).astype(np.uint8))
    got = target.render_quantized(indices, inks, dpi, spp=1, seed=3)
    sigma_t, albedo, edges, sdf = target.quantized_medium(indices, inks, dpi)
    scene = Scene(voxel_size=edges, origin=target.obj.origin, boundary=SDFBoundary(sdf, ior=target.ior),
                  sensor=target.scene.sensor, emitter=target.emitter, g=target.g)
    assert torch.equal(got, render_scene(scene, sigma_t, albedo, spp=1, seed=3))


def test_prepared_print_renders_the_same_image(sphere_target):
    """A print prepared once (ObjectTarget.prepare_quantized) renders bitwise what its raw indices render, for the
    texels and a camera; the caller's indices stay untouched; a print prepared for another resolution is refused."""
    from torch_appearance.fabrication.quantize import micro_grid_shape
    target, inks = sphere_target, InkSet.from_names()
    dpi = (600, 300, 940)
    shape = micro_grid_shape(target.shape, target.obj.voxel_size, dpi)
    rng = np.random.default_rng(7)
    indices = target.quantized_void(rng.integers(0, len(inks), size=shape).astype(np.uint8))
    before = indices.copy()
    prepared = target.prepare_quantized(indices, dpi)
    assert np.array_equal(indices, before)
    assert (prepared.index.numpy() != 255).all()
    for seed in (3, 4):
        assert torch.equal(target.render_quantized(prepared, inks, dpi, spp=1, seed=seed),
                           target.render_quantized(indices, inks, dpi, spp=1, seed=seed))
    cam = target.camera_views(1, size=8)[0]
    assert torch.equal(target.render_quantized(prepared, inks, dpi, 1, 5, sensor=cam),
                       target.render_quantized(indices, inks, dpi, 1, 5, sensor=cam))
    with pytest.raises(ValueError, match=r"printer_dpi: the prepared print is for"):
        target.render_quantized(prepared, inks, (300, 300, 940), spp=1, seed=3)
    with pytest.raises(ValueError, match=r"indices: expected a \(Dz, Hy, Wx\) uint8"):
        target.prepare_quantized(indices.astype(np.int32), dpi)


def _floor_case(scene_kind):
    g = torch.Generator().manual_seed(5)
    if scene_kind == "slab":
        shape = (3, 5, 7, 6)
    else:
        shape = (3, 8, 8, 8)
    sigma_t = (0.02 + 12.0 * torch.rand(shape, generator=g) ** 3).requires_grad_()  # many voxels below the floor
    albedo = (0.01 + 0.98 * torch.rand(shape, generator=g) ** 2).requires_grad_()   # and below 0.05
    return sigma_t, albedo


@pytest.mark.parametrize("kind", ["slab", "scene"])
def test_replay_floors_on_the_fly_equal_the_floored_copies(kind):
    """The replay's default sampling medium (σ_t and albedo floored inside the tracer, no copies of the grids)
    gives bitwise the gradients of the same floors passed as explicit sampling grids (clamp_min copies)."""
    import torch_appearance as ta
    from torch_appearance.render import Scene, SDFBoundary, SurfaceTexels
    from torch_appearance.render.scene import default_sigma_t_floor
    sigma_t, albedo = _floor_case(kind)
    if kind == "slab":
        def render(**k):
            return ta.render_texels(sigma_t, albedo, voxel_size=0.1, spp=3, seed=4, seed_grad=9, face="both", **k)
        slab = Scene.slab(0.1)
        settings, edges = slab.settings, slab.voxel_size
    else:
        k, j, i = torch.meshgrid(*(torch.arange(9.0),) * 3, indexing="ij")
        sdf = ((i - 4) ** 2 + (j - 4) ** 2 + (k - 4) ** 2).sqrt() * 0.1 - 0.33
        pts = torch.tensor([[0.0, 0.0, 0.3], [0.3, 0.0, 0.0], [0.0, -0.3, 0.0]], dtype=torch.float64)
        scene = Scene(voxel_size=0.1, origin=(-0.4, -0.4, -0.4), boundary=SDFBoundary(sdf, ior=1.5),
                      sensor=SurfaceTexels(pts, pts / 0.3, footprint_mm=0.05), g=0.4)

        def render(**k):
            return ta.render_scene(scene, sigma_t, albedo, spp=4, seed=4, seed_grad=9, **k)
        settings, edges = scene.settings, scene.voxel_size
    floor = default_sigma_t_floor(settings, edges, sigma_t.shape)
    assert float((sigma_t < floor).float().mean()) > 0.1 and float((albedo < settings.albedo_floor).float().mean()) > 0.1
    grads = []
    for explicit in (False, True):
        extra = dict(sampling_sigma_t=sigma_t.detach().clamp_min(floor),
                     sampling_albedo=albedo.detach().clamp_min(settings.albedo_floor)) if explicit else {}
        image = render(**extra)
        w = torch.linspace(0.5, 1.5, image.numel()).view_as(image)
        gs, ga = torch.autograd.grad((image * w).sum(), (sigma_t, albedo))
        grads.append((gs, ga))
    assert float(grads[0][0].abs().max()) > 0 and float(grads[0][1].abs().max()) > 0
    assert torch.equal(grads[0][0], grads[1][0]) and torch.equal(grads[0][1], grads[1][1])


@pytest.mark.parametrize("parameterization", ["sigmoid", "softmax"])
def test_unconstrained_mixture_equals_the_constrained_path(parameterization):
    """Without fixed fractions the mixture skips its masking (and its temporaries): the same weights and
    gradients, bitwise, as with a constraint whose mask is empty (which takes the masked path)."""
    from torch_appearance.nn import FixedFraction, MaterialMixture
    shape = (4, 5, 6)
    support = torch.rand(shape, generator=torch.Generator().manual_seed(1)) < 0.6
    outs = []
    for fixed in ((), (FixedFraction(torch.zeros(shape, dtype=torch.bool), "white", 0.5),)):
        m = MaterialMixture(InkSet.from_names(), shape, parameterization=parameterization, support=support,
                            fixed=fixed)
        with torch.no_grad():
            m.logits.copy_(torch.randn(m.logits.shape, generator=torch.Generator().manual_seed(2)) * 3)
        sigma_t, albedo = m()
        (sigma_t.sum() * 0.01 + (albedo ** 2).sum()).backward()
        outs.append((m.weights().detach(), m.logits.grad))
    assert torch.equal(outs[0][0], outs[1][0]) and torch.equal(outs[0][1], outs[1][1])


@pytest.mark.parametrize("grey", [True, False])
def test_naive_extrusion_matches_in_blocks(grey, monkeypatch):
    """The naive extrusion's table matching in blocks of texels picks the same mixtures as over all texels."""
    from torch_appearance.pipelines.print import PrintConfig
    from torch_appearance.pipelines.print import baselines
    rng = np.random.default_rng(6)
    target = rng.uniform(0.05, 0.9, size=(5, 7, 3)).astype(np.float32)
    if grey:
        target[:] = target[..., :1]
    cfg = PrintConfig(thickness_mm=0.3, dpi=150.0, table_steps=2, inks=["cyan", "black", "white"])
    inks = InkSet.from_names(cfg.inks)
    whole, _ = baselines.naive_extrusion(target, inks, cfg, table_spp=2)
    monkeypatch.setattr(baselines, "_MATCH_BLOCK", 4)
    blocks, _ = baselines.naive_extrusion(target, inks, cfg, table_spp=2)
    assert torch.equal(whole, blocks) and torch.unique(whole.flatten(1), dim=1).shape[1] > 2  # several mixtures


def test_all_finite_in_chunks():
    from torch_appearance.checks import all_finite
    x = torch.rand(4, 5, 6)
    assert all_finite(x, chunk=7)
    for where, bad in ((0, math.nan), (-1, math.inf), (57, -math.inf)):
        y = x.clone().reshape(-1)
        y[where] = bad
        assert not all_finite(y.view(4, 5, 6), chunk=7)


def test_replay_thread_buffers_follow_the_paths_not_the_grid():
    """With two threads the replay's second thread deposits into its own gradient buffers. They come zeroed from
    calloc, so pages that no path touches are never resident: a small object in a large grid adds the two gradient
    outputs to the peak memory, not two more grid-sized buffers (Spot at 40 mm: 1.4 GB). (Where the allocator maps
    large blocks fresh, as glibc does above 32 MB.)"""
    import torch_appearance as ta
    from torch_appearance.render import Scene, SDFBoundary, SurfaceTexels
    from torch_appearance.testing import reset_peak_rss, status_kb
    if status_kb("VmHWM") is None or not reset_peak_rss():
        pytest.skip("needs /proc/self/status and a resettable peak (clear_refs)")
    # 0.1 mm voxels, 50 MB per grid (glibc maps blocks above 32 MB fresh from the kernel); a sphere of radius
    # 0.4 mm near one corner
    d, h, w = 64, 256, 256
    k, j, i = torch.meshgrid(torch.arange(d + 1.0), torch.arange(h + 1.0), torch.arange(w + 1.0), indexing="ij")
    sdf = (((i - 6) ** 2 + (j - 6) ** 2 + (k - 6) ** 2).sqrt() * 0.1 - 0.4).to(torch.float32)
    n = torch.randn(64, 3, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    n = n / n.norm(dim=1, keepdim=True)
    scene = Scene(voxel_size=0.1, origin=(-0.6, -0.6, -0.6), boundary=SDFBoundary(sdf, ior=1.5),
                  sensor=SurfaceTexels(0.4 * n, n, footprint_mm=0.03), g=0.4)
    sigma_t = torch.full((3, d, h, w), 8.0).requires_grad_()
    albedo = torch.full((3, d, h, w), 0.9).requires_grad_()
    grid_mb = sigma_t.numel() * 4 / 2 ** 20
    threads = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        image = ta.render_scene(scene, sigma_t, albedo, spp=2, seed=1)
        loss = image.sum()
        assert reset_peak_rss()
        before = status_kb("VmRSS")
        gs, ga = torch.autograd.grad(loss, (sigma_t, albedo))
        growth = (status_kb("VmHWM") - before) / 1024.0
    finally:
        torch.set_num_threads(threads)
    assert float(gs.abs().sum()) > 0 and float(ga.abs().sum()) > 0
    # the two outputs (2 grids) and a little; dense buffers of the second thread would add two more grids
    assert growth < 2.6 * grid_mb, f"backward peak grew by {growth:.0f} MB for {grid_mb:.0f} MB grids"
