#!/usr/bin/env python
"""Benchmark the C++ volume path tracer: forward and backward (path replay) time, throughput and memory.

For each scene and thread count: one warm-up run (forward + backward), then ``--reps`` timed repetitions;
the medians are reported. The backward pass is that of ``loss = (image * w).sum()`` with fixed random
weights ``w``, with ``sigma_t`` and ``albedo`` both requiring grad. ``--one-walk`` also times the render and that
gradient as one walk with ``w`` given first (``adjoint=w``, as the print loop's ema estimator runs). Scenes (all 64 x 64 texels, 0.085 mm
voxels, smooth dielectric boundary with IOR 1.5, HG g = 0.4, top face):

    ink-slab     1 mm (D = 12); sigma_t ~ U(2, 24) mm^-1 and albedo ~ U(0.05, 0.9997), independently per
                 channel and voxel (chromatic: one walk per channel); 16 spp
    achromatic   as ink-slab, but sigma_t grey (the same for R, G, B; albedo still per channel), so one
                 walk serves all three channels: compare its forward_s with ink-slab's
    white-dense  2.5 mm (D = 29) of Vero white: sigma_t = (6, 9, 24) mm^-1, albedo (0.9991, 0.9997, 0.999):
                 long random walks; 4 spp
    thin         D = 12 of almost vacuum (sigma_t = 1e-4 mm^-1, albedo 1) with ~5 % of the voxels dense
                 white ink; 16 spp
    sphere       (render_scene) a dielectric (IOR 1.5) SDF sphere of radius 1.2 mm in a 32^3 grid of ink-like
                 chromatic medium, read by 4096 surface texels (Fibonacci points, footprint radius half a voxel),
                 constant environment; 16 spp
    camera       (render_scene) the same sphere seen by a 64 x 64 perspective camera under a disc light with
                 ambient; 16 spp
    print-slab   the print optimisation's start: 18 voxels (1.5 mm) of the default ink set's 97 % white mixture
                 (MaterialMixture at initialisation, chromatic) at 300 DPI (0.0847 mm voxels), --slab-size texels per
                 side (default 190; the issue's Nefertiti-sized slab is 760), top face; 32 spp

Error per second: unless ``--ref-mult 0``, each scene is also rendered once at ``--ref-mult`` times its spp with an
independent seed (cached under ``<out folder>/reference/``), and the rows give the RMSE of the image and of the two
gradients against it. The reference carries noise of its own, 1/ref-mult of the estimate's variance for the same
estimator; ``*_rmse`` are corrected for it (raw MSE / (1 + 1/ref-mult)). ``efficiency_*`` = 1 / (RMSE² · seconds)
(forward + backward) is the measure to compare variants by: higher is better, independent of spp.

Chromatic estimators (``--chromatic per_channel,hero``): each scene is run once per estimator of a chromatic
sampling density (render_texels' ``chromatic``: one walk per channel, or one hero-channel walk with spectral MIS);
the reference is always the per-channel estimator, so a variant's raw MSE holds the reference's noise variance,
taken as the per-channel row's corrected MSE / ref-mult (run per_channel first) and subtracted. Rows of a variant
carry ``chromatic`` and ``efficiency_*_vs_per_channel`` (its efficiency over that of the per-channel row of the
same scene and thread count: > 1 means the variant gives less error per second).

Walks (``--walks scalar,avx2,avx512``): the float32 slab scenes with a chromatic medium (one walk per channel) run on
a SIMD walk (csrc/volpath/slab_simd.h: AVX2, eight paths per thread; AVX-512, sixteen) where the CPU has it, else on
the scalar walk; all give the same paths. Each scene is run once per walk in the order given, rows carry ``walk``, and
rows after the first carry ``forward_speedup_vs_<first>``, ``backward_speedup_vs_<first>`` and ``efficiency_*_vs_<first>``.

With ``--baseline REV`` the slab scenes are also timed on the extension built from git revision REV (built once
into build/baseline-<sha>/): old and new are loaded in separate worker processes that call the same raw entry
points (``_C.scene_forward``/``scene_backward``, the forward on the parameters, the backward on the floored
reference as render_texels does), alternating old and new for every repetition, and a JSON line per scene gives
``ratio_forward`` and ``ratio_backward`` = new / old (medians, and of the fastest repetitions). With
``--one-walk`` too, the new worker also times ``_C.scene_forward_backward`` (the render and its gradient in one walk,
as the print loop's ``ema`` estimator runs each iteration after its first), and the line adds
``ratio_iteration_one_walk`` = that walk / the old build's forward + backward (medians).

One JSON line per scene and thread count is printed (and all of them written atomically to ``--out``),
with the fields

    scene, walk, texels, grid_dhw, spp, threads, forward_s, backward_s (medians of the wall-clock times),
    backward_over_forward, forward_min_s, backward_min_s (the fastest repetitions: robust to a busy machine),
    scatter_events, events_per_s, backward_scatter_events, backward_events_per_s,
    image_rmse, grad_sigma_t_rmse, grad_albedo_rmse, ref_spp, efficiency_image, efficiency_grad_sigma_t,
    efficiency_grad_albedo (see "Error per second"),
    forward_tracer_s, backward_tracer_s (the tracer's own timers from ``stats``),
    peak_rss_mb (peak resident memory while the scene ran: VmHWM after resetting it, else getrusage maxrss),
    rss_growth_mb (that peak minus the resident memory just before the scene was built), maxrss_mb
    (getrusage maxrss of the whole process so far), grid_mb (sigma_t + albedo), reps, seed

and a bar chart of forward/backward seconds per scene is saved beside ``--out`` (``volpath.png``).

Usage::

    python scripts/bench/bench_volpath.py --threads 1,8 --scenes ink-slab,achromatic --reps 3
    python scripts/bench/bench_volpath.py --baseline fbb88c3 --reps 5     # the slab scenes, new / old
    python scripts/bench/bench_volpath.py --scenes print-slab,ink-slab --chromatic per_channel,hero --threads 2
    python scripts/bench/bench_volpath.py --scenes print-slab --slab-size 760 --walks scalar,avx2,avx512 --threads 2 --spp 4
"""
import argparse
import io
import json
import math
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
import zlib

