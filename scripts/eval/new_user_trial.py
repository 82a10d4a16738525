"""A new user's trial of every ``ta-…`` command (issue 49): bad input, Ctrl-C, two processes at once, ``ulimit -v``.

Every case is a real subprocess (the entry point of ``torch_appearance.cli.entry`` called by ``python -c``, as the
console script runs it; ``python -m`` may end in SIGINT after a handled Ctrl-C, see that module) on tiny inputs made
in a scratch folder (a 12×16 EXR print target, a synthetic board and core, Spot from tests/data), with
OMP_NUM_THREADS=1. The cases:

    ok           the tiny invocation itself (exit 0, its output complete); later cases reuse what it wrote
    missing      the input file does not exist
    corrupt      a truncated file (half of a real PNG, EXR, GLB, NPZ or JSON)
    wrong-type   a file of another kind (a text file named .png, a PNG as a mesh, another tool's folder)
    range        an out-of-range flag value
    out-proc     --out /proc/x (a place where no folder can be made)
    out-file     --out afile/sub (a file on the way)
    sigint       SIGINT once the command is working (every command that writes something)
    resume       after a SIGINT that left a resumable folder: the command that resumes it (ta-optimize-print
                 --resume; ta-select-inks the same command again) must end 0 with its output complete
    concurrent   two processes at once to one --out (every command that writes a folder)
    ulimit       ta-optimize-print of a 300² target 10 mm thick (about 4 GiB) under ``ulimit -v`` (import size + 2 GiB)
    help         ``--help`` (exit 0, a usage line on stdout)
    no-input     the command without any argument (where it needs one: exit 2, one line)
    numeric      with ``--sweep``: every numeric option of the command (read from its parser) set to nonsense values
                 (ints 0, -1, 10**12; floats 0, nan, 1e12; every value of an option with nargs) on the tiny
                 invocation; exit 0 is recorded as ``accepted`` for a person to judge (a seed of 0 is fine, a size of
                 0 is not), a run past ``SWEEP_TIMEOUT_S`` fails (work accepted without a word)

Recorded per case: the command line, the exit status, whether stderr holds a Python traceback, the last line of
stderr (the one-line message), the number of stderr lines, and the state of the output: ``absent``, ``complete``
(the command's result files all there, no temporary names left), ``resumable`` (a print run's checkpoint),
``as-before`` (an output that existed before the case, unchanged), ``partial`` (anything else) or ``n/a``.

A case passes when there is no traceback, no exit 1 (nor a signal's death), the status is 0 (success), 2 (refused
input, one line) or 130 (Ctrl-C), and no output is partial; two processes at once pass when one ran (exit 0) and the
other was refused (exit 2), leaving one complete output. Ctrl-C is sent a few seconds into the command's work (see
``SIGINT_AFTER``), so where a command ends sooner it is recorded as such ("finished before SIGINT").

Examples:
    python scripts/eval/new_user_trial.py --out scripts/eval/measured/new_user_trial
    python scripts/eval/new_user_trial.py --commands ta-render-object,ta-eval-rings --out /tmp/trial
"""
import argparse
import concurrent.futures
import datetime
import importlib.util
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
DATA = os.path.join(ROOT, "tests", "data")
SPOT_OBJ = os.path.join(DATA, "meshes", "spot", "spot_triangulated.obj")
SPOT_TEX = os.path.join(DATA, "meshes", "spot", "spot_texture.png")
BOX_GLB = os.path.join(DATA, "meshes", "BoxTextured.glb")
TRACEBACK = "Traceback (most recent call last)"
GiB = 1 << 30

#: console script -> module of torch_appearance.cli (setup.cfg's console_scripts)
COMMANDS = {
    "ta-optimize-print": "optimize_print", "ta-select-inks": "select_inks", "ta-fit-wood": "fit_wood",
    "ta-voxelize": "voxelize", "ta-render-object": "render_object", "ta-render-wood-volume": "render_wood_volume",
    "ta-detect-rings": "detect_rings", "ta-eval-rings": "eval_rings", "ta-export-print": "export_print",
}

#: the files a complete output holds (a folder), or "file" (one output file), or None (writes nothing)
COMPLETE = {
    "ta-optimize-print": ["summary.json", "config.json", "checkpoint.pt"],
    "ta-select-inks": ["summary.json", "ranking.csv", "ranking.json", "inks.json"],
    "ta-fit-wood": ["summary.json"],
    "ta-voxelize": ["object.npz", "summary.json"],
    "ta-render-object": ["render.png", "render.exr", "timings.json", "config.json"],
    "ta-render-wood-volume": ["summary.json", "figure.png"],
    "ta-export-print": ["export.json"],
    "ta-detect-rings": "file",
    "ta-eval-rings": None,
}

