"""The ``ta-…`` commands as a user meets them: installed as console scripts (setup.cfg), ``--help`` with an example
from any folder, and bad input refused with exit status 2 and one line naming the argument, before any output."""
import configparser
import os
import subprocess
import sys

import pytest

from torch_appearance.testing import command_argv, interrupt_when, run_command

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _commands():
    cfg = configparser.ConfigParser()
    cfg.read(os.path.join(ROOT, "setup.cfg"))
    lines = [ln.strip() for ln in cfg["options.entry_points"]["console_scripts"].splitlines() if ln.strip()]
    return dict((name.strip(), target.strip()) for name, target in (ln.split("=") for ln in lines))


COMMANDS = _commands()


def console_script(name):
    """The argv of what the console script ``name`` runs (the script pip writes for setup.cfg's entry point), without
    the installed script."""
    module, _, func = COMMANDS[name].partition(":")
    return [sys.executable, "-c", f"import sys; from {module} import {func}; sys.argv[0] = {name!r}; sys.exit({func}())"]


def test_every_command_follows_the_naming_scheme():
    """ta-NAME is torch_appearance.cli.entry:NAME (of the standard library only), which runs main() of
    torch_appearance.cli.NAME."""
    from torch_appearance.cli import entry

    assert len(COMMANDS) >= 8
    for name, target in COMMANDS.items():
        module, _, func = target.partition(":")
        assert name.startswith("ta-") and module == "torch_appearance.cli.entry", (name, target)
        assert func == name[3:].replace("-", "_") and func in entry.__all__, (name, target)
        assert os.path.isfile(os.path.join(ROOT, "torch_appearance", "cli", func + ".py")), (name, target)


@pytest.mark.parametrize("name", sorted(COMMANDS))
def test_help_shows_an_example_from_any_folder(name, tmp_path):
    """The installed console script where the venv has it (``pip install -e .``), else what it runs."""
    script = os.path.join(os.path.dirname(sys.executable), name)
    cmd = [script] if os.path.exists(script) else console_script(name)
    env = dict(os.environ, OMP_NUM_THREADS="1")
    env.pop("PYTHONPATH", None)
    out = subprocess.run(cmd + ["--help"], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.startswith(f"usage: {name} "), out.stdout[:200]
    assert "Examples:" in out.stdout and f"\n    {name} " in out.stdout, out.stdout
    assert os.listdir(tmp_path) == []


BAD = {
    "ta-optimize-print": (["--threads", "0"], "--threads"),
    "ta-select-inks": (["-k", "x"], "-k"),
    "ta-fit-wood": (["photo.png", "--dpi", "0"], "--dpi"),
    "ta-voxelize": (["missing.obj", "--dpi", "0"], "--dpi"),
    "ta-render-object": (["--spp", "0"], "--spp"),
    "ta-render-wood-volume": (["--synthetic", "1", "--spp", "x"], "--spp"),
    "ta-detect-rings": (["missing.png", "--out", "."], "--out"),
    "ta-eval-rings": (["a.csv"], "labels_csv"),
    "ta-export-print": (["run", "--format", "stl"], "--format"),
}


@pytest.mark.parametrize("name", sorted(COMMANDS))
def test_bad_input_exits_2_with_one_line(name, tmp_path, monkeypatch):
    assert name in BAD, f"add a bad-input case for {name}"
    args, flag = BAD[name]
    monkeypatch.chdir(tmp_path)
    rc, out, err = run_command(name[3:].replace("-", "_"), *args)
    assert rc == 2, (rc, err)
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"{name}: error: ") and flag in lines[0], err
    assert os.listdir(tmp_path) == []


def test_out_naming_a_file_is_refused(tmp_path):
    target = tmp_path / "taken"
    target.write_text("not a folder")
    rc, _, err = run_command("render_object", "--out", target)
    assert rc == 2 and "--out: expected a folder" in err and target.read_text() == "not a folder"


