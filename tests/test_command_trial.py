"""What the new-user trial (scripts/eval/new_user_trial.py) found, kept as tests with real processes: Ctrl-C and a
second process on one --out for the commands that had neither."""
import os
import subprocess
import sys

import pytest

from torch_appearance.testing import command_argv, interrupt_when

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="SIGINT to a child: POSIX")


def _env():
    return dict(os.environ, OMP_NUM_THREADS="1", PYTHONUNBUFFERED="1")


def _cli(name, *args):
    return command_argv(name, *args)  # as the console script runs it


def test_render_object_refuses_a_second_process_and_ends_in_one_line_on_ctrl_c(tmp_path):
    """ta-render-object while another renders to the same --out: refused in one line, exit 2 (it replaced the
    other's files); Ctrl-C to the one rendering: one line, exit 130, no folder and no lock file left (it was a
    KeyboardInterrupt traceback and exit -2)."""
    out = tmp_path / "r"
    lock = tmp_path / ".r.lock"
    second = []

    def ready():  # the first renders (it holds --out's lock): start the second, then interrupt the first
        if not lock.exists():
            return False
        second.append(subprocess.run(_cli("render_object", "--size", "8", "--spp", "1", "--voxel-size", "0.5",
                                          "--out", out), capture_output=True, text=True, env=_env(), timeout=300))
        return True

    rc, _, err = interrupt_when(_cli("render_object", "--size", "64", "--spp", "100000", "--voxel-size", "0.5",
                                     "--out", out), ready, env=_env(), wait_s=240)
    assert second, "the first never took --out's lock"
    refused = second[0].stderr
    assert second[0].returncode == 2 and len(refused.splitlines()) == 1, refused
    assert refused.startswith(f"ta-render-object: error: --out: {str(out)!r} is being written by another process")
    assert rc == 130 and err == "ta-render-object: interrupted; nothing was written (start it again)\n", err
    assert sorted(os.listdir(tmp_path)) == []


def test_ctrl_c_in_render_wood_volume_leaves_no_partial_folder(tmp_path):
    """SIGINT to ta-render-wood-volume once it has written its first image: one line, exit 130, and the folder it
    made is gone (it was a KeyboardInterrupt traceback and a folder without summary.json)."""
    out = tmp_path / "v"
    rc, _, err = interrupt_when(_cli("render_wood_volume", "--synthetic", "3", "--synthetic-size", "32", "40",
                                     "--veneer-max-mm", "3", "--spp", "256", "--shade-spp", "256", "--threads", "1",
                                     "--quiet", "--out", out),
                                lambda: out.exists() and any(n.endswith(".png") for n in os.listdir(out)),
                                env=_env(), wait_s=240)
    assert rc == 130 and err == "ta-render-wood-volume: interrupted; nothing was written (start it again)\n", err
    assert not out.exists()


def test_ctrl_c_in_select_inks_is_one_line(tmp_path):
    """SIGINT to ta-select-inks once its first set runs: one line saying how to resume, exit 130 (it was a
    KeyboardInterrupt traceback)."""
    out = tmp_path / "sel"
    rc, _, err = interrupt_when(_cli("select_inks", "--target", "colorchecker", "--width-mm", "1.5", "--dpi", "100",
                                     "--thickness-mm", "0.5", "--candidates", "cyan,yellow", "-k", "1",
                                     "--iterations", "100000", "--spp", "2", "--eval-spp", "4", "--table-steps", "2",
                                     "--threads", "1", "--quiet", "--out", out),
                                lambda: (out / "inks.json").exists(), env=_env(), wait_s=240)
    assert rc == 130 and err == (f"ta-select-inks: interrupted; finished sets are kept; run the same command again "
                                 f"to resume the selection in {str(out)!r}\n"), err


def _trial_module():
    import importlib.util

    path = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "scripts", "eval",
                        "new_user_trial.py")
    spec = importlib.util.spec_from_file_location("new_user_trial", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_trials_numeric_sweep_reads_each_commands_options():
    """--sweep sets every numeric option, read from the parser that main() builds (stopped at parse_args), to
    nonsense values; nargs options get one value per argument."""
    trial = _trial_module()
    assert trial.numeric_options("ta-eval-rings") == [("--tolerance-px", float, None), ("--transect", int, None)]
    options = {flag: (kind, nargs) for flag, kind, nargs in trial.numeric_options("ta-fit-wood")}
    assert options["--lobe-shape"] == (int, 2) and options["--max-size"] == (int, None) and "--out" not in options
    cases = trial.sweep_cases("ta-eval-rings", {"detected": "d.csv", "labels": "l.csv"}, "/tmp/w")
    assert [args[-2:] for _, args, _ in cases] == [["--tolerance-px", v] for v in ("0", "nan", "1e12")] + \
        [["--transect", v] for v in ("0", "-1", str(10 ** 12))]
