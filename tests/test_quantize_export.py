"""Tests of probabilistic quantisation (torch_appearance.fabrication.quantize) and slice / volume export."""
from fractions import Fraction
import json
import math
import os

import cv2
import numpy as np
import pytest
import torch
from scipy.stats import chi2, norm

from torch_appearance.fabrication import (INKS, PRINTER_DPI, Ink, InkSet, export_slices, index_volume_to_weights,
                                          load_index_volume, micro_grid_pitch, micro_grid_shape, micro_voxel_size,
                                          quantize_mixture, read_slices, resample_nearest, save_index_volume,
                                          source_index)
from torch_appearance.fabrication import quantize as quantize_module
from torch_appearance.nn import MaterialMixture, mix_inks

DPI_300 = 25.4 / 300  # the optimisation pitch of the paper, mm


def _naive_quantize(weights, voxel_size, dpi, seed):
    """Per-micro-voxel loops with exact rational centres (slow, obviously correct; same random stream)."""
    weights = np.asarray(weights, dtype=np.float64)
    n, d, h, w = weights.shape
    counts = [max(1, math.floor(m * voxel_size * r / 25.4 + 0.5)) for m, r in ((d, dpi[2]), (h, dpi[1]), (w, dpi[0]))]
    u = np.random.Generator(np.random.PCG64(seed)).random(counts)
    out = np.zeros(counts, dtype=np.uint8)
    for k in range(counts[0]):
        for j in range(counts[1]):
            for i in range(counts[2]):
                # centre (i + ½)·(W·s / Wx) divided by s, exactly
                mz, my, mx = (math.floor(Fraction(2 * c + 1, 2) * Fraction(m, cnt))
                              for c, m, cnt in ((k, d, counts[0]), (j, h, counts[1]), (i, w, counts[2])))
                p = weights[:, mz, my, mx] / weights[:, mz, my, mx].sum()
                cdf = np.cumsum(p)
                cdf[-1] = 1.0
                out[k, j, i] = int(np.argmax(u[k, j, i] < cdf))
    return out


def _random_mixture(shape, n, seed, zero_fraction=0.3):
    rng = np.random.default_rng(seed)
    w = rng.gamma(0.7, size=(n, *shape))
    w[rng.random(w.shape) < zero_fraction] = 0.0
    w[0][w.sum(0) == 0] = 1.0
    return w / w.sum(0)


# ----------------------------------------------------------------------------------------------------------------
# grids
# ----------------------------------------------------------------------------------------------------------------
def test_micro_voxel_size_and_grid_shape():
    assert PRINTER_DPI == (600, 300, 940)
    assert micro_voxel_size() == (25.4 / 600, 25.4 / 300, 25.4 / 940)
    assert micro_voxel_size((100, 200, 400)) == (0.254, 0.127, 0.0635)
    # 300-DPI macro voxels: x factor 2, y factor 1, z factor 940/300 = 3.133 (12 layers -> 37.6 -> 38)
    assert micro_grid_shape((12, 64, 50), DPI_300) == (38, 64, 100)
    # 1 mm voxels: 2 mm·940/25.4 = 74.02, 3 mm·300/25.4 = 35.43, 4 mm·600/25.4 = 94.49
    assert micro_grid_shape((2, 3, 4), 1.0) == (74, 35, 94)
    # actual pitch = extent / count: the micro grid covers exactly the macro box
    assert micro_grid_pitch((12, 64, 50), DPI_300) == (50 * DPI_300 / 100, 64 * DPI_300 / 64, 12 * DPI_300 / 38)
    assert micro_grid_pitch((2, 3, 4), 1.0) == pytest.approx((4 / 94, 3 / 35, 2 / 74), rel=1e-15)
    # a grid finer than the printer still gets at least one micro voxel per axis
    assert micro_grid_shape((1, 1, 1), 0.001) == (1, 1, 1)
    with pytest.raises(ValueError, match=r"voxel_size_mm: expected a finite value in \(0, inf\], got -1.0"):
        micro_grid_shape((1, 1, 1), -1.0)
    with pytest.raises(ValueError, match=r"printer_dpi: expected finite values > 0"):
        micro_voxel_size((600, 0, 940))
    with pytest.raises(ValueError, match=r"printer_dpi: expected three numbers"):
        micro_voxel_size((600, 300))
    with pytest.raises(ValueError, match=r"shape: expected \(D, H, W\)"):
        micro_grid_shape((1, 0, 1), 0.1)


