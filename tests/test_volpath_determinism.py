"""Reproducibility: results depend on the seed only, not on thread scheduling or thread count."""
import pytest
import torch

import torch_appearance as ta


def medium(dtype=torch.float32, chromatic=True):
    g = torch.Generator().manual_seed(0)
    sigma = torch.rand(3 if chromatic else 1, 5, 9, 7, generator=g, dtype=dtype) * 20 + 0.5
    sigma = sigma.expand(3, -1, -1, -1).contiguous()
    albedo = torch.rand(3, 5, 9, 7, generator=g, dtype=dtype)
    return sigma, albedo


def run(threads, seed=3, chromatic=True, dtype=torch.float32):
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        sigma, albedo = medium(dtype, chromatic)
        s, a = sigma.requires_grad_(), albedo.requires_grad_()
        img = ta.render_texels(s, a, voxel_size=0.1, face="both", spp=16, seed=seed)
        (img * torch.linspace(0, 1, img.numel(), dtype=dtype).view_as(img)).sum().backward()
        return img.detach(), s.grad, a.grad
    finally:
        torch.set_num_threads(before)


@pytest.mark.parametrize("chromatic", [True, False])
def test_same_seed_identical(chromatic):
    a, b = run(2, chromatic=chromatic), run(2, chromatic=chromatic)
    for x, y in zip(a, b):
        assert torch.equal(x, y)
    c = run(2, seed=4, chromatic=chromatic)
    assert not torch.equal(a[0], c[0])


@pytest.mark.parametrize("chromatic", [True, False])
def test_thread_count_independent(chromatic):
    one, two = run(1, chromatic=chromatic), run(2, chromatic=chromatic)
    assert torch.equal(one[0], two[0])  # forward: bit-identical
    for g1, g2 in zip(one[1:], two[1:]):  # gradients: summation order differs between thread counts only
        torch.testing.assert_close(g2, g1, rtol=1e-5, atol=1e-5 * float(g1.abs().max()))


def test_large_seed_and_negative_seed_are_distinct_streams():
    sigma, albedo = medium()
    imgs = [ta.render_texels(sigma, albedo, voxel_size=0.1, spp=4, seed=s) for s in (0, 1, 2 ** 63, 2 ** 64 - 1, -1)]
    assert torch.equal(imgs[3], imgs[4])  # -1 and 2**64-1 are the same 64 bits
    for i in range(4):
        for j in range(i + 1, 4):
            assert not torch.equal(imgs[i], imgs[j])


def test_float32_float64_agree_statistically():
    s32, a32 = medium(torch.float32)
    i32 = ta.render_texels(s32, a32, voxel_size=0.1, spp=256, seed=1).double()
    i64 = ta.render_texels(s32.double(), a32.double(), voxel_size=0.1, spp=256, seed=2)
    assert abs(float(i32.mean() - i64.mean())) < 5e-3
