"""Runs that survive their users (issue 24 §5): a locked run folder, a slab too large for memory refused before
any file is written, resume from config.json (conflicting flags refused), Ctrl-C (a checkpoint, a resume hint and a
tracer that stops within moments), checkpoints by wall time, and the quantised slab render without dense copies."""
import json
import os
import re
import subprocess
import sys
import textwrap

import numpy as np
import pytest
import torch

from torch_appearance import io as ta_io
from torch_appearance.fabrication import InkSet
from torch_appearance.fabrication.quantize import micro_grid_pitch, quantize_mixture
from torch_appearance.nn.mixture import mix_inks
from torch_appearance.pipelines.print import PrintConfig, optimize_print
from torch_appearance.pipelines.print import loop as print_loop
from torch_appearance.pipelines.print.baselines import render_quantized, render_slab
from torch_appearance.pipelines.print.rendering import render_indexed, slab_scene
from torch_appearance.pipelines.print.slab_target import SlabTarget, slab_memory_bytes
from torch_appearance.pipelines.runs import RunInterrupted, check_memory, lock_run_folder
from torch_appearance.print_error import EVAL_RENDERS
from torch_appearance.testing import command_argv, interrupt_when, run_command, sigint_default, tiny_print_target

QUIET = dict(progress=False, log=lambda *_: None)


def small_cfg(tmp_path, **kw):
    base = dict(target=tiny_print_target(tmp_path / "t.exr"), thickness_mm=0.34, spp=2, eval_spp=4, eval_every=2,
                table_steps=2, iterations=4, out=str(tmp_path / "run"), seed=5)
    base.update(kw)
    return PrintConfig(**base)


def command_env():
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONUNBUFFERED="1")
    return env


def cli(*args):
    return [sys.executable, "-m", "torch_appearance.cli.optimize_print", *[str(a) for a in args]]


# ------------------------------------------------------------------------------------------------ the lock
def test_a_locked_run_folder_is_refused(tmp_path):
    cfg = small_cfg(tmp_path)
    with lock_run_folder(cfg.out):  # another run holds the folder
        with pytest.raises(ValueError, match="out: .* is in use by another run"):
            optimize_print(cfg, **QUIET)
        assert os.listdir(cfg.out) == []  # nothing written beside the other run
    optimize_print(cfg, **QUIET)  # the lock goes with its holder
    assert os.path.isfile(os.path.join(cfg.out, "summary.json"))


def test_two_concurrent_commands_on_one_folder(tmp_path):
    """Two ta-optimize-print processes started together on one --out: one runs, the other exits 2 with one line
    (refused by the lock, or by the finished run's checkpoint if it came late), and the folder holds one run."""
    target = tiny_print_target(tmp_path / "t.exr", 12, 16)
    out = tmp_path / "run"
    args = ["--target", target, "--thickness-mm", "0.34", "--spp", "2", "--eval-spp", "4", "--iterations", "6",
            "--eval-every", "3", "--table-steps", "2", "--quiet", "--out", out]
    procs = [subprocess.Popen(cli(*args, "--seed", seed), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                              env=command_env()) for seed in (1, 2)]
    results = [(p.wait(timeout=600), p.stderr.read()) for p in procs]
    codes = sorted(rc for rc, _ in results)
    assert codes == [0, 2], results
    refused = next(err for rc, err in results if rc == 2).strip()
    assert len(refused.splitlines()) == 1 and ("in use by another run" in refused or "already holds a run" in refused)
    seed = json.load(open(out / "config.json"))["seed"]
    winner = [k for k, (rc, _) in enumerate(results) if rc == 0][0] + 1
    assert seed == winner  # the summary and config describe the run that ran


