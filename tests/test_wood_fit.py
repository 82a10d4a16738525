"""Wood fit pipeline end to end on a synthetic board with known ground truth, plus its run folder and bad input."""
import math
import os

import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree

from torch_appearance import io as ta_io
from torch_appearance.nn.wood import WoodModel
from torch_appearance.pipelines.wood import (WoodFitConfig, boundary_lateness, effective_ring_width, fit_wood,
                                             load_photo, model_boundaries)
from torch_appearance.rings.synthetic import synthetic_board


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    folder = tmp_path_factory.mktemp("wood")
    board = synthetic_board(256, 256, 0.1, seed=3)
    ta_io.write_png(str(folder / "board.png"), board["image"])
    cfg = WoodFitConfig(photo=str(folder / "board.png"), out=str(folder / "run"), pixel_size_mm=0.1, epochs=250,
                        color_epochs=60, preview=False)
    summary = fit_wood(cfg, progress=False, log=lambda *_: None)
    return board, summary, folder / "run"


@pytest.mark.slow
def test_synthetic_board_phase_and_boundaries(fitted):
    """Detected ring boundaries lie within 1.5 px (mean) of the true ones; the fitted phase matches the true growth
    phase 2π·frac(G) up to a constant (the Gabor phase is aligned with the rings' fundamental) with RMS < 0.3 rad."""
    board, summary, run = fitted
    model = WoodModel.load(str(run / "model"))
    with torch.no_grad():
        out = model.render_board(256, 256, 0.1)
    true_phase = 2 * math.pi * (board["G"] - np.floor(board["G"]))
    d = np.angle(np.exp(1j * (out["phase"].numpy() - true_phase)))
    offset = np.angle(np.exp(1j * d).mean())
    rms = float(np.sqrt((np.angle(np.exp(1j * (d - offset))) ** 2).mean()))
    assert rms < 0.3, rms
    assert summary["final_phase_rms"] < summary["initial_phase_rms"]
    lines = model_boundaries(out["G"].numpy(), summary["boundary_lateness"])
    detected = np.concatenate(lines)
    truth = np.concatenate(board["boundaries"])
    assert float(cKDTree(truth).query(detected)[0].mean()) < 1.5
    assert float(cKDTree(detected).query(truth)[0].mean()) < 1.5  # and every true boundary is found


@pytest.mark.slow
def test_synthetic_board_ring_scale(fitted):
    """The recovered ring scale s_r and the mean ring width over the board (1 / mean ∂G/∂r, which is what the
    photo constrains when a radial distortion absorbs part of the scale) are within 5 % of the truth. Seed 3 shows
    16 traced ring lines (9 distinct rings); on boards with 2–4 visible rings the scale is not identifiable to 5 %
    (scripts/eval/eval_wood_synthetic.py reports the spread over seeds)."""
    board, summary, _ = fitted
    true_sr = board["params"]["ring_scale"]
    assert abs(summary["ring_scale_mm"] / true_sr - 1) < 0.05, (summary["ring_scale_mm"], true_sr)
    true_width = effective_ring_width(board["model"], 256, 256, 0.1)
    assert abs(summary["mean_ring_width_mm"] / true_width - 1) < 0.05, (summary["mean_ring_width_mm"], true_width)


@pytest.mark.slow
def test_run_folder(fitted):
    _, summary, run = fitted
    for name in ("fit.png", "phase.npy", "fit_phase.npy", "params.json", "log.csv", "convergence.png",
                 "orientation.png", "magnitude.png", "phase.png", "ring_overlay.png", "board_estimate.json",
                 "model.json", "model.pt", "fit_vs_photo.png", "phase_error.png", "summary.json"):
        assert (run / name).exists(), name
    assert np.load(run / "phase.npy").shape == (256, 256) and np.load(run / "fit_phase.npy").shape == (256, 256)
    header = open(run / "log.csv").readline().strip().split(",")
    assert header[:5] == ["stage", "epoch", "wall_s", "phase_loss", "color_loss"]
    assert 0.5 < summary["ssim_fit_vs_photo"] <= 1.0 and summary["fit_ok"]
    # seed 3 has 9 distinct rings (integer G levels) on the board
    assert summary["visible_rings"] in (8, 9, 10) and summary["ring_scale_reliable"]
    assert not [f for f in os.listdir(run) if f.endswith(".tmp")]


