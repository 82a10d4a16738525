"""Path-replay gradients of general scenes: gradcheck with an explicit reference (each boundary, sensor and emitter),
and unbiasedness of the default gradient (floored replay, separate gradient seed) against finite differences."""
import pytest
import torch

import torch_appearance as ta
from torch_appearance.geometry import sphere_sdf
from torch_appearance.render import (BoxBoundary, ConstantEnvironment, DiscLight, EnvironmentMap, OrthographicCamera,
                                     PerspectiveCamera, Scene, SDFBoundary, SurfaceTexels)

from torch_appearance.testing import assert_z, seed_stats

N, H = 4, 0.1
ORIGIN = (-0.2, -0.2, -0.2)


def medium(seed=0, chromatic=True, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    n = 3 if chromatic else 1
    sigma = (torch.rand(n, N, N, N, generator=g, dtype=dtype) * 15 + 2).expand(3, N, N, N).contiguous()
    albedo = torch.rand(3, N, N, N, generator=g, dtype=dtype) * 0.85 + 0.1
    return sigma, albedo


def envmap():
    g = torch.Generator().manual_seed(7)
    return EnvironmentMap(torch.rand(6, 12, 3, generator=g, dtype=torch.float64) * 2)


SPHERE = sphere_sdf((N,) * 3, H, ORIGIN, (0.01, -0.02, 0.0), 0.17)


def sensor(kind):
    if kind == "texels":
        pts = torch.tensor([[0.0, 0.0, 0.17], [0.17, 0.0, 0.0], [0.0, -0.12, -0.12]], dtype=torch.float64)
        return SurfaceTexels(pts, pts / pts.norm(dim=1, keepdim=True), footprint_mm=0.04)
    if kind == "ortho":
        return OrthographicCamera(origin=(0.05, 0.02, 1.0), target=(0, 0, 0), up=(0, 1, 0), extent_mm=(0.4, 0.4),
                                  resolution=(3, 3))
    return PerspectiveCamera(origin=(0.6, 0.4, 0.5), target=(0, 0, 0), up=(0, 0, 1), fov_y_deg=30,
                             resolution=(3, 3))


CASES = {
    "sdf-dielectric-texels-constant": (SDFBoundary(SPHERE, ior=1.5), "texels", ConstantEnvironment((1.0, 0.8, 0.6))),
    "sdf-matched-ortho-envmap": (SDFBoundary(SPHERE, ior=None), "ortho", envmap()),
    "sdf-dielectric-persp-disc": (SDFBoundary(SPHERE, ior=1.5), "persp", DiscLight((1, 1, 2), 50, 3.0, 0.2)),
    "box-dielectric-persp-envmap": (BoxBoundary(1.5), "persp", envmap()),
    "box-matched-ortho-disc": (BoxBoundary(None), "ortho", DiscLight((0, 0, 1), 30, (2.0, 1.0, 0.5), 0.1)),
}


@pytest.mark.parametrize("case", sorted(CASES))
@pytest.mark.parametrize("chromatic", [True, False], ids=["chromatic", "achromatic"])
def test_gradcheck_explicit_reference(case, chromatic):
    """Fixed seed, explicit sampling medium and seed_grad = seed: the image is a smooth function of σ_t and albedo
    and the backward is its derivative."""
    boundary, kind, emitter = CASES[case]
    scene = Scene(voxel_size=H, origin=ORIGIN, boundary=boundary, sensor=sensor(kind), emitter=emitter, g=0.3,
                  rr_depth=2)
    sigma, albedo = medium(1, chromatic)
    ref_s = (sigma * 1.2).detach()
    ref_a = (albedo * 0.9 + 0.05).detach()

    def f(s, a):
        return ta.render_scene(scene, s, a, spp=8, seed=11, seed_grad=11, sampling_sigma_t=ref_s,
                               sampling_albedo=ref_a)

    out = f(sigma, albedo)
    assert float(out.std()) > 0  # the image depends on the medium
    inputs = (sigma.clone().requires_grad_(), albedo.clone().requires_grad_())
    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-7, rtol=1e-4)


def test_seed_grad_changes_only_the_replay():
    """The forward image depends on seed only; the gradient on seed_grad (default derived from seed)."""
    boundary, kind, emitter = CASES["sdf-dielectric-persp-disc"]
    scene = Scene(voxel_size=H, origin=ORIGIN, boundary=boundary, sensor=sensor(kind), emitter=emitter)
    sigma, albedo = medium(2)

    def run(**kw):
        s = sigma.clone().requires_grad_()
        img = ta.render_scene(scene, s, albedo, spp=4, **kw)
        img.sum().backward()
        return img.detach(), s.grad

    i1, g1 = run(seed=3)
    i2, g2 = run(seed=3, seed_grad=ta.render.derive_seed_grad(3))
    i3, g3 = run(seed=3, seed_grad=99)
    i4, g4 = run(seed=3, seed_grad=99)
    assert torch.equal(i1, i2) and torch.equal(g1, g2)
    assert torch.equal(i1, i3) and not torch.equal(g1, g3)
    assert torch.equal(g3, g4)


@pytest.mark.slow
@pytest.mark.parametrize("case", ["sdf-dielectric-persp-disc", "sdf-dielectric-texels-constant"])
def test_default_gradient_unbiased_against_finite_differences(case):
    """Mean over seeds of the default gradient (detached sampling, floored replay, derived seed_grad) equals the
    central finite difference of the expectation (common random numbers, explicit reference)."""
    boundary, kind, emitter = CASES[case]
    scene = Scene(voxel_size=H, origin=ORIGIN, boundary=boundary, sensor=sensor(kind), emitter=emitter, g=0.4)
    sigma, albedo = medium(3)
    out_shape = scene.output_shape((N, N, N))
    weights = torch.rand(out_shape, generator=torch.Generator().manual_seed(5), dtype=torch.float64)

    def grad(seed):
        s, a = sigma.clone().requires_grad_(), albedo.clone().requires_grad_()
        (ta.render_scene(scene, s, a, spp=256, seed=seed) * weights).sum().backward()
        return torch.cat([s.grad.flatten(), a.grad.flatten()])

    g_mean, g_se = seed_stats(grad, range(24))
    n = sigma.numel()
    # voxels near the sphere's centre (inside the object), σ_t and albedo, all channels
    centre = [(c * N + k) * N * N + j * N + i for c in range(3) for (k, j, i) in [(1, 1, 2), (2, 2, 1), (2, 1, 2)]]
    entries = centre[:5] + [n + e for e in centre[4:]]
    h = 1e-4

    def fd(seed):
        out = []
        for e in entries:
            vals = []
            for sign in (1, -1):
                s, a = sigma.clone(), albedo.clone()
                (s if e < n else a).view(-1)[e % n] += sign * h
                img = ta.render_scene(scene, s, a, spp=512, seed=1000 + seed, sampling_sigma_t=sigma,
                                      sampling_albedo=albedo)
                vals.append(float((img * weights).sum()))
            out.append((vals[0] - vals[1]) / (2 * h))
        return torch.tensor(out, dtype=torch.float64)

    f_mean, f_se = seed_stats(fd, range(16))
    idx = torch.tensor(entries)
    assert_z(g_mean[idx] - f_mean, (g_se[idx] ** 2 + f_se ** 2).sqrt(), 0.0, family_alpha=1e-4,
             what="default gradient − finite difference")
    assert float((f_mean.abs() / f_se).median()) > 5
