"""Data-parallel rendering with torch.distributed (gloo on this machine): two ranks give the single-process image
exactly and its gradients to round-off, and every rank takes the same step."""
import os

import pytest
import torch
import torch.multiprocessing as mp

import torch_appearance as ta
from torch_appearance import distributed


def _problem():
    """A slab and a small SDF object with surface texels; a fixed weighting of the image as the loss."""
    g = torch.Generator().manual_seed(0)
    sigma_t = (2.0 + 18.0 * torch.rand(3, 6, 10, 9, generator=g, dtype=torch.float64)).requires_grad_()
    albedo = (0.5 + 0.49 * torch.rand(3, 6, 10, 9, generator=g, dtype=torch.float64)).requires_grad_()
    import trimesh

    from torch_appearance.geometry import voxelize
    from torch_appearance.render import Scene, SDFBoundary, SurfaceTexels
    obj = voxelize(trimesh.creation.icosphere(radius=0.5), 0.1)
    scene = Scene(voxel_size=obj.voxel_size, origin=obj.origin, boundary=SDFBoundary(obj.sdf.double(), ior=1.5),
                  sensor=SurfaceTexels(obj.texel_points, obj.texel_normals, footprint_mm=0.05), g=0.4)
    d, h, w = obj.grid_shape
    s2 = (3.0 + 10.0 * torch.rand(3, d, h, w, generator=g, dtype=torch.float64)).requires_grad_()
    a2 = (0.6 + 0.39 * torch.rand(3, d, h, w, generator=g, dtype=torch.float64)).requires_grad_()
    return sigma_t, albedo, scene, s2, a2


def _run(render):
    sigma_t, albedo, scene, s2, a2 = _problem()
    slab = render(ta.render_texels, sigma_t=sigma_t, albedo=albedo, voxel_size=0.1, spp=3, seed=11, face="both")
    obj = render(ta.render_scene, scene, sigma_t=s2, albedo=a2, spp=3, seed=12, seed_grad=13)
    wslab = torch.linspace(0.5, 1.5, slab.numel(), dtype=slab.dtype).view_as(slab)
    wobj = torch.linspace(1.5, 0.5, obj.numel(), dtype=obj.dtype).view_as(obj)
    ((slab * wslab).sum() + (obj * wobj).sum()).backward()
    return {"slab": slab.detach(), "obj": obj.detach(), "gs": sigma_t.grad, "ga": albedo.grad, "gs2": s2.grad,
            "ga2": a2.grad}


def _worker(rank, world, store, out):
    import torch.distributed as dist

    torch.set_num_threads(1)
    dist.init_process_group("gloo", init_method=f"file://{store}", rank=rank, world_size=world)
    try:
        torch.save(_run(distributed.render), f"{out}.{rank}")
    finally:
        dist.destroy_process_group()


def _spawn_ranks(target, store, out, timeout, world=2):
    """Run ``target(rank, world, store, out)`` in ``world`` spawned processes; fail after ``timeout`` s or on a
    non-zero exit."""
    ctx = mp.get_context("spawn")
    procs = [ctx.Process(target=target, args=(r, world, store, out)) for r in range(world)]
    for p in procs:
        p.start()
    for p in procs:
        p.join(timeout=timeout)
        if p.is_alive():
            p.kill()
            pytest.fail(f"a rank did not finish within {timeout} s")
        assert p.exitcode == 0, f"rank exited with {p.exitcode}"


def test_two_ranks_equal_one_process(tmp_path):
    torch.set_num_threads(1)
    single = _run(lambda fn, *a, **k: fn(*a, **k))
    _spawn_ranks(_worker, str(tmp_path / "store"), str(tmp_path / "out"), timeout=180)
    ranks = [torch.load(tmp_path / f"out.{r}") for r in range(2)]
    for r in ranks:
        # the images are sums of disjoint shares of the same paths: bitwise equal
        assert torch.equal(r["slab"], single["slab"]) and torch.equal(r["obj"], single["obj"])
        for k in ("gs", "ga", "gs2", "ga2"):
            assert torch.allclose(r[k], single[k], rtol=1e-10, atol=1e-13), k
    for k in ("gs", "ga", "gs2", "ga2"):  # every rank takes the same step
        assert torch.equal(ranks[0][k], ranks[1][k])


