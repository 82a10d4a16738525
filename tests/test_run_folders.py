"""Every command that writes a run folder owns it (issue 49 §3): another tool's folder is refused in one line naming
that tool, exit 2, before any work and with the folder as it was; a second process on the same --out is refused
while the first writes (the folder's lock); and the folder says whose it is (tool.json)."""
import json
import os
import subprocess
import sys
import time

import pytest

from torch_appearance.pipelines.runs import (OWNER_FILE, check_run_folder_owner, claim_run_folder, mark_run_folder,
                                             run_folder_owner)
from torch_appearance.testing import command_argv, interrupt_when, run_command, tiny_print_target

SPOT = os.path.join(os.path.dirname(__file__), "data", "meshes", "spot")


def _photo(path):
    import numpy as np

    from torch_appearance import io as ta_io

    ta_io.write_png(str(path), np.full((16, 16, 3), 0.5, np.float32))
    return str(path)


#: module of torch_appearance.cli -> (its tool, the arguments before --out, given the test's tmp_path)
COMMANDS = {
    "fit_wood": ("ta-fit-wood", lambda tmp: [_photo(tmp / "board.png"), "--quiet"]),
    "render_wood_volume": ("ta-render-wood-volume", lambda tmp: ["--synthetic", "3", "--quiet"]),
    "voxelize": ("ta-voxelize", lambda tmp: [os.path.join(SPOT, "spot_triangulated.obj"), "--height-mm", "10",
                                             "--quiet"]),
    "select_inks": ("ta-select-inks", lambda tmp: ["--target", "colorchecker", "--width-mm", "1.5", "--dpi", "100",
                                                   "--quiet"]),
    "optimize_print": ("ta-optimize-print", lambda tmp: ["--target", tiny_print_target(tmp / "t.exr"), "--quiet"]),
    "render_object": ("ta-render-object", lambda tmp: ["--size", "8", "--spp", "1", "--voxel-size", "0.5"]),
}


def _listing(folder):
    return {entry.name: (entry.stat().st_ino, entry.stat().st_mtime_ns) for entry in os.scandir(folder)}


@pytest.mark.parametrize("name", sorted(COMMANDS))
def test_another_tools_folder_is_refused_in_one_line(name, tmp_path, monkeypatch):
    """--out a folder another tool marked: exit 2, one line naming --out, the owner and what to do; the folder
    unchanged (it was overwritten: ta-optimize-print replaced a fit's summary.json, log.csv, convergence.png)."""
    monkeypatch.chdir(tmp_path)
    tool, args = COMMANDS[name]
    other = "ta-voxelize" if tool != "ta-voxelize" else "ta-fit-wood"
    out = tmp_path / "theirs"
    out.mkdir()
    mark_run_folder(str(out), other)
    (out / "summary.json").write_text("{}")
    before = _listing(out)
    rc, _, err = run_command(name, *args(tmp_path), "--out", out)
    lines = err.strip().splitlines()
    assert rc == 2 and len(lines) == 1, err
    assert lines[0].startswith(f"{tool}: error: --out: {str(out)!r} holds the output of {other} (its tool.json); "
                               f"{tool} writes only into a new folder or one of its own: choose another folder"), err
    assert _listing(out) == before


def test_a_folder_from_before_the_mark_is_known_by_its_files(tmp_path, monkeypatch):
    """A wood fit written before tool.json existed (board_estimate.json, model.json): refused by the print run."""
    monkeypatch.chdir(tmp_path)
    out = tmp_path / "fit"
    out.mkdir()
    for name in ("board_estimate.json", "summary.json", "log.csv"):
        (out / name).write_text("{}")
    assert run_folder_owner(str(out)) == ("ta-fit-wood", "it holds board_estimate.json")
    rc, _, err = run_command("optimize_print", "--target", tiny_print_target(tmp_path / "t.exr"), "--out", out)
    assert rc == 2 and "holds the output of ta-fit-wood (it holds board_estimate.json)" in err, err
    assert sorted(os.listdir(out)) == ["board_estimate.json", "log.csv", "summary.json"]


