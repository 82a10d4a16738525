"""Disc mode (torch_appearance.rings.disc, detect_rings.py --pith): boundaries along several transects of synthetic
discs with known rings, filtering only polar strips (once per transect), the CSV / overlay, bad input; the
CooRecorder .pos reader (hand-written fixture in tests/data/coorecorder, CC0) and eval_rings.py with .pos labels
and transect columns; the automatic pith (``--pith auto``) on synthetic discs."""
import csv
import json
import math
import os
import re

import cv2
import numpy as np
import pytest

import torch_appearance.rings.disc as disc_mod
from torch_appearance.rings import wood_edge
from torch_appearance.rings.coorecorder import read_pos
from torch_appearance.rings.dendro import match_boundaries
from torch_appearance.rings.disc import detect_disc_boundaries, polar_strip, synthetic_disc
from torch_appearance.rings.pith import detect_pith

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
POS = os.path.join(ROOT, "tests", "data", "coorecorder", "handwritten.pos")
PITH = (150.0, 160.0)
ANGLES = [0.0, 60.0, 120.0, 180.0, 240.0, 300.0]


@pytest.fixture(scope="module")
def disc():
    return synthetic_disc(seed=0)  # 320 x 300, 12 eccentric rings 14 -> 7 px, white background, noise 0.02


def _run(name, *args):
    from torch_appearance.testing import run_command
    return run_command(name, *args)


def test_polar_strip_straightens_circles():
    # a pattern that depends only on the distance to the pith is constant along every strip column
    H, W = 200, 220
    y, x = np.mgrid[:H, :W]
    img = np.cos(2 * np.pi * np.hypot(x - 100.0, y - 90.0) / 9.0)
    strip, X, Y = polar_strip(img, (100.0, 90.0), 33.0, 80, half_width=10)
    assert strip.shape == (21, 81)
    r = np.arange(81.0)
    assert np.allclose(np.hypot(X - 100.0, Y - 90.0), r[None, :], atol=1e-9)
    # row s lies s px of arc from the transect (s / r radians), at least half_width px of radius in
    s = np.arange(-10, 11.0)[:, None]
    ang = np.arctan2(Y[:, 1:] - 90.0, X[:, 1:] - 100.0)
    assert np.allclose((ang - math.radians(33.0) + np.pi) % (2 * np.pi) - np.pi, s / np.maximum(r[None, 1:], 10.0))
    interior = strip[:, 20:]  # bilinear interpolation error of a 9 px period stays small
    assert np.abs(interior - np.cos(2 * np.pi * r[None, 20:] / 9.0)).max() < 0.07


def test_pooled_ring_period():
    # strips of 12 px rings on a strong slow brightness trend (heartwood / sapwood): the pooled, detrended spectrum
    # peaks at the ring period (64 log bins: +-5 %)
    rng = np.random.default_rng(0)
    strips = []
    for L in (180, 240, 300):
        r = np.arange(L, dtype=np.float64)
        row = 0.2 * np.cos(2 * np.pi * r / 12.0) + 1.5 * np.cos(2 * np.pi * r / 350.0)
        strips.append(row[None, :] + rng.normal(0, 0.05, (25, L)))
    period = disc_mod._pooled_period([disc_mod._detrend(s) for s in strips], 0.4)
    assert abs(period / 12.0 - 1) < 0.05, period


@pytest.mark.parametrize("include_edge", [False, True])
def test_disc_boundaries_on_synthetic_disc(disc, include_edge):
    rgb, radius = disc
    res = detect_disc_boundaries(rgb, PITH, angles_deg=ANGLES, include_edge=include_edge, pixel_size_mm=0.1)
    assert len(res.transects) == len(ANGLES)
    for deg, tr in zip(ANGLES, res.transects):
        truth = radius(math.radians(deg))  # the last one is the disc edge
        lab = truth if include_edge else truth[:-1]
        m = match_boundaries(tr.info["radius_px"], lab, 3.0)
        assert m["sensitivity"] == 1.0 and m["precision"] == 1.0, (deg, tr.info["radius_px"], lab)
        assert m["mean_error_px"] < 1.0, (deg, m)
        # points lie on the ray from the pith, ordered pith -> bark, widths in mm from the pixel size
        u = np.array([math.cos(math.radians(deg)), math.sin(math.radians(deg))])
        assert np.allclose(tr.points, np.asarray(PITH) + tr.info["radius_px"][:, None] * u, atol=1e-9)
        assert np.all(np.diff(tr.info["radius_px"]) > 0)
        assert np.allclose(tr.widths_mm[1:], 0.1 * np.diff(tr.info["radius_px"]))
        assert (tr.info["kind"][-1] == "edge") == include_edge
        assert tr.info["kind"][:-1] == ["ring"] * (len(tr.points) - 1)


