"""One walk for the image and its gradient when the gradient is known before the render (``render_scene(...,
adjoint=A)``, ``_C.scene_forward_backward``; the print loop's ``ema`` estimator takes the loss's gradient at the
running mean of past renders, so from its second iteration on it knows the adjoint first).

The walk is the gradient replay's (``seed_grad``, the floored reference medium), so its gradients must be bitwise
those of the separate replay with the same adjoint, and its image bitwise the ratio-weighted forward of that floored
reference with seed ``seed_grad`` (on the scalar walk and on the SIMD slab walk alike): an unbiased estimator the
other tests already hold to physics and references. A backward with another gradient falls back to the replay.
"""
import numpy as np
import pytest
import torch

import torch_appearance as ta
import torch_appearance.autograd.volpath as volpath
from torch_appearance.geometry import sphere_sdf, torus_sdf
from torch_appearance.render import (DiscLight, PerspectiveCamera, Scene, SDFBoundary, SurfaceTexels, TraceJob)

N = 30
H = 0.05
ORIGIN = (-0.75, -0.75, -0.75)


def object_scene(kind, where):
    if kind == "sphere":
        sdf = sphere_sdf((N,) * 3, H, ORIGIN, (0.05, 0.0, -0.05), 0.55)
    else:
        sdf = torus_sdf((N,) * 3, H, ORIGIN, (0, 0, 0), 0.45, 0.18)
    if where == "texels":
        u = np.random.default_rng(2).normal(size=(30, 3))
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        centre = np.array((0.05, 0.0, -0.05)) if kind == "sphere" else np.zeros(3)
        radius = 0.55 if kind == "sphere" else 0.45
        return Scene(voxel_size=H, origin=ORIGIN, boundary=SDFBoundary(sdf, ior=1.5), g=0.3,
                     sensor=SurfaceTexels(torch.tensor(centre + radius * u), torch.tensor(u), footprint_mm=0.03))
    return Scene(voxel_size=H, origin=ORIGIN, boundary=SDFBoundary(sdf, ior=1.5), g=0.3,
                 sensor=PerspectiveCamera(origin=(1.5, 0.9, 1.8), target=(0, 0, 0), up=(0, 0, 1), fov_y_deg=35,
                                          resolution=(8, 8)),
                 emitter=DiscLight(direction=(0.2, 0.5, 1.0), angular_radius_deg=15.0, radiance=(3.0, 2.0, 2.5),
                                   ambient=(0.3, 0.2, 0.1)))


def medium(shape, seed, dtype=torch.float64, low_albedo=False):
    """Random per voxel (no two bricks alike: no homogeneous core), some albedos below the replay's floor."""
    gen = torch.Generator().manual_seed(seed)
    sigma_t = 3 + 15 * torch.rand((3, *shape), generator=gen, dtype=torch.float64)
    albedo = 0.6 + 0.399 * torch.rand((3, *shape), generator=gen, dtype=torch.float64)
    if low_albedo:
        albedo[:, ::3] *= 0.04  # below the 0.05 floor: the walk carries ratio weights there
    return sigma_t.to(dtype), albedo.to(dtype)


def adjoint_for(shape, seed, dtype, zeros=True):
    gen = torch.Generator().manual_seed(seed)
    a = torch.rand(shape, generator=gen, dtype=torch.float64) - 0.4
    if zeros:
        a[..., 1].reshape(-1)[::4] = 0  # some zeros: those walks still add to the image
    return a.to(dtype)


def both_ways(render, sigma_t, albedo, adjoint, **kw):
    """(image, grads, stats) of the one-walk render, the separate replay's gradients for the same adjoint, and the
    ratio-weighted forward of the floored reference with seed_grad."""
    s = sigma_t.clone().requires_grad_()
    a = albedo.clone().requires_grad_()
    stats = {}
    image = render(s, a, adjoint=adjoint, stats=stats, **kw)
    (adjoint * image).sum().backward()
    s2 = sigma_t.clone().requires_grad_()
    a2 = albedo.clone().requires_grad_()
    plain = render(s2, a2, **kw)
    gs, ga = torch.autograd.grad(plain, (s2, a2), adjoint)
    return image.detach(), (s.grad, a.grad), (gs, ga), stats


def floored_forward(scene, sigma_t, albedo, job, **kw):
    return ta.render_scene(scene, sigma_t, albedo, sampling_sigma_t=sigma_t.clamp_min(job.sigma_t_floor(
        sigma_t.shape)), sampling_albedo=albedo.clamp_min(job.albedo_floor), seed=job.seed_grad, **kw)


