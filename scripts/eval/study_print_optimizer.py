#!/usr/bin/env python
"""Study of the print optimiser (Nindel et al. 2021): gradient noise/bias and optimiser settings at equal wall time.

Three subcommands, all on the slab target of torch_appearance.pipelines.optimize_print (default: the built-in
ColorChecker, 1 mm, 300 DPI, inks cyan,magenta,yellow,black,white, gamma 1,3,1, evaluation at 64 spp):

  snr      Gradient of the appearance loss with respect to the mixture logits at one fixed state (the initial
           mixture, or the model of an optimize_print checkpoint.pt), over --seeds independent seeds for every
           spp × gradient-seed mode, plus a high-spp reference (mean of --ref-seeds gradients at --ref-spp with
           independent replay seeds). Writes snr.json (SNR median/p90, cosine to the reference, bias estimate,
           per-term and loss-value breakdown) and grads.npz.
  run      One optimisation run with a wall-time budget (optimisation time only; the evaluation renders are
           excluded and logged separately as eval_s). Same seeds, evaluation seed and quantisation seed as
           optimize_print. Estimators: "plain" (the library loop: one render, AppearanceLoss), "mean2" (loss of
           the mean of two independent half-spp renders), "decorr" (two independent half-spp renders C1, C2; E1 is
           replaced by its variance-free form mean((Lab(C1) − T)·(Lab(C2) − T)) = E1(mean) − ¼ mean|Lab C1 − Lab C2|²,
           E2 and E3 are taken of the mean image), "ema" (one render; the loss gradient with respect to the texel
           colours is evaluated at a running mean of the past renders and applied to this render, so the adjoint
           is independent of this render's noise). --init naive starts from the naive extrusion. The budget runs
           on this process's CPU time by default (--budget-clock). Writes log.csv (LOG_FIELDS + cpu_s, eval_s,
           spp_used, eval_E1..3), summary.json (continuous "optimized" and quantised "final" scores, also at
           --final-spp), mixture.npz, final.exr/png.
  baseline The naive-extrusion baseline (quantised, scored like optimize_print) at --eval-spp and --final-spp,
           cached in <study>/baseline.json.
  report   Tables (REPORT_tables.md) and convergence.png (ΔE00 against wall_s, all runs, naive line) from the
           runs under <study>/runs and the snr folders under <study>/snr.

Run it with the package on the path (PYTHONPATH=<checkout> or an installed torch_appearance); use --threads 1 when
several runs share a machine.

Examples:
    python scripts/eval/study_print_optimizer.py baseline --study /tmp/study
    python scripts/eval/study_print_optimizer.py snr --state initial --out /tmp/study/snr/initial
    python scripts/eval/study_print_optimizer.py snr --state /tmp/study/ckpt/checkpoint.pt --out /tmp/study/snr/it25
    python scripts/eval/study_print_optimizer.py run --name adagrad_lr1_s4 --spp 4 --budget-s 240 --study /tmp/study
    python scripts/eval/study_print_optimizer.py run --name decorr_adam --estimator decorr --optimizer adam --lr 0.03 \\
        --spp 4 --budget-s 240 --study /tmp/study
    python scripts/eval/study_print_optimizer.py report --study /tmp/study
"""
import argparse
import csv
import json
import math
import os
import sys
import time

import numpy as np
import torch

from torch_appearance.color import rgb_to_lab
from torch_appearance.nn.losses import AppearanceLoss
from torch_appearance.nn.mixture import MaterialMixture, mix_inks
from torch_appearance.pipelines.print import LOG_FIELDS, PrintConfig, build_target, iteration_seed
from torch_appearance.pipelines.print.baselines import quantize
from torch_appearance.pipelines.print.run_folder import save_image, score
from torch_appearance.print_error import EVAL_RENDERS