import numpy as np
import torch

import torch_appearance
from torch_appearance import io as ta_io
from torch_appearance._ext import _C

VOXEL_SIZE = 0.085  # mm
TEXELS = 64  # per side
WHITE_SIGMA_T = (6.0, 9.0, 24.0)
WHITE_ALBEDO = (0.9991, 0.9997, 0.999)


# --------------------------------------------------------------------------------------------------------------
# scenes
# --------------------------------------------------------------------------------------------------------------
def _uniform(generator, shape, low, high):
    return low + (high - low) * torch.rand(shape, generator=generator, dtype=torch.float64)


def _per_channel(values, shape):
    return torch.tensor(values, dtype=torch.float64).view(3, 1, 1, 1).expand(3, *shape).clone()


def scene_ink_slab(generator):
    shape = (12, TEXELS, TEXELS)
    sigma_t = _uniform(generator, (3, *shape), 2.0, 24.0)
    albedo = _uniform(generator, (3, *shape), 0.05, 0.9997)
    return sigma_t, albedo, 16


def scene_achromatic(generator):
    shape = (12, TEXELS, TEXELS)
    sigma_t = _uniform(generator, (1, *shape), 2.0, 24.0).expand(3, *shape).clone()
    albedo = _uniform(generator, (3, *shape), 0.05, 0.9997)
    return sigma_t, albedo, 16


def scene_white_dense(generator):
    shape = (int(round(2.5 / VOXEL_SIZE)), TEXELS, TEXELS)  # D = 29
    return _per_channel(WHITE_SIGMA_T, shape), _per_channel(WHITE_ALBEDO, shape), 4


def scene_thin(generator):
    shape = (12, TEXELS, TEXELS)
    dense = (torch.rand(shape, generator=generator, dtype=torch.float64) < 0.05).expand(3, *shape)
    sigma_t = torch.where(dense, _per_channel(WHITE_SIGMA_T, shape), torch.full((3, *shape), 1e-4, dtype=torch.float64))
    albedo = torch.where(dense, _per_channel(WHITE_ALBEDO, shape), torch.ones((3, *shape), dtype=torch.float64))
    return sigma_t, albedo, 16


SPHERE_N, SPHERE_R = 32, 1.2  # grid voxels per axis, sphere radius (mm)


def _sphere_medium(generator):
    shape = (SPHERE_N,) * 3
    base = torch.tensor([2.25, 3.75, 19.0], dtype=torch.float64).view(3, 1, 1, 1)
    sigma_t = base * (0.5 + torch.rand((3, *shape), generator=generator, dtype=torch.float64))
    albedo = _uniform(generator, (3, *shape), 0.5, 0.9997)
    return sigma_t, albedo


def _sphere_scene(sensor, emitter):
    from torch_appearance.geometry import sphere_sdf
    from torch_appearance.render import Scene, SDFBoundary
    half = SPHERE_N * VOXEL_SIZE / 2
    origin = (-half, -half, -half)
    sdf = sphere_sdf((SPHERE_N,) * 3, VOXEL_SIZE, origin, (0, 0, 0), SPHERE_R)
    return Scene(voxel_size=VOXEL_SIZE, origin=origin, boundary=SDFBoundary(sdf, ior=1.5), sensor=sensor,
                 emitter=emitter, g=0.4)


