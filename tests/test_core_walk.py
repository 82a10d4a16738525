"""The homogeneous core walk (core::Medium::core, csrc/core/integrator.h): inside an object, bricks of 4³ voxels that
all hold one value tuple (a print's fixed core ink) are crossed in one move per flight, and their collisions read
the core's values without touching the grids; in a gradient replay that is told which voxels' gradients are wanted
(``grad_support``), the core outside them carries no gradient bookkeeping.

The shortcut is exact: a flight through a homogeneous box samples the same collision as the voxel-by-voxel walk
(the optical depth σ·ℓ summed in one piece instead of per voxel), with the same random numbers. So the images and
the gradients inside ``grad_support`` must agree with the exact walk to float64 rounding, for every estimator that
takes the shortcut (per channel, hero, ratio-weighted), with and without a dielectric boundary, seen by surface
texels and by a camera.
"""
import numpy as np
import pytest
import torch

import torch_appearance as ta
from torch_appearance import _C
from torch_appearance.geometry import sphere_sdf
from torch_appearance.render import OrthographicCamera, Scene, SDFBoundary, SurfaceTexels

N = 44                    # voxels per axis
H = 0.05                  # mm
ORIGIN = (-1.1, -1.1, -1.1)
RADIUS = 0.95             # mm
SHELL = 0.25              # mm: the heterogeneous shell; the core inside it holds one ink
CORE = (torch.tensor([6.0, 9.0, 24.0]), torch.tensor([0.9991, 0.9997, 0.999]))  # the library's white ink


def centres():
    c = (torch.arange(N, dtype=torch.float64) + 0.5) * H + ORIGIN[0]
    z, y, x = torch.meshgrid(c, c, c, indexing="ij")
    return (x ** 2 + y ** 2 + z ** 2).sqrt()


def medium(seed=0, dtype=torch.float64):
    """A random ink in the shell (depth < SHELL), white in the core; (σ_t, albedo, shell mask)."""
    gen = torch.Generator().manual_seed(seed)
    shell = centres() > RADIUS - SHELL
    sigma_t = 3 + 20 * torch.rand((3, N, N, N), generator=gen, dtype=torch.float64)
    albedo = 0.8 + 0.199 * torch.rand((3, N, N, N), generator=gen, dtype=torch.float64)
    sigma_t = torch.where(shell, sigma_t, CORE[0].double().view(3, 1, 1, 1))
    albedo = torch.where(shell, albedo, CORE[1].double().view(3, 1, 1, 1))
    return sigma_t.to(dtype), albedo.to(dtype), shell


def scene(sensor, ior=1.5, g=0.4):
    sdf = sphere_sdf((N,) * 3, H, ORIGIN, (0, 0, 0), RADIUS)
    if sensor == "texels":
        u = np.random.default_rng(5).normal(size=(24, 3))
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        sensor = SurfaceTexels(torch.tensor(RADIUS * u), torch.tensor(u), footprint_mm=0.05)
    else:
        sensor = OrthographicCamera(origin=(0.05, 0.02, 3.0), target=(0, 0, 0), up=(0, 1, 0), extent_mm=(2.0, 2.0),
                                    resolution=(6, 6))
    return Scene(voxel_size=H, origin=ORIGIN, boundary=SDFBoundary(sdf, ior=ior), sensor=sensor, g=g)


def with_core(on, fn):
    previous = _C._set_core_walk(on)
    try:
        return fn()
    finally:
        _C._set_core_walk(previous)


@pytest.mark.parametrize("sensor", ["texels", "camera"])
@pytest.mark.parametrize("ior", [None, 1.5])
@pytest.mark.parametrize("chromatic", ["per_channel", "hero"])
def test_forward_equals_the_exact_walk(sensor, ior, chromatic):
    sigma_t, albedo, _ = medium()
    sc = scene(sensor, ior)
    out = {}
    for on in (False, True):
        stats = {}
        image = with_core(on, lambda: ta.render_scene(sc, sigma_t, albedo, spp=4, seed=3, stats=stats,
                                                      chromatic=chromatic))
        out[on] = image, stats
    (i0, s0), (i1, s1) = out[False], out[True]
    assert s0["core_events"] == 0
    assert s1["core_events"] > 0.05 * s1["scatter_events"], (s1["core_events"], s1["scatter_events"])  # exercised
    assert s1["scatter_events"] == s0["scatter_events"]  # the same paths
    assert s1["voxel_steps"] < s0["voxel_steps"]          # crossed in fewer moves
    torch.testing.assert_close(i1, i0, rtol=1e-9, atol=1e-12)


