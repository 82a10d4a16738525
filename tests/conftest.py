"""Shared fixtures and helpers for the test suite (markers are declared in setup.cfg)."""
import math

import pytest
import torch
from scipy.stats import norm

import torch_appearance  # noqa: F401  (fails early, with the build instructions, if the extension is missing)


@pytest.fixture(params=[torch.float32, torch.float64], ids=["f32", "f64"])
def dtype(request):
    return request.param


def bonferroni_z(n_tests, family_alpha=1e-3):
    """Two-sided z threshold for ``n_tests`` simultaneous tests at family-wise error ``family_alpha``."""
    return float(norm.isf(family_alpha / (2 * n_tests)))


def seed_stats(fn, seeds):
    """Mean and standard error over independent seeds of ``fn(seed) -> tensor``."""
    xs = torch.stack([fn(s).double() for s in seeds])
    return xs.mean(0), xs.std(0, unbiased=True) / math.sqrt(len(seeds))


def assert_z(estimate, stderr, expected, *, n_tests=None, family_alpha=1e-3, what="value"):
    """z-test of every entry of ``estimate`` (± ``stderr``) against ``expected`` with a Bonferroni correction."""
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


@pytest.fixture
def walk_kernel():
    """``walk_kernel(mode)`` selects the slab walk for the rest of a test: 0 the scalar walk, 1 the AVX2 walk of
    eight lanes, 2 the AVX-512 walk of sixteen (csrc/volpath/slab_simd.h), -1 automatic (the default); restored
    afterwards."""
    from torch_appearance._ext import _C

    def select(mode):
        _C._set_simd(mode)

    yield select
    _C._set_simd(-1)


def simd_walk_level():
    """The widest SIMD slab walk that runs here: 0 none (no AVX2, or TA_SIMD is 0), 1 AVX2, 2 AVX-512; leaves it
    automatic."""
    from torch_appearance._ext import _C
    _C._set_simd(-1)
    return int(_C._set_simd(-1))