def scene_sphere(generator):
    from torch_appearance.render import ConstantEnvironment, SurfaceTexels
    n = 4096  # Fibonacci sphere
    k = torch.arange(n, dtype=torch.float64) + 0.5
    z = 1 - 2 * k / n
    phi = math.pi * (3 - math.sqrt(5)) * k
    normals = torch.stack([(1 - z * z).sqrt() * phi.cos(), (1 - z * z).sqrt() * phi.sin(), z], dim=1)
    sensor = SurfaceTexels(SPHERE_R * normals, normals, footprint_mm=VOXEL_SIZE / 2)
    sigma_t, albedo = _sphere_medium(generator)
    return sigma_t, albedo, 16, _sphere_scene(sensor, ConstantEnvironment(1.0))


def scene_camera(generator):
    from torch_appearance.render import DiscLight, PerspectiveCamera
    cam = PerspectiveCamera(origin=(4.0, 2.5, 3.0), target=(0, 0, 0), up=(0, 0, 1), fov_y_deg=28,
                            resolution=(TEXELS, TEXELS))
    sigma_t, albedo = _sphere_medium(generator)
    return sigma_t, albedo, 16, _sphere_scene(cam, DiscLight((1, -1, 2), 15, 20.0, 0.5))


PRINT_VOXEL = 25.4 / 300  # mm: the print optimisation's default 300 DPI
PRINT_DEPTH = 18  # voxels: 1.5 mm


def scene_print_slab(generator, size=190):
    from torch_appearance.fabrication import InkSet
    from torch_appearance.nn import MaterialMixture
    with torch.no_grad():
        sigma_t, albedo = MaterialMixture(InkSet.from_names(), shape=(1, 1, 1))()  # 97 % white everywhere
    shape = (PRINT_DEPTH, size, size)
    return (sigma_t.double().reshape(3, 1, 1, 1).expand(3, *shape).clone(),
            albedo.double().reshape(3, 1, 1, 1).expand(3, *shape).clone(), 32)


SCENES = {
    "ink-slab": scene_ink_slab,
    "achromatic": scene_achromatic,
    "white-dense": scene_white_dense,
    "thin": scene_thin,
    "sphere": scene_sphere,
    "camera": scene_camera,
    "print-slab": scene_print_slab,
}
SLAB_SCENES = ("ink-slab", "achromatic", "white-dense", "thin", "print-slab")
SCENE_VOXEL = {"print-slab": PRINT_VOXEL}  # voxel edge (mm) of the scenes that do not use VOXEL_SIZE


def make_scene(name, generator, args):
    """(sigma_t, albedo, default spp, render_scene Scene or None) of a named scene."""
    if name == "print-slab":
        out = scene_print_slab(generator, args.slab_size)
    else:
        out = SCENES[name](generator)
    sigma_t, albedo, spp, *scene = out
    return sigma_t, albedo, spp, (scene[0] if scene else None)


# --------------------------------------------------------------------------------------------------------------
# memory
# --------------------------------------------------------------------------------------------------------------
from torch_appearance.testing import reset_peak_rss as _reset_peak_rss, status_kb as _status_kb  # noqa: E402


def _maxrss_mb():
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return rss / 1024.0 if sys.platform != "darwin" else rss / 2**20  # kB on Linux, bytes on macOS


# --------------------------------------------------------------------------------------------------------------
# timing
# --------------------------------------------------------------------------------------------------------------
def _run_once(sigma_t, albedo, weights, spp, seed, ior, g, scene=None, voxel_size=VOXEL_SIZE, keep=False,
              chromatic="per_channel"):
    """One forward + backward; returns wall seconds, the tracer's stats and (keep) the image and gradients."""
    st = sigma_t.detach().clone().requires_grad_()
    al = albedo.detach().clone().requires_grad_()
    stats = {}
    start = time.perf_counter()
    if scene is None:
        image = torch_appearance.render_texels(
            st, al, voxel_size=voxel_size, face="top", g=g, ior=ior, environment=1.0, spp=spp, seed=seed, stats=stats,
            chromatic=chromatic)
    else:
        image = torch_appearance.render_scene(scene, st, al, spp=spp, seed=seed, stats=stats, chromatic=chromatic)
    forward_s = time.perf_counter() - start
    loss = (image * weights).sum()
    start = time.perf_counter()
    loss.backward()
    backward_s = time.perf_counter() - start
    if st.grad is None or al.grad is None:
        raise RuntimeError("render_texels produced no gradient for sigma_t/albedo")
    if keep:
        return forward_s, backward_s, stats, (image.detach(), st.grad, al.grad)
    return forward_s, backward_s, stats