@pytest.mark.parametrize("n_source", [1, 2, 3, 5, 7, 12])
@pytest.mark.parametrize("n_target", [1, 2, 3, 4, 10, 23, 38])
def test_source_index_maps_centres(n_source, n_target):
    got = source_index(n_source, n_target)
    want = [math.floor(Fraction(2 * i + 1, 2 * n_target) * n_source) for i in range(n_target)]
    assert got.tolist() == want
    assert got.dtype == np.int64 and got.min() >= 0 and got.max() < n_source
    if n_target >= n_source:   # upsampling: every source cell is used, floor(f) or ceil(f) times
        counts = np.bincount(got, minlength=n_source)
        f = n_target / n_source
        assert set(counts.tolist()) <= {math.floor(f), math.ceil(f)}


def test_resample_nearest():
    volume = np.arange(2 * 3, dtype=np.int32).reshape(1, 2, 3)
    out = resample_nearest(volume, (2, 4, 6))
    assert out.shape == (2, 4, 6) and out.dtype == np.int32
    assert out[0].tolist() == [[0, 0, 1, 1, 2, 2], [0, 0, 1, 1, 2, 2], [3, 3, 4, 4, 5, 5], [3, 3, 4, 4, 5, 5]]
    assert np.array_equal(out[1], out[0])
    t = resample_nearest(torch.arange(6.0).view(1, 1, 2, 3).expand(2, 1, 2, 3), (1, 4, 6))
    assert t.shape == (2, 1, 4, 6) and torch.equal(t[1, 0], torch.from_numpy(out[0]).float())


# ----------------------------------------------------------------------------------------------------------------
# quantisation
# ----------------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("voxel_size, shape", [(0.1, (2, 2, 3)), (DPI_300, (3, 2, 2)), (0.02, (2, 3, 2))])
@pytest.mark.parametrize("chunk", [None, 1])
def test_quantize_matches_naive_reference(voxel_size, shape, chunk, monkeypatch):
    if chunk is not None:   # one micro layer per chunk: the random stream must not depend on the chunking
        monkeypatch.setattr(quantize_module, "_CHUNK", chunk)
    weights = _random_mixture(shape, 4, seed=11)
    got = quantize_mixture(torch.from_numpy(weights), voxel_size, seed=5)
    want = _naive_quantize(weights, voxel_size, PRINTER_DPI, seed=5)
    assert got.dtype == np.uint8 and got.shape == want.shape == micro_grid_shape(shape, voxel_size)
    assert np.array_equal(got, want)


def test_quantize_one_hot_is_deterministic_upsampling():
    rng = np.random.default_rng(3)
    macro = rng.integers(0, 5, size=(4, 3, 5))
    weights = index_volume_to_weights(macro, 5, dtype=torch.float64)
    out = quantize_mixture(weights, DPI_300, seed=rng.integers(1 << 30))
    assert out.shape == (13, 3, 10)   # 4·940/300 = 12.53, 3, 5·2
    assert np.array_equal(out, resample_nearest(macro, out.shape).astype(np.uint8))
    # seeds: same seed, same result; another seed, another draw
    mix = _random_mixture((2, 2, 2), 5, seed=4, zero_fraction=0.0)
    a, b, c = (quantize_mixture(mix, DPI_300, seed=s) for s in (1, 1, 2))
    assert np.array_equal(a, b) and not np.array_equal(a, c)


