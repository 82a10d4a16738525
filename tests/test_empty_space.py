"""Empty-space skipping outside SDF objects (core::SDFGrid::skip, find_entry in csrc/core/integrator.h).

A ray outside the object crosses the grid in bricks of 4³ cells: the brick distances must be the exact Chebyshev
distance (checked against a brute force over all pairs of bricks), and skipping may change nothing but the rounding
of the cells' exit distances: images and gradients with and without it agree to float64 rounding on scenes with
much empty space (a small sphere, a torus whose paths leave and re-enter, a hollow shell), seen by cameras and by
surface texels, with and without a dielectric boundary. The walk's own counters show the work it saves.
"""
import numpy as np
import pytest
import torch

import torch_appearance as ta
from torch_appearance import _C
from torch_appearance.geometry import sphere_sdf, spherical_shell_sdf, torus_sdf
from torch_appearance.render import (OrthographicCamera, PerspectiveCamera, Scene, SDFBoundary, SurfaceTexels)

N = 40            # voxels per axis: 10 bricks
H = 0.05          # voxel edge, mm
ORIGIN = (-1.0, -1.0, -1.0)
B = 4             # core::kBrick


def brute_force_distances(cells):
    """Chebyshev distance in bricks to the nearest brick with a cell that is not outside (2), capped at 255."""
    d, h, w = cells.shape
    bz, by, bx = -(-d // B), -(-h // B), -(-w // B)
    occupied = np.zeros((bz, by, bx), bool)
    for z, y, x in zip(*np.nonzero(cells != 2)):
        occupied[z // B, y // B, x // B] = True
    occ = np.argwhere(occupied)
    grid = np.stack(np.meshgrid(np.arange(bz), np.arange(by), np.arange(bx), indexing="ij"), -1).reshape(-1, 3)
    if len(occ) == 0:
        return np.full((bz, by, bx), 255, np.uint8)
    cheb = np.abs(grid[:, None, :] - occ[None, :, :]).max(-1).min(1)
    return np.minimum(cheb, 255).reshape(bz, by, bx).astype(np.uint8)


@pytest.mark.parametrize("shape,fill", [((13, 17, 22), 0.02), ((9, 30, 5), 0.005), ((8, 8, 8), 0.0),
                                        ((21, 11, 14), 0.3)])
def test_brick_distances_are_exact(shape, fill):
    gen = np.random.default_rng(sum(shape))
    cells = np.full(shape, 2, np.uint8)
    mask = gen.random(shape) < fill
    cells[mask] = gen.integers(0, 2, size=int(mask.sum()))
    got = _C._skip_distances(torch.from_numpy(cells)).numpy()
    np.testing.assert_array_equal(got, brute_force_distances(cells))


def test_brick_distances_refuse_bad_input():
    with pytest.raises(RuntimeError, match="cells: expected a \\(D, H, W\\) uint8"):
        _C._skip_distances(torch.zeros(4, 4))


def shape_sdf(kind):
    if kind == "sphere":
        return sphere_sdf((N,) * 3, H, ORIGIN, (0.2, -0.1, 0.05), 0.3)
    if kind == "torus":
        return torus_sdf((N,) * 3, H, ORIGIN, (0, 0, 0), 0.45, 0.15)
    return spherical_shell_sdf((N,) * 3, H, ORIGIN, (0, 0, 0), 0.5, 0.12)


def surface_points(kind, count=30, seed=0):
    """Texels on the analytic surface of each shape (their outward normals); they only need to lie near the SDF's
    trilinear zero set."""
    gen = np.random.default_rng(seed)
    u = gen.normal(size=(count, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    if kind == "sphere":
        return np.array((0.2, -0.1, 0.05)) + 0.3 * u, u
    if kind == "shell":
        return 0.5 * u, u
    phi = gen.uniform(0, 2 * np.pi, count)
    theta = gen.uniform(0, 2 * np.pi, count)
    ring = np.stack([np.cos(phi), np.sin(phi), np.zeros(count)], -1)
    n = np.cos(theta)[:, None] * ring + np.sin(theta)[:, None] * np.array([0, 0, 1.0])
    return 0.45 * ring + 0.15 * n, n


def sensor(kind, shape):
    if kind == "texels":
        p, n = surface_points(shape)
        return SurfaceTexels(torch.tensor(p), torch.tensor(n), footprint_mm=0.03)
    if kind == "ortho":
        return OrthographicCamera(origin=(0.1, -0.05, 3), target=(0, 0, 0), up=(0, 1, 0), extent_mm=(1.6, 1.6),
                                  resolution=(9, 9))
    return PerspectiveCamera(origin=(1.8, 1.1, 2.2), target=(0, 0, 0), up=(0, 0, 1), fov_y_deg=30,
                             resolution=(9, 9))


def medium(seed):
    gen = torch.Generator().manual_seed(seed)
    sigma_t = (4 + 12 * torch.rand((3, N, N, N), generator=gen, dtype=torch.float64)).requires_grad_()
    albedo = (0.6 + 0.39 * torch.rand((3, N, N, N), generator=gen, dtype=torch.float64)).requires_grad_()
    return sigma_t, albedo


def render_both(scene, sigma_t, albedo, spp, seed):
    """Image, its σ_t and albedo gradients for a fixed random adjoint, and the stats, without and with skipping."""
    out = []
    for on in (False, True):
        previous = _C._set_empty_space_skipping(on)
        try:
            stats = {}
            image = ta.render_scene(scene, sigma_t, albedo, spp=spp, seed=seed, stats=stats)
            weights = torch.rand(image.shape, generator=torch.Generator().manual_seed(seed), dtype=image.dtype)
            gs, ga = torch.autograd.grad((image * weights).sum(), (sigma_t, albedo))
        finally:
            _C._set_empty_space_skipping(previous)
        out.append((image.detach(), gs, ga, stats))
    return out


@pytest.mark.parametrize("shape", ["sphere", "torus", "shell"])
@pytest.mark.parametrize("where", ["texels", "ortho", "persp"])
@pytest.mark.parametrize("ior", [None, 1.5])
def test_skipping_changes_nothing_but_rounding(shape, where, ior):
    sigma_t, albedo = medium(7)
    scene = Scene(voxel_size=H, origin=ORIGIN, boundary=SDFBoundary(shape_sdf(shape), ior=ior),
                  sensor=sensor(where, shape), g=0.5)
    (i0, gs0, ga0, s0), (i1, gs1, ga1, s1) = render_both(scene, sigma_t, albedo, spp=4, seed=11)
    assert float(i0.abs().max()) > 0
    assert s1["scatter_events"] == s0["scatter_events"]  # the same paths
    assert s1["voxel_steps"] == s0["voxel_steps"]
    torch.testing.assert_close(i1, i0, rtol=1e-9, atol=1e-12)
    torch.testing.assert_close(gs1, gs0, rtol=1e-9, atol=1e-12)
    torch.testing.assert_close(ga1, ga0, rtol=1e-9, atol=1e-12)
    # the work saved: the search for the surface outside visits far fewer cells
    assert s0["outside_steps"] > 0
    assert s1["outside_steps"] < 0.6 * s0["outside_steps"], (s1["outside_steps"], s0["outside_steps"])


def test_skipping_float32_sphere_camera_agrees():
    """In float32 the images agree to float32 rounding of the hit points (no path decision changes here)."""
    sigma_t, albedo = medium(3)
    scene = Scene(voxel_size=H, origin=ORIGIN, boundary=SDFBoundary(shape_sdf("torus"), ior=1.5),
                  sensor=sensor("persp", "torus"), g=0.3)
    images = []
    for on in (False, True):
        previous = _C._set_empty_space_skipping(on)
        try:
            images.append(ta.render_scene(scene, sigma_t.detach().float(), albedo.detach().float(), spp=8, seed=2))
        finally:
            _C._set_empty_space_skipping(previous)
    torch.testing.assert_close(images[1], images[0], rtol=1e-4, atol=1e-6)