#: seconds after the command has imported (a first stderr line or file, or IMPORT_S) before SIGINT is sent
SIGINT_AFTER = 4.0
#: seconds a numeric-sweep case may run (the tiny invocations end within ~30 s on one thread)
SWEEP_TIMEOUT_S = 90
#: nonsense values of the numeric sweep, by the option's type
SWEEP_VALUES = {int: ["0", "-1", str(10 ** 12)], float: ["0", "nan", "1e12"]}
#: the commands that run without any argument (the rest need an input: exit 2 without one)
RUN_WITHOUT_ARGUMENTS = {"ta-optimize-print", "ta-select-inks", "ta-render-object", "ta-render-wood-volume"}


def _env():
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONUNBUFFERED="1", MPLBACKEND="Agg")
    env["PYTHONPATH"] = ROOT + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    return env


def _argv(command, args):
    """As torch_appearance.testing.command_argv (not imported here: the children import the package from ROOT)."""
    name = COMMANDS[command]
    code = f"import sys; from torch_appearance.cli.entry import {name}; sys.argv[0] = {command!r}; sys.exit({name}())"
    return [sys.executable, "-c", code, *[str(a) for a in args]]


def _sigint_default():
    signal.signal(signal.SIGINT, signal.SIG_DFL)


# ------------------------------------------------------------------------------------------------ inputs
def make_inputs(work):
    """The tiny inputs of every case, written under ``work``; returns their paths by name."""
    import cv2
    import numpy as np

    from torch_appearance import io as ta_io
    from torch_appearance.rings.synthetic import synthetic_board
    from torch_appearance.testing import tiny_print_target

    spec = importlib.util.spec_from_file_location("trial_dendro", os.path.join(ROOT, "tests", "test_dendro.py"))
    dendro = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(dendro)
    p = {}
    p["target"] = tiny_print_target(os.path.join(work, "target.exr"), 12, 16)
    p["big_target"] = tiny_print_target(os.path.join(work, "big_target.exr"), 300, 300)
    p["board"] = os.path.join(work, "board.png")
    ta_io.write_png(p["board"], synthetic_board(96, 96, 0.1, seed=3)["image"])
    rgb, _ = dendro.synthetic_core(dendro.ring_series(0, 30), seed=0)
    p["core"] = os.path.join(work, "core.png")
    cv2.imwrite(p["core"], (rgb[..., ::-1] * 255).astype(np.uint8))
    p["labels"] = os.path.join(work, "labels.csv")
    with open(p["labels"], "w") as handle:
        handle.write("index,x_px,y_px\n0,40,24\n1,80,24\n")

    def truncated(src, name):
        with open(src, "rb") as handle:
            data = handle.read()
        path = os.path.join(work, name)
        with open(path, "wb") as handle:
            handle.write(data[: len(data) // 2])
        return path

    p["png_half"] = truncated(p["board"], "board_half.png")
    p["core_half"] = truncated(p["core"], "core_half.png")
    p["exr_half"] = truncated(p["target"], "target_half.exr")
    p["glb_half"] = truncated(BOX_GLB, "box_half.glb")
    p["text_png"] = os.path.join(work, "notes.png")
    with open(p["text_png"], "w") as handle:
        handle.write("this is a text file, not an image\n")
    p["binary_csv"] = os.path.join(work, "garbage.csv")
    with open(p["binary_csv"], "wb") as handle:
        handle.write(bytes(range(256)) * 4)
    p["afile"] = os.path.join(work, "afile")
    with open(p["afile"], "w") as handle:
        handle.write("a file on the way of --out\n")
    return p


def tiny(command, out, p, seed=0, long=False):
    """The tiny successful invocation of ``command`` writing ``out``; ``long``: one that works for a while (for
    SIGINT); a ``seed`` (two processes at once): the renders a little longer, so that the two overlap."""
    if command == "ta-optimize-print":
        return ["--target", p["target"], "--thickness-mm", "0.34", "--spp", "2", "--eval-spp", "4", "--iterations",
                "400" if long else "4", "--eval-every", "2", "--table-steps", "2", "--threads", "1", "--seed", seed,
                "--quiet", "--out", out]
    if command == "ta-select-inks":
        return ["--target", "colorchecker", "--width-mm", "1.5", "--dpi", "100", "--thickness-mm", "0.5",
                "--candidates", "cyan,yellow", "-k", "1", "--iterations", "200" if long else "3", "--spp", "2",
                "--eval-spp", "4", "--eval-every", "2", "--table-steps", "2", "--seed", seed, "--threads", "1",
                "--quiet", "--out", out]
    if command == "ta-fit-wood":
        return [p["board"], "--epochs", "100000" if long else "3", "--color-epochs", "2", "--p", "8", "--q", "8",
                "--coarse-to-fine", "1", "--seed", seed, "--no-preview", "--quiet", "--out", out]
    if command == "ta-voxelize":  # the long one renders its previews (SIGINT lands in them or in the voxelising)
        return [SPOT_OBJ, "--texture", SPOT_TEX, "--height-mm", "10" if long else "5", "--dpi", "300" if long else
                "100", *([] if long else ["--no-previews"]), "--quiet", "--out", out]
    if command == "ta-render-object":
        return ["--size", "64" if long else "12", "--spp", "512" if long else "64" if seed else "2", "--voxel-size",
                "0.5", "--seed",
                seed, "--out", out]
    if command == "ta-render-wood-volume":
        return ["--synthetic", "3", "--synthetic-size", "32", "40", "--veneer-max-mm", "3", "--veneer-voxel-mm",
                "0.3", "0.3", "--shade", "4", "2", "4", "1", "--shade-voxel-mm", "0.5", "--shade-resolution", "12",
                "12", "--spp", "256" if long else "32" if seed else "2", "--shade-spp", "2", "--passes", "4" if long else "1", "--seed",
                seed, "--threads", "1", "--quiet", "--out", out]
    if command == "ta-detect-rings":
        return [p["core"], "--bark", "right", "--dpi", "2540", "--out", out]
    if command == "ta-eval-rings":
        return [p["detected"], p["labels"], "--tolerance-px", "3"]
    if command == "ta-export-print":
        return [p["run"], "--printer", "generic", "--format", "slices,3mf", "--quiet", "--out", out]
    raise KeyError(command)


def bad_cases(command, p, w):
    """(case, argv after the command, the output path the case would write or None)."""
    o = lambda name: os.path.join(w, f"{COMMANDS[command]}_{name}")  # noqa: E731
    outs = [("out-proc", "/proc/x"), ("out-file", os.path.join(p["afile"], "sub"))]
    if command == "ta-detect-rings":
        outs = [("out-proc", "/proc/x.csv"), ("out-file", os.path.join(p["afile"], "sub.csv"))]
    cases = []
    if command == "ta-optimize-print":
        base = lambda out: ["--thickness-mm", "0.34", "--spp", "2", "--iterations", "4", "--quiet", "--out", out]  # noqa
        cases += [("missing", ["--target", "missing.png", *base(o("missing"))], o("missing")),
                  ("corrupt", ["--target", p["exr_half"], *base(o("corrupt"))], o("corrupt")),
                  ("wrong-type", ["--target", p["text_png"], *base(o("wrong"))], o("wrong")),
                  ("wrong-type", ["--mesh", p["board"], "--height-mm", "5", *base(o("wrong2"))], o("wrong2")),
                  ("range", ["--target", p["target"], "--thickness-mm", "-1", "--quiet", "--out", o("range")],
                   o("range")),
                  ("range", ["--target", p["target"], "--iterations", "1000000000000", "--quiet", "--out",
                             o("range2")], o("range2")),
                  ("resume-none", ["--out", o("none"), "--resume", "--quiet"], o("none"))]
        cases += [(c, ["--target", p["target"], *base(out)], out) for c, out in outs]
    elif command == "ta-select-inks":
        base = lambda out: ["--width-mm", "1.5", "--dpi", "100", "--candidates", "cyan,yellow", "-k", "1",  # noqa
                            "--iterations", "3", "--quiet", "--out", out]
        cases += [("missing", ["--target", "missing.png", *base(o("missing"))], o("missing")),
                  ("corrupt", ["--target", p["png_half"], *base(o("corrupt"))], o("corrupt")),
                  ("wrong-type", ["--target", p["text_png"], *base(o("wrong"))], o("wrong")),
                  ("wrong-type", ["--target", "colorchecker", "--user-inks", p["png_half"], *base(o("wrong2"))],
                   o("wrong2")),
                  ("range", ["--target", "colorchecker", "--width-mm", "1.5", "--candidates", "cyan,yellow", "-k",
                             "5", "--quiet", "--out", o("range")], o("range"))]
        cases += [(c, ["--target", "colorchecker", *base(out)], out) for c, out in outs]
    elif command == "ta-fit-wood":
        base = lambda out: ["--epochs", "3", "--no-preview", "--quiet", "--out", out]  # noqa: E731
        cases += [("missing", ["missing.png", *base(o("missing"))], o("missing")),
                  ("corrupt", [p["png_half"], *base(o("corrupt"))], o("corrupt")),
                  ("wrong-type", [p["text_png"], *base(o("wrong"))], o("wrong")),
                  ("range", [p["board"], "--epochs", "-3", "--no-preview", "--quiet", "--out", o("range")],
                   o("range")),
                  ("range", [p["board"], "--dpi", "0", "--no-preview", "--quiet", "--out", o("range2")], o("range2"))]
        cases += [(c, [p["board"], *base(out)], out) for c, out in outs]
    elif command == "ta-voxelize":
        base = lambda out: ["--height-mm", "5", "--dpi", "100", "--no-previews", "--quiet", "--out", out]  # noqa
        cases += [("missing", ["missing.obj", *base(o("missing"))], o("missing")),
                  ("corrupt", [p["glb_half"], *base(o("corrupt"))], o("corrupt")),
                  ("wrong-type", [p["board"], *base(o("wrong"))], o("wrong")),
                  ("range", [SPOT_OBJ, "--height-mm", "5", "--dpi", "-100", "--out", o("range")], o("range")),
                  ("range", [SPOT_OBJ, "--height-mm", "5000", "--out", o("range2")], o("range2"))]
        cases += [(c, [SPOT_OBJ, "--texture", SPOT_TEX, *base(out)], out) for c, out in outs]
    elif command == "ta-render-object":
        base = lambda out: ["--size", "12", "--spp", "2", "--voxel-size", "0.5", "--out", out]  # noqa: E731
        cases += [("missing", ["--envmap", "missing.exr", *base(o("missing"))], o("missing")),
                  ("corrupt", ["--envmap", p["exr_half"], *base(o("corrupt"))], o("corrupt")),
                  ("wrong-type", ["--envmap", p["board"], *base(o("wrong"))], o("wrong")),
                  ("range", ["--ior", "0.5", *base(o("range"))], o("range")),
                  ("range", ["--voxel-size", "0.001", "--out", o("range2")], o("range2")),
                  ("range", ["--size", "-4", "--out", o("range3")], o("range3"))]
        cases += [(c, base(out), out) for c, out in outs]
    elif command == "ta-render-wood-volume":
        base = lambda out: ["--spp", "2", "--passes", "1", "--quiet", "--out", out]  # noqa: E731
        cases += [("missing", [os.path.join(w, "no_fit"), *base(o("missing"))], o("missing")),
                  ("corrupt", [p["fit_corrupt"], *base(o("corrupt"))], o("corrupt")),
                  ("wrong-type", [p["run"], *base(o("wrong"))], o("wrong")),
                  ("range", ["--synthetic", "3", "--spp", "0", "--out", o("range")], o("range")),
                  ("range", ["--synthetic", "3", "--thickness-mm", "-1", "--out", o("range2")], o("range2"))]
        cases += [(c, ["--synthetic", "3", *base(out)], out) for c, out in outs]
    elif command == "ta-detect-rings":
        csv = lambda name: o(name) + ".csv"  # noqa: E731
        cases += [("missing", ["missing.png", "--out", csv("missing")], csv("missing")),
                  ("corrupt", [p["core_half"], "--out", csv("corrupt")], csv("corrupt")),
                  ("wrong-type", [p["text_png"], "--out", csv("wrong")], csv("wrong")),
                  ("range", [p["core"], "--dpi", "-5", "--out", csv("range")], csv("range")),
                  ("range", [p["core"], "--width-px", "100000", "--out", csv("range2")], csv("range2"))]
        cases += [(c, [p["core"], "--bark", "right", "--out", out], out) for c, out in outs]
    elif command == "ta-eval-rings":
        cases += [("missing", ["missing.csv", p["labels"]], None),
                  ("corrupt", [p["detected"], p["binary_csv"]], None),
                  ("wrong-type", [p["core"], p["labels"]], None),
                  ("range", [p["detected"], p["labels"], "--tolerance-px", "-1"], None),
                  ("range", [p["detected"], p["labels"], "--transect", "99"], None)]
    elif command == "ta-export-print":
        base = lambda out: ["--printer", "generic", "--format", "slices", "--quiet", "--out", out]  # noqa: E731
        cases += [("missing", [os.path.join(w, "no_run"), *base(o("missing"))], o("missing")),
                  ("corrupt", [p["run_corrupt"], *base(o("corrupt"))], o("corrupt")),
                  ("wrong-type", [p["fit"], *base(o("wrong"))], o("wrong")),
                  ("wrong-type", [p["run"], "--printer", p["board"], "--out", o("wrong2")], o("wrong2")),
                  ("range", [p["run"], "--format", "stl", "--out", o("range")], o("range")),
                  ("exists", [p["run"], *base(p["package"])], p["package"])]
        cases += [(c, [p["run"], *base(out)], out) for c, out in outs]
    return cases


def numeric_options(command):
    """``[(flag, type, nargs)]`` of every option of ``command`` that takes numbers (its parser, as ``main`` builds
    it: ``main`` is run up to ``parse_args``, which is stopped)."""
    import importlib

    from torch_appearance.cli.command import CommandParser

    class _Built(Exception):
        pass

    module = importlib.import_module(f"torch_appearance.cli.{COMMANDS[command]}")
    original = CommandParser.parse_args

    def stop(self, *args, **kwargs):
        raise _Built(self)

    CommandParser.parse_args = stop
    try:
        module.main([])
    except _Built as built:
        parser = built.args[0]
    finally:
        CommandParser.parse_args = original
    options = []
    for action in parser._actions:
        kind = action.type if action.type in (int, float) else None
        if kind is None or not action.option_strings:
            continue
        options.append((action.option_strings[-1], kind, action.nargs))
    return options


def sweep_cases(command, p, w):
    """(case, argv, out) of the numeric sweep of ``command``: its tiny invocation with one numeric option set to
    each of :data:`SWEEP_VALUES` (the last of a repeated option wins in argparse)."""
    cases = []
    for flag, kind, nargs in numeric_options(command):
        count = nargs if isinstance(nargs, int) else 1
        for value in SWEEP_VALUES[kind]:
            name = f"{COMMANDS[command]}_sweep{flag.replace('-', '_')}_{value.replace('.', '')}"
            out = os.path.join(w, name + (".csv" if command == "ta-detect-rings" else ""))
            cases.append(("numeric", [*tiny(command, out, p), flag, *[value] * count], out))
    return cases


# ------------------------------------------------------------------------------------------------ one case
def output_state(command, path, before=None):
    """``absent``, ``complete``, ``resumable``, ``as-before``, ``partial`` or ``n/a`` (see the module's doc)."""
    kind = COMPLETE[command]
    if path is None or kind is None:
        return "n/a"
    if path.startswith("/proc/"):
        return "absent" if not os.path.exists(path) else "partial"
    if before is not None and _listing(path) == before:
        return "as-before"
    if not os.path.exists(path):
        return "absent"
    if kind == "file":
        if not os.path.isfile(path):
            return "partial"
        with open(path, errors="replace") as handle:
            return "complete" if handle.readline().startswith("index,") else "partial"
    if not os.path.isdir(path):
        return "partial"
    names = os.listdir(path)
    leftovers = [n for n in names if "tmp" in n.lower() or "partial" in n.lower() or n.startswith(".ta-")]
    if leftovers:
        return "partial"
    if all(n in names for n in kind):
        return "complete"
    if command == "ta-optimize-print" and "checkpoint.pt" in names and "config.json" in names:
        return "resumable"
    if command == "ta-select-inks" and "runs" in names and "summary.json" not in names:
        return "resumable"  # finished sets keep their summary.json, the running one its checkpoint
    return "partial"


def _listing(path):
    if path is None or not os.path.exists(path):
        return None
    if os.path.isfile(path):
        st = os.stat(path)
        return {"": (st.st_ino, st.st_size, st.st_mtime_ns)}
    out = {}
    for base, _, files in os.walk(path):
        for name in files:
            st = os.stat(os.path.join(base, name))
            out[os.path.relpath(os.path.join(base, name), path)] = (st.st_ino, st.st_size, st.st_mtime_ns)
    return out


def _message(err):
    lines = [line for line in err.splitlines() if line.strip()]
    return (lines[-1] if lines else ""), len(lines)


def _record(command, case, args, out, rc, err, before=None, note=""):
    message, n_lines = _message(err)
    state = output_state(command, out, before)
    if rc == 0 and state == "as-before" and COMPLETE[command] not in (None,):
        state = output_state(command, out)  # a success that rewrote nothing: judge what is there
    tb = TRACEBACK in err
    problems = []
    if tb:
        problems.append("traceback")
    if not isinstance(rc, int) or rc not in (0, 2, 130):
        problems.append(f"exit {rc}")
    if rc == 2 and n_lines != 1:
        problems.append(f"{n_lines} stderr lines")
    if state == "partial":
        problems.append("partial output")
    if rc == 0 and state == "absent" and COMPLETE[command] is not None:
        problems.append("exit 0 without output")
    if case not in ("ok", "sigint", "resume", "concurrent", "help", "numeric") and rc == 0:
        problems.append("bad input accepted")
    if case == "numeric" and rc == 0:
        note = (note + "; " if note else "") + "accepted"
    if case == "help" and rc == 0:
        problems = [p for p in problems if p != "exit 0 without output"]
    return {"command": command, "case": case, "argv": [str(a) for a in args], "exit": rc, "traceback": tb,
            "message": message, "stderr_lines": n_lines, "output": state, "note": note,
            "pass": not problems, "problems": problems}


def run_case(command, case, args, out, timeout_s=240, preexec=None, wrap=None):
    before = _listing(out)
    argv = _argv(command, args)
    if wrap:
        argv = wrap(argv)
    t0 = time.monotonic()
    stdout = ""
    try:
        proc = subprocess.run(argv, capture_output=True, text=True, env=_env(), timeout=timeout_s,
                              preexec_fn=preexec or _sigint_default, stdin=subprocess.DEVNULL)
        rc, err, stdout = proc.returncode, proc.stderr, proc.stdout
    except subprocess.TimeoutExpired as expired:
        rc, err = "timeout", (expired.stderr or b"").decode(errors="replace") if isinstance(expired.stderr, bytes) \
            else (expired.stderr or "")
    rec = _record(command, case, args, out, rc, err, before)
    if case == "help" and not (rc == 0 and stdout.startswith(f"usage: {command} ")):
        rec["problems"].append("no usage on stdout")
        rec["pass"] = False
    rec["seconds"] = round(time.monotonic() - t0, 1)
    return rec


def run_sigint(command, args, out, ready_file=None):
    """Start the command, send SIGINT once it works: ``ready_file`` (under ``out``) exists, or else SIGINT_AFTER
    seconds after its first stderr output or file in ``out`` (or 15 s)."""
    before = _listing(out)
    with tempfile.TemporaryFile("w+") as err_file:
        proc = subprocess.Popen(_argv(command, args), stdout=subprocess.DEVNULL, stderr=err_file, text=True,
                                env=_env(), preexec_fn=_sigint_default, stdin=subprocess.DEVNULL)
        t0 = time.monotonic()
        started = None
        while proc.poll() is None and time.monotonic() - t0 < 300:
            if ready_file:
                if os.path.exists(os.path.join(out, ready_file)):
                    break
            else:
                if started is None and (os.fstat(err_file.fileno()).st_size > 0 or
                                        (os.path.isdir(out) and os.listdir(out)) or time.monotonic() - t0 > 15):
                    started = time.monotonic()
                if started is not None and time.monotonic() - started >= SIGINT_AFTER:
                    break
            time.sleep(0.05)
        finished = proc.poll() is not None
        sent = round(time.monotonic() - t0, 1)
        if not finished:
            proc.send_signal(signal.SIGINT)
        try:
            rc = proc.wait(timeout=300)
        except subprocess.TimeoutExpired:
            proc.kill()
            rc = "timeout"
        err_file.seek(0)
        err = err_file.read()
    note = "finished before SIGINT" if finished else f"SIGINT at {sent} s"
    rec = _record(command, "sigint", args, out, rc, err, before, note)
    if not finished and rc == 0:
        rec["note"] += "; ended 0 (the signal came after its work)"
    rec["seconds"] = round(time.monotonic() - t0, 1)
    return rec


def run_concurrent(command, args_pair, out):
    t0 = time.monotonic()
    procs = [subprocess.Popen(_argv(command, a), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                              env=_env(), preexec_fn=_sigint_default, stdin=subprocess.DEVNULL) for a in args_pair]
    results = []
    for proc in procs:
        try:
            _, err = proc.communicate(timeout=600)
            results.append((proc.returncode, err))
        except subprocess.TimeoutExpired:
            proc.kill()
            results.append(("timeout", proc.communicate()[1]))
    codes = [rc for rc, _ in results]
    refused = [err for rc, err in results if rc != 0]
    err = refused[0] if refused else results[1][1]
    rc = 2 if sorted(map(str, codes)) == ["0", "2"] else (codes[0] if codes[0] != 0 else codes[1])
    rec = _record(command, "concurrent", args_pair[1], out, rc, err, None, f"exit statuses {codes}")
    if codes == [0, 0]:
        rec["problems"].append("both exit 0: the later replaced the earlier's output")
        rec["pass"] = False
        rec["message"] = _message(results[1][1])[0]
    for code, e in results:
        if TRACEBACK in e and "traceback" not in rec["problems"]:
            rec["problems"].append("traceback")
            rec["pass"] = False
            rec["traceback"] = True
    rec["seconds"] = round(time.monotonic() - t0, 1)
    return rec


def _mapped_after_import(module):
    code = (f"import torch_appearance.cli.{module}\n"
            "print([int(l.split()[1]) for l in open('/proc/self/status') if l.startswith('VmSize:')][0] * 1024)")
    return int(subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                              env=_env()).stdout)


# ------------------------------------------------------------------------------------------------ the trial
def trial(commands, work, jobs=2, log=print, sweep=False):
    p = make_inputs(work)
    w = os.path.join(work, "outs")
    os.makedirs(w)
    records = []

    def add(rec):
        records.append(rec)
        log(f"{'ok  ' if rec['pass'] else 'FAIL'} {rec['command']:<22} {rec['case']:<11} exit {rec['exit']!s:<4} "
            f"{rec['output']:<9} {rec.get('seconds', '')}s  {rec['message'][:110]}")

    # the successful runs first: later cases read what they wrote
    order = ["ta-optimize-print", "ta-fit-wood", "ta-detect-rings", "ta-voxelize", "ta-render-object",
             "ta-render-wood-volume", "ta-select-inks", "ta-export-print", "ta-eval-rings"]
    needs = {"ta-export-print": ["ta-optimize-print", "ta-fit-wood"], "ta-eval-rings": ["ta-detect-rings"],
             "ta-render-wood-volume": ["ta-optimize-print", "ta-fit-wood"]}
    wanted = [c for c in order if c in commands]
    setup = set(wanted) | {n for c in wanted for n in needs.get(c, [])}
    for command in [c for c in order if c in setup]:
        out = os.path.join(w, COMMANDS[command] + "_ok" + (".csv" if command == "ta-detect-rings" else ""))
        if command == "ta-export-print":
            out = p["package"] = os.path.join(w, "package")
        rec = run_case(command, "ok", tiny(command, out, p), out)
        if command in wanted:
            add(rec)
        if command == "ta-optimize-print":
            p["run"] = out
            p["run_corrupt"] = os.path.join(work, "run_corrupt")
            shutil.copytree(out, p["run_corrupt"])
            q = os.path.join(p["run_corrupt"], "quantized.npz")
            with open(q, "rb") as handle:
                data = handle.read()
            with open(q, "wb") as handle:
                handle.write(data[: len(data) // 2])
        if command == "ta-fit-wood":
            p["fit"] = out
            p["fit_corrupt"] = os.path.join(work, "fit_corrupt")
            shutil.copytree(out, p["fit_corrupt"])
            for name in ("model.json", "params.json"):
                path = os.path.join(p["fit_corrupt"], name)
                if os.path.exists(path):
                    with open(path) as handle:
                        text = handle.read()
                    with open(path, "w") as handle:
                        handle.write(text[: len(text) // 2])
        if command == "ta-detect-rings":
            p["detected"] = out

    cases = [(c, case, args, out) for c in wanted for case, args, out in bad_cases(c, p, w)]
    cases += [(c, "help", ["--help"], None) for c in wanted]
    cases += [(c, "no-input", [], None) for c in wanted if c not in RUN_WITHOUT_ARGUMENTS]
    slow = []
    if sweep:
        slow = [(c, case, args, out, SWEEP_TIMEOUT_S) for c in wanted for case, args, out in sweep_cases(c, p, w)]
    with concurrent.futures.ThreadPoolExecutor(max_workers=max(1, jobs)) as pool:
        for future in concurrent.futures.as_completed([pool.submit(run_case, *c) for c in cases + slow]):
            add(future.result())  # as they end: one slow case does not hold back the log

    ready = {"ta-optimize-print": "checkpoint.pt", "ta-voxelize": "summary.json"}
    for command in wanted:
        if COMPLETE[command] is None:
            continue
        out = os.path.join(w, COMMANDS[command] + "_sigint" + (".csv" if command == "ta-detect-rings" else ""))
        args = tiny(command, out, p, long=True)
        rec = run_sigint(command, args, out, ready.get(command))
        add(rec)
        if rec["output"] == "resumable":  # what the message promises: the command that resumes it ends complete
            resumed = run_case(command, "resume", [*args, "--resume"] if command == "ta-optimize-print" else args,
                               out, timeout_s=600)
            if resumed["exit"] == 0 and resumed["output"] != "complete":
                resumed["pass"] = False
                resumed["problems"].append(f"output {resumed['output']} after the resume")
            add(resumed)

    for command in wanted:
        if COMPLETE[command] in (None, "file"):
            continue
        out = os.path.join(w, COMMANDS[command] + "_two")
        add(run_concurrent(command, [tiny(command, out, p, seed=1), tiny(command, out, p, seed=2)], out))

    limit = None
    for command, args in [("ta-optimize-print", ["--target", p["big_target"], "--thickness-mm", "10", "--quiet"])]:
        if command not in wanted:
            continue
        limit = _mapped_after_import(COMMANDS[command]) + 2 * GiB
        out = os.path.join(w, COMMANDS[command] + "_ulimit")
        kb = limit // 1024
        rec = run_case(command, "ulimit", [*args, "--out", out], out,
                       wrap=lambda argv: ["bash", "-c", f'ulimit -v {kb} && exec "$@"', "bash", *argv])
        rec["note"] = f"ulimit -v {kb} (import + 2 GiB)"
        add(rec)
    return records


def markdown(records, meta):
    lines = [f"# New-user trial of every ta- command ({meta['date']}, {meta['commit']})", "",
             f"{meta['passed']}/{meta['cases']} cases pass (no traceback, no exit 1, exit 0/2/130, one line when "
             f"refused, nothing partial). Run: `{meta['run']}`; {meta['seconds']:.0f} s on {meta['machine']}.", "",
             "| command | case | exit | traceback | output | pass | message (last stderr line) |",
             "|---|---|---|---|---|---|---|"]
    for r in records:
        message = r["message"].replace("|", "\\|")
        if len(message) > 160:
            message = message[:157] + "..."
        note = f" ({r['note']})" if r.get("note") else ""
        verdict = "yes" if r["pass"] else "**no**: " + ", ".join(r["problems"])
        lines.append(f"| {r['command']} | {r['case']}{note} | {r['exit']} | {'yes' if r['traceback'] else 'no'} | "
                     f"{r['output']} | {verdict} | {message} |")
    return "\n".join(lines) + "\n"


def main(argv=None):
    head, _, rest = __doc__.partition("\n\n")
    p = argparse.ArgumentParser(description=head, epilog=rest, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", required=True, help="folder for trial.json and trial.md")
    p.add_argument("--commands", default=",".join(COMMANDS), help="comma-separated ta- commands (default: all)")
    p.add_argument("--jobs", type=int, default=2, help="bad-input cases run at once (default: 2)")
    p.add_argument("--keep", action="store_true", help="keep the scratch folder (its path is printed)")
    p.add_argument("--sweep", action="store_true", help="also set every numeric option to nonsense values (slow: "
                                                        "three runs per option)")
    args = p.parse_args(argv)
    commands = [c.strip() for c in args.commands.split(",") if c.strip()]
    unknown = [c for c in commands if c not in COMMANDS]
    if unknown:
        p.error(f"--commands: unknown {unknown}; expected some of {list(COMMANDS)}")
    os.makedirs(args.out, exist_ok=True)
    # the commit under trial, read before the first case (a commit made while it runs is not what it tried), and
    # whether the working tree differed from it
    commit = subprocess.run(["git", "-C", ROOT, "rev-parse", "--short", "HEAD"], capture_output=True,
                            text=True).stdout.strip()
    dirty = subprocess.run(["git", "-C", ROOT, "status", "--porcelain", "--untracked-files=no"], capture_output=True,
                           text=True).stdout.strip()
    commit += " with uncommitted changes" if dirty else ""
    work = tempfile.mkdtemp(prefix="ta-trial-")
    t0 = time.monotonic()
    try:
        records = trial(commands, work, args.jobs, log=lambda s: print(s, flush=True), sweep=args.sweep)
    finally:
        if args.keep:
            print(f"scratch folder: {work}")
        else:
            shutil.rmtree(work, ignore_errors=True)
    meta = {"date": datetime.date.today().isoformat(), "commit": commit, "cases": len(records),
            "passed": sum(r["pass"] for r in records), "seconds": time.monotonic() - t0,
            "machine": f"{os.cpu_count()} CPUs, OMP_NUM_THREADS=1",
            "run": "python scripts/eval/new_user_trial.py " + " ".join(argv if argv is not None else sys.argv[1:])}
    with open(os.path.join(args.out, "trial.json"), "w") as handle:
        json.dump({"meta": meta, "records": records}, handle, indent=1)
    with open(os.path.join(args.out, "trial.md"), "w") as handle:
        handle.write(markdown(records, meta))
    print(f"{meta['passed']}/{meta['cases']} cases pass -> {args.out}/trial.md")
    return 0


if __name__ == "__main__":
    sys.exit(main())
