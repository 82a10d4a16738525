"""The SIMD object walk (csrc/volpath/object_simd_walk.h: AVX2, eight lanes; AVX-512, sixteen) against the scalar
walk (core/integrator.h), each test once per width this CPU runs, most of them for a chromatic σ_t (one walk per
channel, each lane one channel) and for a grey one (one path for the three channels, each lane three weights).

The lanes walk the flights through the voxels, the homogeneous core's boxes and the collisions; the start at the
sensor, the exact crossing of the surface in mixed cells, and what happens at the surface (Fresnel, refraction,
total internal reflection, the flight outside to the next surface point of a non-convex object) are the scalar
walk's own steps, called per lane. The same random numbers, in the same event order, the same expressions.

With ``_C._set_simd_exact_math(True)`` the lanes call libm for log, exp, sin and cos as the scalar walk does, so every
path is the scalar walk's to the bit: the images are bitwise equal and so are the event and voxel counts; the
gradients are the same deposits added in another order (lanes finish in another order), so they agree to float
rounding. With the walk's own polynomials (the default) a path may part from its scalar twin after many events,
never in distribution: nearly every texel is still the scalar one.
"""
import numpy as np
import pytest
import torch

import torch_appearance as ta
from torch_appearance._ext import _C
from torch_appearance.geometry import sphere_sdf, torus_sdf
from torch_appearance.render import (EnvironmentMap, OrthographicCamera, PerspectiveCamera, Scene, SDFBoundary,
                                     SurfaceTexels, render_scene_indexed)
from torch_appearance.testing import simd_walk_level

pytestmark = pytest.mark.skipif(simd_walk_level() < 1, reason="needs a CPU with AVX2 (or TA_SIMD is 0)")
WIDTHS = [pytest.param(1, id="avx2"),
          pytest.param(2, id="avx512", marks=pytest.mark.skipif(simd_walk_level() < 2, reason="needs AVX-512F"))]

N = 40
H = 0.05
ORIGIN = (-1.0, -1.0, -1.0)
COUNTS = ("scatter_events", "truncated_paths", "voxel_steps", "outside_steps", "core_events")


def _sdf(kind):
    if kind == "sphere":
        return sphere_sdf((N,) * 3, H, ORIGIN, (0.02, -0.01, 0.0), 0.8)
    return torus_sdf((N,) * 3, H, ORIGIN, (0, 0, 0), 0.6, 0.33)  # paths leave it and enter it again


def _surface_points(sdf, count, seed):
    """Points near the zero set of a corner SDF and their outward normals (finite differences)."""
    g = sdf.double()
    grad = torch.stack(torch.gradient(g, spacing=H), dim=0)  # (z, y, x)
    rng = np.random.default_rng(seed)
    band = (g.abs() < 0.6 * H).nonzero()
    pick = band[torch.from_numpy(rng.choice(len(band), size=count, replace=False))]
    pts, nrm = [], []
    for k, j, i in pick.tolist():
        n = torch.stack([grad[2, k, j, i], grad[1, k, j, i], grad[0, k, j, i]])
        n = n / n.norm()
        p = torch.tensor([i * H + ORIGIN[0], j * H + ORIGIN[1], k * H + ORIGIN[2]], dtype=torch.float64)
        pts.append(p - g[k, j, i] * n)
        nrm.append(n)
    return torch.stack(pts), torch.stack(nrm)


def _scene(kind, sensor, ior, g=0.3, environment=False, **settings):
    sdf = _sdf(kind)
    if sensor == "texels":
        pts, nrm = _surface_points(sdf, 48, seed=2)
        sens = SurfaceTexels(pts, nrm, footprint_mm=0.05)
    elif sensor == "ortho":
        sens = OrthographicCamera(origin=(0.1, 0.05, 3.0), target=(0, 0, 0), up=(0, 1, 0), extent_mm=(2.0, 2.0),
                                  resolution=(8, 8))
    else:
        sens = PerspectiveCamera(origin=(1.5, 0.7, 2.5), target=(0, 0, 0), up=(0, 1, 0), fov_y_deg=40,
                                 resolution=(8, 8))
    kw = {}
    if environment:
        envmap = torch.rand((8, 16, 3), generator=torch.Generator().manual_seed(9)) + 0.2
        kw["emitter"] = EnvironmentMap(envmap)
    return Scene(voxel_size=H, origin=ORIGIN, boundary=SDFBoundary(sdf, ior=ior), sensor=sens, g=g, **kw, **settings)


