"""Structured halftoning for ink quantisation: a tiled 3D blue-noise threshold volume.

Drawing each printer micro-voxel's ink independently (the paper's probabilistic quantisation) gives every ink its
fraction of a region only on average: by chance, voxels of one ink clump together and others leave holes, which
shows as grain. A *blue-noise threshold volume* replaces the independent uniform draw by a fixed threshold per
voxel, a permutation of the ranks ``(r + ½) / T³`` over a ``T × T × T`` tile whose low ranks (and every band of
ranks) are spread as evenly as possible. Thresholding a constant mixture with it gives each ink its fraction to
within one voxel per tile, in evenly spread voxels.

The tile comes from the void-and-cluster method (Ulichney, "The void-and-cluster method for dither array
generation", SPIE 1913, 1993), in 3D with periodic boundaries: a Gaussian energy marks the tightest cluster of
set voxels and the largest void; an initial pattern is relaxed by moving points from clusters to voids, its points
are ranked by removing tightest clusters, and the rest by filling largest voids. The 32³ tile takes about 5 s to
compute, so the package ships it (``blue_noise_32.npy``, ``blue_noise_tile(32)`` as uint16; a test checks that
they agree); it is shifted by the seed so that different seeds give different patterns.
"""
import functools
import os

import numpy as np

__all__ = ["blue_noise_tile", "shipped_tile", "blue_noise_thresholds", "TILE"]

#: Edge of the threshold tile in micro-voxels.
TILE = 32
_SHIPPED = os.path.join(os.path.dirname(os.path.abspath(__file__)), "blue_noise_32.npy")


def _kernel(size, sigma):
    """Periodic Gaussian energy kernel (size³), centred at index 0, doubled along each axis so that the kernel
    centred at any voxel is a plain slice (no copy)."""
    d = np.minimum(np.arange(size), size - np.arange(size)).astype(np.float64)
    g = np.exp(-d ** 2 / (2 * sigma ** 2))
    k = g[:, None, None] * g[None, :, None] * g[None, None, :]
    return np.tile(k, (2, 2, 2))


@functools.lru_cache(maxsize=4)
def blue_noise_tile(size=TILE, sigma=1.5, seed=0):
    """The void-and-cluster rank volume: ``int32`` (size, size, size), a permutation of ``0 .. size³ - 1``.

    Args:
        size: tile edge (>= 4). sigma: the energy Gaussian's width in voxels (1.5 is Ulichney's choice).
        seed: the initial random pattern's seed.
    """
    n = size ** 3
    kernel = _kernel(size, sigma)

    def energy_of(points):
        e = np.zeros((size, size, size))
        for p in zip(*np.unravel_index(points, (size,) * 3)):
            _add(e, p, 1.0)
        return e

    def _add(e, p, sign):
        z, y, x = p
        e += sign * kernel[size - z:2 * size - z, size - y:2 * size - y, size - x:2 * size - x]

    rng = np.random.Generator(np.random.PCG64(seed))
    ones = max(1, n // 10)
    pattern = np.zeros(n, dtype=bool)
    pattern[rng.permutation(n)[:ones]] = True
    energy = energy_of(np.flatnonzero(pattern)).reshape(-1)
    flat_e = energy.reshape(-1)
    # phase 0: move the tightest cluster to the largest void until that would put it back
    for _ in range(20 * n):
        cluster = int(np.argmax(np.where(pattern, flat_e, -np.inf)))
        pattern[cluster] = False
        _add(flat_e.reshape((size,) * 3), np.unravel_index(cluster, (size,) * 3), -1.0)
        void = int(np.argmin(np.where(pattern, np.inf, flat_e)))
        pattern[void] = True
        _add(flat_e.reshape((size,) * 3), np.unravel_index(void, (size,) * 3), 1.0)
        if void == cluster:
            break
    rank = np.empty(n, dtype=np.int32)
    initial = pattern.copy()
    e0 = flat_e.copy()
    # phase 1: rank the initial points, removing the tightest cluster each time
    left = int(initial.sum())
    while left:
        cluster = int(np.argmax(np.where(initial, e0, -np.inf)))
        initial[cluster] = False
        _add(e0.reshape((size,) * 3), np.unravel_index(cluster, (size,) * 3), -1.0)
        left -= 1
        rank[cluster] = left
    # phase 2 and 3: fill the largest void until the tile is full (ranks ones .. n-1)
    filled = pattern
    for r in range(ones, n):
        void = int(np.argmin(np.where(filled, np.inf, flat_e)))
        filled[void] = True
        _add(flat_e.reshape((size,) * 3), np.unravel_index(void, (size,) * 3), 1.0)
        rank[void] = r
    return rank.reshape((size,) * 3)


@functools.lru_cache(maxsize=1)
def shipped_tile():
    """The shipped ``blue_noise_tile(TILE)`` (int32), checked to be a permutation of 0 .. TILE³ - 1."""
    tile = np.load(_SHIPPED, allow_pickle=False).astype(np.int32)
    if tile.shape != (TILE,) * 3 or not np.array_equal(np.sort(tile.reshape(-1)), np.arange(TILE ** 3)):
        raise ValueError(f"{_SHIPPED!r}: not a {TILE}³ rank permutation; reinstall torch_appearance")
    return tile


def blue_noise_thresholds(shape, seed):
    """A function ``thresholds(z0, z1)`` giving the float64 ``(z1 - z0, Hy, Wx)`` thresholds in (0, 1) of micro
    layers ``z0 .. z1-1`` of a ``(Dz, Hy, Wx)`` volume: the tiled blue-noise ranks ``(r + ½) / T³``, the tile
    shifted by three offsets drawn from ``seed``."""
    dz, hy, wx = shape
    tile = shipped_tile()
    t = tile.shape[0]
    values = (tile.astype(np.float64) + 0.5) / tile.size
    oz, oy, ox = np.random.Generator(np.random.PCG64(int(seed))).integers(0, t, 3)
    jy = (np.arange(hy) + oy) % t
    ix = (np.arange(wx) + ox) % t

    def thresholds(z0, z1):
        kz = (np.arange(z0, z1) + oz) % t
        return values[kz[:, None, None], jy[None, :, None], ix[None, None, :]]

    return thresholds
