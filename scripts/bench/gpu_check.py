#!/usr/bin/env python
"""The tracer's CUDA path checked on a GPU in one run (issue 47): every case is caught and reported, none stops the
run, so one call of a lent machine yields all the information; well under 5 minutes on an H200 (the extension's
build, which `make gpu-check` runs first, aside).

Steps, each recorded in the JSON (ok, figures, or the traceback):
  compile    the four programs (forward/replay x f32/f64) with NVRTC for the GPU present (sm_XY cubin), timed;
  layout     sizeof/offsets of core::Scene<T> as the GPU compiler lays it out, against the host's (_C.scene_layout);
  cases      small scenes (a box slab of face texels, dielectric and index matched; an SDF dielectric object with
             surface texels under an environment map; orthographic and perspective cameras; a disc light; a palette
             print), one walk per channel (l1), three lanes (l3) and hero, float32 and float64:
               same seed    CPU (scalar walk) and GPU images per texel: max |diff|, fraction equal to 1e-5 relative;
               t-tests      --seeds independent seeds per device: max |t| of the per-element means against the
                            Bonferroni bound (alpha 0.01, 2k - 2 degrees of freedom), and the t of the sums over all
                            elements (power against a small bias: a 1 % albedo change fails it);
               gradients    d(w . image)/d sigma_t and d albedo by replay, the same seed_grad: max |diff| over
                            max |grad|, and the t-tests across seeds; with grad_support (compact buffers) on the object, and the
                            one walk of the ema estimator (render_scene(adjoint=...));
  memory     a job larger than the GPU's free memory refused before it is built (one line, bytes needed and free);
  gradcheck  torch.autograd.gradcheck in float64 on a tiny slab on the GPU;
  stiff      sigma_t 1e-6 ... 1e4 mm^-1 and albedo 0 and 1 on the GPU: finite image and gradients;
  timing     a moderate slab and object, forward + backward, CPU (all cores, its SIMD walks) against the GPU.

Without a CUDA device it says "no GPU" and exits 2 (--device cpu runs every step against the CPU itself: a check of
this script, about 20 s on 2 cores). Exit status 1 when any step failed. Writes gpu_check.json under --out (default:
$OUT when set).
"""
import argparse
import json
import os
import platform
import statistics
import sys
import time
import traceback
import warnings

RECORD_NAME = "gpu_check.json"


def _parser():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], epilog=__doc__.split("\n\n", 1)[1],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default=os.environ.get("OUT"),
                   help="folder of the JSON record (default: $OUT when set, else none is written)")
    p.add_argument("--seeds", type=int, default=16, help="independent seeds per device for the t-tests "
                   "(default: %(default)s)")
    p.add_argument("--spp", type=int, default=8, help="samples per element of the case renders (default: %(default)s)")
    p.add_argument("--quick", action="store_true", help="float32 only, three cases, no timing (a smoke test)")
    p.add_argument("--bench-slab", type=int, default=256, help="the timing slab's side in voxels (x 16 deep; "
                   "default: %(default)s)")
    p.add_argument("--bench-spp", type=int, default=32, help="samples per texel of the timing (default: %(default)s)")
    p.add_argument("--device", default="cuda", help="the device checked against the CPU (default: %(default)s); "
                   "'cpu' runs every step of this script against the CPU itself, a check of the script without a GPU")
    return p


def _sync(torch, device):
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize()


class Log:
    """Prints a line and keeps it for the record."""

    def __init__(self):
        self.lines = []

    def __call__(self, *parts):
        line = " ".join(str(p) for p in parts)
        print(line, flush=True)
        self.lines.append(line)


def _step(record, log, name, fn):
    """Runs fn() -> dict, recording its figures or its traceback; never raises."""
    start = time.perf_counter()
    try:
        result = fn() or {}
        ok = bool(result.pop("ok", True))
    except Exception:  # noqa: BLE001 - every failure is reported and the run goes on
        result, ok = {"traceback": traceback.format_exc()}, False
        log(f"[{name}] FAILED\n{result['traceback']}")
    result.update(name=name, ok=ok, wall_s=round(time.perf_counter() - start, 3))
    record["steps"].append(result)
    log(f"[{name}] {'ok' if ok else 'FAILED'} ({result['wall_s']} s) "
        + json.dumps({k: v for k, v in result.items() if k not in ("name", "ok", "wall_s", "traceback")},
                     default=str)[:600])
    return result