@pytest.mark.parametrize("kind,where", [("sphere", "texels"), ("torus", "camera")])
@pytest.mark.parametrize("chromatic", ["per_channel", "hero"])
def test_one_walk_gives_the_replays_gradients_and_the_floored_forward(kind, where, chromatic):
    scene = object_scene(kind, where)
    sigma_t, albedo = medium((N, N, N), 1, low_albedo=True)
    shape = scene.output_shape((N, N, N))
    adjoint = adjoint_for(shape, 2, torch.float64)
    kw = dict(spp=3, seed=5, chromatic=chromatic)
    image, (gs, ga), (gs_r, ga_r), stats = both_ways(
        lambda s, a, **k: ta.render_scene(scene, s, a, **k), sigma_t, albedo, adjoint, **kw)
    assert stats["with_adjoint"] and stats["backward_s"] == 0.0
    assert float(gs_r.abs().max()) > 0 and float(ga_r.abs().max()) > 0
    assert torch.equal(gs, gs_r) and torch.equal(ga, ga_r)
    job = TraceJob(scene, spp=3, seed=5, chromatic=chromatic)
    reference = floored_forward(scene, sigma_t, albedo, job, spp=3, chromatic=chromatic)
    assert float(image.abs().max()) > 0
    assert torch.equal(image, reference)


