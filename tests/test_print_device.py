"""``ta-optimize-print --device`` and the print loop's device: the CPU gives the run it gave without the flag, bit for
bit; a GPU that is not there is refused before any work; ``auto`` says what it chose and why; an iteration reads one
thing back from its device, the log row; a checkpoint holds CPU tensors. (No GPU here: a faked one only checks the
selection, never a render.)"""
import csv
import json
import os
import re

import pytest
import torch

from torch_appearance.pipelines import PrintConfig, optimize_print
from torch_appearance.pipelines.print import config as print_config
from torch_appearance.pipelines.print import loop
from torch_appearance.testing import run_command, tiny_print_target

no_gpu = pytest.mark.skipif(torch.cuda.is_available(), reason="a GPU is present")


def _flags(tmp_path, iterations=3):
    target = tiny_print_target(tmp_path / "t.exr", 4, 4)
    return ["--target", target, "--thickness-mm", "0.17", "--spp", "2", "--eval-spp", "4", "--eval-every", "2",
            "--iterations", iterations, "--table-steps", "1", "--quiet"]


def _log(folder):
    """log.csv without its wall times."""
    return [{k: v for k, v in row.items() if k != "wall_s"} for row in csv.DictReader(open(folder / "log.csv"))]


@no_gpu
def test_device_cpu_is_the_run_without_the_flag_bit_for_bit(tmp_path):
    flags = _flags(tmp_path)
    rc, out, err = run_command("optimize_print", *flags, "--out", tmp_path / "auto")
    assert rc == 0, err
    # auto chose the CPU and said why, in one line, before the run's own lines
    assert out.splitlines()[0] == ("device: cpu (--device auto: no CUDA device is visible to torch "
                                   "(torch.cuda.is_available() is False))"), out
    rc, out, err = run_command("optimize_print", *flags, "--device", "cpu", "--out", tmp_path / "cpu")
    assert rc == 0, err
    assert out.splitlines()[0] == "device: cpu"
    for name in ("mixture.npz", "quantized.npz", "final.exr", "optimized.exr", "baseline.exr", "initial.exr"):
        assert (tmp_path / "auto" / name).read_bytes() == (tmp_path / "cpu" / name).read_bytes(), name
    assert _log(tmp_path / "auto") == _log(tmp_path / "cpu")
    for run in ("auto", "cpu"):
        assert json.loads((tmp_path / run / "summary.json").read_text())["device"] == "cpu"
        assert json.loads((tmp_path / run / "config.json").read_text())["device"] == "cpu"


@no_gpu
@pytest.mark.parametrize("device", ["cuda", "cuda:1"])
def test_device_cuda_without_a_gpu_is_refused_before_any_work(tmp_path, device):
    out = tmp_path / "run"
    rc, stdout, err = run_command("optimize_print", *_flags(tmp_path), "--device", device, "--out", out)
    assert rc == 2 and err.count("\n") == 1, err
    assert err.startswith(f"ta-optimize-print: error: --device: {device} cannot be used here: no CUDA device is "
                          f"visible to torch"), err
    assert not out.exists() and stdout == ""


def test_a_bad_device_is_refused_in_the_commands_words(tmp_path):
    rc, _, err = run_command("optimize_print", *_flags(tmp_path), "--device", "tpu", "--out", tmp_path / "run")
    assert rc == 2 and err.count("\n") == 1
    assert "--device: expected auto, cpu, cuda or cuda:N, got 'tpu'" in err
    assert not (tmp_path / "run").exists()


@no_gpu
def test_the_library_refuses_a_device_it_cannot_use(tmp_path):
    target = tiny_print_target(tmp_path / "t.exr", 4, 4)
    with pytest.raises(ValueError, match=r"^device: cuda cannot be used here: no CUDA device is visible"):
        optimize_print(PrintConfig(target=target, thickness_mm=0.17, iterations=1, device="cuda",
                                   out=str(tmp_path / "run")), progress=False, log=lambda *_: None)
    assert not (tmp_path / "run").exists()
    with pytest.raises(ValueError, match=r"^device: expected 'cpu', 'cuda' or 'cuda:N', got 'tpu'$"):
        PrintConfig(device="tpu").validate()
    with pytest.raises(TypeError, match=r"^device: expected 'cpu', 'cuda' or 'cuda:N', got int$"):
        PrintConfig(device=0).validate()


