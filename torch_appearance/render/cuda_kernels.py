"""The tracer's CUDA kernels, compiled at run time with NVRTC: no nvcc, no CUDA toolkit, no CUDA_HOME.

The kernels are thin wrappers in ``csrc/cuda/`` around the same tracing core (``csrc/core/``) that the CPU extension
compiles: one thread per path, the CPU's random streams, atomic gradient deposits. This module compiles them with
the NVRTC that torch's CUDA wheel brings (through NVIDIA's ``cuda-bindings``, module ``cuda.bindings.nvrtc``), for
a virtual architecture (``compute_XY``: PTX) or a real one (``sm_XY``: cubin, for the GPU present), and caches the
result on disk. :mod:`torch_appearance.render.cuda_launch` loads and launches them.

A *program* is one source file for one dtype: ``forward`` (the forward walks and the image of their sums) or
``replay`` (the gradient replay, which with an image is also the one walk of the ``ema`` estimator), each for
``f32`` or ``f64``. :func:`kernel_names` lists its kernels; :func:`compile_program` compiles it::

    >>> kernel_names("replay", "f32")[:2]
    ('ta_replay_f32_l1_box_diel', 'ta_replay_f32_l1_box_matched')
    >>> len(kernel_names("forward", "f64"))  # 3 lane kinds x 2 boundaries x 2 optics x 2 weights, + the image
    25

The cache lives under ``$TA_CACHE_DIR`` or ``~/.cache/torch_appearance`` (folder ``nvrtc``), one file per program,
architecture and key: a hash of the sources (every file of ``csrc/core`` and ``csrc/cuda``), the options, the
architecture and NVRTC's version. Entries are written atomically (a temporary file renamed into place), so
concurrent processes never read half a file.
"""
import hashlib
import json
import os
import tempfile
import time
from dataclasses import dataclass
from typing import Optional, Sequence, Tuple

__all__ = ["PROGRAMS", "DTYPES", "CompiledProgram", "NvrtcError", "kernel_names", "compile_program", "compile_source",
           "csrc_dir",
           "cache_dir", "cuda_include_dirs", "default_arch"]

#: program name -> source file under csrc/
PROGRAMS = {"forward": "cuda/forward.cu", "replay": "cuda/replay.cu"}
#: dtype name -> the value of -DTA_CUDA_DTYPE (csrc/cuda/launch.cuh)
DTYPES = {"f32": 32, "f64": 64}
#: the kernels' configuration names, as csrc/cuda/forward.cu and replay.cu spell them
LANES = ("l1", "l3", "hero")
BOUNDARIES = ("box", "sdf")
OPTICS = ("diel", "matched")
WEIGHTS = ("ratio", "plain")
#: options every program is compiled with: C++17 as the core is written, and no fused multiply-add (the CPU build's
#: -ffp-contract=off), so that a GPU path stays the CPU path up to the rounding of the math functions
BASE_OPTIONS = ("-std=c++17", "--fmad=false")


class NvrtcError(RuntimeError):
    """A program that NVRTC did not compile; ``log`` holds NVRTC's log."""

    def __init__(self, message, log=""):
        super().__init__(message + (f"\n{log}" if log else ""))
        self.log = log


@dataclass(frozen=True)
class CompiledProgram:
    """One compiled program.

    Attributes:
        program: ``forward`` or ``replay``.
        dtype: ``f32`` or ``f64``.
        arch: the architecture it was compiled for (``compute_XY`` or ``sm_XY``).
        code: the PTX text (bytes, NUL-terminated as NVRTC returns it; for ``compute_XY``) or the cubin (``sm_XY``).
        kind: ``"ptx"`` or ``"cubin"``.
        log: NVRTC's log (empty when it had nothing to say; warnings otherwise).
        names: the program's kernels (``extern "C"``, so their names in the code are these).
        options: the NVRTC options used, architecture and include paths included.
        seconds: wall-clock seconds of the compilation (0 when it came from the cache).
        cached: whether it came from the cache.
        path: the cache file of the code (None with the cache off).
    """
    program: str
    dtype: str
    arch: str
    code: bytes
    kind: str
    log: str
    names: Tuple[str, ...]
    options: Tuple[str, ...]
    seconds: float
    cached: bool
    path: Optional[str]