def test_one_walk_with_grad_support_and_a_core():
    """A print's case: a homogeneous core outside grad_support, which the replay crosses in bricks (exact up to
    rounding against the forward's own core walk)."""
    scene = object_scene("sphere", "texels")
    sigma_t, albedo = medium((N, N, N), 3)
    k, j, i = torch.meshgrid(*(torch.arange(N, dtype=torch.float64),) * 3, indexing="ij")
    r = (((i + 0.5) * H + ORIGIN[0] - 0.05) ** 2 + ((j + 0.5) * H + ORIGIN[1]) ** 2
         + ((k + 0.5) * H + ORIGIN[2] + 0.05) ** 2).sqrt()
    core = r < 0.3
    sigma_t[:, core] = torch.tensor([6.0, 9.0, 24.0], dtype=torch.float64).view(3, 1)
    albedo[:, core] = torch.tensor([0.9991, 0.9997, 0.999], dtype=torch.float64).view(3, 1)
    adjoint = adjoint_for((30, 3), 4, torch.float64)
    kw = dict(spp=4, seed=9, grad_support=~core)
    image, (gs, ga), (gs_r, ga_r), _ = both_ways(
        lambda s, a, **k: ta.render_scene(scene, s, a, **k), sigma_t, albedo, adjoint, **kw)
    assert torch.equal(gs, gs_r) and torch.equal(ga, ga_r)
    assert float(gs[:, core].abs().max()) == 0
    job = TraceJob(scene, spp=4, seed=9)
    torch.testing.assert_close(image, floored_forward(scene, sigma_t, albedo, job, spp=4), rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("face", ["top", "both"])
def test_one_walk_on_the_slab_walk(face):
    """float32 slabs take the SIMD slab walk where the CPU has one (the scalar walk otherwise): the same two
    equalities."""
    sigma_t, albedo = medium((6, 20, 18), 6, torch.float32, low_albedo=True)
    shape = (2, 20, 18, 3) if face == "both" else (20, 18, 3)
    kw = dict(voxel_size=0.08, face=face, spp=4, seed=11)
    # the SIMD walk deposits each path when its lane ends it, so the order of the additions follows the batch's
    # walks: with zeros in the adjoint the separate replay skips those walks (the one walk cannot: they add to the
    # image) and its sums are rounded in another order; without zeros the walks and their order are the same
    image, (gs, ga), (gs_r, ga_r), _ = both_ways(ta.render_texels, sigma_t, albedo,
                                                 adjoint_for(shape, 7, torch.float32, zeros=False), **kw)
    assert float(gs_r.abs().max()) > 0 and float(ga_r.abs().max()) > 0
    assert torch.equal(gs, gs_r) and torch.equal(ga, ga_r)
    _, (gs, ga), (gs_r, ga_r), _ = both_ways(ta.render_texels, sigma_t, albedo, adjoint_for(shape, 7, torch.float32),
                                             **kw)
    torch.testing.assert_close(gs, gs_r, rtol=1e-4, atol=1e-6)
    torch.testing.assert_close(ga, ga_r, rtol=1e-4, atol=1e-6)
    scene = Scene.slab(0.08, face=face)
    job = TraceJob(scene, spp=4, seed=11, seed_grad=11)
    reference = ta.render_texels(sigma_t, albedo, sampling_sigma_t=sigma_t.clamp_min(job.sigma_t_floor(
        sigma_t.shape)), sampling_albedo=albedo.clamp_min(job.albedo_floor), **kw)
    assert torch.equal(image, reference)


def test_another_gradient_is_replayed():
    scene = object_scene("sphere", "texels")
    sigma_t, albedo = medium((N, N, N), 8)
    adjoint = adjoint_for((30, 3), 9, torch.float64)
    s = sigma_t.clone().requires_grad_()
    stats = {}
    image = ta.render_scene(scene, s, albedo, spp=2, seed=1, adjoint=adjoint, stats=stats)
    (2.0 * adjoint * image).sum().backward()  # not the adjoint given: a replay
    assert stats["backward_s"] > 0
    s2 = sigma_t.clone().requires_grad_()
    (g,) = torch.autograd.grad(ta.render_scene(scene, s2, albedo, spp=2, seed=1), (s2,), adjoint)
    assert torch.equal(s.grad, 2.0 * g)


def test_without_grad_the_adjoint_is_ignored():
    scene = object_scene("sphere", "texels")
    sigma_t, albedo = medium((N, N, N), 10)
    adjoint = adjoint_for((30, 3), 1, torch.float64)
    a = ta.render_scene(scene, sigma_t, albedo, spp=2, seed=3, adjoint=adjoint)
    assert torch.equal(a, ta.render_scene(scene, sigma_t, albedo, spp=2, seed=3))


def test_adjoint_is_checked():
    scene = object_scene("sphere", "texels")
    sigma_t, albedo = medium((N, N, N), 10)
    s = sigma_t.requires_grad_()
    with pytest.raises(ValueError, match=r"adjoint: expected the image's shape \(30, 3\), got \(29, 3\)"):
        ta.render_scene(scene, s, albedo, spp=1, adjoint=torch.zeros(29, 3, dtype=torch.float64))
    with pytest.raises(TypeError, match="adjoint: expected a tensor"):
        ta.render_scene(scene, s, albedo, spp=1, adjoint=np.zeros((30, 3)))
    with pytest.raises(ValueError, match="adjoint: expected finite values"):
        ta.render_scene(scene, s, albedo, spp=1, adjoint=torch.full((30, 3), float("nan"), dtype=torch.float64))


def test_print_loop_walks_once_from_its_second_iteration(tmp_path, monkeypatch):
    """The ema estimator (the default) knows its adjoint before the render from the second iteration on."""
    from torch_appearance import io as ta_io
    from torch_appearance.pipelines.print import PrintConfig, optimize_print
    img = np.zeros((6, 6, 3), np.float32)
    img[:, :3] = (0.5, 0.1, 0.05)
    img[:, 3:] = (0.05, 0.2, 0.5)
    ta_io.write_exr(str(tmp_path / "t.exr"), img)
    calls = []
    real = volpath.call_tracer

    def spy(fn, *args):
        calls.append(fn.__name__)
        return real(fn, *args)

    monkeypatch.setattr(volpath, "call_tracer", spy)
    optimize_print(PrintConfig(target=str(tmp_path / "t.exr"), thickness_mm=0.17, spp=2, eval_spp=4, eval_every=10,
                               iterations=4, table_steps=1, out=str(tmp_path / "run")), progress=False,
                   log=lambda *_: None)
    # iterations 1 to 3 (no probe render: the seconds per iteration are timed on the run's own iterations);
    # iteration 0's adjoint needs its own render, so it alone replays
    assert calls.count("scene_forward_backward") == 3
    assert calls.count("scene_backward") == 1


def test_a_second_backward_gets_the_same_gradients():
    """retain_graph: the deposited gradients serve every backward with the adjoint, not only the first."""
    scene = object_scene("sphere", "texels")
    sigma_t, albedo = medium((N, N, N), 11)
    adjoint = adjoint_for((30, 3), 12, torch.float64)
    s = sigma_t.clone().requires_grad_()
    surrogate = (adjoint * ta.render_scene(scene, s, albedo, spp=2, seed=4, adjoint=adjoint)).sum()
    (first,) = torch.autograd.grad(surrogate, (s,), retain_graph=True)
    (second,) = torch.autograd.grad(surrogate, (s,))
    assert float(first.abs().max()) > 0
    assert torch.equal(first, second)