def _run_one_walk(sigma_t, albedo, weights, spp, seed, ior, g, scene=None, voxel_size=VOXEL_SIZE,
                  chromatic="per_channel"):
    """The same render and gradient with the adjoint ``weights`` known first (render's ``adjoint``: one walk for
    both, as the print loop's ema estimator from its second iteration on); returns wall seconds."""
    st = sigma_t.detach().clone().requires_grad_()
    al = albedo.detach().clone().requires_grad_()
    start = time.perf_counter()
    if scene is None:
        image = torch_appearance.render_texels(
            st, al, voxel_size=voxel_size, face="top", g=g, ior=ior, environment=1.0, spp=spp, seed=seed,
            chromatic=chromatic, adjoint=weights)
    else:
        image = torch_appearance.render_scene(scene, st, al, spp=spp, seed=seed, chromatic=chromatic, adjoint=weights)
    (image * weights).sum().backward()
    return time.perf_counter() - start


def _reference(name, sigma_t, albedo, weights, spp, args, scene, voxel_size):
    """Image and gradients at ``args.ref_mult`` × spp with an independent seed, cached in <out>/reference/."""
    ref_spp = spp * args.ref_mult
    size = "x".join(str(n) for n in sigma_t.shape[1:])
    folder = os.path.join(os.path.dirname(os.path.abspath(args.out)), "reference")
    path = os.path.join(folder, f"{name}-{size}-spp{ref_spp}-ior{args.ior}-g{args.g}-seed{args.seed}.pt")
    if os.path.exists(path):
        return torch.load(path), ref_spp
    print(f"{name}: reference at {ref_spp} spp (once, cached in {path}) ...", file=sys.stderr, flush=True)
    *_, ref = _run_once(sigma_t, albedo, weights, ref_spp, args.seed + 7919, args.ior, args.g, scene, voxel_size,
                        keep=True)
    os.makedirs(folder, exist_ok=True)
    buffer = io.BytesIO()
    torch.save(ref, buffer)
    ta_io.atomic_write_bytes(path, buffer.getvalue())
    return ref, ref_spp


def _rmse(estimate, reference, ref_mult, ref_var=None):
    """RMSE of a Monte Carlo estimate against a noisy reference of the same estimator at ref_mult × the samples:
    E|x − r|² = σ²(1 + 1/ref_mult), so the raw MSE is divided by that factor. With ``ref_var`` (the reference's
    noise variance, for an estimator other than the reference's) that is subtracted instead."""
    mse = float(((estimate.double() - reference.double()) ** 2).mean())
    if ref_var is not None:
        return math.sqrt(max(mse - ref_var, 0.0))
    return math.sqrt(mse / (1.0 + 1.0 / ref_mult))


def bench_scene(name, threads, args, chromatic="per_channel", ref_var=None):
    """One JSON row; ``ref_var`` (key → the reference's noise variance) corrects the RMSE of a variant whose
    estimator differs from the reference's (see "Chromatic estimators")."""
    torch.set_num_threads(threads)
    peak_reset = _reset_peak_rss() and _status_kb("VmHWM") is not None
    baseline_kb = _status_kb("VmRSS")  # after the reset, so that VmHWM >= baseline
    generator = torch.Generator().manual_seed(args.seed + zlib.crc32(name.encode()))
    sigma_t, albedo, default_spp, scene = make_scene(name, generator, args)
    voxel_size = SCENE_VOXEL.get(name, VOXEL_SIZE)
    sigma_t = sigma_t.to(torch.float32).contiguous()
    albedo = albedo.to(torch.float32).contiguous()
    spp = args.spp if args.spp is not None else default_spp
    _, depth, height, width = sigma_t.shape
    out_shape = (height, width, 3) if scene is None else scene.output_shape((depth, height, width))
    weights = torch.rand(out_shape, generator=generator, dtype=torch.float64).to(torch.float32)

    _run_once(sigma_t, albedo, weights, spp, args.seed, args.ior, args.g, scene, voxel_size,
              chromatic=chromatic)  # warm-up
    runs = [_run_once(sigma_t, albedo, weights, spp, args.seed, args.ior, args.g, scene, voxel_size,
                      keep=rep == args.reps - 1, chromatic=chromatic) for rep in range(args.reps)]
    forward_s = statistics.median(r[0] for r in runs)
    backward_s = statistics.median(r[1] for r in runs)
    stats = runs[-1][2]
    one_walk = {}
    if args.one_walk:
        one_s = statistics.median(_run_one_walk(sigma_t, albedo, weights, spp, args.seed, args.ior, args.g, scene,
                                                voxel_size, chromatic) for _ in range(args.reps))
        one_walk = {"one_walk_s": round(one_s, 6), "two_walks_over_one": round((forward_s + backward_s) / one_s, 4)}

    def _median_stat(key):
        values = [r[2][key] for r in runs if r[2].get(key) is not None]
        return statistics.median(values) if values else None

    events = stats.get("scatter_events")
    backward_events = stats.get("backward_scatter_events")
    if peak_reset:
        peak_mb = _status_kb("VmHWM") / 1024.0
    else:
        peak_mb = _maxrss_mb()
    error = {}
    if args.ref_mult > 0:
        ref, ref_spp = _reference(name, sigma_t, albedo, weights, spp, args, scene, voxel_size)
        seconds = forward_s + backward_s
        error["ref_spp"] = ref_spp
        for key, est, want in zip(("image", "grad_sigma_t", "grad_albedo"), runs[-1][3], ref):
            rmse = _rmse(est, want, args.ref_mult, None if ref_var is None else ref_var.get(key))
            error[f"{key}_rmse"] = float(f"{rmse:.6g}")
            error[f"efficiency_{key}"] = float(f"{1.0 / (rmse * rmse * seconds):.6g}") if rmse > 0 else None
    return {
        "scene": name,
        "chromatic": chromatic,
        "hero": stats.get("hero"),
        "lanes": stats.get("lanes"),
        "texels": math.prod(out_shape[:-1]),
        "grid_dhw": [depth, height, width],
        "spp": spp,
        "threads": torch.get_num_threads(),
        "forward_s": round(forward_s, 6),
        "backward_s": round(backward_s, 6),
        "backward_over_forward": round(backward_s / forward_s, 4),
        "forward_min_s": round(min(r[0] for r in runs), 6),
        "backward_min_s": round(min(r[1] for r in runs), 6),
        "scatter_events": events,
        "events_per_s": round(events / forward_s) if events is not None else None,
        "backward_scatter_events": backward_events,
        "backward_events_per_s": round(backward_events / backward_s) if backward_events is not None else None,
        "forward_tracer_s": _median_stat("forward_s"),
        "backward_tracer_s": _median_stat("backward_s"),
        "peak_rss_mb": round(peak_mb, 1),
        "peak_rss_source": "VmHWM" if peak_reset else "ru_maxrss",
        # (clamped at 0: the kernel's RSS counters are synchronised lazily, so tiny negative differences occur)
        "rss_growth_mb": round(max(0.0, peak_mb - baseline_kb / 1024.0), 1) if baseline_kb is not None else None,
        "maxrss_mb": round(_maxrss_mb(), 1),
        "grid_mb": round((sigma_t.numel() + albedo.numel()) * sigma_t.element_size() / 2**20, 3),
        **error,
        **one_walk,
        "reps": args.reps,
        "seed": args.seed,
    }