def _medium(kind="sphere", seed=1, core=True, dense=1.0):
    """A float32 medium: random in a shell near the surface, one white ink deeper than 0.06 mm (the homogeneous
    core)."""
    gen = torch.Generator().manual_seed(seed)
    sigma_t = (torch.rand((3, N, N, N), generator=gen) * 20 + 2) * dense
    albedo = torch.rand((3, N, N, N), generator=gen) * 0.2 + 0.79
    if core:
        f = _sdf(kind)
        centre = sum(f[k:k + N, j:j + N, i:i + N] for k in (0, 1) for j in (0, 1) for i in (0, 1)) / 8
        deep = centre < -0.06
        sigma_t = torch.where(deep, torch.tensor([6.0, 9.0, 24.0]).view(3, 1, 1, 1), sigma_t)
        albedo = torch.where(deep, torch.tensor([0.9991, 0.9997, 0.999]).view(3, 1, 1, 1), albedo)
    return sigma_t.contiguous(), albedo.contiguous()


def _grey_medium(kind="sphere", seed=1, core=True, dense=1.0):
    """_medium with σ_t grey (channel 0's in all three, the core's 9 mm⁻¹) and the albedo chromatic: one path per
    lane serves the three channels (the scalar walk's LANES = 3, stats["lanes"] == 3)."""
    sigma_t, albedo = _medium(kind, seed, core=False, dense=dense)
    sigma_t = sigma_t[:1].expand(3, -1, -1, -1).clone()
    if core:
        f = _sdf(kind)
        centre = sum(f[k:k + N, j:j + N, i:i + N] for k in (0, 1) for j in (0, 1) for i in (0, 1)) / 8
        deep = centre < -0.06
        sigma_t = torch.where(deep, torch.tensor(9.0), sigma_t)
        albedo = torch.where(deep, torch.tensor([0.9991, 0.9997, 0.999]).view(3, 1, 1, 1), albedo)
    return sigma_t.contiguous(), albedo.contiguous()


# one walk per channel (a chromatic σ_t), or one path for the three channels per lane (a grey σ_t)
LANES = pytest.mark.parametrize("lanes", [pytest.param(1, id="per-channel"), pytest.param(3, id="three-channels")])


def _medium_of(lanes, kind="sphere", **kw):
    return _medium(kind, **kw) if lanes == 1 else _grey_medium(kind, **kw)


def _run(mode, scene, sigma_t, albedo, exact=True, threads=2, **kw):
    """(image, grad σ_t, grad albedo, stats) with the walk `mode` (0 scalar, 1 AVX2, 2 AVX-512)."""
    _C._set_simd(mode)
    old = _C._set_simd_exact_math(exact)
    torch.set_num_threads(threads)
    try:
        s = sigma_t.clone().requires_grad_()
        a = albedo.clone().requires_grad_()
        stats = {}
        image = ta.render_scene(scene, s, a, stats=stats, **kw)
        weights = torch.linspace(-1.0, 2.0, image.numel()).reshape(image.shape)
        (image * weights).sum().backward()
    finally:
        _C._set_simd_exact_math(old)
        _C._set_simd(-1)
    return image.detach(), s.grad, a.grad, stats


def _assert_grads_close(simd, scalar, rtol=2e-5):
    for k in (1, 2):
        g_v, g_s = simd[k], scalar[k]
        assert bool(torch.isfinite(g_v).all())
        scale = float(g_s.abs().max())
        assert scale > 0
        err = float((g_v - g_s).abs().max())
        assert err <= rtol * scale, f"gradient {k}: max difference {err:.3g} against max |g| {scale:.3g}"


