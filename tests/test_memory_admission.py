"""Memory admission from what the process may really use (issue 49 §5): the smallest of the machine's available
memory, the address-space limit less what is mapped, and the cgroup v2/v1 limit less its usage, read by every guard;
a job the machine's memory would admit is refused under ``ulimit -v`` in one line, before any file."""
import os
import subprocess
import sys

import pytest

from torch_appearance.fabrication import InkSet
from torch_appearance.pipelines.print.slab_target import slab_memory_bytes
from torch_appearance.pipelines.runs import available_memory_bytes, check_memory, memory_limits
from torch_appearance.testing import address_space_limit, tiny_print_target

GiB = 1 << 30
pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="procfs, rlimits and cgroups: Linux")


def _env():
    return dict(os.environ, OMP_NUM_THREADS="1", PYTHONUNBUFFERED="1")


def _mapped_after_import(module):
    """VmSize in bytes of a fresh interpreter that imported ``module`` (what a command maps before its guard)."""
    code = (f"import {module}\n"
            "print([int(l.split()[1]) for l in open('/proc/self/status') if l.startswith('VmSize:')][0] * 1024)")
    return int(subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                              env=_env()).stdout)


def _machine_available():
    return memory_limits().get("MemAvailable") or 0


def test_slab_admitted_by_the_machine_is_refused_under_ulimit_v(tmp_path):
    """A 300² target 10 mm thick (≈ 4.1 GiB) fits the machine's MemAvailable (the former guard admitted it), but not
    an address space of what the command maps at import + 2 GiB: refused in one line, exit 2, no run folder."""
    target = tiny_print_target(tmp_path / "t.exr", 300, 300)
    inks = InkSet.from_names()
    depth = round(10 / (25.4 / 300))
    need = slab_memory_bytes((depth, 300, 300), len(inks))
    if _machine_available() < need + GiB:
        pytest.skip(f"the machine has less than {need / GiB + 1:.1f} GiB available: the former guard refuses too")
    check_memory("target", need, "it", "fix", available=_machine_available())  # the former guard: admitted
    limit = _mapped_after_import("torch_appearance.cli.optimize_print") + 2 * GiB
    out = tmp_path / "run"
    proc = subprocess.run([sys.executable, "-m", "torch_appearance.cli.optimize_print", "--target", target,
                           "--thickness-mm", "10", "--quiet", "--out", str(out)], capture_output=True, text=True,
                          env=_env(), preexec_fn=address_space_limit(limit), timeout=300)
    err = proc.stderr.strip()
    assert proc.returncode == 2, (proc.returncode, err)
    assert len(err.splitlines()) == 1, err
    assert err.startswith("ta-optimize-print: error: --target: a 300×300×"), err
    assert "needs about 4.1 GiB of memory, this process may use" in err, err
    assert "(its address-space limit (ulimit -v))" in err and "--dpi" in err, err
    assert not out.exists()


def test_object_admitted_by_the_machine_is_refused_under_ulimit_v(tmp_path):
    """An object print (Spot at 25 mm, ≈ 2.9 GiB by object_memory_bytes) that the machine's memory admits is refused
    under an address space of what the command maps at import + 2 GiB, after loading the mesh and before voxelising
    it: one line naming --height-mm, exit 2, no run folder."""
    from torch_appearance.pipelines.print.object_target import object_memory_bytes
    spot = os.path.join(os.path.dirname(__file__), "data", "meshes", "spot")
    need = object_memory_bytes(13e6)  # at least: the grid is about 224 × 236 × 262 voxels
    if _machine_available() < need + GiB:
        pytest.skip("the machine refuses this object too")
    limit = _mapped_after_import("torch_appearance.cli.optimize_print") + 2 * GiB
    out = tmp_path / "run"
    proc = subprocess.run([sys.executable, "-m", "torch_appearance.cli.optimize_print", "--mesh",
                           os.path.join(spot, "spot_triangulated.obj"), "--texture",
                           os.path.join(spot, "spot_texture.png"), "--height-mm", "25", "--quiet", "--out", str(out)],
                          capture_output=True, text=True, env=_env(), preexec_fn=address_space_limit(limit),
                          timeout=300)
    err = proc.stderr.strip()
    assert proc.returncode == 2 and len(err.splitlines()) == 1, (proc.returncode, err)
    assert err.startswith("ta-optimize-print: error: --height-mm: a "), err
    assert "-voxel object (" in err and "(its address-space limit (ulimit -v))" in err and "--dpi" in err, err
    assert not out.exists()


