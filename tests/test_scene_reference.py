"""The fast tracer against the independent numpy reference (torch_appearance.testing.reference_tracer: delta
tracking, analog collisions and Fresnel, SDF crossings by marching + bisection) on tiny chromatic heterogeneous
scenes: per-pixel and per-texel z-tests with a Bonferroni correction."""
import numpy as np
import pytest
import torch

import torch_appearance as ta
from torch_appearance.geometry import sphere_sdf
from torch_appearance.render import (BoxBoundary, ConstantEnvironment, DiscLight, EnvironmentMap, OrthographicCamera,
                                     PerspectiveCamera, Scene, SDFBoundary, SurfaceTexels)

from torch_appearance.testing import assert_z
from torch_appearance.testing.reference_tracer import reference_render_scene

N, H = 6, 0.1
ORIGIN = (-0.3, -0.25, -0.3)
CENTRE, RADIUS = (0.01, 0.03, -0.02), 0.23


def medium(scale=1.0):
    g = torch.Generator().manual_seed(4)
    sigma = scale * (2 + 12 * torch.rand(3, N, N, N, generator=g, dtype=torch.float64))
    albedo = 0.55 + 0.44 * torch.rand(3, N, N, N, generator=g, dtype=torch.float64)
    return sigma, albedo


def env_image():
    g = torch.Generator().manual_seed(8)
    return 0.2 + 2 * torch.rand(5, 10, 3, generator=g, dtype=torch.float64)


def texels():
    g = np.random.default_rng(3)
    d = g.normal(size=(6, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return np.asarray(CENTRE) + RADIUS * d, d


# (name, boundary kind, ior, sensor, emitter, g, σ scale)
CASES = [
    # a nearly clear glass ball: the image is the environment refracted through it (a lens)
    ("sdf-1.5-orthographic-envmap-clear", "sdf", 1.5,
     dict(kind="orthographic", origin=(0.0, 0.02, 0.6), target=(0, 0, 0), up=(0, 1, 0), extent=(0.5, 0.5),
          resolution=(4, 4)),
     dict(kind="envmap"), 0.0, 0.05),
    ("sdf-1.5-perspective-constant", "sdf", 1.5,
     dict(kind="perspective", origin=(0.7, 0.5, 0.6), target=(0, 0, 0), up=(0, 0, 1), fov_y_deg=40,
          resolution=(4, 4)),
     dict(kind="constant", radiance=(1.0, 0.7, 0.4)), 0.4, 1.0),
    ("sdf-1.5-texels-envmap", "sdf", 1.5, "texels", dict(kind="envmap"), 0.2, 1.0),
    ("sdf-matched-orthographic-disc", "sdf", None,
     dict(kind="orthographic", origin=(0.05, -0.6, 0.1), target=(0, 0, 0), up=(0, 0, 1), extent=(0.6, 0.6),
          resolution=(4, 4)),
     dict(kind="disc", direction=(0.3, 1.0, 0.2), angle_deg=35.0, radiance=(3.0, 2.0, 1.0), ambient=(0.2, 0.3, 0.4)),
     0.6, 1.0),
    ("sdf-2.0-orthographic-envmap", "sdf", 2.0,
     dict(kind="orthographic", origin=(0.5, 0.3, 0.5), target=(0, 0, 0), up=(0, 0, 1), extent=(0.6, 0.6),
          resolution=(3, 4)),
     dict(kind="envmap"), 0.0, 1.0),
    ("box-1.5-perspective-disc", "box", 1.5,
     dict(kind="perspective", origin=(0.6, -0.7, 0.5), target=(0, 0, 0), up=(0, 0, 1), fov_y_deg=45,
          resolution=(4, 4)),
     dict(kind="disc", direction=(0.0, 0.5, 1.0), angle_deg=50.0, radiance=2.0, ambient=0.25), 0.3, 1.0),
]


def ours(boundary, ior, sensor, emitter):
    sdf = sphere_sdf((N,) * 3, H, ORIGIN, CENTRE, RADIUS)
    b = SDFBoundary(sdf, ior=ior) if boundary == "sdf" else BoxBoundary(ior)
    if sensor == "texels":
        p, n = texels()
        s = SurfaceTexels(torch.tensor(p), torch.tensor(n), footprint_mm=0.04)
    elif sensor["kind"] == "perspective":
        s = PerspectiveCamera(sensor["origin"], sensor["target"], sensor["up"], fov_y_deg=sensor["fov_y_deg"],
                              resolution=sensor["resolution"])
    else:
        s = OrthographicCamera(sensor["origin"], sensor["target"], sensor["up"], extent_mm=sensor["extent"],
                               resolution=sensor["resolution"])
    if emitter["kind"] == "constant":
        e = ConstantEnvironment(emitter["radiance"])
    elif emitter["kind"] == "envmap":
        e = EnvironmentMap(env_image())
    else:
        e = DiscLight(emitter["direction"], emitter["angle_deg"], emitter["radiance"], emitter["ambient"])
    return b, s, e


def reference_dicts(sensor, emitter):
    if sensor == "texels":
        p, n = texels()
        sensor = dict(kind="surface_texels", points=p, normals=n, radius=np.full(len(p), 0.04))
    emitter = dict(emitter)
    if emitter["kind"] == "envmap":
        emitter["image"] = env_image().numpy()
    if emitter["kind"] == "disc":
        for k in ("radiance", "ambient"):
            emitter[k] = np.broadcast_to(np.asarray(emitter[k], dtype=float), (3,))
    return sensor, emitter


@pytest.mark.slow
@pytest.mark.parametrize("case", CASES, ids=[c[0] for c in CASES])
def test_scene_matches_reference(case):
    name, boundary, ior, sensor, emitter, g, scale = case
    sigma, albedo = medium(scale)
    b, s, e = ours(boundary, ior, sensor, emitter)
    scene = Scene(voxel_size=H, origin=ORIGIN, boundary=b, sensor=s, emitter=e, g=g)
    seeds = range(32)
    xs = torch.stack([ta.render_scene(scene, sigma, albedo, spp=128, seed=k) for k in seeds])
    mean, se = xs.mean(0), xs.std(0) / len(seeds) ** 0.5
    rs, re = reference_dicts(sensor, emitter)
    sdf = sphere_sdf((N,) * 3, H, ORIGIN, CENTRE, RADIUS).numpy()
    diag = {}
    ref_mean, ref_se = reference_render_scene(sigma.numpy(), albedo.numpy(), voxel_size=H, origin=ORIGIN, g=g,
                                              boundary=boundary, sdf=sdf if boundary == "sdf" else None, ior=ior,
                                              sensor=rs, emitter=re, spp=4096, rng=np.random.default_rng(11),
                                              diagnostics=diag)
    assert diag.get("stuck", 0) == 0
    ref_mean, ref_se = torch.as_tensor(ref_mean), torch.as_tensor(ref_se)
    # pixels that see only the emitter have no variance in either: compare them exactly
    flat = (se == 0) & (ref_se == 0)
    assert torch.allclose(mean[flat], ref_mean[flat], rtol=1e-5, atol=1e-6)
    z = assert_z(mean - ref_mean, (se ** 2 + ref_se ** 2).sqrt().clamp_min(1e-12), 0.0, what=name)
    print(f"{name}: max |z| = {z:.2f} over {mean.numel()} values")