def test_rings_that_shrink_five_fold_towards_the_bark_are_all_found():
    """Ring width falling from 40 px at the pith to 8 px at the bark (as on the human-labelled discs, several-fold
    along a radius), with noisy pixels: every ring is found within 3 px along four transects, with the automatic
    pith."""
    widths = np.geomspace(40, 8, 14)
    size = int(2 * widths.sum() * 1.12 + 40)
    pith = (size / 2 + 3.0, size / 2 - 5.0)
    # pixel noise 0.08 on a white background: the border must still read as one colour, and the wood -> background
    # step at the disc edge must not count as a ring (both failed before: the last ring was lost to a false one)
    rgb, radius = synthetic_disc(size=(size, size), pith=pith, widths=widths, ecc=0.04, seed=1, noise=0.08)
    angles = [0.0, 90.0, 180.0, 270.0]
    res = detect_disc_boundaries(rgb, "auto", angles_deg=angles)
    assert all(tr.info["edge_px"] is not None for tr in res.transects)
    assert math.dist(res.pith, pith) < 0.02 * widths.sum()
    for deg, tr in zip(angles, res.transects):
        truth = radius(math.radians(deg))[:-1]
        # the transect starts at the detected pith: compare the boundary points, not radii from different centres
        u = np.array([math.cos(math.radians(deg)), math.sin(math.radians(deg))])
        labels = np.asarray(pith) + truth[:, None] * u
        found = np.hypot(*(tr.points - np.asarray(pith)).T)
        m = match_boundaries(found, np.hypot(*(labels - np.asarray(pith)).T), 3.0)
        assert m["sensitivity"] == 1.0 and m["precision"] == 1.0, (deg, np.round(found), np.round(truth))


def _strip_of_rings(widths, *, rows=25, ramp=0.5, noise=0.01, seed=0):
    """A polar strip (rows = arc, columns = radius from the pith): sawtooth rings of the given widths (px) on a
    brightness ramp along the radius, with the true boundary positions."""
    B = np.cumsum(widths)
    L = int(B[-1]) + 20
    x = np.arange(L) + 0.5
    k = np.searchsorted(B, x)
    t = (x - np.r_[0, B][k]) / np.r_[widths, widths[-1]][k]
    ring = np.where(t < 0.65, 0.75 - 0.1 * t, 0.7 - 0.35 * (t - 0.65) / 0.35)
    v = ring[None, :] + ramp * x[None, :] / L + noise * np.random.default_rng(seed).standard_normal((rows, L))
    return v, B


def test_local_ring_period_follows_the_rings():
    """The filter's local frequency along a transect follows the ring width (40 px rings, then 12 px rings), and
    every boundary of both is found."""
    v, B = _strip_of_rings(np.r_[np.full(10, 40.0), np.full(12, 12.0)])
    pos, info = disc_mod._strip_boundaries(v, np.ones_like(v), period=30.0, p_periods=2.0, band=1.0, p=None, q=None,
                                           f_max=0.4, min_rel_rise=0.1, edge_level=1.0, tilt_sigma=2.0,
                                           max_tilt_deg=40.0, device="cpu", num_workers=1, calls=[])
    lp = info["local_period_px"]
    assert lp.shape == (v.shape[1],)
    assert abs(np.median(lp[100:350]) - 40.0) < 2.0
    assert abs(np.median(lp[430:int(B[-1]) - 20]) - 12.0) < 1.0
    # every boundary but those of the last 40 px, where the strip ends inside a ring (no edge to stop at)
    assert match_boundaries(pos, B[B < v.shape[1] - 40], 2.0)["f1"] == 1.0


def test_narrow_ring_boundaries_come_from_the_fine_pass_only_between_close_coarse_ones():
    """The fine pass's boundaries are added where one coarse cycle spans narrow rings (a coarse gap below
    narrow_gap P, here 0.8 P), not in wide rings (its extra cycles there are earlywood texture), and not twice."""
    coarse = np.array([100.0, 140.0, 300.0, 330.0])
    fine = np.array([101.0, 121.0, 140.5, 220.0, 302.0, 307.0, 323.0])
    out = disc_mod._narrow_ring_boundaries(coarse, fine, period=80.0, fine_period=40.0, end=400.0,
                                           narrow_gap=0.8)
    # 121 splits the 40 px gap 100-140; 220 lies in a 160 px gap (a wide ring); 101 / 140.5 / 302 repeat coarse
    # ones; 307 and 323 sit within a quarter of the 30 px gap 300-330 of its ends
    np.testing.assert_array_equal(out, [100.0, 121.0, 140.0, 300.0, 330.0])
    # the pith (0) and the strip's end close the list: a narrow first or last ring is found too
    out = disc_mod._narrow_ring_boundaries(np.array([40.0]), np.array([20.0, 70.0]), period=80.0, fine_period=40.0,
                                           end=100.0, narrow_gap=0.8)
    np.testing.assert_array_equal(out, [20.0, 40.0, 70.0])
    np.testing.assert_array_equal(disc_mod._narrow_ring_boundaries(coarse, np.zeros(0), period=80.0,
                                                                   fine_period=40.0, end=400.0, narrow_gap=0.8),
                                  coarse)