@pytest.mark.parametrize("overrides,match", [
    (dict(pixel_size_mm=0.0), "pixel_size_mm: expected"),
    (dict(pixel_size_mm=-1.0), "pixel_size_mm: expected"),
    (dict(p=0), "p: expected an int >= 1"),
    (dict(q=0), "q: expected an int >= 1"),
    (dict(epochs=-1), "epochs: expected"),
    (dict(distortion="spiral"), "distortion: expected"),
    (dict(photometric_levels=(4, 0)), "photometric_levels: expected"),
    (dict(photometric_spp=1), "photometric_spp: expected"),
    (dict(photometric_estimator="exact"), "photometric_estimator: expected"),
    (dict(photometric_anchor=-1.0), "photometric_anchor: expected"),
    (dict(photometric_color_lr=-0.1), "photometric_color_lr: expected"),
    # issue 49: nonsense sizes refused before any work (max_size 0 was a cv2.error traceback, inf rates NaN fits)
    (dict(max_size=0), r"max_size: expected an int >= 8 \(the photo's longest side"),
    (dict(max_size=5), "max_size: expected an int >= 8"),
    (dict(lr=math.inf), "lr: expected a finite value > 0, got inf"),
    (dict(lr=1e12), r"lr: expected at most 1 \(a ring width per step\), got 1000000000000.0"),  # an IndexError
    (dict(photometric_color_lr=2.0), r"photometric_color_lr: expected at most 1 \(a colour range per step\)"),
    (dict(photometric_lr=math.inf), "photometric_lr: expected a finite value > 0"),
    (dict(photometric_color_lr=math.inf), "photometric_color_lr: expected a finite value >= 0"),
    (dict(coarse_to_fine=7), r"coarse_to_fine: expected at most 6 \(the 32 × 64-texel distortion texture"),
    (dict(epochs=10 ** 11), "epochs: 100000000000 epochs take at least 3.17 years"),
])
def test_bad_config(tmp_path, overrides, match):
    ta_io.write_png(str(tmp_path / "x.png"), np.full((16, 16, 3), 0.5, np.float32))
    kw = dict(photo=str(tmp_path / "x.png"), out=str(tmp_path / "run"))
    kw.update(overrides)
    with pytest.raises(ValueError, match=match):
        fit_wood(WoodFitConfig(**kw), progress=False, log=lambda *_: None)


def test_bad_photos(tmp_path):
    with pytest.raises(ValueError, match="photo: expected an image file"):
        load_photo(str(tmp_path / "missing.png"))
    (tmp_path / "junk.png").write_bytes(b"not a png")
    with pytest.raises(ValueError, match="photo: cannot decode .*junk.png"):
        load_photo(str(tmp_path / "junk.png"))
    ta_io.write_png(str(tmp_path / "tiny.png"), np.zeros((4, 4, 3), np.float32))
    with pytest.raises(ValueError, match="photo: expected at least 8×8"):
        load_photo(str(tmp_path / "tiny.png"))
    ta_io.write_png(str(tmp_path / "strip.png"), np.zeros((10, 200, 3), np.float32))
    with pytest.raises(ValueError, match=r"max_size: 100 px makes the 10 × 200 px photo 5 × 100 px; expected at "
                                         r"least 8 px a side, so at least 160"):
        load_photo(str(tmp_path / "strip.png"), max_size=100)
    assert load_photo(str(tmp_path / "strip.png"), max_size=160)[0].shape == (8, 160, 3)
    ta_io.write_png(str(tmp_path / "flat.png"), np.full((64, 64, 3), 0.5, np.float32))
    with pytest.raises(ValueError, match="photo: found"):
        fit_wood(WoodFitConfig(photo=str(tmp_path / "flat.png"), out=str(tmp_path / "run"), p=8, q=8),
                 progress=False, log=lambda *_: None)


def _banded_board():
    """A flat-sawn board without distortion (s_r = 0.8 mm) whose rings alternate between two constant colours:
    all its colour changes are jumps at ring boundaries."""
    m = WoodModel(ring_scale_mm=0.8, n_rings=2, distortion=None, dtype=torch.float64, color_bins=2)
    cmap = torch.tensor([[[0.62, 0.44, 0.27]] * 2, [[0.27, 0.14, 0.06]] * 2], dtype=torch.float64)
    m.set_parameters(rotation=torch.tensor([1.7708, 0.0, 0.0]), translation=torch.tensor([-6.0, 3.0, 0.0]),
                     color_map=cmap)
    return m


