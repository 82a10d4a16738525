"""The tracing core (csrc/core/) is plain C++17 without PyTorch: compile a small program against it with the system
compiler under -Wall -Wextra -pedantic -Werror and run its white-furnace and Beer–Lambert checks
(tests/cpp/core_standalone.cpp)."""
import os
import shutil
import subprocess

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


@pytest.mark.skipif(shutil.which("c++") is None, reason="needs a C++ compiler")
def test_core_compiles_and_runs_without_torch(tmp_path):
    exe = str(tmp_path / "core_standalone")
    subprocess.run(["c++", "-std=c++17", "-O2", "-Wall", "-Wextra", "-pedantic", "-Werror",
                    "-I", os.path.join(ROOT, "csrc"), os.path.join(ROOT, "tests", "cpp", "core_standalone.cpp"),
                    "-o", exe], check=True, capture_output=True, text=True)
    run = subprocess.run([exe], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stdout + run.stderr
    assert "white furnace: 0 bad paths" in run.stdout
