"""The tracer's entry points on a CUDA device: the kernels of ``csrc/cuda/`` (compiled at run time by
:mod:`torch_appearance.render.cuda_kernels`) launched on torch's current stream, with torch's allocator.

The four functions here take the arguments and return the values of the C++ entry points of ``torch_appearance._C``
(``scene_forward``, ``scene_backward``, ``scene_forward_backward``, ``scene_forward_indexed``), so the autograd
Functions call one or the other by the device of their tensors (:func:`tracer_for`). Per call:

1. the scene is built on the host as the CPU builds it and relocated onto the device (``_C.scene_to_device``: the
   bytes of ``core::Scene<T>``, its pointers in device memory; the grids already there are used in place);
2. the kernel of the configuration the CPU's dispatch would choose (``csrc/volpath/dispatch.h``: lanes 1, 3 or hero;
   box or SDF boundary; dielectric or index matched; ratio weights or plain) walks one path per thread, the paths
   numbered as ``csrc/cuda/launch.cuh`` says and split into launches of at most :data:`PATHS_PER_LAUNCH` consecutive
   paths; the terms go into per-element double sums, the gradient deposits into the gradient grids (or the compact
   buffers of ``grad_support``'s voxels) by atomic adds;
3. ``ta_image_<dtype>`` turns the sums into the image (``core::element_radiance``).

The compiled modules are loaded once per device (``cuModuleLoadData``; a cubin for the GPU present, else its PTX).
Nothing here runs without a CUDA device: :func:`cuda_unavailable` says what is missing.
"""
import ctypes
import struct
import threading
from dataclasses import dataclass, field
from typing import List

import torch

from .._ext import _C
from . import cuda_kernels

__all__ = ["PATHS_PER_LAUNCH", "BLOCK", "DeviceCounts", "cuda_unavailable", "tracer_for", "forward_kernel_name",
           "replay_kernel_name", "layout_probe_source", "layout_from_ptx", "layout_mismatches", "pack_launch",
           "kernel_params", "pointer", "share_count", "image_shape", "check_device_memory", "scene_forward",
           "scene_backward", "scene_forward_backward", "scene_forward_indexed"]

#: threads per block (csrc/cuda/launch.cuh kBlock)
BLOCK = 128
#: the most paths (threads) of one launch; a larger job is split into launches of consecutive paths
PATHS_PER_LAUNCH = 1 << 24
#: the replay's tape per thread, in segments (csrc/cuda/replay.cu; longer paths are replayed in two passes)
TAPE_SEGMENTS = 64


@dataclass
class DeviceCounts:
    """The counters of a render on a device, with the attributes of ``_C.ForwardCounts`` (the voxel visits and the
    core's events of the forward walks; ``tally`` is the CPU's diagnostics and stays empty)."""
    scatter_events: int = 0
    truncated_paths: int = 0
    voxel_steps: int = 0
    outside_steps: int = 0
    core_events: int = 0
    tally: List[int] = field(default_factory=list)


def cuda_unavailable():
    """None when CUDA tensors can be rendered here, else one line saying what is missing (no CUDA device visible to
    torch, or no NVRTC through ``cuda-bindings``)."""
    if not torch.cuda.is_available():
        return ("no CUDA device is visible to torch (torch.cuda.is_available() is False"
                + ("" if torch.version.cuda else "; this torch is a CPU-only build") + ")")
    try:
        from cuda.bindings import driver, nvrtc  # noqa: F401
    except ImportError as exc:
        return f"NVIDIA's cuda-bindings (NVRTC and the driver API) is not importable: pip install cuda-bindings ({exc})"
    return None


def device_unusable(device):
    """None when tensors on ``device`` (a ``torch.device`` or its name) can be rendered here, else one line naming
    it and saying why not: CUDA missing (:func:`cuda_unavailable`), an index past the GPUs torch sees, or a device
    that is neither the CPU nor CUDA. The one check behind ``--device`` and ``PrintConfig.device``.

    Example:
        >>> device_unusable("cpu") is None
        True
    """
    device = torch.device(device)
    if device.type == "cpu":
        return None
    if device.type != "cuda":
        return f"expected the CPU or a CUDA device, got {device}"
    missing = cuda_unavailable()
    if missing:
        return f"{device} cannot be used here: {missing}"
    if (device.index or 0) >= torch.cuda.device_count():
        return f"expected cuda:0 ... cuda:{torch.cuda.device_count() - 1} (the GPUs torch sees), got {device}"
    return None