def test_fine_pass_starts_before_the_first_narrow_gap():
    """The fine pass filters from two filter lengths before the first coarse gap narrower than narrow_gap P (the pith
    at 0 and the strip's end close the list), from 0 when that is the first ring, near the end when none is."""
    assert disc_mod._fine_pass_start([100.0, 200.0, 260.0, 300.0], 400.0, 50.0, 40) == 220  # gap 260-300
    assert disc_mod._fine_pass_start([30.0, 200.0], 400.0, 50.0, 40) == 0
    assert disc_mod._fine_pass_start([100.0, 200.0, 300.0], 400.0, 50.0, 40) == 360


def test_bark_zone_finds_the_narrow_rings_before_the_edge():
    """Between the last boundary and the wood's edge, steps of the profile as strong as a fifth of the outer rings'
    own steps are boundaries (4 px rings the Gabor passes skip); a flat zone adds none."""
    x = np.arange(200, dtype=np.float64)
    B = np.r_[np.arange(20.0, 150.0, 20.0), np.arange(144.0, 171.0, 4.0)]  # rings of 20 px, then seven of 4 px
    edges = np.r_[0.0, B, 200.0]
    k = np.searchsorted(edges, x, side="right") - 1
    v = 1.0 - 0.5 * (x - edges[k]) / np.diff(edges)[k]                 # sawtooth: darkening, then a sharp rise
    add = wood_edge.bark_zone_boundaries(B[B <= 140], v, end=172.0)
    assert match_boundaries(add, B[B > 140], 1.0)["f1"] == 1.0, add
    assert len(wood_edge.bark_zone_boundaries(B[B <= 140], np.where(x > 141, v[141], v), end=172.0)) == 0


def test_bark_gaps_find_a_narrow_ring_skipped_between_two_boundaries():
    """``bark_gaps``: rings of 20 px, then 12 px ones towards the bark (like C17C north, where the passes ran one
    cycle over two): a ring skipped inside the last gaps is found (one per gap, on its sharp rise), a gap further in
    than ``gaps`` is not searched, and a flat gap or a weak rise adds nothing."""
    x = np.arange(260, dtype=np.float64)
    B = np.r_[np.arange(20.0, 161.0, 20.0), np.arange(172.0, 233.0, 12.0)]  # ... 160, then 172, 184, ..., 232
    edges = np.r_[0.0, B, 260.0]
    k = np.searchsorted(edges, x, side="right") - 1
    v = 1.0 - 0.5 * (x - edges[k]) / np.diff(edges)[k]                 # sawtooth: darkening, then a sharp rise
    found = np.array([b for b in B if b not in (172.0, 208.0)])         # two rings skipped
    end = 244.0
    add = wood_edge.gap_boundaries(found, v, end, gaps=3)              # the gaps 196 -> 220 -> 232 -> 244
    assert match_boundaries(add, np.array([208.0]), 1.0)["f1"] == 1.0, add
    add = wood_edge.gap_boundaries(found, v, end, gaps=6)              # reaches 160 -> 184 too
    assert match_boundaries(add, np.array([172.0, 208.0]), 1.0)["f1"] == 1.0, add
    assert len(wood_edge.gap_boundaries(found, v, end, gaps=0)) == 0
    flat = np.where((x > 197) & (x < 219), v[197], v)                  # no rise inside 196 -> 220
    assert len(wood_edge.gap_boundaries(found, flat, end, gaps=3)) == 0
    weak = np.where((x > 197) & (x < 219), 1.0 - 0.05 * (x - 196.0) / 24.0, v)   # a rise a tenth of the others'
    weak[208:219] += 0.03
    assert len(wood_edge.gap_boundaries(found, weak, end, gaps=3)) == 0


def _disc_on_a_cloth(bark_rgb, bark_px):
    """A 760² synthetic disc (12 rings, 30 -> 14 px) on a black cloth, with a bark of ``bark_px`` and a wooden table
    along the top: ``(rgb, radius, pith, rho, edge, xx)`` with ``rho`` the distance from the pith and ``edge`` the
    disc's edge radius at every pixel."""
    widths = np.linspace(30, 14, 12)
    size = 760
    pith = (372.0, 385.0)
    rgb, radius = synthetic_disc(size=(size, size), pith=pith, widths=widths, ecc=0.03, seed=2,
                                 background=(0.08, 0.08, 0.08))
    yy, xx = np.mgrid[0:size, 0:size]
    phi = np.arctan2(yy - pith[1], xx - pith[0])
    rho = np.hypot(xx - pith[0], yy - pith[1])
    edge = widths.sum() * (1 + 0.03 * np.cos(phi - 0.7))
    rgb[(rho >= edge) & (rho < edge + bark_px)] = bark_rgb
    rgb[:90] = np.where(rho[:90, :, None] >= edge[:90, :, None] + bark_px, (0.85, 0.62, 0.35), rgb[:90])  # a table
    return rgb, radius, pith, rho, edge, xx


