"""Print optimisation pipeline: targets, texel grids, quantised evaluation, the run folder, resume, bad input."""
import csv
import math
import os

import numpy as np
import pytest
import torch

from torch_appearance import io as ta_io
from torch_appearance.fabrication.inks import InkSet
from torch_appearance.nn.mixture import mix_inks
from torch_appearance.pipelines import PrintConfig, optimize_print
from torch_appearance.pipelines.print import LOG_FIELDS, slab_texel_grid
from torch_appearance.pipelines.print.baselines import naive_extrusion, render_quantized
from torch_appearance.pipelines.print.target_images import ZEBRA_STRIPES, colorchecker_patches, load_target, zebra_target
from torch_appearance.testing import assert_z, seed_stats


def test_zebra_target_stripes():
    img = zebra_target(height=64, band_width=4)
    assert img.shape == (64, 24, 3)
    for k, stripe in enumerate(ZEBRA_STRIPES):
        column = img[:, 4 * k, 0]
        changes = np.flatnonzero(np.diff(column) != 0) + 1
        assert changes[0] == stripe and np.all(np.diff(changes) == stripe)


def test_colorchecker_patches_against_colour_science():
    import colour
    rgb = colorchecker_patches()
    assert rgb.shape == (24, 3)
    # patch 19 "white 9.5" is bright and neutral, patch 24 "black 2" dark; patch 13 "blue" is blue
    lab = colour.XYZ_to_Lab(colour.sRGB_to_XYZ(rgb, apply_cctf_decoding=False))
    assert lab[18, 0] > 90 and abs(lab[18, 1]) < 3 and abs(lab[18, 2]) < 3
    assert lab[23, 0] < 25
    assert rgb[12, 2] > rgb[12, 0] and rgb[12, 2] > rgb[12, 1]


def test_slab_texel_grid_places_faces():
    faces = torch.rand(2, 3, 4, 3)
    grid, mask = slab_texel_grid(faces, 5)
    assert grid.shape == (3, 5, 3, 4) and mask.shape == (5, 3, 4)
    torch.testing.assert_close(grid[:, 4].permute(1, 2, 0), faces[0])  # top = layer D − 1
    torch.testing.assert_close(grid[:, 0].permute(1, 2, 0), faces[1])  # bottom = layer 0
    assert int(mask.sum()) == 2 * 12 and not bool(mask[1:4].any())
    with pytest.raises(ValueError, match="thickness_mm: a two-sided target needs at least 2"):
        slab_texel_grid(faces, 1)


