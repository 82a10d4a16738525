"""Helpers for testing code built on torch_appearance (as ``torch.testing`` and ``torch_scatter.testing``): z-tests of
Monte Carlo estimates, statistics over seeds, the walk this CPU runs, memory probes, running a ``ta-…`` command
in-process, and interrupting one in a child process as Ctrl-C would.

Monte Carlo results are tested statistically (DESIGN.md, "How correctness is shown"): an estimate with its standard
error is compared with an expected value by a z-test, with a Bonferroni correction when many entries are tested at
once, so a family of tests fails by chance with probability ``family_alpha``.

Example:
    >>> import torch
    >>> from torch_appearance.testing import assert_z, seed_stats
    >>> mean, se = seed_stats(lambda s: torch.rand(4, generator=torch.Generator().manual_seed(s)), range(400))
    >>> assert_z(mean, se, 0.5, what="uniform mean") < bonferroni_z(4)
    True
"""
import contextlib
import importlib
import io
import math
import signal
import subprocess
import sys
import time
import warnings

import torch

__all__ = ["bonferroni_z", "seed_stats", "assert_z", "simd_walk_level", "status_kb", "reset_peak_rss",
           "tiny_print_target", "run_command", "command_argv", "sigint_default", "address_space_limit",
           "interrupt_when", "run_stiff_case", "SIGMAS", "ALBEDOS", "GS", "IORS", "THICKNESS"]


def bonferroni_z(n_tests, family_alpha=1e-3):
    """Two-sided z threshold for ``n_tests`` simultaneous tests at family-wise error ``family_alpha``.

    Example:
        >>> round(bonferroni_z(1, 0.05), 3)
        1.96
    """
    from scipy.stats import norm
    return float(norm.isf(family_alpha / (2 * n_tests)))


def seed_stats(fn, seeds):
    """Mean and standard error over independent seeds of ``fn(seed) -> tensor`` (float64, the shape of one result)."""
    xs = torch.stack([fn(s).double() for s in seeds])
    return xs.mean(0), xs.std(0, unbiased=True) / math.sqrt(len(seeds))


def assert_z(estimate, stderr, expected, *, n_tests=None, family_alpha=1e-3, what="value"):
    """z-test of every entry of ``estimate`` (± ``stderr``) against ``expected`` with a Bonferroni correction over
    ``n_tests`` (default: the number of entries). Returns the largest |z|; raises AssertionError naming the worst
    entry."""
    estimate, stderr = estimate.double(), stderr.double()
    expected = torch.as_tensor(expected, dtype=torch.float64).expand_as(estimate)
    n = estimate.numel() if n_tests is None else n_tests
    zmax = bonferroni_z(n, family_alpha)
    z = (estimate - expected).abs() / stderr.clamp_min(1e-300)
    worst = int(torch.argmax(z))
    assert bool((z <= zmax).all()), (
        f"{what}: |z| up to {float(z.flatten()[worst]):.2f} > {zmax:.2f} at flat index {worst}: "
        f"estimate {float(estimate.flatten()[worst]):.6g} ± {float(stderr.flatten()[worst]):.3g}, "
        f"expected {float(expected.flatten()[worst]):.6g}")
    return float(z.max())


def simd_walk_level():
    """The widest SIMD slab walk that runs here: 0 none (no AVX2, or TA_SIMD is 0), 1 AVX2, 2 AVX-512; leaves the
    choice automatic."""
    from .._ext import _C
    _C._set_simd(-1)
    return int(_C._set_simd(-1))


def status_kb(field):
    """A ``kB`` field of /proc/self/status (Linux: ``VmRSS``, ``VmHWM``, ...), or None where there is none."""
    try:
        with open("/proc/self/status") as handle:
            for line in handle:
                if line.startswith(field + ":"):
                    return int(line.split()[1])
    except OSError:
        return None
    return None