# ---- scenes

def _grid(n):
    return (n, n, n)


def _scenes(torch, ta_render, sphere_sdf):
    """name -> (scene builder(dtype) -> Scene, grid shape, chromatic σ_t, chromatic estimator, palette)."""
    N, H, O = 16, 0.08, (-0.64, -0.64, -0.64)

    def sdf():
        return sphere_sdf(_grid(N), H, O, (0.01, -0.02, 0.0), 0.5)

    def texels(count=200):
        gen = torch.Generator().manual_seed(5)
        n = torch.randn((count, 3), generator=gen, dtype=torch.float64)
        n = n / n.norm(dim=1, keepdim=True)
        return torch.tensor([0.01, -0.02, 0.0], dtype=torch.float64) + 0.5 * n, n

    envmap = torch.rand((8, 16, 3), generator=torch.Generator().manual_seed(9)) + 0.2
    R = ta_render

    def slab(ior):
        return lambda: R.Scene.slab(0.1, face="both", ior=ior, environment=(1.0, 0.9, 0.8))

    def obj(sensor, ior, emitter=None):
        def build():
            if sensor == "texels":
                pts, nrm = texels()
                sens = R.SurfaceTexels(pts, nrm, footprint_mm=0.04)
            elif sensor == "ortho":
                sens = R.OrthographicCamera(origin=(0.05, 0.0, 2.0), target=(0, 0, 0), up=(0, 1, 0),
                                            extent_mm=(1.3, 1.3), resolution=(16, 16))
            else:
                sens = R.PerspectiveCamera(origin=(1.2, 0.6, 2.0), target=(0, 0, 0), up=(0, 1, 0), fov_y_deg=40,
                                           resolution=(16, 16))
            kw = {"emitter": emitter} if emitter is not None else {}
            return R.Scene(voxel_size=H, origin=O, boundary=R.SDFBoundary(sdf(), ior=ior), sensor=sens, g=0.3, **kw)
        return build

    disc = R.DiscLight(direction=(0.3, 0.2, 1.0), angular_radius_deg=20, radiance=(3.0, 2.5, 2.0),
                       ambient=(0.3, 0.3, 0.3))
    return {
        "slab-diel-l1": (slab(1.4), (6, 20, 20), True, "per_channel", False),
        "slab-matched-l3": (slab(None), (6, 20, 20), False, "per_channel", False),
        "object-texels-env-l1": (obj("texels", 1.5, R.EnvironmentMap(envmap)), _grid(N), True, "per_channel", False),
        "object-texels-l3": (obj("texels", 1.5), _grid(N), False, "per_channel", False),
        "camera-ortho-disc-hero": (obj("ortho", None, disc), _grid(N), True, "hero", False),
        "camera-persp-diel-l1": (obj("persp", 1.3), _grid(N), True, "per_channel", False),
        "palette-texels": (obj("texels", 1.5), _grid(N), True, "per_channel", True),
    }