def test_disc_edge_without_a_uniform_background():
    """A photo like the human-labelled discs: dark bark around the disc, a black cloth, a wooden table and a white
    ruler at the border (so the border is not one colour and nothing can be masked by colour). The wood ends where
    the bark begins: nothing is detected in the bark, the cloth, the table or the ruler, and every ring is found."""
    rgb, radius, pith, rho, edge, _ = _disc_on_a_cloth((0.22, 0.14, 0.09), 14)
    rgb[:, -60:] = np.where(rho[:, -60:, None] >= edge[:, -60:, None] + 14, (0.95, 0.95, 0.93), rgb[:, -60:])
    angles = [0.0, 90.0, 180.0, 270.0]
    res = detect_disc_boundaries(rgb, pith, angles_deg=angles)
    assert res.info["background"] is None                       # the border is not one colour
    for deg, tr in zip(angles, res.transects):
        truth = radius(math.radians(deg))
        assert tr.info["edge_px"] is not None and abs(tr.info["edge_px"] - truth[-1]) < 3.0, (deg, tr.info["edge_px"])
        m = match_boundaries(tr.info["radius_px"], truth[:-1], 3.0)
        assert m["sensitivity"] == 1.0 and m["precision"] == 1.0, (deg, np.round(tr.info["radius_px"]), truth)


def test_disc_edge_at_a_light_bark_against_a_tinted_ruler():
    """Like C13C east of the human-labelled discs: a thin light bark and, right against it, a light blue ruler,
    brighter than the wood and not grey (so neither dark nor grey says it is not wood). Its hue, far from the
    wood's, ends the wood at the bark: no boundary on the ruler's edge, every ring found."""
    rgb, radius, pith, rho, edge, xx = _disc_on_a_cloth((0.55, 0.42, 0.30), 8)  # a light bark, 8 px
    ruler = (rho >= edge + 8) & (xx > pith[0] + 150)
    rgb[ruler] = (0.70, 0.86, 0.97)                              # light blue, saturation 0.28
    res = detect_disc_boundaries(rgb, pith, angles_deg=[0.0, 20.0, 340.0])
    assert res.info["background"] is None
    for deg, tr in zip([0.0, 20.0, 340.0], res.transects):
        truth = radius(math.radians(deg))
        # within 5 px: the edge is put on the steepest fall of brightness near it, and the light bark falls less
        # than the last latewood darkens (3.5 px inside at 0 degrees)
        assert tr.info["edge_px"] is not None and abs(tr.info["edge_px"] - truth[-1]) < 5.0, (deg, tr.info["edge_px"])
        m = match_boundaries(tr.info["radius_px"], truth[:-1], 3.0)
        assert m["sensitivity"] == 1.0 and m["precision"] == 1.0, (deg, np.round(tr.info["radius_px"]), truth)


def test_wood_edge_half_way_down_a_gradual_fall_into_the_bark():
    """``bark_level``: a wood that fades over 20 px (0.80 -> 0.40) before a steep drop into a dark bark (0.20), on a
    cloth: the steepest fall is the drop; half-way down the fall from the wood to the bark (0.50) lies 6 px before
    it, inside the fade, where the TRAS discs' people click (C13C north: a 20 px fade, the click 6 px inside)."""
    L = 400
    v = np.full(L, 0.80)
    v[300:320] = np.linspace(0.80, 0.40, 20)
    v[320:] = 0.20
    rows = np.repeat((v[:, None] * np.array([1.0, 0.75, 0.5]))[None], 9, axis=0)
    rows = rows + np.random.default_rng(0).normal(0, 0.005, rows.shape)
    steepest = wood_edge.wood_colour_end(rows)
    half = wood_edge.wood_colour_end(rows, fall_level=0.5)
    assert abs(steepest - 319) <= 1, steepest
    assert abs(half - 314) <= 1, half                             # 0.80 - 0.5 * 0.6 = 0.50 at column 314.25
    with pytest.raises(ValueError, match="bark_level"):
        detect_disc_boundaries(np.full((64, 64, 3), 0.5, np.float32), (32, 32), bark_level=1.5)


@pytest.mark.parametrize("mag_weight", [True, False])
def test_crack_along_a_transect(disc, mag_weight):
    # an open crack (background colour) 25 px wide along the 0-degree transect hides 25 of the strip's 33 rows:
    # it is masked and filled along the rings from the wood beside it, so the boundaries are still found; without
    # the amplitude weighting of the rows (mag_weight=False) only the mask and the fill handle it
    rgb, radius = disc
    cracked = rgb.copy()
    cracked[148:173, 165:260] = 1.0
    res = detect_disc_boundaries(cracked, PITH, angles_deg=[0.0], mag_weight=mag_weight)
    m = match_boundaries(res.transects[0].info["radius_px"], radius(0.0)[:-1], 3.0)
    assert m["sensitivity"] >= 0.95 and m["precision"] >= 0.95, (res.transects[0].info["radius_px"], radius(0.0))


def test_disc_filling_the_frame(disc):
    # a crop inside the disc: the border is wood, not background, so nothing may be masked as background
    rgb, radius = disc
    crop = np.ascontiguousarray(rgb[60:260, 50:250])
    res = detect_disc_boundaries(crop, (100.0, 100.0), angles_deg=[0.0, 90.0, 180.0, 270.0], include_edge=True)
    assert res.info["background"] is None
    for deg, tr in zip([0.0, 90.0, 180.0, 270.0], res.transects):
        truth = radius(math.radians(deg))
        truth = truth[truth < 97.0]  # the crop ends 99 px from the pith in every direction
        assert "edge" not in tr.info["kind"]
        m = match_boundaries(tr.info["radius_px"], truth, 3.0)
        assert m["sensitivity"] >= 0.85 and m["precision"] >= 0.85, (deg, tr.info["radius_px"], truth)


