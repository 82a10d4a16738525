"""Printer-ready output (issue 27): printer profiles, GrabCAD Voxel Print packages read back voxel for voxel,
packages of a run folder (the run's volume, or its mixture quantised again for another printer), streaming with
bounded memory, the halftoning options, and the refusals of ta-export-print."""
import json
import os
import signal
import subprocess
import sys
import time
import tracemalloc
import xml.etree.ElementTree as ET
import zipfile

import numpy as np
import pytest
import torch

from torch_appearance import io as ta_io
from torch_appearance.fabrication import InkSet, load_index_volume, quantize_mixture, save_index_volume
from torch_appearance.fabrication.export import VOID, IndexVolumeLayers
from torch_appearance.fabrication.gcvf import read_gcvf, write_gcvf
from torch_appearance.fabrication.halftone import blue_noise_tile
from torch_appearance.fabrication.printer import builtin_printers, load_printer
from torch_appearance.fabrication.quantize import iter_quantized, micro_grid_shape
from torch_appearance.pipelines.print import PrintConfig, optimize_print
from torch_appearance.pipelines.print.config import iteration_seed
from torch_appearance.pipelines.print.package import export_run
from torch_appearance.testing import command_argv, reset_peak_rss, sigint_default, status_kb, tiny_print_target

QUIET = dict(progress=False, log=lambda *_: None)


def material_volume(indices, ink_names, printer, materials):
    """The run's ink indices as indices into a package's material list ``materials`` (255 stays 255)."""
    lut = np.full(256, VOID, np.uint8)
    for i, m in enumerate(printer.material_indices(ink_names)):
        lut[i] = materials.index(printer.material_names[m])
    return lut[indices]


# ------------------------------------------------------------------------------------------------ profiles
def test_builtin_profiles_and_their_resolution():
    assert builtin_printers() == ["generic", "j750", "j750-hq"]
    j750, hq = load_printer("j750"), load_printer("J750-HQ")
    assert j750.dpi[:2] == (600.0, 300.0) and j750.dpi[2] == pytest.approx(25.4 / 0.027)
    assert hq.dpi[2] == pytest.approx(25.4 / 0.014) and hq.layer_thickness_nm == 14000
    assert j750.matches((600, 300, 940)) and not hq.matches((600, 300, 940))
    inks = InkSet.from_names()
    assert [j750.material_names[m] for m in j750.material_indices(inks.names)] == [
        "VeroCY-V", "VeroMGT-V", "VeroYL-V", "VeroBlackPlus", "VUltraWhite"]
    assert load_printer(j750) is j750 and load_printer(j750.source).to_dict() == j750.to_dict()


def test_profile_refusals(tmp_path):
    with pytest.raises(ValueError, match="neither a built-in profile"):
        load_printer("no-such-printer")
    with pytest.raises(TypeError, match="printer"):
        load_printer(3)
    with pytest.raises(ValueError, match="no material for the ink 'orange'"):
        load_printer("j750").material_indices(["cyan", "orange"])
    good = load_printer("generic").to_dict()

    def refused(change, message):
        data = json.loads(json.dumps(good))
        change(data)
        path = tmp_path / "p.json"
        path.write_text(json.dumps(data))
        with pytest.raises(ValueError, match=message):
            load_printer(str(path))

    refused(lambda d: d["materials"][1].update(rgba=d["materials"][0]["rgba"]), "distinct RGB")
    refused(lambda d: d["inks"].update(cyan="VeroMystery"), "not one of the materials")
    refused(lambda d: d.pop("layer_thickness_nm"), "missing key")
    refused(lambda d: d.update(dpi=[600]), "dpi")
    refused(lambda d: d.update(colour="red"), "unknown key")
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(ValueError, match="not valid JSON"):
        load_printer(str(tmp_path / "bad.json"))