def tracer_for(*tensors, names=None):
    """The entry points for ``tensors`` (those that are not None): the C++ extension ``_C`` for CPU tensors, this
    module for CUDA tensors of one device.

    Raises:
        ValueError: tensors on two devices (one line naming both), on a device that is neither CPU nor CUDA, or CUDA
            tensors where they cannot be rendered (what is missing).
    """
    names = names or [f"tensor {k}" for k in range(len(tensors))]
    first = None
    for name, x in zip(names, tensors):
        if x is None:
            continue
        if first is None:
            first = (name, x.device)
        elif x.device != first[1]:
            raise ValueError(f"{name}: expected the device of {first[0]} ({first[1]}), got {x.device}")
    device = torch.device("cpu") if first is None else first[1]
    if device.type == "cpu":
        return _C
    if device.type != "cuda":
        raise ValueError(f"{first[0]}: expected a CPU or CUDA tensor, got device {device}")
    missing = cuda_unavailable()
    if missing is not None:
        raise ValueError(f"{first[0]}: CUDA tensors cannot be rendered here: {missing}")
    import sys
    return sys.modules[__name__]


# ---- what the CPU's dispatch chooses (csrc/volpath/dispatch.h), as kernel names (csrc/cuda/*.cu)

def _dtype_name(dtype):
    if dtype == torch.float32:
        return "f32"
    if dtype == torch.float64:
        return "f64"
    raise TypeError(f"dtype: expected float32 or float64, got {dtype}")


def _config(options):
    lanes = "hero" if options.lanes == 3 and options.hero else ("l3" if options.lanes == 3 else "l1")
    boundary = "sdf" if options.boundary.kind == 1 else "box"
    optics = "diel" if options.boundary.ior > 0 else "matched"
    return lanes, boundary, optics


def forward_kernel_name(options, dtype, ratio):
    """The forward kernel that walks ``options``' scene as ``scene_forward_cpu`` would (its dispatch_scene and
    ``ratio``): ``ta_forward_<dtype>_<lanes>_<boundary>_<optics>_<weights>``."""
    lanes, boundary, optics = _config(options)
    return f"ta_forward_{_dtype_name(dtype)}_{lanes}_{boundary}_{optics}_{'ratio' if ratio else 'plain'}"


def replay_kernel_name(options, dtype):
    """The replay kernel of ``options``' scene (as ``scene_backward_cpu`` dispatches):
    ``ta_replay_<dtype>_<lanes>_<boundary>_<optics>``."""
    lanes, boundary, optics = _config(options)
    return f"ta_replay_{_dtype_name(dtype)}_{lanes}_{boundary}_{optics}"


# ---- the paths of a job and the kernels' parameters

def share_count(elements, rank, world):
    """The sensor elements of this process's share (volpath/threading.h Share): t = rank + world·u, u < count."""
    return (elements - rank + world - 1) // world if rank < elements else 0


def image_shape(options, grid_shape):
    """The image's shape for a (D, H, W) grid: (F, H, W, 3)/(H, W, 3) face texels, (N, 3) surface texels,
    (rows, cols, 3) cameras (volpath/scene_build.cpp image_shape)."""
    sensor = options.sensor
    if sensor.kind == 0:
        return (2,) + tuple(grid_shape[1:]) + (3,) if sensor.face == 2 else tuple(grid_shape[1:]) + (3,)
    if sensor.kind == 1:
        return (int(sensor.points.shape[0]), 3)
    return (int(sensor.rows), int(sensor.cols), 3)


def pack_launch(rank, world, count, first, paths):
    """The bytes of ``ta::cuda::Launch`` (csrc/cuda/launch.cuh: five int64, 40 bytes)."""
    return struct.pack("<5q", rank, world, count, first, paths)


def kernel_params(args):
    """The ``void**`` array of a launch: one pointer per kernel parameter, to a host buffer holding its bytes.

    Args:
        args: the parameters in order, each as bytes (a struct passed by value: its bytes; a pointer or an int64:
            8 little-endian bytes; see :func:`pointer`).

    Returns:
        (address of the array, the ctypes objects that must stay alive until the launch has been made).
    """
    buffers = [ctypes.create_string_buffer(bytes(a), len(a)) for a in args]
    array = (ctypes.c_void_p * len(buffers))(*[ctypes.addressof(b) for b in buffers])
    return ctypes.addressof(array), (array, buffers)


