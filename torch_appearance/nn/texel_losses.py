"""The appearance losses' sparse texel path: E1, E2, E3 (Nindel et al. 2021, eqs. 11–18) on ``(N, 3)`` texel
colours at ``(N, 3)`` voxel positions, without a voxel grid.

:class:`TexelFilters` holds the Gaussian (SSIM) and Sobel (edge) filters of :mod:`.losses` as exact sparse
texel-to-texel CSR matrices, built once per set of positions; :func:`texel_appearance_loss` takes the same value
and gradients as :func:`~torch_appearance.nn.losses.appearance_loss` on the colours placed on the grid, at a cost
that grows with the texels and their neighbours, not with the bounding box (objects in the print pipeline use it,
through :meth:`~torch_appearance.nn.losses.AppearanceLoss.forward_texels`). Conventions (L*a*b* normalisation,
mask-normalised neighbourhoods, edges of the difference) are those of :mod:`.losses`.
"""
import torch
from kornia.filters import get_gaussian_kernel1d

from ..checks import check_finite, check_tensor, describe
from ..color import rgb_to_lab
from .losses import (_EDGE_FACTOR, _FLOAT_DTYPES, LAB_OFFSET, LAB_SCALE, SSIM_C1, SSIM_C2, _check_gamma, _check_like,
                     _check_window, _combine_terms, _sobel_taps)

__all__ = ["TexelFilters", "texel_appearance_loss"]

#: Rows of texels whose neighbour lists are built at once (bounds the temporary memory of the construction).
_ROW_CHUNK = 4096


def _check_positions(positions):
    shape_desc = "(N, 3) with N >= 1 (voxel indices z, y, x)"
    check_tensor("positions", positions, shape_desc, ndim=2, last=3, dtypes="integer", nonempty=True)


def _csr(crow, col, values, n):
    import warnings
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Sparse CSR tensor support is in beta")
        return torch.sparse_csr_tensor(crow, col, values, (n, n), check_invariants=False)


class _SparseFilter(torch.autograd.Function):
    """``A @ x`` for a sparse ``(N, N)`` CSR matrix with ``Aᵀ = sign · A`` (symmetric or antisymmetric kernels)."""

    @staticmethod
    def forward(ctx, x, matrix, sign):
        ctx.matrix, ctx.sign = matrix, sign
        return matrix @ x

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad):
        grad_x = None
        if ctx.needs_input_grad[0]:
            grad_x = ctx.matrix @ grad.contiguous()
            if ctx.sign < 0:
                grad_x = grad_x.neg_()
        return grad_x, None, None  # matrix, sign