# ------------------------------------------------------------------------------------------------ GCVF
def test_gcvf_round_trip_every_voxel_and_the_config_file(tmp_path):
    rng = np.random.default_rng(3)
    indices = rng.integers(0, 5, size=(7, 9, 13)).astype(np.uint8)
    indices[:, :2, :3] = VOID
    printer = load_printer("j750")
    names = ["cyan", "magenta", "yellow", "black", "white"]
    info = write_gcvf(tmp_path / "x.gcvf", indices, printer, names)
    back, meta = read_gcvf(tmp_path / "x.gcvf")
    assert np.array_equal(back, material_volume(indices, names, printer, meta["materials"]))
    assert meta["materials"] == info["materials"] == ["VeroCY-V", "VeroMGT-V", "VeroYL-V", "VeroBlackPlus",
                                                      "VUltraWhite"]
    # the package read with a plain zip and XML reader
    with zipfile.ZipFile(tmp_path / "x.gcvf") as z:
        assert sorted(n for n in z.namelist() if n.endswith(".png")) == sorted(f"layer_{k}.png" for k in range(7))
        root = ET.fromstring(z.read("ConfigFile.xml"))
        import cv2
        layer3 = cv2.imdecode(np.frombuffer(z.read("layer_3.png"), np.uint8), cv2.IMREAD_UNCHANGED)
    assert root.findtext("Resolution/XDpi") == "600" and root.findtext("Resolution/YDpi") == "300"
    assert root.findtext("Resolution/SliceThicknessNanoMeter") == "27000"
    assert root.findtext("SliceDimensions/SliceWidth") == "13" and root.findtext("SliceDimensions/SliceHeight") == "9"
    assert root.findtext("SliceRange/NumberOfSlices") == "7" and root.findtext("SliceRange/StartIndex") == "0"
    counts = [int(m.findtext("VoxelCount")) for m in root.findall("MaterialList/Material")]
    assert counts == [int((indices == k).sum()) for k in range(5)]
    # pixel (row j, column i) of layer k is voxel (k, j, i): the RGB of its material, the background outside
    rgb = layer3[..., ::-1]
    assert tuple(rgb[0, 0]) == (0, 0, 0) and tuple(rgb[5, 7]) == printer.materials[indices[3, 5, 7]][1][:3]


