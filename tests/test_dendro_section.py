"""Dendrochronology, section mode: ring boundary on microscopy cross-sections (synthetic cells and real patches).

Real patches: tests/data/rings_microscopy (MIT, see the README there), human ring-boundary masks.
"""
import os

import cv2
import numpy as np
import pytest
from scipy.spatial import cKDTree

from torch_appearance.rings.dendro import (boundary_f_measure, detect_section_boundaries, mask_centerline,
                                           resample_polyline)

DATA = os.path.join(os.path.dirname(os.path.abspath(__file__)), "data", "rings_microscopy")


def synthetic_section(size=192, seed=0, noise=0.04, small=6.0, large=12.0):
    """RGB section ``(size, size, 3)`` and the true boundary ``(size, 2)`` ``(x, y)``, one point per column.

    Voronoi cells from jittered seeds: small cells (``small`` px) with thick (2 px) dark walls above the curve
    ``y = 0.45 size + 0.1 x + 8 sin(2 pi x / 150)`` (latewood), large cells (``large`` px) with thin (1 px) walls
    below (earlywood); stained walls (pinkish), white lumens, Gaussian noise. The true boundary is the edge between
    the last latewood and the first earlywood cell in each column (within half a cell of the curve).
    """
    rng = np.random.default_rng(seed)
    curve = lambda x: 0.45 * size + 0.1 * (x - size / 2) + 8 * np.sin(2 * np.pi * x / 150)  # noqa: E731
    seeds = []
    for sp, side in ((small, -1), (large, 1)):
        g = np.arange(-sp, size + sp, sp)
        X, Y = np.meshgrid(g, g)
        P = np.stack([X.ravel(), Y.ravel()], 1) + rng.uniform(-0.3, 0.3, (X.size, 2)) * sp
        keep = np.sign(P[:, 1] - curve(P[:, 0])) == side
        seeds.append(np.c_[P[keep], np.full(keep.sum(), side)])
    seeds = np.concatenate(seeds)
    yy, xx = np.mgrid[:size, :size]
    pix = np.stack([xx.ravel(), yy.ravel()], 1).astype(float)
    lab = cKDTree(seeds[:, :2]).query(pix)[1].reshape(size, size)
    edge = np.zeros((size, size), bool)
    edge[:, 1:] |= lab[:, 1:] != lab[:, :-1]
    edge[1:, :] |= lab[1:, :] != lab[:-1, :]
    late = seeds[lab, 2] < 0
    thick = cv2.dilate(edge.astype(np.uint8), np.ones((2, 2), np.uint8)) > 0
    wall = np.where(late, thick, edge)
    v = np.where(wall, 0.35, 0.92) + rng.normal(0, noise, (size, size))
    rgb = np.clip(np.stack([v * 0.95 + 0.05, v * 0.75, v * 0.9 + 0.05], -1), 0, 1).astype(np.float32)
    first_early = np.argmax(~late, axis=0).astype(float)  # first earlywood row per column
    return rgb, np.stack([np.arange(size, dtype=float), first_early - 0.5], 1)


@pytest.mark.parametrize("seed,rotate", [(0, False), (2, True)])
def test_synthetic_section_boundary_recovered(seed, rotate):
    # measured (seeds 0-5): mean distance 1.9-3.0 px, F1 at 6 px 0.77-0.96, F1 at 3 px 0.54-0.78; seed 2 is the
    # worst of those (3.0 px, 0.77)
    rgb, truth = synthetic_section(seed=seed)
    if rotate:  # rotated by 90 degrees: near-vertical boundary, earlywood on the left
        rgb, truth = np.ascontiguousarray(rgb[::-1].transpose(1, 0, 2)), np.stack([191 - truth[:, 1], truth[:, 0]], 1)
    res = detect_section_boundaries(rgb, cell_px=8)
    m = boundary_f_measure(res.points, truth, tolerance_px=6)
    assert m["mean_error_px"] <= 3.5 and m["f1"] >= 0.7, m
    # the whole boundary is found, end to end
    assert np.ptp(res.points[:, 1 if rotate else 0]) >= 180


