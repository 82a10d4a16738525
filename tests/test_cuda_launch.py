"""The CUDA launcher (torch_appearance/render/cuda_launch.py), the parts that need no GPU: the kernel each scene's
configuration takes (the CPU dispatch's choice, csrc/volpath/dispatch.h), the bytes of the Launch struct and of the
kernel parameters, the share and image shapes (against the CPU's), the layout of core::Scene<T> as NVRTC compiles it
(static_asserts against the host's offsets; a wrong offset fails the compile), and the refusals of the dispatch by
device. The launches themselves run on a GPU only: scripts/bench/gpu_check.py."""
import ctypes
import struct
import types

import pytest
import torch

from torch_appearance._ext import _C
from torch_appearance.render import Scene, TraceJob, cuda_kernels, cuda_launch


def _options(lanes=1, hero=0, sdf=False, ior=1.5):
    o = _C.SceneOptions()
    o.lanes, o.hero = lanes, hero
    o.boundary.kind = 1 if sdf else 0
    o.boundary.ior = -1.0 if ior is None else ior
    return o


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_kernel_names_follow_the_cpu_dispatch(dtype):
    d = "f32" if dtype == torch.float32 else "f64"
    forward, replay = set(cuda_kernels.kernel_names("forward", d)), set(cuda_kernels.kernel_names("replay", d))
    seen = set()
    for lanes, hero, want in ((1, 0, "l1"), (1, 1, "l1"), (3, 0, "l3"), (3, 1, "hero")):  # hero only with 3 lanes
        for sdf in (False, True):
            for ior in (None, 1.0, 1.5):  # a dielectric of index 1 is still a dielectric (ior > 0)
                o = _options(lanes, hero, sdf, ior)
                optics = "matched" if ior is None else "diel"
                base = f"{d}_{want}_{'sdf' if sdf else 'box'}_{optics}"
                for ratio in (False, True):
                    name = cuda_launch.forward_kernel_name(o, dtype, ratio)
                    assert name == f"ta_forward_{base}_{'ratio' if ratio else 'plain'}" and name in forward
                    seen.add(name)
                assert cuda_launch.replay_kernel_name(o, dtype) == f"ta_replay_{base}" in replay
    assert seen == forward - {f"ta_image_{d}"}
    with pytest.raises(TypeError, match="dtype: expected float32 or float64"):
        cuda_launch.forward_kernel_name(_options(), torch.float16, False)


def test_launch_struct_and_kernel_parameters():
    raw = cuda_launch.pack_launch(1, 4, 10, 1 << 33, 77)
    assert len(raw) == 40 and struct.unpack("<5q", raw) == (1, 4, 10, 1 << 33, 77)
    x = torch.arange(4.0)
    args = [b"\x01" * 632, raw, cuda_launch.pointer(x), cuda_launch.pointer(None), struct.pack("<q", -5)]
    address, alive = cuda_launch.kernel_params(args)
    array = (ctypes.c_void_p * len(args)).from_address(address)
    for k, a in enumerate(args):
        assert ctypes.string_at(array[k], len(a)) == a
    assert struct.unpack("<Q", args[2])[0] == x.data_ptr() and struct.unpack("<Q", args[3])[0] == 0


@pytest.mark.parametrize("scene_kind", ["slab", "both", "camera"])
def test_share_and_image_shape_match_the_cpu(scene_kind):
    from torch_appearance.render import OrthographicCamera
    if scene_kind == "camera":
        scene = Scene(voxel_size=0.1, sensor=OrthographicCamera(origin=(0.2, 0.15, 2.0), target=(0.2, 0.15, 0),
                                                                up=(0, 1, 0), extent_mm=(0.4, 0.3), resolution=(3, 5)))
    else:
        scene = Scene.slab(0.1, face="top" if scene_kind == "slab" else "both")
    shape = (2, 3, 4)
    sigma_t = torch.full((3,) + shape, 5.0)
    albedo = torch.full((3,) + shape, 1.0)  # the white furnace: every traced element sees 1
    for rank, world in ((0, 1), (1, 3), (2, 3)):
        job = TraceJob(scene, spp=1, seed=1, partition=(rank, world))
        options = job.scene_options(3, 1, shape, torch.float32)
        image, _ = _C.scene_forward(sigma_t, albedo, sigma_t, albedo, False, options)
        assert cuda_launch.image_shape(options, shape) == tuple(image.shape)
        elements = image.numel() // 3
        traced = (image.reshape(-1, 3).abs().sum(1) > 0).sum().item()
        assert cuda_launch.share_count(elements, rank, world) == len(range(rank, elements, world)) == traced