@pytest.mark.parametrize("name", sorted(set(COMMANDS) - {"render_object"}))
def test_a_folder_another_process_writes_is_refused(name, tmp_path, monkeypatch):
    """While another run of the same tool holds --out (its lock: flock on the folder, across processes): exit 2,
    one line saying it is in use, nothing written."""
    monkeypatch.chdir(tmp_path)
    tool, args = COMMANDS[name]
    out = tmp_path / "run"
    argv = args(tmp_path)
    with claim_run_folder(str(out), tool):
        (out / "partial.txt").write_text("the other run's")
        before = _listing(out)
        rc, _, err = run_command(name, *argv, "--out", out)
        assert _listing(out) == before
    lines = err.strip().splitlines()
    assert rc == 2 and len(lines) == 1, err
    assert lines[0].startswith(f"{tool}: error: --out: {str(out)!r} is in use by another run or export"), err


def test_export_force_never_replaces_another_tools_folder(tmp_path, monkeypatch):
    """--force replaces a package, not a wood fit given as --out by mistake."""
    from test_printer_packages import fake_run

    monkeypatch.chdir(tmp_path)
    run = fake_run(str(tmp_path / "run"), 5)
    out = tmp_path / "fit"
    out.mkdir()
    mark_run_folder(str(out), "ta-fit-wood")
    rc, _, err = run_command("export_print", run, "--out", out, "--force", "--quiet")
    assert rc == 2 and err.count("\n") == 1 and "holds the output of ta-fit-wood" in err, err
    assert os.listdir(out) == [OWNER_FILE]


def test_the_claim_marks_the_folder_and_leaves_none_when_nothing_was_written(tmp_path):
    folder = str(tmp_path / "new")
    with claim_run_folder(folder, "ta-fit-wood"):
        assert json.loads(open(os.path.join(folder, OWNER_FILE)).read()) == {"tool": "ta-fit-wood"}
    assert not os.path.exists(folder)  # a refused input (nothing but the mark) leaves no folder
    with claim_run_folder(folder, "ta-fit-wood"):
        open(os.path.join(folder, "fit.png"), "w").close()
    assert sorted(os.listdir(folder)) == ["fit.png", OWNER_FILE]
    before = _listing(folder)
    with claim_run_folder(folder, "ta-fit-wood"):  # the same tool again: the mark is not rewritten
        pass
    assert _listing(folder) == before
    with pytest.raises(ValueError, match=r"^out: .* holds the output of ta-fit-wood \(its tool.json\); "
                                         r"ta-voxelize writes only"):
        check_run_folder_owner(folder, "ta-voxelize")
    with open(os.path.join(folder, OWNER_FILE), "w") as f:
        f.write("not json")
    with pytest.raises(ValueError, match="holds the output of another tool \\(its tool.json names none that can"):
        check_run_folder_owner(folder, "ta-fit-wood")


def test_a_user_folder_is_taken_and_its_files_kept(tmp_path):
    """A folder no tool marked (the user's own, or results/): taken, its files left alone, the mark added."""
    folder = tmp_path / "mine"
    folder.mkdir()
    (folder / "notes.txt").write_text("mine")
    assert run_folder_owner(str(folder)) is None
    with claim_run_folder(str(folder), "ta-render-wood-volume"):
        pass
    assert sorted(os.listdir(folder)) == ["notes.txt"]  # nothing written: the mark went again
    with claim_run_folder(str(folder), "ta-render-wood-volume"):
        (folder / "figure.png").write_text("x")
    assert run_folder_owner(str(folder)) == ("ta-render-wood-volume", "its tool.json")


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="SIGINT to a child: POSIX")
def test_two_fits_on_one_folder_and_ctrl_c(tmp_path):
    """Two real ta-fit-wood processes on one --out: the second is refused in one line while the first fits, and
    the first, interrupted, leaves no folder."""
    from test_commands import _board

    _board(tmp_path / "board.png")
    out = tmp_path / "fit"
    env = dict(os.environ, OMP_NUM_THREADS="1")
    command = command_argv("fit_wood", tmp_path / "board.png", "--epochs", "100000", "--no-preview", "--quiet",
                           "--out", out)
    second = []

    def ready():
        if not (out / "board_estimate.json").exists():
            return False
        second.append(subprocess.run([str(a) for a in command], capture_output=True, text=True, env=env,
                                     timeout=300))
        return True

    t0 = time.monotonic()
    rc, _, err = interrupt_when(command, ready, env=env, wait_s=240)
    assert second, f"the first fit never wrote board_estimate.json in {time.monotonic() - t0:.0f} s"
    assert second[0].returncode == 2 and second[0].stderr.count("\n") == 1, second[0].stderr
    assert f"--out: {str(out)!r} is in use by another run" in second[0].stderr
    assert rc == 130 and err == "ta-fit-wood: interrupted; nothing was written (start it again)\n", err
    assert not out.exists()