def test_auto_takes_a_gpu_when_torch_sees_one(tmp_path, monkeypatch):
    """A faked GPU checks the selection only: the run it would start is caught before it renders."""
    from torch_appearance.cli import optimize_print as command
    from torch_appearance.render import cuda_launch

    monkeypatch.setattr(cuda_launch, "cuda_unavailable", lambda: None)
    monkeypatch.setattr(torch.cuda, "current_device", lambda: 0)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    monkeypatch.setattr(torch.cuda, "get_device_name", lambda device=None: "Faked GPU")
    monkeypatch.setattr("torch_appearance.pipelines.runs.gpu_memory_limits", lambda device: {})
    started = []
    monkeypatch.setattr(command, "optimize_print", lambda cfg, **kwargs: started.append(cfg))
    rc, out, err = run_command("optimize_print", *_flags(tmp_path), "--out", tmp_path / "run")
    assert rc == 0, err
    assert out.splitlines()[0] == "device: cuda:0 (--device auto: Faked GPU)"
    assert [cfg.device for cfg in started] == ["cuda:0"]


def test_one_usability_check_for_the_library_and_the_commands(tmp_path, monkeypatch, capsys):
    """``cuda_launch.device_unusable`` decides for ``optimize_print`` and ``--device`` alike: with one faked GPU,
    cuda:1 is refused by both in their own words, cuda:0 and the CPU pass."""
    from torch_appearance.cli.command import CommandParser, resolve_device
    from torch_appearance.pipelines.print.loop import _check_device_usable
    from torch_appearance.render import cuda_launch

    monkeypatch.setattr(cuda_launch, "cuda_unavailable", lambda: None)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    monkeypatch.setattr(torch.cuda, "get_device_name", lambda device=None: "Faked GPU")
    expected = "expected cuda:0 ... cuda:0 (the GPUs torch sees), got cuda:1"
    assert cuda_launch.device_unusable("cuda:1") == expected
    assert cuda_launch.device_unusable("cuda:0") is None and cuda_launch.device_unusable("cpu") is None
    assert cuda_launch.device_unusable("meta") == "expected the CPU or a CUDA device, got meta"
    with pytest.raises(ValueError, match=r"^device: " + re.escape(expected) + r"; use device='cpu'$"):
        _check_device_usable("cuda:1")
    _check_device_usable("cuda:0")
    with pytest.raises(SystemExit):
        resolve_device(CommandParser("ta-x", "X."), "cuda:1")
    assert f"--device: {expected}; use --device cpu or auto (see ta-x --help)" in capsys.readouterr().err
    assert resolve_device(CommandParser("ta-x", "X."), "cuda:0") == torch.device("cuda", 0)


def test_a_resumed_run_may_change_its_device():
    """A checkpoint holds CPU tensors: the device is not one of the settings a resumed run must keep."""
    assert "device" in print_config.RESUME_MAY_CHANGE
    assert print_config.config_conflicts(PrintConfig(device="cuda:0"), PrintConfig(device="cpu")) == []


def test_checkpoints_hold_cpu_tensors_and_load_onto_the_cpu(tmp_path, monkeypatch):
    target = tiny_print_target(tmp_path / "t.exr", 4, 4)
    cfg = PrintConfig(target=target, thickness_mm=0.17, spp=2, eval_spp=4, eval_every=2, iterations=2,
                      table_steps=1, out=str(tmp_path / "run"))
    optimize_print(cfg, progress=False, log=lambda *_: None)
    state = torch.load(tmp_path / "run" / "checkpoint.pt", weights_only=False)
    tensors = []

    def walk(value):
        if isinstance(value, torch.Tensor):
            tensors.append(value)
        elif isinstance(value, dict):
            for v in value.values():
                walk(v)
        elif isinstance(value, (list, tuple)):
            for v in value:
                walk(v)

    walk({k: state[k] for k in ("model", "optimizer", "ema")})
    assert tensors and all(t.device.type == "cpu" for t in tensors)
    # a checkpoint of a GPU run is read onto the CPU (the run moves it to its own device)
    loads = []
    real_load = torch.load
    monkeypatch.setattr(torch, "load", lambda *a, **k: loads.append(k.get("map_location")) or real_load(*a, **k))
    summary = optimize_print(PrintConfig(**{**cfg.__dict__, "iterations": 3, "resume": True}), progress=False,
                             log=lambda *_: None)
    assert loads == ["cpu"] and summary["device"] == "cpu"