@pytest.mark.parametrize("width", WIDTHS)
@LANES
@pytest.mark.parametrize("kind,sensor,ior", [
    ("sphere", "texels", 1.5),      # dielectric, seen by its surface texels
    ("sphere", "ortho", None),      # index matched, a camera
    ("torus", "texels", 1.33),      # re-entry of a non-convex object
    ("torus", "persp", 2.4),        # total internal reflection beyond 24.6°
])
def test_exact_math_lanes_are_the_scalar_walk_to_the_bit(width, lanes, kind, sensor, ior):
    """Three channels per lane: p_s the largest reference albedo, roulette on the largest reference weight, three
    albedo factors, tape collisions with three factors, as the scalar LANES = 3 walk."""
    sc = _scene(kind, sensor, ior)
    sigma_t, albedo = _medium_of(lanes, kind)
    kw = dict(spp=3, seed=11)
    scalar = _run(0, sc, sigma_t, albedo, **kw)
    simd = _run(width, sc, sigma_t, albedo, **kw)
    assert scalar[3]["lanes"] == lanes and simd[3]["lanes"] == lanes
    if lanes == 3:  # the channels differ (a chromatic albedo): three weights, not one copied
        assert float((scalar[0][..., 0] - scalar[0][..., 2]).abs().max()) > 1e-3
    assert torch.equal(simd[0], scalar[0]), float((simd[0] - scalar[0]).abs().max())
    for key in COUNTS:
        assert simd[3][key] == scalar[3][key], (key, simd[3][key], scalar[3][key])
    assert scalar[3]["core_events"] > 0 and scalar[3]["outside_steps"] > 0  # both shortcuts exercised
    assert simd[3]["backward_scatter_events"] == scalar[3]["backward_scatter_events"]
    _assert_grads_close(simd, scalar)


@pytest.mark.parametrize("width", WIDTHS)
@LANES
def test_exact_math_with_an_environment_map_and_the_one_walk(width, lanes):
    """The escape direction is the scalar walk's (an environment map sees it), and the walk that renders and deposits
    at once (``adjoint``) is the scalar one too."""
    sc = _scene("torus", "ortho", 1.5, environment=True)
    sigma_t, albedo = _medium_of(lanes, "torus", seed=4)
    adjoint = torch.linspace(-1.0, 1.0, 8 * 8 * 3).reshape(8, 8, 3)
    out = {}
    for mode in (0, width):
        _C._set_simd(mode)
        old = _C._set_simd_exact_math(True)
        try:
            stats = {}
            image = ta.render_scene(sc, sigma_t, albedo, spp=2, seed=5, stats=stats)
            s = sigma_t.clone().requires_grad_()
            a = albedo.clone().requires_grad_()
            one = ta.render_scene(sc, s, a, spp=2, seed=5, adjoint=adjoint)
            (one * adjoint).sum().backward()
            out[mode] = image, one.detach(), s.grad, a.grad
        finally:
            _C._set_simd_exact_math(old)
            _C._set_simd(-1)
    assert stats["lanes"] == lanes
    assert torch.equal(out[width][0], out[0][0])
    assert torch.equal(out[width][1], out[0][1])
    for k in (2, 3):
        scale = float(out[0][k].abs().max())
        assert scale > 0
        assert float((out[width][k] - out[0][k]).abs().max()) <= 2e-5 * scale


@pytest.mark.parametrize("width", WIDTHS)
def test_polynomial_lanes_are_the_scalar_walk_in_distribution(width):
    """The default walk (its own log, exp, sin, cos): nearly every texel is its scalar twin's, and the rest agree in
    distribution (a z-test of the mean difference over many texels)."""
    sc = _scene("sphere", "texels", 1.5)
    sigma_t, albedo = _medium("sphere", seed=2)
    kw = dict(spp=4, seed=3)
    scalar = _run(0, sc, sigma_t, albedo, exact=False, **kw)
    simd = _run(width, sc, sigma_t, albedo, exact=False, **kw)
    close = (simd[0] - scalar[0]).abs() <= 1e-4 * scalar[0].abs().clamp_min(1e-3)
    assert float(close.float().mean()) >= 0.9, float(close.float().mean())
    for key in ("scatter_events", "voxel_steps"):
        assert abs(simd[3][key] - scalar[3][key]) <= 0.02 * scalar[3][key], key
    _assert_same_in_distribution(width, sc, sigma_t, albedo)


def _assert_same_in_distribution(width, sc, sigma_t, albedo):
    """Independent seeds, many texels: the mean difference of the two walks within 4 standard errors."""
    a = _run(width, sc, sigma_t, albedo, exact=False, spp=16, seed=101)[0]
    b = _run(0, sc, sigma_t, albedo, exact=False, spp=16, seed=202)[0]
    d = (a - b).flatten().double()
    z = float(d.mean() / (d.std() / d.numel() ** 0.5))
    assert abs(z) < 4.0, z


