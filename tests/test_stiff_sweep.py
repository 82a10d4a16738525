"""Stiff and extreme cases (σ_t from 0 to 1e4 mm⁻¹, albedo 0 … 1, g = ±0.99, ior None/1+1e-6/1.5/3, one voxel or
2.5 mm): finite, bounded, physically consistent outputs and gradients. The full sweep is scripts/bench/stiff_sweep.py."""
import itertools

import pytest

from torch_appearance.testing import ALBEDOS, IORS, SIGMAS, run_stiff_case as run_case

CASES = list(itertools.product(SIGMAS, ALBEDOS, (-0.99, 0.99), IORS))


@pytest.mark.parametrize("sigma,albedo,g,ior", CASES)
def test_one_voxel_slab(sigma, albedo, g, ior):
    result = run_case(sigma, albedo, g, ior, "1 voxel", spp=64)
    assert not result["failed"], result


@pytest.mark.slow
@pytest.mark.parametrize("sigma,albedo,ior", list(itertools.product((1e-6, 1.0, 1e2), (0.0, 0.9997, 1.0), (None, 3.0))))
def test_thick_slab(sigma, albedo, ior):
    result = run_case(sigma, albedo, 0.0, ior, "2.5 mm", spp=16, max_depth=65536)
    assert not result["failed"], result
