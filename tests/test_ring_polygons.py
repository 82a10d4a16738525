"""Whole rings traced round a disc (rings.ring_polygons.trace_whole_rings, place_whole_rings; issue 48 item 2).

The transects' boundaries are given (the true rings, one missed on one transect, a false one added on another), so
these tests check the tracer and the placing alone, against the generator's true ring curves."""
import math

import numpy as np
import pytest

from torch_appearance.rings.dendro import hsv_value
from torch_appearance.rings.disc import synthetic_disc
from torch_appearance.rings.ring_polygons import place_whole_rings, trace_whole_rings

PITH = (150.0, 160.0)
ANGLES = np.arange(8) * 45.0 + 10.0


@pytest.fixture(scope="module")
def traced():
    rgb, radius = synthetic_disc(seed=1)  # 320 x 300, 12 eccentric rings 14 -> 7 px (the last one the disc edge)
    radii = [radius(math.radians(a))[:-1].copy() for a in ANGLES]
    lengths = [float(radius(math.radians(a))[-1]) for a in ANGLES]
    missed = radii[2][6]
    radii[2] = np.delete(radii[2], 6)                               # transect 2 misses ring 6
    false = 0.5 * (radii[5][3] + radii[5][4])
    radii[5] = np.sort(np.r_[radii[5], false])                      # transect 5 has a false boundary
    w = trace_whole_rings(hsv_value(rgb), PITH, ANGLES, radii, lengths, period_px=11.0)
    return w, radius, radii, lengths, missed, false


def test_every_ring_closes_round_the_disc_on_its_true_curve(traced):
    w, radius, *_ = traced
    truth = np.array([radius(t)[:-1] for t in w["thetas"]]).T       # (11, J)
    assert w["rings"].shape == truth.shape                          # every ring inside the edge, none twice
    assert np.abs(w["rings"] - truth).max() <= 2.0
    assert np.all(np.diff(w["rings"], axis=0) > 0)                  # rings do not cross
    assert np.all(w["support"] >= 7 / 8) and np.all(w["scores"] >= 0.6)


def test_a_missed_ring_is_placed_and_a_false_boundary_dropped(traced):
    w, _, radii, lengths, missed, false = traced
    keep, new = place_whole_rings(radii[2], w["crossings"][2], inner_px=5.5, length_px=lengths[2],
                                  support=w["support"])
    assert keep.all() and len(new) == 1 and abs(new[0] - missed) <= 1.5
    keep, new = place_whole_rings(radii[5], w["crossings"][5], inner_px=5.5, length_px=lengths[5],
                                  support=w["support"])
    assert len(new) == 0 and radii[5][~keep].tolist() == [false]
    # nothing is dropped beyond the second outermost ring (where narrow rings the tracer could not follow lie)
    last = 0.5 * (radii[5][-1] + radii[5][-2])
    keep, _ = place_whole_rings(np.r_[radii[5], last], w["crossings"][5], inner_px=5.5, length_px=lengths[5],
                                support=w["support"])
    assert keep[-1] and not keep.all()
    # neither without its switch; a ring few transects found does not act
    keep, new = place_whole_rings(radii[5], w["crossings"][5], inner_px=5.5, length_px=lengths[5], drop=False)
    assert keep.all()
    _, new = place_whole_rings(radii[2], w["crossings"][2], inner_px=5.5, length_px=lengths[2], place=False)
    assert len(new) == 0
    low = np.where(np.arange(len(w["support"])) == 6, 0.25, w["support"])
    _, new = place_whole_rings(radii[2], w["crossings"][2], inner_px=5.5, length_px=lengths[2], support=low)
    assert len(new) == 0


def test_trace_whole_rings_refuses_mismatched_transects():
    with pytest.raises(ValueError, match="radii, lengths"):
        trace_whole_rings(np.zeros((50, 50)), (25.0, 25.0), [0.0, 90.0, 180.0], [np.zeros(0)] * 2, [20.0] * 3,
                          period_px=8.0)


