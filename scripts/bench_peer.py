#!/usr/bin/env python
"""Side by side with Mitsuba 3 (prbvolpath, path-replay backpropagation): agreement, speed, error against time.

The same scene in both renderers: a slab box of nearest-filtered voxel grids, HG g = 0.4, smooth dielectric
IOR 1.5, constant environment radiance 1, an orthographic sensor over the top face with one pixel per texel (our
texel sensor). Prints JSON lines (and writes them to --out):

  agreement_grey      grey σ_t (the peer is reliable): per-texel primal z-test (Bonferroni) and per-voxel gradient
                      z-test of a linear objective Σ w·image with fixed random weights, both over independent seeds
  chromatic_bias      chromatic σ_t (the peer's RGB volume sampling is known to be biased here): both renderers
                      against the independent numpy reference tracer (tests/reference_tracer.py)
  timing              forward and forward+backward at equal spp after warm-up (the peer JIT-compiles first),
                      medians; ratio_forward and ratio_forward_backward = peer time / our time
  efficiency          RMSE of the primal image and of the gradient against a high-spp reference for a ladder of
                      spp, against wall time, for both renderers (efficiency.png + efficiency.json)

Needs the optional peer: `make bench-peer` installs mitsuba==3.5.2 and drjit==0.4.6 into the venv and points
DRJIT_LIBLLVM_PATH at Debian's libLLVM-15 (package libllvm15). The test suite never needs it.
"""
import argparse
import json
import math
import os
import statistics
import sys
import time

import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
import torch_appearance as ta  # noqa: E402
from torch_appearance import io as ta_io  # noqa: E402


def _load_mitsuba():
    if "DRJIT_LIBLLVM_PATH" not in os.environ:
        for cand in ("/lib/x86_64-linux-gnu/libLLVM-15.so.1", "/usr/lib/x86_64-linux-gnu/libLLVM-15.so.1"):
            if os.path.exists(cand):
                os.environ["DRJIT_LIBLLVM_PATH"] = cand
                break
    try:
        import drjit as dr
        import mitsuba as mi
    except ImportError as exc:
        sys.exit(f"bench_peer.py: the peer renderer is not installed ({exc}); run `make bench-peer`")
    mi.set_variant("llvm_ad_rgb")
    return mi, dr


mi, dr = None, None
KEY_SIGMA = "slab.interior_medium.sigma_t.data"


# ------------------------------------------------------------------------------------------------ scenes
def make_scene(kind, size, depth, seed=0):
    """(sigma_t, albedo) float32 (3, D, H, W): 'grey' (σ_t equal in R, G, B) or 'chromatic' (ink-like)."""
    g = torch.Generator().manual_seed(seed)
    shape = (depth, size, size)
    if kind == "grey":
        sigma = (2 + 22 * torch.rand(1, *shape, generator=g)).expand(3, *shape).contiguous()
    else:
        base = torch.tensor([2.25, 3.75, 19.0]).view(3, 1, 1, 1)
        sigma = base * (0.5 + torch.rand(3, *shape, generator=g))
    albedo = 0.05 + (0.9997 - 0.05) * torch.rand(3, *shape, generator=g)
    return sigma.float(), albedo.float()


