"""Dendrochronology: ring boundaries on synthetic cores, the matching metric, the CLI's bad-input handling, and
section mode (microscopy cross-sections: synthetic cells, and real patches in tests/data/rings_microscopy, MIT,
see the README there, with human ring-boundary masks)."""
import os
import subprocess
import sys
import warnings

import cv2
import numpy as np
import pytest
from scipy.spatial import cKDTree

from torch_appearance.rings.dendro import (boundary_f_measure, detect_core_boundaries, detect_section_boundaries,
                                           detect_transect_boundaries, growth_direction, mask_centerline,
                                           match_boundaries, resample_polyline, ring_widths_mm)

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def synthetic_core(widths, height=48, noise=0.03, pores=True, tilt=0.0, seed=0, ss=4, lead=12.0, tail=12.0):
    """RGB core image ``(H, W, 3)`` with the bark on the right, and the true boundary x positions (pixels).

    Each ring (pith -> bark) is light earlywood fading slowly, then the last 35 % darkens to latewood, then a sharp
    step up to the next earlywood: the boundary. Rings are tilted by ``tilt`` px of x per row, rendered with ``ss``
    times supersampling along x, then dark pores and Gaussian noise are added. Extra rings pad both ends so that
    the image is filled with rings; boundaries within 1 px of the ends are not counted.
    """
    rng = np.random.default_rng(seed)
    widths = np.r_[widths[0], widths[0], widths, widths[-1], widths[-1], widths[-1]]
    b = np.cumsum(widths) - 2 * widths[0] - lead
    W = int(np.ceil(b[-4] + tail))
    xs = (np.arange(W * ss) + 0.5) / ss - 0.5
    ys = np.arange(height) - (height - 1) / 2
    X = xs[None, :] - tilt * ys[:, None]
    starts = np.r_[b[0] - widths[0], b]
    k = np.searchsorted(b, X, side="right")
    s0 = starts[np.minimum(k, len(starts) - 1)]
    wk = np.r_[widths, widths[-1]][np.minimum(k, len(widths))]
    frac = np.clip((X - s0) / wk, 0, 1)
    late = 0.35
    v = np.where(frac < 1 - late, 0.8 - 0.15 * frac / (1 - late), 0.65 - 0.4 * (frac - (1 - late)) / late)
    v = v.reshape(height, W, ss).mean(2)
    if pores:
        yy, xx = np.ogrid[:height, :W]
        for _ in range(W // 4):
            cx, cy, r = rng.uniform(0, W), rng.uniform(0, height), rng.uniform(0.3, 1.0)
            v = np.where((xx - cx) ** 2 + (yy - cy) ** 2 <= r * r, v * 0.5, v)
    v = v + rng.normal(0, noise, v.shape)
    rgb = np.clip(np.stack([v, 0.85 * v, 0.6 * v], -1), 0, 1).astype(np.float32)
    return rgb, b[(b >= 1) & (b <= W - 2)]


def ring_series(seed, n=60):
    """Ring widths shrinking from ~25 px to 3 px and growing back to ~12 px, with +-20 % jitter."""
    rng = np.random.default_rng(seed)
    w = np.clip(np.r_[np.linspace(25, 3, n // 2), np.linspace(3, 12, n // 2)] * rng.uniform(0.8, 1.2, n), 3, None)
    w[n // 2 - 2:n // 2 + 2] = 3.0  # a run of the narrowest rings
    return w


@pytest.mark.parametrize("seed,tilt,bark", [(0, 0.0, "right"), (1, 0.0, "left"), (2, 0.15, "right"),
                                            (3, 0.0, "bottom")])
def test_synthetic_core_sensitivity_precision(seed, tilt, bark):
    widths = ring_series(seed)
    assert widths.min() <= 3.0 + 1e-9
    rgb, b = synthetic_core(widths, seed=seed, tilt=tilt)
    W = rgb.shape[1]
    yc = (rgb.shape[0] - 1) / 2
    truth = np.stack([b, np.full_like(b, yc)], 1)
    if bark == "left":  # mirror: the bark is now on the left, pith on the right
        rgb, truth = rgb[:, ::-1], np.stack([(W - 1) - b, np.full_like(b, yc)], 1)
    elif bark == "bottom":  # transpose: core axis vertical, bark at the bottom
        rgb, truth = rgb.transpose(1, 0, 2), truth[:, ::-1]
    res = detect_core_boundaries(np.ascontiguousarray(rgb), bark=bark, pixel_size_mm=0.01)
    m = match_boundaries(res.points, truth, tolerance_px=3)
    assert m["sensitivity"] >= 0.95 and m["precision"] >= 0.95, m
    # ordered pith -> bark: monotone along the axis away from the pith
    axis = res.points[:, 1] if bark == "bottom" else res.points[:, 0]
    assert np.all(np.diff(axis) < 0) if bark == "left" else np.all(np.diff(axis) > 0)
    assert np.isnan(res.widths_mm[0]) and np.allclose(res.widths_mm[1:], res.widths_px[1:] * 0.01)


def test_transect_on_synthetic_rings():
    rgb, b = synthetic_core(np.full(20, 12.0), height=64, seed=5, pores=False)
    y = 32.0
    res = detect_transect_boundaries(rgb, (2.0, y, rgb.shape[1] - 3.0, y), dpi=2540)
    truth = np.stack([b, np.full_like(b, y)], 1)
    truth = truth[(truth[:, 0] > 4) & (truth[:, 0] < rgb.shape[1] - 5)]
    m = match_boundaries(res.points, truth, tolerance_px=3)
    assert m["sensitivity"] >= 0.9 and m["precision"] >= 0.9, m


# ---------------------------------------------------------------------------------------------------------------
# matching metric
# ---------------------------------------------------------------------------------------------------------------
def test_match_perfect_and_empty():
    pts = np.array([[10.0, 5.0], [30.0, 5.0]])
    m = match_boundaries(pts, pts, 3)
    assert (m["sensitivity"], m["precision"], m["f1"], m["mean_error_px"]) == (1.0, 1.0, 1.0, 0.0)
    m = match_boundaries(np.zeros((0, 2)), pts, 3)
    assert m["sensitivity"] == 0 and m["precision"] == 0 and m["f1"] == 0 and np.isnan(m["mean_error_px"])


def test_match_duplicates_count_once():
    labels = [[10.0, 0.0], [50.0, 0.0]]
    detected = [[10.0, 0.0], [11.0, 0.0], [10.5, 0.0], [50.0, 0.0]]  # two duplicates of the first boundary
    m = match_boundaries(detected, labels, 3)
    assert m["matched"] == 2 and m["sensitivity"] == 1.0 and m["precision"] == 0.5
    assert m["mean_error_px"] == 0.0  # the exact duplicate is chosen


def test_match_misses_and_tolerance_edge():
    labels = [[0.0, 0.0], [20.0, 0.0], [40.0, 0.0], [60.0, 0.0]]
    detected = [[3.0, 0.0], [23.01, 0.0], [40.0, 2.0]]  # at tolerance (in), just beyond (out), 2 px in y (in)
    m = match_boundaries(detected, labels, 3)
    assert m["matched"] == 2 and m["sensitivity"] == 0.5 and m["precision"] == pytest.approx(2 / 3)
    assert m["f1"] == pytest.approx(2 * 0.5 * (2 / 3) / (0.5 + 2 / 3))
    assert m["mean_error_px"] == pytest.approx(2.5)


def test_match_optimal_not_greedy():
    # greedy nearest-first would pair detection 1 with label 0 (distance 1) and leave label 1 unmatched
    labels = [[0.0], [4.0]]
    detected = [[2.5], [1.0]]
    m = match_boundaries(detected, labels, 3)
    assert m["matched"] == 2


def test_match_bad_tolerance():
    for tol in (0, -1, float("nan")):
        with pytest.raises(ValueError, match="tolerance_px"):
            match_boundaries([[0, 0]], [[0, 0]], tol)


def test_ring_widths_mm():
    wpx, wmm = ring_widths_mm([[0, 0], [3, 4], [3, 10]], 0.5)
    assert np.isnan(wpx[0]) and np.allclose(wpx[1:], [5, 6]) and np.allclose(wmm[1:], [2.5, 3])


# ---------------------------------------------------------------------------------------------------------------
# CLI
# ---------------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("seed,tilt", [(0, 0.0), (2, 0.15)])
def test_growth_direction_from_the_rings_shape(seed, tilt):
    """Without a bark side the detector finds it: the same core mirrored (or turned upright) gives the same
    boundaries mirrored, and the estimate names the side the sharp latewood -> earlywood steps face."""
    rgb, b = synthetic_core(ring_series(seed), seed=seed, tilt=tilt)
    W = rgb.shape[1]
    right = detect_core_boundaries(rgb, pixel_size_mm=0.01)
    assert right.info["bark"] == "right" and right.info["growth"]["confident"], right.info["growth"]
    left = detect_core_boundaries(np.ascontiguousarray(rgb[:, ::-1]), pixel_size_mm=0.01)
    assert left.info["bark"] == "left" and left.info["growth"]["z"] == pytest.approx(-right.info["growth"]["z"],
                                                                                        rel=0.3)
    assert np.allclose(left.points[:, 0], (W - 1) - right.points[:, 0], atol=1e-6)
    assert np.allclose(left.widths_px[1:], right.widths_px[1:], atol=1e-6)
    up = detect_core_boundaries(np.ascontiguousarray(rgb.transpose(1, 0, 2)[::-1]), pixel_size_mm=0.01)
    assert up.info["bark"] == "top" and len(up.points) == len(right.points)
    m = match_boundaries(right.points, np.stack([b, np.full_like(b, (rgb.shape[0] - 1) / 2)], 1), tolerance_px=3)
    assert m["f1"] >= 0.95, m


def test_a_contradicted_bark_side_is_warned_of():
    rgb, _ = synthetic_core(ring_series(1), seed=1)
    with pytest.warns(UserWarning, match="bark='left', but the rings' shape says the bark is on the right"):
        detect_core_boundaries(rgb, bark="left")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        detect_core_boundaries(rgb, bark="right")
    flat = np.full((40, 30, 3), 0.5, np.float32)  # too short to tell: a side must be given
    with pytest.raises(ValueError, match="bark: the core is too short .* give the side"):
        detect_core_boundaries(flat)
    with pytest.raises(ValueError, match="blocks"):
        growth_direction(rgb, blocks=2)


def run(script, *args):
    """Run a CLI script in a fresh interpreter (as a user would): CompletedProcess."""
    return subprocess.run([sys.executable, "-m", f"torch_appearance.cli.{script}", *map(str, args)],
                          capture_output=True, text=True, timeout=120)


@pytest.fixture(scope="module")
def run_inproc():
    """Run a ta-… command's ``main(argv)`` in this process (no interpreter start-up: the bad-input cases are many).

    Returns ``run(name, *args) -> (returncode, stdout, stderr)``; argparse errors (SystemExit) give their code.
    """
    from torch_appearance.testing import run_command
    return run_command


@pytest.fixture(scope="module")
def core_png(tmp_path_factory):
    rgb, b = synthetic_core(ring_series(0, 30), seed=0)
    path = tmp_path_factory.mktemp("core") / "core.png"
    cv2.imwrite(str(path), (rgb[..., ::-1] * 255).astype(np.uint8))
    return path, b


def test_cli_detect_and_eval(core_png, tmp_path):
    path, b = core_png
    out, ovl, lab = tmp_path / "rings.csv", tmp_path / "overlay.png", tmp_path / "labels.csv"
    r = run("detect_rings", path, "--out", out, "--overlay", ovl, "--bark", "right", "--dpi", 2540)
    assert r.returncode == 0, r.stderr
    lines = out.read_text().splitlines()
    assert lines[0] == "index,x_px,y_px,width_px,width_mm" and lines[1].endswith(",,")
    assert ovl.stat().st_size > 0
    lab.write_text("year,x_px,ring_width_mm\n" + "".join(f"{2000 + i},{x:.1f},NA\n" for i, x in enumerate(b)))
    r = run("eval_rings", out, lab, "--tolerance-px", 3)
    assert r.returncode == 0, r.stderr
    assert "sensitivity" in r.stdout and "F1" in r.stdout


def test_cli_bad_inputs(core_png, tmp_path, run_inproc):
    path, _ = core_png
    out, ovl = tmp_path / "o.csv", tmp_path / "o.png"
    bad = tmp_path / "broken.png"
    bad.write_bytes(b"not an image")
    cases = [((bad, "--out", out, "--overlay", ovl), "cannot read image"),
             ((tmp_path / "missing.png", "--out", out), "cannot read image"),
             ((path, "--out", out, "--overlay", ovl, "--transect", "0,0,5000,10"),
              "transect end: expected (x, y) inside the image"),
             ((path, "--out", out, "--transect=-5,3,20,3"), "transect start: expected (x, y) inside the image"),
             ((path, "--out", out, "--overlay", ovl, "--transect", "10,10,10,10"), "zero length"),
             ((path, "--out", out, "--transect", "1,2,3"), "four numbers"),
             ((path, "--out", out, "--dpi", "0"), "--dpi")]
    for args, msg in cases:
        rc, _, err = run_inproc("detect_rings", *args)
        assert rc not in (0, None) and msg in err, (args, err)
        assert not out.exists() and not ovl.exists(), args
    assert sorted(p.name for p in tmp_path.iterdir()) == ["broken.png"]  # no partial or temporary files


@pytest.mark.parametrize("args, start", [  # issue 49: accepted silently outside the mode that reads them
    (["--helpers", "-1"], "--helpers: expected 0 ... 16 (helper transects between neighbours), got -1"),
    (["--helpers", "1000000000000"], "--helpers: expected 0 ... 16"),  # was taken in core mode; disc: a library line
    (["--half-width", "1"], "--half-width: expected 2 ... 200 (px of arc either side of a transect"),  # library's
    (["--half-width", "1000000000000"], "--half-width: expected 2 ... 200"),  # taken in core mode; disc: library's
    (["--cell-px", "nan"], "--cell-px: expected a finite value > 0, got nan"),
    (["--cell-px", "0"], "--cell-px: expected a finite value > 0, got 0.0"),
    (["--dpi", "nan"], "--dpi: expected a finite value > 0, got nan"),
    (["--pixel-size-mm", "inf"], "--pixel-size-mm: expected a finite value > 0, got inf"),
])
def test_cli_refuses_nonsense_numbers_in_any_mode(args, start, tmp_path, run_inproc):
    rc, out, err = run_inproc("detect_rings", tmp_path / "core.png", "--out", tmp_path / "o.csv", *args)
    assert rc == 2 and err.strip().splitlines() == [err.strip()] and \
        err.startswith("ta-detect-rings: error: " + start), err
    assert os.listdir(tmp_path) == []


def test_cli_eval_bad_inputs(tmp_path, run_inproc):
    good = tmp_path / "d.csv"
    good.write_text("index,x_px,y_px\n0,1,1\n")
    nocol = tmp_path / "l.csv"
    nocol.write_text("year,position\n2000,5\n")
    cases = [((good, good, "--tolerance-px", 0), "tolerance"), ((good, good, "--tolerance-px", -2), "tolerance"),
             ((good, nocol), "x_px"), ((good, tmp_path / "missing.csv"), "labels_csv: no such file")]
    for args, msg in cases:
        rc, out, err = run_inproc("eval_rings", *args)
        assert rc not in (0, None) and msg in err and out == "", (args, err)


# ---------------------------------------------------------------------------------------------------------------
# section mode (microscopy)
# ---------------------------------------------------------------------------------------------------------------
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
    # Patches 4 and 5 are not asserted: the curve found runs parallel to the label 8 and 14 px away (docs/bench_log.md).
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


def test_cli_section_mode(tmp_path, run_inproc):
    img = os.path.join(DATA, "input_00002_preview.png")
    out, ovl = tmp_path / "b.csv", tmp_path / "b.png"
    rc, stdout, err = run_inproc("detect_rings", img, "--mode", "section", "--out", out, "--overlay", ovl)
    assert rc == 0, err
    lines = out.read_text().splitlines()
    assert lines[0] == "index,x_px,y_px" and len(lines) > 200 and ovl.stat().st_size > 0
    pts = np.array([[float(v) for v in ln.split(",")[1:]] for ln in lines[1:]])
    mask = cv2.imread(os.path.join(DATA, "mask_00002.png"), cv2.IMREAD_GRAYSCALE)
    assert boundary_f_measure(pts, mask_centerline(mask), 3)["f1"] >= 0.9
    out.unlink(), ovl.unlink()
    for args, msg in [(("--cell-px", 0), "--cell-px: expected a finite value > 0"),
                      (("--bark", "left"), "do not apply")]:
        rc, _, err = run_inproc("detect_rings", img, "--mode", "section", "--out", out, "--overlay", ovl, *args)
        assert rc not in (0, None) and msg in err, (args, err)
        assert not out.exists() and not ovl.exists()


def test_split_modules_keep_the_old_imports():
    """Section mode and the scoring moved out of rings.dendro (issue 49's clean rooms): the old names still import
    from there and are the same objects."""
    from torch_appearance.rings import dendro, evaluation, section
    assert dendro.detect_section_boundaries is section.detect_section_boundaries
    assert dendro.SectionBoundary is section.SectionBoundary
    for name in ("match_boundaries", "boundary_f_measure", "mask_centerline", "resample_polyline"):
        assert getattr(dendro, name) is getattr(evaluation, name)
    with pytest.raises(AttributeError):
        dendro.no_such_name


def test_cli_refuses_a_core_width_that_adds_only_work(core_png, tmp_path, run_inproc):
    """--width-px 100000 on a 48-px-wide core (it ran > 10 min without a word): refused at once, in one line naming
    --width-px, the bound and why; the largest width the bound allows still runs."""
    import time

    path, _ = core_png
    out = tmp_path / "o.csv"
    t0 = time.perf_counter()
    rc, _, err = run_inproc("detect_rings", path, "--out", out, "--bark", "right", "--width-px", 100000)
    assert rc == 2 and err.count("\n") == 1 and time.perf_counter() - t0 < 30, err
    assert err.startswith("ta-detect-rings: error: --width-px: expected at most 82 px, the larger of the core's "
                          "width across its axis (48 px) and the curved Gabor's longest contour (82 px): a wider "
                          "resampling adds no detail, only time and memory"), err
    assert err.rstrip().endswith("got 100000") and not out.exists()
    rc, _, err = run_inproc("detect_rings", path, "--out", out, "--bark", "right", "--width-px", 3)
    assert rc == 2 and err == "ta-detect-rings: error: --width-px: expected an int >= 8 (px), got 3\n", err  # "or None"
    rc, _, err = run_inproc("detect_rings", path, "--out", out, "--bark", "right", "--width-px", 82)
    assert rc == 0 and out.exists(), err