def test_filters_only_strips_once(disc, monkeypatch):
    rgb, _ = disc
    calls = []
    real = disc_mod.curved_gabor

    def counting(gray, *args, **kw):
        calls.append(np.asarray(gray).shape)
        return real(gray, *args, **kw)

    monkeypatch.setattr(disc_mod, "curved_gabor", counting)
    hw = 12
    res = detect_disc_boundaries(rgb, PITH, angles_deg=ANGLES[:4], half_width=hw, link=False)
    H, W = rgb.shape[:2]
    # two filter calls per transect (the ring period and the fine pass), none for the whole image
    assert len(calls) == 8
    assert all(s[0] == 2 * hw + 1 for s in calls)  # each call is a strip of 2 hw + 1 rows
    filtered = sum(a * b for a, b in calls)
    assert filtered == res.info["filtered_px"]
    # at most twice the strips of rays to the image border: far less than filtering the image once per transect
    assert filtered <= 2 * 4 * (2 * hw + 1) * (math.hypot(H, W) / 2 + 1)
    assert filtered < 0.5 * H * W
    calls.clear()
    detect_disc_boundaries(rgb, PITH, angles_deg=ANGLES[:4], half_width=hw, fine_scale=None, link=False)
    assert len(calls) == 4  # one pass
    calls.clear()
    # linked (the default): one helper transect between neighbours, filtered like the others but not returned
    res = detect_disc_boundaries(rgb, PITH, angles_deg=ANGLES[:4], half_width=hw)
    assert len(calls) == 16 and len(res.transects) == 4
    assert np.allclose(np.sort(res.info["helpers_deg"]), [30.0, 90.0, 150.0, 270.0])  # midway, the wide gap too
    calls.clear()
    detect_disc_boundaries(rgb, PITH, angles_deg=ANGLES[:4], half_width=hw, helpers=0)
    assert len(calls) == 8


def test_transects_by_end_points(disc):
    rgb, radius = disc
    ends = [(290.0, 160.0), (150.0, 20.0)]  # 0 and 270 degrees; both reach beyond the disc edge
    res = detect_disc_boundaries(rgb, PITH, ends=ends)
    assert np.allclose(res.angles_deg, [0.0, 270.0])
    for deg, tr in zip([0.0, 270.0], res.transects):
        m = match_boundaries(tr.info["radius_px"], radius(math.radians(deg))[:-1], 3.0)
        assert m["f1"] == 1.0, (deg, tr.info["radius_px"])
    # a short transect ends at its end point, inside the disc
    res = detect_disc_boundaries(rgb, PITH, ends=[(150.0 + 60.0, 160.0)])
    assert np.allclose(res.ends[0], (210.0, 160.0)) and res.transects[0].info["radius_px"].max() <= 60.0


def test_bad_input(disc):
    rgb, _ = disc
    with pytest.raises(ValueError, match=r"pith: expected \(x, y\) inside the image"):
        detect_disc_boundaries(rgb, (-3.0, 20.0))
    with pytest.raises(ValueError, match=r"pith: expected \(x, y\) inside the image"):
        detect_disc_boundaries(rgb, (10.0, 400.0))
    with pytest.raises(ValueError, match=r"pith: expected two numbers \(x, y\)"):
        detect_disc_boundaries(rgb, (1.0, 2.0, 3.0))
    with pytest.raises(ValueError, match="zero length"):
        detect_disc_boundaries(rgb, PITH, ends=[PITH])
    with pytest.raises(ValueError, match=r"ends\[0\]: expected \(x, y\) inside the image"):
        detect_disc_boundaries(rgb, PITH, ends=[(5000.0, 10.0)])
    with pytest.raises(ValueError, match="zero length"):  # pith on the border, ray pointing out of the image
        detect_disc_boundaries(rgb, (0.0, 50.0), angles_deg=[180.0])
    with pytest.raises(ValueError, match="half_width"):
        detect_disc_boundaries(rgb, PITH, half_width=0)
    with pytest.raises(ValueError, match="angles_deg"):
        detect_disc_boundaries(rgb, PITH, angles_deg=[float("nan")])
    bad = rgb.copy()
    bad[160, 200] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        detect_disc_boundaries(bad, PITH, angles_deg=[0.0])
    with pytest.raises(ValueError, match="shape"):
        detect_disc_boundaries(rgb[..., :2], PITH)
    with pytest.raises(TypeError, match="real numbers"):
        detect_disc_boundaries(rgb.astype(np.complex64), PITH)


# ---------------------------------------------------------------------------------------------------------------
# CLI
# ---------------------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def disc_png(disc, tmp_path_factory):
    rgb, radius = disc
    path = tmp_path_factory.mktemp("disc") / "disc.png"
    cv2.imwrite(str(path), (rgb[..., ::-1] * 255 + 0.5).astype(np.uint8))
    return path, radius