def test_an_iteration_reads_back_only_its_log_row(tmp_path, monkeypatch):
    """Counts the device→host reads in the optimisation loop, outside its evaluations and checkpoints: ``item``,
    ``tolist``, ``cpu`` and ``numpy`` called from torch_appearance's code, and ``float``/``int``/``bool`` of a tensor
    in the print package's own code: one ``tolist`` per iteration (the log row), nothing else. (Not counted: torch's
    optimisers reading their CPU step counters with ``item``, and the input checks of the tracer's front door and of
    the appearance loss, which take ``bool``/``float`` of reductions.)"""
    counts = {}
    counting = [False]
    package = os.path.join("torch_appearance", "")
    print_package = os.path.join("torch_appearance", "pipelines", "print", "")

    def counted(name, where):
        real = getattr(torch.Tensor, name)

        def wrapper(self, *args, **kwargs):
            import sys
            caller = sys._getframe(1).f_code.co_filename
            if counting[0] and where in caller:
                counts[name] = counts.get(name, 0) + 1
            return real(self, *args, **kwargs)
        return wrapper

    for name in ("item", "tolist", "cpu", "numpy"):
        monkeypatch.setattr(torch.Tensor, name, counted(name, package))
    for name in ("__float__", "__int__", "__bool__"):
        monkeypatch.setattr(torch.Tensor, name, counted(name, print_package))

    def counted_in(method, on):
        real = getattr(loop._Run, method)

        def wrapper(self, *args, **kwargs):
            before, counting[0] = counting[0], on
            try:
                return real(self, *args, **kwargs)
            finally:
                counting[0] = before
        monkeypatch.setattr(loop._Run, method, wrapper)

    counted_in("iterate", True)
    for method in ("evaluate", "score", "checkpoint"):  # once per evaluation or checkpoint, not per iteration
        counted_in(method, False)
    target = tiny_print_target(tmp_path / "t.exr", 4, 4)
    for estimator in ("ema", "plain"):
        counts.clear()
        optimize_print(PrintConfig(target=target, thickness_mm=0.17, spp=2, eval_spp=4, eval_every=5, iterations=5,
                                   table_steps=1, estimator=estimator, out=str(tmp_path / estimator)),
                       progress=False, log=lambda *_: None)
        assert counts == {"tolist": 5}, (estimator, counts)


def test_on_a_gpu_its_free_memory_admits_the_slab(tmp_path, monkeypatch):
    """A faked GPU with 1 MiB free: the slab is refused by the GPU's memory, in one line, before the run folder (the
    selection and the admission only; nothing renders)."""
    from torch_appearance.render import cuda_launch

    monkeypatch.setattr(cuda_launch, "cuda_unavailable", lambda: None)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "current_device", lambda: 0)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    monkeypatch.setattr(torch.cuda, "get_device_name", lambda device=None: "Faked GPU")
    monkeypatch.setattr(torch.cuda, "mem_get_info", lambda index: (1 << 20, 80 << 30))
    out = tmp_path / "run"
    rc, _, err = run_command("optimize_print", *_flags(tmp_path), "--device", "cuda", "--out", out)
    assert rc == 2 and err.count("\n") == 1, err
    assert err.startswith("ta-optimize-print: error: --target: a 4×4×2-voxel slab") and "cuda:0 has 0.0 GiB free" \
        in err, err
    assert not out.exists()