@pytest.mark.parametrize("estimator", ["reparam", "naive"])
def test_photometric_stage_recovers_a_shifted_board_only_with_boundary_gradients(estimator):
    """Stage 3 alone (no phase anchor, no prior, colour map frozen) against a Gaussian-filtered photo of a known
    board, started with the board shifted by 0.25 mm (~0.3 ring widths): through the reparameterised render the
    rings move back onto the truth (phase RMS vs the true 2π·frac(G) from > 1 rad to < 0.3 rad); naive autograd of
    the same samples misses the boundary term, which is all the geometry gradient there is on this banded board, so
    it does not move."""
    import copy

    from torch_appearance.nn.wood_reparam import pixel_samples, reparam_render
    from torch_appearance.pipelines.wood import photometric_stage, wrap

    h = w = 24
    p = 0.2
    truth = _banded_board()
    pts, centres = pixel_samples(h, w, p, 256, 123, 0.5, dtype=torch.float64)
    shift = torch.full((2,), -0.5 * p, dtype=torch.float64)   # photo pixel (y, x) is the board point (x·p, y·p)
    with torch.no_grad():
        photo = reparam_render(truth, h, w, p, spp=256, samples=(pts + shift, centres + shift))
        true_phase = truth.render_board(h, w, p)["phase"]

    def phase_rms(m):
        with torch.no_grad():
            return float(wrap(m.render_board(h, w, p)["phase"] - true_phase).pow(2).mean().sqrt())

    model = copy.deepcopy(truth)
    with torch.no_grad():
        model.translation[0] += 0.25
    start = phase_rms(model)
    cfg = WoodFitConfig(photo="", pixel_size_mm=p, photometric=True, photometric_epochs=50, photometric_levels=(1,),
                        photometric_anchor=0.0, smoothness=0.0, photometric_estimator=estimator, photometric_lr=0.03,
                        photometric_color_lr=0.0)
    rows = photometric_stage(model, photo, true_phase, h, w, cfg)
    assert len(rows) == 50 and all(r["stage"] == 3 for r in rows)
    end = phase_rms(model)
    assert start > 1.0
    if estimator == "reparam":
        assert end < 0.3, (start, end)
    else:
        assert abs(end - start) < 1e-6, (start, end)


def test_luminance_histogram_match_restores_washed_out_latewood():
    """A colour map squeezed toward its mean (per-bin means over a slightly misregistered phase do this) is remapped
    so that the render's luminance distribution is the photo's: luminance per pixel within 0.01, contrast ratio ~1."""
    from torch_appearance.pipelines.wood import latewood_contrast, match_luminance_histogram

    board = synthetic_board(96, 96, seed=2, noise=0.0)
    model = board["model"]
    y = torch.tensor([0.2126, 0.7152, 0.0722], dtype=torch.float64)
    with torch.no_grad():
        photo = model.render_board(96, 96, 0.1)["image"].clamp(0, 1)
        mean = model.color_map.mean((0, 1), keepdim=True)
        model.color_map.copy_(mean + 0.4 * (model.color_map - mean))  # washed out
        washed = model.render_board(96, 96, 0.1)["image"].clamp(0, 1)
        before = latewood_contrast(washed.numpy(), photo.numpy())["ratio"]
        match_luminance_histogram(model, washed, photo)
        fixed = model.render_board(96, 96, 0.1)["image"].clamp(0, 1)
    after = latewood_contrast(fixed.numpy(), photo.numpy())["ratio"]
    assert before < 0.5
    assert abs(after - 1.0) < 0.03, after
    err = (fixed.double().reshape(-1, 3) @ y - photo.double().reshape(-1, 3) @ y).abs()
    assert float(err.max()) < 0.01, float(err.max())


def test_boundary_lateness_from_the_photo_is_shift_equivariant_and_finds_the_true_boundary():
    # the synthetic board's sharp latewood -> earlywood step lies at integer G: read along the TRUE G the estimate is
    # 0 (mod 1); along G shifted by a constant it moves by that constant (the colour map's 16-bin estimate does not)
    board = synthetic_board(192, 192, 0.1, seed=3, noise=0.01)
    G = board["G"].astype(np.float64)
    rgb = board["image"]
    est = boundary_lateness(board["model"], G, rgb)
    assert min(est, 1.0 - est) <= 0.02, est
    for shift in (0.13, 0.37, 0.71):
        moved = boundary_lateness(board["model"], G - shift, rgb)
        d = (moved - (est - shift)) % 1.0
        assert min(d, 1.0 - d) <= 0.01, (shift, moved, est)
    with pytest.raises(ValueError, match="same"):
        boundary_lateness(board["model"], G[:-1], rgb)