# ------------------------------------------------------------------------------------------------ memory
def test_slab_too_large_is_refused_before_any_file(tmp_path):
    out = tmp_path / "run"
    rc, _, err = run_command("optimize_print", "--target", tiny_print_target(tmp_path / "t.exr"), "--width-mm", "2000",
                             "--out", out, "--quiet")
    assert rc == 2 and len(err.strip().splitlines()) == 1
    assert re.search(r"--width-mm/--height-mm: a 23622×17717×12-voxel slab \(2000\.0 × 1500\.\d × 1 mm at 300 DPI\) "
                     r"needs about \d+\.\d GiB of memory, this (machine has|process may use)", err), err
    assert "GiB of memory" in err and "--dpi" in err
    assert not out.exists()


def test_slab_memory_check_against_a_given_budget(tmp_path):
    cfg = small_cfg(tmp_path)
    inks = InkSet.from_names()
    need = slab_memory_bytes((cfg.depth, 6, 8), len(inks))
    SlabTarget.from_config(cfg, inks, log=lambda *_: None, available=need + 1)
    with pytest.raises(ValueError, match=r"^target: a 8×6×4-voxel slab .* needs about 0\.4 GiB of memory, this "
                                         r"machine has 0\.0 GiB available"):
        SlabTarget.from_config(cfg, inks, log=lambda *_: None, available=1 << 20)
    check_memory("x", 10, "it", "fix", available=None)  # this machine's own figure: 10 bytes fit


def test_a_slab_of_fewer_than_four_texels_is_refused_by_the_library(tmp_path):
    """``width_mm``/``height_mm`` that round to fewer than MIN_SLAB_TEXELS texels: a ValueError naming the argument
    (the side given, or the one whose aspect made the other too small), not a 1-texel slab."""
    inks = InkSet.from_names()
    quiet = dict(log=lambda *_: None)
    with pytest.raises(ValueError, match=r"^width_mm: a slab 0\.01 mm wide is 0 texels at 300 DPI .* at least 4 "):
        SlabTarget.from_config(small_cfg(tmp_path, width_mm=0.01), inks, **quiet)
    with pytest.raises(ValueError, match=r"^height_mm: a slab 0\.25 mm high is 3 texels"):
        SlabTarget.from_config(small_cfg(tmp_path, width_mm=5.0, height_mm=0.25), inks, **quiet)
    with pytest.raises(ValueError, match=r"^width_mm: a slab 0\.255 mm high \(the height at the target's 8×6 aspect"):
        SlabTarget.from_config(small_cfg(tmp_path, width_mm=0.34), inks, **quiet)
    assert SlabTarget.from_config(small_cfg(tmp_path, width_mm=0.34, height_mm=0.34), inks, **quiet).shape[1:] == (4, 4)


def test_quantised_slab_render_equals_the_dense_one_hot_render():
    """The palette render of a quantised slab (uint8 indices + ink tables, 1 byte per printer voxel) equals, bit for
    bit, the render of the dense one-hot mixture it replaces (σ_t and albedo, 24 bytes per printer voxel): one- and
    two-sided, dielectric and index matched."""
    torch.manual_seed(0)
    inks = InkSet.from_names()
    for ior, faces in ((1.5, 1), (None, 2)):
        cfg = PrintConfig(thickness_mm=0.34, ior=ior)
        w = torch.distributions.Dirichlet(torch.ones(len(inks))).sample((cfg.depth, 5, 6)).permute(3, 0, 1, 2)
        idx = quantize_mixture(w.contiguous(), cfg.voxel_size, cfg.printer_dpi, seed=2)
        edges = micro_grid_pitch((cfg.depth, 5, 6), cfg.voxel_size, cfg.printer_dpi)
        palette = render_indexed(slab_scene(edges, faces=faces, g=0.4, ior=ior), idx, inks, spp=4, seed=9)
        onehot = torch.nn.functional.one_hot(torch.as_tensor(idx.astype(np.int64)), len(inks))
        sigma_t, albedo = mix_inks(onehot.permute(3, 0, 1, 2).float().contiguous(), inks)
        dense = render_slab(sigma_t, albedo, cfg, inks, faces, 4, 9, voxel_size=edges)
        assert torch.equal(palette if faces == 2 else palette[None], dense)
        assert render_quantized(idx, inks, cfg, (5, 6), faces, 4, 9).shape == (faces, 5, 6, 3)


