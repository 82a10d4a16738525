"""Tests of the sparse texel path of the appearance losses (``TexelFilters``, ``texel_appearance_loss``,
``AppearanceLoss.forward_parts_texels``).

The sparse path must give the dense grid path's E1, E2, E3 and gradients (float64, to rounding) on texel sets that
look like object surfaces (a sphere shell cropped to its bounding box, so texels lie on every grid border) and on
scattered texels; its matrices must equal an explicit texel-to-texel weight matrix written from the kernels.
"""
import numpy as np
import pytest
import torch

from torch_appearance.nn import texel_losses
from torch_appearance.nn.losses import (AppearanceLoss, TexelFilters, appearance_loss, sobel_kernels_3d,
                                        texel_appearance_loss)

TIGHT = dict(rtol=1e-12, atol=1e-13)


def _sphere_shell(radius=5.3):
    """Voxels of a ball with a 6-neighbour outside it (as ``voxelize`` picks texels), cropped to the bounding
    box: ``(mask (D, H, W), positions (N, 3))``; texels touch all six faces of the grid."""
    n = int(np.ceil(2 * radius)) + 1
    c = (n - 1) / 2
    z, y, x = np.meshgrid(*(np.arange(n),) * 3, indexing="ij")
    inside = (z - c) ** 2 + (y - c) ** 2 + (x - c) ** 2 <= radius**2
    padded = np.pad(inside, 1)
    outside_nb = np.zeros_like(inside)
    for axis in range(3):
        for shift in (-1, 1):
            outside_nb |= ~np.roll(padded, shift, axis)[1:-1, 1:-1, 1:-1]
    shell = inside & outside_nb
    keep = [np.flatnonzero(shell.any(axis=tuple(a for a in range(3) if a != ax))) for ax in range(3)]
    shell = shell[np.ix_(*keep)]
    mask = torch.from_numpy(shell)
    return mask, mask.nonzero()


def _scattered(shape=(7, 9, 8), fraction=0.25, seed=0):
    g = torch.Generator().manual_seed(seed)
    mask = torch.rand(shape, generator=g) < fraction
    for corner in ((0, 0, 0), (-1, -1, -1), (0, -1, 0), (-1, 0, -1)):  # texels on the grid border and corners
        mask[corner] = True
    return mask, mask.nonzero()


