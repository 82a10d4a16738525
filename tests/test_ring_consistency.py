"""Consistency across the transects of a disc (torch_appearance.rings.consistency and detect_disc_boundaries(link=
True)): ring curves traced between neighbouring transects against the analytic rings of synthetic discs; a missing
ring is inferred and an off-ring boundary moved, from both neighbours only; nothing is invented on a clean disc."""
import math

import numpy as np
import pytest

from scipy import ndimage

from torch_appearance.rings.consistency import closed_rings, link_transects, sector_edges, trace_curves
from torch_appearance.rings.dendro import hsv_value, match_boundaries
from torch_appearance.rings.disc import detect_disc_boundaries, synthetic_disc

PITH = (150.0, 160.0)
WIDE = np.linspace(20.0, 12.0, 8)  # 8 rings, 20 -> 12 px: the last boundary (about 128 px out) is the disc edge


@pytest.fixture(scope="module")
def wide_disc():
    return synthetic_disc(size=(320, 300), pith=PITH, widths=WIDE, ecc=0.08, seed=3)


def test_trace_follows_its_own_ring_across_a_gap():
    # two sinusoidal rings 12 px apart, all ridge pixels worth the same (as sector_edges makes them); the first
    # fades out for 15 rays (19 px of arc): a curve started on it bridges the gap and stays on it rather than
    # moving to the other ring (12 px cost 3 x 12 / 1.26 = 29 > the 15 that ring would gain it), and a curve started
    # on the second stays there
    J, R = 120, 400
    th = np.linspace(0.0, 0.5, J)  # arc step at r = 300 px: 1.26 px
    E = np.zeros((J, R))
    j = np.arange(J)
    r1 = np.round(300 + 4 * np.sin(2 * np.pi * j / J)).astype(int)
    E[j, r1] = 1.0
    E[j[50:65], r1[50:65]] = 0.0
    E[j, r1 + 12] = 1.0
    arrive, score, paths = trace_curves(E, th, [r1[0], r1[0] + 12])
    assert arrive.tolist() == [float(r1[-1]), float(r1[-1] + 12)]
    assert np.array_equal(paths[0][:50], r1[:50])
    assert np.abs(paths[0] - r1).max() <= 2  # inside the gap it runs straight, back on the ridge soon after
    assert np.abs(paths[0][72:] - r1[72:]).max() <= 1
    assert np.abs(paths[1] - (r1 + 12)).max() <= 1  # on its ridge (cutting a corner where following costs more)
    assert 0 < score[0] < score[1] <= 1.0


