"""The ``ta-…`` commands as a user meets them: installed as console scripts (setup.cfg), ``--help`` with an example
from any folder, and bad input refused with exit status 2 and one line naming the argument, before any output."""
import configparser
import os
import subprocess
import sys

import pytest

from torch_appearance.testing import run_command

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _commands():
    cfg = configparser.ConfigParser()
    cfg.read(os.path.join(ROOT, "setup.cfg"))
    lines = [ln.strip() for ln in cfg["options.entry_points"]["console_scripts"].splitlines() if ln.strip()]
    return dict((name.strip(), target.strip()) for name, target in (ln.split("=") for ln in lines))


COMMANDS = _commands()


def test_every_command_follows_the_naming_scheme():
    assert len(COMMANDS) >= 8
    for name, target in COMMANDS.items():
        module, _, func = target.partition(":")
        assert name.startswith("ta-") and func == "main", (name, target)
        assert module == "torch_appearance.cli." + name[3:].replace("-", "_"), (name, target)


@pytest.mark.parametrize("name", sorted(COMMANDS))
def test_help_shows_an_example_from_any_folder(name, tmp_path):
    """The installed console script where the venv has it (``pip install -e .``), else the module."""
    script = os.path.join(os.path.dirname(sys.executable), name)
    cmd = [script] if os.path.exists(script) else [sys.executable, "-m", COMMANDS[name].partition(":")[0]]
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
