"""Files dendrochronologists use (issue 26): Tucson ``.rwl`` ring-width series and CooRecorder ``.pos`` coordinate
files written by the project and read back, a Tucson file typed by hand from the format's description, refusals of
malformed files, and ``ta-detect-rings --pos/--rwl`` on a synthetic disc and core."""
import csv

import cv2
import numpy as np
import pytest

from torch_appearance.rings import RingSeries, read_pos, read_rwl, write_pos, write_rwl
from torch_appearance.rings.disc import synthetic_disc


def _run(name, *args):
    from torch_appearance.testing import run_command
    return run_command(name, *args)


# ---------------------------------------------------------------------------------------------------------------
# Tucson .rwl
# ---------------------------------------------------------------------------------------------------------------
def test_rwl_typed_by_hand_from_the_format():
    """A file typed column by column from the format's description: the reader's values are the typed ones."""
    text = ("ABC01   1995   123   456   789   234   567\r\n"
            "ABC01   2000   111     0   222   999\r\n"
            "XYZ     2003  1500  2500 -9999\r\n")
    series = read_rwl_text(text)
    assert list(series) == ["ABC01", "XYZ"]
    a, x = series["ABC01"], series["XYZ"]
    assert (a.first_year, a.last_year) == (1995, 2002)
    assert np.allclose(a.widths_mm, [1.23, 4.56, 7.89, 2.34, 5.67, 1.11, 0.0, 2.22])
    assert (x.first_year, x.last_year) == (2003, 2004) and np.allclose(x.widths_mm, [1.5, 2.5])


_TMP = {}


def read_rwl_text(text, name="typed.rwl"):
    path = _TMP["dir"] / name
    path.write_bytes(text.encode("ascii"))
    return read_rwl(path)


@pytest.fixture(autouse=True)
def _tmp(tmp_path):
    _TMP["dir"] = tmp_path


@pytest.mark.parametrize("precision", [0.001, 0.01])
def test_rwl_round_trip_and_layout(tmp_path, precision):
    rng = np.random.default_rng(3)
    a = RingSeries.ending("C13C00", 2018, np.r_[rng.uniform(0.05, 6.0, 22), 0.0])  # 23 rings, a missing one
    b = RingSeries("C13C01", 1987, rng.uniform(0.5, 3.0, 10))
    path = tmp_path / "disc.rwl"
    write_rwl(path, [a, b], precision=precision)
    lines = path.read_bytes().decode("ascii").split("\r\n")
    assert lines[-1] == "" and all(len(line) <= 72 for line in lines)
    # a series starts at its first year and continues at decades; the stop marker follows its last value
    assert lines[0].startswith("C13C00  1996") and len(lines[0]) == 12 + 4 * 6  # 1996..1999
    assert lines[1].startswith("C13C00  2000") and len(lines[1]) == 12 + 10 * 6
    stop = "   999" if precision == 0.01 else " -9999"
    assert lines[2].startswith("C13C00  2010") and lines[2].endswith("     0" + stop)
    assert lines[3].startswith("C13C01  1987") and len(lines[3]) == 12 + 3 * 6  # 1987..1989
    back = read_rwl(path)
    for s in (a, b):
        got = back[s.id]
        assert (got.first_year, got.last_year) == (s.first_year, s.last_year)
        assert np.max(np.abs(got.widths_mm - s.widths_mm)) <= precision / 2 + 1e-12


def test_rwl_refusals(tmp_path):
    ok = RingSeries("A", 2000, [1.0, 2.0])
    for bad, match in [(RingSeries("TOO_LONG_9", 2000, [1.0]), "1 to 8 characters"),
                       (RingSeries("A B", 2000, [1.0]), "without spaces"),
                       (RingSeries("A", 2000, [1.0, -0.5]), ">= 0 mm"),
                       (RingSeries("A", 2000, [1.0, float("nan")]), "finite"),
                       (RingSeries("A", 2000, []), "no ring widths"),
                       (RingSeries("A", 9999, [1.0, 1.0]), "4-column year"),
                       (RingSeries("A", 2000, [9.99]), "precision 0.01")]:
        with pytest.raises(ValueError, match=match):
            write_rwl(tmp_path / "x.rwl", bad, precision=0.01)
    with pytest.raises(ValueError, match="distinct"):
        write_rwl(tmp_path / "x.rwl", [ok, ok])
    with pytest.raises(ValueError, match="precision"):
        write_rwl(tmp_path / "x.rwl", ok, precision=0.1)
    with pytest.raises(TypeError, match="RingSeries"):
        write_rwl(tmp_path / "x.rwl", [(1, 2)])
    assert not (tmp_path / "x.rwl").exists()
    write_rwl(tmp_path / "ok.rwl", ok)
    whole = (tmp_path / "ok.rwl").read_bytes()
    cut = tmp_path / "cut.rwl"
    cut.write_bytes(whole[:-8])  # the stop marker cut off
    with pytest.raises(ValueError, match="no stop marker"):
        read_rwl(cut)
    with pytest.raises(ValueError, match="without its stop marker"):
        read_rwl_text("A       2000   100   200\r\nB       2000   100   999\r\n")
    with pytest.raises(ValueError, match="expected a data line"):
        read_rwl_text("A       2000   100   200\r\nA       2002   1x0   999\r\n")
    with pytest.raises(ValueError, match="holds no ring-width series"):
        read_rwl_text("just a header line\r\n")


