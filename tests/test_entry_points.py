"""Ctrl-C at the very start of any ``ta-…`` command (issue 49 §6): while the command imports torch it ends with one
line and exit 130, never a ``KeyboardInterrupt`` traceback. The console scripts run ``torch_appearance.cli.entry``,
which with the package's ``__init__`` imports only the standard library (torch loads on first use); a real SIGINT
goes to a real child as soon as torch's library is mapped into it (read from /proc/PID/maps, so the signal lands
inside the imports), and then at later moments."""
import os
import signal
import subprocess
import sys
import time

import pytest

from test_commands import COMMANDS, console_script
from torch_appearance.testing import sigint_default

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="SIGINT to a child, /proc/PID/maps")


def _importing_torch(pid):
    """True once libtorch is mapped into the process ``pid`` (it is inside ``import torch``)."""
    try:
        with open(f"/proc/{pid}/maps") as maps:
            return "libtorch" in maps.read()
    except OSError:
        return False


def _interrupt(argv, delay_s=None):
    """Start ``argv``, send SIGINT ``delay_s`` seconds after torch's library is mapped into it (None: no signal);
    (status, stderr, seconds from the mapping to the end)."""
    env = dict(os.environ, OMP_NUM_THREADS="1")
    proc = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=env,
                            preexec_fn=sigint_default)
    deadline = time.monotonic() + 120
    while not _importing_torch(proc.pid) and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.002)
    mapped = time.monotonic()
    if delay_s is not None:
        time.sleep(delay_s)
        proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    return proc.returncode, err, time.monotonic() - mapped


@pytest.mark.parametrize("name", sorted(COMMANDS))
def test_ctrl_c_while_a_command_imports_is_one_line(name):
    """SIGINT as torch loads: exit 130 and one line (it was a traceback and exit -2)."""
    rc, err, _ = _interrupt(console_script(name) + ["--help"], 0.0)
    assert "Traceback" not in err, err
    assert rc == 130 and err == f"{name}: interrupted while starting; nothing was done\n", (rc, err)


def test_ctrl_c_at_later_moments_is_never_a_traceback():
    """SIGINT at increasing delays after torch starts loading, through the imports (and, near the end, main()'s
    --help): exit 130 with one line while it runs, or 0 when --help was done before the signal came; never a
    traceback. The delays are fractions of the time the command takes here without a signal."""
    name = "ta-fit-wood"
    rc, err, whole_s = _interrupt(console_script(name) + ["--help"])
    assert rc == 0 and err == "", err
    outcomes = []
    for fraction in (0.0, 0.3, 0.6, 0.9, 0.98, 1.5):
        rc, err, _ = _interrupt(console_script(name) + ["--help"], fraction * whole_s)
        assert "Traceback" not in err and err.count("\n") <= 1, (fraction, rc, err)
        assert (rc, err) in ((0, ""), (130, f"{name}: interrupted while starting; nothing was done\n"),
                             (130, f"{name}: interrupted\n")), (fraction, rc, err)
        outcomes.append(rc)
    assert outcomes[0] == 130, outcomes


def test_a_ctrl_c_that_main_lets_through_is_one_line(monkeypatch, capsys):
    from torch_appearance.cli import entry

    def main():
        raise KeyboardInterrupt

    monkeypatch.setattr(entry, "_import_main", lambda name: main)
    previous = signal.getsignal(signal.SIGINT)
    try:
        assert entry.fit_wood() == 130
        assert signal.getsignal(signal.SIGINT) == signal.SIG_IGN  # what a console script does once main() is done
    finally:  # not this test session's Ctrl-C (nor its children's, which would inherit SIG_IGN)
        signal.signal(signal.SIGINT, previous)
    assert capsys.readouterr().err == "ta-fit-wood: interrupted\n"


def test_the_entry_module_imports_no_torch():
    """torch_appearance.cli.entry, and with it the package and torch_appearance.cli, import only the standard library
    (else a Ctrl-C could land in torch before the entry's handler) and leave SIGINT as Python sets it."""
    code = ("import signal, sys, torch_appearance.cli.entry; "
            "print(sorted(m for m in sys.modules if m.split('.')[0] in ('torch', 'numpy'))[:3]); "
            "print(sorted(m for m in sys.modules if m.split('.')[0] == 'torch_appearance')); "
            "print(signal.getsignal(signal.SIGINT) is signal.default_int_handler)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60,
                         preexec_fn=sigint_default)
    assert out.returncode == 0, out.stderr
    assert out.stdout.splitlines() == [
        "[]", str(["torch_appearance", "torch_appearance.cli", "torch_appearance.cli.entry"]), "True"], out.stdout


def test_a_ctrl_c_handled_after_code_run_from_a_string_exits_130():
    """A command that handles a Ctrl-C which first left code run from a string (``exec(text)``, as dataclasses and
    namedtuple run it) exits with 130 as a console script: CPython 3.11 marks such an interrupt as unhandled, and
    ``python -m`` would then end the process by SIGINT (exit -2) after the command had printed its line."""
    code = """
import sys
from torch_appearance.cli import entry

def main():
    try:
        exec("raise KeyboardInterrupt", {})
    except KeyboardInterrupt:
        print("ta-fit-wood: interrupted; nothing was written", file=sys.stderr)
        return entry.INTERRUPTED

entry._import_main = lambda name: main
sys.argv[0] = "ta-fit-wood"
sys.exit(entry.fit_wood())
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60,
                         preexec_fn=sigint_default)
    assert (out.returncode, out.stderr) == (130, "ta-fit-wood: interrupted; nothing was written\n"), out
