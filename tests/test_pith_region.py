"""The pith's own edge as a closed curve round the pith (rings.pith_region, issue 48 item 3), on synthetic discs of
rings.synthetic_discs with a dark pith of known edge (``make_disc(pith_px=...)``): found where it is, not found where
there is none, placed on every transect by disc mode as ring 0 (inside the quarter ring period where the transects
themselves find nothing)."""
import math

import numpy as np
import pytest

from torch_appearance.rings.dendro import hsv_value
from torch_appearance.rings.disc import detect_disc_boundaries
from torch_appearance.rings.pith_region import pith_edge, place_pith_edge
from torch_appearance.rings.synthetic_discs import make_disc

ANGLES = (20.0, 110.0, 200.0, 290.0)
# rings 40 -> 20 px wide: the disc's ring period is about 30 px, so disc mode drops everything within 7.5 px of the
# pith, and a pith edge at about 6 px is found by nothing but the pith region's model
WIDE = dict(size=(300, 300), n_rings=5, inner_width_px=40.0, outer_width_px=20.0)


def _edge(disc, **kw):
    truth = [disc.boundaries_along(a) for a in ANGLES]
    skip = 1 if disc.info["pith_px"] > 0 else 0
    return pith_edge(hsv_value(disc.rgb), disc.pith, ANGLES, [b[skip:] for b in truth], period_px=30.0, **kw), truth


@pytest.mark.parametrize("seed", [0, 1])
def test_pith_edge_follows_the_known_edge(seed):
    disc = make_disc(**WIDE, pith_px=6.0, seed=seed)
    e, truth = _edge(disc)
    assert e["found"] and e["support"] > 0.9 and e["contrast"] > 1.0
    assert np.abs(e["crossings"] - [b[0] for b in truth]).max() < 1.0
    # the whole curve round the pith, not only at the transects
    true_curve = np.interp(e["thetas"], disc.phis, disc.radii[0], period=2 * math.pi)
    assert np.mean(np.abs(e["radius"] - true_curve) <= 1.5) > 0.95


@pytest.mark.parametrize("seed", [0, 1])
def test_no_pith_edge_where_there_is_none(seed):
    """Without a pith the locally normalised edge map still has ridges on most rays (support > 0.75): the contrast
    against the rings' own rises is what says no."""
    e, _ = _edge(make_disc(**WIDE, seed=seed))
    assert not e["found"] and e["contrast"] < 0.3


def test_place_pith_edge():
    keep, new = place_pith_edge([2.0, 5.0, 40.0, 80.0], 16.0)
    assert keep.tolist() == [False, False, True, True] and new.tolist() == [16.0]
    keep, new = place_pith_edge([14.5, 40.0], 16.0)               # already there: nothing placed, nothing dropped
    assert keep.tolist() == [True, True] and new.size == 0
    keep, new = place_pith_edge([], 16.0)
    assert keep.size == 0 and new.tolist() == [16.0]


def test_disc_mode_puts_the_pith_edge_on_every_transect():
    disc = make_disc(**WIDE, pith_px=6.0, seed=0)
    off = detect_disc_boundaries(disc.rgb, disc.pith, angles_deg=ANGLES)
    on = detect_disc_boundaries(disc.rgb, disc.pith, angles_deg=ANGLES, pith_edge=True)
    assert off.info["pith_edge"] is None and on.info["pith_edge"]["found"]
    for t_off, t_on, a in zip(off.transects, on.transects, ANGLES):
        truth = disc.boundaries_along(a)
        assert t_off.info["radius_px"][0] > 20.0 and "pith_edge" not in t_off.info["kind"]  # missed without it
        assert t_on.info["kind"][0] == "pith_edge" and abs(t_on.info["radius_px"][0] - truth[0]) < 1.0
        assert np.allclose(t_on.info["radius_px"][1:], t_off.info["radius_px"])  # the rest unchanged
        assert np.allclose(t_on.points[0], disc.pith + t_on.info["radius_px"][0] * np.array(
            [math.cos(math.radians(a)), math.sin(math.radians(a))]))


def test_disc_mode_refuses_bad_pith_edge_options():
    disc = make_disc(size=(64, 64), n_rings=3, inner_width_px=8.0, outer_width_px=6.0)
    with pytest.raises(TypeError, match="pith_edge"):
        detect_disc_boundaries(disc.rgb, disc.pith, pith_edge=1)
    with pytest.raises(ValueError, match="pith_edge_min_support"):
        detect_disc_boundaries(disc.rgb, disc.pith, pith_edge=True, pith_edge_min_support=1.5)
    with pytest.raises(ValueError, match="pith_px"):
        make_disc(inner_width_px=10.0, pith_px=6.0)


@pytest.mark.parametrize("on", [False, True])
def test_kinds_stay_one_per_boundary_when_linking_adds_some(on):
    """On this disc the linking infers a ring on one transect (its boundary count grows after the pith-edge flags
    could first have been sized): every transect still has one kind per boundary."""
    disc = make_disc(size=(300, 300), n_rings=12, inner_width_px=20.0, outer_width_px=3.0, jpeg_quality=25)
    res = detect_disc_boundaries(disc.rgb, disc.pith, angles_deg=ANGLES, pith_edge=on)
    assert sum(tr.info["kind"].count("inferred") for tr in res.transects) > 0
    for tr in res.transects:
        assert len(tr.info["kind"]) == len(tr.info["radius_px"]) == len(tr.points)


def test_cli_pith_edge(tmp_path):
    """``ta-detect-rings --pith-edge``: ring 0 in the CSV as kind pith_edge on every transect, the curve drawn white
    on the overlay; without the flag no such row."""
    import csv

    import cv2

    from torch_appearance.testing import run_command

    disc = make_disc(**WIDE, pith_px=6.0, seed=0)
    path = tmp_path / "disc.png"
    cv2.imwrite(str(path), (disc.rgb[..., ::-1] * 255 + 0.5).astype(np.uint8))
    pith = f"{disc.pith[0]:.2f},{disc.pith[1]:.2f}"
    angles = ",".join(f"{a:g}" for a in ANGLES)
    kinds = {}
    for flag in ("--pith-edge", None):
        out, ovl = tmp_path / f"{flag}.csv", tmp_path / f"{flag}.png"
        args = [path, "--pith", pith, "--angles", angles, "--out", out, "--overlay", ovl] + ([flag] if flag else [])
        rc, _, err = run_command("detect_rings", *args)
        assert rc == 0, err
        with open(out, newline="") as f:
            kinds[flag] = [(int(r["transect"]), r["kind"], float(r["radius_px"])) for r in csv.DictReader(f)]
    on = [(t, r) for t, k, r in kinds["--pith-edge"] if k == "pith_edge"]
    assert [t for t, _ in on] == [0, 1, 2, 3]
    assert all(abs(r - disc.boundaries_along(ANGLES[t])[0]) < 1.0 for t, r in on)
    assert not [k for _, k, _ in kinds[None] if k == "pith_edge"]
    rc, _, err = run_command("detect_rings", path, "--pith", pith, "--bark-gaps", "-1", "--out", tmp_path / "x.csv")
    assert rc != 0 and "--bark-gaps" in err
