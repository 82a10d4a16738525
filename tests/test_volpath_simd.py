"""The SIMD slab walks (csrc/volpath/slab_simd_walk.h: AVX2, eight lanes; AVX-512, sixteen) against the scalar walk
(core/integrator.h), each test once per width this CPU runs.

They draw the same random numbers (Philox, counter (texel, sample, channel, event)) in the same event order and apply
the same estimator; the SIMD walks only compute log, sin, cos and a few quotients in a different way, to the last
bit. So a path and its scalar twin take the same voxels and events, the images agree texel by texel (they are
bitwise equal here), the event counts agree, and the gradients agree to float rounding. A wrong event order, a
missed boundary case or a wrong weight would part the paths and show up as differences of order one.
"""
import pytest
import torch

import torch_appearance as ta
from torch_appearance._ext import _C

from torch_appearance.testing import simd_walk_level

pytestmark = pytest.mark.skipif(simd_walk_level() < 1, reason="needs a CPU with AVX2 (or TA_SIMD is 0)")
WIDTHS = [pytest.param(1, id="avx2"),
          pytest.param(2, id="avx512", marks=pytest.mark.skipif(simd_walk_level() < 2, reason="needs AVX-512F"))]


def _medium(shape, seed=3):
    """A chromatic float32 medium with exact zeros (σ_t = 0: the floored reference; α = 0: zero-safe weights)."""
    gen = torch.Generator().manual_seed(seed)
    sigma_t = torch.rand((3, *shape), generator=gen, dtype=torch.float64) * 20 + 1
    albedo = torch.rand((3, *shape), generator=gen, dtype=torch.float64) * 0.3 + 0.7
    sigma_t[:, 0, 0, :2] = 0.0
    albedo[:, -1, 1, 1:3] = 0.0
    return sigma_t.float(), albedo.float()


def _run(walk_kernel, mode, sigma_t, albedo, threads=2, **kwargs):
    """(image, grad σ_t, grad albedo, stats) of render_texels with the walk `mode` (0 scalar, 1 AVX2, 2 AVX-512)."""
    walk_kernel(mode)
    torch.set_num_threads(threads)
    s = sigma_t.clone().requires_grad_()
    a = albedo.clone().requires_grad_()
    stats = {}
    image = ta.render_texels(s, a, voxel_size=0.1, stats=stats, **kwargs)
    weights = torch.linspace(-1.0, 2.0, image.numel()).reshape(image.shape)
    (image * weights).sum().backward()
    return image.detach(), s.grad, a.grad, stats


def _assert_twins(simd, scalar, grad_rtol=1e-3, replay_events=True):
    image_s, image_c = simd[0], scalar[0]
    # texel by texel: equal up to float rounding of the weights (exp, log: a few ulp per event)
    same = float(((image_s - image_c).abs() <= 1e-5 * image_c.abs().clamp_min(1e-3)).float().mean())
    assert same >= 0.99, f"only {same:.3f} of the texel values are the scalar walk's"
    assert float((image_s - image_c).abs().max()) < 0.05
    for key in ("scatter_events", "truncated_paths"):
        a, b = simd[3][key], scalar[3][key]
        assert abs(a - b) <= 1e-3 * max(b, 1000), f"{key}: SIMD {a} vs scalar {b}"
    if replay_events:
        a, b = simd[3]["backward_scatter_events"], scalar[3]["backward_scatter_events"]
        assert abs(a - b) <= 1e-3 * b, f"backward_scatter_events: SIMD {a} vs scalar {b}"
    for k, name in ((1, "sigma_t"), (2, "albedo")):
        g_s, g_c = simd[k], scalar[k]
        assert bool(torch.isfinite(g_s).all())
        rel = float((g_s - g_c).abs().sum() / g_c.abs().sum())
        assert rel <= grad_rtol, f"grad {name}: relative L1 difference {rel:.3g}"


@pytest.mark.parametrize("width", WIDTHS)
@pytest.mark.parametrize("face,ior", [("top", 1.5), ("bottom", 1.3), ("both", None)])
def test_simd_walk_is_the_scalar_walk(walk_kernel, width, face, ior):
    sigma_t, albedo = _medium((6, 11, 13))
    kw = dict(face=face, ior=ior, g=0.3, spp=8, seed=5)
    simd = _run(walk_kernel, width, sigma_t, albedo, **kw)
    scalar = _run(walk_kernel, 0, sigma_t, albedo, **kw)
    _assert_twins(simd, scalar)


@pytest.mark.parametrize("width", WIDTHS)
def test_simd_walk_cut_by_depth_and_roulette(walk_kernel, width):
    """max_depth cuts (counted, contributing 0) and Russian roulette from the first interaction on."""
    sigma_t, albedo = _medium((8, 9, 9), seed=4)
    kw = dict(face="top", ior=1.5, g=-0.2, spp=8, seed=9, max_depth=12, rr_depth=0)
    simd = _run(walk_kernel, width, sigma_t, albedo, **kw)
    scalar = _run(walk_kernel, 0, sigma_t, albedo, **kw)
    assert scalar[3]["truncated_paths"] > 100  # the cut is exercised
    _assert_twins(simd, scalar)


@pytest.mark.parametrize("width", WIDTHS)
def test_simd_walk_with_explicit_sampling_medium(walk_kernel, width):
    """Ratio weights f/p_ref ≠ 1 in the forward and the replay (a sampling medium unlike the parameters)."""
    sigma_t, albedo = _medium((5, 8, 8), seed=6)
    ref_s = (sigma_t * 0.7 + 2.0).detach()
    ref_a = (albedo * 0.5 + 0.4).clamp(max=1.0).detach()
    kw = dict(face="top", ior=1.5, g=0.5, spp=8, seed=2, sampling_sigma_t=ref_s, sampling_albedo=ref_a)
    simd = _run(walk_kernel, width, sigma_t, albedo, **kw)
    scalar = _run(walk_kernel, 0, sigma_t, albedo, **kw)
    assert float(simd[0].std()) > 0
    _assert_twins(simd, scalar)


