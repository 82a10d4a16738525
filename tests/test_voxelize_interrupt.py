"""Ctrl-C during ta-voxelize (issue 49 §4): a real SIGINT to a real process while it renders its previews ends with
one line and exit 130, never a crash inside VTK, and leaves object.npz whole (or, before it was written, nothing)."""
import os
import signal
import subprocess
import sys
import time

import pytest

from torch_appearance.geometry.voxelize import VoxelObject
from torch_appearance.testing import command_argv, interrupt_when, sigint_default

SPOT = os.path.join(os.path.dirname(__file__), "data", "meshes", "spot")
pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="SIGINT to a child: POSIX")


def _command(out):
    return command_argv("voxelize", os.path.join(SPOT, "spot_triangulated.obj"), "--texture",
                        os.path.join(SPOT, "spot_texture.png"), "--height-mm", "10", "--quiet", "--out", out)


def _env():
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONUNBUFFERED="1")
    env.pop("TA_PREVIEW_BACKEND", None)  # pyvista/VTK where this machine renders offscreen
    return env


@pytest.mark.parametrize("delay_s", [0.0, 0.5, 2.0])
def test_ctrl_c_during_the_previews_ends_in_one_line(tmp_path, delay_s):
    """SIGINT ``delay_s`` after summary.json appears (the previews start right after it): exit 130, one line naming
    what is complete, object.npz loads, no temporary file left."""
    out = str(tmp_path / "vox")
    seen = []

    def ready():
        if not seen and os.path.exists(os.path.join(out, "summary.json")):
            seen.append(time.monotonic())
        return bool(seen) and time.monotonic() - seen[0] >= delay_s

    rc, stdout, err = interrupt_when(_command(out), ready, env=_env())
    assert rc == 130, (rc, err[-2000:])
    lines = err.strip().splitlines()
    assert lines == [f"ta-voxelize: interrupted; object.npz in {out} is complete, the previews are not "
                     f"(--no-previews skips them)"], err
    obj = VoxelObject.load(os.path.join(out, "object.npz"))
    assert len(obj.texel_points) > 1000
    assert not [name for name in os.listdir(out) if "tmp" in name or "partial" in name], os.listdir(out)
    assert stdout == ""


def test_ctrl_c_while_voxelising_leaves_nothing(tmp_path):
    """SIGINT once the progress lines say it voxelises (stderr to a file the test reads): exit 130, the progress
    lines then one line, and no --out folder."""
    out = str(tmp_path / "vox")
    log = tmp_path / "stderr.txt"
    command = [a for a in _command(out) if a != "--quiet"]
    with open(log, "w") as err_file:
        proc = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=err_file, text=True, env=_env(),
                                preexec_fn=sigint_default)
        deadline = time.monotonic() + 300
        while "voxelising at" not in log.read_text() and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.01)
        proc.send_signal(signal.SIGINT)
        proc.communicate(timeout=120)
    lines = log.read_text().strip().splitlines()
    assert proc.returncode == 130, lines[-20:]
    assert lines[-1] == "ta-voxelize: interrupted; nothing written (object.npz was not finished)", lines
    assert all(line.startswith("[voxelize") for line in lines[:-1]), lines
    assert not os.path.exists(out)