# --------------------------------------------------------------------------------------------------------------
# old code against new code (--baseline)
# --------------------------------------------------------------------------------------------------------------
ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

# Runs in a fresh interpreter: loads one build of the extension (two builds cannot share a process: pybind11
# registers the option types globally), times one forward and one backward after a warm-up, prints JSON.
# WORKER_LOAD is the part every such worker shares (bench_objects.py too): argv is (extension, data, threads); it
# leaves the module in C and the torch.save'd dict in d.
WORKER_LOAD = r"""
import importlib.util, json, sys, time, torch
so, data, threads = sys.argv[1], sys.argv[2], int(sys.argv[3])
torch.set_num_threads(threads)
spec = importlib.util.spec_from_file_location("ta_bench_ext._C", so)
C = importlib.util.module_from_spec(spec)
spec.loader.exec_module(C)
d = torch.load(data)
"""
_WORKER = WORKER_LOAD + r"""
o, b, se, e = C.SceneOptions(), C.BoundaryOptions(), C.SensorOptions(), C.EmitterOptions()
opt = dict(d["options"])
b.ior, se.face, e.radiance = opt.pop("ior"), opt.pop("face"), opt.pop("environment")
o.boundary, o.sensor, o.emitter = b, se, e
for k, v in opt.items():
    setattr(o, k, v)
s, a, rs, ra, w = d["sigma_t"], d["albedo"], d["ref_sigma_t"], d["ref_albedo"], d["weights"]
image, _ = C.scene_forward(s, a, s, a, False, o)
C.scene_backward(w, s, a, rs, ra, True, True, o)
t0 = time.perf_counter()
image, counts = C.scene_forward(s, a, s, a, False, o)
t1 = time.perf_counter()
gs, ga, _ = C.scene_backward(w, s, a, rs, ra, True, True, o)
t2 = time.perf_counter()
one = None
if d.get("one_walk") and hasattr(C, "scene_forward_backward"):  # the render and its gradient in one walk
    C.scene_forward_backward(w, s, a, rs, ra, True, True, o)
    t3 = time.perf_counter()
    C.scene_forward_backward(w, s, a, rs, ra, True, True, o)
    one = time.perf_counter() - t3
with open(f"/proc/self/status") as f:
    peak = [int(l.split()[1]) / 1024 for l in f if l.startswith("VmHWM:")]
print(json.dumps({"forward_s": t1 - t0, "backward_s": t2 - t1, "one_walk_s": one, "checksum": float(image.double().sum()),
                  "grad_checksum": [float(gs.double().sum()), float(ga.double().sum()), float(gs.double().abs().sum()),
                                    float(ga.double().abs().sum())], "peak_rss_mb": peak[0] if peak else None}))
"""