def pointer(tensor):
    """A device pointer parameter (8 bytes): the tensor's data pointer, or NULL for None."""
    return struct.pack("<Q", 0 if tensor is None else tensor.data_ptr())


def _int64(value):
    return struct.pack("<q", int(value))


def layout_probe_source(names, ctype):
    """A CUDA program whose kernel ``ta_layout_check(long long* out)`` writes sizeof and alignof of
    ``core::Scene<ctype>`` and then the byte offset of each member in ``names`` (paths such as
    ``medium.sigma_t.data``), as the device compiler lays the struct out; the values are compile-time constants, so
    they can be read from the PTX (:func:`layout_from_ptx`) without a GPU."""
    if ctype not in ("float", "double"):
        raise ValueError(f"ctype: expected 'float' or 'double', got {ctype!r}")
    lines = ['#include "core/integrator.h"', f"using TaScene = ta::core::Scene<{ctype}>;",
             "__device__ TaScene ta_layout_probe;",
             'extern "C" __global__ void ta_layout_check(long long* out) {',
             "  const char* base = reinterpret_cast<const char*>(&ta_layout_probe);",
             "  out[0] = sizeof(TaScene);", "  out[1] = alignof(TaScene);"]
    for k, name in enumerate(names):
        lines.append(f"  out[{k + 2}] = reinterpret_cast<const char*>(&ta_layout_probe.{name}) - base;")
    return "\n".join(lines + ["}"]) + "\n"