def kernel_names(program, dtype):
    """The kernels of ``program`` (``forward`` or ``replay``) for ``dtype`` (``f32`` or ``f64``), as a tuple of
    ``extern "C"`` names: ``ta_forward_<dtype>_<lanes>_<boundary>_<optics>_<weights>`` and ``ta_image_<dtype>``, or
    ``ta_replay_<dtype>_<lanes>_<boundary>_<optics>``."""
    _check_program(program, dtype)
    if program == "forward":
        names = [f"ta_forward_{dtype}_{lanes}_{b}_{o}_{w}"
                 for lanes in LANES for b in BOUNDARIES for o in OPTICS for w in WEIGHTS]
        return tuple(names + [f"ta_image_{dtype}"])
    return tuple(f"ta_replay_{dtype}_{lanes}_{b}_{o}" for lanes in LANES for b in BOUNDARIES for o in OPTICS)


def _check_program(program, dtype):
    if program not in PROGRAMS:
        raise ValueError(f"program: expected one of {sorted(PROGRAMS)}, got {program!r}")
    if dtype not in DTYPES:
        raise ValueError(f"dtype: expected one of {sorted(DTYPES)}, got {dtype!r}")


def csrc_dir():
    """The C++ sources (``csrc/``, holding ``core/`` and ``cuda/``): ``$TA_CSRC_DIR``, else the folder beside the
    package in a source checkout."""
    path = os.environ.get("TA_CSRC_DIR") or os.path.join(
        os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "csrc")
    if not os.path.isfile(os.path.join(path, "cuda", "launch.cuh")):
        raise FileNotFoundError(f"TA_CSRC_DIR: no CUDA sources (cuda/launch.cuh) under {path}; the kernels are "
                                f"compiled from a source checkout of torch_appearance, or set TA_CSRC_DIR to its csrc/")
    return path


def cache_dir():
    """The folder of compiled programs: ``$TA_CACHE_DIR/nvrtc``, else ``~/.cache/torch_appearance/nvrtc``."""
    root = os.environ.get("TA_CACHE_DIR") or os.path.join(os.path.expanduser("~"), ".cache", "torch_appearance")
    return os.path.join(root, "nvrtc")


def cuda_include_dirs():
    """The CUDA headers of the installed NVIDIA wheels (``site-packages/nvidia/cu13/include`` with torch's CUDA 13
    wheel; ``nvidia/cuda_runtime/include`` and ``nvidia/cuda_nvrtc/include`` with the CUDA 12 layout), found on
    ``sys.path`` at run time; an empty tuple when none is installed (the kernels need only NVRTC's built-in headers
    then)."""
    import sys
    found = []
    for base in sys.path:
        for sub in (("cu13", "include"), ("cuda_runtime", "include"), ("cuda_nvrtc", "include")):
            path = os.path.join(base or ".", "nvidia", *sub)
            if os.path.isfile(os.path.join(path, "cuda_runtime.h")) or os.path.isfile(os.path.join(path, "nvrtc.h")):
                path = os.path.realpath(path)
                if path not in found:
                    found.append(path)
    return tuple(found)


def default_arch():
    """``sm_XY`` of the current CUDA device (torch's view), for a cubin that runs there; RuntimeError without one."""
    import torch
    if not torch.cuda.is_available():
        raise RuntimeError("arch: no CUDA device is visible to torch; name a virtual architecture (e.g. "
                           "'compute_90', which compiles to PTX) instead of None")
    major, minor = torch.cuda.get_device_capability()
    return f"sm_{major}{minor}"


