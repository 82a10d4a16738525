"""General scenes against physics: white furnace, Beer–Lambert through an SDF sphere, and consistency between
scene pieces that must agree (box as SDF vs box, camera over a slab vs face texels, surface vs face texels)."""
import math

import numpy as np
import pytest
import torch

import torch_appearance as ta
from torch_appearance.geometry import box_sdf, sphere_sdf, spherical_shell_sdf, torus_sdf
from torch_appearance.render import (BoxBoundary, ConstantEnvironment, DiscLight, FaceTexels, OrthographicCamera,
                                     PerspectiveCamera, Scene, SDFBoundary, SurfaceTexels)

from torch_appearance.testing import assert_z

N = 12          # voxels per axis
H = 0.1         # voxel edge, mm
ORIGIN = (-0.6, -0.6, -0.6)


def shape_sdf(kind):
    if kind == "sphere":
        return sphere_sdf((N,) * 3, H, ORIGIN, (0, 0, 0), 0.45)
    if kind == "torus":
        return torus_sdf((N,) * 3, H, ORIGIN, (0, 0, 0), 0.33, 0.15)
    return spherical_shell_sdf((N,) * 3, H, ORIGIN, (0, 0, 0), 0.4, 0.12)


def texels_on(sdf, count=40, seed=0):
    """Surface points and normals found on the trilinear zero set by bisection along random rays from the centre
    outwards (sphere-like shapes) — the texels only need to lie on or near the surface."""
    gen = np.random.default_rng(seed)
    d = gen.normal(size=(count, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    pts, nrm = [], []
    f = sdf.numpy()

    def value(p):
        x = (p - np.array(ORIGIN)) / H
        i = np.clip(np.floor(x).astype(int), 0, N - 1)
        t = x - i
        c = f[i[2]:i[2] + 2, i[1]:i[1] + 2, i[0]:i[0] + 2]
        return sum(c[kz, ky, kx] * (t[0] if kx else 1 - t[0]) * (t[1] if ky else 1 - t[1]) * (t[2] if kz else 1 - t[2])
                   for kz in (0, 1) for ky in (0, 1) for kx in (0, 1))

    for di in d:
        ts = np.linspace(0.0, 0.59, 600)
        vals = np.array([value(t * di) for t in ts])
        k = np.nonzero((vals[:-1] > 0) != (vals[1:] > 0))[0]
        if len(k) == 0:
            continue
        lo, hi = ts[k[-1]], ts[k[-1] + 1]  # the outermost crossing
        for _ in range(50):
            mid = (lo + hi) / 2
            if (value(mid * di) > 0) == (vals[k[-1]] > 0):
                lo = mid
            else:
                hi = mid
        p = hi * di
        eps = 1e-4
        g = np.array([value(p + eps * e) - value(p - eps * e) for e in np.eye(3)])
        pts.append(p)
        nrm.append(g / np.linalg.norm(g))
    return torch.tensor(np.array(pts)), torch.tensor(np.array(nrm))


def sensors(sdf):
    pts, nrm = texels_on(sdf)
    return {
        "texels": SurfaceTexels(pts, nrm, footprint_mm=0.05),
        "ortho": OrthographicCamera(origin=(0.1, -0.05, 3), target=(0, 0, 0), up=(0, 1, 0), extent_mm=(1.3, 1.3),
                                    resolution=(10, 10)),
        "persp": PerspectiveCamera(origin=(1.5, 1.0, 2.0), target=(0, 0, 0), up=(0, 0, 1), fov_y_deg=35,
                                   resolution=(10, 10)),
    }


@pytest.mark.parametrize("shape", ["sphere", "torus", "shell"])
@pytest.mark.parametrize("ior", [None, 1.5, 3.0])
@pytest.mark.parametrize("sigma", [1e-4, 8.0, 50.0])
def test_white_furnace_sdf(shape, ior, sigma):
    """Albedo 1 under a uniform unit environment: every sensor sees exactly 1, whatever the shape, σ_t and IOR."""
    sdf = shape_sdf(shape)
    gen = torch.Generator().manual_seed(1)
    sigma_t = (sigma * (0.5 + torch.rand((3, N, N, N), generator=gen, dtype=torch.float64))).float()
    albedo = torch.ones_like(sigma_t)
    for name, sensor in sensors(sdf).items():
        scene = Scene(voxel_size=H, origin=ORIGIN, boundary=SDFBoundary(sdf, ior=ior), sensor=sensor, g=0.3)
        stats = {}
        image = ta.render_scene(scene, sigma_t, albedo, spp=16, seed=3, stats=stats)
        assert stats["truncated_paths"] == 0
        err = float((image - 1).abs().max())
        assert err < 1e-5, f"{shape}, ior {ior}, σ {sigma}, {name}: max |L − 1| = {err:.3g}"


def test_white_furnace_box_cameras_and_emitter_scale():
    """The box boundary seen by cameras, and a grey emitter of radiance 0.7: exactly 0.7."""
    sigma_t = torch.full((3, 4, 6, 5), 20.0)
    albedo = torch.ones_like(sigma_t)
    for sensor in sensors(shape_sdf("sphere")).values():
        if isinstance(sensor, SurfaceTexels):
            continue
        for ior in (None, 1.5):
            scene = Scene(voxel_size=0.1, origin=(-0.25, -0.3, -0.2), boundary=BoxBoundary(ior), sensor=sensor,
                          emitter=ConstantEnvironment(0.7))
            image = ta.render_scene(scene, sigma_t, albedo, spp=8, seed=0)
            assert float((image - 0.7).abs().max()) < 1e-5


def trilinear(sdf, p):
    """The trilinear interpolant of the corner grid at world points p (..., 3) (independent numpy code)."""
    f = sdf.numpy()
    x = (np.asarray(p) - np.array(ORIGIN)) / H
    i = np.clip(np.floor(x).astype(int), 0, N - 1)
    t = x - i
    out = 0.0
    for kz in (0, 1):
        for ky in (0, 1):
            for kx in (0, 1):
                w = (np.where(kx, t[..., 0], 1 - t[..., 0]) * np.where(ky, t[..., 1], 1 - t[..., 1])
                     * np.where(kz, t[..., 2], 1 - t[..., 2]))
                out = out + w * f[i[..., 2] + kz, i[..., 1] + ky, i[..., 0] + kx]
    return out


def chord_by_marching(sdf, x, y, steps=40000):
    """Length of the vertical line (x, y, ·) inside the trilinear zero set: dense sampling + bisection."""
    z = np.linspace(ORIGIN[2] + 1e-9, ORIGIN[2] + N * H - 1e-9, steps)
    pts = np.stack([np.full_like(z, x), np.full_like(z, y), z], axis=-1)
    v = trilinear(sdf, pts)
    k = np.nonzero((v[:-1] < 0) != (v[1:] < 0))[0]
    roots = []
    for j in k:
        lo, hi = z[j], z[j + 1]
        for _ in range(60):
            mid = (lo + hi) / 2
            if (trilinear(sdf, np.array([x, y, mid])) < 0) == (v[j] < 0):
                lo = mid
            else:
                hi = mid
        roots.append((lo + hi) / 2)
    assert len(roots) % 2 == 0
    return sum(roots[i + 1] - roots[i] for i in range(0, len(roots), 2))


def test_beer_lambert_through_sdf_sphere():
    """A non-scattering index-matched sphere seen by an orthographic camera: exp(−σ_t ℓ) where ℓ is the chord through
    the SDF's trilinear surface (exactly, against an independent root finder), and within the stated discretisation
    bound of the analytic chord 2√(R² − r²)."""
    R, sigma = 0.45, 3.0
    sdf = sphere_sdf((N,) * 3, H, ORIGIN, (0, 0, 0), R)
    sigma_t = torch.full((3, N, N, N), sigma, dtype=torch.float64)
    albedo = torch.zeros_like(sigma_t)
    ref = torch.full_like(sigma_t, 1e-12)  # sampling medium with (almost) no collisions: weight exp(−(σ−σ̂)ℓ)
    # bound on the trilinear zero set's distance from the sphere: interpolation error of the distance function,
    # h²/8·Σ|∂²f/∂x_a²| <= 3h²/(8·(R − h√3)) near the surface
    delta = 3 * H ** 2 / (8 * (R - H * math.sqrt(3)))
    for r in np.linspace(0.0, 0.42, 15):
        x, y = r * math.cos(0.7), r * math.sin(0.7)
        cam = OrthographicCamera(origin=(x, y, 2.0), target=(x, y, 0.0), up=(0, 1, 0), extent_mm=(1e-7, 1e-7),
                                 resolution=(1, 1))
        scene = Scene(voxel_size=H, origin=ORIGIN, boundary=SDFBoundary(sdf, ior=None), sensor=cam)
        value = float(ta.render_scene(scene, sigma_t, albedo, spp=4, sampling_sigma_t=ref, sampling_albedo=ref)[0, 0, 0])
        chord = chord_by_marching(sdf, x, y)
        assert value == pytest.approx(math.exp(-sigma * chord), rel=1e-6, abs=1e-9), f"r = {r:.3f}"
        exact = 2 * math.sqrt(R * R - r * r)
        bound = 2 * delta * R / math.sqrt(R * R - r * r)  # the chord's sensitivity to a radial surface shift
        assert abs(chord - exact) <= bound, f"r = {r:.3f}: chord {chord:.5f}, analytic {exact:.5f} ± {bound:.5f}"


def slab_medium(seed, d=6, h=16, w=16, dtype=torch.float32):
    gen = torch.Generator().manual_seed(seed)
    sigma_t = (2 + 18 * torch.rand((3, d, h, w), generator=gen, dtype=torch.float64)).to(dtype)
    albedo = (0.5 + 0.49 * torch.rand((3, d, h, w), generator=gen, dtype=torch.float64)).to(dtype)
    return sigma_t, albedo


def seeds_mean(fn, seeds):
    xs = torch.stack([fn(s).double() for s in seeds])
    return xs.mean(0), xs.std(0) / math.sqrt(len(seeds))


def assert_same(a, b, what, n_tests=None):
    """Two independent estimates (mean, stderr) agree: z-test of the difference."""
    diff = a[0] - b[0]
    se = (a[1] ** 2 + b[1] ** 2).sqrt()
    return assert_z(diff, se, 0.0, n_tests=n_tests, what=what)


@pytest.mark.parametrize("ior", [None, 1.5])
def test_orthographic_camera_over_slab_equals_top_face_texels(ior):
    sigma_t, albedo = slab_medium(0, h=6, w=8)
    d, h, w = sigma_t.shape[1:]
    s = 0.1
    face = Scene(voxel_size=s, boundary=BoxBoundary(ior), sensor=FaceTexels("top"))
    cam = OrthographicCamera(origin=(w * s / 2, h * s / 2, 5.0), target=(w * s / 2, h * s / 2, 0.0), up=(0, 1, 0),
                             extent_mm=(w * s, h * s), resolution=(h, w))
    camera = Scene(voxel_size=s, boundary=BoxBoundary(ior), sensor=cam)
    seeds = range(24)
    a = seeds_mean(lambda k: ta.render_scene(face, sigma_t, albedo, spp=16, seed=k), seeds)
    b = seeds_mean(lambda k: ta.render_scene(camera, sigma_t, albedo, spp=16, seed=1000 + k).flip(0), seeds)
    assert_same(a, b, "camera vs face texels")


@pytest.mark.parametrize("ior", [None, 1.5])
def test_surface_texels_on_flat_face_equal_face_texels(ior):
    """Laterally homogeneous dense slab, centre texels (≥ 10 mean free paths from the sides, where the disc and
    square footprints see the same medium)."""
    d, h, w, s = 5, 16, 16, 0.1
    sigma_t = torch.linspace(5, 25, d).view(1, d, 1, 1).expand(3, d, h, w).contiguous()
    albedo = torch.tensor([0.95, 0.8, 0.6]).view(3, 1, 1, 1).expand(3, d, h, w).contiguous()
    centre = [(j, i) for j in range(6, 10) for i in range(6, 10)]
    pts = torch.tensor([((i + 0.5) * s, (j + 0.5) * s, d * s) for j, i in centre], dtype=torch.float64)
    nrm = torch.tensor([(0.0, 0.0, 1.0)] * len(centre), dtype=torch.float64)
    surf = Scene(voxel_size=s, boundary=BoxBoundary(ior), sensor=SurfaceTexels(pts, nrm, footprint_mm=s / 2))
    face = Scene(voxel_size=s, boundary=BoxBoundary(ior), sensor=FaceTexels("top"))
    seeds = range(16)
    idx = torch.tensor([j * w + i for j, i in centre])
    a = seeds_mean(lambda k: ta.render_scene(face, sigma_t, albedo, spp=64, seed=k).reshape(-1, 3)[idx], seeds)
    b = seeds_mean(lambda k: ta.render_scene(surf, sigma_t, albedo, spp=64, seed=500 + k), seeds)
    assert_same(a, b, "surface vs face texels")


@pytest.mark.parametrize("ior", [None, 1.5])
def test_box_as_sdf_equals_box_boundary(ior):
    """The grid box padded by one voxel, its SDF exactly zero on the box faces: the same surface, the same image."""
    sigma_t, albedo = slab_medium(2, d=4, h=6, w=6)
    d, h, w = sigma_t.shape[1:]
    s = 0.1
    padded_s = torch.nn.functional.pad(sigma_t, (1, 1, 1, 1, 1, 1), value=7.0)  # medium outside: must not count
    padded_a = torch.nn.functional.pad(albedo, (1, 1, 1, 1, 1, 1), value=0.3)
    sdf = box_sdf((d + 2, h + 2, w + 2), s, (-s, -s, -s), (0, 0, 0), (w * s, h * s, d * s))
    cams = [OrthographicCamera(origin=(0.9, 0.7, 1.8), target=(0.3, 0.3, 0.2), up=(0, 0, 1), extent_mm=(1.2, 1.0),
                               resolution=(6, 8)),
            PerspectiveCamera(origin=(-0.8, 1.5, 1.1), target=(0.3, 0.3, 0.2), up=(0, 0, 1), fov_y_deg=40,
                              resolution=(6, 8))]
    for cam in cams:
        box = Scene(voxel_size=s, boundary=BoxBoundary(ior), sensor=cam, emitter=DiscLight((0, 1, 1), 40, 2.0, 0.3))
        sdfs = Scene(voxel_size=s, origin=(-s, -s, -s), boundary=SDFBoundary(sdf, ior=ior), sensor=cam,
                     emitter=DiscLight((0, 1, 1), 40, 2.0, 0.3))
        seeds = range(16)
        a = seeds_mean(lambda k: ta.render_scene(box, sigma_t, albedo, spp=32, seed=k), seeds)
        b = seeds_mean(lambda k: ta.render_scene(sdfs, padded_s, padded_a, spp=32, seed=100 + k), seeds)
        assert_same(a, b, f"box vs box-as-SDF ({type(cam).__name__})", n_tests=2 * a[0].numel())


@pytest.mark.parametrize("ior", [None, 1.5])
def test_degenerate_rays_white_furnace(ior):
    """Rays exactly along voxel-corner planes and edges, axis-aligned and diagonal, through corner points, and
    grazing the sphere: no NaN, no stuck or truncated paths, still exactly 1 in the white furnace."""
    sdf = shape_sdf("sphere")
    sigma_t = torch.full((3, N, N, N), 6.0)
    albedo = torch.ones_like(sigma_t)
    lines = [((0.0, 0.0, 3.0), (0.0, 0.0, 0.0), (0, 1, 0)),          # along the z axis: a corner line
             ((0.1, 0.2, 3.0), (0.1, 0.2, 0.0), (0, 1, 0)),          # another corner line
             ((3.0, 0.0, 0.0), (0.0, 0.0, 0.0), (0, 0, 1)),          # along x through the centre
             ((3.0, 3.0, 3.0), (0.0, 0.0, 0.0), (0, 0, 1)),          # the main diagonal through corners
             ((0.45, 0.0, 3.0), (0.45, 0.0, 0.0), (0, 1, 0)),        # tangent to the analytic sphere
             ((0.0, 0.4499, -3.0), (0.0, 0.4499, 0.0), (1, 0, 0)),   # grazing from below
             ((0.6, 0.6, 3.0), (0.6, 0.6, 0.0), (0, 1, 0))]          # along the grid's outer edge
    for origin, target, up in lines:
        cam = OrthographicCamera(origin=origin, target=target, up=up, extent_mm=(1e-9, 1e-9), resolution=(1, 2))
        scene = Scene(voxel_size=H, origin=ORIGIN, boundary=SDFBoundary(sdf, ior=ior), sensor=cam)
        stats = {}
        image = ta.render_scene(scene, sigma_t, albedo, spp=64, seed=5, stats=stats)
        assert stats["truncated_paths"] == 0, origin
        assert bool(torch.isfinite(image).all()) and float((image - 1).abs().max()) < 1e-5, origin