def build_baseline(rev):
    """Path of the extension built from git revision ``rev`` (built once into build/baseline-<sha>/)."""
    import glob
    import shutil
    sha = subprocess.check_output(["git", "rev-parse", "--verify", f"{rev}^{{commit}}"], cwd=ROOT,
                                  text=True).strip()
    target = os.path.join(ROOT, "build", f"baseline-{sha[:12]}")
    found = glob.glob(os.path.join(target, "torch_appearance", "_C*.so"))
    if found:
        return found[0], sha
    partial = target + ".partial"
    shutil.rmtree(partial, ignore_errors=True)
    os.makedirs(partial)
    archive = subprocess.run(["git", "archive", sha], cwd=ROOT, check=True, capture_output=True).stdout
    subprocess.run(["tar", "-x", "-C", partial], input=archive, check=True)
    print(f"building the baseline extension of {sha[:12]} (once) ...", file=sys.stderr, flush=True)
    subprocess.run([sys.executable, "setup.py", "--quiet", "build_ext", "--inplace"], cwd=partial, check=True,
                   stdout=sys.stderr)  # keep stdout for the JSON lines
    os.replace(partial, target)
    return glob.glob(os.path.join(target, "torch_appearance", "_C*.so"))[0], sha


def compare_baseline(name, threads, args, old_so, sha):
    """new / old time ratios of one slab scene, old and new alternating in worker processes."""
    from torch_appearance.autograd.volpath import sampling_lanes
    from torch_appearance.render import Scene, TraceJob
    generator = torch.Generator().manual_seed(args.seed + zlib.crc32(name.encode()))
    sigma_t, albedo, default_spp, _ = make_scene(name, generator, args)
    voxel_size = SCENE_VOXEL.get(name, VOXEL_SIZE)
    sigma_t = sigma_t.to(torch.float32).contiguous()
    albedo = albedo.to(torch.float32).contiguous()
    spp = args.spp if args.spp is not None else default_spp
    _, depth, height, width = sigma_t.shape
    weights = torch.rand((height, width, 3), generator=generator, dtype=torch.float64).to(torch.float32)
    slab = TraceJob(Scene.slab(voxel_size, g=args.g, ior=args.ior), spp=spp, seed=args.seed)
    ref_s = sigma_t.clamp_min(slab.sigma_t_floor(sigma_t.shape)).contiguous()
    ref_a = albedo.clamp_min(slab.albedo_floor).contiguous()
    options = dict(voxel_size=[voxel_size] * 3, face=0, g=args.g, ior=args.ior, environment=[1.0, 1.0, 1.0],
                   spp=spp, seed=args.seed, max_depth=slab.scene.max_depth, rr_depth=slab.scene.rr_depth,
                   lanes=sampling_lanes(sigma_t))
    new_so = torch_appearance._C.__file__
    with tempfile.TemporaryDirectory() as tmp:
        data = os.path.join(tmp, "scene.pt")
        torch.save(dict(sigma_t=sigma_t, albedo=albedo, ref_sigma_t=ref_s, ref_albedo=ref_a, weights=weights,
                        options=options, one_walk=args.one_walk), data)
        runs = {"old": [], "new": []}
        for _ in range(args.reps):
            for which, so in (("old", old_so), ("new", new_so)):
                out = subprocess.run([sys.executable, "-c", _WORKER, so, data, str(threads)], check=True,
                                     capture_output=True, text=True).stdout
                runs[which].append(json.loads(out.strip().splitlines()[-1]))
    med = {w: {k: statistics.median(r[k] for r in runs[w]) for k in ("forward_s", "backward_s")} for w in runs}
    low = {w: {k: min(r[k] for r in runs[w]) for k in ("forward_s", "backward_s")} for w in runs}
    one_walk = {}
    if args.one_walk and all(r.get("one_walk_s") is not None for r in runs["new"]):
        # the ema print loop's iteration (one walk) against the old build's forward + backward
        new_one = statistics.median(r["one_walk_s"] for r in runs["new"])
        old_two = statistics.median(r["forward_s"] + r["backward_s"] for r in runs["old"])
        one_walk = {"new_one_walk_s": round(new_one, 6), "old_iteration_s": round(old_two, 6),
                    "ratio_iteration_one_walk": round(new_one / old_two, 4)}
    return {
        "scene": name, "compare": "new/old", "baseline": sha[:12], "threads": threads, "spp": spp, **one_walk,
        "old_forward_s": round(med["old"]["forward_s"], 6), "new_forward_s": round(med["new"]["forward_s"], 6),
        "old_backward_s": round(med["old"]["backward_s"], 6), "new_backward_s": round(med["new"]["backward_s"], 6),
        "ratio_forward": round(med["new"]["forward_s"] / med["old"]["forward_s"], 4),
        "ratio_backward": round(med["new"]["backward_s"] / med["old"]["backward_s"], 4),
        "ratio_forward_min": round(low["new"]["forward_s"] / low["old"]["forward_s"], 4),
        "ratio_backward_min": round(low["new"]["backward_s"] / low["old"]["backward_s"], 4),
        "old_peak_rss_mb": max(r["peak_rss_mb"] or 0 for r in runs["old"]),
        "new_peak_rss_mb": max(r["peak_rss_mb"] or 0 for r in runs["new"]),
        "same_image": runs["old"][0]["checksum"] == runs["new"][0]["checksum"],
        "same_gradient_checksums": runs["old"][0].get("grad_checksum") == runs["new"][0].get("grad_checksum"),
        "reps": args.reps,
    }