@pytest.mark.parametrize("width", WIDTHS)
@pytest.mark.parametrize("capacity", [0, 4])
def test_simd_replay_of_paths_longer_than_the_lane_tape(walk_kernel, width, capacity):
    """Paths that do not fit their lane's tape are replayed by the scalar code (walk and deposit)."""
    sigma_t, albedo = _medium((6, 9, 10), seed=8)
    kw = dict(face="both", ior=1.5, g=0.3, spp=4, seed=3)
    old = _C._set_tape_capacity(capacity)
    try:
        short = _run(walk_kernel, width, sigma_t, albedo, **kw)
    finally:
        _C._set_tape_capacity(old)
    simd = _run(walk_kernel, width, sigma_t, albedo, **kw)
    scalar = _run(walk_kernel, 0, sigma_t, albedo, **kw)
    _assert_twins(short, scalar, replay_events=False)  # (the replayed paths are walked again: more events)
    _assert_twins(simd, scalar)
    if capacity == 0:  # every path was walked a second time by the scalar replay
        assert short[3]["backward_scatter_events"] > 1.5 * simd[3]["backward_scatter_events"]


@pytest.mark.parametrize("width", WIDTHS)
def test_simd_walk_does_not_depend_on_threads_or_partition(walk_kernel, width):
    sigma_t, albedo = _medium((5, 10, 12), seed=1)
    kw = dict(face="top", ior=1.5, g=0.3, spp=4, seed=7)
    one = _run(walk_kernel, width, sigma_t, albedo, threads=1, **kw)
    two = _run(walk_kernel, width, sigma_t, albedo, threads=2, **kw)
    assert torch.equal(one[0], two[0])
    walk_kernel(width)
    with torch.no_grad():
        parts = [ta.render_texels(sigma_t, albedo, voxel_size=0.1, partition=(r, 3), **kw) for r in range(3)]
    assert torch.equal(sum(parts), one[0])


@pytest.mark.parametrize("width", WIDTHS)
def test_simd_walk_serves_float32_slabs_only(walk_kernel, width):
    """float64 grids keep the scalar walk: its images equal the scalar walk's bitwise with a SIMD walk on."""
    sigma_t, albedo = _medium((4, 6, 6))
    kw = dict(face="top", ior=1.5, g=0.3, spp=4, seed=1)
    on = _run(walk_kernel, width, sigma_t.double(), albedo.double(), **kw)
    off = _run(walk_kernel, 0, sigma_t.double(), albedo.double(), **kw)
    for x, y in zip(on[:3], off[:3]):
        assert torch.equal(x, y)


@pytest.mark.skipif(simd_walk_level() < 2, reason="needs AVX-512F")
def test_avx2_and_avx512_walks_take_the_same_paths(walk_kernel):
    """Both widths compute every event with the same IEEE operations: the images are bitwise equal, the event counts
    equal, and the gradients differ only by the order of the deposits (float rounding)."""
    sigma_t, albedo = _medium((6, 12, 10), seed=11)
    ref_s = (sigma_t * 0.8 + 1.0).detach()
    for kw in (dict(face="both", ior=1.5, g=0.4, spp=6, seed=4),
               dict(face="top", ior=None, g=-0.3, spp=6, seed=8, sampling_sigma_t=ref_s)):
        a = _run(walk_kernel, 1, sigma_t, albedo, **kw)
        b = _run(walk_kernel, 2, sigma_t, albedo, **kw)
        assert torch.equal(a[0], b[0])
        for key in ("scatter_events", "truncated_paths", "backward_scatter_events"):
            assert a[3][key] == b[3][key], key
        for k in (1, 2):
            assert float((a[k] - b[k]).abs().sum() / a[k].abs().sum()) < 1e-5


@pytest.mark.parametrize("env,most", [("0", 0), ("avx2", 1)])
def test_ta_simd_limits_the_walk(env, most):
    """TA_SIMD=0 leaves the scalar walk, TA_SIMD=avx2 at most the AVX2 walk (read once, at the first render)."""
    import os
    import subprocess
    import sys
    code = "from torch_appearance._ext import _C; print(_C._set_simd(-1))"
    out = subprocess.run([sys.executable, "-c", code], env={**os.environ, "TA_SIMD": env}, capture_output=True,
                         text=True, timeout=120, check=True)
    level = int(out.stdout.strip().splitlines()[-1])
    assert level <= most
    if env == "avx2":
        assert level == min(simd_walk_level(), 1)


def test_set_simd_refuses_unknown_modes():
    with pytest.raises(RuntimeError, match="mode: expected -1"):
        _C._set_simd(3)


@pytest.mark.parametrize("width", WIDTHS)
def test_simd_walk_below_the_albedo_floor(walk_kernel, width):
    """Albedo under the sampling floor (0.05) in much of the medium: the walk samples with the floored albedo and
    weighs with the medium's own (ratio f/p ≠ 1 at every such collision)."""
    sigma_t, albedo = _medium((5, 8, 9), seed=12)
    albedo = albedo * 0.06  # about 0.04–0.06: half the voxels under the floor
    kw = dict(face="top", ior=1.5, g=0.2, spp=16, seed=6)
    simd = _run(walk_kernel, width, sigma_t, albedo, **kw)
    scalar = _run(walk_kernel, 0, sigma_t, albedo, **kw)
    assert float(simd[2].abs().sum()) > 0
    _assert_twins(simd, scalar)