# ---- issue 49: an --out that cannot be written, refused before any work, in one line naming --out
def _unwritable_outs(tmp_path):
    (tmp_path / "afile").write_text("a file, not a folder")
    outs = [str(tmp_path / "afile" / "sub")]
    if os.path.isdir("/proc") and not os.path.exists("/proc/x"):
        outs.append("/proc/x")  # exists as a folder where nothing can be made, even by root
    return outs


# each with an input that would be refused later: the --out check must come first, before the work
BEFORE_WORK = {
    "optimize_print": lambda out: ["--target", "missing.png", "--out", out],
    "voxelize": lambda out: ["missing.obj", "--out", out],
    "render_object": lambda out: ["--voxel-size", "0.001", "--out", out],
    "fit_wood": lambda out: ["missing.png", "--out", out],
    "detect_rings": lambda out: ["missing.png", "--out", out + ".csv"],
}


@pytest.mark.parametrize("name", sorted(BEFORE_WORK))
def test_an_out_that_cannot_be_written_is_refused_first(name, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    for out in _unwritable_outs(tmp_path):
        rc, _, err = run_command(name, *BEFORE_WORK[name](out))
        lines = err.strip().splitlines()
        assert rc == 2 and len(lines) == 1 and "error: --out: " in lines[0], (out, err)
    assert (tmp_path / "afile").read_text() == "a file, not a folder"
    assert sorted(os.listdir(tmp_path)) == ["afile"]  # no probe left behind


def _one_line(rc, err, start):
    lines = err.strip().splitlines()
    assert rc == 2 and len(lines) == 1 and lines[0].startswith(start), (rc, err)
    assert "Traceback" not in err
    return lines[0]


@pytest.mark.parametrize("args, start", [
    (["--ior", "0.5"], "ta-render-object: error: --ior: expected a finite value in [1, inf], got 0.5, or 0"),
    (["--light-deg", "200"], "ta-render-object: error: --light-deg: expected a finite value in (0, 180]"),
    (["--voxel-size", "0.001"], "ta-render-object: error: --voxel-size: a 10004³-voxel grid"),  # 24 TB, not tried
    (["--envmap", "missing.exr"], "ta-render-object: error: --envmap: no such file 'missing.exr'"),
])
def test_render_object_refuses_bad_values_in_one_line(args, start, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    _one_line(*run_command("render_object", *args, "--out", "r")[::2], start)
    assert os.listdir(tmp_path) == []


@pytest.mark.parametrize("args, start", [
    (["--spp", "1000000000"], "--spp: 1000000000 samples per texel"),  # was std::bad_alloc in the time estimate
    (["--eval-spp", "1000000000"], "--eval-spp: 1000000000 samples per texel"),
    (["--width-mm", "0.01"], "--width-mm: a slab 0.01 mm wide is 0 texels"),  # was a 1×1-texel slab
    (["--width-mm", "0.25", "--height-mm", "5"], "--width-mm: a slab 0.25 mm wide is 3 texels"),
    (["--height-mm", "0.2"], "--height-mm: a slab 0.2 mm high is 2 texels"),
    (["--width-mm", "0.4"], "--width-mm: a slab 0.271 mm high (the height at the target's 62×42 aspect) is 3"),
    (["--width-mm", "-1"], "--width-mm: expected > 0, got -1.0"),
    (["--inks", "white,foo"], "--inks: unknown ink 'foo'"),
    (["--gamma", "1,2"], "--gamma: expected 3 comma-separated numbers, got '1,2'"),
    (["--mesh", "missing.obj", "--height-mm", "5"], "--mesh: no such file 'missing.obj'"),
    (["--mesh", "missing.obj"], "--height-mm: an object print needs the object's height in mm"),
    (["--remap-baseline"], "--remap-baseline: the 2.5D remapped baseline is for objects (--mesh)"),
    (["--table-steps", "1000000000000"], "--table-steps: 1000000000000 steps give 4.17e+46 mixtures of the 5 inks"),
    (["--ior", "nan"], "--ior: expected a finite value >= 1, got nan"),  # was a JSON writer's error, not naming it
    (["--threads", "1000000000000"], "--threads: expected 1 ... "),  # was torch's overflow, a traceback
    (["--lr", "1000000000000"], "--lr: expected at most 100 (a step moves each of the mixture's parameters"),
])
def test_optimize_print_messages_name_its_flags(args, start, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    rc, _, err = run_command("optimize_print", *args, "--out", "r", "--quiet")
    line = _one_line(rc, err, "ta-optimize-print: error: " + start)
    assert ": --" not in line.split(": error: ", 1)[1]  # no doubled prefix (--gamma: --gamma:)
    assert os.listdir(tmp_path) == []


def test_optimize_print_advice_names_flags(tmp_path, monkeypatch):
    """``pass resume=True (--resume)`` of the library reads ``pass --resume`` (a folder that holds a run)."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "r").mkdir()
    (tmp_path / "r" / "checkpoint.pt").write_bytes(b"")
    rc, _, err = run_command("optimize_print", "--out", "r", "--quiet")
    line = _one_line(rc, err, "ta-optimize-print: error: --out: 'r' already holds a run")
    assert "pass --resume to continue it" in line and "resume=True" not in line


def test_view_options_on_a_slab_are_warned_in_one_line(tmp_path, monkeypatch):
    """``--views``/``--view-size``/``--view-spp`` make camera views of objects; on a slab they were ignored without
    a word. The run itself is replaced: only the command's reading of its flags is checked."""
    from torch_appearance.cli import optimize_print as command

    monkeypatch.chdir(tmp_path)
    started = []
    monkeypatch.setattr(command, "optimize_print", lambda cfg, **kwargs: started.append(cfg))
    rc, _, err = run_command("optimize_print", "--views", "2", "--view-spp=8", "--out", "r", "--quiet")
    assert rc == 0 and len(started) == 1, err
    assert err.strip().splitlines() == ["ta-optimize-print: warning: --views, --view-spp: camera views are made of "
                                        "objects (--mesh); a slab has none: ignored"]
    rc, _, err = run_command("optimize_print", "--out", "r2", "--quiet")
    assert rc == 0 and "warning" not in err, err


def test_slab_aspect_change_is_warned_in_one_line():
    from torch_appearance.cli.optimize_print import check_slab_size
    from torch_appearance.pipelines.print import PrintConfig

    said = []
    check_slab_size(PrintConfig(target="colorchecker", width_mm=40.0, height_mm=40.0), said.append)
    assert len(said) == 1 and said[0].startswith("width_mm/height_mm: a 40 × 40 mm slab stretches the target's "
                                                 "62×42 texels (aspect 1.48) to an aspect of 1.00")
    for kept in (dict(width_mm=40.0), dict(height_mm=10.0), dict(width_mm=62.0, height_mm=42.0)):
        check_slab_size(PrintConfig(target="colorchecker", **kept), said.append)
    assert len(said) == 1


def _fake_run(folder, checkpoint_bytes):
    import dataclasses

    from torch_appearance import io as ta_io
    from torch_appearance.pipelines.print import PrintConfig

    folder.mkdir()
    ta_io.write_json(str(folder / "config.json"), dataclasses.asdict(PrintConfig(out=str(folder))))
    (folder / "checkpoint.pt").write_bytes(checkpoint_bytes)


def _checkpoint_bytes():
    import io

    import torch

    buffer = io.BytesIO()
    torch.save({"model": {"w": torch.zeros(4096)}, "optimizer": {}, "rows": [], "iteration": 3, "wall_s": 1.0,
                "baseline": None, "grid_dhw": [1, 2, 3], "inks": ["white"]}, buffer)
    return buffer.getvalue()


def test_resume_of_a_truncated_checkpoint_is_refused_naming_it(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    whole = _checkpoint_bytes()
    _fake_run(tmp_path / "r", whole[: len(whole) // 2])
    rc, _, err = run_command("optimize_print", "--out", "r", "--resume", "--quiet")
    line = _one_line(rc, err, "ta-optimize-print: error: --resume: the checkpoint 'r/checkpoint.pt' cannot be read")
    assert "truncated or damaged" in line
    assert (tmp_path / "r" / "checkpoint.pt").read_bytes() == whole[: len(whole) // 2]


def test_load_checkpoint_names_a_damaged_file(tmp_path):
    from torch_appearance.pipelines.runs import load_checkpoint

    whole = _checkpoint_bytes()
    path = tmp_path / "checkpoint.pt"
    path.write_bytes(whole)
    assert load_checkpoint(str(path))["iteration"] == 3
    damaged = {"truncated": whole[:-100], "empty": b"", "overwritten": whole[:200] + b"x" * 400 + whole[600:]}
    for what, data in damaged.items():
        path.write_bytes(data)
        with pytest.raises(ValueError, match=r"^resume: the checkpoint '.*checkpoint.pt' cannot be read .*truncated "
                                             r"or damaged"):
            load_checkpoint(str(path))
    import torch
    torch.save({"iteration": 3}, str(path))
    with pytest.raises(ValueError, match="no model, optimizer"):
        load_checkpoint(str(path))


def test_voxelize_refuses_a_units_guess_it_would_not_apply(tmp_path, monkeypatch):
    """Spot is 1.7 file units tall: read as mm it is a 1.7 mm cow, while the guess says metres (as trimesh, a
    guess is not applied silently): refused naming --scale; --scale 1 keeps the millimetres on purpose."""
    monkeypatch.chdir(tmp_path)
    spot = os.path.join(ROOT, "tests", "data", "meshes", "spot", "spot_triangulated.obj")
    rc, _, err = run_command("voxelize", spot, "--out", "v", "--no-previews", "--quiet")
    line = _one_line(rc, err, "ta-voxelize: error: --scale: the model is 0.943 × 1.69 × 1.72 file units, which "
                              "reads as metres")
    assert "--scale 1000" in line and "--scale 1 " in line and "--height-mm" in line
    assert os.listdir(tmp_path) == []
    rc, out, err = run_command("voxelize", spot, "--scale", "1", "--dpi", "100", "--out", "v", "--no-previews",
                               "--quiet")
    assert rc == 0, err


def test_voxelize_grid_too_large_names_dpi(tmp_path, monkeypatch):
    """A grid beyond the memory limit is refused naming --dpi (it read voxel_size:, the library's name), in one line
    without --quiet too (the refusal came after two progress lines)."""
    monkeypatch.chdir(tmp_path)
    spot = os.path.join(ROOT, "tests", "data", "meshes", "spot", "spot_triangulated.obj")
    rc, _, err = run_command("voxelize", spot, "--height-mm", "5000", "--out", "v", "--no-previews")
    line = _one_line(rc, err, "ta-voxelize: error: --dpi: 0.0846667 mm gives a 59058×58113×32423 grid that needs")
    assert "voxel_size" not in line
    assert os.listdir(tmp_path) == []
    # absurd heights refused before the mesh is loaded (1e12 mm: a numpy RuntimeWarning from trimesh, then refused)
    for height, start in (("1e12", "--height-mm: 1e+12 mm at 300 DPI is 1.18e+13 voxels tall; expected at most"),
                          ("nan", "--height-mm: expected a finite value > 0, got nan")):
        rc, _, err = run_command("voxelize", spot, "--height-mm", height, "--out", "v", "--no-previews", "--quiet")
        _one_line(rc, err, "ta-voxelize: error: " + start)
    assert os.listdir(tmp_path) == []


def test_voxelize_hint_names_the_flag(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "quad.obj").write_text("v 0 0 0\nv 4 0 0\nv 4 4 0\nv 0 0 4\nvt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\n"
                                       "f 1/1 3/3 2/2\nf 1/1 2/2 4/4\nf 2/2 3/3 4/4\nf 3/3 1/1 4/4\n")
    rc, _, err = run_command("voxelize", "quad.obj", "--scale", "1", "--dpi", "50", "--out", "v", "--no-previews")
    assert rc == 0, err
    assert "pass --texture PATH (the base-colour image)" in err and "texture=" not in err


def test_eval_rings_refuses_header_only_labels(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "d.csv").write_text("index,x_px,y_px\n0,1,1\n")
    (tmp_path / "l.csv").write_text("index,x_px,y_px\n")
    rc, out, err = run_command("eval_rings", "d.csv", "l.csv")
    _one_line(rc, err, "ta-eval-rings: error: labels_csv: 'l.csv' holds no labelled boundary")
    assert out == "" and "nan" not in err


EVAL_FILES = {
    "d.csv": "index,x_px,y_px\n0,40,24\n1,80,24\n",
    "hdr.csv": "index,x_px,y_px\n",
    "empty.csv": "",
    "nan.csv": "index,x_px,y_px\n0,41,24\n1,inf,24\n",
    "semi.csv": "x_px;y_px\n40;24\n",
    "tr.csv": "transect,x_px,y_px\n0,40,24\n1,80,24\n",
    "tr_labels.csv": "transect,x_px,y_px\n0,40,24\n1,200,24\n",
    "x_only.csv": "x_px\n41\n80\n",
}


@pytest.mark.parametrize("args, start", [
    (["d.csv", "empty.csv"], "labels_csv: 'empty.csv' is empty; expected a CSV with an x_px column"),
    (["empty.csv", "d.csv"], "detected_csv: 'empty.csv' is empty"),
    (["d.csv", "missing.csv"], "labels_csv: no such file 'missing.csv'"),
    (["d.csv", "."], "labels_csv: expected a CSV file, got the folder '.'"),
    (["d.csv", "nan.csv"], "labels_csv: 'nan.csv': column x_px holds inf in data row 2"),  # was "labels contains"
    (["d.csv", "semi.csv"], "labels_csv: 'semi.csv' has no x_px column (columns: x_px;y_px)"),
    (["d.csv", "tr_labels.csv"], "labels_csv: 'tr_labels.csv' holds several transects, while detected_csv"),
    (["tr.csv", "tr_labels.csv", "--transect", "2"], "--transect 2: detected_csv 'tr.csv' has no transect 2"),
    (["d.csv", "d.csv", "--tolerance-px", "inf"], "--tolerance-px: expected a finite value > 0 (pixels), got inf"),
    (["d.csv", "d.csv", "--tolerance-px", "nan"], "--tolerance-px: expected a finite value > 0 (pixels), got nan"),
])
def test_eval_rings_refuses_bad_files_in_one_line_naming_the_argument(args, start, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    for name, text in EVAL_FILES.items():
        (tmp_path / name).write_text(text)
    rc, out, err = run_command("eval_rings", *args)
    _one_line(rc, err, "ta-eval-rings: error: " + start)
    assert out == ""


def test_eval_rings_results_are_honest(tmp_path, monkeypatch):
    """--transect K scores transect K of the labels too (all labels were scored against it: sensitivity 0.5 for a
    perfect transect); a spreadsheet's byte-order mark is read; x only and nothing detected are said so."""
    monkeypatch.chdir(tmp_path)
    for name, text in EVAL_FILES.items():
        (tmp_path / name).write_text(text)
    (tmp_path / "bom.csv").write_text("x_px,y_px\n40,24\n80,24\n", encoding="utf-8-sig")
    rc, out, err = run_command("eval_rings", "tr.csv", "tr_labels.csv", "--transect", "0")
    assert rc == 0 and out.startswith("sensitivity 1.0000  precision 1.0000") and "labelled 1," in out, (out, err)
    rc, out, err = run_command("eval_rings", "d.csv", "bom.csv")
    assert rc == 0 and "F1 1.0000" in out and "x only" not in out, (out, err)
    rc, out, err = run_command("eval_rings", "d.csv", "x_only.csv")
    assert rc == 0 and out.rstrip().endswith("tolerance 3 px, x only: a file has no y_px)"), out
    rc, out, err = run_command("eval_rings", "hdr.csv", "d.csv")
    assert rc == 0 and "precision - (nothing detected)" in out and "detected 0," in out, out


def test_ctrl_c_in_export_print_is_one_line(tmp_path, monkeypatch):
    from torch_appearance.cli import export_print

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(export_print, "export_run", interrupted)
    try:
        rc, _, err = run_command("export_print", tmp_path, "--out", tmp_path / "pkg")
    except KeyboardInterrupt:  # not let through: it would stop the test session
        pytest.fail("Ctrl-C escaped ta-export-print's main() (a traceback for the user)")
    assert rc == 130 and err == "ta-export-print: interrupted; nothing was written (an existing package is as it " \
                                "was)\n", err


def _board(path):
    from torch_appearance import io as ta_io
    from torch_appearance.rings.synthetic import synthetic_board

    ta_io.write_png(str(path), synthetic_board(128, 128, 0.1, seed=3)["image"])


def test_ctrl_c_in_fit_wood_leaves_no_partial_fit(tmp_path):
    """SIGINT to a running ta-fit-wood, once it has written its first files: one line, exit 130, and the folder it
    made is gone (a folder without summary.json is never left silently)."""
    _board(tmp_path / "board.png")
    out = tmp_path / "fit"
    env = dict(os.environ, OMP_NUM_THREADS="1")
    rc, _, err = interrupt_when(command_argv("fit_wood", tmp_path / "board.png", "--epochs", "100000", "--no-preview",
                                             "--quiet", "--out", out),
                                lambda: (out / "board_estimate.json").exists(), env=env, wait_s=240)
    assert rc == 130 and err == "ta-fit-wood: interrupted; nothing was written (start it again)\n", err
    assert not out.exists()


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="SIGINT to a child, /proc")
def test_interrupt_when_leaves_no_child_behind(tmp_path):
    """A child that outlives interrupt_when's timeout (here one that ignores SIGINT) is killed and reaped before the
    timeout is raised."""
    pid_file = tmp_path / "pid"
    code = (f"import os, signal, time; signal.signal(signal.SIGINT, signal.SIG_IGN); "
            f"open({str(pid_file)!r}, 'w').write(str(os.getpid())); time.sleep(120)")
    with pytest.raises(subprocess.TimeoutExpired):
        interrupt_when([sys.executable, "-c", code], lambda: pid_file.exists() and pid_file.read_text() != "",
                       wait_s=30, timeout_s=1)
    assert not os.path.exists(f"/proc/{pid_file.read_text()}")  # neither running nor a zombie


def test_an_interrupted_fit_over_an_earlier_one_drops_its_summary(tmp_path):
    from torch_appearance.cli.command import folder_listing, undo_partial

    folder = tmp_path / "fit"
    folder.mkdir()
    for name in ("summary.json", "phase.npy", "notes.txt"):
        (folder / name).write_text("earlier")
    before = folder_listing(str(folder))
    assert undo_partial(str(folder), before, "fit") == f"{str(folder)!r} is as it was (start it again)"
    (folder / "orientation.png").write_text("new")  # added by the interrupted fit: removed
    os.remove(folder / "phase.npy")
    (folder / "phase.npy").write_text("replaced")   # replaced: the earlier fit is no longer whole
    message = undo_partial(str(folder), before, "fit")
    assert "partly replaced (phase.npy)" in message and "summary.json is removed" in message
    assert sorted(os.listdir(folder)) == ["notes.txt", "phase.npy"]


# ---- issue 49: ta-fit-wood's sizes and ranges refused in one line before any work (the 128² board: h + w = 256)
@pytest.mark.parametrize("args, start", [
    (["--max-size", "0"], "--max-size: expected an int >= 8"),  # was a cv2.error traceback
    (["--max-size", "3"], "--max-size: expected an int >= 8"),  # was "found 0 growth ring(s)"
    (["--color-bins", "100000000"], "--color-bins: expected at most 256 (the 128 × 128 px photo's height + width"),
    (["--lobe-shape", "100000", "100000"], "--lobe-shape: expected at most 16384 texels"),  # 40 GB: a traceback
    (["--lobe-shape", "4"], "--lobe-shape: expected 2 arguments"),
    (["--lobe-shape", "2", "1"], "--lobe-shape: expected 0 0 (no lobe texture) or HTHETA >= 4 and HP >= 2, got 2 1"),
    (["--p", "1000"], "--p: expected at most 256 (the 128 × 128 px photo's height + width: a curve of 2p+1 = 2001 px "
                      "leaves the photo, so the steps beyond add only work; the filter would take about"),
    (["--q", "100000"], "--q: expected at most 256"),
    (["--coarse-to-fine", "100000"], "--coarse-to-fine: expected at most 6"),  # ran for hours
    (["--lr", "inf"], "--lr: expected a finite value > 0, got inf"),  # was an IndexError traceback
    (["--dpi", "inf"], "--dpi: expected a finite value > 0, got inf"),  # named --pixel-size-mm
    (["--dpi", "1000000000000"], "--dpi: expected 2.54 ... 254000 (pixels of 10 ... 0.0001 mm"),  # was taken
    (["--pixel-size-mm", "1000000000000"], "--pixel-size-mm: expected 0.0001 ... 10 mm per pixel"),  # was taken
    (["--lobe-radius-rings", "1000000000000"], "--lobe-radius-rings: expected at most 50 ring widths"),  # was taken
    (["--photometric-epochs", "5"], "--photometric-epochs: set for stage 3, which runs only with --photometric"),
    (["--photometric", "--photometric-levels", "1000"],  # stage 3 skipped the level without a word
     "--photometric-levels: expected downsampling factors of at most 32"),
    (["--photometric", "--photometric-spp", "1000000000"],  # a 4.6 TB allocation, a traceback
     "--photometric-spp: stage 3's 4096000000000 filter samples per step"),
    (["--photometric", "--photometric-color-lr", "inf"], "--photometric-color-lr: expected a finite value >= 0"),
])
def test_fit_wood_refuses_nonsense_sizes_in_one_line(args, start, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    _board(tmp_path / "board.png")
    rc, out, err = run_command("fit_wood", "board.png", *args, "--no-preview", "--quiet", "--out", "fit")
    _one_line(rc, err, "ta-fit-wood: error: " + start)
    assert sorted(os.listdir(tmp_path)) == ["board.png"]


def test_fit_wood_says_how_long_a_long_gabor_filter_takes_before_it(tmp_path, monkeypatch):
    """A filter estimated at SAY_GABOR_S or more is announced (with its estimate) before it starts."""
    from torch_appearance.pipelines.wood import fit as fit_module
    from torch_appearance.pipelines.wood import WoodFitConfig
    from torch_appearance.rings.gabor import curved_gabor_seconds

    _board(tmp_path / "board.png")
    said = []

    def stop(*args):
        said.append("work")
        raise KeyboardInterrupt

    monkeypatch.setattr(fit_module, "detect_board", stop)
    cfg = WoodFitConfig(photo=str(tmp_path / "board.png"), out=str(tmp_path / "fit"), p=200, q=50, preview=False)
    expected = curved_gabor_seconds((128, 128), 200, 50)
    monkeypatch.setattr(fit_module, "SAY_GABOR_S", expected * 0.99)
    with pytest.raises(KeyboardInterrupt):
        fit_module.fit_wood(cfg, progress=False, log=said.append)
    assert len(said) == 2 and said[1] == "work", said
    assert said[0].startswith("fit_wood: the curved Gabor filter of the 128 × 128 px photo with p = 200, q = 50 "
                              f"takes about {expected:.0f} s"), said
    said.clear()
    monkeypatch.setattr(fit_module, "SAY_GABOR_S", expected * 1.01)
    with pytest.raises(KeyboardInterrupt):
        fit_module.fit_wood(cfg, progress=False, log=said.append)
    assert said == ["work"]