def test_the_device_compiler_lays_out_the_scene_as_the_host():
    pytest.importorskip("cuda.bindings.nvrtc", reason="NVRTC through cuda-bindings (torch's CUDA wheel)")
    for dtype, ctype in ((torch.float32, "float"), (torch.float64, "double")):
        layout = _C.scene_layout(dtype)
        assert cuda_launch.layout_mismatches(layout, ctype) == []
    # the check can fail: a host offset off by 8 bytes is reported
    layout = _C.scene_layout(torch.float32)
    name, offset = layout.pointers[5]
    wrong = types.SimpleNamespace(size=layout.size, align=layout.align, pointers=[(name, offset + 8)], fields=[])
    assert cuda_launch.layout_mismatches(wrong, "float") == [(name, offset + 8, offset)]


def test_the_dispatch_by_device_and_its_refusals(monkeypatch):
    x = torch.zeros(2)
    assert cuda_launch.tracer_for(x, None, x) is _C
    assert cuda_launch.tracer_for() is _C
    with pytest.raises(ValueError, match=r"^albedo: expected the device of sigma_t \(cpu\), got meta$"):
        cuda_launch.tracer_for(x, torch.zeros(2, device="meta"), names=["sigma_t", "albedo"])
    with pytest.raises(ValueError, match="sigma_t: expected a CPU or CUDA tensor, got device meta"):
        cuda_launch.tracer_for(torch.zeros(2, device="meta"), names=["sigma_t"])
    fake = types.SimpleNamespace(device=torch.device("cuda", 0))
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(ValueError, match="sigma_t: CUDA tensors cannot be rendered here: no CUDA device is visible"):
        cuda_launch.tracer_for(fake, names=["sigma_t"])


def test_render_scene_refuses_mixed_devices():
    import torch_appearance as ta
    sigma_t = torch.full((3, 2, 2, 2), 5.0)
    with pytest.raises(ValueError, match=r"albedo: expected the device of sigma_t \(cpu\), got meta"):
        ta.render_scene(Scene.slab(0.1), sigma_t, torch.full((3, 2, 2, 2), 0.9, device="meta"))


@pytest.mark.skipif(torch.cuda.is_available(), reason="a GPU is present")
def test_the_device_option_of_the_commands(capsys):
    from torch_appearance.cli.command import CommandParser, resolve_device
    p = CommandParser("ta-x", "X.")
    lines = []
    assert resolve_device(p, "auto", log=lines.append) == torch.device("cpu")
    assert lines == ["device: cpu (--device auto: no CUDA device is visible to torch (torch.cuda.is_available() is "
                     "False))"]
    assert resolve_device(p, "CPU") == torch.device("cpu")
    for value, message in (("cuda:1", "--device: cuda:1 cannot be used here: no CUDA device is visible to torch"),
                           ("gpu", "--device: expected auto, cpu, cuda or cuda:N, got 'gpu'")):
        with pytest.raises(SystemExit) as info:
            resolve_device(p, value)
        assert info.value.code == 2
        assert message in capsys.readouterr().err


def test_the_wood_volume_config_checks_its_device():
    from torch_appearance.pipelines.wood_volume_render import WoodVolumeConfig
    assert WoodVolumeConfig(synthetic_seed=1, device="cuda:0").validate().device == "cuda:0"
    with pytest.raises(ValueError, match="device: expected 'cpu', 'cuda' or 'cuda:N', got 'tpu'"):
        WoodVolumeConfig(synthetic_seed=1, device="tpu").validate()


def _recorded_launches(monkeypatch, paths_per_launch):
    """cuda_launch with its launches recorded instead of made (CPU tensors stand in for the device's)."""
    import contextlib
    calls = []
    monkeypatch.setattr(cuda_launch, "PATHS_PER_LAUNCH", paths_per_launch)
    monkeypatch.setattr(torch.cuda, "device", lambda device: contextlib.nullcontext())
    monkeypatch.setattr(cuda_launch, "_launch", lambda device, program, dtype, name, threads, args:
                        calls.append((program, dtype, name, threads, [bytes(a) for a in args])))
    monkeypatch.setattr(cuda_launch, "check_device_memory", lambda device, needed, what:
                        calls.append(("memory", what, needed)))
    return calls