def reset_peak_rss():
    """Reset the kernel's peak-RSS mark (VmHWM) of this process; True when that worked (Linux)."""
    try:
        with open("/proc/self/clear_refs", "w") as handle:
            handle.write("5")
        return True
    except OSError:
        return False


def tiny_print_target(path, h=6, w=8):
    """Write a two-colour (H, W) linear-RGB EXR print target (left half red-brown, right half blue) to ``path`` and
    return the path as a str: the smallest slab target a print run takes."""
    import numpy as np

    from .. import io as ta_io

    img = np.zeros((h, w, 3), np.float32)
    img[:, : w // 2] = (0.5, 0.1, 0.05)
    img[:, w // 2:] = (0.05, 0.2, 0.5)
    ta_io.write_exr(str(path), img)
    return str(path)


def run_command(name, *args):
    """Run the ``ta-…`` command ``name`` (a module of :mod:`torch_appearance.cli`, e.g. ``"detect_rings"``) in this
    process, as ``main(argv)`` with the arguments as strings.

    Returns:
        (exit status, stdout, stderr); an ``argparse`` exit counts as its status.
    """
    module = importlib.import_module(f"torch_appearance.cli.{name}")
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            rc = module.main([str(a) for a in args])
        except SystemExit as stop:
            rc = stop.code if isinstance(stop.code, int) else (0 if stop.code is None else 1)
    sys.stdout.flush()
    return rc, out.getvalue(), err.getvalue()


def command_argv(name, *args):
    """The argv that runs the ``ta-…`` command ``name`` (a module of :mod:`torch_appearance.cli`, e.g.
    ``"fit_wood"``) in a child process as its installed console script does: the entry point in
    :mod:`torch_appearance.cli.entry`, called by ``python -c`` (which, like the script file, exits with the status
    the command returns; ``python -m`` may end in SIGINT instead, see that module).

    Example:
        >>> command_argv("fit_wood", "board.png", 3)[-2:]
        ['board.png', '3']
    """
    prog = "ta-" + name.replace("_", "-")
    code = f"import sys; from torch_appearance.cli.entry import {name}; sys.argv[0] = {prog!r}; sys.exit({name}())"
    return [sys.executable, "-c", code, *[str(a) for a in args]]


def sigint_default():
    """``preexec_fn`` for a child that must see SIGINT as a terminal's Ctrl-C: a suite started in the background of
    a non-interactive shell has SIGINT ignored, and a child keeps that (then Python installs no handler)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def address_space_limit(limit_bytes):
    """``preexec_fn`` for a child run under ``ulimit -v``: its ``RLIMIT_AS`` (soft and hard) set to ``limit_bytes``,
    and SIGINT as a terminal's Ctrl-C (:func:`sigint_default`)."""
    import resource

    def apply():
        sigint_default()
        resource.setrlimit(resource.RLIMIT_AS, (int(limit_bytes), int(limit_bytes)))

    return apply


def interrupt_when(command, ready, *, env=None, wait_s=300.0, timeout_s=120.0):
    """Start ``command`` (an argv list, e.g. :func:`command_argv`) in a child process, send it SIGINT once ``ready()``
    is true (or it has ended, or ``wait_s`` seconds have passed), and wait for it (at most ``timeout_s`` seconds, then
    it is killed and reaped, and ``subprocess.TimeoutExpired`` raised).

    Returns:
        (exit status, stdout, stderr) of the child, as text.
    """
    proc = subprocess.Popen([str(a) for a in command], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=env, preexec_fn=sigint_default)
    try:
        deadline = time.monotonic() + wait_s
        while not ready() and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.02)
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=timeout_s)
    except BaseException:  # a timeout, a failing ready(), the test run stopped: the child must not outlive it
        proc.kill()
        proc.communicate()
        raise
    return proc.returncode, out, err