def test_gcvf_refusals_leave_no_file(tmp_path):
    printer = load_printer("j750")
    volume = np.zeros((3, 4, 5), np.uint8)
    with pytest.raises(ValueError, match="no material for the ink 'orange'"):
        write_gcvf(tmp_path / "x.gcvf", volume, printer, ["orange"])
    with pytest.raises(ValueError, match="ink index 2"):
        write_gcvf(tmp_path / "x.gcvf", volume + 2, printer, ["cyan", "white"])

    class Short:
        shape = (3, 4, 5)

        def __iter__(self):
            yield np.zeros((4, 5), np.uint8)
            raise RuntimeError("the source broke")

    with pytest.raises(RuntimeError, match="broke"):
        write_gcvf(tmp_path / "x.gcvf", Short(), printer, ["cyan"])
    assert os.listdir(tmp_path) == []
    # a truncated package is refused
    write_gcvf(tmp_path / "x.gcvf", volume, printer, ["cyan"])
    data = (tmp_path / "x.gcvf").read_bytes()
    (tmp_path / "cut.gcvf").write_bytes(data[: len(data) // 2])
    with pytest.raises(ValueError, match="not a GCVF package"):
        read_gcvf(tmp_path / "cut.gcvf")
    # a layer with a colour that is no material's, and a missing layer
    import cv2
    with zipfile.ZipFile(tmp_path / "x.gcvf") as old, zipfile.ZipFile(tmp_path / "odd.gcvf", "w") as new, \
            zipfile.ZipFile(tmp_path / "gap.gcvf", "w") as gap:
        for name in old.namelist():
            data = old.read(name)
            if name == "layer_1.png":
                data = cv2.imencode(".png", np.full((4, 5, 3), 7, np.uint8))[1].tobytes()
            else:
                gap.writestr(name, data)
            new.writestr(name, data)
    with pytest.raises(ValueError, match=r"layer_1.png: pixel \(row 0, column 0\) has colour \[7, 7, 7\]"):
        read_gcvf(tmp_path / "odd.gcvf")
    with pytest.raises(ValueError, match=r"missing \['layer_1.png'\]"):
        read_gcvf(tmp_path / "gap.gcvf")


# ------------------------------------------------------------------------------------------------ run folders
@pytest.fixture(scope="module")
def slab_run(tmp_path_factory):
    folder = tmp_path_factory.mktemp("slab")
    cfg = PrintConfig(target=tiny_print_target(folder / "t.exr"), thickness_mm=0.34, spp=2, eval_spp=4, eval_every=2,
                      iterations=2, naive_baseline=False, out=str(folder / "run"), seed=5)
    optimize_print(cfg, **QUIET)
    return str(folder / "run")


@pytest.fixture(scope="module")
def object_run(tmp_path_factory):
    import trimesh

    folder = tmp_path_factory.mktemp("object")
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    rgb = np.clip(0.5 + 0.4 * mesh.vertex_normals, 0, 1)
    mesh.visual.vertex_colors = np.c_[(rgb * 255).astype(np.uint8), np.full(len(rgb), 255, np.uint8)]
    mesh.export(folder / "sphere.ply")
    cfg = PrintConfig(mesh=str(folder / "sphere.ply"), height_mm=1.6, dpi=100.0, shell_mm=0.55, spp=2, eval_spp=4,
                      eval_every=2, iterations=2, views=0, naive_baseline=False, printer="j750",
                      out=str(folder / "run"))
    summary = optimize_print(cfg, **QUIET)
    assert summary["package"]["printer"] == "j750"
    return str(folder / "run")


def test_the_optimiser_writes_the_printers_package(object_run):
    """--printer: the run is quantised at the printer's resolution and its package holds that volume exactly."""
    config = json.load(open(os.path.join(object_run, "config.json")))
    assert config["printer"] == "j750" and config["printer_dpi"][2] == pytest.approx(25.4 / 0.027)
    indices, inks, dpi = load_index_volume(os.path.join(object_run, "quantized.npz"))
    assert (indices == VOID).any() and (indices != VOID).any()
    back, meta = read_gcvf(os.path.join(object_run, "package-j750", "print.gcvf"))
    printer = load_printer("j750")
    assert np.array_equal(back, material_volume(indices, inks.names, printer, meta["materials"]))
    assert meta["layers"] == indices.shape[0] and meta["dpi_xy"] == (600.0, 300.0)
    record = json.load(open(os.path.join(object_run, "package-j750", "export.json")))
    assert record["volume"] == "run" and set(record["formats"]) == {"gcvf", "3mf"}
    # the 3MF read back through lib3mf: the same volume, the profile's materials, a closed coloured mesh inside the box
    from torch_appearance.fabrication.threemf import read_3mf
    import trimesh
    volume = read_3mf(os.path.join(object_run, "package-j750", "print-volume.3mf"))
    names = [m[0] for m in volume["materials"]]
    assert names == ["VeroCY-V", "VeroMGT-V", "VeroYL-V", "VeroBlackPlus", "VUltraWhite"]
    assert np.array_equal(volume["indices"], material_volume(indices, inks.names, printer, names))
    plain = read_3mf(os.path.join(object_run, "package-j750", "print.3mf"))
    assert plain["indices"] is None and plain["vertex_rgb"] is not None
    mesh = trimesh.Trimesh(plain["vertices"], plain["faces"], process=False)
    box = np.array(volume["grid_shape"][::-1]) * np.array(volume["pitch_mm"])
    assert mesh.is_watertight and mesh.volume > 0 and np.all(mesh.bounds[0] >= 0) and np.all(mesh.bounds[1] <= box)


def test_export_of_a_slab_run_for_its_own_and_another_printer(slab_run, tmp_path):
    indices, inks, dpi = load_index_volume(os.path.join(slab_run, "quantized.npz"))
    j750 = load_printer("j750")
    record = export_run(slab_run, tmp_path / "p", "j750", ("gcvf", "slices"), **QUIET)
    assert record["volume"] == "run"                 # 940 DPI of the run is the j750's 27 µm within 1 %
    back, meta = read_gcvf(tmp_path / "p" / "print.gcvf")
    assert np.array_equal(back, material_volume(indices, inks.names, j750, meta["materials"]))
    from torch_appearance.fabrication import read_slices
    slices, palette = read_slices(tmp_path / "p" / "slices")
    assert np.array_equal(slices, indices) and palette["layers"] == indices.shape[0]
    # 14 µm layers: the mixture quantised again at that resolution with the run's quantisation seed
    hq = load_printer("j750-hq")
    record = export_run(slab_run, tmp_path / "hq", "j750-hq", ("gcvf",), **QUIET)
    assert record["volume"] == "requantized"
    weights = np.load(os.path.join(slab_run, "mixture.npz"))["weights"]
    config = json.load(open(os.path.join(slab_run, "config.json")))
    expected = quantize_mixture(weights, config["voxel_size_mm"], hq.dpi, seed=iteration_seed(config["seed"], -2),
                                halftone=config["halftone"])
    assert expected.shape[0] > 1.8 * indices.shape[0] and config["halftone"] == "blue-noise"   # the default
    back, meta = read_gcvf(tmp_path / "hq" / "print.gcvf")
    assert np.array_equal(back, material_volume(expected, inks.names, hq, meta["materials"]))
    assert meta["layer_thickness_nm"] == 14000


def test_export_of_an_object_for_another_printer_marks_the_outside_void(object_run, tmp_path):
    """Requantised object: the same outside as the optimiser's (independent reference: PyTorch's trilinear
    interpolation of the whole corner SDF)."""
    hq = load_printer("j750-hq")
    export_run(object_run, tmp_path / "hq", hq, ("gcvf",), **QUIET)
    back, meta = read_gcvf(tmp_path / "hq" / "print.gcvf")
    weights = np.load(os.path.join(object_run, "mixture.npz"))["weights"]
    config = json.load(open(os.path.join(object_run, "config.json")))
    expected = quantize_mixture(weights, config["voxel_size_mm"], hq.dpi, seed=iteration_seed(config["seed"], -2),
                                halftone=config["halftone"])
    sdf = torch.from_numpy(np.load(os.path.join(object_run, "object.npz"))["sdf"]).float()
    dz, hy, wx = expected.shape
    s = torch.nn.functional.interpolate(sdf[None, None], size=(dz + 1, hy + 1, wx + 1), mode="trilinear",
                                        align_corners=True)[0, 0]
    centre = sum(s[a:a + dz, b:b + hy, c:c + wx] for a in (0, 1) for b in (0, 1) for c in (0, 1)) / 8
    expected[(centre > 0).numpy()] = VOID
    inks = InkSet.from_names()
    assert np.array_equal(back, material_volume(expected, inks.names, hq, meta["materials"]))


def test_runs_recorded_before_the_halftone_option_were_random():
    assert PrintConfig().halftone == "blue-noise"
    assert PrintConfig.from_record({"seed": 3}).halftone == "random"
    assert PrintConfig.from_record({"halftone": "blue-noise"}).halftone == "blue-noise"
    with pytest.raises(ValueError, match="halftone"):
        PrintConfig(halftone="ordered").validate()


# ------------------------------------------------------------------------------------------------ streaming
def fake_run(folder, layers, h=24, w=32, n_inks=3, iterations=10):
    """A finished slab run folder whose quantised volume is ``layers`` tall (a tall thin print) and ``h`` × ``w``
    printer voxels wide, with the mixture's shape and the final texels that a 3MF export reads, and the log and summary
    of a run of ``iterations`` iterations."""
    from torch_appearance.pipelines.print.run_folder import LOG_FIELDS, npz_bytes

    os.makedirs(folder)
    inks = InkSet.from_names(["cyan", "yellow", "white"][:n_inks])
    voxel = 25.4 / 300
    depth = max(1, round(layers * 300 / 940))                       # macro layers whose micro grid has ~layers
    macro = (depth, h, w // 2)
    micro = micro_grid_shape(macro, voxel, (600, 300, 940))
    rng = np.random.default_rng(0)
    save_index_volume(os.path.join(folder, "quantized.npz"),
                      rng.integers(0, n_inks, size=micro).astype(np.uint8), inks, (600, 300, 940))
    ta_io.atomic_write_bytes(os.path.join(folder, "mixture.npz"), npz_bytes(
        weights=np.full((n_inks, *macro), 1.0 / n_inks, np.float32), inks=np.array(inks.names), voxel_size_mm=voxel))
    ta_io.write_exr(os.path.join(folder, "final.exr"), rng.random((h, w // 2, 3)).astype(np.float32))
    ta_io.write_json(os.path.join(folder, "config.json"), {
        "kind": "slab", "inks": [ink.to_dict() for ink in inks], "voxel_size_mm": voxel,
        "printer_dpi": [600, 300, 940], "seed": 0, "halftone": "random"})
    ta_io.write_csv(os.path.join(folder, "log.csv"), [{"iteration": i, "loss": 1.0 / (1 + i)}
                                                      for i in range(iterations + 1)], LOG_FIELDS)
    ta_io.write_json(os.path.join(folder, "summary.json"), {"kind": "slab", "iterations": iterations})
    return folder


def test_3mf_export_memory_does_not_grow_with_the_number_of_layers(tmp_path):
    """lib3mf keeps buffers per package part until the package is written (~100 kB per sheet); the sheets are
    streamed into the package instead, so a print 4× as tall peaks at the same resident memory."""
    export_run(fake_run(str(tmp_path / "warm"), 3, h=48, w=96), None, "j750", ("3mf",), **QUIET)
    grown = []
    for layers in (300, 1200):
        run = fake_run(str(tmp_path / f"run{layers}"), layers, h=48, w=96)
        import gc
        gc.collect()
        before = status_kb("VmRSS")
        if before is None or not reset_peak_rss():
            pytest.skip("the peak resident memory needs Linux /proc/self/status and clear_refs")
        export_run(run, None, "j750", ("3mf",), **QUIET)
        grown.append(1024 * (status_kb("VmHWM") - before))
    # 3 materials × 900 more sheets: lib3mf's own packaging grew by ~300 MB here
    assert grown[1] - grown[0] < 40e6, grown
    record = json.load(open(os.path.join(run, "package-j750", "export.json")))
    from torch_appearance.fabrication.threemf import read_3mf
    back = read_3mf(os.path.join(run, "package-j750", "print-volume.3mf"))
    indices, inks, _ = load_index_volume(os.path.join(run, "quantized.npz"))
    printer = load_printer("j750")
    names = [m[0] for m in back["materials"]]
    assert np.array_equal(back["indices"], material_volume(indices, inks.names, printer, names))
    assert record["files"]["print-volume.3mf"]["materials"] == names


def test_export_memory_does_not_grow_with_the_number_of_layers(tmp_path):
    """The volume is streamed: the traced peak (numpy's buffers are traced) of a 4× taller print stays far below the
    volume's size and grows only by bookkeeping per layer."""
    export_run(fake_run(str(tmp_path / "warm"), 3), None, "j750", ("gcvf", "slices"), **QUIET)  # imports, caches
    peaks = []
    for layers in (500, 2000):
        run = fake_run(str(tmp_path / f"run{layers}"), layers, h=64, w=96)
        tracemalloc.start()
        export_run(run, None, "j750", ("gcvf", "slices"), **QUIET)
        peaks.append(tracemalloc.get_traced_memory()[1])
        tracemalloc.stop()
    volume = 2000 * 64 * 96
    assert peaks[1] < 0.25 * volume, peaks
    # what grows is bookkeeping (the zip's directory entry and a file name per layer), not voxels (6 KB per layer)
    assert (peaks[1] - peaks[0]) / 1500 < 1024, peaks
    # the streamed layers are the volume's
    indices, _, _ = load_index_volume(os.path.join(run, "quantized.npz"))
    assert np.array_equal(np.stack(list(IndexVolumeLayers(os.path.join(run, "quantized.npz")))), indices)


def test_streamed_quantisation_equals_the_whole_volume():
    rng = np.random.default_rng(1)
    w = rng.random((4, 5, 6, 7))
    w /= w.sum(0, keepdims=True)
    for halftone in ("random", "blue-noise"):
        whole = quantize_mixture(w, 0.1, (600, 300, 940), seed=4, halftone=halftone)
        blocks = iter_quantized(w, 0.1, (600, 300, 940), seed=4, halftone=halftone)
        got = np.concatenate([b for _, b in blocks])
        assert blocks.shape == whole.shape and np.array_equal(got, whole)


# ------------------------------------------------------------------------------------------------ halftoning
def test_the_shipped_tile_is_the_computed_one():
    from torch_appearance.fabrication.halftone import shipped_tile
    assert np.array_equal(shipped_tile(), blue_noise_tile(32))


def test_blue_noise_tile_is_a_permutation_with_little_low_frequency_energy():
    tile = blue_noise_tile(16)
    assert np.array_equal(np.sort(tile.reshape(-1)), np.arange(16 ** 3))
    f = np.sqrt(sum(a ** 2 for a in np.meshgrid(*[np.fft.fftfreq(16)] * 3, indexing="ij")))
    low = (f > 0) & (f <= 0.2)
    for fraction in (0.1, 0.3, 0.5):
        dots = (tile < fraction * tile.size).astype(float)
        power = np.abs(np.fft.fftn(dots - dots.mean())) ** 2
        white = fraction * (1 - fraction) * tile.size        # expected power of independent draws
        assert power[low].mean() < 0.1 * white, (fraction, power[low].mean() / white)


@pytest.mark.parametrize("halftone", ["random", "blue-noise"])
def test_halftoning_keeps_the_mixtures_ink_frequencies(halftone):
    """Per macro voxel random mixtures: the count of each ink over the print is the sum of its weights over the
    micro voxels, within sampling error (4 σ of independent draws)."""
    rng = np.random.default_rng(7)
    w = rng.dirichlet(np.ones(4) * 0.7, size=(6, 10, 12)).transpose(3, 0, 1, 2)      # (N, D, H, W)
    dpi = (600, 300, 940)
    voxel = 25.4 / 150
    out = quantize_mixture(w, voxel, dpi, seed=11, halftone=halftone)
    dz, hy, wx = out.shape
    from torch_appearance.fabrication.quantize import source_index
    iz, iy, ix = (source_index(n, m) for n, m in zip(w.shape[1:], (dz, hy, wx)))
    p = w[:, iz[:, None, None], iy[None, :, None], ix[None, None, :]].reshape(4, -1)   # (N, micro voxels)
    expected = p.sum(1)
    sigma = np.sqrt((p * (1 - p)).sum(1))
    counts = np.bincount(out.reshape(-1), minlength=4)
    z = np.abs(counts - expected) / sigma
    assert np.all(z < 4), z
    # a constant mixture: blue noise spreads each ink evenly (box-filtered occupancy varies far less)
    flat = np.broadcast_to(np.array([0.3, 0.7])[:, None, None, None], (2, 4, 8, 8)).copy()
    v = quantize_mixture(flat, voxel, dpi, seed=2, halftone=halftone).astype(float)
    k = 4
    boxes = v[: v.shape[0] // k * k, : v.shape[1] // k * k, : v.shape[2] // k * k]
    boxes = boxes.reshape(boxes.shape[0] // k, k, boxes.shape[1] // k, k, boxes.shape[2] // k, k).mean((1, 3, 5))
    ratio = boxes.var() / (0.21 / k ** 3)              # against independent draws' variance of a box mean
    assert (ratio < 0.25) if halftone == "blue-noise" else (0.5 < ratio < 2.0), ratio


# ------------------------------------------------------------------------------------------------ the command
class Result:
    def __init__(self, returncode, stdout, stderr):
        self.returncode, self.stdout, self.stderr = returncode, stdout, stderr


@pytest.fixture
def cli(capsys):
    """ta-export-print in this process (its main(), as the console script calls it): exit status and output."""
    from torch_appearance.cli.export_print import main

    def run(*args):
        try:
            code = main([str(a) for a in args])
        except SystemExit as stop:
            code = stop.code
        out, err = capsys.readouterr()
        return Result(code, out, err)

    return run


def test_the_installed_command_exits_with_2(tmp_path):
    result = subprocess.run([sys.executable, "-m", "torch_appearance.cli.export_print", str(tmp_path)],
                            capture_output=True, text=True, env=dict(os.environ, OMP_NUM_THREADS="1"))
    assert result.returncode == 2 and result.stderr.count("\n") == 1 and "not a print run" in result.stderr


def test_the_command_refuses_bad_input_in_one_line_and_leaves_no_file(tmp_path, cli):
    run = fake_run(str(tmp_path / "run"), 5)
    before = sorted(os.listdir(run))

    def refused(args, message):
        result = cli(run, *args)
        assert result.returncode == 2, result.stderr
        lines = result.stderr.strip().splitlines()
        assert len(lines) == 1 and message in lines[0], result.stderr
        assert sorted(os.listdir(run)) == before

    refused(["--printer", "no-such"], "neither a built-in profile")
    profile = load_printer("generic").to_dict()
    del profile["inks"]["yellow"]
    (tmp_path / "p.json").write_text(json.dumps(profile))
    refused(["--printer", tmp_path / "p.json"], "no material for the ink 'yellow'")
    refused(["--format", "stl"], "--format")
    os.makedirs(tmp_path / "taken")
    refused(["--out", tmp_path / "taken"], f"--out: {str(tmp_path / 'taken')!r} exists; pass --force to replace it")
    assert os.listdir(tmp_path / "taken") == []
    result = cli(tmp_path, "--printer", "j750")
    assert result.returncode == 2 and "not a print run" in result.stderr
    os.remove(os.path.join(run, "quantized.npz"))
    result = cli(run)
    assert result.returncode == 2 and "has not finished" in result.stderr
    ta_io.write_json(os.path.join(run, "config.json"), {"inks": []})
    result = cli(run)
    assert result.returncode == 2 and "incompatible version" in result.stderr


def test_a_failed_export_leaves_no_package_and_fixed_fractions_are_not_requantised(tmp_path, monkeypatch):
    run = fake_run(str(tmp_path / "run"), 6)
    import torch_appearance.fabrication.gcvf as gcvf

    def broken(path, *args, **kwargs):
        open(path, "wb").write(b"half a package")
        raise RuntimeError("the disk is full")

    monkeypatch.setattr(gcvf, "write_gcvf", broken)
    with pytest.raises(RuntimeError, match="disk is full"):
        export_run(run, tmp_path / "out", "j750", ("slices", "gcvf"), **QUIET)
    assert sorted(os.listdir(tmp_path)) == ["run"]              # neither the package nor its temporary folder
    monkeypatch.undo()
    config = json.load(open(os.path.join(run, "config.json")))
    ta_io.write_json(os.path.join(run, "config.json"), {**config, "fixed": ["white=0.5:mask.png"]})
    with pytest.raises(ValueError, match="fixed ink fractions"):
        export_run(run, tmp_path / "hq", "j750-hq", ("gcvf",), **QUIET)
    assert sorted(os.listdir(tmp_path)) == ["run"]


def test_the_command_writes_and_replaces_with_force(tmp_path, cli):
    run = fake_run(str(tmp_path / "run"), 4)
    assert cli(run, "--format", "gcvf", "--quiet").returncode == 0
    package = os.path.join(run, "package-j750")
    assert sorted(os.listdir(package)) == ["export.json", "print.gcvf"]
    assert cli(run, "--format", "gcvf").returncode == 2
    assert cli(run, "--format", "slices", "--force", "--quiet").returncode == 0
    assert sorted(os.listdir(package)) == ["export.json", "slices"]
    listing = cli("--list-printers")
    assert listing.returncode == 0 and "j750-hq" in listing.stdout and "14 um" in listing.stdout


# ------------------------------------------------------------------------------------------------ the reader
def test_the_export_reader_asks_no_run_its_kind():
    """What differs between slab and object runs is a method of the run's reader (SlabRun, ObjectRun), chosen once
    from config.json by the table RUN_TYPES: no ``.kind`` and no kind name anywhere else in the module (STYLE.md,
    habit 23)."""
    import ast
    import inspect

    from torch_appearance.pipelines.print import package

    tree = ast.parse(inspect.getsource(package))
    table = next(n for n in ast.walk(tree) if isinstance(n, ast.Assign)
                 and any(isinstance(t, ast.Name) and t.id == "RUN_TYPES" for t in n.targets))
    in_table = {id(n) for n in ast.walk(table)}
    asked = [n.lineno for n in ast.walk(tree) if isinstance(n, ast.Attribute) and n.attr == "kind"]
    asked += [n.lineno for n in ast.walk(tree) if isinstance(n, ast.Constant) and n.value in package.RUN_TYPES
              and id(n) not in in_table]
    assert not asked, f"package.py asks a run its kind at lines {sorted(asked)}"
    assert set(package.RUN_TYPES) == {"slab", "object"}


def test_open_run_gives_the_reader_of_the_target_type(slab_run, object_run):
    from torch_appearance.pipelines.print.package import ObjectRun, SlabRun, open_run

    slab, obj = open_run(slab_run), open_run(object_run)
    assert type(slab) is SlabRun and type(obj) is ObjectRun
    assert slab.final_texels().shape[-1] == 3 and slab.final_texels().ndim == 4   # (F, H, W, 3)
    assert obj.final_texels().ndim == 2 and obj.outside((4, 6, 8)) is not None and slab.outside((4, 6, 8)) is None
    assert slab.iteration() == 2 and obj.iteration() == 2
    # the run's own export, at its end under its lock, records the iteration too
    assert json.load(open(os.path.join(object_run, "package-j750", "export.json")))["iteration"] == 2


# ------------------------------------------------------------------------------------------------ concurrent use
def command_env():
    return dict(os.environ, OMP_NUM_THREADS="1", PYTHONUNBUFFERED="1")


def export_cli(*args):
    return [sys.executable, "-m", "torch_appearance.cli.export_print", *[str(a) for a in args]]


_PAUSED_EXPORT = """
import os, sys, time
import torch_appearance.fabrication.gcvf as gcvf
from torch_appearance.cli.export_print import main

write, flags = gcvf.write_gcvf, sys.argv[1]

def paused(*args, **kwargs):  # mid-write: the package's temporary folder exists, OUT does not yet
    open(flags + ".started", "w").close()
    while not os.path.exists(flags + ".go"):
        time.sleep(0.02)
    return write(*args, **kwargs)

gcvf.write_gcvf = paused
sys.exit(main(sys.argv[2:]))
"""


def _wait_for(path, proc, seconds=120):
    deadline = time.monotonic() + seconds
    while not os.path.exists(path):
        assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()
        time.sleep(0.02)


def test_a_second_export_to_one_out_is_refused_while_the_first_writes(tmp_path, cli):
    """Two ta-export-print processes to one --out: the second, started while the first writes (its existence check
    passes: OUT is not there yet), is refused with one line and exit 2, with or without --force; the first's package
    is complete; a later one is refused without --force. No lock file or temporary folder is left."""
    run = fake_run(str(tmp_path / "run"), 6)
    out, flags = tmp_path / "p", str(tmp_path / "flag")
    first = subprocess.Popen([sys.executable, "-c", _PAUSED_EXPORT, flags, run, "--format", "gcvf,slices",
                              "--out", out], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                             env=command_env())
    _wait_for(flags + ".started", first)
    for extra in ([], ["--force"]):
        second = subprocess.run(export_cli(run, "--format", "slices", "--out", out, *extra), capture_output=True,
                                text=True, env=command_env(), timeout=300)
        lines = second.stderr.strip().splitlines()
        assert second.returncode == 2 and len(lines) == 1, second.stderr
        assert f"--out: {str(out)!r} is being written by another process" in lines[0], second.stderr
    open(flags + ".go", "w").close()
    _, err = first.communicate(timeout=300)
    assert first.returncode == 0, err
    assert "\r" not in err    # its progress bars (stderr is a pipe): whole lines
    assert sorted(os.listdir(out)) == ["export.json", "print.gcvf", "slices"]
    assert json.load(open(out / "export.json"))["iteration"] == 10
    assert sorted(p for p in os.listdir(tmp_path) if p.startswith(".")) == []
    refused = cli(run, "--format", "slices", "--out", out)
    assert refused.returncode == 2 and "exists; pass --force" in refused.stderr
    assert cli(run, "--format", "slices", "--out", out, "--force", "--quiet").returncode == 0


def test_an_export_is_refused_while_a_run_writes_its_folder_and_records_the_iteration(tmp_path, cli):
    """ta-export-print of a run that ta-optimize-print --resume is extending: refused (exit 2, one line) while the
    run holds its folder; after the run was interrupted, refused again (its volume is of an older iteration than its
    log); once the run wrote its results, exported with that iteration in export.json."""
    run = tmp_path / "run"
    target = tiny_print_target(tmp_path / "t.exr", 6, 8)
    optimize_print(PrintConfig(target=target, thickness_mm=0.34, spp=2, eval_spp=4, eval_every=1, iterations=2,
                               naive_baseline=False, out=str(run), seed=5), progress=False, log=lambda *_: None)
    assert cli(run, "--format", "slices", "--out", tmp_path / "p2", "--quiet").returncode == 0
    assert json.load(open(tmp_path / "p2" / "export.json"))["iteration"] == 2
    extending = subprocess.Popen(command_argv("optimize_print", "--out", run, "--resume", "--iterations", "100000",
                                              "--quiet"), stdout=subprocess.PIPE,
                                 stderr=subprocess.PIPE, text=True, env=command_env(),
                                 preexec_fn=sigint_default)
    try:
        deadline = time.monotonic() + 300
        while len(ta_io_rows(run)) <= 4:  # the resumed run has logged iterations: it holds the folder
            assert extending.poll() is None and time.monotonic() < deadline, extending.communicate()
            time.sleep(0.05)
        during = subprocess.run(export_cli(run, "--format", "slices", "--out", tmp_path / "p3"),
                                capture_output=True, text=True, env=command_env(), timeout=300)
        lines = during.stderr.strip().splitlines()
        assert during.returncode == 2 and len(lines) == 1, during.stderr
        assert f"run: {str(run)!r} is in use by a run that is writing it" in lines[0]
        assert not os.path.exists(tmp_path / "p3")
    finally:
        extending.send_signal(signal.SIGINT)
        _, err = extending.communicate(timeout=120)
    assert extending.returncode == 130, err
    logged = int(ta_io_rows(run)[-1]["iteration"])
    assert logged > 2
    stale = cli(run, "--format", "slices", "--out", tmp_path / "p3")
    assert stale.returncode == 2 and len(stale.stderr.strip().splitlines()) == 1, stale.stderr
    assert f"was extended to iteration {logged} but its results are of iteration 2" in stale.stderr
    assert not os.path.exists(tmp_path / "p3")
    from torch_appearance.testing import run_command
    rc, _, err = run_command("optimize_print", "--out", run, "--resume", "--iterations", logged, "--quiet")
    assert rc == 0, err
    assert cli(run, "--format", "slices", "--out", tmp_path / "p3", "--quiet").returncode == 0
    assert json.load(open(tmp_path / "p3" / "export.json"))["iteration"] == logged


def ta_io_rows(folder):
    import csv
    try:
        with open(os.path.join(folder, "log.csv"), newline="") as handle:
            return list(csv.DictReader(handle))
    except FileNotFoundError:
        return []


def test_write_errors_name_out_not_the_temporary_folder(tmp_path, cli, monkeypatch):
    run = fake_run(str(tmp_path / "run"), 4)
    open(tmp_path / "afile", "w").close()
    blocked = cli(run, "--format", "gcvf", "--out", tmp_path / "afile" / "p", "--quiet")
    assert blocked.returncode == 2 and len(blocked.stderr.strip().splitlines()) == 1, blocked.stderr
    assert f"--out: cannot write the package {str(tmp_path / 'afile' / 'p')!r}" in blocked.stderr
    import errno

    import torch_appearance.fabrication.gcvf as gcvf

    def full(path, *args, **kwargs):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), path)

    monkeypatch.setattr(gcvf, "write_gcvf", full)
    result = cli(run, "--format", "gcvf", "--out", tmp_path / "p", "--quiet")
    assert result.returncode == 2 and len(result.stderr.strip().splitlines()) == 1, result.stderr
    assert result.stderr.strip().endswith(f"--out: cannot write the package {str(tmp_path / 'p')!r}: "
                                          f"{os.strerror(errno.ENOSPC)}")
    assert ".tmp" not in result.stderr and ".lock" not in result.stderr
    assert sorted(os.listdir(tmp_path)) == ["afile", "run"]      # no package, no temporary folder, no lock file


def test_an_export_beyond_the_memory_the_process_may_use_is_refused_before_any_file(tmp_path, cli, monkeypatch):
    """The export's memory (export_memory_bytes: more when the mixture is quantised again) against what the process
    may use (runs.memory_limits; here a cgroup limit): refused in one line before the volume is prepared, no package."""
    from torch_appearance.pipelines import runs
    from torch_appearance.pipelines.print.package import export_memory_bytes

    run = fake_run(str(tmp_path / "run"), 5)
    own, again = export_memory_bytes((3, 2, 24, 16), False), export_memory_bytes((3, 2, 24, 16), True)
    assert again > own
    monkeypatch.setattr(runs, "memory_limits",
                        lambda proc="/proc", device=None: {"cgroup memory.max": (own + again) // 2})
    assert cli(run, "--printer", "j750").returncode == 0  # its own volume: admitted
    result = cli(run, "--printer", "j750-hq", "--out", tmp_path / "hq")
    assert result.returncode == 2 and result.stderr.count("\n") == 1, result.stderr
    assert "needs about" in result.stderr and "(its cgroup memory.max)" in result.stderr, result.stderr
    assert not (tmp_path / "hq").exists()