def layout_from_ptx(ptx):
    """{index: value} of the constants the probe's kernel stores (``out[index] = value``), read from its PTX."""
    import re
    text = ptx.decode(errors="replace") if isinstance(ptx, bytes) else ptx
    regs = {m.group(1): int(m.group(2)) for m in re.finditer(r"mov\.[us]64\s+(%rd\d+),\s*(-?\d+);", text)}
    out = {}
    for m in re.finditer(r"st\.global\.[us]64\s+\[%rd\d+(?:\+(\d+))?\],\s*(%rd\d+|-?\d+);", text):
        value = m.group(2)
        out[int(m.group(1) or 0) // 8] = regs[value] if value.startswith("%") else int(value)
    return out


def layout_mismatches(host_layout, ctype, arch="compute_90"):
    """The members of ``core::Scene<ctype>`` whose offsets (and the struct's size and alignment) differ between the
    host (``host_layout``: ``_C.scene_layout(dtype)``) and NVRTC, as ``[(name, host, device)]``; empty when the
    scene's bytes mean the same on both sides (they cross from host to kernel as they are)."""
    names = [n for n, _ in list(host_layout.pointers) + list(host_layout.fields)]
    host = [host_layout.size, host_layout.align] + [o for _, o in list(host_layout.pointers) + list(host_layout.fields)]
    ptx = cuda_kernels.compile_source(layout_probe_source(names, ctype), "layout_probe.cu", arch)
    device = layout_from_ptx(ptx)
    labels = ["sizeof", "alignof"] + names
    return [(labels[k], host[k], device.get(k)) for k in range(len(host)) if device.get(k) != host[k]]


# ---- the driver: modules per device, launches on torch's stream

_LOCK = threading.Lock()
_MODULES = {}  # (device index, program, dtype) -> (CUmodule, {name: CUfunction}, how it was loaded)


def _driver():
    from cuda.bindings import driver
    return driver


def _check(result, what):
    driver = _driver()
    err = result[0] if isinstance(result, tuple) else result
    if err != driver.CUresult.CUDA_SUCCESS:
        _, text = driver.cuGetErrorString(err)
        raise RuntimeError(f"torch_appearance: {what} failed: {err.name if hasattr(err, 'name') else err} "
                           f"({text.decode() if isinstance(text, bytes) else text})")
    return result[1:] if isinstance(result, tuple) and len(result) > 1 else None


def _options():
    return (f"-DTA_CUDA_TAPE_SEGMENTS={TAPE_SEGMENTS}",)


def _module(device, program, dtype):
    """The loaded module of ``program`` for ``dtype`` on ``device`` (torch's primary context of that device)."""
    index = device.index if device.index is not None else torch.cuda.current_device()
    key = (index, program, dtype)
    with _LOCK:
        if key in _MODULES:
            return _MODULES[key]
        driver = _driver()
        with torch.cuda.device(index):
            torch.cuda.current_stream()  # torch's context of the device is current on this thread
            (ctx,) = _check(driver.cuCtxGetCurrent(), "cuCtxGetCurrent")
            if int(ctx) == 0:
                _check(driver.cuInit(0), "cuInit")
                (dev,) = _check(driver.cuDeviceGet(index), "cuDeviceGet")
                (ctx,) = _check(driver.cuDevicePrimaryCtxRetain(dev), "cuDevicePrimaryCtxRetain")
                _check(driver.cuCtxSetCurrent(ctx), "cuCtxSetCurrent")
            major, minor = torch.cuda.get_device_capability(index)
            errors = []
            for arch in (f"sm_{major}{minor}", f"compute_{major}{minor}"):  # the cubin, else the driver JITs PTX
                try:
                    code = cuda_kernels.compile_program(program, dtype, arch, options=_options()).code
                    (module,) = _check(driver.cuModuleLoadData(code), f"cuModuleLoadData ({program} {dtype} {arch})")
                    break
                except Exception as exc:  # noqa: BLE001 - tried in turn, all reported
                    errors.append(str(exc))
            else:
                raise RuntimeError("torch_appearance: the CUDA kernels do not load on this GPU:\n" + "\n".join(errors))
            functions = {}
            for name in cuda_kernels.kernel_names(program, dtype):
                (functions[name],) = _check(driver.cuModuleGetFunction(module, name.encode()),
                                            f"cuModuleGetFunction {name}")
            _MODULES[key] = (module, functions, arch)
        return _MODULES[key]


def _launch(device, program, dtype, name, threads, args):
    """Launches kernel ``name`` with ``threads`` threads (blocks of :data:`BLOCK`) on torch's current stream."""
    if threads <= 0:
        return
    driver = _driver()
    _, functions, _ = _module(device, program, dtype)
    with torch.cuda.device(device):  # the device's (primary) context is current for the launch
        stream = torch.cuda.current_stream(device).cuda_stream
        address, alive = kernel_params(args)
        blocks = (threads + BLOCK - 1) // BLOCK
        _check(driver.cuLaunchKernel(functions[name], blocks, 1, 1, BLOCK, 1, 1, 0, driver.CUstream(stream), address,
                                     0), f"cuLaunchKernel {name}")
    del alive  # the driver copied the parameters at the launch


def _paths(options, count):
    return count * options.spp * (3 if options.lanes == 1 else 1)


def _launches(total):
    """(first, paths) of the launches of a job of ``total`` paths."""
    for first in range(0, total, PATHS_PER_LAUNCH):
        yield first, min(PATHS_PER_LAUNCH, total - first)


def _image(device, dtype, scene_bytes, options, grid_shape, count, acc):
    shape = image_shape(options, grid_shape)
    rank, world = options.part_rank, options.part_world
    out = (torch.zeros if world > 1 else torch.empty)(shape, dtype=dtype, device=device)
    d = _dtype_name(dtype)
    _launch(device, "forward", d, f"ta_image_{d}", count,
            [scene_bytes.numpy().tobytes(), pack_launch(rank, world, count, 0, count), pointer(acc), pointer(out)])
    return out


def _elements(options, grid_shape):
    shape = image_shape(options, grid_shape)
    n = 1
    for s in shape[:-1]:
        n *= s
    return n


def _scene_bytes_on_device(options, grid_shape, dtype, cells):
    """Bytes the relocated scene's own buffers take on the device (an upper bound): the SDF's corners, cell kinds
    and brick distances (twice: skip and core), the texels' points, normals and radii, the environment map."""
    item = 4 if dtype == torch.float32 else 8
    D, H, W = grid_shape
    total = 0
    if options.boundary.kind == 1:
        total += (D + 1) * (H + 1) * (W + 1) * item + cells + 2 * (-(-D // 4)) * (-(-H // 4)) * (-(-W // 4))
    if options.sensor.kind == 1:
        total += int(options.sensor.points.shape[0]) * 7 * item
    if options.emitter.kind == 1:
        total += int(options.emitter.map.numel()) * item
    return total


def check_device_memory(device, needed, what):
    """Refuses a job whose new device buffers (``needed`` bytes) exceed what the device has free, counting the memory
    torch's allocator holds but does not use, before anything is built or launched.

    Raises:
        ValueError: one line with the bytes needed and free.
    """
    free, _ = torch.cuda.mem_get_info(device)
    free += torch.cuda.memory_reserved(device) - torch.cuda.memory_allocated(device)
    if needed > free:
        raise ValueError(f"{what}: needs {needed / 2**30:.2f} GiB more on {device}, which has {free / 2**30:.2f} GiB "
                         f"free ({needed} > {free} bytes); render on the CPU, or a smaller grid, fewer texels or "
                         f"pixels")


def scene_forward(sigma_t, albedo, ref_sigma_t, ref_albedo, ratio, options):
    """``_C.scene_forward`` on the grids' CUDA device: (image, :class:`DeviceCounts`)."""
    device = sigma_t.device
    grid_shape = tuple(sigma_t.shape[1:])
    count = share_count(_elements(options, grid_shape), options.part_rank, options.part_world)
    check_device_memory(device, _scene_bytes_on_device(options, grid_shape, sigma_t.dtype, sigma_t.numel() // 3)
                        + count * 3 * 8 + count * 3 * sigma_t.element_size(), "render_scene")
    with torch.cuda.device(device):  # the scene's buffers on the device's current stream, as the launches
        scene_bytes, keep = _C.scene_to_device(sigma_t, albedo, ref_sigma_t, ref_albedo, options, 0.0, 0.0, False,
                                               device)
        return _forward(device, sigma_t.dtype, scene_bytes, options, tuple(sigma_t.shape[1:]), bool(ratio), keep)


def scene_forward_indexed(index, sigma_t_table, albedo_table, options):
    """``_C.scene_forward_indexed`` on the index's CUDA device: (image, :class:`DeviceCounts`)."""
    device = index.device
    grid_shape = tuple(index.shape)
    count = share_count(_elements(options, grid_shape), options.part_rank, options.part_world)
    check_device_memory(device, _scene_bytes_on_device(options, grid_shape, sigma_t_table.dtype, index.numel())
                        + index.numel() + count * 3 * (8 + sigma_t_table.element_size()), "render_scene_indexed")
    with torch.cuda.device(device):
        scene_bytes, keep = _C.scene_to_device_indexed(index, sigma_t_table, albedo_table, options, device)
        return _forward(device, sigma_t_table.dtype, scene_bytes, options, tuple(index.shape), False, keep)


def _forward(device, dtype, scene_bytes, options, grid_shape, ratio, keep):
    count = share_count(_elements(options, grid_shape), options.part_rank, options.part_world)
    acc = torch.zeros((max(count, 1), 3), dtype=torch.float64, device=device)
    counts = torch.zeros(5, dtype=torch.int64, device=device)  # unsigned long long in the kernel
    name = forward_kernel_name(options, dtype, ratio)
    raw = scene_bytes.numpy().tobytes()
    for first, paths in _launches(_paths(options, count)):
        _launch(device, "forward", _dtype_name(dtype), name, paths,
                [raw, pack_launch(options.part_rank, options.part_world, count, first, paths), pointer(acc),
                 pointer(counts)])
    image = _image(device, dtype, scene_bytes, options, grid_shape, count, acc)
    c = counts.tolist()
    del keep  # the scene's buffers: freed in stream order after the kernels that read them
    return image, DeviceCounts(c[0], c[1], c[2], c[3], c[4])


def _check_grad_output(grad_output, sigma_t, expected):
    if grad_output.device != sigma_t.device or grad_output.dtype != sigma_t.dtype:
        raise ValueError(f"grad_output: expected a {sigma_t.dtype} tensor on {sigma_t.device}, got "
                         f"{grad_output.dtype} on {grad_output.device}")
    if grad_output.numel() != expected:
        raise ValueError(f"grad_output: expected {expected} values (the image's), got {grad_output.numel()}")
    if not bool(torch.isfinite(grad_output).all()):
        raise ValueError("grad_output: expected finite values")


def _replay(grad_output, sigma_t, albedo, ref_sigma_t, ref_albedo, need_sigma_t, need_albedo, options,
            sigma_t_floor, albedo_floor, with_image):
    device, dtype = sigma_t.device, sigma_t.dtype
    grid_shape = tuple(sigma_t.shape[1:])
    elements = _elements(options, grid_shape)
    _check_grad_output(grad_output, sigma_t, elements * 3)
    go = grad_output.contiguous()
    support = options.grad_support if options.grad_support is not None and options.grad_support.numel() else None
    N = sigma_t.numel() // 3
    compact = support is not None and (need_sigma_t or need_albedo) and N < (1 << 31)
    gs = ga = image = None
    if not need_sigma_t and not need_albedo and not with_image:
        return None, gs, ga, 0, 0
    count = share_count(elements, options.part_rank, options.part_world)
    grads = (int(need_sigma_t) + int(need_albedo)) * sigma_t.numel() * sigma_t.element_size()
    check_device_memory(device, _scene_bytes_on_device(options, grid_shape, dtype, N) + grads * (2 if compact else 1)
                        + (N * 4 if compact else 0) + (count * 3 * 8 if with_image else 0), "render_scene backward")
    scene_bytes, keep = _C.scene_to_device(sigma_t, albedo, ref_sigma_t, ref_albedo, options, sigma_t_floor,
                                           albedo_floor, True, device)
    rank = None
    if compact:  # deposits into compact buffers of the asked voxels, numbered in grid order (AskedVoxels)
        asked = support.to(device).reshape(-1)
        rank = torch.where(asked, asked.to(torch.int64).cumsum(0) - 1, -1).to(torch.int32)
        plane = int(asked.sum())
        buf_s = torch.zeros(3 * max(plane, 1), dtype=dtype, device=device) if need_sigma_t else None
        buf_a = torch.zeros(3 * max(plane, 1), dtype=dtype, device=device) if need_albedo else None
    else:
        plane = N
        buf_s = torch.zeros_like(sigma_t) if need_sigma_t else None
        buf_a = torch.zeros_like(albedo) if need_albedo else None
    acc = torch.zeros((max(count, 1), 3), dtype=torch.float64, device=device) if with_image else None
    counts = torch.zeros(3, dtype=torch.int64, device=device)
    name = replay_kernel_name(options, dtype)
    raw = scene_bytes.numpy().tobytes()
    for first, paths in _launches(_paths(options, count)):
        _launch(device, "replay", _dtype_name(dtype), name, paths,
                [raw, pack_launch(options.part_rank, options.part_world, count, first, paths), pointer(go),
                 pointer(buf_s), pointer(buf_a), _int64(plane), pointer(rank), pointer(acc), pointer(counts)])
    if with_image:
        image = _image(device, dtype, scene_bytes, options, grid_shape, count, acc)
    if compact:
        keep_flat = support.to(device).reshape(-1)
        if need_sigma_t:
            gs = torch.zeros_like(sigma_t)
            gs.view(3, -1)[:, keep_flat] = buf_s[:3 * plane].view(3, plane)
        if need_albedo:
            ga = torch.zeros_like(albedo)
            ga.view(3, -1)[:, keep_flat] = buf_a[:3 * plane].view(3, plane)
    else:
        gs, ga = buf_s, buf_a
        if support is not None:  # only the asked voxels' gradients are complete: the others are 0
            k = support.to(device).unsqueeze(0)
            if gs is not None:
                gs.mul_(k)
            if ga is not None:
                ga.mul_(k)
    c = counts.tolist()
    del keep
    return image, gs, ga, c[0], c[1]


def scene_backward(grad_output, sigma_t, albedo, ref_sigma_t, ref_albedo, need_sigma_t, need_albedo, options,
                   sigma_t_floor=0.0, albedo_floor=0.0):
    """``_C.scene_backward`` on the grids' CUDA device: (grad_sigma_t or None, grad_albedo or None, scatter events)."""
    with torch.cuda.device(sigma_t.device):
        _, gs, ga, events, _ = _replay(grad_output, sigma_t, albedo, ref_sigma_t, ref_albedo, need_sigma_t,
                                       need_albedo, options, sigma_t_floor, albedo_floor, False)
    return gs, ga, events


def scene_forward_backward(grad_output, sigma_t, albedo, ref_sigma_t, ref_albedo, need_sigma_t, need_albedo, options,
                           sigma_t_floor=0.0, albedo_floor=0.0):
    """``_C.scene_forward_backward`` on the grids' CUDA device: (image, grad_sigma_t, grad_albedo,
    :class:`DeviceCounts` with the walks' scatter events and truncated walks)."""
    with torch.cuda.device(sigma_t.device):
        image, gs, ga, events, cut = _replay(grad_output, sigma_t, albedo, ref_sigma_t, ref_albedo, need_sigma_t,
                                             need_albedo, options, sigma_t_floor, albedo_floor, True)
    return image, gs, ga, DeviceCounts(scatter_events=events, truncated_paths=cut)