# ---- stiff and extreme tracer cases (tests/test_stiff_sweep.py runs a part, scripts/bench/stiff_sweep.py all)
SIGMAS = (0.0, 1e-6, 1e-2, 1.0, 1e2, 1e4)  # mm⁻¹
ALBEDOS = (0.0, 1e-3, 0.5, 0.9997, 1.0)
GS = (-0.99, 0.0, 0.99)
IORS = (None, 1.0 + 1e-6, 1.5, 3.0)  # 1 + 1e-6: a dielectric that is almost index matched
THICKNESS = ("1 voxel", "2.5 mm")
STIFF_VOXEL_MM = 0.1  # mm


def run_stiff_case(sigma, albedo, g, ior, thickness, *, texels=3, spp=64, seed=0, max_depth=4096):
    """Render one uniform slab case forward and backward; return measured quantities and failed checks.

    Checks (each only where it applies):
      finite image and gradients; 0 <= L <= environment (+ float round-off);
      white furnace (albedo 1): L = 1 exactly unless paths were cut by max_depth (then the cut fraction is reported
      and must explain the deficit exactly);
      Beer–Lambert (albedo 0): L = R + (1 − R)²T/(1 − RT) (or T index-matched), z-test at 5σ;
      gradient sign: ∂L/∂σ_t <= 0 when albedo = 0 (more extinction, less light), ∂L/∂albedo >= 0 everywhere.
    """
    from ..render.volpath import render_texels

    depth = 1 if thickness == "1 voxel" else int(round(2.5 / STIFF_VOXEL_MM))
    shape = (3, depth, texels, texels)
    s = torch.full(shape, float(sigma), dtype=torch.float64, requires_grad=True)
    a = torch.full(shape, float(albedo), dtype=torch.float64, requires_grad=True)
    stats = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # truncation is checked below from the counts
        img = render_texels(s, a, voxel_size=STIFF_VOXEL_MM, g=g, ior=ior, spp=spp, seed=seed, max_depth=max_depth,
                               stats=stats)
    img.sum().backward()
    failed = []
    if not bool(torch.isfinite(img).all()):
        failed.append("non-finite image")
    if not (bool(torch.isfinite(s.grad).all()) and bool(torch.isfinite(a.grad).all())):
        failed.append("non-finite gradient")
    img = img.detach()
    if float(img.min()) < 0 or float(img.max()) > 1 + 1e-9:
        failed.append(f"radiance outside [0, env]: [{float(img.min())}, {float(img.max())}]")
    walks = texels * texels * spp * (1 if stats["lanes"] == 3 else 3)
    cut = stats["truncated_paths"] / walks
    if albedo == 1.0:
        deficit = 1.0 - float(img.mean())
        if abs(deficit - cut) > 1e-9:
            failed.append(f"furnace deficit {deficit:.3g} not explained by cut paths {cut:.3g}")
    if albedo == 0.0:
        t = math.exp(-sigma * depth * STIFF_VOXEL_MM)
        expected = t if ior is None else (lambda r: r + (1 - r) ** 2 * t / (1 - r * t))(((ior - 1) / (ior + 1)) ** 2)
        n = img.numel() // 3 * spp
        se = math.sqrt(max(expected * (1 - expected), 1e-12) / n)
        if abs(float(img.mean()) - expected) > 5 * se + 1e-12:
            failed.append(f"Beer–Lambert {float(img.mean()):.6g} vs {expected:.6g} (se {se:.2g})")
        if float(s.grad.sum()) > 1e-12:
            failed.append(f"∂L/∂σ_t > 0 with albedo 0: {float(s.grad.sum())}")
    if float(a.grad.sum()) < -1e-9:
        failed.append(f"∂L/∂albedo < 0: {float(a.grad.sum())}")
    return {"sigma": sigma, "albedo": albedo, "g": g, "ior": ior, "thickness": thickness, "mean": float(img.mean()),
            "cut_fraction": cut, "grad_sigma_sum": float(s.grad.sum()), "grad_albedo_sum": float(a.grad.sum()),
            "failed": failed}
