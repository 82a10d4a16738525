"""The single-walk replay of the backward pass (csrc/core/tape.h) against the two-pass replay it replaced.

The single walk records each path's events in a per-thread tape and deposits them once the path's weight is known;
a path that does not fit the tape is walked twice (the two-pass replay). Both must give bitwise the same gradients
(same expressions, operands and order). ``_C._set_tape_capacity(0)`` sends every path through the two-pass replay,
a small capacity mixes both, so each comparison below checks the tape deposit against an independent code path.
All of it is the scalar walk's (the SIMD slab walks are tested against it in test_volpath_simd.py).
"""
import math

import pytest
import torch

import torch_appearance as ta
from torch_appearance._ext import _C
from torch_appearance.render import DiscLight, OrthographicCamera, Scene, SDFBoundary


@pytest.fixture(autouse=True)
def _scalar_walk(walk_kernel):
    walk_kernel(0)


@pytest.fixture
def tape_capacity():
    """Set the tape capacity for one call; restores the default afterwards."""
    old = _C._set_tape_capacity(1 << 14)
    _C._set_tape_capacity(old)

    def set_capacity(segments):
        _C._set_tape_capacity(segments)

    yield set_capacity
    _C._set_tape_capacity(old)


def _medium(dtype, shape, chromatic, seed=3):
    gen = torch.Generator().manual_seed(seed)
    base = torch.rand((3 if chromatic else 1, *shape), generator=gen, dtype=torch.float64) * 20 + 1
    sigma_t = base.expand(3, *shape).clone()
    albedo = torch.rand((3, *shape), generator=gen, dtype=torch.float64) * 0.3 + 0.7
    # exact zeros: σ_t = 0 (the floored reference samples collisions there) and α = 0 (zero-safe weights)
    sigma_t[:, 0, 0, :2] = 0.0
    albedo[:, -1, 1, 1:3] = 0.0
    return sigma_t.to(dtype), albedo.to(dtype)


def _gradients(render, sigma_t, albedo, need=(True, True), threads=2, stats=None):
    torch.set_num_threads(threads)
    s = sigma_t.clone().requires_grad_(need[0])
    a = albedo.clone().requires_grad_(need[1])
    image = render(s, a, {} if stats is None else stats)
    weights = torch.linspace(-1.0, 2.0, image.numel(), dtype=image.dtype).reshape(image.shape)
    (image * weights).sum().backward()
    return image.detach(), s.grad, a.grad


def _assert_same(first, second):
    for x, y in zip(first, second):
        assert (x is None) == (y is None)
        if x is not None:
            assert torch.equal(x, y), f"max |difference| {float((x - y).abs().max()):.3g}"


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("chromatic", [True, False])  # one walk per channel (lanes 1) / one walk for three (lanes 3)
@pytest.mark.parametrize("need", [(True, True), (True, False), (False, True)])
def test_slab_tape_equals_two_pass_replay(tape_capacity, dtype, chromatic, need):
    sigma_t, albedo = _medium(dtype, (5, 6, 7), chromatic)

    def render(s, a, stats):
        return ta.render_texels(s, a, voxel_size=0.1, face="both", g=0.3, ior=1.5, spp=3, seed=11, stats=stats)

    stats = [{}, {}, {}]
    tape = _gradients(render, sigma_t, albedo, need, stats=stats[0])
    tape_capacity(0)
    two_pass = _gradients(render, sigma_t, albedo, need, stats=stats[1])
    tape_capacity(4)  # most paths overflow the first tapes, the tape grows, later paths fit: both kinds mixed
    mixed = _gradients(render, sigma_t, albedo, need, stats=stats[2])
    _assert_same(tape, two_pass)
    _assert_same(tape, mixed)
    assert any(g is not None and bool((g != 0).any()) for g in tape[1:])
    # the replay walks counted: one per path with the tape, a second one for every escaped path without it
    events = [st["backward_scatter_events"] for st in stats]
    assert events[0] < events[2] < events[1]


def test_scene_with_direction_dependent_emitter(tape_capacity):
    """SDF dielectric boundary (crossings and re-entries) and a disc light: the escape direction decides L_e."""
    n, h = 8, 0.1
    k, j, i = torch.meshgrid(*(torch.arange(n + 1, dtype=torch.float64),) * 3, indexing="ij")
    sdf = ((i - n / 2) ** 2 + (j - n / 2) ** 2 + (k - n / 2) ** 2).sqrt() * h - 0.3
    scene = Scene(voxel_size=h, origin=(-0.4, -0.4, -0.4), boundary=SDFBoundary(sdf, ior=1.5), g=0.2,
                  sensor=OrthographicCamera(origin=(0.3, 0.2, 2), target=(0, 0, 0), up=(0, 1, 0),
                                            extent_mm=(0.8, 0.8), resolution=(6, 6)),
                  emitter=DiscLight((1, -1, 2), 20.0, 5.0, 0.3))
    sigma_t, albedo = _medium(torch.float64, (n, n, n), chromatic=True, seed=5)

    def render(s, a, stats):
        return ta.render_scene(scene, s, a, spp=4, seed=2, stats=stats)

    tape = _gradients(render, sigma_t, albedo)
    tape_capacity(0)
    two_pass = _gradients(render, sigma_t, albedo)
    _assert_same(tape, two_pass)
    assert math.isfinite(float(tape[1].abs().sum())) and bool((tape[1] != 0).any())


def test_tape_capacity_is_checked():
    with pytest.raises(RuntimeError, match="segments: expected >= 0"):
        _C._set_tape_capacity(-1)