def _nvrtc():
    try:
        from cuda.bindings import nvrtc
    except ImportError as exc:
        raise RuntimeError("torch_appearance: compiling the CUDA kernels needs NVRTC through NVIDIA's cuda-bindings "
                           "(module cuda.bindings.nvrtc), which is not importable here: install it with "
                           "`pip install cuda-bindings` (torch's CUDA wheels bring it with NVRTC) "
                           f"({exc})") from exc
    try:
        err, major, minor = nvrtc.nvrtcVersion()
    except Exception as exc:  # the bindings load libnvrtc on first use
        raise RuntimeError(f"torch_appearance: cuda-bindings is installed but NVRTC's library (libnvrtc) does not "
                           f"load: install torch's CUDA wheel or the nvidia-cuda-nvrtc wheel ({exc})") from exc
    _ok(nvrtc, err, "nvrtcVersion")
    return nvrtc, (major, minor)


def _ok(nvrtc, err, what, log=""):
    if err != nvrtc.nvrtcResult.NVRTC_SUCCESS:
        _, text = nvrtc.nvrtcGetErrorString(err)
        raise NvrtcError(f"torch_appearance: {what} failed: {text.decode() if isinstance(text, bytes) else text}",
                         log)


def _check_arch(arch):
    if arch is None:
        return default_arch()
    if not isinstance(arch, str) or not any(
            arch.startswith(p) and arch[len(p):].rstrip("af").isdigit() for p in ("compute_", "sm_")):
        raise ValueError(f"arch: expected 'compute_XY' (PTX), 'sm_XY' (cubin) or None (the current GPU), "
                         f"got {arch!r}")
    return arch


def _sources_hash(root):
    digest = hashlib.sha256()
    for sub in ("core", "cuda"):
        folder = os.path.join(root, sub)
        for name in sorted(os.listdir(folder)):
            path = os.path.join(folder, name)
            if os.path.isfile(path):
                digest.update(f"{sub}/{name}\0".encode())
                with open(path, "rb") as handle:
                    digest.update(handle.read())
                digest.update(b"\0")
    return digest.hexdigest()


def _write_atomic(path, data):
    folder = os.path.dirname(path)
    os.makedirs(folder, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=folder, prefix=".tmp-", suffix=os.path.basename(path))
    try:
        with os.fdopen(fd, "wb") as handle:
            handle.write(data)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def compile_program(program, dtype="f32", arch="compute_90", *, options: Sequence[str] = (), cache=True):
    """Compiles one program of the tracer's CUDA kernels with NVRTC (or takes it from the disk cache).

    Args:
        program: ``"forward"`` or ``"replay"`` (:data:`PROGRAMS`).
        dtype: ``"f32"`` or ``"f64"``: the kernels of that floating-point type.
        arch: ``"compute_XY"`` (a virtual architecture: PTX, which the driver compiles for any newer GPU; needs no
            GPU here), ``"sm_XY"`` (a real one: cubin), or None: ``sm_XY`` of the current CUDA device.
        options: further NVRTC options, e.g. ``("-DTA_CUDA_TAPE_SEGMENTS=128",)`` (the replay's tape per thread).
        cache: read and write the disk cache (:func:`cache_dir`).

    Returns:
        a :class:`CompiledProgram` with the code and NVRTC's log.

    Raises:
        RuntimeError: NVRTC is not available (``cuda-bindings`` missing, or its library does not load).
        NvrtcError: NVRTC did not compile the program (the message holds its log).
    """
    _check_program(program, dtype)
    arch = _check_arch(arch)
    if isinstance(options, str) or not all(isinstance(o, str) for o in options):
        raise TypeError(f"options: expected a sequence of str, got {options!r}")
    nvrtc, version = _nvrtc()
    root = csrc_dir()
    kind = "cubin" if arch.startswith("sm_") else "ptx"
    opts = (BASE_OPTIONS + (f"-DTA_CUDA_DTYPE={DTYPES[dtype]}", f"--gpu-architecture={arch}", f"-I{root}")
            + tuple(f"-I{d}" for d in cuda_include_dirs()) + tuple(options))
    key = hashlib.sha256(json.dumps({"sources": _sources_hash(root), "program": program, "options": opts,
                                     "nvrtc": list(version)}).encode()).hexdigest()[:24]
    path = os.path.join(cache_dir(), f"{program}_{dtype}_{arch}_{key}.{kind}") if cache else None
    names = kernel_names(program, dtype)
    if path is not None and os.path.isfile(path) and os.path.isfile(path + ".log"):
        with open(path, "rb") as handle:
            code = handle.read()
        with open(path + ".log", encoding="utf-8") as handle:
            log = handle.read()
        return CompiledProgram(program, dtype, arch, code, kind, log, names, opts, 0.0, True, path)

    source_name = PROGRAMS[program]
    with open(os.path.join(root, source_name), "rb") as handle:
        source = handle.read()
    start = time.perf_counter()
    code, log = _compile(nvrtc, source, source_name, opts, kind, f"{program}, {dtype}, {arch}")
    seconds = time.perf_counter() - start
    if path is not None:
        _write_atomic(path + ".log", log.encode())  # the log first: the code's presence marks a complete entry
        _write_atomic(path, code)
    return CompiledProgram(program, dtype, arch, code, kind, log, names, opts, seconds, False, path)