def test_cli_disc_mode(disc_png, tmp_path):
    path, radius = disc_png
    out, ovl = tmp_path / "disc.csv", tmp_path / "disc_overlay.png"
    rc, stdout, err = _run("detect_rings", path, "--pith", "150,160", "--angles", "0,120,240",
                           "--transect", "150,20", "--edge", "--dpi", 254, "--out", out, "--overlay", ovl)
    assert rc == 0, err
    with open(out, newline="") as f:
        rows = list(csv.DictReader(f))
    assert list(rows[0]) == ["transect", "angle_deg", "index", "kind", "x_px", "y_px", "radius_px", "width_px",
                             "width_mm"]
    assert sorted({int(r["transect"]) for r in rows}) == [0, 1, 2, 3]
    for k, deg in enumerate([0.0, 120.0, 240.0, 270.0]):
        mine = [r for r in rows if int(r["transect"]) == k]
        assert [int(r["index"]) for r in mine] == list(range(len(mine)))
        assert all(float(r["angle_deg"]) == deg for r in mine)
        assert mine[-1]["kind"] == "edge" and mine[0]["width_mm"] == ""
        m = match_boundaries(np.array([float(r["radius_px"]) for r in mine]), radius(math.radians(deg)), 3.0)
        assert m["f1"] == 1.0, (deg, [r["radius_px"] for r in mine])
        assert math.isclose(float(mine[1]["width_mm"]), float(mine[1]["width_px"]) * 0.1, rel_tol=1e-3)
    img = cv2.imread(str(ovl))
    assert img is not None and img.shape[:2] == (320, 300)
    # the whole rings beside the CSV: labelme polygons, each on one true ring all the way round
    with open(tmp_path / "disc_rings.json") as f:
        rings = json.load(f)
    assert rings["imageHeight"] == 320 and rings["imageWidth"] == 300 and rings["center"] == [160.0, 150.0]
    assert len(rings["shapes"]) >= 4 and "whole rings closed round the disc" in stdout
    for shape in rings["shapes"]:
        assert shape["shape_type"] == "polygon"
        q = np.asarray(shape["points"]) - np.array(PITH)
        r, phi = np.hypot(q[:, 0], q[:, 1]), np.arctan2(q[:, 1], q[:, 0])
        true = np.array([radius(a) for a in phi])                 # (N, K)
        k = np.argmin(np.abs(true - r[:, None]).mean(0))
        assert np.abs(true[:, k] - r).max() <= 3.0, shape["label"]
        assert np.ptp(np.unwrap(np.sort(phi))) > 1.9 * math.pi  # round the whole disc
    # eval_rings.py: the CSV against itself as labels (transect columns on both sides: matched per transect)
    rc, stdout, err = _run("eval_rings", out, out, "--tolerance-px", 1)
    assert rc == 0 and "F1 1.0000" in stdout, (stdout, err)
    rc, stdout, err = _run("eval_rings", out, out, "--transect", 7)
    assert rc != 0 and "no transect 7" in err


def test_cli_disc_bad_inputs(disc_png, tmp_path):
    path, _ = disc_png
    out, ovl = tmp_path / "o.csv", tmp_path / "o.png"
    cases = [(("--pith", "400,10"), "pith: expected (x, y) inside the image"),
             (("--pith", "150,160", "--transect", "150,160"), "zero length"),
             (("--pith", "150,160", "--transect", "1,2,3,4"), "end point X,Y"),
             (("--pith", "150"), "--pith"),
             (("--pith", "150,160", "--angles", "0,x"), "--angles"),
             (("--transect", "1,1,50,1", "--transect", "1,1,1,50"), "--pith"),
             (("--angles", "0,90", "--mode", "core"), "do not combine with --mode core"),
             (("--pith", "auto", "--mode", "section"), "do not combine with --mode section"),
             (("--pith", "150,160", "--bark", "left"), "--pith"),
             (("--rings", "r.json", "--mode", "core"), "--rings is disc mode")]
    for args, msg in cases:
        rc, _, err = _run("detect_rings", path, *args, "--out", out, "--overlay", ovl)
        assert rc not in (0, None) and msg in err, (args, err)
        assert not out.exists() and not ovl.exists(), args
    assert list(tmp_path.iterdir()) == []  # no partial or temporary files


def test_cli_disc_truncated_image(disc_png, tmp_path):
    path, _ = disc_png
    cut = tmp_path / "cut.png"
    cut.write_bytes(path.read_bytes()[:5000])  # a PNG cut off after its first 5 kB
    out, ovl = tmp_path / "o.csv", tmp_path / "o.png"
    rc, _, err = _run("detect_rings", cut, "--pith", "150,160", "--out", out, "--overlay", ovl)
    assert rc not in (0, None) and "cannot read image" in err and "cut.png" in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cut.png"]


