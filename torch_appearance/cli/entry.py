"""The console-script entry points of the ``ta-…`` commands (setup.cfg ``[options.entry_points]``): one function per
command, which runs ``main()`` of its module in :mod:`torch_appearance.cli`.

Importing a command's module imports torch: seconds in which a Ctrl-C used to end in a ``KeyboardInterrupt``
traceback, before any of the command's code could catch it. This module, the package's ``__init__`` and
:mod:`torch_appearance.cli` import only the standard library (the package loads torch on first use), so the console
script gets here with torch not yet loaded; the command's module is then imported with Ctrl-C ending the process at
once, with one line and the exit status 130 (nothing has been written yet; no exception unwinds through a native
module being loaded); a ``KeyboardInterrupt`` that ``main()`` lets through ends the same way, and a Ctrl-C after
``main()`` has returned leaves its exit status as it is.

``python -m torch_appearance.cli.NAME`` runs ``main()`` without this module (for development): a Ctrl-C while it
imports torch is a traceback, and after a Ctrl-C that ``main()`` handled (one line, the cleanup done) the process may
still end killed by SIGINT instead of exiting with 130. CPython 3.11 marks a ``KeyboardInterrupt`` that leaves code
run from a string (``exec(text)``: dataclasses and namedtuple build their methods so) as unhandled even when a caller
catches it, and under ``-m`` ``Py_RunMain`` ends a marked process by SIGINT once it has shut down; a script file (the
installed console script) and ``python -c`` exit with their status first. A shell reports 130 either way, and a death
by SIGINT is what a calling shell script expects after Ctrl-C, so nothing undoes it (``os._exit`` would skip the
interpreter's shutdown). Tests run the commands as the console scripts do
(:func:`torch_appearance.testing.command_argv`).
"""
import importlib
import os
import signal
import sys
import threading

__all__ = ["optimize_print", "select_inks", "fit_wood", "voxelize", "render_object", "render_wood_volume",
           "detect_rings", "eval_rings", "export_print", "INTERRUPTED"]

#: exit status after Ctrl-C (128 + SIGINT), as torch_appearance.cli.command.INTERRUPTED
INTERRUPTED = 130


def _prog(name):
    return "ta-" + name.replace("_", "-")


def _import_main(name):
    """``main`` of ``torch_appearance.cli.<name>``, imported with SIGINT ending the process (one line, exit 130) where
    Python handles SIGINT (an ignored SIGINT, a background job's, stays ignored)."""
    previous = signal.getsignal(signal.SIGINT)
    if threading.current_thread() is not threading.main_thread() or previous is not signal.default_int_handler:
        return importlib.import_module(f"torch_appearance.cli.{name}").main

    def exit_now(signum, frame):
        os.write(2, f"{_prog(name)}: interrupted while starting; nothing was done\n".encode())
        os._exit(INTERRUPTED)

    signal.signal(signal.SIGINT, exit_now)
    try:
        return importlib.import_module(f"torch_appearance.cli.{name}").main
    finally:
        signal.signal(signal.SIGINT, previous)


def _run(name):
    """Run the command ``name`` (a module of torch_appearance.cli); returns its exit status. Once ``main()`` has
    returned (or exited), SIGINT is ignored: a Ctrl-C while the interpreter shuts down (torch's teardown takes a
    while; Python restores the default SIGINT for it) would kill the finished command and report it as
    interrupted."""
    main = _import_main(name)
    status = None
    try:
        try:
            status = main()
        finally:  # also when main() exits by SystemExit (argparse's --help and errors)
            _ignore_sigint()
    except KeyboardInterrupt:  # one that main() did not handle itself, or one that came as it returned
        _ignore_sigint()
        if status is None:
            print(f"{_prog(name)}: interrupted", file=sys.stderr)
            status = INTERRUPTED
    return status


def _ignore_sigint():
    if threading.current_thread() is threading.main_thread() and callable(signal.getsignal(signal.SIGINT)):
        signal.signal(signal.SIGINT, signal.SIG_IGN)


def optimize_print():
    """``ta-optimize-print``."""
    return _run("optimize_print")


def select_inks():
    """``ta-select-inks``."""
    return _run("select_inks")


def fit_wood():
    """``ta-fit-wood``."""
    return _run("fit_wood")


def voxelize():
    """``ta-voxelize``."""
    return _run("voxelize")


def render_object():
    """``ta-render-object``."""
    return _run("render_object")


def render_wood_volume():
    """``ta-render-wood-volume``."""
    return _run("render_wood_volume")


def detect_rings():
    """``ta-detect-rings``."""
    return _run("detect_rings")


def eval_rings():
    """``ta-eval-rings``."""
    return _run("eval_rings")


def export_print():
    """``ta-export-print``."""
    return _run("export_print")