def test_quantized_frequencies_match_mixture():
    """Counts per macro voxel and ink against the mixture: chi-square per voxel (Bonferroni), exact zeros, and
    a power check (a mixture off by 0.02 is rejected)."""
    n_inks, shape, voxel_size = 5, (2, 3, 4), 1.0                 # factors 37, 11.67, 23.62 (non-integer)
    weights = _random_mixture(shape, n_inks, seed=21)
    weights[:, 0, 0, 0] = [0.97, 0.0075, 0.0075, 0.0075, 0.0075]  # the initial mixture: rare inks too
    indices = quantize_mixture(weights.astype(np.float32), voxel_size, seed=9)
    assert indices.shape == (74, 35, 94)
    iz, iy, ix = source_index(2, 74), source_index(3, 35), source_index(4, 94)
    macro = (iz[:, None, None] * 3 + iy[None, :, None]) * 4 + ix[None, None, :]   # flat macro index per micro
    counts = np.zeros((n_inks, 24), dtype=np.int64)
    np.add.at(counts, (indices.ravel(), np.broadcast_to(macro, indices.shape).ravel()), 1)
    per_voxel = counts.sum(0)
    # the mapping covers each macro voxel with a box of floor/ceil(factor) micro voxels per axis
    for factors, axis_counts in ((37,), np.bincount(iz)), ((11, 12), np.bincount(iy)), ((23, 24), np.bincount(ix)):
        assert set(axis_counts.tolist()) <= set(factors)
    assert per_voxel.sum() == indices.size and per_voxel.min() >= 37 * 11 * 23

    p = weights.reshape(n_inks, 24)
    assert counts[p == 0].sum() == 0, "an ink with zero weight was drawn"
    family_alpha = 1e-3
    limit = chi2.isf(family_alpha / 24, df=np.count_nonzero(p, axis=0) - 1)

    def chi_square(prob):
        expected = per_voxel * prob
        used = prob > 0
        return np.where(used, (counts - expected) ** 2 / np.where(used, expected, 1.0), 0.0).sum(0)

    stat = chi_square(p)
    assert (stat <= limit).all(), f"chi-square {stat.max():.1f} > {limit[np.argmax(stat - limit)]:.1f}"
    # pooled per-ink z-tests over the whole volume
    expected = (per_voxel * p).sum(1)
    sd = np.sqrt((per_voxel * p * (1 - p)).sum(1))
    z = np.abs(counts.sum(1) - expected) / sd
    assert (z <= norm.isf(family_alpha / (2 * n_inks))).all(), z
    # power: the test would notice draws from a mixture shifted by 0.02 between two inks
    shifted = p.copy()
    shifted[0] += 0.02
    shifted[1] -= 0.02
    ok = (shifted >= 0).all(0) & (p[1] > 0.02)
    shifted[:, ~ok] = p[:, ~ok]
    assert ok.sum() >= 5 and (chi_square(shifted)[ok] > limit[ok]).mean() > 0.5


def test_quantize_refusals():
    good = np.full((2, 1, 1, 1), 0.5)
    with pytest.raises(ValueError, match=r"weights: expected weights >= 0"):
        quantize_mixture(np.array([1.5, -0.5]).reshape(2, 1, 1, 1), 0.1)
    with pytest.raises(ValueError, match=r"weights: expected finite values, got 1 NaN/Inf"):
        quantize_mixture(np.array([np.nan, 0.5]).reshape(2, 1, 1, 1), 0.1)
    with pytest.raises(ValueError, match=r"weights: expected per-voxel sums of 1"):
        quantize_mixture(np.full((2, 1, 1, 1), 0.6), 0.1)
    with pytest.raises(ValueError, match=r"weights: expected shape \(N, D, H, W\)"):
        quantize_mixture(np.full((2, 1, 1), 0.5), 0.1)
    with pytest.raises(ValueError, match=r"at most 256 inks"):
        quantize_mixture(np.full((257, 1, 1, 1), 1 / 257), 0.1)
    with pytest.raises(TypeError, match=r"weights: expected a floating-point dtype"):
        quantize_mixture(np.ones((1, 1, 1, 1), dtype=np.int64), 0.1)
    with pytest.raises(TypeError, match=r"weights: expected a torch.Tensor or numpy.ndarray"):
        quantize_mixture([[[[1.0]]]], 0.1)
    with pytest.raises(TypeError, match=r"voxel_size_mm: expected a real number"):
        quantize_mixture(good, "0.1")
    with pytest.raises(ValueError, match=r"seed: expected an int >= 0"):
        quantize_mixture(good, 0.1, seed=-1)