def test_the_launcher_splits_a_job_into_consecutive_launches(monkeypatch):
    """The forward's launches (recorded, not made): the kernel of the CPU's dispatch, consecutive paths covering
    count × spp × 3 walks (one lane per channel), the Launch of each, the scene's bytes, then the image kernel."""
    calls = _recorded_launches(monkeypatch, 100)
    scene = Scene.slab(0.1, face="both", ior=1.4)
    shape = (2, 3, 4)
    gen = torch.Generator().manual_seed(0)
    sigma_t = torch.rand((3,) + shape, generator=gen) * 5 + 1
    albedo = torch.full((3,) + shape, 0.9)
    job = TraceJob(scene, spp=5, seed=1, partition=(1, 3))
    options = job.scene_options(1, 1, shape, torch.float32)
    image, counts = cuda_launch.scene_forward(sigma_t, albedo, sigma_t, albedo, False, options)
    assert tuple(image.shape) == (2, 3, 4, 3) and counts.scatter_events == 0
    count = cuda_launch.share_count(24, 1, 3)
    total = count * 5 * 3
    assert calls[0] == ("memory", "render_scene", count * 3 * 8 + count * 3 * 4)  # box: no scene buffers
    walks = [c for c in calls if c[0] != "memory" and c[2].startswith("ta_forward")]
    assert {c[2] for c in walks} == {"ta_forward_f32_l1_box_diel_plain"}
    first = 0
    for program, dtype, name, threads, args in walks:
        assert (program, dtype) == ("forward", "f32") and len(args) == 4
        assert struct.unpack("<5q", args[1]) == (1, 3, count, first, threads) and threads <= 100
        assert len(args[0]) == _C.scene_layout(torch.float32).size
        first += threads
    assert first == total and len(walks) == (total + 99) // 100
    program, dtype, name, threads, args = calls[-1]
    assert name == "ta_image_f32" and threads == count and struct.unpack("<5q", args[1])[:3] == (1, 3, count)
    assert struct.unpack("<Q", args[3])[0] == image.data_ptr()


def test_the_replay_launch_takes_the_compact_buffers_of_grad_support(monkeypatch):
    calls = _recorded_launches(monkeypatch, 1 << 20)
    scene = Scene.slab(0.1, ior=None)
    shape = (2, 3, 4)
    support = torch.zeros(shape, dtype=torch.bool)
    support[0, 1:, :2] = True
    sigma_t = torch.full((3,) + shape, 4.0)
    albedo = torch.full((3,) + shape, 0.9)
    job = TraceJob(scene, spp=2, seed=1, grad_support=support)
    options = job.scene_options(3, 1, shape, torch.float64)
    grad_out = torch.ones((3, 4, 3), dtype=torch.float64)
    gs, ga, events = cuda_launch.scene_backward(grad_out, sigma_t.double(), albedo.double(), sigma_t.double(),
                                                albedo.double(), True, False, options, 0.5, 0.05)
    assert ga is None and tuple(gs.shape) == (3,) + shape and events == 0
    memory, (program, dtype, name, threads, args) = calls
    assert memory[:2] == ("memory", "render_scene backward") and memory[2] >= 2 * sigma_t.numel() * 8
    assert (program, dtype, name) == ("replay", "f64", "ta_replay_f64_l3_box_matched")
    assert threads == 12 * 2 and len(args) == 9
    assert struct.unpack("<q", args[5])[0] == int(support.sum())  # plane: the asked voxels
    assert struct.unpack("<Q", args[6])[0] != 0 and struct.unpack("<Q", args[4])[0] == 0  # rank; no albedo buffer
    with pytest.raises(ValueError, match="grad_output: expected 36 values"):
        cuda_launch.scene_backward(grad_out[:2], sigma_t.double(), albedo.double(), sigma_t.double(),
                                   albedo.double(), True, False, options, 0.5, 0.05)


def test_a_job_too_large_for_the_device_is_refused_before_it_is_built(monkeypatch):
    monkeypatch.setattr(torch.cuda, "mem_get_info", lambda device: (3 << 30, 80 << 30))
    monkeypatch.setattr(torch.cuda, "memory_reserved", lambda device: 1 << 30)
    monkeypatch.setattr(torch.cuda, "memory_allocated", lambda device: 0)
    cuda_launch.check_device_memory("cuda:0", 4 << 30, "render_scene")  # 3 GiB free + 1 GiB cached but unused
    with pytest.raises(ValueError, match=r"^render_scene: needs 4\.50 GiB more on cuda:0, which has 4\.00 GiB free "
                                         r"\(4831838208 > 4294967296 bytes\)"):
        cuda_launch.check_device_memory("cuda:0", (4 << 30) + (1 << 29), "render_scene")
