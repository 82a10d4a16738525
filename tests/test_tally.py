"""The walk's diagnostic tally (``_C._set_tally``): the scalar walk counts its scattering events and voxel moves by a
caller's (D, H, W) bins, e.g. by depth below an object's surface (scripts/bench/bench_objects.py --depth-bin-mm).
The bins must partition the walk's own totals exactly, agree with its count of events in the homogeneous core, and
counting must not change the image."""
import pytest
import torch

import torch_appearance as ta
from torch_appearance import _C
from torch_appearance.geometry import sphere_sdf
from torch_appearance.render import Scene, SDFBoundary, SurfaceTexels

N, H, ORIGIN, RADIUS = 24, 0.05, (-0.6, -0.6, -0.6), 0.5


def scene():
    u = torch.randn(16, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    u = u / u.norm(dim=1, keepdim=True)
    sdf = sphere_sdf((N,) * 3, H, ORIGIN, (0, 0, 0), RADIUS)
    return Scene(voxel_size=H, origin=ORIGIN, boundary=SDFBoundary(sdf, ior=1.5),
                 sensor=SurfaceTexels(RADIUS * u, u, footprint_mm=0.05), g=0.3)


def medium():
    gen = torch.Generator().manual_seed(1)
    return 5 + 10 * torch.rand((3, N, N, N), generator=gen), 0.9 + 0.09 * torch.rand((3, N, N, N), generator=gen)


def render(bins, chromatic="per_channel"):
    stats = {}
    _C._set_tally(bins)
    try:
        image = ta.render_scene(scene(), *medium(), spp=4, seed=2, stats=stats, chromatic=chromatic)
    finally:
        _C._set_tally(None)
    return image, stats


@pytest.mark.parametrize("chromatic", ["per_channel", "hero"])
def test_bins_partition_the_walks_totals(chromatic):
    plain, s0 = render(None, chromatic)
    assert "tally" not in s0
    one, s1 = render(torch.zeros((N,) * 3, dtype=torch.uint8), chromatic)
    assert torch.equal(one, plain)  # counting changes nothing
    assert s1["tally"].shape == (256, 2)
    assert s1["tally"][0].tolist() == [s1["scatter_events"], s1["voxel_steps"]]
    assert int(s1["tally"][1:].abs().sum()) == 0
    bins = torch.randint(0, 7, (N,) * 3, generator=torch.Generator().manual_seed(3), dtype=torch.uint8)
    _, s2 = render(bins, chromatic)
    assert s2["tally"].sum(0).tolist() == [s2["scatter_events"], s2["voxel_steps"]]
    assert bool((s2["tally"][:7] > 0).all()) and int(s2["tally"][7:].abs().sum()) == 0


def test_core_bin_counts_the_core_events():
    """In a homogeneous sphere the core (csrc/core/medium.h) is every 4³ brick whose cells lie wholly inside: binning
    those voxels apart, the tally's events there must be the walk's own count of core events."""
    sdf = scene().boundary.sdf
    corners = torch.stack([sdf[k:k + N, j:j + N, i:i + N] for k in (0, 1) for j in (0, 1) for i in (0, 1)])
    inside = (corners < 0).all(0)
    core = inside.view(N // 4, 4, N // 4, 4, N // 4, 4).all(5).all(3).all(1)
    bins = core.repeat_interleave(4, 0).repeat_interleave(4, 1).repeat_interleave(4, 2).to(torch.uint8)
    stats = {}
    _C._set_tally(bins)
    try:
        ta.render_scene(scene(), torch.full((3, N, N, N), 12.0), torch.full((3, N, N, N), 0.99), spp=4, seed=2,
                        stats=stats)
    finally:
        _C._set_tally(None)
    assert stats["core_events"] > 0
    assert int(stats["tally"][1, 0]) == stats["core_events"]


def test_tally_refuses_bad_bins():
    with pytest.raises(RuntimeError, match="bins: expected a \\(D, H, W\\) uint8"):
        _C._set_tally(torch.zeros(4, 4, dtype=torch.uint8))
    with pytest.raises(RuntimeError, match="tally: expected bins of the grid's shape"):
        render(torch.zeros((N, N, N + 1), dtype=torch.uint8))