def test_render_quantized_single_ink_equals_continuous():
    """One ink everywhere: the quantised volume at 600 × 300 × 940 DPI is the same medium over the same box,
    so its texels averaged back to the 300 DPI grid equal the continuous render (in distribution)."""
    inks = InkSet.from_names(["yellow", "white"])
    cfg = PrintConfig(thickness_mm=0.34, dpi=300)
    d, h, w = cfg.depth, 4, 5
    weights = torch.zeros(2, d, h, w)
    weights[0, d // 2:] = 1.0  # yellow over white
    weights[1, :d // 2] = 1.0
    from torch_appearance.fabrication.quantize import quantize_mixture
    indices = quantize_mixture(weights, cfg.voxel_size, cfg.printer_dpi, seed=1)
    assert indices.shape == (13, 4, 10)  # 0.339 mm at 940 DPI; y at 300 DPI; x at 600 DPI
    quant, se_q = seed_stats(lambda k: render_quantized(indices, inks, cfg, (h, w), 1, 256, k)[0], range(8))
    sigma_t, albedo = mix_inks(weights, inks)
    from torch_appearance import render_texels
    cont, se_c = seed_stats(lambda k: render_texels(sigma_t, albedo, voxel_size=cfg.voxel_size, spp=256,
                                                    seed=50 + k), range(8))
    assert_z(quant - cont, (se_q ** 2 + se_c ** 2).sqrt(), 0.0, what="quantised vs continuous")


def test_naive_extrusion_grey_uses_black_white_by_lightness():
    inks = InkSet.from_names()
    cfg = PrintConfig(thickness_mm=0.17)
    target = zebra_target(height=6, band_width=1)
    weights, table = naive_extrusion(target, inks, cfg, table_spp=16)
    assert table["kind"].startswith("black/white")
    assert weights.shape == (5, cfg.depth, 6, 6)
    used = weights.sum((1, 2, 3))
    assert float(used[inks.index("cyan")]) == 0.0 and float(used[inks.index("black")]) > 0
    torch.testing.assert_close(weights.sum(0), torch.ones_like(weights[0]))
    # lighter target texels get less black ink
    black = weights[inks.index("black"), 0]
    lum = torch.as_tensor(target[..., 1])
    assert float(black[lum > 0.5].mean()) < float(black[lum < 0.5].mean())


def tiny_target(path, h=6, w=8):
    img = np.zeros((h, w, 3), np.float32)
    img[:, : w // 2] = (0.5, 0.1, 0.05)
    img[:, w // 2:] = (0.05, 0.2, 0.5)
    ta_io.write_exr(str(path), img)
    return img


def test_run_folder_resume_and_refusal(tmp_path):
    target = tiny_target(tmp_path / "t.exr")
    out = tmp_path / "run"
    kw = dict(target=str(tmp_path / "t.exr"), thickness_mm=0.34, spp=2, eval_spp=8, eval_every=3, table_steps=2,
              out=str(out), seed=3)
    optimize_print(PrintConfig(iterations=3, **kw), progress=False, log=lambda *_: None)
    first = list(csv.DictReader(open(out / "log.csv")))
    assert [int(r["iteration"]) for r in first] == [0, 1, 2, 3]
    with pytest.raises(ValueError, match="already holds a run.*resume"):
        optimize_print(PrintConfig(iterations=6, **kw), progress=False, log=lambda *_: None)
    summary = optimize_print(PrintConfig(iterations=6, resume=True, **kw), progress=False, log=lambda *_: None)
    rows = list(csv.DictReader(open(out / "log.csv")))
    assert list(rows[0].keys())[:len(LOG_FIELDS)] == LOG_FIELDS
    assert [int(r["iteration"]) for r in rows] == list(range(7))
    assert rows[:4] == first  # the resumed run kept the first part of the log
    walls = [float(r["wall_s"]) for r in rows]
    assert walls == sorted(walls)
    assert all(r["dE00_mean"] for r in rows if int(r["iteration"]) in (0, 3, 6))
    for name in ("config.json", "log.csv", "convergence.png", "target.exr", "baseline.exr", "initial.exr",
                 "optimized.exr", "final.exr", "final.png", "dE00_heatmap.png", "ink_usage_by_depth.png",
                 "mixture.npz", "quantized.npz", "slices/palette.json", "checkpoint.pt", "summary.json"):
        assert (out / name).exists(), name
    final = ta_io.read_exr(str(out / "final.exr"))
    assert final.shape == target.shape and np.isfinite(final).all()
    assert summary["quantized_shape_dhw"][0] == 13 and len(os.listdir(out / "slices")) == 13 + 1
    assert not [f for f in os.listdir(out) if f.startswith(".") or f.endswith(".tmp")]  # no temp files left
    # every figure is the print's, free of render noise, scored from the evaluation's own four renders; the raw
    # figure of their mean is kept beside it and reads higher at 8 spp
    evaluated = [r for r in rows if r["dE00_mean"]]
    for scores in [summary["final_quantized"], summary["baseline_naive_extrusion"], summary["optimized_continuous"],
                   *[{k: float(r[k]) for k in ("dE00_mean", "dE00_mean_raw", "dE00_mean_se")} for r in evaluated]]:
        assert scores["dE00_mean"] < scores["dE00_mean_raw"] and scores["dE00_mean_se"] > 0
    assert summary["evaluation"]["renders"] == 4 and summary["evaluation"]["spp_each"] == 2
    assert 0 < summary["evaluation"]["share_of_job"] < 1
    # a slab is scored whole: every texel of its face (it once said 1, the length of the target's first axis)
    assert summary["evaluation"]["texels"] == summary["texels"] == target.shape[0] * target.shape[1]


def test_same_seed_reproducible(tmp_path):
    tiny_target(tmp_path / "t.exr", 4, 4)
    logs = []
    for k in range(2):
        cfg = PrintConfig(target=str(tmp_path / "t.exr"), thickness_mm=0.17, spp=2, eval_spp=4, eval_every=2,
                          iterations=2, table_steps=1, out=str(tmp_path / f"r{k}"))
        optimize_print(cfg, progress=False, log=lambda *_: None)
        logs.append([(r["loss"], r["dE00_mean"]) for r in csv.DictReader(open(tmp_path / f"r{k}" / "log.csv"))])
    assert logs[0] == logs[1]


@pytest.mark.parametrize("overrides,exc,match", [
    (dict(target="no_such_file.png"), ValueError, "target: expected a built-in target"),
    (dict(target="x.txt"), ValueError, "target: expected a built-in target"),
    (dict(inks="cyan,unobtainium"), ValueError, "unobtainium"),
    (dict(spp=0), ValueError, "spp: expected > 0"),
    (dict(optimizer="sgd"), ValueError, "optimizer: expected"),
    (dict(gamma=(1.0, -1.0, 0.0)), ValueError, "gamma: expected"),
    (dict(thickness_mm=0.01), ValueError, "thickness_mm: expected at least one voxel"),
])
def test_bad_config(tmp_path, overrides, exc, match):
    kw = dict(target="zebra", iterations=1, out=str(tmp_path / "run"))
    kw.update(overrides)
    with pytest.raises(exc, match=match):
        optimize_print(PrintConfig(**kw), progress=False, log=lambda *_: None)


def test_bad_targets(tmp_path):
    ta_io.write_exr(str(tmp_path / "a.exr"), np.zeros((4, 4, 3), np.float32))
    ta_io.write_exr(str(tmp_path / "b.exr"), np.zeros((4, 5, 3), np.float32))
    with pytest.raises(ValueError, match=r"bottom_target: expected the size of the top target"):
        optimize_print(PrintConfig(target=str(tmp_path / "a.exr"), bottom_target=str(tmp_path / "b.exr"),
                                   out=str(tmp_path / "r")), progress=False, log=lambda *_: None)
    nan = np.zeros((4, 4, 3), np.float32)
    nan[1, 1, 1] = math.nan
    raw = tmp_path / "nan.exr"
    import OpenEXR
    OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}, {"RGB": nan}).write(str(raw))
    with pytest.raises(ValueError, match="target: expected finite values"):
        load_target(str(raw))


def test_init_naive_starts_from_the_naive_extrusion(tmp_path):
    """init='naive': the run's starting mixture is the naive extrusion (to the 1e-3 floor), so its initial render
    scores like the naive baseline's continuous mixture, and the white start does not."""
    tiny_target(tmp_path / "t.exr")
    kw = dict(target=str(tmp_path / "t.exr"), thickness_mm=0.34, spp=2, eval_spp=8, eval_every=1, table_steps=2,
              iterations=1, lr=1e-9, seed=3)
    optimize_print(PrintConfig(init="naive", out=str(tmp_path / "naive"), **kw), progress=False,
                   log=lambda *_: None)
    cfg = PrintConfig(**kw)
    naive, _ = naive_extrusion(tiny_target(tmp_path / "u.exr"), InkSet.from_names(cfg.inks), cfg)
    weights = np.load(tmp_path / "naive" / "mixture.npz")["weights"]
    assert weights.shape == tuple(naive.shape)
    assert np.abs(weights - naive.numpy()).max() < 5 * 1e-3
    optimize_print(PrintConfig(init="white", out=str(tmp_path / "white"), **kw), progress=False, log=lambda *_: None)
    white = np.load(tmp_path / "white" / "mixture.npz")["weights"]
    assert np.abs(white - naive.numpy()).max() > 0.3


def test_auto_evaluation_subset_scores_a_slab_whole(tmp_path):
    """``eval_texels="auto"`` sizes an object's evaluation subset; a slab given it is still scored whole."""
    logged = []
    summary = optimize_print(PrintConfig(target="zebra", width_mm=2.0, height_mm=2.0, iterations=2, eval_every=2,
                                         eval_texels="auto", out=str(tmp_path / "run")), progress=False,
                             log=logged.append)
    assert summary["evaluation"]["texels"] == summary["texels"]
    assert not [line for line in logged if "random texels" in line]