def _medium(torch, shape, dtype, chromatic, seed=1):
    gen = torch.Generator().manual_seed(seed)
    sigma_t = torch.rand((3,) + shape, generator=gen, dtype=torch.float64) * 20 + 2
    if not chromatic:
        sigma_t = sigma_t[:1].expand(3, -1, -1, -1).clone()
    albedo = torch.rand((3,) + shape, generator=gen, dtype=torch.float64) * 0.2 + 0.79
    if shape[0] == shape[1] == shape[2]:  # the object: a homogeneous core (crossed in bricks)
        c = slice(shape[0] // 4, 3 * shape[0] // 4)
        sigma_t[:, c, c, c] = torch.tensor([6.0, 9.0, 24.0] if chromatic else [9.0] * 3, dtype=torch.float64).view(
            3, 1, 1, 1)
        albedo[:, c, c, c] = 0.999
    return sigma_t.to(dtype).contiguous(), albedo.to(dtype).contiguous()


def _compare(torch, cpu, gpu):
    a, b = cpu.double().cpu(), gpu.double().cpu()
    diff = (a - b).abs()
    equal = diff <= 1e-5 * a.abs() + 1e-12
    return {"max_abs_diff": float(diff.max()), "max_abs": float(a.abs().max()),
            "frac_equal_1e-5": float(equal.double().mean()), "finite": bool(torch.isfinite(b).all())}


def _ztest(torch, xs, ys, alpha=0.01):
    """Per element, the two-sample t statistic of the means of two sets of k independent renders (pooled variance,
    2k - 2 degrees of freedom, a rounding floor of 1e-6 relative in the standard error), its maximum against the
    Bonferroni bound over the elements tested (those whose renders vary); elements constant in both sets but at
    different values (a handful is noise of small k) are counted apart."""
    x, y = torch.stack([t.double().cpu() for t in xs]), torch.stack([t.double().cpu() for t in ys])
    k = x.shape[0]
    mx, my = x.mean(0), y.mean(0)
    pooled = (x.var(0) + y.var(0)) / 2
    scale = torch.maximum(mx.abs(), my.abs())
    se = (pooled * 2 / k + (1e-6 * scale) ** 2).sqrt()
    live = pooled > 0
    t = (mx - my).abs()[live] / se[live]
    m = max(int(live.sum()), 1)
    try:
        from scipy.stats import t as student
        bound = float(student.ppf(1 - alpha / (2 * m), 2 * k - 2))
    except ImportError:  # the normal bound: too strict for few seeds
        bound = statistics.NormalDist().inv_cdf(1 - alpha / (2 * m))
    max_t = float(t.max()) if t.numel() else 0.0
    degenerate = int(((~live) & ((mx - my).abs() > 1e-6 * scale + 1e-12)).sum())
    frac = degenerate / max(int((~live).sum()) + m, 1)
    # the same test of the renders' sums over all elements: one statistic, much more power against a small bias
    sx, sy = x.reshape(k, -1).sum(1), y.reshape(k, -1).sum(1)
    se_sum = float(((sx.var() + sy.var()) / k + (1e-6 * sx.mean().abs()) ** 2).sqrt())
    sum_t = abs(float(sx.mean() - sy.mean())) / se_sum if se_sum > 0 else 0.0
    try:
        from scipy.stats import t as student
        sum_bound = float(student.ppf(1 - alpha / 2, 2 * k - 2))
    except ImportError:
        sum_bound = statistics.NormalDist().inv_cdf(1 - alpha / 2)
    return {"max_t": round(max_t, 3), "bonferroni_bound": round(bound, 3), "seeds": k, "tested": int(live.sum()),
            "constant_but_different": degenerate, "sum_t": round(sum_t, 3), "sum_bound": round(sum_bound, 3),
            "ok": max_t < bound and frac <= 0.01 and sum_t < sum_bound}


def _render(torch, ta, scene, sigma_t, albedo, device, seed, spp, chromatic, palette, grad=False, weight=None,
            support=None, adjoint=False):
    """(image, grad σ_t, grad albedo) on `device`; the CPU takes its scalar walk (the GPU's)."""
    if palette:
        index = (sigma_t[0] * 0).to(torch.uint8)
        index[sigma_t[0] > 10] = 1
        index[sigma_t[0] > 18] = 2
        st = torch.tensor([[5.0, 6.0, 7.0], [10.0, 12.0, 14.0], [20.0, 15.0, 9.0]], dtype=sigma_t.dtype)
        al = torch.tensor([[0.9, 0.8, 0.7], [0.95, 0.9, 0.99], [0.3, 0.6, 0.9]], dtype=sigma_t.dtype)
        image = ta.render.render_scene_indexed(scene, index.to(device), st.to(device), al.to(device), spp=spp,
                                               seed=seed)
        return image, None, None
    s = sigma_t.detach().clone().to(device).requires_grad_(grad)  # a fresh leaf per render (no accumulated .grad)
    a = albedo.detach().clone().to(device).requires_grad_(grad)
    kw = {"grad_support": support} if support is not None else {}
    if adjoint:
        kw["adjoint"] = weight.to(device)
    image = ta.render_scene(scene, s, a, spp=spp, seed=seed, seed_grad=seed + 7, chromatic=chromatic, **kw)
    if not grad:
        return image.detach(), None, None
    (image * weight.to(device)).sum().backward()
    return image.detach(), s.grad, a.grad


def _case(torch, ta, _C, build, shape, chromatic, estimator, palette, dtype, args, grad_support=False,
          adjoint=False):
    scene = build()
    sigma_t, albedo = _medium(torch, shape, dtype, chromatic)
    out = {"dtype": str(dtype)[6:]}
    old = _C._set_simd(0)  # the CPU's scalar walk: the GPU walks the same steps
    try:
        grad = not palette
        image_shape = scene.output_shape(shape)
        weight = torch.rand(image_shape, generator=torch.Generator().manual_seed(3), dtype=dtype)
        support = None
        if grad_support:
            support = torch.zeros(shape, dtype=torch.bool)
            support[:, :, : shape[2] // 2] = True
        kw = dict(spp=args.spp, chromatic=estimator, palette=palette, grad=grad, weight=weight, support=support,
                  adjoint=adjoint)
        t0 = time.perf_counter()
        cpu = _render(torch, ta, scene, sigma_t, albedo, "cpu", 11, **kw)
        t1 = time.perf_counter()
        gpu = _render(torch, ta, scene, sigma_t, albedo, args.device, 11, **kw)
        _sync(torch, args.device)
        t2 = time.perf_counter()
        out.update(cpu_s=round(t1 - t0, 3), gpu_s=round(t2 - t1, 3))
        out["image_same_seed"] = _compare(torch, cpu[0], gpu[0])
        ok = out["image_same_seed"]["finite"] and out["image_same_seed"]["frac_equal_1e-5"] > 0.5
        if grad:
            for k, name in ((1, "grad_sigma_t"), (2, "grad_albedo")):
                c = _compare(torch, cpu[k], gpu[k])
                scale = max(c["max_abs"], 1e-30)
                c["max_diff_over_max_grad"] = c["max_abs_diff"] / scale
                out[f"{name}_same_seed"] = c
                ok &= c["finite"] and c["max_diff_over_max_grad"] < 0.1  # the z-test below is the real check
        xs, ys, gx, gy = [], [], [], []
        for k in range(args.seeds):
            a = _render(torch, ta, scene, sigma_t, albedo, "cpu", 1000 + k, **kw)
            b = _render(torch, ta, scene, sigma_t, albedo, args.device, 5000 + k, **kw)
            xs.append(a[0])
            ys.append(b[0])
            if grad:
                gx.append(torch.cat([a[1].reshape(-1), a[2].reshape(-1)]))
                gy.append(torch.cat([b[1].reshape(-1), b[2].reshape(-1)]))
        out["image_ztest"] = _ztest(torch, xs, ys)
        ok &= out["image_ztest"]["ok"]
        if grad:
            out["grad_ztest"] = _ztest(torch, gx, gy)
            ok &= out["grad_ztest"]["ok"]
        if grad_support and grad:
            outside = ~support
            out["grad_outside_support_zero"] = bool((gpu[1].cpu()[:, outside] == 0).all())
            ok &= out["grad_outside_support_zero"]
    finally:
        _C._set_simd(old)
    out["ok"] = bool(ok)
    return out


def _memory_refusal(torch):
    """A job needing 1 PiB on the device is refused in one line naming the bytes, before anything is built."""
    from torch_appearance.render import cuda_launch
    try:
        cuda_launch.check_device_memory(torch.device("cuda", 0), 1 << 50, "render_scene")
    except ValueError as error:
        return {"message": str(error), "ok": "needs" in str(error) and "free" in str(error)}
    return {"ok": False, "message": "not refused"}


def _gradcheck(torch, ta, device):
    scene = ta.render.Scene.slab(0.1, ior=1.4)
    gen = torch.Generator().manual_seed(2)
    sigma = (torch.rand((3, 2, 2, 2), generator=gen, dtype=torch.float64) * 5 + 1).to(device)
    albedo = (torch.rand((3, 2, 2, 2), generator=gen, dtype=torch.float64) * 0.5 + 0.4).to(device)
    ref_s, ref_a = (sigma * 1.2).detach(), albedo.clamp_min(0.5).detach()

    def f(s, a):
        return ta.render_scene(scene, s, a, spp=8, seed=11, seed_grad=11, sampling_sigma_t=ref_s,
                               sampling_albedo=ref_a)

    inputs = (sigma.clone().requires_grad_(), albedo.clone().requires_grad_())
    return {"ok": bool(torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-7, rtol=1e-4))}


def _stiff(torch, ta, device):
    scene = ta.render.Scene.slab(0.1, ior=1.5)
    bad = []
    for sigma in (1e-6, 1e-2, 1.0, 1e2, 1e4):
        for alb in (0.0, 0.5, 1.0):
            s = torch.full((3, 4, 3, 3), sigma, device=device, requires_grad=True)
            a = torch.full((3, 4, 3, 3), alb, device=device, requires_grad=True)
            with warnings.catch_warnings():  # paths cut at max_depth in the thickest media: counted, not a failure
                warnings.simplefilter("ignore", RuntimeWarning)
                image = ta.render_scene(scene, s, a, spp=64, seed=3)
            image.sum().backward()
            finite = all(bool(torch.isfinite(t).all()) for t in (image, s.grad, a.grad))
            if not finite or float(image.detach().max()) > 1.0 + 1e-4:
                bad.append((sigma, alb, float(image.max())))
    return {"ok": not bad, "failed": bad}


def _layout(torch, _C):
    """The device compiler's sizeof/offsetof of Scene<T> (read from a probe's PTX) against the host's."""
    from torch_appearance.render import cuda_launch
    arch = "compute_{}{}".format(*torch.cuda.get_device_capability(0))
    out = {}
    for dtype, ctype in ((torch.float32, "float"), (torch.float64, "double")):
        out[ctype] = cuda_launch.layout_mismatches(_C.scene_layout(dtype), ctype, arch)
    out["ok"] = not any(out.values())
    return out


def _timing(torch, ta, _C, args):
    out = {}
    n = args.bench_slab
    gen = torch.Generator().manual_seed(1)
    sigma = torch.rand((3, 16, n, n), generator=gen) * 20 + 2
    albedo = torch.rand((3, 16, n, n), generator=gen) * 0.2 + 0.79
    scene = ta.render.Scene.slab(0.05, ior=1.4)
    for key, device in (("cpu", "cpu"), ("gpu", args.device)):
        s = sigma.to(device).requires_grad_()
        a = albedo.to(device).requires_grad_()
        ta.render_scene(scene, s, a, spp=1, seed=0).sum().backward()  # warm-up (compile, load)
        _sync(torch, device)
        s.grad = a.grad = None
        t0 = time.perf_counter()
        image = ta.render_scene(scene, s, a, spp=args.bench_spp, seed=1)
        _sync(torch, device)
        t1 = time.perf_counter()
        image.mean().backward()
        _sync(torch, device)
        t2 = time.perf_counter()
        out[f"slab_{n}x{n}x16_spp{args.bench_spp}_{key}"] = {"forward_s": round(t1 - t0, 4),
                                                              "backward_s": round(t2 - t1, 4), "device": str(device)}
    cpu = out[f"slab_{n}x{n}x16_spp{args.bench_spp}_cpu"]
    gpu = out[f"slab_{n}x{n}x16_spp{args.bench_spp}_gpu"]
    out["speedup_forward"] = round(cpu["forward_s"] / max(gpu["forward_s"], 1e-9), 1)
    out["speedup_backward"] = round(cpu["backward_s"] / max(gpu["backward_s"], 1e-9), 1)
    out["cpu_threads"] = torch.get_num_threads()
    if torch.device(args.device).type == "cuda":
        out["peak_gpu_bytes"] = int(torch.cuda.max_memory_allocated())
    return out


def main(argv=None):
    args = _parser().parse_args(argv)
    if args.seeds < 2:
        raise SystemExit("--seeds: expected >= 2 (the z-tests need a variance)")
    log = Log()
    record = {"started": time.strftime("%Y-%m-%d %H:%M:%S"), "python": platform.python_version(), "steps": [],
              "argv": sys.argv[1:] if argv is None else list(argv)}
    import torch
    record["torch"] = torch.__version__
    record["device"] = args.device
    on_gpu = torch.device(args.device).type == "cuda"
    if on_gpu and not torch.cuda.is_available():
        log(f"gpu_check: no GPU: torch {torch.__version__} sees no CUDA device (torch.cuda.is_available() is "
            f"False); nothing was checked")
        record["ok"] = False
        record["no_gpu"] = True
        _write(record, log, args.out)
        return 2
    if on_gpu:
        record["gpu"] = torch.cuda.get_device_name(0)
        record["capability"] = list(torch.cuda.get_device_capability(0))
        log(f"gpu_check: {record['gpu']} sm_{''.join(map(str, record['capability']))}, torch {torch.__version__}, "
            f"python {record['python']}")
    else:
        log(f"gpu_check: --device {args.device}: the script's steps against the CPU itself (no GPU is checked)")
    started = time.perf_counter()
    try:
        import torch_appearance as ta
        from torch_appearance._ext import _C
        from torch_appearance.geometry import sphere_sdf
        from torch_appearance.render import cuda_kernels as ck
        from torch_appearance.render import cuda_launch
    except Exception:  # noqa: BLE001
        log("gpu_check: torch_appearance does not import:\n" + traceback.format_exc())
        record["ok"] = False
        _write(record, log, args.out)
        return 1
    missing = cuda_launch.cuda_unavailable() if on_gpu else None
    if missing:
        log(f"gpu_check: CUDA tensors cannot be rendered here: {missing}")

    def compile_all():  # the four programs at once (NVRTC compiles in threads), into the disk cache the runs read
        from concurrent.futures import ThreadPoolExecutor
        arch = ck.default_arch()
        out = {"arch": arch}
        jobs = [(program, dtype) for program in sorted(ck.PROGRAMS) for dtype in sorted(ck.DTYPES)]
        with ThreadPoolExecutor(len(jobs)) as pool:
            done = pool.map(lambda j: ck.compile_program(j[0], j[1], arch, options=cuda_launch._options()), jobs)
            for (program, dtype), res in zip(jobs, done):
                out[f"{program}_{dtype}"] = {"seconds": round(res.seconds, 2), "cached": res.cached,
                                             "bytes": len(res.code), "log": res.log[:400]}
        return out

    if on_gpu:
        _step(record, log, "compile", compile_all)
        _step(record, log, "layout", lambda: _layout(torch, _C))
    scenes = _scenes(torch, ta.render, sphere_sdf)
    names = list(scenes) if not args.quick else ["slab-diel-l1", "object-texels-env-l1", "camera-ortho-disc-hero"]
    dtypes = (torch.float32,) if args.quick else (torch.float32, torch.float64)
    for name in names:
        build, shape, chromatic, estimator, palette = scenes[name]
        for dtype in dtypes:
            _step(record, log, f"case {name} {str(dtype)[6:]}",
                  lambda: _case(torch, ta, _C, build, shape, chromatic, estimator, palette, dtype, args))
    build, shape, chromatic, estimator, palette = scenes["object-texels-env-l1"]
    _step(record, log, "case object grad_support f32",
          lambda: _case(torch, ta, _C, build, shape, chromatic, estimator, False, torch.float32, args,
                        grad_support=True))
    _step(record, log, "case object adjoint (ema walk) f32",
          lambda: _case(torch, ta, _C, build, shape, chromatic, estimator, False, torch.float32, args, adjoint=True))
    if on_gpu:
        _step(record, log, "memory refusal", lambda: _memory_refusal(torch))
    _step(record, log, "gradcheck f64", lambda: _gradcheck(torch, ta, args.device))
    _step(record, log, "stiff", lambda: _stiff(torch, ta, args.device))
    if not args.quick:
        _step(record, log, "timing", lambda: _timing(torch, ta, _C, args))
    record["ok"] = all(s["ok"] for s in record["steps"])
    record["wall_s"] = round(time.perf_counter() - started, 1)
    failed = [s["name"] for s in record["steps"] if not s["ok"]]
    log(f"gpu_check: {len(record['steps']) - len(failed)} of {len(record['steps'])} steps ok in {record['wall_s']} s"
        + (f"; failed: {', '.join(failed)}" if failed else ""))
    _write(record, log, args.out)
    return 0 if record["ok"] else 1


def _write(record, log, folder):
    if not folder:
        return
    os.makedirs(folder, exist_ok=True)
    record["log"] = log.lines
    path = os.path.join(folder, RECORD_NAME)
    with open(path, "w", encoding="utf-8") as fh:
        json.dump(record, fh, indent=1, default=str)
    print(f"gpu_check: wrote {path}", flush=True)


if __name__ == "__main__":
    sys.exit(main())