def _compile(nvrtc, source, source_name, opts, kind, what):
    """(code, log) of one NVRTC compilation of ``source`` (bytes) with the options ``opts``."""
    err, prog = nvrtc.nvrtcCreateProgram(source, source_name.encode(), 0, [], [])
    _ok(nvrtc, err, "nvrtcCreateProgram")
    try:
        encoded = [o.encode() for o in opts]
        (result,) = nvrtc.nvrtcCompileProgram(prog, len(encoded), encoded)
        err, size = nvrtc.nvrtcGetProgramLogSize(prog)
        _ok(nvrtc, err, "nvrtcGetProgramLogSize")
        # NVRTC writes into the buffer: a bytearray, never a bytes object (``b" " * 1`` is CPython's shared one-byte
        # b" ", which an empty log's NUL would overwrite for the whole process: torch.load then read strides of 32
        # as 0)
        raw = bytearray(size)
        (err,) = nvrtc.nvrtcGetProgramLog(prog, raw)
        _ok(nvrtc, err, "nvrtcGetProgramLog")
        log = bytes(raw).rstrip(b"\0").decode(errors="replace").strip()
        _ok(nvrtc, result, f"NVRTC compiling {source_name} ({what})", log)
        get_size, get = ((nvrtc.nvrtcGetCUBINSize, nvrtc.nvrtcGetCUBIN) if kind == "cubin"
                         else (nvrtc.nvrtcGetPTXSize, nvrtc.nvrtcGetPTX))
        err, size = get_size(prog)
        _ok(nvrtc, err, get_size.__name__)
        code = bytearray(size)
        (err,) = get(prog, code)
        _ok(nvrtc, err, get.__name__)
    finally:
        nvrtc.nvrtcDestroyProgram(prog)
    return bytes(code), log


def compile_source(source, name, arch="compute_90", *, options: Sequence[str] = ()):
    """Compiles a CUDA source text with the options of the tracer's programs (the core's include path, C++17, no
    fused multiply-add), without the cache: e.g. a check of how the device compiler lays out the core's structs.

    Args:
        source: the program's text (str).
        name: its file name, for NVRTC's messages.
        arch: ``compute_XY`` (PTX), ``sm_XY`` (cubin) or None (the current GPU).
        options: further NVRTC options.

    Returns:
        the code (PTX or cubin bytes).

    Raises:
        NvrtcError: NVRTC did not compile it (the message holds its log).
    """
    if not isinstance(source, str) or not isinstance(name, str):
        raise TypeError(f"source, name: expected str, got {type(source).__name__}, {type(name).__name__}")
    arch = _check_arch(arch)
    nvrtc, _ = _nvrtc()
    root = csrc_dir()
    opts = (BASE_OPTIONS + ("-DTA_CUDA_DTYPE=32", f"--gpu-architecture={arch}", f"-I{root}")
            + tuple(f"-I{d}" for d in cuda_include_dirs()) + tuple(options))
    code, _ = _compile(nvrtc, source.encode(), name, opts, "cubin" if arch.startswith("sm_") else "ptx", arch)
    return code