def _load(k):
    rgb = cv2.imread(os.path.join(DATA, f"input_0000{k}_preview.png"))[..., ::-1].astype(np.float32) / 255
    mask = cv2.imread(os.path.join(DATA, f"mask_0000{k}.png"), cv2.IMREAD_GRAYSCALE)
    return rgb, mask


@pytest.fixture(scope="module")
def real_results():
    out = {}
    for k in (1, 2, 3):
        rgb, mask = _load(k)
        pts, lab = detect_section_boundaries(rgb).points, mask_centerline(mask)
        out[k] = boundary_f_measure(pts, lab, 3.0), boundary_f_measure(pts, lab, 6.0)
    return out


def test_real_patch_2_within_3px(real_results):
    # measured: sens 1.00 / prec 0.99 / F1 1.00 at 3 px, mean distance 1.7 px
    m3, _ = real_results[2]
    assert m3["f1"] >= 0.9 and m3["mean_error_px"] <= 2.5, m3


def test_real_patches_1_3_near_the_label(real_results):
    # measured at 6 px: patch 1 F1 0.77 (mean 3.6 px), patch 3 F1 0.70 (mean 5.7 px); at 3 px only 0.37 / 0.37.
    # Patches 4 and 5 are not asserted: the curve found runs parallel to the label 8 and 14 px away (README).
    for k, (f1_min, mean_max) in {1: (0.6, 5.0), 3: (0.55, 7.5)}.items():
        _, m6 = real_results[k]
        assert m6["f1"] >= f1_min and m6["mean_error_px"] <= mean_max, (k, m6)


def test_mask_centerline_and_f_measure():
    mask = np.zeros((40, 60), np.uint8)
    mask[19:23, 5:55] = 255  # a 4 px wide horizontal band: centre line rows 20-21
    c = mask_centerline(mask)
    assert set(np.unique(c[:, 1])) <= {20.0, 21.0} and c[:, 0].min() <= 6 and c[:, 0].max() >= 53
    line = np.array([[5.0, 20.5], [54.0, 20.5]])
    m = boundary_f_measure(line, c, 3)
    assert m["sensitivity"] == 1.0 and m["precision"] == 1.0 and m["mean_error_px"] <= 0.6  # rows 20, 21 vs 20.5
    m = boundary_f_measure(line + [0, 5], c, 3)  # shifted 5 px: nothing within tolerance
    assert m["sensitivity"] == 0 and m["precision"] == 0 and m["f1"] == 0
    half = np.array([[5.0, 20.5], [30.0, 20.5]])
    m = boundary_f_measure(half, c, 3)
    assert m["precision"] == 1.0 and 0.45 <= m["sensitivity"] <= 0.6
    m = boundary_f_measure(np.zeros((0, 2)), c, 3)
    assert m["f1"] == 0 and np.isnan(m["mean_error_px"])
    assert len(resample_polyline([[0, 0], [10, 0]], 1.0)) == 11


def test_section_bad_inputs():
    rgb = np.full((64, 64, 3), 0.5, np.float32)
    with pytest.raises(ValueError, match="cell_px"):
        detect_section_boundaries(rgb, cell_px=0)
    with pytest.raises(ValueError, match="too small"):
        detect_section_boundaries(rgb[:20, :20], cell_px=8)
    with pytest.raises(ValueError, match="n_angles"):
        detect_section_boundaries(rgb, n_angles=0)
    with pytest.raises(ValueError, match="min_rel_contrast"):
        detect_section_boundaries(rgb, min_rel_contrast=1.5)
    with pytest.raises(TypeError):
        detect_section_boundaries(np.full((64, 64, 3), "a"))
    with pytest.raises(ValueError, match="tolerance_px"):
        boundary_f_measure([[0, 0], [1, 1]], [[0, 0]], 0)
    with pytest.raises(ValueError, match="detected"):
        boundary_f_measure([[0, 0, 0]], [[0, 0]], 3)