# --------------------------------------------------------------------------------------------------------------
# output
# --------------------------------------------------------------------------------------------------------------
def plot(rows, path):
    """Grouped bars of forward and backward seconds per scene (and thread count)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    labels = [f"{r['scene']}{' (hero)' if r.get('hero') else ''}{' ' + r['walk'] if r.get('walk') != 'auto' else ''}"
              f"\n{r['threads']} thr, {r['spp']} spp" for r in rows]
    x = np.arange(len(rows))
    fig, ax = plt.subplots(figsize=(max(6.0, 1.6 * len(rows)), 4.0))
    ax.bar(x - 0.2, [r["forward_s"] for r in rows], 0.4, label="forward")
    ax.bar(x + 0.2, [r["backward_s"] for r in rows], 0.4, label="backward (path replay)")
    ax.set_xticks(x)
    ax.set_xticklabels(labels, fontsize=8)
    ax.set_ylabel("seconds (median)")
    ax.set_title(f"torch_appearance volume path tracer, {rows[0]['texels']} texels")
    ax.legend()
    fig.tight_layout()
    directory, name = os.path.split(path)
    tmp = os.path.join(directory, f".{name}.partial.png")
    try:  # atomic: render to a temporary file in the same folder, then rename
        fig.savefig(tmp, dpi=120)
        os.replace(tmp, path)
    finally:
        plt.close(fig)
        if os.path.exists(tmp):
            os.unlink(tmp)


def _int_list(text):
    try:
        values = [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers, got {text!r}") from None
    if not values or min(values) < 1:
        raise argparse.ArgumentTypeError(f"expected integers >= 1, got {text!r}")
    return values


def _names_from(choices, what):
    """argparse type: a comma-separated list of names from ``choices`` (``what`` names them in the error)."""
    def parse(text):
        names = [v.strip() for v in text.split(",") if v.strip()]
        unknown = [n for n in names if n not in choices]
        if not names or unknown:
            raise argparse.ArgumentTypeError(f"unknown {what} {unknown or text!r}; choose from {', '.join(choices)}")
        return names
    return parse


WALKS = {"auto": -1, "scalar": 0, "avx2": 1, "avx512": 2}


def _chromatic_names():
    from torch_appearance.render.scene import CHROMATIC
    return CHROMATIC


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], epilog=__doc__.split("\n\n", 1)[1],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenes", type=_names_from(SCENES, "scene(s)"), default=list(SCENES),
                        help=f"comma-separated scenes (default: {','.join(SCENES)})")
    parser.add_argument("--threads", type=_int_list, default=[torch.get_num_threads()],
                        help=f"comma-separated torch thread counts (default: {torch.get_num_threads()}, torch's own)")
    parser.add_argument("--spp", type=int, default=None, help="samples per texel for every scene (default: per scene)")
    parser.add_argument("--reps", type=int, default=3, help="timed repetitions after the warm-up (default: %(default)s)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the scenes and the tracer (default: %(default)s)")
    parser.add_argument("--ior", type=float, default=1.5, help="index of refraction (default: %(default)s)")
    parser.add_argument("--g", type=float, default=0.4, help="Henyey-Greenstein parameter (default: %(default)s)")
    parser.add_argument("--out", default="results/bench/volpath.jsonl",
                        help="JSON-lines result file; the plot goes beside it (default: %(default)s)")
    parser.add_argument("--no-plot", action="store_true", help="do not draw the bar chart")
    parser.add_argument("--slab-size", type=int, default=190,
                        help="print-slab: texels per side (default: %(default)s; the issue's slab is 760)")
    parser.add_argument("--ref-mult", type=int, default=8,
                        help="reference spp = this × spp for the RMSE columns; 0: no reference (default: %(default)s)")
    parser.add_argument("--chromatic", type=_names_from(_chromatic_names(), "estimator(s)"), default=["per_channel"],
                        help="comma-separated estimators for chromatic media, from per_channel,hero; run per_channel "
                             "first (default: %(default)s)")
    parser.add_argument("--walks", type=_names_from(WALKS, "walk(s)"), default=["auto"],
                        help="comma-separated slab walks to time, from auto,scalar,avx2,avx512 (avx2, avx512: eight or "
                             "sixteen paths per thread in SIMD lanes, float32 slabs on CPUs with the instruction set; "
                             "auto: the widest that serves); rows after the first carry speed-ups and error-per-second "
                             "ratios against it (default: auto)")
    parser.add_argument("--one-walk", action="store_true",
                        help="also time the render and its gradient as one walk, the adjoint (the weights) known "
                             "first (one_walk_s, two_walks_over_one); with --baseline, that walk against the old "
                             "build's forward + backward (ratio_iteration_one_walk)")
    parser.add_argument("--baseline", metavar="REV", default=None,
                        help="also time the slab scenes on the extension of git revision REV and print new/old ratios")
    args = parser.parse_args(argv)
    if args.spp is not None and args.spp < 1:
        parser.error(f"--spp must be >= 1, got {args.spp}")
    if args.reps < 1:
        parser.error(f"--reps must be >= 1, got {args.reps}")
    if args.slab_size < 1:
        parser.error(f"--slab-size must be >= 1, got {args.slab_size}")
    if args.ref_mult < 0:
        parser.error(f"--ref-mult must be >= 0, got {args.ref_mult}")
    _C._set_simd(-1)
    level = _C._set_simd(-1)
    for walk in ("avx2", "avx512"):
        if walk in args.walks and WALKS[walk] > level:
            parser.error(f"--walks {walk}: this CPU cannot run it (or TA_SIMD limits the walks); the widest here is "
                         f"{[k for k, v in WALKS.items() if v == level][0]}")
    return args


def main(argv=None):
    args = parse_args(argv)
    directory = os.path.dirname(os.path.abspath(args.out))
    os.makedirs(directory, exist_ok=True)
    rows = []
    for threads in args.threads:
        for name, chromatic in ((n, c) for n in args.scenes for c in args.chromatic):
            base = [r for r in rows if r["scene"] == name and r["threads"] == threads
                    and r["chromatic"] == "per_channel"]
            ref_var = None
            if chromatic != "per_channel" and base and args.ref_mult > 0:
                ref_var = {k: base[0][f"{k}_rmse"] ** 2 / args.ref_mult
                           for k in ("image", "grad_sigma_t", "grad_albedo")}
            first = None
            for walk in args.walks:
                _C._set_simd(WALKS[walk])
                row = bench_scene(name, threads, args, chromatic, ref_var)
                row["walk"] = walk
                if base and chromatic != "per_channel" and args.ref_mult > 0:
                    same_walk = [r for r in base if r["walk"] == walk] or base
                    for k in ("image", "grad_sigma_t", "grad_albedo"):
                        e0, e1 = same_walk[0].get(f"efficiency_{k}"), row.get(f"efficiency_{k}")
                        row[f"efficiency_{k}_vs_per_channel"] = round(e1 / e0, 4) if e0 and e1 else None
                if first is None:
                    first = row
                else:  # the same scene with the first walk: speed-up and error-per-second ratios
                    row[f"forward_speedup_vs_{first['walk']}"] = round(first["forward_s"] / row["forward_s"], 3)
                    row[f"backward_speedup_vs_{first['walk']}"] = round(first["backward_s"] / row["backward_s"], 3)
                    for k in ("image", "grad_sigma_t", "grad_albedo"):
                        e0, e1 = first.get(f"efficiency_{k}"), row.get(f"efficiency_{k}")
                        if e0 and e1:
                            row[f"efficiency_{k}_vs_{first['walk']}"] = round(e1 / e0, 4)
                if name == "achromatic":
                    chromatic_rows = [r for r in rows if r["scene"] == "ink-slab" and r["threads"] == row["threads"]
                                      and r["spp"] == row["spp"] and r["walk"] == walk]
                    if chromatic_rows:
                        row["forward_speedup_vs_ink_slab"] = round(chromatic_rows[0]["forward_s"] / row["forward_s"], 3)
                        row["backward_speedup_vs_ink_slab"] = round(chromatic_rows[0]["backward_s"] / row["backward_s"],
                                                                    3)
                rows.append(row)
                print(json.dumps(row), flush=True)
            _C._set_simd(-1)
    comparisons = []
    if args.baseline is not None:
        old_so, sha = build_baseline(args.baseline)
        for threads in args.threads:
            for name in args.scenes:
                if name in SLAB_SCENES:
                    comparisons.append(compare_baseline(name, threads, args, old_so, sha))
                    print(json.dumps(comparisons[-1]), flush=True)
    rows_out = rows + comparisons
    ta_io.atomic_write_bytes(args.out, "".join(json.dumps(r) + "\n" for r in rows_out).encode())
    if not args.no_plot:
        plot(rows, os.path.join(directory, os.path.splitext(os.path.basename(args.out))[0] + ".png"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