def test_ratio_weighted_forward_equals_the_exact_walk():
    """An explicit sampling medium that differs in the shell (ratio weights there) and equals the core."""
    sigma_t, albedo, shell = medium()
    ref_s = torch.where(shell, sigma_t * 1.3 + 1, sigma_t)
    ref_a = torch.where(shell, (albedo * 0.97).clamp(max=1), albedo)
    sc = scene("texels")
    images, core_events = [], []
    for on in (False, True):
        stats = {}
        images.append(with_core(on, lambda: ta.render_scene(sc, sigma_t, albedo, spp=4, seed=9, stats=stats,
                                                            sampling_sigma_t=ref_s, sampling_albedo=ref_a)))
        core_events.append(stats["core_events"])
    assert core_events[0] == 0 and core_events[1] > 0
    torch.testing.assert_close(images[1], images[0], rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("sensor", ["texels", "camera"])
@pytest.mark.parametrize("chromatic", ["per_channel", "hero"])
def test_replay_with_grad_support_equals_the_exact_replay_there(sensor, chromatic):
    """The gradients inside grad_support equal the exact replay's (which walks the core voxel by voxel and deposits
    everywhere); outside they are 0. The support is the shell and a ball of core ink at the centre, whose voxels
    hold the core's values but must keep their gradients."""
    sigma_t, albedo, shell = medium(1)
    support = shell | (centres() < 0.35)
    sc = scene(sensor)

    def grads(support, on):
        s = sigma_t.clone().requires_grad_()
        a = albedo.clone().requires_grad_()
        image = with_core(on, lambda: ta.render_scene(sc, s, a, spp=16, seed=5, chromatic=chromatic,
                                                      grad_support=support))
        weights = torch.rand(image.shape, generator=torch.Generator().manual_seed(2), dtype=image.dtype)
        with_core(on, lambda: (image * weights).sum().backward())
        return image.detach(), s.grad, a.grad

    i0, gs0, ga0 = grads(None, False)
    i1, gs1, ga1 = grads(support, True)
    torch.testing.assert_close(i1, i0, rtol=1e-9, atol=1e-12)
    assert float(gs0[:, ~support].abs().max()) > 0  # the exact replay has core gradients, which grad_support drops
    assert float(gs1[:, ~support].abs().max()) == 0 and float(ga1[:, ~support].abs().max()) == 0
    inner = support & ~shell
    assert float(gs0[:, inner].abs().max()) > 0  # the centre ball is reached and has gradients to keep
    torch.testing.assert_close(gs1[:, support], gs0[:, support], rtol=1e-9, atol=1e-12)
    torch.testing.assert_close(ga1[:, support], ga0[:, support], rtol=1e-9, atol=1e-12)


def test_float32_forward_agrees():
    sigma_t, albedo, _ = medium(2, torch.float32)
    sc = scene("texels")
    images = [with_core(on, lambda: ta.render_scene(sc, sigma_t, albedo, spp=8, seed=1)) for on in (False, True)]
    torch.testing.assert_close(images[1], images[0], rtol=1e-4, atol=1e-5)


def test_no_core_without_a_common_tuple():
    """A medium with no two equal bricks has no core: the walk is the exact one, bit for bit."""
    gen = torch.Generator().manual_seed(4)
    sigma_t = 3 + 20 * torch.rand((3, N, N, N), generator=gen, dtype=torch.float64)
    albedo = 0.8 + 0.199 * torch.rand((3, N, N, N), generator=gen, dtype=torch.float64)
    sc = scene("texels")
    stats = {}
    a = with_core(True, lambda: ta.render_scene(sc, sigma_t, albedo, spp=2, seed=1, stats=stats))
    b = with_core(False, lambda: ta.render_scene(sc, sigma_t, albedo, spp=2, seed=1))
    assert stats["core_events"] == 0
    assert torch.equal(a, b)


def test_grad_support_is_checked():
    sigma_t, albedo, shell = medium()
    sc = scene("texels")
    with pytest.raises(ValueError, match="grad_support: expected the grid's shape"):
        ta.render_scene(sc, sigma_t, albedo, spp=1, grad_support=shell[:-1])
    with pytest.raises(ValueError, match="grad_support: expected a CPU or CUDA bool tensor"):
        ta.render_scene(sc, sigma_t, albedo, spp=1, grad_support=shell.float())
    with pytest.raises(TypeError, match="grad_support: expected a bool tensor"):
        ta.render_scene(sc, sigma_t, albedo, spp=1, grad_support=shell.numpy())