def _evaluation(render, spp, seed):
    """(K, F, H, W, 3) the evaluation renders of the print loop: K = EVAL_RENDERS independent renders of spp / K
    spp (``render(spp, seed)``), as :func:`score` takes them."""
    return torch.stack([render(spp // EVAL_RENDERS, iteration_seed(seed, k)) for k in range(EVAL_RENDERS)])


def _score_top(renders, target):
    """The print loop's scores (free of render noise) of the top face of evaluation ``renders``."""
    return score(renders[:, 0], target.target[0])


def _quantize_and_render(target, weights, inks, cfg, spp, seed, quant_seed):
    """Printer-resolution indices of ``weights`` and their evaluation renders (as the print loop scores a result)."""
    indices = quantize(target, weights, inks, cfg, quant_seed)
    prepared = target.prepare_quantized(indices, cfg.printer_dpi)  # once for all its renders
    return indices, _evaluation(lambda n, k: target.render_quantized(prepared, inks, cfg.printer_dpi, n, k), spp,
                                seed)


EXTRA_FIELDS = ["cpu_s", "eval_s", "spp_used"]


# ------------------------------------------------------------------------------------------------ shared setup
def add_common(p):
    p.add_argument("--target", default="colorchecker", help="slab target (default: %(default)s)")
    p.add_argument("--width-mm", type=float, default=None, help="slab width (default: the target's own size)")
    p.add_argument("--dpi", type=float, default=300.0, help="optimisation voxel pitch (default: %(default)s)")
    p.add_argument("--thickness-mm", type=float, default=1.0, help="(default: %(default)s)")
    p.add_argument("--inks", default="cyan,magenta,yellow,black,white", help="(default: %(default)s)")
    p.add_argument("--gamma", default="1,3,1", help="loss weights E1,E2,E3 (default: %(default)s)")
    p.add_argument("--eval-spp", type=int, default=64, help="evaluation renders (default: %(default)s)")
    p.add_argument("--seed", type=int, default=0, help="run seed as in optimize_print (default: %(default)s)")
    p.add_argument("--threads", type=int, default=1, help="torch threads (default: %(default)s)")


def make_cfg(args, **kw):
    gamma = tuple(float(v) for v in args.gamma.split(","))
    return PrintConfig(target=args.target, width_mm=args.width_mm, dpi=args.dpi, thickness_mm=args.thickness_mm,
                       inks=tuple(s.strip() for s in args.inks.split(",")), gamma=gamma, eval_spp=args.eval_spp,
                       seed=args.seed, **kw)


def write_json(path, obj):
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    with open(path + ".tmp", "w") as f:
        json.dump(obj, f, indent=1, default=float)
    os.replace(path + ".tmp", path)


def build_info():
    import torch_appearance as ta
    from torch_appearance._ext import _C
    return {"torch_appearance": os.path.dirname(ta.__file__), "build_hash": _C.source_hash,
            "torch": torch.__version__, "threads": torch.get_num_threads()}


def render_plain(target, model, spp, seed, criterion):
    s, a = model()
    image = target.render(s, a, spp, seed)
    loss, parts = criterion.forward_parts(target.to_grid(image), target.target_grid, target.mask)
    return loss, parts, image


def half_seeds(seed):
    """Two distinct seeds for the two half-spp renders of one iteration (first = the iteration seed)."""
    return seed, iteration_seed(seed, 7)


def render_two(target, model, spp, seed, criterion, estimator):
    """Two independent renders of spp//2 each; loss of their mean ("mean2") or variance-free E1 ("decorr")."""
    half = max(1, spp // 2)
    s, a = model()
    s1, s2 = half_seeds(seed)
    c1 = target.render(s, a, half, s1)
    c2 = target.render(s, a, half, s2)
    mean = 0.5 * (c1 + c2)
    loss, parts = criterion.forward_parts(target.to_grid(mean), target.target_grid, target.mask)
    if estimator == "mean2":
        return loss, parts, mean
    lab_t = rgb_to_lab(target.target.to(c1.dtype), dim=-1)
    e1x = ((rgb_to_lab(c1, dim=-1) - lab_t) * (rgb_to_lab(c2, dim=-1) - lab_t)).sum(-1).mean()
    g1, g2, g3 = criterion.gamma
    total = (g1 * e1x + g2 * parts["E2"] + g3 * parts["E3"]) / (g1 + g2 + g3)
    parts = {"E1": e1x, "E2": parts["E2"], "E3": parts["E3"]}
    return total, parts, mean


def loss_and_image(target, model, spp, seed, criterion, estimator):
    if estimator == "plain":
        return render_plain(target, model, spp, seed, criterion)
    return render_two(target, model, spp, seed, criterion, estimator)


# ------------------------------------------------------------------------------------------------ baseline
def cmd_baseline(args):
    torch.set_num_threads(args.threads)
    cfg = make_cfg(args)
    os.makedirs(args.study, exist_ok=True)
    path = os.path.join(args.study, "baseline.json")
    target = build_target(cfg, log=lambda *a: None)
    inks = target.inks
    eval_seed, quant_seed = iteration_seed(cfg.seed, -1), iteration_seed(cfg.seed, -2)
    t0 = time.perf_counter()
    weights, table = target.naive_weights(inks, cfg)
    out = {"config": {"target": cfg.target, "width_mm": cfg.width_mm, "dpi": cfg.dpi, "grid_dhw": list(target.shape),
                      "eval_spp": cfg.eval_spp, "final_spp": args.final_spp}, "table": table, **build_info()}
    for spp in sorted({cfg.eval_spp, args.final_spp}):
        _, img = _quantize_and_render(target, weights, inks, cfg, spp, eval_seed, quant_seed)
        out[f"quantized_spp{spp}"] = _score_top(img, target)
        with torch.no_grad():
            s, a = mix_inks(weights, inks)
            cont = _evaluation(lambda n, k: target.render(s.contiguous(), a.contiguous(), n, k), spp, eval_seed)
        out[f"continuous_spp{spp}"] = _score_top(cont, target)
    out["seconds"] = time.perf_counter() - t0
    np.save(os.path.join(args.study, "baseline_weights.npy"), weights.numpy())
    write_json(path, out)
    print(json.dumps(out, indent=1, default=float))


# ------------------------------------------------------------------------------------------------ snr
def _grad_sample(target, model, spp, seed, criterion, mode, cfg, per_term=False, adj_spp=40):
    """Gradient of the loss w.r.t. the logits for one seed; optionally the per-term gradients too."""
    if mode == "adjhi":  # the adjoint (loss gradient w.r.t. the texels) at an independent adj_spp render, applied
        cfg.gradient_seed = "same"  # to this spp render: emulates the "ema" estimator's low-noise, independent primal
        model.zero_grad(set_to_none=True)
        s, a = model()
        image = target.render(s, a, spp, seed)
        with torch.no_grad():
            primal = target.render(s.detach(), a.detach(), adj_spp, iteration_seed(seed, 99))
        x = primal.clone().requires_grad_(True)
        value, parts = criterion.forward_parts(target.to_grid(x), target.target_grid, target.mask)
        (adjoint,) = torch.autograd.grad(value, x)
        (adjoint * image).sum().backward()
        row = {"loss": float(value), **{k: float(v) for k, v in parts.items()}}
        return model.logits.grad.detach().reshape(-1).numpy().copy(), row, {}
    estimator = "plain"
    if mode.startswith("decorr"):  # two independent half-spp renders, variance-free E1 ("decorr_ind": their
        estimator = "decorr"       # replays with independent seeds too)
        mode = "independent" if mode == "decorr_ind" else "same"
    cfg.gradient_seed = mode
    model.zero_grad(set_to_none=True)
    loss, parts, image = loss_and_image(target, model, spp, seed, criterion, estimator)
    row = {"loss": float(loss), **{k: float(v) for k, v in parts.items()}}
    terms = {}
    if per_term:
        g = criterion.gamma
        for k, (name, w) in enumerate(zip(("E1", "E2", "E3"), g)):
            if w > 0:
                (gr,) = torch.autograd.grad(w / sum(g) * parts[name], model.logits, retain_graph=True)
                terms[name] = gr.detach().reshape(-1).numpy().copy()
    loss.backward()
    return model.logits.grad.detach().reshape(-1).numpy().copy(), row, terms


def _cos(a, b):
    return float(np.dot(a, b) / (np.linalg.norm(a) * np.linalg.norm(b) + 1e-300))


def _snr_stats(g, ref, ref_noise_var, depth_index, top_layers):
    """Statistics of (n, P) gradients against the reference (P,)."""
    n = g.shape[0]
    mu, sd = g.mean(0), g.std(0, ddof=1)
    snr = np.abs(mu) / np.maximum(sd, 1e-30)
    snr_ref = np.abs(ref) / np.maximum(sd, 1e-30)  # the true signal against this estimator's noise
    top = depth_index < top_layers
    cos_each = np.array([_cos(gi, ref) for gi in g])
    b = mu - ref
    ref2 = float(np.dot(ref, ref))
    # E||mu - ref||² = ||bias||² + Σσ²/n + (reference noise); subtract the two noise terms
    noise_mu = float((sd ** 2).sum() / n)
    bias2 = float(np.dot(b, b)) - noise_mu - ref_noise_var
    along = float(np.dot(mu, ref) / ref2)  # component of the mean along the reference (1 = unbiased there)
    single_rel_noise = float(np.sqrt((sd ** 2).sum() / ref2))
    return {
        "n": int(n),
        "snr_median": float(np.median(snr)), "snr_p90": float(np.percentile(snr, 90)),
        "snr_median_top": float(np.median(snr[top])), "snr_p90_top": float(np.percentile(snr[top], 90)),
        "snr_ref_median": float(np.median(snr_ref)), "snr_ref_p90": float(np.percentile(snr_ref, 90)),
        "snr_ref_median_top": float(np.median(snr_ref[top])), "snr_ref_p90_top": float(np.percentile(snr_ref[top], 90)),
        "frac_snr_gt1": float((snr > 1).mean()), "frac_snr_gt1_top": float((snr[top] > 1).mean()),
        "cos_each_mean": float(cos_each.mean()), "cos_each_min": float(cos_each.min()),
        "cos_each_max": float(cos_each.max()),
        "cos_mean_ref": _cos(mu, ref),
        "mean_along_ref": along,
        "rel_bias": float(math.sqrt(max(bias2, 0.0) / ref2)), "rel_bias_raw": float(np.linalg.norm(b) / math.sqrt(ref2)),
        "rel_noise_single": single_rel_noise,
        "norm_ratio_single": float(np.linalg.norm(g, axis=1).mean() / math.sqrt(ref2)),
        "sign_agree_mean_ref": float((np.sign(mu) == np.sign(ref)).mean()),
        "sign_agree_mean_ref_top": float((np.sign(mu[top]) == np.sign(ref[top])).mean()),
    }


def cmd_snr(args):
    torch.set_num_threads(args.threads)
    cfg = make_cfg(args)
    target = build_target(cfg, log=lambda *a: None)
    criterion = AppearanceLoss(gamma=tuple(cfg.gamma))
    model = MaterialMixture(target.inks, tuple(target.shape), parameterization=cfg.parameterization)
    state_name = "initial"
    if args.state != "initial":
        state = torch.load(args.state, weights_only=False)
        model.load_state_dict(state["model"])
        state_name = f"{args.state} (iteration {state['iteration']})"
    os.makedirs(args.out, exist_ok=True)
    n_inks, (d, h, w) = model.n_inks, target.shape
    # depth of every logit (0 = the top layer, the printed face)
    depth_index = np.broadcast_to((d - 1 - np.arange(d))[None, :, None, None], (n_inks, d, h, w)).reshape(-1)
    base = iteration_seed(args.seed_base, 0)
    t0 = time.perf_counter()
    # reference: mean of ref_seeds independent-replay gradients at ref_spp
    ref_g, ref_rows = [], []
    if args.skip_reference:
        prev = np.load(args.skip_reference)
        ref_g = list(prev["reference_samples"].astype(np.float64))
        prev_json = json.load(open(os.path.join(os.path.dirname(args.skip_reference), "snr.json")))
        ref_rows = [prev_json["reference"]["loss"]] * len(ref_g)
    for k in range(0 if args.skip_reference else args.ref_seeds):
        g, row, _ = _grad_sample(target, model, args.ref_spp, iteration_seed(base, 10_000 + k), criterion,
                                 "independent", cfg)
        ref_g.append(g)
        ref_rows.append(row)
        print(f"snr: reference {k + 1}/{args.ref_seeds} at {args.ref_spp} spp ({time.perf_counter() - t0:.0f} s)",
              flush=True)
    ref_g = np.stack(ref_g)
    ref = ref_g.mean(0)
    ref_noise_var = float((ref_g.var(0, ddof=1)).sum() / len(ref_g)) if len(ref_g) > 1 else 0.0
    half = len(ref_g) // 2
    ref_self_cos = _cos(ref_g[:half].mean(0), ref_g[half:].mean(0)) if half else float("nan")
    args.ref_seeds = len(ref_g)
    result = {"state": state_name, "grid_dhw": [d, h, w], "inks": list(target.inks.names), **build_info(),
              "reference": {"spp": args.ref_spp, "seeds": args.ref_seeds, "mode": "independent",
                            "self_cos_halves": ref_self_cos,
                            "rel_noise_of_ref": float(math.sqrt(ref_noise_var / float(np.dot(ref, ref)))),
                            "loss": {k: float(np.mean([r[k] for r in ref_rows])) for k in ref_rows[0]}},
              "configs": {}}
    arrays = {"reference": ref.astype(np.float32), "reference_samples": ref_g.astype(np.float32)}
    for spp in args.spp:
        for mode in args.modes:
            gs, rows, term_g = [], [], {"E1": [], "E2": [], "E3": []}
            for k in range(args.seeds):
                g, row, terms = _grad_sample(target, model, spp, iteration_seed(base, k), criterion, mode, cfg,
                                             per_term=args.per_term and spp <= 8, adj_spp=args.adj_spp)
                gs.append(g)
                rows.append(row)
                for name, v in terms.items():
                    term_g[name].append(v)
            gs = np.stack(gs)
            key = f"spp{spp}_{mode}"
            stats = _snr_stats(gs, ref, ref_noise_var, depth_index, args.top_layers)
            stats["loss"] = {k: float(np.mean([r[k] for r in rows])) for k in rows[0]}
            stats["loss_std"] = {k: float(np.std([r[k] for r in rows], ddof=1)) for k in rows[0]}
            if args.per_term and term_g["E1"]:
                tn = {name: float(np.linalg.norm(np.mean(v, 0))) for name, v in term_g.items() if v}
                stats["term_norm_of_mean"] = tn
                stats["term_cos_mean_ref"] = {name: _cos(np.mean(v, 0), ref) for name, v in term_g.items() if v}
            result["configs"][key] = stats
            arrays[key] = gs.astype(np.float32)
            print(f"snr: {key}: median SNR {stats['snr_median']:.3f}, cos(g_i, ref) {stats['cos_each_mean']:.3f}, "
                  f"cos(mean, ref) {stats['cos_mean_ref']:.3f}, rel bias {stats['rel_bias']:.3f} "
                  f"({time.perf_counter() - t0:.0f} s)", flush=True)
            write_json(os.path.join(args.out, "snr.json"), result)
    # bias directions: is the 4-spp same-seed bias the 32-spp one scaled (a variance term ∝ 1/spp)?
    keys = [f"spp{s}_same" for s in args.spp if f"spp{s}_same" in arrays]
    if len(keys) >= 2:
        b = {k: arrays[k].mean(0) - ref for k in keys}
        result["bias_direction"] = {f"cos({keys[i]},{keys[j]})": _cos(b[keys[i]], b[keys[j]])
                                    for i in range(len(keys)) for j in range(i + 1, len(keys))}
        result["bias_norm_ratio"] = {k: float(np.linalg.norm(b[k]) / np.linalg.norm(b[keys[-1]])) for k in keys}
    # per-depth-layer gradient magnitude of the reference and noise (4 spp same, if present)
    ref_layer = [float(np.abs(ref[depth_index == z]).mean()) for z in range(d)]
    result["reference_abs_by_depth"] = ref_layer
    for key in [k for k in arrays if k.startswith("spp")]:
        sd = arrays[key].std(0, ddof=1)
        result["configs"][key]["sd_by_depth"] = [float(sd[depth_index == z].mean()) for z in range(d)]
    result["seconds"] = time.perf_counter() - t0
    write_json(os.path.join(args.out, "snr.json"), result)
    np.savez_compressed(os.path.join(args.out, "grads.npz"), **arrays)
    print(json.dumps({k: v for k, v in result.items() if k != "configs"}, indent=1, default=float))


# ------------------------------------------------------------------------------------------------ run
def cmd_run(args):
    torch.set_num_threads(args.threads)
    cfg = make_cfg(args, spp=args.spp, optimizer=args.optimizer, lr=args.lr, gradient_seed=args.gradient_seed)
    cfg.validate()
    folder = os.path.join(args.study, "runs", args.name)
    os.makedirs(folder, exist_ok=True)
    target = build_target(cfg, log=lambda *a: None)
    inks = target.inks
    criterion = AppearanceLoss(gamma=tuple(cfg.gamma))
    model = MaterialMixture(inks, tuple(target.shape), parameterization=cfg.parameterization)
    if args.init == "naive":  # informed start: the naive extrusion's mixtures (logit of the clipped weights)
        w0, _ = target.naive_weights(inks, cfg)
        w0 = w0.double().clamp(args.init_floor, 1.0 - args.init_floor)
        w0 = w0 / w0.sum(0, keepdim=True)
        with torch.no_grad():
            model.logits.copy_(torch.log(w0) - torch.log1p(-w0))
    opt_cls = torch.optim.Adagrad if cfg.optimizer == "adagrad" else torch.optim.Adam
    optimizer = opt_cls(model.parameters(), lr=cfg.lr)
    eval_seed, quant_seed = iteration_seed(cfg.seed, -1), iteration_seed(cfg.seed, -2)
    config = {"name": args.name, "estimator": args.estimator, "optimizer": cfg.optimizer, "lr": cfg.lr,
              "spp": cfg.spp, "gradient_seed": cfg.gradient_seed, "budget_s": args.budget_s, "budget_clock": args.budget_clock, "init": args.init, "ema_beta": args.ema_beta if args.estimator == "ema" else None,
              "eval_every_s": args.eval_every_s, "eval_spp": cfg.eval_spp, "final_spp": args.final_spp,
              "target": cfg.target, "width_mm": cfg.width_mm, "dpi": cfg.dpi, "grid_dhw": list(target.shape),
              "gamma": list(cfg.gamma), "inks": list(inks.names), **build_info()}
    write_json(os.path.join(folder, "config.json"), config)

    def evaluate(spp=cfg.eval_spp):
        with torch.no_grad():
            s, a = model()
            return _evaluation(lambda n, k: target.render(s, a, n, k), spp, eval_seed)

    def eval_row(row):
        t = time.perf_counter()
        renders = evaluate()
        row.update(_score_top(renders, target))
        with torch.no_grad():
            _, parts = criterion.forward_parts(target.to_grid(renders.mean(0)), target.target_grid, target.mask)
        row.update({f"eval_{k}": float(v) for k, v in parts.items()})
        return time.perf_counter() - t

    rows = []
    eval_s = 0.0
    row0 = {"iteration": 0, "wall_s": 0.0, "cpu_s": 0.0, "seed": eval_seed, "spp_used": 0}
    eval_s += eval_row(row0)
    row0["eval_s"] = eval_s
    rows.append(row0)
    fields = LOG_FIELDS + EXTRA_FIELDS + ["eval_E1", "eval_E2", "eval_E3"]

    def flush():
        with open(os.path.join(folder, "log.csv"), "w", newline="") as f:
            wr = csv.DictWriter(f, fieldnames=fields, extrasaction="ignore")
            wr.writeheader()
            for r in rows:
                wr.writerow(r)

    ema = {"sum": None, "k": 0}  # estimator "ema": detached running mean of the renders (the adjoint's primal)

    def ema_step(seed):
        """Loss gradient at the running-mean image (past iterations only), applied to this iteration's render:
        the adjoint is independent of this render's noise, and its primal averages ~1/(1 − β) renders."""
        s_, a_ = model()
        image = target.render(s_, a_, cfg.spp, seed)
        now = image.detach()
        primal = now if ema["k"] == 0 else ema["sum"] / (1.0 - args.ema_beta ** ema["k"])
        x = primal.clone().requires_grad_(True)
        value, parts_ = criterion.forward_parts(target.to_grid(x), target.target_grid, target.mask)
        (adjoint,) = torch.autograd.grad(value, x)
        ema["sum"] = (now * (1.0 - args.ema_beta) if ema["sum"] is None
                      else args.ema_beta * ema["sum"] + (1.0 - args.ema_beta) * now)
        ema["k"] += 1
        return (adjoint * image).sum(), value.detach(), parts_

    opt_wall = opt_cpu = 0.0
    next_eval = args.eval_every_s
    it = 0
    def clock():  # the budget's clock: this process's CPU time (robust to other jobs on a shared machine) or wall
        return opt_cpu if args.budget_clock == "cpu" else opt_wall

    while clock() < args.budget_s:
        t_w, t_c = time.perf_counter(), time.process_time()
        seed = iteration_seed(cfg.seed, it)
        if args.estimator == "ema":
            surrogate, loss, parts = ema_step(seed)
        else:
            loss, parts, _ = loss_and_image(target, model, cfg.spp, seed, criterion, args.estimator)
            surrogate = loss
        optimizer.zero_grad(set_to_none=True)
        surrogate.backward()
        optimizer.step()
        opt_wall += time.perf_counter() - t_w
        opt_cpu += time.process_time() - t_c
        it += 1
        row = {"iteration": it, "wall_s": opt_wall, "cpu_s": opt_cpu, "loss": float(loss),
               **{k: float(v) for k, v in parts.items()}, "seed": seed, "spp_used": cfg.spp}
        if clock() >= next_eval or clock() >= args.budget_s:
            eval_s += eval_row(row)
            next_eval = (math.floor(clock() / args.eval_every_s) + 1) * args.eval_every_s
            print(f"{args.name}: it {it} wall {opt_wall:.0f}s cpu {opt_cpu:.0f}s dE00 {row['dE00_mean']:.2f} loss {row['loss']:.1f}",
                  flush=True)
            flush()
        row["eval_s"] = eval_s
        rows.append(row)
    flush()

    # results: continuous (last evaluation) and quantised, at eval_spp and final_spp
    weights = model.weights().detach()
    np.savez_compressed(os.path.join(folder, "mixture.npz"), weights=weights.numpy().astype(np.float32))
    summary = {**config, "iterations": it, "wall_s": opt_wall, "cpu_s": opt_cpu, "eval_s": eval_s,
               "seconds_per_iteration": opt_wall / max(it, 1)}
    for spp in sorted({cfg.eval_spp, args.final_spp}):
        summary[f"optimized_spp{spp}"] = _score_top(evaluate(spp), target)
        _, img = _quantize_and_render(target, weights, inks, cfg, spp, eval_seed, quant_seed)
        summary[f"final_spp{spp}"] = _score_top(img, target)
        if spp == cfg.eval_spp:
            save_image(folder, "final", img.mean(0)[0].numpy())
    w = weights.double().mean((2, 3)).numpy()[:, ::-1]  # (N, D), depth 0 = top layer
    summary["ink_usage_top_layer"] = dict(zip(inks.names, map(float, w[:, 0])))
    summary["ink_usage_mean"] = dict(zip(inks.names, map(float, w.mean(1))))
    write_json(os.path.join(folder, "summary.json"), summary)
    print(json.dumps({k: summary[k] for k in summary if k.startswith(("optimized", "final", "iterations"))},
                     default=float))


# ------------------------------------------------------------------------------------------------ report
def _read_log(path):
    with open(path) as f:
        return [{k: (float(v) if v not in ("", None) else None) for k, v in r.items()} for r in csv.DictReader(f)]


def _at_time(rows, t, clock="wall_s", tol=1.0):
    """Last evaluated dE00 at or before optimisation time t (+ tol: the evaluation scheduled at t runs after the
    iteration that crosses it) on ``clock`` (wall_s or cpu_s); None if the run ended before t."""
    ev = [r for r in rows if r.get("dE00_mean") is not None]
    if not ev or ev[-1][clock] < t - tol:
        return None
    ev = [r for r in ev if r[clock] <= t + tol]
    return ev[-1]["dE00_mean"] if ev else None


def _first_below(rows, level, clock="wall_s"):
    ev = [r for r in rows if r.get("dE00_mean") is not None and r["dE00_mean"] < level]
    return ev[0][clock] if ev else None


def cmd_report(args):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    base = json.load(open(os.path.join(args.study, "baseline.json")))
    eval_spp, final_spp = base["config"]["eval_spp"], base["config"]["final_spp"]
    naive = base[f"quantized_spp{eval_spp}"]["dE00_mean"]
    naive_hi = base[f"quantized_spp{final_spp}"]["dE00_mean"]
    runs = []
    rdir = os.path.join(args.study, "runs")
    for name in sorted(os.listdir(rdir)) if os.path.isdir(rdir) else []:
        sp = os.path.join(rdir, name, "summary.json")
        if not os.path.exists(sp):
            continue
        runs.append((name, json.load(open(sp)), _read_log(os.path.join(rdir, name, "log.csv"))))
    lines = [f"Naive extrusion (quantised): ΔE00 {naive:.2f} at {eval_spp} spp, {naive_hi:.2f} at {final_spp} spp "
             f"(continuous: {base[f'continuous_spp{eval_spp}']['dE00_mean']:.2f} / "
             f"{base[f'continuous_spp{final_spp}']['dE00_mean']:.2f}).", ""]
    checkpoints = [float(t) for t in args.times.split(",")]
    clock = f"{args.clock}_s"
    lines += [f"Times are optimisation {args.clock} seconds (column {clock} of log.csv; evaluation renders excluded).", ""]
    head = ("| run | estimator | optimiser | lr | spp | grad seed | it | s/it | cpu/wall | " +
            " | ".join(f"ΔE00 @{t:g}s" for t in checkpoints) +
            f" | optimized @{eval_spp} | final @{eval_spp} | optimized @{final_spp} | final @{final_spp} | "
            f"first < naive [s] |")
    lines += [head, "|" + "---|" * (head.count("|") - 1)]
    for name, s, rows in runs:
        at = [(_at_time(rows, t, clock)) for t in checkpoints]
        fb = _first_below(rows, naive, clock)
        lines.append(
            f"| {name} | {s['estimator']} | {s['optimizer']} | {s['lr']:g} | {s['spp']} | {s['gradient_seed']} | "
            f"{s['iterations']} | {s['seconds_per_iteration']:.2f} | {s['cpu_s'] / max(s['wall_s'], 1e-9):.2f} | " +
            " | ".join("–" if v is None else f"{v:.2f}" for v in at) +
            f" | {s[f'optimized_spp{eval_spp}']['dE00_mean']:.2f} | {s[f'final_spp{eval_spp}']['dE00_mean']:.2f} | "
            f"{s[f'optimized_spp{final_spp}']['dE00_mean']:.2f} | {s[f'final_spp{final_spp}']['dE00_mean']:.2f} | "
            f"{'–' if fb is None else f'{fb:.0f}'} |")
    lines.append("")
    # SNR tables
    sdir = os.path.join(args.study, "snr")
    for name in sorted(os.listdir(sdir)) if os.path.isdir(sdir) else []:
        sp = os.path.join(sdir, name, "snr.json")
        if not os.path.exists(sp):
            continue
        r = json.load(open(sp))
        ref = r["reference"]
        lines += [f"SNR at state **{name}** ({r['state']}); reference: mean of {ref['seeds']} gradients at "
                  f"{ref['spp']} spp (independent replay), cos between its halves {ref['self_cos_halves']:.3f}, "
                  f"relative noise {ref['rel_noise_of_ref']:.3f}; reference E1 {ref['loss']['E1']:.1f}.", ""]
        head = ("| config | SNR median | SNR p90 | SNR median (top layer) | SNR p90 (top) | ref/σ median (top) | "
                "cos(g_i, ref) mean [min, max] | cos(mean, ref) | mean along ref | rel. bias | rel. noise (1 sample) "
                "| sign agree (top) | E1 mean |")
        lines += [head, "|" + "---|" * (head.count("|") - 1)]
        for key, c in r["configs"].items():
            lines.append(
                f"| {key} | {c['snr_median']:.3f} | {c['snr_p90']:.3f} | {c['snr_median_top']:.3f} | "
                f"{c['snr_p90_top']:.3f} | {c['snr_ref_median_top']:.3f} | {c['cos_each_mean']:.3f} "
                f"[{c['cos_each_min']:.3f}, {c['cos_each_max']:.3f}] | {c['cos_mean_ref']:.3f} | "
                f"{c['mean_along_ref']:.3f} | {c['rel_bias']:.3f} | {c['rel_noise_single']:.2f} | "
                f"{c['sign_agree_mean_ref_top']:.3f} | {c['loss']['E1']:.1f} |")
        if "bias_direction" in r:
            lines.append("")
            lines.append("Bias direction (mean − reference) between spp: " +
                         ", ".join(f"{k} = {v:.3f}" for k, v in r["bias_direction"].items()) +
                         "; norm ratio: " + ", ".join(f"{k} {v:.2f}" for k, v in r["bias_norm_ratio"].items()))
        lines.append("")
    with open(os.path.join(args.study, "REPORT_tables.md"), "w") as f:
        f.write("\n".join(lines) + "\n")
    print("\n".join(lines))

    # left: the library's estimator ("plain") from the white start; right: other estimators and starts, with the
    # plain 4- and 64-spp runs repeated for reference
    groups = [[r for r in runs if r[1]["estimator"] == "plain" and r[1].get("init", "white") == "white"],
              [r for r in runs if r[1]["estimator"] != "plain" or r[1].get("init", "white") != "white"
               or r[0] in args.context.split(",")]]
    titles = ["library loop (one render, AppearanceLoss): optimiser × lr × spp",
              "other estimators / naive start (dashed: decorr, dotted: mean2, solid: ema / plain)"]
    styles = {"plain": "-", "mean2": ":", "decorr": "--", "ema": "-"}
    fig, axes = plt.subplots(1, 2, figsize=(16, 6.5), sharey=True)
    for ax, group, title in zip(axes, groups, titles):
        for k, (name, s, rows) in enumerate(group):
            ev = [r for r in rows if r.get("dE00_mean") is not None]
            lw = 2.2 if s["estimator"] == "ema" else 1.3
            ax.plot([r[clock] for r in ev], [r["dE00_mean"] for r in ev], styles.get(s["estimator"], "-"),
                    marker="o" if s.get("init", "white") == "white" else "^", ms=2.5, lw=lw,
                    color=plt.cm.tab20(k % 20), label=name)
        ax.axhline(naive, color="k", ls=":", lw=2, label=f"naive extrusion, quantised ({naive:.2f})")
        ax.axhline(base[f"continuous_spp{eval_spp}"]["dE00_mean"], color="0.5", ls="-.", lw=1.2,
                   label=f"naive extrusion, continuous ({base[f'continuous_spp{eval_spp}']['dE00_mean']:.2f})")
        ax.set(xlabel=f"optimisation {args.clock} time [s] ({clock}; evaluation renders excluded)",
               title=title, ylim=(args.ymin, args.ymax))
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, ncol=2, loc="upper right")
    axes[0].set_ylabel(f"mean CIEDE2000 of the continuous mixture ({eval_spp}-spp render, fixed seed)")
    fig.suptitle(f"ColorChecker slab {base['config']['grid_dhw']} (D×H×W): ΔE00 against {args.clock} time")
    fig.tight_layout()
    fig.savefig(os.path.join(args.study, args.plot_name), dpi=120)
    print("wrote", os.path.join(args.study, args.plot_name))


# ------------------------------------------------------------------------------------------------ main
def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], epilog=__doc__.split("\n\n", 1)[1],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="cmd", required=True)

    b = sub.add_parser("baseline", help="naive extrusion baseline -> <study>/baseline.json")
    add_common(b)
    b.add_argument("--study", default="/tmp/study")
    b.add_argument("--final-spp", type=int, default=256)

    s = sub.add_parser("snr", help="gradient SNR / bias at one state")
    add_common(s)
    s.add_argument("--state", default="initial", help="'initial' or an optimize_print checkpoint.pt")
    s.add_argument("--spp", type=lambda t: [int(v) for v in t.split(",")], default=[4, 32])
    s.add_argument("--modes", type=lambda t: t.split(","), default=["same", "independent"],
                   help="gradient estimators: same, independent (plain loss, gradient replay with the forward's or an "
                        "independent seed), decorr, decorr_ind (two half-spp renders, variance-free E1), "
                        "adjhi (loss gradient at an independent --adj-spp render, applied to this render)")
    s.add_argument("--adj-spp", type=int, default=40, help="mode adjhi: spp of the adjoint's primal render")
    s.add_argument("--skip-reference", default=None, help="reuse the reference of this grads.npz")
    s.add_argument("--seeds", type=int, default=16)
    s.add_argument("--ref-spp", type=int, default=512)
    s.add_argument("--ref-seeds", type=int, default=8)
    s.add_argument("--seed-base", type=int, default=987654321, help="seeds of the gradient samples")
    s.add_argument("--top-layers", type=int, default=1, help="layers counted as 'top' (default: %(default)s)")
    s.add_argument("--per-term", action="store_true", help="also the E1/E2/E3 gradient contributions")
    s.add_argument("--out", required=True)

    r = sub.add_parser("run", help="one optimisation run with a wall-time budget")
    add_common(r)
    r.add_argument("--study", default="/tmp/study")
    r.add_argument("--name", required=True)
    r.add_argument("--estimator", choices=("plain", "mean2", "decorr", "ema"), default="plain",
                   help="plain: the library loop; mean2/decorr: two half-spp renders (see above); ema: the loss "
                        "gradient with respect to the texel colours is taken at a running mean of the past renders "
                        "(β = --ema-beta) and applied to this iteration's render (surrogate Σ adjoint·C)")
    r.add_argument("--ema-beta", type=float, default=0.9, help="estimator ema: decay (default: %(default)s)")
    r.add_argument("--optimizer", choices=("adagrad", "adam"), default="adagrad")
    r.add_argument("--lr", type=float, default=1.0)
    r.add_argument("--spp", type=int, default=4, help="samples per texel per iteration (two halves for "
                   "mean2/decorr)")
    r.add_argument("--gradient-seed", choices=("same", "independent"), default="same")
    r.add_argument("--budget-s", type=float, default=240.0, help="optimisation time budget in s, evaluation "
                   "renders excluded (default: %(default)s)")
    r.add_argument("--budget-clock", choices=("cpu", "wall"), default="cpu",
                   help="clock of the budget and of the evaluation schedule: this process's CPU time (default; with "
                        "--threads 1 it equals the wall time of an unloaded core, and other jobs on a shared machine "
                        "do not eat into it) or wall time")
    r.add_argument("--eval-every-s", type=float, default=15.0, help="(default: %(default)s)")
    r.add_argument("--final-spp", type=int, default=256, help="also score the end state at this spp")
    r.add_argument("--init", choices=("white", "naive"), default="white",
                   help="start: 97 %% white (the paper's default) or the naive extrusion (default: %(default)s)")
    r.add_argument("--init-floor", type=float, default=0.005,
                   help="--init naive: every ink's weight is at least this (default: %(default)s)")

    t = sub.add_parser("report", help="tables and convergence.png")
    t.add_argument("--study", default="/tmp/study")
    t.add_argument("--times", default="30,60,120,240", help="table columns: ΔE00 at these wall times")
    t.add_argument("--context", default="ada1_s4_same,ada1_s64_same",
                   help="plain runs repeated in the right panel of the plot (default: %(default)s)")
    t.add_argument("--clock", choices=("wall", "cpu"), default="cpu", help="time axis (default: %(default)s)")
    t.add_argument("--plot-name", default="convergence.png", help="(default: %(default)s)")
    t.add_argument("--ymin", type=float, default=10.0)
    t.add_argument("--ymax", type=float, default=45.0)
    return p.parse_args(argv)


def main(argv=None):
    args = parse_args(argv)
    {"baseline": cmd_baseline, "snr": cmd_snr, "run": cmd_run, "report": cmd_report}[args.cmd](args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
