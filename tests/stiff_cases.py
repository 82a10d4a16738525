"""Stiff and extreme tracer cases: one function that renders a case and checks what physics guarantees.

Used by tests/test_stiff_sweep.py (a sweep sized for the test budget) and scripts/bench/stiff_sweep.py (the full sweep).
"""
import math
import warnings

import torch

import torch_appearance as ta

SIGMAS = (0.0, 1e-6, 1e-2, 1.0, 1e2, 1e4)  # mm⁻¹
ALBEDOS = (0.0, 1e-3, 0.5, 0.9997, 1.0)
GS = (-0.99, 0.0, 0.99)
IORS = (None, 1.0 + 1e-6, 1.5, 3.0)  # 1 + 1e-6: a dielectric that is almost index matched
THICKNESS = ("1 voxel", "2.5 mm")
VOXEL = 0.1  # mm


def run_case(sigma, albedo, g, ior, thickness, *, texels=3, spp=64, seed=0, max_depth=4096):
    """Render one uniform slab case forward and backward; return measured quantities and failed checks.

    Checks (each only where it applies):
      finite image and gradients; 0 <= L <= environment (+ float round-off);
      white furnace (albedo 1): L = 1 exactly unless paths were cut by max_depth (then the cut fraction is reported
      and must explain the deficit exactly);
      Beer–Lambert (albedo 0): L = R + (1 − R)²T/(1 − RT) (or T index-matched), z-test at 5σ;
      gradient sign: ∂L/∂σ_t <= 0 when albedo = 0 (more extinction, less light), ∂L/∂albedo >= 0 everywhere.
    """
    depth = 1 if thickness == "1 voxel" else int(round(2.5 / VOXEL))
    shape = (3, depth, texels, texels)
    s = torch.full(shape, float(sigma), dtype=torch.float64, requires_grad=True)
    a = torch.full(shape, float(albedo), dtype=torch.float64, requires_grad=True)
    stats = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # truncation is checked below from the counts
        img = ta.render_texels(s, a, voxel_size=VOXEL, g=g, ior=ior, spp=spp, seed=seed, max_depth=max_depth,
                               stats=stats)
    img.sum().backward()
    failed = []
    if not bool(torch.isfinite(img).all()):
        failed.append("non-finite image")
    if not (bool(torch.isfinite(s.grad).all()) and bool(torch.isfinite(a.grad).all())):
        failed.append("non-finite gradient")
    img = img.detach()
    if float(img.min()) < 0 or float(img.max()) > 1 + 1e-9:
        failed.append(f"radiance outside [0, env]: [{float(img.min())}, {float(img.max())}]")
    walks = texels * texels * spp * (1 if stats["lanes"] == 3 else 3)
    cut = stats["truncated_paths"] / walks
    if albedo == 1.0:
        deficit = 1.0 - float(img.mean())
        if abs(deficit - cut) > 1e-9:
            failed.append(f"furnace deficit {deficit:.3g} not explained by cut paths {cut:.3g}")
    if albedo == 0.0:
        t = math.exp(-sigma * depth * VOXEL)
        expected = t if ior is None else (lambda r: r + (1 - r) ** 2 * t / (1 - r * t))(((ior - 1) / (ior + 1)) ** 2)
        n = img.numel() // 3 * spp
        se = math.sqrt(max(expected * (1 - expected), 1e-12) / n)
        if abs(float(img.mean()) - expected) > 5 * se + 1e-12:
            failed.append(f"Beer–Lambert {float(img.mean()):.6g} vs {expected:.6g} (se {se:.2g})")
        if float(s.grad.sum()) > 1e-12:
            failed.append(f"∂L/∂σ_t > 0 with albedo 0: {float(s.grad.sum())}")
    if float(a.grad.sum()) < -1e-9:
        failed.append(f"∂L/∂albedo < 0: {float(a.grad.sum())}")
    return {"sigma": sigma, "albedo": albedo, "g": g, "ior": ior, "thickness": thickness, "mean": float(img.mean()),
            "cut_fraction": cut, "grad_sigma_sum": float(s.grad.sum()), "grad_albedo_sum": float(a.grad.sum()),
            "failed": failed}