@pytest.mark.parametrize("width", WIDTHS)
def test_three_channel_lanes_with_polynomials_in_distribution(width):
    """Three channels per lane with the walk's own log, exp, sin and cos: most texels are their scalar twins' (and not
    all: the lanes, not the scalar walk, walked them), the rest agree in distribution."""
    sc = _scene("sphere", "texels", 1.5)
    sigma_t, albedo = _grey_medium("sphere", seed=2, dense=4.0)  # long enough paths that some part from their twins
    kw = dict(spp=16, seed=3)
    scalar = _run(0, sc, sigma_t, albedo, exact=False, **kw)
    simd = _run(width, sc, sigma_t, albedo, exact=False, **kw)
    assert simd[3]["lanes"] == 3
    close = (simd[0] - scalar[0]).abs() <= 1e-4 * scalar[0].abs().clamp_min(1e-3)
    assert 0.9 <= float(close.float().mean()) < 1.0, float(close.float().mean())
    _assert_same_in_distribution(width, sc, sigma_t, albedo)


@pytest.mark.parametrize("width", WIDTHS)
@LANES
@pytest.mark.parametrize("capacity", [0, 4])
def test_paths_longer_than_the_lane_tape_are_replayed_exactly(width, lanes, capacity):
    sc = _scene("sphere", "texels", 1.5)
    sigma_t, albedo = _medium_of(lanes, seed=6)
    old = _C._set_tape_capacity(capacity)
    try:
        scalar = _run(0, sc, sigma_t, albedo, spp=2, seed=8)
        simd = _run(width, sc, sigma_t, albedo, spp=2, seed=8)
    finally:
        _C._set_tape_capacity(old)
    assert simd[3]["lanes"] == lanes
    assert torch.equal(simd[0], scalar[0])
    _assert_grads_close(simd, scalar)


@pytest.mark.parametrize("width", WIDTHS)
@LANES
def test_floored_sampling_medium_and_zeros(width, lanes):
    """The replay samples max(σ_t, floor), max(α, floor); exact zeros in σ_t and α give zero-safe weights (with three
    channels per lane, zeros in one channel's albedo: each channel its own)."""
    sc = _scene("sphere", "texels", None, sigma_t_floor=4.0, albedo_floor=0.5)
    sigma_t, albedo = _medium_of(lanes, seed=7, core=False)
    sigma_t[:, 18:22, 18:22, 5:12] = 0.0
    albedo[:1 if lanes == 3 else 3, 20:23, 4:10, 18:22] = 0.0
    kw = dict(spp=3, seed=2)
    scalar = _run(0, sc, sigma_t, albedo, **kw)
    simd = _run(width, sc, sigma_t, albedo, **kw)
    assert simd[3]["lanes"] == lanes
    assert torch.equal(simd[0], scalar[0])
    _assert_grads_close(simd, scalar)


@pytest.mark.parametrize("width", WIDTHS)
@LANES
@pytest.mark.filterwarnings("ignore:render_scene.*max_depth")
def test_cut_by_depth(width, lanes):
    sc = _scene("sphere", "texels", 1.5, max_depth=12)
    sigma_t, albedo = _medium_of(lanes, seed=3, dense=8.0)
    kw = dict(spp=2, seed=4)
    scalar = _run(0, sc, sigma_t, albedo, **kw)
    simd = _run(width, sc, sigma_t, albedo, **kw)
    assert scalar[3]["truncated_paths"] > 0
    assert simd[3]["lanes"] == lanes
    assert torch.equal(simd[0], scalar[0])
    assert simd[3]["truncated_paths"] == scalar[3]["truncated_paths"]


def test_double_hero_and_tally_keep_the_scalar_walk():
    """What the lanes do not serve (float64, the hero walk) runs the scalar walk: the same image with and without
    the SIMD walks."""
    sc = _scene("sphere", "texels", 1.5)
    sigma_t, albedo = _medium("sphere", seed=5)
    for kw in (dict(sigma_t=sigma_t.double(), albedo=albedo.double()), dict(sigma_t=sigma_t, albedo=albedo,
                                                                               chromatic="hero")):
        images = []
        for mode in (0, -1):
            _C._set_simd(mode)
            try:
                images.append(ta.render_scene(sc, spp=2, seed=1, **kw))
            finally:
                _C._set_simd(-1)
        assert torch.equal(images[0], images[1])


