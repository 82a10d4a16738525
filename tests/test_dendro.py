"""Dendrochronology: ring boundaries on synthetic cores, the matching metric, and the CLI's bad-input handling."""
import importlib.util
import os
import subprocess
import sys

import numpy as np
import pytest

from torch_appearance.rings.dendro import (detect_core_boundaries, detect_transect_boundaries, match_boundaries,
                                           ring_widths_mm)

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
def run(script, *args):
    """Run a CLI script in a fresh interpreter (as a user would): CompletedProcess."""
    return subprocess.run([sys.executable, os.path.join(ROOT, "scripts", script), *map(str, args)],
                          capture_output=True, text=True, timeout=120)


def _load_script(script):
    spec = importlib.util.spec_from_file_location(script[:-3], os.path.join(ROOT, "scripts", script))
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def run_inproc():
    """Run a CLI script's ``main(argv)`` in this process (no interpreter start-up: the bad-input cases are many).

    Returns ``run(script, *args) -> (returncode, stdout, stderr)``; argparse errors (SystemExit) give their code.
    """
    import contextlib
    import io

    mods = {}

    def run_(script, *args):
        mod = mods.setdefault(script, _load_script(script))
        out, err = io.StringIO(), io.StringIO()
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                rc = mod.main([str(a) for a in args])
            except SystemExit as e:
                rc = e.code
        return rc, out.getvalue(), err.getvalue()

    return run_


@pytest.fixture(scope="module")
def core_png(tmp_path_factory):
    import cv2

    rgb, b = synthetic_core(ring_series(0, 30), seed=0)
    path = tmp_path_factory.mktemp("core") / "core.png"
    cv2.imwrite(str(path), (rgb[..., ::-1] * 255).astype(np.uint8))
    return path, b


def test_cli_detect_and_eval(core_png, tmp_path):
    path, b = core_png
    out, ovl, lab = tmp_path / "rings.csv", tmp_path / "overlay.png", tmp_path / "labels.csv"
    r = run("detect_rings.py", path, "--out", out, "--overlay", ovl, "--bark", "right", "--dpi", 2540)
    assert r.returncode == 0, r.stderr
    lines = out.read_text().splitlines()
    assert lines[0] == "index,x_px,y_px,width_px,width_mm" and lines[1].endswith(",,")
    assert ovl.stat().st_size > 0
    lab.write_text("year,x_px,ring_width_mm\n" + "".join(f"{2000 + i},{x:.1f},NA\n" for i, x in enumerate(b)))
    r = run("eval_rings.py", out, lab, "--tolerance-px", 3)
    assert r.returncode == 0, r.stderr
    assert "sensitivity" in r.stdout and "F1" in r.stdout


def test_cli_bad_inputs(core_png, tmp_path, run_inproc):
    path, _ = core_png
    out, ovl = tmp_path / "o.csv", tmp_path / "o.png"
    bad = tmp_path / "broken.png"
    bad.write_bytes(b"not an image")
    cases = [((bad, "--out", out, "--overlay", ovl), "cannot read image"),
             ((tmp_path / "missing.png", "--out", out), "cannot read image"),
             ((path, "--out", out, "--overlay", ovl, "--transect", "0,0,5000,10"), "outside the image"),
             ((path, "--out", out, "--transect=-5,3,20,3"), "outside the image"),
             ((path, "--out", out, "--overlay", ovl, "--transect", "10,10,10,10"), "zero length"),
             ((path, "--out", out, "--transect", "1,2,3"), "four numbers"),
             ((path, "--out", out, "--dpi", "0"), "--dpi")]
    for args, msg in cases:
        rc, _, err = run_inproc("detect_rings.py", *args)
        assert rc not in (0, None) and msg in err, (args, err)
        assert not out.exists() and not ovl.exists(), args
    assert sorted(p.name for p in tmp_path.iterdir()) == ["broken.png"]  # no partial or temporary files


def test_cli_eval_bad_inputs(tmp_path, run_inproc):
    good = tmp_path / "d.csv"
    good.write_text("index,x_px,y_px\n0,1,1\n")
    nocol = tmp_path / "l.csv"
    nocol.write_text("year,position\n2000,5\n")
    cases = [((good, good, "--tolerance-px", 0), "tolerance"), ((good, good, "--tolerance-px", -2), "tolerance"),
             ((good, nocol), "x_px"), ((good, tmp_path / "missing.csv"), "cannot read")]
    for args, msg in cases:
        rc, out, err = run_inproc("eval_rings.py", *args)
        assert rc not in (0, None) and msg in err and out == "", (args, err)
