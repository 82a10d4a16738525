#!/usr/bin/env python
"""Time a print-optimisation step data-parallel over ranks against one process, with two simulated nodes on loopback.

One step is what ``optimize_print`` does per iteration on a slab: ``MaterialMixture`` → σ_t, albedo →
``render_texels`` (through :func:`torch_appearance.distributed.render`) → appearance loss (E1–E3) → backward
(path replay) → Adagrad step. The script runs the same ``--iterations`` steps in each configuration and prints the
seconds per iteration (the first, warm-up iteration excluded) and how far each result is from the single-process,
one-thread run:

    1proc-1thr   one process, 1 torch thread                       (the reference)
    1proc-Nthr   one process, --threads-total torch threads
    nproc        torchrun --nproc_per_node R on one machine, 1 thread per rank
    2nodes       two torchrun launches --nnodes 2 --node_rank 0/1 (--nproc_per_node 1 each) that meet on
                 127.0.0.1 (static --master_addr/--master_port, or --rdzv c10d: --rdzv_backend c10d
                 --rdzv_endpoint), 1 thread per rank: the several-machine command line, on this machine

Checks: the iteration-0 image must equal the single-process image bitwise (every rank traces a fixed interleaved
share of the texels with the global random numbers); the iteration-0 gradient of the logits and the logits after
the last step must agree to float rounding (the gradient grids are summed over ranks in another order). The
communication volume per iteration is counted at the ``all_reduce`` calls (payload bytes per rank: the image
forward, the σ_t and albedo gradient grids backward; a ring all-reduce moves about 2·(R−1)/R of that over each
rank's link).

Every launch runs under a wall-clock ``--timeout``; on a failure or a timeout the launched process groups are
killed (SIGTERM, then SIGKILL) so that no rank is left waiting on a dead peer.

Examples:
    python scripts/bench/bench_distributed.py                                   # all four configurations
    python scripts/bench/bench_distributed.py --width-mm 6 --spp 8 --iterations 3 --configs 1proc-1thr,2nodes
    python scripts/bench/bench_distributed.py --rdzv c10d --json results/bench_distributed.json
"""
import argparse
import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
CONFIGS = ("1proc-1thr", "1proc-Nthr", "nproc", "2nodes")


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], epilog=__doc__.split("\n\n", 1)[1],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--width-mm", type=float, default=6.0, help="slab width and height in mm (default: %(default)s)")
    p.add_argument("--thickness-mm", type=float, default=1.0, help="slab thickness in mm (default: %(default)s)")
    p.add_argument("--dpi", type=float, default=300.0, help="voxel pitch (default: %(default)s)")
    p.add_argument("--spp", type=int, default=4, help="samples per texel per iteration (default: %(default)s)")
    p.add_argument("--iterations", type=int, default=4,
                   help="steps per configuration; the first is a warm-up and not timed (default: %(default)s)")
    p.add_argument("--ranks", type=int, default=2, help="ranks of the nproc configuration (default: %(default)s)")
    p.add_argument("--threads-total", type=int, default=2,
                   help="torch threads of the 1proc-Nthr configuration (default: %(default)s)")
    p.add_argument("--configs", default=",".join(CONFIGS),
                   help=f"comma-separated subset of {', '.join(CONFIGS)} (default: all)")
    p.add_argument("--rdzv", choices=("static", "c10d"), default="static",
                   help="2nodes rendezvous: static (--master_addr/--master_port/--node_rank) or c10d "
                        "(--rdzv_backend c10d --rdzv_endpoint) (default: %(default)s)")
    p.add_argument("--timeout", type=float, default=600.0,
                   help="seconds one configuration may take before its processes are killed (default: %(default)s)")
    p.add_argument("--json", default=None, help="also write the results table to this JSON file")
    p.add_argument("--worker", default=None, help=argparse.SUPPRESS)  # internal: run the steps, write this file
    p.add_argument("--threads", type=int, default=1, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    for name in ("width_mm", "thickness_mm", "dpi"):
        if not getattr(args, name) > 0:
            p.error(f"--{name.replace('_', '-')}: expected > 0, got {getattr(args, name)}")
    for name in ("spp", "ranks", "threads_total", "threads"):
        if getattr(args, name) < 1:
            p.error(f"--{name.replace('_', '-')}: expected >= 1, got {getattr(args, name)}")
    if args.iterations < 2:
        p.error(f"--iterations: expected >= 2 (one warm-up and at least one timed step), got {args.iterations}")
    args.configs = [c.strip() for c in args.configs.split(",") if c.strip()]
    unknown = [c for c in args.configs if c not in CONFIGS]
    if unknown or not args.configs:
        p.error(f"--configs: expected names from {', '.join(CONFIGS)}, got {args.configs}")
    return args


# ------------------------------------------------------------------------------------------------ worker
def worker(args):
    """Run the steps in this process (one rank under torchrun, or alone); rank 0 writes ``args.worker``."""
    import torch
    import torch.distributed as dist

    torch.set_num_threads(args.threads)
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world > 1:
        import datetime
        dist.init_process_group("gloo", timeout=datetime.timedelta(seconds=max(30.0, args.timeout / 2)))
    sent = {"calls": 0, "bytes": 0}
    if world > 1:  # count the payload of every all_reduce (the image forward, the gradient grids backward)
        original = dist.all_reduce

        def counting_all_reduce(tensor, *a, **k):
            sent["calls"] += 1
            sent["bytes"] += tensor.numel() * tensor.element_size()
            return original(tensor, *a, **k)

        dist.all_reduce = counting_all_reduce
    try:
        result = _steps(args, torch)
        result["all_reduce_calls_per_iteration"] = sent["calls"] / args.iterations
        result["all_reduce_bytes_per_iteration"] = sent["bytes"] / args.iterations
        result["world"], result["threads"] = world, torch.get_num_threads()
        if world == 1 or dist.get_rank() == 0:
            import io

            from torch_appearance.io import atomic_write_bytes
            buffer = io.BytesIO()
            torch.save(result, buffer)
            atomic_write_bytes(args.worker, buffer.getvalue())
    finally:
        if world > 1:
            dist.destroy_process_group()


def _steps(args, torch):
    from torch_appearance import distributed
    from torch_appearance.nn.losses import AppearanceLoss
    from torch_appearance.nn.mixture import MaterialMixture
    from torch_appearance.pipelines.print import PrintConfig, build_target
    from torch_appearance.pipelines.print import iteration_seed as _iteration_seed

    cfg = PrintConfig(target="colorchecker", width_mm=args.width_mm, height_mm=args.width_mm,
                      thickness_mm=args.thickness_mm, dpi=args.dpi, spp=args.spp)
    target = build_target(cfg, log=lambda *_: None)
    model = MaterialMixture(target.inks, target.shape)
    optimizer = torch.optim.Adagrad(model.parameters(), lr=cfg.lr)
    criterion = AppearanceLoss(gamma=tuple(cfg.gamma))
    times, first = [], {}
    for it in range(args.iterations):
        if distributed.rank_and_world()[1] > 1:
            torch.distributed.barrier()
        t0 = time.perf_counter()
        sigma_t, albedo = model()
        image = target.render(sigma_t, albedo, cfg.spp, _iteration_seed(cfg.seed, it))
        loss, _ = target.appearance(criterion, image)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        if it == 0:
            first = {"image": image.detach().clone(), "grad": model.logits.grad.detach().clone()}
        optimizer.step()
        times.append(time.perf_counter() - t0)
    return {**first, "logits": model.logits.detach().clone(), "times": times, "grid_dhw": list(target.shape),
            "texels": int(image[..., 0].numel()), "loss_last": float(loss)}


# ------------------------------------------------------------------------------------------------ launcher
def _free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _worker_argv(args, out, threads):
    return [os.path.abspath(__file__), "--worker", out, "--threads", str(threads), "--width-mm", str(args.width_mm),
            "--thickness-mm", str(args.thickness_mm), "--dpi", str(args.dpi), "--spp", str(args.spp),
            "--iterations", str(args.iterations), "--timeout", str(args.timeout)]


def _kill(procs):
    """SIGTERM then SIGKILL the process groups of ``procs`` (torchrun and its ranks) that are still running."""
    for sig in (signal.SIGTERM, signal.SIGKILL):
        alive = [p for p in procs if p.poll() is None]
        for p in alive:
            try:
                os.killpg(p.pid, sig)
            except ProcessLookupError:
                pass
        deadline = time.monotonic() + 5.0
        while any(p.poll() is None for p in alive) and time.monotonic() < deadline:
            time.sleep(0.1)


def _launch(commands, timeout, env):
    """Start ``commands`` together (each in its own session), wait at most ``timeout`` s for all of them; on a
    non-zero exit or the timeout kill the rest and raise RuntimeError with the tail of their output."""
    logs = [tempfile.TemporaryFile(mode="w+") for _ in commands]
    procs = [subprocess.Popen(c, stdout=log, stderr=subprocess.STDOUT, env=env, cwd=ROOT, start_new_session=True)
             for c, log in zip(commands, logs)]
    deadline, error = time.monotonic() + timeout, None
    try:
        while error is None and any(p.poll() is None for p in procs):
            failed = [p for p in procs if p.poll() not in (None, 0)]
            if failed:
                error = f"exit status {failed[0].returncode}"
            elif time.monotonic() > deadline:
                error = f"no result within --timeout {timeout:g} s"
            time.sleep(0.2)
        if error is None and any(p.returncode != 0 for p in procs):
            error = f"exit status {[p.returncode for p in procs]}"
    finally:
        _kill(procs)
    if error is not None:
        tails = []
        for c, log in zip(commands, logs):
            log.seek(0)
            tails.append(f"$ {' '.join(c)}\n" + "".join(log.readlines()[-15:]))
        raise RuntimeError(f"{error}; the launched processes were stopped.\n" + "\n".join(tails))


def run_config(name, args, folder):
    """Run one configuration; returns the worker's result dict plus ``wall_s`` (launch to exit)."""
    out = os.path.join(folder, f"{name}.pt")
    env = dict(os.environ)
    env["PYTHONPATH"] = ROOT + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    for key in ("WORLD_SIZE", "RANK", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT"):  # not inherited from a launcher
        env.pop(key, None)
    run = [sys.executable, "-m", "torch.distributed.run"]
    if name == "1proc-1thr":
        commands = [[sys.executable] + _worker_argv(args, out, 1)]
    elif name == "1proc-Nthr":
        commands = [[sys.executable] + _worker_argv(args, out, args.threads_total)]
    elif name == "nproc":
        commands = [run + ["--nproc_per_node", str(args.ranks), "--master_addr", "127.0.0.1", "--master_port",
                           str(_free_port())] + _worker_argv(args, out, 1)]
    else:
        port = str(_free_port())
        if args.rdzv == "static":
            commands = [run + ["--nnodes", "2", "--node_rank", str(k), "--nproc_per_node", "1", "--master_addr",
                               "127.0.0.1", "--master_port", port] + _worker_argv(args, out, 1) for k in (0, 1)]
        else:
            commands = [run + ["--nnodes", "2", "--nproc_per_node", "1", "--rdzv_backend", "c10d", "--rdzv_endpoint",
                               f"127.0.0.1:{port}", "--rdzv_id", f"bench{port}"] + _worker_argv(args, out, 1)
                        for _ in (0, 1)]
    env["OMP_NUM_THREADS"] = str(args.threads_total if name == "1proc-Nthr" else 1)
    t0 = time.perf_counter()
    _launch(commands, args.timeout, env)
    import torch
    result = torch.load(out, weights_only=False)
    result["wall_s"] = time.perf_counter() - t0
    result["commands"] = [" ".join(c) for c in commands]
    return result


def main(argv=None):
    args = parse_args(argv)
    if args.worker is not None:
        worker(args)
        return 0
    import torch
    from torch_appearance.progress import progress_bar
    configs = args.configs if "1proc-1thr" in args.configs else ["1proc-1thr"] + args.configs
    rows, ref = [], None
    with tempfile.TemporaryDirectory(prefix="bench_distributed_") as folder:
        bar = progress_bar(configs, desc="bench_distributed", unit="config")
        for name in bar:
            bar.set_postfix_str(name)
            try:
                r = run_config(name, args, folder)
            except RuntimeError as error:
                print(f"bench_distributed.py: {name} failed: {error}", file=sys.stderr)
                return 1
            if ref is None:
                ref = r
            timed = r["times"][1:]
            image_equal = bool(torch.equal(r["image"], ref["image"]))
            scale = float(ref["grad"].abs().max())
            rows.append({
                "config": name, "ranks": r["world"], "threads_per_rank": r["threads"],
                "s_per_iteration": sum(timed) / len(timed), "first_iteration_s": r["times"][0], "wall_s": r["wall_s"],
                "image_equal": image_equal,
                "image_max_abs_diff": float((r["image"] - ref["image"]).abs().max()),
                "grad_max_abs_diff": float((r["grad"] - ref["grad"]).abs().max()), "grad_max_abs": scale,
                "logits_max_abs_diff": float((r["logits"] - ref["logits"]).abs().max()),
                # Adagrad's first step is lr·g/(|g| + eps): a gradient within round-off of 0 may step by up to lr,
                # so the largest logit difference is not a measure of agreement; the share of large ones is
                "logits_share_diff_gt_1e-3": float(((r["logits"] - ref["logits"]).abs() > 1e-3).double().mean()),
                "loss_last_rel_diff": abs(r["loss_last"] - ref["loss_last"]) / abs(ref["loss_last"]),
                "all_reduce_calls_per_iteration": r["all_reduce_calls_per_iteration"],
                "all_reduce_bytes_per_iteration": r["all_reduce_bytes_per_iteration"],
                "commands": r["commands"]})
    base = rows[0]["s_per_iteration"]
    first = rows[0]
    print(f"\nslab {ref['grid_dhw']} voxels (D, H, W), {ref['texels']} texels, {args.spp} spp, float32, "
          f"{args.iterations - 1} timed iterations; load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} CPUs")
    print(f"{'config':12s} {'ranks':>5s} {'thr':>4s} {'s/it':>8s} {'speed-up':>8s} {'image':>7s} "
          f"{'|Δgrad|max':>11s} {'Δlogits>1e-3':>12s} {'Δloss rel':>9s} {'all_reduce B/it':>16s}")
    for r in rows:
        print(f"{r['config']:12s} {r['ranks']:5d} {r['threads_per_rank']:4d} {r['s_per_iteration']:8.3f} "
              f"{base / r['s_per_iteration']:8.2f} {'equal' if r['image_equal'] else 'DIFFER':>7s} "
              f"{r['grad_max_abs_diff']:11.3g} {r['logits_share_diff_gt_1e-3']:12.2%} {r['loss_last_rel_diff']:9.1e} "
              f"{r['all_reduce_bytes_per_iteration']:16,.0f}")
    print(f"(|grad| max {first['grad_max_abs']:.3g}; image max |Δ| of every row: "
          f"{max(r['image_max_abs_diff'] for r in rows):.3g}; Δlogits>1e-3: share of the logits that differ by more "
          f"than 1e-3 after the last step (largest: {max(r['logits_max_abs_diff'] for r in rows):.3g}; Adagrad's "
          f"first step lr·g/(|g| + eps) turns round-off in gradients near 0 into steps of up to lr))")
    if args.json:
        from torch_appearance.io import write_json
        write_json(args.json, {"settings": {k: v for k, v in vars(args).items() if k != "worker"},
                               "grid_dhw": ref["grid_dhw"], "texels": ref["texels"], "rows": rows})
    ok = all(r["image_equal"] for r in rows)
    if not ok:
        print("bench_distributed.py: an image differs from the single-process image", file=sys.stderr)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