# ---------------------------------------------------------------------------------------------------------------
# CooRecorder .pos
# ---------------------------------------------------------------------------------------------------------------
def test_pos_round_trip(tmp_path):
    pith = np.array([1520.25, 1610.5])
    pts = pith + np.outer([40.0, 95.5, 151.25, 230.0], [0.6, 0.8])  # a transect from the pith, 156 DPI
    path = tmp_path / "t.pos"
    write_pos(path, pts, 156.0, pith_px=pith, image_file="/somewhere/C13C.jpg", last_year=2018)
    raw = path.read_bytes().decode("ascii")
    assert raw.endswith("\r\n") and "#DPI 156.0\r\n" in raw and "SCALE 1\r\n" in raw and "#C DATED 2018" in raw
    pos = read_pos(path)
    assert pos.dpi == 156.0 and pos.header["Imagefile"] == "C13C.jpg"
    px = 0.0005 * 156.0 / 25.4  # half of the file's 0.001 mm
    assert np.allclose(pos.pith_px, pith, atol=px) and np.allclose(pos.points_px[0], pith, atol=px)
    assert np.allclose(pos.boundaries_px(), pts, atol=px)
    write_pos(tmp_path / "core.pos", pts, 156.0)  # no pith: the points alone
    assert np.allclose(read_pos(tmp_path / "core.pos").boundaries_px(first_is_pith=False), pts, atol=px)
    for args, match in [((np.zeros((0, 2)), 156.0), "K >= 1"), ((pts, 0.0), "dpi"), ((pts[:, :1], 156.0), "K, 2"),
                        ((pts, 156.0, [1.0]), "pith_px")]:
        with pytest.raises(ValueError, match=match):
            write_pos(tmp_path / "bad.pos", *args)
    assert not (tmp_path / "bad.pos").exists()


# ---------------------------------------------------------------------------------------------------------------
# ta-detect-rings --pos / --rwl
# ---------------------------------------------------------------------------------------------------------------
def test_cli_disc_writes_pos_and_rwl(tmp_path):
    rgb, _ = synthetic_disc(seed=0)
    image = tmp_path / "disc7.png"
    cv2.imwrite(str(image), (rgb[..., ::-1] * 255 + 0.5).astype(np.uint8))
    out = tmp_path / "disc.csv"
    rc, stdout, err = _run("detect_rings", image, "--pith", "150,160", "--angles", "0,90,180,270", "--dpi", 254,
                           "--out", out, "--pos", tmp_path / "disc.pos", "--rwl", tmp_path / "disc.rwl",
                           "--last-year", 2020)
    assert rc == 0, err
    with open(out, newline="") as f:
        rows = list(csv.DictReader(f))
    series = read_rwl(tmp_path / "disc.rwl")
    assert list(series) == [f"disc7{k:02d}" for k in range(4)]
    for k in range(4):
        mine = [r for r in rows if int(r["transect"]) == k]
        radius_mm = np.array([float(r["radius_px"]) for r in mine]) * 0.1  # 254 DPI: 0.1 mm per pixel
        s = series[f"disc7{k:02d}"]
        assert s.last_year == 2020 and len(s.widths_mm) == len(mine)
        assert np.allclose(np.cumsum(s.widths_mm), radius_mm, atol=0.0005 * len(mine) + 0.001)
        pos = read_pos(tmp_path / f"disc_t{k}.pos")
        assert np.allclose(pos.pith_px, [150.0, 160.0], atol=0.01)
        xy = np.array([[float(r["x_px"]), float(r["y_px"])] for r in mine])
        assert np.allclose(pos.boundaries_px(), xy, atol=0.011)
    assert "disc.rwl" in stdout and "disc_t3.pos" in stdout


def test_cli_ring_files_need_a_scale_and_a_year(tmp_path):
    rgb, _ = synthetic_disc(seed=0)
    image = tmp_path / "d.png"
    cv2.imwrite(str(image), (rgb[..., ::-1] * 255 + 0.5).astype(np.uint8))
    out = tmp_path / "o.csv"
    for args, match in [(("--pith", "150,160", "--rwl", tmp_path / "o.rwl", "--last-year", 2020), "--dpi"),
                        (("--pith", "150,160", "--dpi", 254, "--rwl", tmp_path / "o.rwl"), "--last-year"),
                        (("--mode", "section", "--dpi", 254, "--pos", tmp_path / "o.pos"), "section"),
                        (("--pith", "150,160", "--dpi", 254, "--rwl", tmp_path / "o.rwl", "--last-year", 2020,
                          "--series-id", "TOOLONG"), "--series-id"),
                        (("--pith", "150,160", "--last-year", 2020),  # was ignored without a word
                         "--last-year: it dates the ring files; give --pos or --rwl, or leave it out"),
                        (("--pith", "150,160", "--dpi", 254, "--rwl", tmp_path / "o.rwl", "--last-year", 10 ** 12),
                         "--last-year: expected a year in -999 ... 9999")]:  # was refused after all the work
        rc, _, err = _run("detect_rings", image, *args, "--out", out)
        assert rc == 2 and match in err, (args, err)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["d.png"]
