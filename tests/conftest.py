"""Shared fixtures of the test suite (markers are declared in setup.cfg; helpers live in torch_appearance.testing)."""
import pytest
import torch

from torch_appearance import _C  # noqa: F401  (fails early, with the build instructions, if the extension is missing)


@pytest.fixture(params=[torch.float32, torch.float64], ids=["f32", "f64"])
def dtype(request):
    return request.param


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