def test_index_volume_to_weights_and_mixing():
    inks = InkSet.from_names(["cyan", "magenta", "white"])
    indices = np.array([[[0, 1, 2], [2, 2, 0]]], dtype=np.uint8)
    onehot = index_volume_to_weights(indices, 3)
    assert onehot.shape == (3, 1, 2, 3) and onehot.dtype == torch.float32
    assert torch.equal(onehot.sum(0), torch.ones(1, 2, 3)) and torch.equal(onehot.argmax(0), torch.from_numpy(
        indices.astype(np.int64)))
    sigma_t, albedo = mix_inks(onehot.double(), inks)
    for j in range(2):
        for i in range(3):
            ink = inks[int(indices[0, j, i])]
            assert sigma_t[:, 0, j, i].tolist() == pytest.approx(ink.sigma_t, rel=1e-15)
            assert albedo[:, 0, j, i].tolist() == pytest.approx(ink.albedo, rel=1e-15)
    with pytest.raises(ValueError, match=r"indices: expected values in \[0, 2\), got range \[0, 2\]"):
        index_volume_to_weights(indices, 2)
    with pytest.raises(TypeError, match="indices: expected an integer dtype"):
        index_volume_to_weights(indices.astype(np.float32), 3)
    with pytest.raises(ValueError, match=r"indices: expected shape \(Dz, Hy, Wx\)"):
        index_volume_to_weights(indices[0], 3)


def test_mixture_to_quantised_volume_end_to_end():
    mixture = MaterialMixture(InkSet.from_names(), (12, 4, 4))
    indices = quantize_mixture(mixture.weights(), DPI_300, seed=0)   # a float32 tensor with grad
    assert indices.shape == (38, 4, 8)
    frequencies = np.bincount(indices.ravel(), minlength=5) / indices.size
    # 97 % white: 1216 draws, binomial sd 0.0049; 5 sd
    assert abs(frequencies[4] - 0.97) < 5 * math.sqrt(0.97 * 0.03 / indices.size)


# ----------------------------------------------------------------------------------------------------------------
# slices and index volumes
# ----------------------------------------------------------------------------------------------------------------
def _inks6():
    return InkSet.from_names(["cyan", "magenta", "yellow", "black", "white", "transparent"])


def test_slices_round_trip(tmp_path):
    inks = _inks6()
    indices = np.random.default_rng(1).integers(0, 6, size=(5, 7, 9)).astype(np.uint8)
    folder = tmp_path / "slices"
    palette = export_slices(indices, inks, folder)
    assert sorted(os.listdir(folder)) == ["palette.json"] + [f"slice_{z:04d}.png" for z in range(5)]
    back, palette_read = read_slices(folder)
    assert back.dtype == np.uint8 and np.array_equal(back, indices)
    assert palette_read == palette == json.loads((folder / "palette.json").read_text())
    assert palette["order"] == "bottom_to_top" and palette["dpi"] == [600, 300, 940]
    assert palette["layer_thickness_mm"] == 25.4 / 940 and palette["shape"] == [5, 7, 9]
    assert [e["name"] for e in palette["inks"]] == list(inks.names)
    assert [e["index"] for e in palette["inks"]] == list(range(6))
    assert palette["inks"][0]["rgb"] == [0, 255, 255] and palette["inks"][5]["rgb"] == [128, 128, 128]
    # the pixels themselves: slice z = layer z from the bottom, row j = y, column i = x, exact palette colours
    for z in (0, 4):
        bgr = cv2.imread(str(folder / f"slice_{z:04d}.png"), cv2.IMREAD_UNCHANGED)
        assert bgr.shape == (7, 9, 3) and bgr.dtype == np.uint8
        assert np.array_equal(bgr[..., ::-1], inks.display_rgb()[indices[z]])


