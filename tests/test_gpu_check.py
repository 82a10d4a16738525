"""The prepared device check (scripts/bench/gpu_check.py) where there is no GPU: its --help, and a run that says
"no GPU", writes its record and exits 2 instead of passing. (On a GPU machine the run itself is the check.)"""
import json
import os
import subprocess
import sys

import pytest
import torch

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SCRIPT = os.path.join(ROOT, "scripts", "bench", "gpu_check.py")


def _run(*args, **env):
    return subprocess.run([sys.executable, SCRIPT, *args], cwd=ROOT, capture_output=True, text=True, timeout=300,
                          env=dict(os.environ, PYTHONPATH=ROOT, **env))


def test_help():
    result = _run("--help")
    assert result.returncode == 0, result.stderr
    assert "usage:" in result.stdout and "--seeds" in result.stdout and "no GPU" in result.stdout


@pytest.mark.skipif(torch.cuda.is_available(), reason="a GPU is present: the check runs instead")
def test_without_a_gpu_it_says_so_and_fails(tmp_path):
    result = _run("--quick", OUT=str(tmp_path))
    assert result.returncode == 2, result.stdout + result.stderr
    assert result.stdout.startswith("gpu_check: no GPU: torch ")
    record = json.loads((tmp_path / "gpu_check.json").read_text())
    assert record["no_gpu"] is True and record["ok"] is False and record["steps"] == []


def test_every_step_runs_against_the_cpu_itself(tmp_path):
    """--device cpu: the script's own logic (scenes, renders on both sides, comparisons, t-tests, gradcheck, stiff
    media) without a GPU; no step may end in a traceback (the statistics themselves are the GPU run's business)."""
    result = _run("--device", "cpu", "--quick", "--seeds", "3", "--spp", "2", "--out", str(tmp_path))
    assert result.returncode in (0, 1), result.stdout + result.stderr
    record = json.loads((tmp_path / "gpu_check.json").read_text())
    names = [s["name"] for s in record["steps"]]
    assert names == ["case slab-diel-l1 float32", "case object-texels-env-l1 float32",
                     "case camera-ortho-disc-hero float32", "case object grad_support f32",
                     "case object adjoint (ema walk) f32", "gradcheck f64", "stiff"]
    assert not [s["name"] for s in record["steps"] if "traceback" in s]
    case = record["steps"][0]
    assert case["image_same_seed"]["max_abs_diff"] == 0.0  # the CPU against itself, same seed: the same image
    assert {"max_t", "bonferroni_bound", "sum_t", "sum_bound"} <= set(case["image_ztest"])