# ---------------------------------------------------------------------------------------------------------------
# CooRecorder .pos
# ---------------------------------------------------------------------------------------------------------------
def test_read_pos_fixture():
    pos = read_pos(POS)
    assert pos.dpi == 254.0 and pos.header["Imagefile"] == "disc7.jpg" and pos.header["YearsToPith"] == "0"
    # 254 dpi: 10 px per mm; the D (gap) line is skipped, the double point keeps its first point
    expected_mm = [(10.0, 20.0), (11.0, 20.0), (12.5, 20.0), (13.2, 20.0), (14.6, 20.4), (16.5, 20.4)]
    assert np.allclose(pos.points_mm, expected_mm)
    assert np.allclose(pos.points_px, np.array(expected_mm) * 10.0)
    assert np.allclose(pos.jumps_px, [[133.0, 204.0]])
    assert np.allclose(pos.pith_px, [100.0, 200.0])
    assert np.allclose(pos.boundaries_px(), np.array(expected_mm[1:]) * 10.0)
    assert len(pos.boundaries_px(first_is_pith=False)) == 6


def test_read_pos_bad(tmp_path):
    no_dpi = tmp_path / "a.pos"
    no_dpi.write_text("#DENDRO\nSCALE 1\n1.0,2.0\n")
    with pytest.raises(ValueError, match="#DPI"):
        read_pos(no_dpi)
    bad = tmp_path / "b.pos"
    bad.write_text("#DPI 1200\n1.0;2.0\n")
    with pytest.raises(ValueError, match="line 2"):
        read_pos(bad)
    empty = tmp_path / "c.pos"
    empty.write_text("#DPI 1200\nSCALE 1\n")
    with pytest.raises(ValueError, match="no points"):
        read_pos(empty)
    with pytest.raises(ValueError, match="cannot read"):
        read_pos(tmp_path / "missing.pos")


def test_eval_rings_with_pos_labels(tmp_path):
    det = tmp_path / "det.csv"
    # the fixture's boundaries (px): 110,200 125,200 132,200 146,204 165,204; one detection 4 px off, one missed,
    # one extra, plus a second transect that --transect 0 leaves out
    det.write_text("transect,index,x_px,y_px\n0,0,110.5,200\n0,1,129,200\n0,2,132,200.5\n0,3,165,204\n"
                   "0,4,180,204\n1,0,110,200\n")
    rc, out, err = _run("eval_rings", det, POS, "--transect", 0, "--tolerance-px", 3)
    assert rc == 0, err
    assert "matched 3, detected 5, labelled 5" in out and "F1 0.6000" in out, out
    rc, out, err = _run("eval_rings", det, POS, "--transect", 0, "--tolerance-px", 5)
    assert "matched 4, detected 5, labelled 5" in out, out
    rc, out, err = _run("eval_rings", det, POS, "--transect", 0, "--pos-keep-first")
    assert "labelled 6" in out, out
    rc, out, err = _run("eval_rings", det, POS)  # several transects but no --transect
    assert rc != 0 and "--transect" in err


def test_read_pos_bark_first_with_pith_header(tmp_path):
    """The layout public .pos readers expect: a preamble line with the path, header, the outermost boundary first
    and the pith only in the header. Boundaries come out pith -> bark, all of them; a stray line after the first
    point is still an error."""
    text = ("C:\\\\dendro\\\\disc9_a.pos\n"
            "#DENDRO (Cybis Dendro program compatible format) Coordinate file written as\n"
            "#Imagefile disc9.jpg\n#DPI 254\n#All coordinates in millimeters (mm)\nSCALE 1\n"
            "#C DATED 2019;\n#C PithCoordinates=10.000,20.000;\n#C licensedTo=Someone;\n\n"
            "16.5,20.4\n14.6,20.4  14.8,20.9\n13.2,20.0#ZERO1\nD12.9,20.0#W#\n12.5,20.0\n11.0,20.0\n")
    path = tmp_path / "disc9_a.pos"
    path.write_text(text)
    pos = read_pos(path)
    assert pos.header["preamble"][0].endswith("disc9_a.pos")
    expected_px = np.array([(11.0, 20.0), (12.5, 20.0), (13.2, 20.0), (14.6, 20.4), (16.5, 20.4)]) * 10.0
    assert np.allclose(pos.boundaries_px(), expected_px)
    assert len(pos.boundaries_px(first_is_pith=False)) == 5
    path.write_text(text + "not a point\n")
    with pytest.raises(ValueError, match="line 17"):
        read_pos(path)


# ---------------------------------------------------------------------------------------------------------------
# automatic pith
# ---------------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("size,pith,widths,ecc", [((320, 300), (150.0, 160.0), None, 0.06),
                                                   ((600, 700), (430.0, 250.0), np.linspace(20, 6, 20), 0.0),
                                                   ((480, 480), (200.0, 290.0), np.linspace(9, 18, 14), 0.1)])
def test_pith_auto_on_synthetic_discs(size, pith, widths, ecc):
    """The pith from the ring orientation field alone, within 2 % of the disc's radius (the issue's bar), and
    within a few of its own standard errors."""
    rgb, radius = synthetic_disc(size=size, pith=pith, widths=widths, ecc=ecc, seed=4)
    est = detect_pith(rgb)
    err = math.hypot(*(est.xy - np.array(pith)))
    r = float(np.mean([radius(phi)[-1] for phi in np.linspace(0, 2 * math.pi, 8, endpoint=False)]))
    assert err <= 0.02 * r, (est.xy, pith, r)
    assert np.isfinite(est.sigma_px) and est.sigma_px < 0.05 * r