class TexelFilters:
    """Exact sparse texel-to-texel forms of the Gaussian (SSIM) and Sobel (edge) filters of the appearance losses.

    Texels are voxels ``positions`` of a grid whose other voxels are empty (zero), so the filtered value at texel
    ``i`` is ``Σ_j k(p_j − p_i) x_j`` over the texels ``j`` inside the kernel's window (``|p_j − p_i|∞ ≤ r``). The
    class builds these sums once as ``(N, N)`` CSR matrices (:func:`torch.sparse_csr_tensor`): the 3D Gaussian
    ``g(dz) g(dy) g(dx)`` (``window_size`` taps, std ``sigma``, kornia's taps as in :func:`masked_ssim3d`) and the
    three Sobel kernels of :func:`sobel_kernels_3d`. The neighbour lists come from the sorted linear voxel keys:
    for every texel and every ``(dz, dy)`` row of the window, the texels with ``|dx| ≤ r`` are one contiguous
    run of the sorted keys (two :func:`torch.searchsorted` per row), so construction is vectorised, costs
    ``O(N (2r+1)² log N + nnz)`` and memory follows the texels, not the bounding box.

    Internally the texels are kept in the sorted key order (:attr:`order`); the losses are sums over texels, so
    the order does not change them. Matrices are built on first use per dtype and device and cached.

    Memory: ``nnz`` ≈ N × (texels in an 11³ window) for the Gaussian (≈ 150–250 per texel on a surface),
    ≤ 27 N for the Sobel structure; values in the compute dtype, column indices int32 (int64 above 2³¹ entries).

    Args:
        positions: ``(N, 3)`` integer voxel indices ``(z, y, x)`` (``k, j, i``) of the texels, all distinct.
        window_size: odd number of Gaussian taps per axis (default 11).
        sigma: Gaussian standard deviation in voxels (default 1.5).

    Example:
        >>> pos = torch.tensor([[0, 0, 0], [0, 0, 1], [0, 1, 0], [3, 3, 3]])
        >>> f = TexelFilters(pos, window_size=5)  # |Δ|∞ <= 2: the first three are neighbours, the last is alone
        >>> f.num_texels, f.gaussian_nnz(torch.float64)
        (4, 10)
    """

    def __init__(self, positions, window_size=11, sigma=1.5):
        _check_positions(positions)
        _check_window(window_size, sigma)
        self.window_size, self.sigma = window_size, float(sigma)
        self.positions = positions.detach().to("cpu", torch.int64).clone()
        self.num_texels = int(self.positions.shape[0])
        r = max(window_size // 2, 1)
        lo = self.positions.min(0).values
        pos = self.positions - lo + r  # every window offset stays inside the padded box: no wrap-around of keys
        extent = pos.max(0).values + r + 1
        self._strides = (int(extent[1] * extent[2]), int(extent[2]))
        if float(extent[0]) * float(extent[1]) * float(extent[2]) >= 2.0**62:
            raise ValueError(f"positions span {tuple((extent - 2 * r).tolist())} voxels: too large for 64-bit keys")
        keys = pos[:, 0] * self._strides[0] + pos[:, 1] * self._strides[1] + pos[:, 2]
        self._keys, self.order = torch.sort(keys)
        if self.num_texels > 1 and bool((self._keys[1:] == self._keys[:-1]).any()):
            dup = int((self._keys[1:] == self._keys[:-1]).sum())
            raise ValueError(f"positions: expected distinct voxels, got {dup} duplicate(s) among {self.num_texels}")
        self._pos = pos[self.order]  # (N, 3) in sorted order
        self._cache = {}

    def __repr__(self):
        return f"TexelFilters(num_texels={self.num_texels}, window_size={self.window_size}, sigma={self.sigma})"

    def matches(self, positions, window_size, sigma):
        """Whether these filters were built for ``positions`` (same values) and window."""
        return (window_size == self.window_size and float(sigma) == self.sigma and isinstance(positions, torch.Tensor)
                and tuple(positions.shape) == tuple(self.positions.shape)
                and torch.equal(positions.detach().to("cpu", torch.int64), self.positions))

    # ---------------------------------------------------------------------------------------------- construction
    def _runs(self, start, stop, row_shift, radius):
        """For texels ``start:stop`` (sorted order) and every window row ``(dz, dy)``: the first sorted index and the
        number of texels with ``|dx| <= radius`` in that row, ``(n_c, R)`` each (the run is contiguous)."""
        base = self._keys[start:stop, None] + row_shift[None, :]
        first = torch.searchsorted(self._keys, base - radius)
        return first, torch.searchsorted(self._keys, base + radius, right=True) - first

    def _build(self, radius, taps, dtype):
        """CSR structure of the ``(2r+1)³`` window and, per kernel ``(tz, ty, tx)`` (each ``2r+1`` float64 taps),
        the values ``tz[dz+r] ty[dy+r] tx[dx+r]``; ``(crow, col, [values...])`` with rows/columns in sorted order.

        Two passes over chunks of rows (counts, then entries written into preallocated arrays), so the temporary
        memory is bounded by the chunk, not by ``nnz``."""
        n, (sz, sy) = self.num_texels, self._strides
        d = torch.arange(-radius, radius + 1)
        dz, dy = torch.meshgrid(d, d, indexing="ij")
        dz, dy = dz.reshape(-1), dy.reshape(-1)  # (R,) rows of the window, in increasing key order
        row_shift = dz * sz + dy * sy
        chunks = [(a, min(a + _ROW_CHUNK, n)) for a in range(0, n, _ROW_CHUNK)]
        row_nnz = torch.cat([self._runs(a, b, row_shift, radius)[1].sum(1) for a, b in chunks])
        nnz = int(row_nnz.sum())
        index_dtype = torch.int32 if nnz < 2**31 - 1 else torch.int64
        crow = torch.zeros(n + 1, dtype=torch.int64)
        torch.cumsum(row_nnz, 0, out=crow[1:])
        col = torch.empty(nnz, dtype=index_dtype)
        values = [torch.empty(nnz, dtype=dtype) for _ in taps]
        for a, b in chunks:
            first, counts = self._runs(a, b, row_shift, radius)
            counts = counts.reshape(-1)  # (n_c R,) in row-major (texel, window row) order
            lo, hi = int(crow[a]), int(crow[b])
            run_start = torch.cumsum(counts, 0) - counts
            j = torch.repeat_interleave(first.reshape(-1) - run_start, counts, output_size=hi - lo)
            j += torch.arange(hi - lo)
            pair = torch.repeat_interleave(counts, output_size=hi - lo)  # (texel, window row) of each entry
            del first, counts, run_start
            ox = self._pos[j, 2] - self._pos[a + pair // len(dz), 2] + radius
            w = pair % len(dz)
            oz, oy = dz[w] + radius, dy[w] + radius
            del pair, w
            col[lo:hi] = j
            for out, (tz, ty, tx) in zip(values, taps):
                out[lo:hi] = tz[oz] * ty[oy] * tx[ox]
            del j, ox, oz, oy
        return crow.to(index_dtype), col, values

    def _matrices(self, kind, dtype, device):
        key = (kind, dtype, torch.device(device))
        if key not in self._cache:
            if kind == "gaussian":
                r = self.window_size // 2
                g = get_gaussian_kernel1d(self.window_size, self.sigma, dtype=torch.float64).reshape(-1)
                crow, col, (values,) = self._build(r, [(g, g, g)], dtype)
                matrix = _csr(crow, col, values, self.num_texels).to(device)
                weight = (matrix @ torch.ones(self.num_texels, 1, dtype=dtype, device=device))  # Σ_j g over texels
                self._cache[key] = (matrix, weight)
            else:
                h, d = _sobel_taps(torch.float64, None)
                crow, col, values = self._build(1, [(h, h, d), (h, d, h), (d, h, h)], dtype)
                self._cache[key] = tuple(_csr(crow, col, v, self.num_texels).to(device) for v in values)
        return self._cache[key]

    def gaussian_nnz(self, dtype=torch.float32, device="cpu"):
        """Number of stored entries of the Gaussian matrix (builds it if needed)."""
        return int(self._matrices("gaussian", dtype, device)[0].values().numel())

    def nbytes(self):
        """Bytes held by the cached matrices."""
        total = 0
        for value in self._cache.values():
            for m in value:
                if m.layout == torch.sparse_csr:
                    total += sum(t.numel() * t.element_size() for t in (m.crow_indices(), m.col_indices(), m.values()))
                else:
                    total += m.numel() * m.element_size()
        return total

    # ---------------------------------------------------------------------------------------------- filters
    def gaussian(self, x):
        """``(N, C)`` (sorted order) → ``(N, C)``: ``Σ_j g(p_j − p_i) x_j`` over texels; differentiable."""
        matrix, _ = self._matrices("gaussian", x.dtype, x.device)
        return _SparseFilter.apply(x, matrix, 1)

    def gaussian_weight(self, dtype, device):
        """``(N, 1)``: ``Σ_j g(p_j − p_i)`` over texels (``G∗m`` of the dense path), sorted order."""
        return self._matrices("gaussian", dtype, device)[1]

    def sobel(self, x):
        """``(N, C)`` (sorted order) → three ``(N, C)`` Sobel responses ``(S_x, S_y, S_z)`` with zero outside."""
        return tuple(_SparseFilter.apply(x, m, -1) for m in self._matrices("sobel", x.dtype, x.device))


def _check_texel_pair(pred, target, filters):
    n = filters.num_texels
    shape_desc = f"({n}, 3) or (B, {n}, 3) (one linear RGB colour per texel position)"
    for name, x in (("pred", pred), ("target", target)):
        check_tensor(name, x, shape_desc, ndim=(2, 3), last=3, dtypes=_FLOAT_DTYPES)
        if x.shape[-2] != n:
            raise ValueError(f"{name}: expected shape {shape_desc}, got {tuple(x.shape)}")
        if x.dim() == 3 and x.shape[0] == 0:
            raise ValueError(f"{name}: expected a batch of B >= 1, got shape {tuple(x.shape)}")
    _check_like(("pred", "target"), pred, target)
    for name, x in (("pred", pred), ("target", target)):
        check_finite(name, x)


def _texel_columns(x, order):
    """``(N, 3)`` or ``(B, N, 3)`` → ``(N, B·3)`` in the filters' sorted texel order."""
    if x.dim() == 2:
        x = x[None]
    b, n, c = x.shape
    return x.index_select(1, order.to(x.device)).permute(1, 0, 2).reshape(n, b * c)


def texel_appearance_loss(pred, target, filters, gamma=(1.0, 3.0, 1.0), return_parts=False):
    r"""E (eq. 18) on per-texel colours: the same value as :func:`appearance_loss` on the voxel grid, without it.

    ``appearance_loss(texels_to_grid(pred), texels_to_grid(target), mask)`` equals
    ``texel_appearance_loss(pred, target, TexelFilters(positions))`` to float rounding (same E1, E2, E3, same
    gradients): the Gaussian and Sobel filters of E2 and E3 are the sparse texel-to-texel matrices of
    :class:`TexelFilters`, so time and memory grow with the texels and their neighbours, not with the grid.

    Args:
        pred: ``(N, 3)`` or ``(B, N, 3)`` linear RGB per texel (row ``n`` at ``filters.positions[n]``),
            float32/float64.
        target: same shape, dtype and device.
        filters: :class:`TexelFilters` of the texel positions (it also fixes the SSIM window).
        gamma: ``(γ1, γ2, γ3)`` as in :func:`appearance_loss`.
        return_parts: also return ``{"E1", "E2", "E3"}``; a part with γ = 0 is computed without gradient.

    Returns:
        the scalar total, or ``(total, parts)`` with ``return_parts``.

    Example:
        >>> pos = torch.stack(torch.meshgrid(torch.arange(2), torch.arange(4), torch.arange(4), indexing="ij"),
        ...                   -1).reshape(-1, 3)
        >>> x, t = torch.rand(32, 3), torch.rand(32, 3)
        >>> total, parts = texel_appearance_loss(x, t, TexelFilters(pos), return_parts=True)
        >>> sorted(parts)
        ['E1', 'E2', 'E3']
    """
    if not isinstance(filters, TexelFilters):
        raise TypeError(f"filters: expected a TexelFilters, got {describe(filters)}")
    gamma = _check_gamma(gamma)
    _check_texel_pair(pred, target, filters)
    batch = 1 if pred.dim() == 2 else pred.shape[0]
    count = batch * filters.num_texels
    x, y = _texel_columns(pred, filters.order), _texel_columns(target, filters.order)  # (N, B·3)
    lab_x, lab_y = rgb_to_lab(x.view(-1, batch, 3), dim=-1), rgb_to_lab(y.view(-1, batch, 3), dim=-1)
    scale = torch.tensor(LAB_SCALE, dtype=x.dtype, device=x.device)
    offset = torch.tensor(LAB_OFFSET, dtype=x.dtype, device=x.device)
    norm_x = (lab_x * scale + offset).reshape(x.shape)
    norm_y = (lab_y * scale + offset).reshape(x.shape)

    def color():
        return (lab_x - lab_y).square().sum() / count

    def ssim():
        inv = 1.0 / filters.gaussian_weight(x.dtype, x.device)
        # the moments are taken of the colours minus a constant per column (the target's mean): variances and
        # covariances do not change, the means are shifted back, and the cancellation in E[x²] − E[x]² shrinks
        # from |x|² to |x − shift|² (in float32 this makes the sparse sums as accurate as the dense separable ones)
        shift = norm_y.detach().mean(dim=0, keepdim=True)
        cx, cy = norm_x - shift, norm_y - shift
        moments = filters.gaussian(torch.cat([cx, cx * cx, cx * cy, cy, cy * cy], dim=1)) * inv
        mu_x, e_xx, e_xy, mu_y, e_yy = moments.split(norm_x.shape[1], dim=1)
        var_x, var_y, cov = e_xx - mu_x.square(), e_yy - mu_y.square(), e_xy - mu_x * mu_y
        mu_x, mu_y = mu_x + shift, mu_y + shift
        mu_xy = mu_x * mu_y
        luminance = (2.0 * mu_xy + SSIM_C1) / (mu_x.square() + mu_y.square() + SSIM_C1)
        structure = (2.0 * cov + SSIM_C2) / (var_x + var_y + SSIM_C2)
        return 1.0 - (luminance * structure).sum() / (3 * count)

    def edge():
        responses = filters.sobel(norm_x - norm_y)
        return _EDGE_FACTOR * sum(s.square().sum() for s in responses) / count

    return _combine_terms(gamma, (color, ssim, edge), return_parts)