def test_partition_shares_sum_to_the_image_and_are_checked():
    sigma_t, albedo, scene, s2, a2 = _problem()
    full = ta.render_scene(scene, s2, a2, spp=2, seed=5)
    shares = [ta.render_scene(scene, s2, a2, spp=2, seed=5, partition=(r, 3)) for r in range(3)]
    assert torch.equal(sum(shares), full)
    assert bool((shares[1][0::3] == 0).all()) and bool((shares[1][1::3] == full[1::3]).all())
    with pytest.raises(ValueError, match="partition"):
        ta.render_texels(sigma_t, albedo, voxel_size=0.1, partition=(2, 2))
    with pytest.raises(TypeError, match="partition"):
        ta.render_texels(sigma_t, albedo, voxel_size=0.1, partition=(0.0, 2))
    assert distributed.rank_and_world() == (0, 1)
    assert distributed.render(ta.render_scene, scene, sigma_t=s2, albedo=a2, spp=2, seed=5).equal(full)
    # the medium is named, never guessed from positions: a positional tensor that takes a gradient is refused
    with pytest.raises(TypeError, match="sigma_t=, albedo="):
        distributed.render(ta.render_scene, scene, s2, a2, spp=2, seed=5)
    with pytest.raises(ValueError, match="partition"):
        distributed.render(ta.render_scene, scene, sigma_t=s2, albedo=a2, partition=(0, 1))


def _print_worker(rank, world, store, out):
    import torch.distributed as dist

    from torch_appearance.pipelines import PrintConfig, optimize_print

    torch.set_num_threads(1)
    dist.init_process_group("gloo", init_method=f"file://{store}", rank=rank, world_size=world)
    try:
        optimize_print(PrintConfig(**_PRINT, out=out), progress=False, log=lambda *_: None)
    finally:
        dist.destroy_process_group()


_PRINT = dict(target="colorchecker", width_mm=1.2, dpi=150.0, thickness_mm=0.5, spp=2, eval_spp=4, eval_every=2,
              iterations=3, table_steps=2, printer_dpi=(300.0, 300.0, 300.0))


def test_print_optimisation_under_two_ranks_follows_one_process(tmp_path):
    """optimize_print unchanged under torch.distributed: rank 0 writes the run folder (the other rank nothing), and
    the log follows the single-process run (the same images; gradients equal to round-off)."""
    import csv

    from torch_appearance.pipelines import PrintConfig, optimize_print

    torch.set_num_threads(1)
    before = _rank_folders()
    optimize_print(PrintConfig(**_PRINT, out=str(tmp_path / "one")), progress=False, log=lambda *_: None)
    _spawn_ranks(_print_worker, str(tmp_path / "store"), str(tmp_path / "two"), timeout=240)
    one = list(csv.DictReader(open(tmp_path / "one" / "log.csv")))
    two = list(csv.DictReader(open(tmp_path / "two" / "log.csv")))
    assert len(one) == len(two) == 4
    assert float(two[0]["loss"]) == float(one[0]["loss"])  # iteration 0: the same image
    for a, b in zip(one, two):
        assert float(b["loss"]) == pytest.approx(float(a["loss"]), rel=1e-4)
        if a["dE00_mean"]:
            assert float(b["dE00_mean"]) == pytest.approx(float(a["dE00_mean"]), rel=1e-3)
    import json
    assert json.load(open(tmp_path / "two" / "config.json"))["ranks"] == 2
    assert _rank_folders() == before  # rank 1's private folder is gone


def _rank_folders():
    import tempfile
    return sorted(n for n in os.listdir(tempfile.gettempdir()) if n.startswith("optimize_print_rank"))


def test_the_process_group_backend_follows_the_device():
    """gloo on the CPU; with CUDA tensors NCCL (and gloo for the CPU tensors such a run still reduces), each rank on
    the GPU of its LOCAL_RANK whatever index the run's device names."""
    assert distributed.process_group_backend("cpu") == "gloo"
    assert distributed.process_group_backend(torch.device("cpu")) == "gloo"
    for device in ("cuda", "cuda:0", torch.device("cuda", 1)):
        assert distributed.process_group_backend(device) == "cpu:gloo,cuda:nccl"
    assert torch.distributed.Backend(distributed.process_group_backend("cuda")) == "cpu:gloo,cuda:nccl"
    assert distributed.rank_device("cuda:0", {"LOCAL_RANK": "2"}) == torch.device("cuda", 2)
    assert distributed.rank_device("cuda", {}) == torch.device("cuda", 0)
    assert distributed.rank_device("cpu", {"LOCAL_RANK": "2"}) == torch.device("cpu")
    with pytest.raises(ValueError, match=r"^device: expected 'cpu', 'cuda' or 'cuda:N', got 'tpu'$"):
        distributed.process_group_backend("tpu")
    with pytest.raises(ValueError, match=r"^LOCAL_RANK: expected an int >= 0 \(torchrun sets it\), got 'x'$"):
        distributed.rank_device("cuda", {"LOCAL_RANK": "x"})