@pytest.mark.parametrize("width", WIDTHS)
def test_palette_medium_of_a_quantised_print(width):
    """A palette medium (render_scene_indexed: a uint8 index volume and (P, 3) tables, as a quantised print's
    evaluation renders it) in lanes: the scalar walk's image to the bit, and the dense render's."""
    sc = _scene("torus", "texels", 1.5)
    gen = torch.Generator().manual_seed(12)
    index = torch.randint(0, 5, (N, N, N), generator=gen, dtype=torch.uint8)
    f = _sdf("torus")
    centre = sum(f[k:k + N, j:j + N, i:i + N] for k in (0, 1) for j in (0, 1) for i in (0, 1)) / 8
    index[centre < -0.06] = 4  # one entry deep inside: the homogeneous core
    sigma_table = torch.rand((5, 3), generator=gen) * 20 + 2
    albedo_table = torch.rand((5, 3), generator=gen) * 0.2 + 0.79
    images = {}
    for mode in (0, width):
        _C._set_simd(mode)
        old = _C._set_simd_exact_math(True)
        try:
            images[mode] = render_scene_indexed(sc, index, sigma_table, albedo_table, spp=3, seed=2)
        finally:
            _C._set_simd_exact_math(old)
            _C._set_simd(-1)
    assert torch.equal(images[width], images[0])
    dense_s = sigma_table[index.long()].permute(3, 0, 1, 2).contiguous()
    dense_a = albedo_table[index.long()].permute(3, 0, 1, 2).contiguous()
    _C._set_simd(width)
    old = _C._set_simd_exact_math(True)
    try:
        dense = ta.render_scene(sc, dense_s, dense_a, spp=3, seed=2)
    finally:
        _C._set_simd_exact_math(old)
        _C._set_simd(-1)
    assert torch.equal(images[width], dense)


@pytest.fixture(scope="module")
def small_spot():
    """Spot (public domain, tests/data) at 6 mm and 150 DPI with a 0.4 mm shell, as ta-optimize-print prepares it,
    and its 97 % white start (the print loop's mixture: random in no voxel, white in the core)."""
    import os
    from torch_appearance.nn.mixture import MaterialMixture
    from torch_appearance.pipelines.print import PrintConfig
    from torch_appearance.pipelines.print.config import load_inks
    from torch_appearance.pipelines.print.object_target import ObjectTarget
    spot = os.path.join(os.path.dirname(__file__), "data", "meshes", "spot")
    cfg = PrintConfig(mesh=os.path.join(spot, "spot_triangulated.obj"), texture=os.path.join(spot, "spot_texture.png"),
                      height_mm=6.0, dpi=150.0, shell_mm=0.4, out="unused")
    inks = load_inks(cfg.inks)
    target = ObjectTarget.from_config(cfg, inks, log=lambda *a: None)
    model = MaterialMixture(inks, tuple(target.shape), support=target.support, core_ink="white")
    with torch.no_grad():  # a heterogeneous shell: random logits
        for prm in model.parameters():
            prm.copy_(torch.randn(prm.shape, generator=torch.Generator().manual_seed(3)))
        sigma_t, albedo = model()
    return target, sigma_t.float().contiguous(), albedo.float().contiguous()


@pytest.mark.parametrize("width", WIDTHS)
def test_small_spot_as_the_print_loop_renders_it(width, small_spot):
    """Spot's surface texels, dielectric, the shell's gradients only (``grad_support``), as the print loop asks."""
    target, sigma_t, albedo = small_spot
    kw = dict(spp=2, seed=7, grad_support=target.support)
    scalar = _run(0, target.scene, sigma_t, albedo, **kw)
    simd = _run(width, target.scene, sigma_t, albedo, **kw)
    assert scalar[0].shape[0] > 500
    assert torch.equal(simd[0], scalar[0])
    for key in COUNTS:
        assert simd[3][key] == scalar[3][key], (key, simd[3][key], scalar[3][key])
    assert scalar[3]["core_events"] > 0
    _assert_grads_close(simd, scalar)

