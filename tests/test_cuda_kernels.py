"""The tracer's CUDA kernels (csrc/cuda/) compile with the NVRTC of torch's CUDA wheel, without a GPU: every program
(forward, replay; float32 and float64) to PTX for compute_80 and compute_90, with no error and no warning in NVRTC's
log, and every kernel that torch_appearance.render.cuda_kernels names is an entry of the PTX. Also the module's
cache (a second call reads the file; other options, another entry) and its refusals.

Each program and architecture is one test (15-40 s each on 2 shared cores, 3-5 minutes for the file); the cache is a
fresh folder per test, so every test compiles."""
import os
import re

import pytest

from torch_appearance.render import cuda_kernels as ck

nvrtc = pytest.importorskip("cuda.bindings.nvrtc", reason="NVRTC through cuda-bindings (torch's CUDA wheel)")

ARCHS = ("compute_80", "compute_90")


@pytest.fixture
def cache(tmp_path, monkeypatch):
    monkeypatch.setenv("TA_CACHE_DIR", str(tmp_path))
    return tmp_path


def _entries(ptx):
    return {name.decode() for name in re.findall(rb"\.entry\s+(\w+)", ptx)}


@pytest.mark.parametrize("arch", ARCHS)
@pytest.mark.parametrize("dtype", sorted(ck.DTYPES))
@pytest.mark.parametrize("program", sorted(ck.PROGRAMS))
def test_every_kernel_compiles_to_ptx_without_warnings(program, dtype, arch, cache):
    out = ck.compile_program(program, dtype, arch)
    assert out.kind == "ptx" and not out.cached
    assert out.log == "", f"NVRTC said, compiling {program} {dtype} for {arch}:\n{out.log}"
    assert f".target sm_{arch.split('_')[1]}".encode() in out.code
    assert _entries(out.code) == set(out.names)
    assert len(out.names) == (25 if program == "forward" else 12)


def _tiny_csrc(tmp_path):
    """A copy of csrc/'s core and CUDA glue whose forward program is one small kernel (compiles in a second)."""
    import shutil
    root = tmp_path / "csrc"
    shutil.copytree(ck.csrc_dir(), root, ignore=shutil.ignore_patterns("*.cpp", "volpath"))
    (root / "cuda" / "forward.cu").write_text(
        '#include "cuda/launch.cuh"\n'
        'extern "C" __global__ void ta_tiny(float* x) { x[threadIdx.x] = ta::core::tinf<float>(); }\n')
    return root


def test_the_cache_returns_the_same_code_and_keys_the_options(cache, tmp_path, monkeypatch):
    monkeypatch.setenv("TA_CSRC_DIR", str(_tiny_csrc(tmp_path)))
    first = ck.compile_program("forward", "f32", "compute_80")
    assert b".entry ta_tiny" in first.code and not first.cached
    again = ck.compile_program("forward", "f32", "compute_80")
    assert again.cached and again.code == first.code and again.path == first.path and again.log == first.log
    assert os.path.dirname(first.path) == os.path.join(str(cache), "nvrtc")
    assert not [f for f in os.listdir(os.path.dirname(first.path)) if f.startswith(".tmp-")]
    other = ck.compile_program("forward", "f32", "compute_80", options=("-DTA_CUDA_TAPE_SEGMENTS=32",))
    assert not other.cached and other.path != first.path
    assert not ck.compile_program("forward", "f32", "compute_90").cached  # another architecture
    (tmp_path / "csrc" / "core" / "defs.h").write_text(
        (tmp_path / "csrc" / "core" / "defs.h").read_text() + "\n// an edit\n")
    assert not ck.compile_program("forward", "f32", "compute_80").cached  # other sources
    assert not ck.compile_program("forward", "f32", "compute_80", cache=False).cached


def test_nvrtc_errors_carry_the_log(cache, tmp_path, monkeypatch):
    """A broken kernel fails with NVRTC's log naming the file and line (a copy of csrc/ with one error put in)."""
    import shutil
    broken = tmp_path / "csrc"
    shutil.copytree(ck.csrc_dir(), broken, ignore=shutil.ignore_patterns("*.cpp", "volpath"))
    source = (broken / "cuda" / "replay.cu").read_text()
    (broken / "cuda" / "replay.cu").write_text(source.replace("n[2] = two_pass;", "n[2] = two_pass_;"))
    monkeypatch.setenv("TA_CSRC_DIR", str(broken))
    with pytest.raises(ck.NvrtcError, match=r"(?s)cuda/replay\.cu.*two_pass_") as info:
        ck.compile_program("replay", "f32", "compute_80", options=("-DTA_CUDA_TAPE_SEGMENTS=4",))
    assert "identifier \"two_pass_\" is undefined" in info.value.log


def test_refusals_name_the_argument(cache):
    with pytest.raises(ValueError, match="program: expected one of"):
        ck.compile_program("walk", "f32", "compute_90")
    with pytest.raises(ValueError, match="dtype: expected one of"):
        ck.kernel_names("forward", "f16")
    with pytest.raises(ValueError, match="arch: expected 'compute_XY'"):
        ck.compile_program("forward", "f32", "90")
    with pytest.raises(TypeError, match="options: expected a sequence of str"):
        ck.compile_program("forward", "f32", "compute_90", options="-G")


def test_a_missing_nvrtc_is_refused_with_the_fix(cache, monkeypatch):
    import builtins
    real_import = builtins.__import__

    def no_cuda(name, *args, **kwargs):
        if name.startswith("cuda"):
            raise ImportError(f"No module named {name!r}")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_cuda)
    with pytest.raises(RuntimeError, match=r"needs NVRTC through NVIDIA's cuda-bindings.*pip install cuda-bindings"):
        ck.compile_program("forward", "f32", "compute_90")


def test_compiling_leaves_python_s_shared_bytes_alone():
    """NVRTC writes its log and code into buffers of ours: a compilation with an empty log (one NUL byte) once wrote
    into CPython's shared one-byte ``b" "``, after which every torch.load in the process read a stride of 32 as 0 (a
    print run resumed after a GPU render failed in Adagrad)."""
    import io

    import torch

    code = ck.compile_source('extern "C" __global__ void ta_empty_log(long long* out) { out[0] = 1; }\n',
                             "empty_log.cu", "compute_80")
    assert isinstance(code, bytes) and b".entry ta_empty_log" in code
    assert b" "[0] == 32 and bytes([32]).decode() == " "
    buffer = io.BytesIO()
    torch.save(torch.zeros(5, 2, 4, 4), buffer)
    buffer.seek(0)
    assert torch.load(buffer).stride() == (32, 16, 4, 1)
