"""Helpers for testing code built on torch_appearance (as ``torch.testing`` and ``torch_scatter.testing``): z-tests of
Monte Carlo estimates, statistics over seeds, the walk this CPU runs, memory probes, and running a ``ta-…`` command
in-process.

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
import sys

import torch

__all__ = ["bonferroni_z", "seed_stats", "assert_z", "simd_walk_level", "status_kb", "reset_peak_rss",
           "run_command"]


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
    from ._ext import _C
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