def mitsuba_scene(sigma, albedo, s, spp, max_depth, majorant):
    T = mi.ScalarTransform4f
    _, d, h, w = sigma.shape
    X, Y, Z = w * s, h * s, d * s
    grid_tf = T.scale([X, Y, Z])

    def grid(x, extra=None):
        out = {"type": "gridvolume", "data": np.ascontiguousarray(x.numpy().transpose(1, 2, 3, 0)), "raw": True,
               "filter_type": "nearest", "to_world": grid_tf}
        out.update(extra or {})
        return out

    return mi.load_dict({
        "type": "scene",
        "integrator": {"type": "prbvolpath", "max_depth": max_depth, "rr_depth": max_depth},
        "sensor": {"type": "orthographic",
                   # orthographic extent is [-1, 1] horizontally and [-1/aspect, 1/aspect] vertically
                   "to_world": T.look_at(origin=[X / 2, Y / 2, Z + 1.0], target=[X / 2, Y / 2, 0.0], up=[0, 1, 0])
                   @ T.scale([X / 2, X / 2, 1]),
                   "film": {"type": "hdrfilm", "width": w, "height": h, "rfilter": {"type": "box"},
                            "pixel_format": "rgb"},
                   "sampler": {"type": "independent", "sample_count": spp}},
        "emitter": {"type": "constant", "radiance": {"type": "rgb", "value": 1.0}},
        "slab": {"type": "cube", "to_world": T.translate([X / 2, Y / 2, Z / 2]) @ T.scale([X / 2, Y / 2, Z / 2]),
                 "bsdf": {"type": "dielectric", "int_ior": 1.5, "ext_ior": 1.0},
                 "interior": {"type": "heterogeneous", "sigma_t": grid(sigma, {"max_value": float(majorant)}),
                              "albedo": grid(albedo), "scale": 1.0, "phase": {"type": "hg", "g": 0.4},
                              "sample_emitters": False}},
    })


class Peer:
    """Mitsuba renders in our conventions: image (H, W, 3) with texel [j, i]; gradient (3, D, H, W)."""

    def __init__(self, sigma, albedo, s, max_depth):
        self.shape = sigma.shape
        self.scene = mitsuba_scene(sigma, albedo, s, 1, max_depth, float(sigma.max()))
        self.params = mi.traverse(self.scene)

    def forward(self, spp, seed):
        img = mi.render(self.scene, spp=spp, seed=seed)
        return torch.from_numpy(np.array(img)[::-1].copy())  # film rows run top-down: flip to texel j

    def forward_backward(self, spp, seed, weights):
        dr.enable_grad(self.params[KEY_SIGMA])
        self.params.update()
        img = mi.render(self.scene, self.params, spp=spp, seed=seed, seed_grad=seed + 7919)
        w = mi.TensorXf(np.ascontiguousarray(weights.numpy()[::-1]))
        loss = dr.sum(dr.ravel(img * w))
        dr.backward(loss)
        grad = np.array(dr.grad(self.params[KEY_SIGMA]))  # (D, H, W, 3)
        dr.disable_grad(self.params[KEY_SIGMA])
        self.params.update()
        primal = torch.from_numpy(np.array(img)[::-1].copy())
        return primal, torch.from_numpy(grad.transpose(3, 0, 1, 2).copy())


class Ours:
    def __init__(self, sigma, albedo, s, max_depth):
        self.sigma, self.albedo, self.s, self.max_depth = sigma, albedo, s, max_depth

    def forward(self, spp, seed):
        with torch.no_grad():
            return ta.render_texels(self.sigma, self.albedo, voxel_size=self.s, spp=spp, seed=seed,
                                    max_depth=self.max_depth)

    def forward_backward(self, spp, seed, weights):
        s = self.sigma.clone().requires_grad_()
        img = ta.render_texels(s, self.albedo, voxel_size=self.s, spp=spp, seed=seed, max_depth=self.max_depth)
        (img * weights).sum().backward()
        return img.detach(), s.grad


def seed_stats(fn, k, offset=0):
    xs = torch.stack([fn(offset + i).double() for i in range(k)])
    return xs.mean(0), xs.std(0) / math.sqrt(k)


def zmax(a, sa, b, sb):
    z = (a - b).abs() / (sa ** 2 + sb ** 2).sqrt().clamp_min(1e-30)
    return float(z.max()), z


def bonferroni(n, alpha=1e-3):
    from scipy.stats import norm
    return float(norm.isf(alpha / (2 * n)))


def timed(fn, reps):
    times = []
    for r in range(reps):
        t = time.perf_counter()
        fn(r)
        times.append(time.perf_counter() - t)
    return statistics.median(times)