# ------------------------------------------------------------------------------------------------ resume
def test_resume_takes_the_settings_of_config_json(tmp_path):
    out = tmp_path / "run"
    first = ["--target", "zebra", "--width-mm", "1.2", "--thickness-mm", "0.34", "--spp", "2", "--eval-spp", "4",
             "--iterations", "2", "--eval-every", "1", "--table-steps", "2", "--seed", "4", "--quiet", "--out", out]
    assert run_command("optimize_print", *first)[0] == 0
    rc, _, err = run_command("optimize_print", "--out", out, "--resume", "--spp", "8", "--gamma", "1,3,1",
                             "--target", "colorchecker")
    assert rc == 2 and len(err.strip().splitlines()) == 1, err
    assert "--spp 8 (the run has 2)" in err and "--target colorchecker (the run has zebra)" in err
    assert "--gamma" not in err  # given, but equal to the run's
    rc, _, err = run_command("optimize_print", "--out", out, "--resume", "--iterations", "4", "--quiet")
    assert rc == 0, err
    config = json.load(open(out / "config.json"))
    assert (config["target"], config["spp"], config["seed"], config["iterations"]) == ("zebra", 2, 4, 4)
    assert [int(r) for r in ta_io_log_column(out, "iteration")] == [0, 1, 2, 3, 4]
    rc, _, err = run_command("optimize_print", "--out", tmp_path / "none", "--resume")
    assert rc == 2 and "holds no run to resume" in err


def ta_io_log_column(folder, name):
    import csv
    return [row[name] for row in csv.DictReader(open(os.path.join(folder, "log.csv")))]


def test_library_resume_refuses_other_settings(tmp_path):
    cfg = small_cfg(tmp_path, iterations=2)
    optimize_print(cfg, **QUIET)
    import dataclasses
    with pytest.raises(ValueError, match=r"resume: the run in .* other settings: spp 4 \(the run has 2\)"):
        optimize_print(dataclasses.replace(cfg, spp=4, resume=True, iterations=3), **QUIET)
    with pytest.raises(ValueError, match="iterations: the checkpoint .* is at iteration 2; expected at least"):
        optimize_print(dataclasses.replace(cfg, resume=True, iterations=1), **QUIET)