def test_disc_mode_traces_whole_rings_and_does_not_place_them_by_default(monkeypatch):
    """Disc mode's defaults (leave-one-disc-out, issue 48): the whole rings are traced (and are the polygons), they
    drop boundaries on no ring, and they are not placed on the transects; whole_rings=False traces none."""
    import torch_appearance.rings.ring_polygons as rp
    from torch_appearance.rings.disc import detect_disc_boundaries
    calls = []

    def spy(*args, **kw):
        calls.append((kw["place"], kw["drop"]))
        return place_whole_rings(*args, **kw)

    monkeypatch.setattr(rp, "place_whole_rings", spy)
    rgb, _ = synthetic_disc(seed=1)
    res = detect_disc_boundaries(rgb, PITH, angles_deg=[0.0, 90.0, 180.0, 270.0])
    whole = res.info["rings_polar"]["whole"]
    assert whole is not None and len(whole["rings"]) >= 8 and res.info["whole_rings_seconds"] > 0
    assert len(rp.ring_polygons(res)) == len(whole["rings"])
    assert calls and set(calls) == {(False, True)}           # one call per transect (helpers too): drop, no place
    calls.clear()
    detect_disc_boundaries(rgb, PITH, angles_deg=[0.0, 90.0, 180.0, 270.0], whole_place=True, whole_drop=False)
    assert set(calls) == {(True, False)}
    calls.clear()
    off = detect_disc_boundaries(rgb, PITH, angles_deg=[0.0, 90.0, 180.0, 270.0], whole_rings=False)
    assert off.info["rings_polar"]["whole"] is None and off.info["whole_rings_seconds"] is None and not calls


def _band_trace_naive(Eb, u0, pen, close_px):
    """:func:`_band_trace` written out one seed, ray and height at a time (the slow, obviously right reference)."""
    N, J1, B = Eb.shape
    m = (pen.shape[2] - 1) // 2
    paths, score = np.zeros((N, J1), dtype=int), np.zeros(N)
    for n in range(N):
        S = [-math.inf] * B
        u = int(np.clip(np.round(u0[n]), 0, B - 1))
        for k in (-1, 0, 1):
            uu = min(max(u + k, 0), B - 1)
            S[uu] = Eb[n, 0, uu] - 0.1 * abs(k)
        back = [[0] * B for _ in range(J1)]
        for i in range(1, J1):
            new = []
            for v in range(B):
                best, arg = -math.inf, 0
                for k in range(2 * m + 1):  # from height v + k - m, a move of m - k; the first best move wins
                    w = v + k - m
                    val = S[w] - pen[n, i - 1, k] if 0 <= w < B else -math.inf
                    if val > best:
                        best, arg = val, k
                new.append(best + Eb[n, i, v])
                back[i][v] = arg
            S = new
        S = [s if abs(v - u) <= close_px else -math.inf for v, s in enumerate(S)]
        cur = int(np.argmax(S))
        score[n] = S[cur] / J1
        for i in range(J1 - 1, -1, -1):
            paths[n, i] = cur
            if i > 0:
                cur = cur + back[i][cur] - m
    return paths, score


def test_band_trace_matches_the_naive_dynamic_programme():
    # small integer responses and symmetric move costs: many ties, which the first best move must break as the
    # reference does; a band edge of -1 and a seed near the top (moves out of the band are impossible)
    from torch_appearance.rings.ring_polygons import _band_trace
    rng = np.random.default_rng(5)
    N, J1, B, m = 3, 14, 11, 3
    Eb = rng.integers(0, 3, size=(N, J1, B)).astype(np.float64)
    Eb[:, :, -2:] = -1.0
    pen = np.broadcast_to(0.5 * np.abs(np.arange(m, -m - 1, -1)).astype(np.float64), (N, J1 - 1, 2 * m + 1))
    pen = pen + 0.25 * rng.integers(0, 2, size=(N, J1 - 1, 1))
    u0 = np.array([2.0, 5.4, 10.0])
    paths, score = _band_trace(Eb, u0, pen, close_px=2.0)
    ref_paths, ref_score = _band_trace_naive(Eb, u0, pen, 2.0)
    np.testing.assert_array_equal(paths, ref_paths)
    np.testing.assert_array_equal(score, ref_score)


def test_a_value_blurred_once_gives_the_same_whole_rings_and_links():
    # disc mode blurs the photo's value once for the linking and the whole rings (value_blurred=True)
    from torch_appearance.rings.consistency import blurred_value, link_transects
    rgb, radius = synthetic_disc(seed=4)
    value = hsv_value(rgb)
    radii = [radius(math.radians(a))[:-1].copy() for a in ANGLES]
    lengths = [float(radius(math.radians(a))[-1]) for a in ANGLES]
    a = trace_whole_rings(value, PITH, ANGLES, radii, lengths, period_px=11.0)
    b = trace_whole_rings(blurred_value(value), PITH, ANGLES, radii, lengths, period_px=11.0, value_blurred=True)
    for key in ("thetas", "rings", "scores", "crossings", "support"):
        np.testing.assert_array_equal(a[key], b[key], err_msg=key)
    la = link_transects(value, PITH, ANGLES, radii, lengths, period_px=11.0)
    lb = link_transects(blurred_value(value), PITH, ANGLES, radii, lengths, period_px=11.0, value_blurred=True)
    for x, y in zip(la, lb):
        for key in ("radius_px", "inferred", "confirmed", "closed", "closed_crossings"):
            np.testing.assert_array_equal(x[key], y[key], err_msg=key)