def _colours(n, seed, batch=None, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    shape = (n, 3) if batch is None else (batch, n, 3)
    return 0.05 + 0.9 * torch.rand(shape, generator=g, dtype=dtype)


def _to_grid(values, positions, shape):
    """(N, 3) or (B, N, 3) → (3, D, H, W) or (B, 3, D, H, W), zeros elsewhere (differentiable)."""
    batch = values.dim() == 3
    v = values if batch else values[None]
    grid = v.new_zeros(tuple(shape) + (v.shape[0], 3))
    grid = grid.index_put((positions[:, 0], positions[:, 1], positions[:, 2]), v.transpose(0, 1))
    grid = grid.permute(3, 4, 0, 1, 2)
    return grid if batch else grid[0]


CASES = {"sphere_shell": _sphere_shell, "scattered": _scattered}


@pytest.mark.parametrize("case", sorted(CASES))
@pytest.mark.parametrize("batch", [None, 2])
def test_sparse_equals_dense_parts_and_gradients(case, batch):
    mask, pos = CASES[case]()
    n = len(pos)
    pred = _colours(n, 1, batch).requires_grad_(True)
    target = _colours(n, 2, batch).requires_grad_(True)
    total_d, parts_d = appearance_loss(_to_grid(pred, pos, mask.shape), _to_grid(target, pos, mask.shape), mask,
                                       gamma=(1.0, 3.0, 1.0), return_parts=True)
    filters = TexelFilters(pos)
    total_s, parts_s = texel_appearance_loss(pred, target, filters, gamma=(1.0, 3.0, 1.0), return_parts=True)
    assert sorted(parts_s) == ["E1", "E2", "E3"]
    for k in ("E1", "E2", "E3"):
        torch.testing.assert_close(parts_s[k], parts_d[k], **TIGHT, msg=f"{case} {k}")
        gd = torch.autograd.grad(parts_d[k], (pred, target), retain_graph=True)
        gs = torch.autograd.grad(parts_s[k], (pred, target), retain_graph=True)
        for a, b in zip(gs, gd):
            assert float(b.abs().max()) > 0
            torch.testing.assert_close(a, b, **TIGHT, msg=f"{case} grad {k}")
    torch.testing.assert_close(total_s, total_d, **TIGHT)


def test_float32_ssim_is_accurate():
    """In float32 the SSIM moments are sums of ~100 texels; E[x²] − E[x]² must not lose the variance to
    cancellation (the sparse path centres the colours first): E2 within 4e-6 of its float64 value on a smooth
    texture plus noise (without the centring the error is 3e-5)."""
    _, pos = _sphere_shell(12.3)
    p = pos.double()
    target = 0.5 + 0.3 * torch.stack([torch.sin(p[:, 0] / 5), torch.cos(p[:, 1] / 7), torch.sin(p[:, 2] / 4 + 1)], 1)
    pred = (target + 0.05 * torch.randn(target.shape, generator=torch.Generator().manual_seed(0),
                                        dtype=torch.float64)).clamp(0, 1)
    f = TexelFilters(pos)
    e64 = float(texel_appearance_loss(pred, target, f, gamma=(0, 1, 0)))
    e32 = float(texel_appearance_loss(pred.float(), target.float(), f, gamma=(0, 1, 0)))
    assert abs(e32 - e64) < 4e-6, (e32, e64)


@pytest.mark.parametrize("window_size, sigma", [(1, 1.5), (3, 0.7), (7, 2.0)])
def test_other_windows_and_a_lone_texel(window_size, sigma):
    """Other SSIM windows (down to one tap, where the Sobel window is the wider one) and a texel with no
    neighbour give the dense path's values."""
    mask, pos = _scattered((5, 6, 7), 0.3, seed=11)
    mask[:, :, 6] = False
    mask[0, 0, 6] = True  # alone: |Δ|∞ >= 2 to every other texel
    mask[:2, :2, 5] = False
    pos = mask.nonzero()
    pred, target = _colours(len(pos), 5), _colours(len(pos), 6)
    _, dense = appearance_loss(_to_grid(pred, pos, mask.shape), _to_grid(target, pos, mask.shape), mask,
                               window_size=window_size, sigma=sigma, return_parts=True)
    _, sparse = texel_appearance_loss(pred, target, TexelFilters(pos, window_size, sigma), return_parts=True)
    for k in ("E1", "E2", "E3"):
        torch.testing.assert_close(sparse[k], dense[k], **TIGHT, msg=k)


def test_matrices_equal_explicit_texel_weights():
    """The CSR matrices hold exactly ``k(p_j − p_i)`` for every pair of texels within the window (an explicit
    all-pairs reference from the 1D taps and ``sobel_kernels_3d``), in the filters' sorted order."""
    _, pos = _scattered((6, 8, 7), 0.3, seed=3)
    window, sigma = 5, 1.1
    f = TexelFilters(pos, window_size=window, sigma=sigma)
    p = pos[f.order].numpy()
    off = p[None, :, :] - p[:, None, :]  # (N, N, 3): p_j − p_i
    r = window // 2
    k = np.arange(-r, r + 1)
    g = np.exp(-k**2 / (2 * sigma**2))
    g /= g.sum()
    inside = (np.abs(off) <= r).all(-1)
    expected = np.where(inside, np.prod(g[np.clip(off + r, 0, 2 * r)], -1), 0.0)
    matrix, weight = f._matrices("gaussian", torch.float64, "cpu")
    np.testing.assert_allclose(matrix.to_dense().numpy(), expected, rtol=1e-13, atol=0)
    np.testing.assert_allclose(weight[:, 0].numpy(), expected.sum(1), rtol=1e-13)
    sobel = sobel_kernels_3d(dtype=torch.float64).numpy()  # [S_x, S_y, S_z][z, y, x]
    near = (np.abs(off) <= 1).all(-1)
    idx = np.clip(off + 1, 0, 2)
    for s, m in zip(sobel, f._matrices("sobel", torch.float64, "cpu")):
        ref = np.where(near, s[idx[..., 0], idx[..., 1], idx[..., 2]], 0.0)
        np.testing.assert_array_equal(m.to_dense().numpy(), ref)
    assert f.gaussian_nnz(torch.float64) == int(inside.sum())


def test_chunked_construction_is_the_same(monkeypatch):
    """The matrices are built in chunks of rows; chunks that split the texels anywhere give the same CSR arrays."""
    _, pos = _sphere_shell(4.2)
    whole = TexelFilters(pos)._matrices("gaussian", torch.float64, "cpu")[0]
    sobel = TexelFilters(pos)._matrices("sobel", torch.float64, "cpu")
    monkeypatch.setattr(texel_losses, "_ROW_CHUNK", 7)
    chunked = TexelFilters(pos)
    parts = chunked._matrices("gaussian", torch.float64, "cpu")[0]
    for a, b in zip((whole.crow_indices(), whole.col_indices(), whole.values()),
                    (parts.crow_indices(), parts.col_indices(), parts.values())):
        assert torch.equal(a, b)
    for a, b in zip(sobel, chunked._matrices("sobel", torch.float64, "cpu")):
        assert torch.equal(a.to_dense(), b.to_dense())


def test_gradcheck_and_order_invariance():
    mask, pos = _scattered((4, 5, 4), 0.4, seed=5)
    n = len(pos)
    f = TexelFilters(pos, window_size=3, sigma=0.9)
    x, t = _colours(n, 7).requires_grad_(True), _colours(n, 8)
    assert torch.autograd.gradcheck(lambda a: texel_appearance_loss(a, t, f), (x,))
    perm = torch.randperm(n, generator=torch.Generator().manual_seed(0))
    shuffled = texel_appearance_loss(x[perm], t[perm], TexelFilters(pos[perm], window_size=3, sigma=0.9))
    torch.testing.assert_close(shuffled, texel_appearance_loss(x, t, f), **TIGHT)


def test_module_forward_parts_texels_matches_and_caches():
    mask, pos = _sphere_shell(3.7)
    crit = AppearanceLoss(gamma=(1.0, 3.0, 0.0))
    x, t = _colours(len(pos), 3).float(), _colours(len(pos), 4).float()
    total_s, parts_s = crit.forward_parts_texels(x, t, pos)
    total_d, parts_d = crit.forward_parts(_to_grid(x, pos, mask.shape), _to_grid(t, pos, mask.shape), mask)
    for k in ("E1", "E2", "E3"):
        torch.testing.assert_close(parts_s[k], parts_d[k], rtol=2e-5, atol=1e-6)
    assert not parts_s["E3"].requires_grad  # γ3 = 0: reported without gradient, like the dense path
    torch.testing.assert_close(crit.forward_texels(x, t, pos), total_d, rtol=2e-5, atol=1e-6)
    first = crit.texel_filters(pos)
    assert crit.texel_filters(pos.clone()) is first  # equal positions reuse the matrices
    other = pos.clone()
    other[0, 0] += 100
    assert crit.texel_filters(other) is not first


def test_bad_inputs_are_named():
    _, pos = _scattered((3, 3, 3), 0.5)
    with pytest.raises(TypeError, match="positions"):
        TexelFilters(pos.double())
    with pytest.raises(ValueError, match="positions"):
        TexelFilters(pos[:, :2])
    with pytest.raises(ValueError, match="distinct"):
        TexelFilters(torch.cat([pos, pos[:1]]))
    f = TexelFilters(pos)
    x = _colours(len(pos), 0)
    with pytest.raises(ValueError, match="pred: expected shape"):
        texel_appearance_loss(x[:-1], x[:-1], f)
    with pytest.raises(TypeError, match="target: expected the dtype of pred"):
        texel_appearance_loss(x, x.float(), f)
    bad = x.clone()
    bad[0, 0] = float("nan")
    with pytest.raises(ValueError, match="target: expected finite values, got 1 NaN/Inf"):
        texel_appearance_loss(x, bad, f)
    with pytest.raises(TypeError, match="filters"):
        texel_appearance_loss(x, x, pos)