def test_pith_auto_refines_up_to_the_photo_resolution():
    # a 2048 px disc: the lines come from a 512 px copy, then twice at 2x in crops of 40 % and 20 % of the long side
    # (the second at the photo's own resolution); each level brings the estimate closer
    pith = np.array([1010.3, 1040.7])
    rgb, radius = synthetic_disc(size=(2048, 2048), pith=tuple(pith), widths=np.linspace(60, 20, 30), ecc=0.05,
                                 seed=5, ss=1, noise=0.03)
    errs = [float(np.linalg.norm(detect_pith(rgb, refine_levels=k).xy - pith)) for k in (0, 1)]
    est = detect_pith(rgb)
    assert est.info["levels"] == 2 and est.info["final_scale"] == 1.0
    err = float(np.linalg.norm(est.xy - pith))
    assert err < errs[1] < errs[0] and err <= 0.002 * radius(0.0)[-1], (errs, err)
    with pytest.raises(ValueError, match="refine_levels"):
        detect_pith(rgb, refine_levels=-1)


def test_pith_auto_in_disc_mode(disc, tmp_path):
    rgb, radius = disc
    res = detect_disc_boundaries(rgb, "auto", angles_deg=[0.0, 120.0, 240.0])
    assert res.info["pith"]["auto"] and math.hypot(*(res.pith - np.array(PITH))) < 0.02 * radius(0.0)[-1]
    for k, deg in enumerate([0.0, 120.0, 240.0]):
        m = match_boundaries(res.transects[k].info["radius_px"], radius(math.radians(deg))[:-1], 3.0)
        assert m["f1"] >= 0.9, (deg, m)
    with pytest.raises(ValueError, match="pith: expected .* or 'auto'"):
        detect_disc_boundaries(rgb, "middle")
    with pytest.raises(ValueError, match="too few pixels with ring structure"):
        detect_pith(np.full((64, 64, 3), 0.5, np.float32))
    with pytest.raises(ValueError, match="window"):
        detect_pith(rgb, window=4)


def test_cli_disc_mode_finds_the_pith(disc_png, tmp_path):
    path, radius = disc_png
    out = tmp_path / "auto.csv"
    rc, _, err = _run("detect_rings", path, "--mode", "disc", "--angles", "0,180", "--out", out)
    assert rc == 0, err
    assert re.search(r"pith \(auto\): 1[45]\d\.\d,1[56]\d\.\d px, standard error \d+\.\d px", err), err
    rows = list(csv.DictReader(open(out, newline="")))
    assert {int(r["transect"]) for r in rows} == {0, 1}


def test_ring_polygons_close_round_the_disc(disc):
    """Whole rings chained from the linked transects' curves: each polygon follows one true ring all the way round;
    a result that is not a disc's is refused; without linking there is none."""
    from torch_appearance.rings.ring_polygons import labelme_json, ring_polygons
    rgb, radius = disc
    res = detect_disc_boundaries(rgb, PITH, angles_deg=ANGLES)
    polys = ring_polygons(res)
    assert len(polys) >= 6
    for p in polys:
        q = p["points"] - np.array(PITH)
        r, phi = np.hypot(q[:, 0], q[:, 1]), np.arctan2(q[:, 1], q[:, 0])
        true = np.array([radius(a) for a in phi])
        k = np.argmin(np.abs(true - r[:, None]).mean(0))
        assert np.abs(true[:, k] - r).max() <= 3.0
    blob = json.loads(labelme_json(polys, "disc.png", rgb.shape, pith=PITH))
    assert len(blob["shapes"]) == len(polys) and blob["shapes"][0]["label"] == "0"
    assert ring_polygons(detect_disc_boundaries(rgb, PITH, angles_deg=ANGLES, link=False)) == []
    with pytest.raises(ValueError, match="res"):
        ring_polygons(object())


def test_closed_switch_reaches_the_linking(disc, monkeypatch):
    """closed=False traces no closed rings (link_transects gets closed_px=0); the default lets it choose."""
    from torch_appearance.rings import consistency
    seen = []
    real = consistency.link_transects

    def spy(*args, **kw):
        seen.append(kw.get("closed_px"))
        return real(*args, **kw)

    monkeypatch.setattr(consistency, "link_transects", spy)
    rgb, _ = disc
    res = detect_disc_boundaries(rgb, PITH, angles_deg=ANGLES[:3], closed=False, helpers=0)
    assert seen == [0.0] and not any(any(tr.info["closed"]) or tr.info["dropped_px"] for tr in res.transects)
    detect_disc_boundaries(rgb, PITH, angles_deg=ANGLES[:3], helpers=0)
    assert seen[1] is None
    with pytest.raises(TypeError, match="closed"):
        detect_disc_boundaries(rgb, PITH, closed="no")