def test_slices_overwrite_removes_stale_layers(tmp_path):
    inks = _inks6()
    export_slices(np.zeros((4, 2, 3), dtype=np.uint8), inks, tmp_path)
    thinner = np.full((2, 2, 3), 4, dtype=np.uint8)
    export_slices(thinner, inks, tmp_path, dpi=(300, 300, 600))
    assert sorted(os.listdir(tmp_path)) == ["palette.json", "slice_0000.png", "slice_0001.png"]
    back, palette = read_slices(tmp_path)
    assert np.array_equal(back, thinner) and palette["layer_thickness_mm"] == 25.4 / 600


def test_slices_refusals(tmp_path):
    inks = _inks6()
    indices = np.zeros((2, 2, 2), dtype=np.uint8)
    with pytest.raises(ValueError, match=r"indices: expected values in \[0, 6\).*got 6"):
        export_slices(indices + 6, inks, tmp_path)
    with pytest.raises(TypeError, match="indices: expected dtype uint8, got int64"):
        export_slices(indices.astype(np.int64), inks, tmp_path)
    with pytest.raises(ValueError, match=r"indices: expected shape \(Dz, Hy, Wx\)"):
        export_slices(indices[0], inks, tmp_path)
    twins = InkSet([INKS["white"], Ink("snow", (1, 1, 1), (1, 1, 1), display_rgb=(1.0, 1.0, 1.0))])
    with pytest.raises(ValueError, match=r"share a display_rgb .*\['white/snow'\]"):
        export_slices(indices, twins, tmp_path)
    assert os.listdir(tmp_path) == []   # nothing written by refused calls
    # damaged folders
    export_slices(indices, inks, tmp_path)
    image = cv2.imread(str(tmp_path / "slice_0001.png"))
    image[1, 0] = (1, 2, 3)
    cv2.imwrite(str(tmp_path / "slice_0001.png"), image)
    with pytest.raises(ValueError, match=r"slice_0001.png'.*\(row 1, column 0\) has colour \[3, 2, 1\].*not in the"):
        read_slices(tmp_path)
    os.remove(tmp_path / "slice_0001.png")
    with pytest.raises(FileNotFoundError):
        read_slices(tmp_path)


def test_index_volume_round_trip(tmp_path):
    inks = InkSet([INKS["white"], Ink("Mine", (0.1, 2.5, 1e-3), (0.25, 0.5, 1.0), g=0.1)])
    indices = np.random.default_rng(2).integers(0, 2, size=(3, 4, 5)).astype(np.uint8)
    path = tmp_path / "volume.npz"
    save_index_volume(path, indices, inks, dpi=(600, 300, 940))
    assert os.listdir(tmp_path) == ["volume.npz"]
    back, inks_back, dpi = load_index_volume(path)
    assert np.array_equal(back, indices) and back.dtype == np.uint8
    assert inks_back == inks and dpi == (600.0, 300.0, 940.0)
    with np.load(path, allow_pickle=False) as archive:   # plain arrays, no pickles
        assert sorted(archive.files) == ["dpi", "indices", "inks_json"]
    with pytest.raises(ValueError, match=r"path: expected a path ending with \.npz, got '.*volume\.npy'"):
        save_index_volume(tmp_path / "volume.npy", indices, inks)
    with pytest.raises(ValueError, match=r"indices: expected values in \[0, 2\)"):
        save_index_volume(path, indices + 2, inks)


def test_slices_round_trip_with_void(tmp_path):
    """Micro-voxels outside an object (VOID) export in the void colour and read back as VOID."""
    from torch_appearance.fabrication.export import VOID, VOID_RGB

    inks = InkSet.from_names()
    rng = np.random.default_rng(1)
    indices = rng.integers(0, len(inks), size=(4, 5, 6)).astype(np.uint8)
    indices[rng.random(indices.shape) < 0.3] = VOID
    palette = export_slices(indices, inks, tmp_path / "s")
    assert palette["void"] == {"index": VOID, "rgb": list(VOID_RGB)}
    back, _ = read_slices(tmp_path / "s")
    assert np.array_equal(back, indices)
    save_index_volume(str(tmp_path / "v.npz"), indices, inks)
    assert np.array_equal(load_index_volume(str(tmp_path / "v.npz"))[0], indices)