# ------------------------------------------------------------------------------------------------ main
def main(argv=None):
    global mi, dr
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], epilog=__doc__.split("\n\n", 1)[1],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--size", type=int, default=32, help="texels per side of the agreement scenes (default: %(default)s)")
    p.add_argument("--depth", type=int, default=12, help="voxel layers (default: %(default)s)")
    p.add_argument("--voxel-size", type=float, default=0.085, help="mm (default: %(default)s)")
    p.add_argument("--seeds", type=int, default=16, help="independent renders per agreement estimate (default: %(default)s)")
    p.add_argument("--spp", type=int, default=64, help="spp of each agreement render (default: %(default)s)")
    p.add_argument("--timing-size", type=int, default=64, help="texels per side of the timing scene (default: %(default)s)")
    p.add_argument("--timing-spp", type=int, default=16, help="(default: %(default)s)")
    p.add_argument("--reps", type=int, default=5, help="timed repetitions (default: %(default)s)")
    p.add_argument("--max-depth", type=int, default=1024, help="interaction limit in both (default: %(default)s)")
    p.add_argument("--skip", default="", help="comma-separated parts to skip: agreement,chromatic,timing,efficiency")
    p.add_argument("--out", default="results/bench/peer.jsonl", help="JSON lines; plots beside it (default: %(default)s)")
    args = p.parse_args(argv)
    mi, dr = _load_mitsuba()
    skip = set(filter(None, args.skip.split(",")))
    lines = []
    folder = os.path.dirname(args.out) or "."
    os.makedirs(folder, exist_ok=True)

    def emit(d):
        d = {k: (round(v, 6) if isinstance(v, float) else v) for k, v in d.items()}
        print(json.dumps(d), flush=True)
        lines.append(d)

    s = args.voxel_size
    # ---- grey scene: primal and gradient agreement
    sigma, albedo = make_scene("grey", args.size, args.depth)
    ours, peer = Ours(sigma, albedo, s, args.max_depth), Peer(sigma, albedo, s, args.max_depth)
    weights = torch.rand(args.size, args.size, 3, generator=torch.Generator().manual_seed(5))
    if "agreement" not in skip:
        pair_o = [ours.forward_backward(args.spp, 1000 + k, weights) for k in range(args.seeds)]
        pair_p = [peer.forward_backward(args.spp, 2000 + k, weights) for k in range(args.seeds)]
        io_, go_ = (torch.stack([x[i].double() for x in pair_o]) for i in (0, 1))
        ip_, gp_ = (torch.stack([x[i].double() for x in pair_p]) for i in (0, 1))
        n = args.seeds
        zi, _ = zmax(io_.mean(0), io_.std(0) / n ** .5, ip_.mean(0), ip_.std(0) / n ** .5)
        zg, zgall = zmax(go_.mean(0), go_.std(0) / n ** .5, gp_.mean(0), gp_.std(0) / n ** .5)
        rel = float((go_.mean(0).sum() - gp_.mean(0).sum()) / gp_.mean(0).sum().abs())
        # arbiter: central finite difference of the expectation along "all σ_t + h" (our smooth explicit-reference
        # estimator, common random numbers), against the sum of each renderer's gradient
        h, ref_s, ref_a = 0.05, sigma.double(), albedo.double()

        def fd(k):
            f = lambda x: float((ta.render_texels(x, ref_a, voxel_size=s, spp=args.spp * 4, seed=700 + k,
                                                  max_depth=args.max_depth, sampling_sigma_t=ref_s,
                                                  sampling_albedo=ref_a) * weights.double()).sum())
            return torch.tensor((f(ref_s + h) - f(ref_s - h)) / (2 * h))

        fd_mean, fd_se = seed_stats(fd, n)
        sum_o, sum_p = go_.sum((1, 2, 3, 4)), gp_.sum((1, 2, 3, 4))
        z_fd = lambda x: float((x.mean() - fd_mean).abs() / ((x.std() / n ** .5) ** 2 + fd_se ** 2).sqrt())
        emit({"part": "agreement_grey", "fd_directional": float(fd_mean), "fd_se": float(fd_se),
              "ours_grad_sum_se": float(sum_o.std() / n ** .5), "peer_grad_sum_se": float(sum_p.std() / n ** .5),
              "ours_z_vs_fd": z_fd(sum_o), "peer_z_vs_fd": z_fd(sum_p), "texels": args.size ** 2, "depth": args.depth, "seeds": n, "spp": args.spp,
              "primal_max_z": zi, "primal_threshold": bonferroni(io_[0].numel()),
              "primal_mean_ours": float(io_.mean()), "primal_mean_peer": float(ip_.mean()),
              "grad_max_z": zg, "grad_threshold": bonferroni(go_[0].numel()),
              "grad_frac_z_gt_3": float((zgall > 3).double().mean()),
              "grad_sum_ours": float(go_.mean(0).sum()), "grad_sum_peer": float(gp_.mean(0).sum()),
              "grad_sum_rel_diff": rel})

        # arbiter per voxel: where the renderers disagree most, central finite differences of the expectation
        top = torch.topk(zgall.flatten(), 8).indices
        fd_vox = []
        for flat in top.tolist():
            def fd_one(k, flat=flat):
                step = torch.zeros_like(ref_s).view(-1)
                step[flat] = h
                step = step.view_as(ref_s)
                f = lambda x: float((ta.render_texels(x, ref_a, voxel_size=s, spp=args.spp * 4, seed=1700 + k,
                                                      max_depth=args.max_depth, sampling_sigma_t=ref_s,
                                                      sampling_albedo=ref_a) * weights.double()).sum())
                return torch.tensor((f(ref_s + step) - f(ref_s - step)) / (2 * h))
            fm, fs = seed_stats(fd_one, n)
            o, po = go_.reshape(n, -1)[:, flat], gp_.reshape(n, -1)[:, flat]
            zo = float((o.mean() - fm).abs() / ((o.std() / n ** .5) ** 2 + fs ** 2).sqrt())
            zp = float((po.mean() - fm).abs() / ((po.std() / n ** .5) ** 2 + fs ** 2).sqrt())
            fd_vox.append({"index_cdhw": list(np.unravel_index(flat, tuple(go_.shape[1:]))), "fd": float(fm),
                           "fd_se": float(fs), "ours": float(o.mean()), "peer": float(po.mean()),
                           "ours_z": zo, "peer_z": zp})
        emit({"part": "gradient_arbiter", "voxels": len(fd_vox),
              "ours_max_z_vs_fd": max(v["ours_z"] for v in fd_vox),
              "peer_max_z_vs_fd": max(v["peer_z"] for v in fd_vox),
              "cases": [{k: ([int(i) for i in x] if k == "index_cdhw" else round(x, 5)) for k, x in v.items()} for v in fd_vox]})

    # ---- chromatic: both against the independent numpy reference
    if "chromatic" not in skip:
        sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "tests"))
        from reference_tracer import reference_render_texels
        cs, ca = make_scene("chromatic", 6, 4, seed=3)
        ref_mean, ref_se = reference_render_texels(cs.double().numpy(), ca.double().numpy(), voxel_size=0.1,
                                                   g=0.4, ior=1.5, spp=20000, seed=1, max_depth=args.max_depth)
        ref_mean, ref_se = torch.from_numpy(ref_mean), torch.from_numpy(ref_se)
        o = Ours(cs, ca, 0.1, args.max_depth)
        pr = Peer(cs, ca, 0.1, args.max_depth)
        om, ose = seed_stats(lambda k: o.forward(256, 3000 + k), 32)
        pm, pse = seed_stats(lambda k: pr.forward(256, 4000 + k), 32)
        zo, _ = zmax(om, ose, ref_mean, ref_se)
        zp, _ = zmax(pm, pse, ref_mean, ref_se)
        rel_o = ((om - ref_mean) / ref_mean).mean((0, 1))
        rel_p = ((pm - ref_mean) / ref_mean).mean((0, 1))
        emit({"part": "chromatic_bias", "texels": 36, "threshold": bonferroni(om.numel()),
              "ours_max_z": zo, "peer_max_z": zp,
              "ours_mean_rel_bias_rgb": [float(v) for v in rel_o], "peer_mean_rel_bias_rgb": [float(v) for v in rel_p],
              "reference_mean_rgb": [float(v) for v in ref_mean.mean((0, 1))]})

    # ---- timing at equal spp
    if "timing" not in skip:
        ts, ta_ = make_scene("grey", args.timing_size, args.depth, seed=1)
        o, pr = Ours(ts, ta_, s, args.max_depth), Peer(ts, ta_, s, args.max_depth)
        w = torch.rand(args.timing_size, args.timing_size, 3, generator=torch.Generator().manual_seed(6))
        for fn in (lambda r: o.forward(args.timing_spp, r), lambda r: pr.forward(args.timing_spp, r),
                   lambda r: o.forward_backward(args.timing_spp, r, w), lambda r: pr.forward_backward(args.timing_spp, r, w)):
            fn(99)  # warm-up (the peer JIT-compiles its kernels)
        fo = timed(lambda r: o.forward(args.timing_spp, r), args.reps)
        fp = timed(lambda r: pr.forward(args.timing_spp, r), args.reps)
        bo = timed(lambda r: o.forward_backward(args.timing_spp, r, w), args.reps)
        bp = timed(lambda r: pr.forward_backward(args.timing_spp, r, w), args.reps)
        emit({"part": "timing", "texels": args.timing_size ** 2, "depth": args.depth, "spp": args.timing_spp,
              "threads": torch.get_num_threads(), "ours_forward_s": fo, "peer_forward_s": fp,
              "ours_forward_backward_s": bo, "peer_forward_backward_s": bp,
              "ratio_forward": fp / fo, "ratio_forward_backward": bp / bo})

    # ---- error against time
    if "efficiency" not in skip:
        ref_img, _ = seed_stats(lambda k: ours.forward(256, 5000 + k), 16)
        ref_grad = torch.stack([ours.forward_backward(256, 6000 + k, weights)[1].double() for k in range(16)]).mean(0)
        rows = []
        for spp in (1, 2, 4, 8, 16, 32):
            for name, r in (("ours", ours), ("peer", peer)):
                r.forward_backward(spp, 77, weights)  # warm-up for this spp
                errs_i, errs_g, tf, tb = [], [], [], []
                for k in range(4):
                    t = time.perf_counter()
                    img = r.forward(spp, 8000 + k)
                    tf.append(time.perf_counter() - t)
                    t = time.perf_counter()
                    _, g = r.forward_backward(spp, 9000 + k, weights)
                    tb.append(time.perf_counter() - t)
                    errs_i.append(float(((img.double() - ref_img) ** 2).mean().sqrt()))
                    errs_g.append(float(((g.double() - ref_grad) ** 2).mean().sqrt()))
                row = {"renderer": name, "spp": spp, "forward_s": statistics.median(tf),
                       "forward_backward_s": statistics.median(tb), "rmse_image": statistics.mean(errs_i),
                       "rmse_grad": statistics.mean(errs_g)}
                rows.append(row)
                emit({"part": "efficiency", **row})
        ta_io.write_json(os.path.join(folder, "efficiency.json"), rows)
        _plot(rows, os.path.join(folder, "efficiency.png"))
    ta_io.atomic_write_bytes(args.out, ("\n".join(json.dumps(d) for d in lines) + "\n").encode())
    return 0


def _plot(rows, path):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(10, 4))
    for name, style in (("ours", "o-"), ("peer", "s--")):
        r = [x for x in rows if x["renderer"] == name]
        label = "torch_appearance" if name == "ours" else "Mitsuba 3 prbvolpath"
        ax[0].loglog([x["forward_s"] for x in r], [x["rmse_image"] for x in r], style, label=label)
        ax[1].loglog([x["forward_backward_s"] for x in r], [x["rmse_grad"] for x in r], style, label=label)
    ax[0].set(xlabel="forward wall time [s]", ylabel="RMSE of the image", title="primal: error vs time")
    ax[1].set(xlabel="forward + backward wall time [s]", ylabel="RMSE of ∂(Σ w·image)/∂σ_t",
              title="gradient: error vs time")
    for a in ax:
        a.legend(fontsize=8)
        a.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    ta_io.save_figure(fig, path)


if __name__ == "__main__":
    sys.exit(main())