def test_render_object_grid_refused_under_ulimit_v(tmp_path):
    """ta-render-object's grid (a 100³ grid admitted by the machine) refused by the address-space limit."""
    from torch_appearance.cli.render_object import BYTES_PER_VOXEL
    n = int(-(-2 * 5.0 // 0.05)) + 4
    need = n ** 3 * BYTES_PER_VOXEL
    if _machine_available() < need + GiB:
        pytest.skip("the machine refuses this grid too")
    limit = _mapped_after_import("torch_appearance.cli.render_object") + min(need // 2, 2 * GiB)
    out = tmp_path / "r"
    proc = subprocess.run([sys.executable, "-m", "torch_appearance.cli.render_object", "--voxel-size", "0.05",
                           "--out", str(out)], capture_output=True, text=True, env=_env(),
                          preexec_fn=address_space_limit(limit), timeout=300)
    err = proc.stderr.strip()
    assert proc.returncode == 2 and len(err.splitlines()) == 1, (proc.returncode, err)
    assert err.startswith(f"ta-render-object: error: --voxel-size: a {n}³-voxel grid"), err
    assert "(its address-space limit (ulimit -v))" in err, err
    assert not out.exists()


def _fake_proc(tmp_path, cgroup, mountinfo, meminfo_kb=64 * 1024 * 1024):
    proc = tmp_path / "proc"
    (proc / "self").mkdir(parents=True)
    (proc / "meminfo").write_text(f"MemTotal: {2 * meminfo_kb} kB\nMemAvailable: {meminfo_kb} kB\n")
    (proc / "self" / "status").write_text("VmSize: 1000 kB\nVmData: 500 kB\n")
    (proc / "self" / "cgroup").write_text(cgroup)
    (proc / "self" / "mountinfo").write_text(mountinfo)
    return str(proc)


def test_cgroup_v2_limit_less_its_usage_binds(tmp_path):
    """cgroup v2: memory.max − (memory.current − inactive_file), the smallest over the cgroup and its parents; "max"
    is no limit."""
    root = tmp_path / "cg2"
    leaf = root / "user.slice" / "job"
    leaf.mkdir(parents=True)
    (root / "user.slice" / "memory.max").write_text(f"{6 * GiB}\n")
    (root / "user.slice" / "memory.current").write_text(f"{1 * GiB}\n")
    (leaf / "memory.max").write_text("max\n")
    (leaf / "memory.current").write_text(f"{GiB // 2}\n")
    proc = _fake_proc(tmp_path, "0::/user.slice/job\n",
                      f"41 23 0:38 / {root} rw,relatime - cgroup2 cgroup2 rw\n")
    assert memory_limits(proc) == {"MemAvailable": 64 * GiB, "cgroup memory.max": 5 * GiB}
    (leaf / "memory.max").write_text(f"{3 * GiB}\n")
    (leaf / "memory.stat").write_text(f"anon 1\ninactive_file {GiB // 4}\n")
    assert memory_limits(proc)["cgroup memory.max"] == 3 * GiB - GiB // 4
    assert available_memory_bytes(proc) == 3 * GiB - GiB // 4


def test_cgroup_v1_limit_and_a_namespaced_view(tmp_path):
    """cgroup v1: memory.limit_in_bytes − usage_in_bytes; 2^63 rounded to a page is no limit; a container that sees
    its own cgroup as the mount's root (the path in /proc/self/cgroup not below the mount) reads the mount point."""
    root = tmp_path / "memory"
    root.mkdir()
    (root / "memory.limit_in_bytes").write_text("9223372036854771712\n")
    (root / "memory.usage_in_bytes").write_text(f"{GiB}\n")
    mountinfo = f"35 31 0:32 /docker/abc {root} rw,relatime - cgroup cgroup rw,memory\n"
    proc = _fake_proc(tmp_path, "4:memory:/docker/abc\n0::/\n", mountinfo, meminfo_kb=8 * 1024 * 1024)
    assert memory_limits(proc) == {"MemAvailable": 8 * GiB}
    (root / "memory.limit_in_bytes").write_text(f"{4 * GiB}\n")
    assert memory_limits(proc) == {"MemAvailable": 8 * GiB, "cgroup memory.limit_in_bytes": 3 * GiB}


def test_check_memory_names_the_limit_that_binds(monkeypatch):
    from torch_appearance.pipelines import runs
    monkeypatch.setattr(runs, "memory_limits", lambda proc="/proc", device=None: {"MemAvailable": 8 * GiB,
                                                                       "cgroup memory.max": 2 * GiB})
    with pytest.raises(ValueError, match=r"^x: it needs about 3\.0 GiB of memory, this process may use 2\.0 GiB "
                                         r"\(its cgroup memory\.max\); fix$"):
        check_memory("x", 3 * GiB, "it", "fix")
    check_memory("x", GiB, "it", "fix")
    monkeypatch.setattr(runs, "memory_limits", lambda proc="/proc", device=None: {"MemAvailable": 2 * GiB})
    with pytest.raises(ValueError, match=r"this machine has 2\.0 GiB available; fix$"):
        check_memory("x", 3 * GiB, "it", "fix")


def test_a_cuda_devices_free_memory_binds_and_is_named(monkeypatch):
    """memory_limits(device=cuda) adds torch.cuda.mem_get_info's free bytes (here faked: no GPU needed); the refusal
    names the GPU when it binds, the host limits when they do; a CPU device or None adds nothing."""
    import torch

    from torch_appearance.pipelines import runs

    calls = []
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "current_device", lambda: 0)
    monkeypatch.setattr(torch.cuda, "mem_get_info", lambda index: (calls.append(index), (GiB // 2, 80 * GiB))[1])
    assert runs.gpu_memory_limits(None) == {} and runs.gpu_memory_limits("cpu") == {} and calls == []
    assert runs.gpu_memory_limits("cuda:1") == {"free memory of cuda:1": GiB // 2} and calls == [1]
    limits = memory_limits(device="cuda")
    assert limits["free memory of cuda:0"] == GiB // 2 and "MemAvailable" in limits
    assert "free memory of cuda:0" not in memory_limits()
    with pytest.raises(ValueError, match=r"^x: it needs about 1\.0 GiB of memory, cuda:0 has 0\.5 GiB free; fix$"):
        check_memory("x", GiB, "it", "fix", device="cuda")
    check_memory("x", GiB, "it", "fix")  # the host's memory alone admits it
    check_memory("x", GiB // 4, "it", "fix", device=torch.device("cuda", 0))


def test_the_wood_fit_admits_its_filter_on_its_device(tmp_path, monkeypatch):
    """ta-fit-wood --p 100000 (a 13 GB chunk: a RuntimeError traceback from the allocator) is refused by its work
    bound (curves longer than the photo); a filter within it that the memory the process may use does not hold (here
    a 16 MiB limit) is refused in one line naming --p/--q before anything is written; with --device cuda the GPU's
    free memory binds and is named."""
    import numpy as np
    import torch

    from torch_appearance import io as ta_io
    from torch_appearance.pipelines import runs
    from torch_appearance.testing import run_command

    photo = tmp_path / "board.png"
    ta_io.write_png(str(photo), np.full((64, 64, 3), 0.5, np.float32))
    out = tmp_path / "fit"
    rc, _, err = run_command("fit_wood", photo, "--p", 100000, "--quiet", "--out", out)
    assert rc == 2 and err.count("\n") == 1, err
    assert err.startswith("ta-fit-wood: error: --p: expected at most 128 (the 64 × 64 px photo's height + width"), err
    with monkeypatch.context() as patch:
        patch.setattr(runs, "memory_limits", lambda proc="/proc", device=None: {"MemAvailable": 16 << 20})
        rc, _, err = run_command("fit_wood", photo, "--p", 128, "--quiet", "--out", out)
    assert rc == 2 and err.count("\n") == 1, err
    assert err.startswith("ta-fit-wood: error: --p/--q: the curved Gabor filter of a 64 × 64 photo with curves of "
                          "2p+1 = 257"), err
    assert not out.exists()
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "current_device", lambda: 0)
    monkeypatch.setattr(torch.cuda, "mem_get_info", lambda index: (1 << 20, 80 * GiB))
    rc, _, err = run_command("fit_wood", photo, "--device", "cuda", "--quiet", "--out", out)
    assert rc == 2 and "cuda:0 has 0.001 GiB free" in err, err
    assert not out.exists()