def test_sector_edges_are_ridges_on_the_ring_boundaries(wide_disc):
    rgb, radius = wide_disc
    E, th = sector_edges(hsv_value(rgb).astype(np.float64), PITH, 0.0, math.pi / 3, 125.0, period_px=16.0)
    assert E.shape[1] == 126 and math.isclose(th[0], 0.0) and math.isclose(th[-1], math.pi / 3)
    for j in (0, len(th) // 2, len(th) - 1):
        truth = radius(th[j])[:-1]
        ridge = np.nonzero(E[j] > 0)[0]
        # every true boundary (20 px or more from the pith) has a ridge within 2 px, and ridges are nowhere else
        for b in truth[truth > 20]:
            assert np.abs(ridge - b).min() <= 2.0, (j, b, ridge)
        assert all(np.abs(truth - r).min() <= 3.0 for r in ridge if r > 20), (j, ridge, truth)


def test_link_infers_a_missing_ring_and_moves_an_off_ring_boundary(wide_disc):
    rgb, radius = wide_disc
    angles = np.arange(0.0, 360.0, 60.0)
    truth = [radius(math.radians(a))[:-1] for a in angles]
    radii = [t.copy() for t in truth]
    radii[0] = np.delete(radii[0], 4)              # transect 0 missed ring 4
    radii[2] = radii[2].copy()
    radii[2][2] += 4.5                              # transect 2 put ring 2 on the earlywood beside it
    spurious = 0.5 * (truth[4][2] + truth[4][3])
    radii[4] = np.sort(np.r_[radii[4], spurious])  # transect 4 has a false ring mid-ring
    lengths = [radius(math.radians(a))[-1] - 3.0 for a in angles]
    out = link_transects(hsv_value(rgb), PITH, angles, radii, lengths, period_px=16.0)
    assert len(out) == 6
    # transect 0: ring 4 inferred where it is, marked; nothing else inferred anywhere
    r0 = out[0]["radius_px"]
    assert out[0]["inferred"].sum() == 1
    assert abs(r0[out[0]["inferred"]][0] - truth[0][4]) <= 1.5
    assert sum(o["inferred"].sum() for o in out[1:]) == 0
    # transect 2: ring 2 moved back onto its ring (4.5 px is more than min_tol_px = 3 and less than 0.3 of the
    # rings about it, 18 px)
    assert len(out[2]["moved"]) == 1 and abs(out[2]["moved"][0][1] - truth[2][2]) <= 1.5
    assert np.abs(out[2]["radius_px"] - truth[2]).max() <= 1.5
    # transect 4: the false ring is kept (dropping cost more true rings than false ones on real discs) but no
    # neighbour's curve met it; every true boundary was met
    k = int(np.argmin(np.abs(out[4]["radius_px"] - spurious)))
    assert not out[4]["confirmed"][k]
    assert out[4]["confirmed"].sum() == len(truth[4])
    # the untouched transects come back unchanged
    for t in (1, 3, 5):
        assert np.array_equal(out[t]["radius_px"], truth[t]) and out[t]["moved"] == []


def _blurred_value(rgb):
    return ndimage.gaussian_filter(hsv_value(rgb).astype(np.float64), 1.0)


def test_closed_rings_follow_every_ring_round_the_pith(wide_disc):
    rgb, radius = wide_disc
    th, rings, scores = closed_rings(_blurred_value(rgb), PITH, np.radians([0.0, 90.0, 180.0, 270.0]), 8.0, 100.0,
                                     period_px=16.0)
    assert th.shape == (rings.shape[1],) and th[0] == 0.0 and th[-1] < 2 * math.pi
    truth = np.array([radius(t)[:-1] for t in th])  # (J, 7) true boundary radii on every ray
    inside = [k for k in range(truth.shape[1]) if truth[:, k].max() < 97.0]
    assert len(inside) == 5 and len(rings) == len(inside), [r.mean() for r in rings]
    for ring, k in zip(rings, inside):  # on its ring all the way round (the eccentric rings move by 8 px)
        assert np.abs(ring - truth[:, k]).max() <= 2.5, (k, np.abs(ring - truth[:, k]).max())
    assert np.all(scores > 0.6)


def test_closed_rings_refuse_an_edge_that_does_not_rise_all_round():
    # plain wood (value 0.5, noise 0.02) with one ring boundary at 60 px (a rise of 0.15 all round) and a stain
    # edge at 30 px that rises by 0.1 on two of every three 30-degree sectors and falls on the third. Along the
    # ring the stain is still an edge with ridges on two thirds of the circle, and a closed curve follows it (score
    # about 2/3); but the value falls across it on a third of its rays, which no ring boundary does
    pith = (100.0, 100.0)
    y, x = np.mgrid[:200, :200]
    r = np.hypot(x - pith[0], y - pith[1])
    sector = (np.degrees(np.arctan2(y - pith[1], x - pith[0])) % 360.0 // 30.0).astype(int)
    sign = np.where(sector % 3 == 2, -1.0, 1.0)
    v = 0.5 + 0.15 * (r > 60.0) + 0.1 * sign * (r > 30.0) + np.random.default_rng(0).normal(0.0, 0.02, r.shape)
    v = ndimage.gaussian_filter(v, 1.0)
    starts = np.radians([15.0, 105.0, 195.0, 285.0])  # on rising sectors
    _, loose, sl = closed_rings(v, pith, starts, 8.0, 90.0, period_px=16.0, min_rise=0.0)
    _, rings, sc = closed_rings(v, pith, starts, 8.0, 90.0, period_px=16.0)
    assert [round(float(q.mean())) for q in loose] == [30, 60] and 0.6 <= sl[0] < 0.75
    assert [round(float(q.mean())) for q in rings] == [60] and np.abs(rings[0] - 60.0).max() <= 1.0 and sc[0] > 0.95


def test_link_infers_closed_rings_near_the_pith_and_drops_what_lies_between_them(wide_disc):
    # ring 1 (about 41 px) missed on every transect: no curve starts on it, so only the closed rings find it; a
    # false boundary halfway between rings 0 and 1 on transect 3 lies between closed rings and far from all of them
    rgb, radius = wide_disc
    angles = np.arange(0.0, 360.0, 60.0)
    truth = [radius(math.radians(a))[:-1] for a in angles]
    radii = [np.delete(t, 1) for t in truth]
    spurious = 0.5 * (truth[3][0] + truth[3][1])    # 10 px from both, more than half a ring period (8 px)
    radii[3] = np.sort(np.r_[radii[3], spurious])
    lengths = [radius(math.radians(a))[-1] - 3.0 for a in angles]
    out = link_transects(hsv_value(rgb), PITH, angles, radii, lengths, period_px=16.0)
    for t, o in enumerate(out):
        got = o["radius_px"][o["closed"]]
        assert len(got) == 1 and abs(got[0] - truth[t][1]) <= 1.5, (t, got, truth[t][1])
        assert o["inferred"][o["closed"]].all() and not o["confirmed"][o["closed"]].any()
        assert len(o["closed_crossings"]) >= 4 and len(o["closed_rings"][1]) == len(o["closed_crossings"])
    assert out[3]["dropped"] == [spurious]
    assert all(o["dropped"] == [] for t, o in enumerate(out) if t != 3)
    for t, o in enumerate(out):
        assert np.abs(o["radius_px"] - truth[t]).max() <= 1.5
    # closed_px=0: nothing traced round the pith, nothing inferred (no neighbour has ring 1) or dropped
    off = link_transects(hsv_value(rgb), PITH, angles, radii, lengths, period_px=16.0, closed_px=0.0)
    assert not any(o["closed"].any() or o["inferred"].any() or o["dropped"] for o in off)


def test_link_keeps_a_confirmed_ring_that_did_not_close(wide_disc, monkeypatch):
    # rings 1 and 2 do not close (as behind a wide crack or knot): only rings 0 and 3 come back from closed_rings.
    # The transects' boundaries on rings 1 and 2 lie between closed rings and far from both, but the neighbours'
    # curves confirm them: they are kept. A false boundary there that no neighbour confirms is dropped.
    import torch_appearance.rings.consistency as consistency
    rgb, radius = wide_disc
    real = consistency.closed_rings

    def only_rings_0_and_3(*args, **kwargs):
        thetas, rings, scores = real(*args, **kwargs)
        keep = [k for k, ring in enumerate(rings) if abs(ring.mean() - 20.4) < 3 or abs(ring.mean() - 73.6) < 3]
        return thetas, rings[keep], scores[keep]

    monkeypatch.setattr(consistency, "closed_rings", only_rings_0_and_3)
    angles = np.arange(0.0, 360.0, 60.0)
    truth = [radius(math.radians(a))[:-1] for a in angles]
    radii = [t.copy() for t in truth]
    spurious = truth[2][1] + 0.5 * (truth[2][2] - truth[2][1])
    radii[2] = np.sort(np.r_[radii[2], spurious])
    lengths = [radius(math.radians(a))[-1] - 3.0 for a in angles]
    out = consistency.link_transects(hsv_value(rgb), PITH, angles, radii, lengths, period_px=16.0)
    assert all(len(o["closed_crossings"]) == 2 for o in out)
    assert out[2]["dropped"] == [spurious]
    for t, o in enumerate(out):
        assert np.abs(o["radius_px"] - truth[t]).max() <= 1.5 and len(o["radius_px"]) == len(truth[t]), t


def test_link_needs_three_transects(wide_disc):
    rgb, radius = wide_disc
    radii = [radius(0.0)[:-1][1:], radius(math.pi)[:-1]]
    out = link_transects(hsv_value(rgb), PITH, [0.0, 180.0], radii, [120.0, 120.0], period_px=16.0)
    assert [o["radius_px"].tolist() for o in out] == [r.tolist() for r in radii]
    assert not any(o["inferred"].any() for o in out)


def test_disc_mode_infers_a_ring_hidden_on_one_transect(wide_disc):
    rgb, radius = wide_disc
    rgb = rgb.copy()
    # a stain over ring boundary 3 around the transect at 0 degrees: +-30 px of arc, +-6 px of radius, filled with
    # the colour of the middle of a ring (no latewood -> earlywood step left there)
    b = radius(0.0)[3]
    y, x = np.mgrid[:rgb.shape[0], :rgb.shape[1]]
    r = np.hypot(x - PITH[0], y - PITH[1])
    arc = r * np.abs((np.arctan2(y - PITH[1], x - PITH[0]) + math.pi) % (2 * math.pi) - math.pi)
    stain = (np.abs(r - b) <= 6.0) & (arc <= 30.0)
    mid = rgb[(np.abs(r - (b - 0.5 * WIDE[3])) < 1.0) & (arc <= 30.0)].mean(0)
    rgb[stain] = mid
    angles = [0.0, 90.0, 180.0, 270.0]
    plain = detect_disc_boundaries(rgb, PITH, angles_deg=angles, link=False)
    linked = detect_disc_boundaries(rgb, PITH, angles_deg=angles)
    assert np.abs(plain.transects[0].info["radius_px"] - b).min() > 5.0  # the 1D detector misses it
    tr = linked.transects[0]
    k = int(np.argmin(np.abs(tr.info["radius_px"] - b)))
    # within 3 px (0.2 of the ring): inside the stain the curves run at a constant radius (their slope costs, the
    # transect's own ray has no ridge to snap to) while this eccentric ring moves by about 1.5 px there
    assert abs(tr.info["radius_px"][k] - b) <= 3.0 and tr.info["kind"][k] == "inferred"
    assert len(tr.info["kind"]) == len(tr.points) == len(tr.info["confirmed"])
    # every transect still finds all its rings, nothing false is added
    for a, t in zip(angles, linked.transects):
        truth = radius(math.radians(a))[:-1]
        m = match_boundaries(t.info["radius_px"], truth[truth > 8], 3.0)
        assert m["sensitivity"] == 1.0 and m["precision"] == 1.0, (a, t.info["radius_px"], truth)
    assert linked.info["link_seconds"] is not None and len(linked.info["helpers_deg"]) == 4


def test_link_infers_on_a_transect_with_no_boundary_of_its_own(wide_disc):
    # a transect whose detector found nothing gets the rings both neighbours' curves agree on
    rgb, radius = wide_disc
    angles = [0.0, 120.0, 240.0]
    truth = [radius(math.radians(a))[:-1] for a in angles]
    radii = [truth[0], np.zeros(0), truth[2]]
    lengths = [radius(math.radians(a))[-1] - 3.0 for a in angles]
    out = link_transects(hsv_value(rgb), PITH, angles, radii, lengths, period_px=16.0)
    got = out[1]["radius_px"]
    assert out[1]["inferred"].all() and len(got) >= len(truth[1]) - 2
    assert all(np.abs(truth[1] - x).min() <= 3.0 for x in got), (got, truth[1])


def test_bad_link_arguments(wide_disc):
    rgb, _ = wide_disc
    with pytest.raises(ValueError, match="radii, lengths"):
        link_transects(hsv_value(rgb), PITH, [0.0, 120.0, 240.0], [np.zeros(0)] * 2, [100.0] * 3, period_px=16.0)
    with pytest.raises(ValueError, match="helpers"):
        detect_disc_boundaries(rgb, PITH, helpers=-1)
    with pytest.raises(TypeError, match="link"):
        detect_disc_boundaries(rgb, PITH, link="yes")


def _trace_curves_naive(E, thetas, starts, smooth=3.0, max_tilt_deg=40.0, snap_px=2):
    """:func:`trace_curves` written out one start, ray and radius at a time (the slow, obviously right reference)."""
    J, R = E.shape
    dth = abs(thetas[1] - thetas[0])
    tilt = math.tan(math.radians(max_tilt_deg))
    m = int(min(R - 1, 63, math.ceil(tilt * (R - 1) * dth) + 1))
    arrive, score, paths = [], [], np.zeros((len(starts), J))
    for n, r0 in enumerate(starts):
        S = [-math.inf] * R
        r0 = int(np.clip(np.round(r0), 0, R - 1))
        for k in (-1, 0, 1):
            rr = min(max(r0 + k, 0), R - 1)
            S[rr] = E[0, rr] - (0.0 if k == 0 else 0.1)
        back = [[0] * R for _ in range(J)]
        for j in range(1, J):
            new = []
            for r in range(R):
                arc = max(r * dth, 1e-3)
                best, arg = -math.inf, 0
                for k, sh in enumerate(range(-m, m + 1)):  # from r - sh; the first best move wins
                    pen = smooth * (abs(sh) / arc) if abs(sh) <= tilt * arc + 1.0 else math.inf
                    val = S[r - sh] - pen if 0 <= r - sh < R else -math.inf
                    if val > best:
                        best, arg = val, k
                new.append(best + E[j, r])
                back[j][r] = arg
            S = new
        cur = int(np.argmax(S))
        score.append(S[cur] / J)
        end = cur
        for j in range(J - 1, -1, -1):
            paths[n, j] = cur
            if j > 0:
                cur = cur - (back[j][cur] - m)
        lo = min(max(end - snap_px, 0), R - 1)
        win = [E[-1, min(max(lo + i, 0), R - 1)] for i in range(2 * snap_px + 1)]
        arrive.append(float(min(max(lo + int(np.argmax(win)), 0), R - 1)))
    return np.array(arrive), np.array(score), paths


def test_trace_curves_matches_the_naive_dynamic_programme():
    # ridges of equal worth, moves of 2 px forbidden (steeper than the tilt at every radius here), starts at the ends
    # of the radius range; without a cost per move (smooth 0) most moves tie, and the first best must win as in the
    # reference
    rng = np.random.default_rng(7)
    J, R = 9, 28
    E = np.where(rng.random((J, R)) < 0.3, 1.0, 0.0)
    E[:, 10] = 0.95
    th = np.linspace(0.0, 0.25, J)  # m = 2 at R = 28
    starts = [0.0, 9.6, 14.5, 27.0]
    for smooth in (3.0, 0.0):
        got = trace_curves(E, th, starts, smooth=smooth)
        ref = _trace_curves_naive(E, th, starts, smooth=smooth)
        for a, b in zip(got, ref):
            np.testing.assert_array_equal(a, b)