# ------------------------------------------------------------------------------------------------ Ctrl-C
def test_interrupted_and_resumed_equals_uninterrupted(tmp_path, monkeypatch):
    """Ctrl-C inside an iteration's render: the checkpoint holds the iterations done before it, and the resumed run
    ends with the same mixture, bit for bit, as a run never interrupted."""
    import dataclasses
    whole = small_cfg(tmp_path, out=str(tmp_path / "whole"), iterations=5)
    optimize_print(whole, **QUIET)
    parted = dataclasses.replace(whole, out=str(tmp_path / "parted"))
    calls = {"n": 0}
    render = print_loop.SlabTarget.render

    def interrupting(self, *args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 3 * EVAL_RENDERS - 1:  # iteration 3's render (initial evaluation, 1, 2, evaluation at 2, 3)
            raise KeyboardInterrupt
        return render(self, *args, **kwargs)

    monkeypatch.setattr(print_loop.SlabTarget, "render", interrupting)
    with pytest.raises(RunInterrupted, match="interrupted at iteration 2 of 5; the checkpoint is in") as stop:
        optimize_print(parted, **QUIET)
    assert stop.value.iteration == 2 and isinstance(stop.value, KeyboardInterrupt)
    assert torch.load(os.path.join(parted.out, "checkpoint.pt"), weights_only=False)["iteration"] == 2
    monkeypatch.setattr(print_loop.SlabTarget, "render", render)
    optimize_print(dataclasses.replace(parted, resume=True), **QUIET)
    a, b = (np.load(os.path.join(c.out, "mixture.npz"))["weights"] for c in (whole, parted))
    assert np.array_equal(a, b)
    assert ta_io_log_column(whole.out, "loss") == ta_io_log_column(parted.out, "loss")


def test_checkpoints_by_wall_time(tmp_path, monkeypatch):
    """Besides every evaluation, a checkpoint follows any iteration that ends checkpoint_s after the last one."""
    saved = []
    checkpoint = print_loop._Run.checkpoint
    monkeypatch.setattr(print_loop._Run, "checkpoint", lambda self, it, wall: (saved.append(it),
                                                                               checkpoint(self, it, wall)))
    optimize_print(small_cfg(tmp_path, out=str(tmp_path / "a"), eval_every=10, iterations=4), **QUIET)
    assert saved == [4]  # only at the final evaluation
    saved.clear()
    optimize_print(small_cfg(tmp_path, out=str(tmp_path / "b"), eval_every=10, iterations=4, checkpoint_s=1e-9),
                   **QUIET)
    assert saved == [1, 2, 3, 4]


def test_schedule_defaults_follow_the_kind_of_target(tmp_path):
    """spp, iterations, eval_spp and eval_every left at None take the schedule of the target's kind (objects need
    far fewer, cheaper iterations than a slab); given values are kept, and the run records the values it used."""
    from torch_appearance.pipelines.print.config import SCHEDULES
    assert SCHEDULES["object"]["spp"] < SCHEDULES["slab"]["spp"]
    slab, obj = PrintConfig().resolved(), PrintConfig(mesh="m.obj", height_mm=25.0).resolved()
    for name in ("spp", "iterations", "eval_spp", "eval_every"):
        assert getattr(slab, name) == SCHEDULES["slab"][name] and getattr(obj, name) == SCHEDULES["object"][name]
    assert PrintConfig(mesh="m.obj", height_mm=25.0, spp=3).resolved().spp == 3
    with pytest.raises(ValueError, match="spp: expected > 0, got 0"):
        PrintConfig(spp=0).validate()
    cfg = small_cfg(tmp_path, eval_every=None, iterations=2)  # slab: every 50 iterations, and at the last
    optimize_print(cfg, **QUIET)
    config = json.load(open(os.path.join(cfg.out, "config.json")))
    assert (config["eval_every"], config["spp"]) == (SCHEDULES["slab"]["eval_every"], 2)
    assert [r for r in ta_io_log_column(cfg.out, "dE00_mean") if r] != [] and \
        len([r for r in ta_io_log_column(cfg.out, "dE00_mean") if r]) == 2  # iterations 0 and 2


def test_results_reuse_the_last_evaluation(tmp_path, monkeypatch):
    """The continuous result is the last iteration's evaluation render (same state, same seed), not a second render;
    a finished run resumed renders it again and gets the same texels, bit for bit."""
    import dataclasses
    cfg = small_cfg(tmp_path, iterations=2, eval_every=2)
    calls = {"n": 0}
    render = print_loop.SlabTarget.render

    def counting(self, *args, **kwargs):
        calls["n"] += 1
        return render(self, *args, **kwargs)

    monkeypatch.setattr(print_loop.SlabTarget, "render", counting)
    optimize_print(cfg, **QUIET)
    assert calls["n"] == 2 * EVAL_RENDERS + 2  # the initial evaluation, iterations 1 and 2, the evaluation at 2
    first = ta_io.read_exr(os.path.join(cfg.out, "optimized.exr"))
    optimize_print(dataclasses.replace(cfg, resume=True), **QUIET)
    assert calls["n"] == 3 * EVAL_RENDERS + 2  # the resumed run has no evaluation in memory
    assert np.array_equal(first, ta_io.read_exr(os.path.join(cfg.out, "optimized.exr")))


_SLOW_RENDER = textwrap.dedent("""
    import os, signal, threading, time, torch
    import torch_appearance as ta
    torch.set_num_threads(1)
    sigma_t = torch.full((3, 24, 64, 64), 200.0)   # white and thick: a render of a minute or more
    albedo = torch.full((3, 24, 64, 64), 0.9999)
    small = ta.render_texels(sigma_t[:, :2, :4, :4], albedo[:, :2, :4, :4], voxel_size=0.05, spp=2)
    threading.Timer(0.5, os.kill, (os.getpid(), signal.SIGINT)).start()
    start = time.perf_counter()
    try:
        ta.render_texels(sigma_t, albedo, voxel_size=0.05, spp=256)
        print("finished", time.perf_counter() - start)
    except KeyboardInterrupt:
        print("interrupted", round(time.perf_counter() - start, 2))
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler   # Python's handler is back
    again = ta.render_texels(sigma_t[:, :2, :4, :4], albedo[:, :2, :4, :4], voxel_size=0.05, spp=2)
    print("equal after", bool(torch.equal(small, again)))
""")


def test_ctrl_c_stops_the_tracer_within_moments():
    """SIGINT while the C++ tracer runs (GIL released, a render of minutes): it stops between sensor elements and
    Python gets KeyboardInterrupt at once; the next render is unchanged."""
    done = subprocess.run([sys.executable, "-c", _SLOW_RENDER], capture_output=True, text=True, timeout=300,
                          env=command_env(), preexec_fn=sigint_default)
    assert done.returncode == 0, done.stderr
    lines = done.stdout.split("\n")
    assert lines[0].startswith("interrupted"), done.stdout
    assert float(lines[0].split()[1]) < 3.0
    assert lines[1] == "equal after True"


def test_ctrl_c_writes_a_checkpoint_and_says_how_to_resume(tmp_path):
    """SIGINT to a running ta-optimize-print: exit 130 with the resume command and no traceback; the checkpoint
    loads; the same folder resumed with no other flag finishes the run with its settings."""
    out = tmp_path / "run"
    args = ["--target", "zebra", "--width-mm", "3", "--thickness-mm", "0.5", "--spp", "4", "--eval-spp", "4",
            "--iterations", "60", "--eval-every", "1", "--init", "white", "--no-naive-baseline", "--quiet",
            "--out", out]
    rc, _, err = interrupt_when(command_argv("optimize_print", *args), lambda: (out / "checkpoint.pt").exists(), env=command_env())
    assert rc == 130, err
    assert "Traceback" not in err
    assert f"resume with: ta-optimize-print --out {out} --resume" in err
    state = torch.load(out / "checkpoint.pt", weights_only=False)
    assert 1 <= state["iteration"] < 60
    rc, _, err = run_command("optimize_print", "--out", out, "--resume", "--quiet")
    assert rc == 0, err
    assert json.load(open(out / "summary.json"))["iterations"] == 60
    assert [int(r) for r in ta_io_log_column(out, "iteration")] == list(range(61))


def test_ctrl_c_in_the_remap_baseline_points_at_the_outer_run(tmp_path, monkeypatch):
    """Ctrl-C inside the 2.5D remapped baseline's own slab run: the interruption names the object run's folder
    (resuming it resumes the slab run too), not the nested one."""
    glb = os.path.join(os.path.dirname(__file__), "data", "meshes", "BoxTextured.glb")
    cfg = PrintConfig(mesh=glb, height_mm=2.0, dpi=100.0, shell_mm=0.5, spp=2, eval_spp=4, eval_every=2,
                      iterations=2, table_steps=2, printer_dpi=(300.0, 300.0, 300.0), out=str(tmp_path / "run"),
                      remap_baseline=True, views=0)

    def interrupted(*args, **kwargs):
        raise RunInterrupted("interrupted at iteration 1 of 2", str(tmp_path / "run" / "remap25d" / "slab"), 1)

    monkeypatch.setattr(print_loop, "remap_baseline", interrupted)
    with pytest.raises(RunInterrupted, match="2.5D remapped baseline's slab run .* continue this run with --resume") \
            as stop:
        optimize_print(cfg, **QUIET)
    assert stop.value.folder == cfg.out
