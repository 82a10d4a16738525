"""Wood appearance matching (thesis ch. 2): fit a procedural solid-wood texture to one photograph of a board.

photo → curved Gabor filter (orientation, magnitude, phase J_φ) → ring tracing at J_φ = π/2 → board location
(projected tree centre, ring scale, transform) → growth direction: the centre line placed where one lateness
profile explains both sides (``choose_pith_side``), phase sign resolved → initial ``WoodModel`` (radial distortion
from the traced rings and the unwrapped phase residual) → stage 1: cyclic phase loss E = wrap(J_φ − I_φ)² with Adam
(lr 0.03, 500 epochs) over the board transform, ring scale and distortion, the distortion coarse to fine (3
levels, so no texel cell slips by a ring) → stage 2: colour map (32 lateness bins) with the geometry frozen → run
folder.
``scripts/fit_wood.py`` is the command-line front end.
"""
import copy
import dataclasses
import io as _io
import math
import os
import time
from dataclasses import dataclass
from typing import Optional

import numpy as np
import torch

from .. import io as ta_io
from ..color import srgb_to_linear

__all__ = ["WoodFitConfig", "fit_wood", "load_photo", "phase_loss", "wrap", "effective_ring_width",
           "boundary_lateness", "model_boundaries", "LOG_FIELDS", "photometric_stage", "fit_metrics",
           "latewood_contrast"]

LOG_FIELDS = ["stage", "epoch", "wall_s", "phase_loss", "color_loss", "phase_rms", "photometric_loss"]
POOR_FIT_PHASE_RMS = 0.8  # rad; fits above it are flagged (summary["fit_ok"] = False) and warned about
# Fewer distinct rings than this on the board leave the ring scale poorly determined (the number of rings between
# the pith and the board trades against the axis distance); measured on synthetic boards (eval_wood_synthetic.py):
# s_r errors of 8-127 % with 2-4 visible rings, 3-7 % with 6-9.
MIN_RINGS_FOR_SCALE = 6


@dataclass
class WoodFitConfig:
    """Settings of one wood fit (every field is a flag of scripts/fit_wood.py)."""
    photo: str
    out: str = "results/wood"
    pixel_size_mm: float = 0.1
    epochs: int = 500
    lr: float = 0.03
    color_epochs: int = 200
    color_lr: float = 0.05
    p: int = 80
    q: int = 80
    distortion: str = "radial"
    distortion_shape: tuple = (32, 64)
    smoothness: float = 1.0  # weight of the distortion prior (squared texel-to-texel change, in ring widths)
    color_bins: int = 32  # lateness samples of the colour map (a thin latewood line needs a few of its own)
    coarse_to_fine: int = 3  # stage-1 distortion levels (1: the full texture from the start, as before)
    # after stage 2: remap the colour map's luminance so that the fit's luminance histogram is the photo's (the
    # per-bin photo means blur latewood into earlywood wherever the fitted phase is off by a fraction of a ring)
    contrast_match: bool = False
    # stage 3 (photometric): geometry + colour map against the photo's colours (CIELAB L2) through the
    # reparameterised render (correct boundary gradients), coarse to fine over photometric_levels (downsampling
    # factors of the photo), photometric_epochs Adam steps in all, split evenly over the levels
    photometric: bool = False
    photometric_epochs: int = 120
    photometric_lr: float = 0.005  # geometry, in ring widths per step (as lr)
    photometric_color_lr: float = 0.01  # colour map, linear RGB per step (0: frozen)
    photometric_spp: int = 4
    photometric_levels: tuple = (4, 2)
    photometric_weight: float = 10.0  # multiplies the CIELAB term (mean ΔE² / 100)
    photometric_anchor: float = 1.0  # weight of the stage-1 cyclic phase loss kept in stage 3 (0: colour only)
    photometric_estimator: str = "reparam"  # "naive": fixed-sample autograd, no boundary term (for comparison)
    device: str = "cpu"
    max_size: Optional[int] = None
    seed: int = 0
    preview: bool = True

    def validate(self):
        if not (isinstance(self.pixel_size_mm, (int, float)) and math.isfinite(self.pixel_size_mm)
                and self.pixel_size_mm > 0):
            raise ValueError(f"pixel_size_mm: expected a finite value > 0, got {self.pixel_size_mm!r}")
        for name in ("epochs", "color_epochs", "photometric_epochs"):
            v = getattr(self, name)
            if not isinstance(v, int) or v < 0:
                raise ValueError(f"{name}: expected an int >= 0, got {v!r}")
        for name in ("p", "q", "coarse_to_fine"):
            v = getattr(self, name)
            if not isinstance(v, int) or v < 1:
                raise ValueError(f"{name}: expected an int >= 1, got {v!r}")
        for name in ("color_bins",):
            v = getattr(self, name)
            if not isinstance(v, int) or v < 2:
                raise ValueError(f"{name}: expected an int >= 2, got {v!r}")
        for name in ("photometric", "contrast_match"):
            if not isinstance(getattr(self, name), bool):
                raise TypeError(f"{name}: expected a bool, got {type(getattr(self, name)).__name__}")
        if not isinstance(self.photometric_spp, int) or self.photometric_spp < 2:
            raise ValueError(f"photometric_spp: expected an int >= 2, got {self.photometric_spp!r}")
        levels = self.photometric_levels
        if (not isinstance(levels, (tuple, list)) or not levels
                or any(isinstance(f, bool) or not isinstance(f, int) or f < 1 for f in levels)):
            raise ValueError(f"photometric_levels: expected a non-empty sequence of ints >= 1 (downsampling factors, "
                             f"coarse first), got {levels!r}")
        if self.photometric_estimator not in ("reparam", "naive"):
            raise ValueError(f"photometric_estimator: expected 'reparam' or 'naive', "
                             f"got {self.photometric_estimator!r}")
        for name in ("photometric_weight", "photometric_anchor"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v >= 0):
                raise ValueError(f"{name}: expected a finite value >= 0, got {v!r}")
        if not (isinstance(self.photometric_color_lr, (int, float)) and self.photometric_color_lr >= 0):
            raise ValueError(f"photometric_color_lr: expected >= 0 (0: colour map frozen in stage 3), got "
                             f"{self.photometric_color_lr!r}")
        for name in ("lr", "color_lr", "photometric_lr"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and v > 0):
                raise ValueError(f"{name}: expected > 0, got {v!r}")
        if self.distortion not in ("radial", "azimuthal"):
            raise ValueError(f"distortion: expected 'radial' or 'azimuthal', got {self.distortion!r}")
        if self.device not in ("cpu", "cuda") and not str(self.device).startswith("cuda:"):
            raise ValueError(f"device: expected 'cpu' or 'cuda[:N]', got {self.device!r}")
        if str(self.device).startswith("cuda") and not torch.cuda.is_available():
            raise ValueError(f"device: {self.device!r} requested but CUDA is not available")


def load_photo(path, max_size=None):
    """A photo as linear RGB (H, W, 3) float32 and its luminance (H, W) in [0, 1] (sRGB decoded).

    Read with :func:`torch_appearance.io.read_image`: 8/16-bit sRGB images are decoded to linear, EXR is linear,
    grey is repeated over R, G, B, alpha is dropped; truncated or corrupt files are refused.

    Raises:
        ValueError: missing, unreadable, truncated or corrupt file, or smaller than 8×8 pixels.
    """
    import cv2

    if not isinstance(path, (str, os.PathLike)) or not os.path.isfile(path):
        raise ValueError(f"photo: expected an image file, got {path!r} (no such file)")
    rgb = ta_io.read_image(path, space="linear", name="photo")
    if min(rgb.shape[:2]) < 8:
        raise ValueError(f"photo: expected at least 8×8 pixels, got {rgb.shape[:2]}")
    if max_size is not None and max(rgb.shape[:2]) > max_size:
        f = max_size / max(rgb.shape[:2])
        rgb = cv2.resize(rgb, (round(rgb.shape[1] * f), round(rgb.shape[0] * f)), interpolation=cv2.INTER_AREA)
    gray = rgb @ np.array([0.2126, 0.7152, 0.0722], np.float32)
    return rgb.astype(np.float32), gray.astype(np.float32)


def wrap(x):
    """Wrap angles to (−π, π] (differentiable almost everywhere)."""
    return x - 2 * math.pi * torch.floor((x + math.pi) / (2 * math.pi))


def phase_loss(model_phase, photo_phase, weight):
    """Cyclic phase loss E = Σ w·wrap(J_φ − I_φ)² / Σ w."""
    d = wrap(photo_phase - model_phase)
    return (weight * d * d).sum() / weight.sum()


def _save_png(path, rgb_linear):
    ta_io.write_png(path, np.clip(np.asarray(rgb_linear, np.float32), 0, 1))


def _save_gray(path, x, lo=None, hi=None, cmap="gray"):
    import matplotlib
    matplotlib.use("Agg")
    x = np.asarray(x, np.float64)
    lo = np.nanmin(x) if lo is None else lo
    hi = np.nanmax(x) if hi is None else hi
    rgb = matplotlib.colormaps[cmap](np.clip((x - lo) / max(hi - lo, 1e-12), 0, 1))[..., :3]
    ta_io.write_png(path, srgb_to_linear(torch.from_numpy(rgb.astype(np.float32))).numpy())




def _overlay(folder, rgb, rings, estimate):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(6, 6 * rgb.shape[0] / rgb.shape[1]))
    ax.imshow(np.clip(rgb, 0, 1) ** (1 / 2.2))
    for k, ring in enumerate(rings):
        ax.plot(ring[:, 0], ring[:, 1], lw=0.8, color=plt.cm.tab10(k % 10))
    if estimate is not None:
        cx, cy = estimate.centre_point_px
        psi = estimate.axis_angle
        L = max(rgb.shape)
        ax.plot([cx - L * math.cos(psi), cx + L * math.cos(psi)], [cy - L * math.sin(psi), cy + L * math.sin(psi)],
                "w--", lw=1, label="projected tree axis")
        ax.legend(loc="lower right", fontsize=7)
    ax.set(xlim=(0, rgb.shape[1]), ylim=(rgb.shape[0], 0), title=f"{len(rings)} traced rings")
    ax.axis("off")
    fig.tight_layout()
    ta_io.save_figure(fig, os.path.join(folder, "ring_overlay.png"), dpi=110)


def _cube_preview(model, shape, pixel_size, path, resolution=96):
    """Offscreen pyvista render of the fitted texture carved onto a cube (edge = the board's shorter side)."""
    import pyvista as pv

    h, w = shape
    edge = min(h, w) * pixel_size
    faces = []
    n = resolution
    a = np.linspace(0, edge, n)
    uu, vv = np.meshgrid(a, a)
    # board-space cube [0, edge]² × [−edge, 0] (w < 0 goes into the board): top, front and side faces
    for pts in (np.stack([uu, vv, np.zeros_like(uu)], -1),
                np.stack([uu, np.full_like(uu, edge), -vv], -1),
                np.stack([np.full_like(uu, edge), uu, -vv], -1)):
        with torch.no_grad():
            out = model.evaluate(torch.as_tensor(pts.reshape(-1, 3), dtype=model.rotation.dtype), board=True)
        rgb = out["rgb"].clamp(0, 1).numpy() ** (1 / 2.2)
        grid = pv.StructuredGrid(pts[..., 0], pts[..., 1], pts[..., 2])
        grid.point_data["rgb"] = (rgb * 255).astype(np.uint8)
        faces.append(grid)
    pv.OFF_SCREEN = True
    plotter = pv.Plotter(off_screen=True, window_size=(480, 480))
    for f in faces:
        plotter.add_mesh(f, scalars="rgb", rgb=True, lighting=False)
    plotter.camera_position = [(2.2 * edge, 1.6 * edge, 1.8 * edge), (edge / 2, edge / 2, -edge / 2), (0, 0, 1)]
    image = plotter.screenshot(return_img=True)
    plotter.close()
    ta_io.write_png(path, srgb_to_linear(torch.from_numpy(image[..., :3].astype(np.float32) / 255)).numpy())




def fit_wood(cfg: WoodFitConfig, progress=True, log=print):
    """Fit a WoodModel to one board photo and write the run folder ``cfg.out``.

    Run folder (fixed names): ``fit.png`` (rendered fit at the photo's size), ``phase.npy`` (the photo's Gabor phase,
    sign-resolved, rad), ``fit_phase.npy`` (the fitted model's phase), ``params.json`` (fitted parameters),
    ``log.csv`` (stage, epoch, wall_s, phase_loss, color_loss, phase_rms), ``convergence.png``; also
    ``orientation.png``, ``magnitude.png``, ``phase.png``, ``ring_overlay.png``, ``board_estimate.json``,
    ``model.json`` + ``model.pt`` (WoodModel.save), ``fit_vs_photo.png``, ``phase_error.png``, ``cube_preview.png``,
    ``summary.json``; with ``cfg.photometric`` also ``fit_before_photometric.png`` and
    ``model_before_photometric.json`` + ``.pt`` (the fit after stages 1-2), and ``summary["photometric"]``.

    Returns:
        the summary dict.
    """
    from ..metrics import ssim_2d
    from ..rings.board import choose_pith_side, estimate_board, initial_wood_model
    from ..rings.gabor import curved_gabor
    from ..rings.tracing import trace_rings

    cfg.validate()
    torch.manual_seed(cfg.seed)
    rgb, gray = load_photo(cfg.photo, cfg.max_size)
    os.makedirs(cfg.out, exist_ok=True)  # only once the photo has been read: a refused photo leaves no run folder
    h, w = gray.shape
    timings = {}

    t0 = time.perf_counter()
    gab = curved_gabor(gray, p=cfg.p, q=cfg.q, device=cfg.device)
    timings["gabor_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    rings = trace_rings(gab.phase, gab.orientation, gab.magnitude)
    timings["tracing_s"] = time.perf_counter() - t0
    if len(rings) < 2:
        raise ValueError(f"photo: found {len(rings)} growth ring(s) in {cfg.photo!r}; need at least 2 to locate the "
                         f"board (is pixel_size_mm right, and are rings visible?)")
    t0 = time.perf_counter()
    try:
        estimate = estimate_board(rings, (h, w), cfg.pixel_size_mm)
    except ValueError as exc:
        _overlay(cfg.out, rgb, rings, None)
        raise ValueError(
            f"photo: the {len(rings)} ring lines traced in {cfg.photo!r} fit no tree axis behind a planar board "
            f"({exc}). The fit needs a tangential or radial face, whose rings are nested arches or parallel bands "
            f"around one projected axis; end grain (rings closed around the pith), a knot or several stems in view "
            f"break that. Crop the photo to a knot-free region of one face (ring_overlay.png in {cfg.out!r} shows "
            f"the traced rings)") from None
    # growth direction: the projected centre where one lateness profile explains both sides (mirror-free)
    estimate, pith_info = choose_pith_side(estimate, gab.phase, gray, magnitude=gab.magnitude, rings=rings)
    model, info = initial_wood_model(estimate, gab.phase, magnitude=gab.magnitude, rings=rings,
                                     distortion=cfg.distortion, distortion_shape=tuple(cfg.distortion_shape),
                                     dtype=torch.float32, return_info=True, color_bins=cfg.color_bins)
    timings["board_estimate_s"] = time.perf_counter() - t0
    photo_phase = info["resolved_phase"].astype(np.float32)

    folder = cfg.out
    np.save(os.path.join(folder, "phase.npy"), photo_phase)
    _save_gray(os.path.join(folder, "orientation.png"), gab.orientation, 0, math.pi, cmap="twilight")
    _save_gray(os.path.join(folder, "magnitude.png"), gab.magnitude)
    _save_gray(os.path.join(folder, "phase.png"), photo_phase, 0, 2 * math.pi, cmap="twilight")
    _overlay(folder, rgb, rings, estimate)
    ta_io.write_json(os.path.join(folder, "board_estimate.json"), estimate.to_dict())

    device = torch.device(cfg.device)
    model = model.to(device)
    target_phase = torch.as_tensor(photo_phase, device=device)
    mag = torch.as_tensor(gab.magnitude, device=device)
    weight = (mag / mag.mean().clamp_min(1e-12)).clamp(max=3.0)  # confidence: Gabor amplitude
    target_rgb = torch.as_tensor(rgb, device=device)

    # ---- stage 1: geometry from the cyclic phase loss
    geometry = [p for n, p in model.named_parameters() if n != "color_map"]
    groups = _phase_normalised_groups(model, h, w, cfg)
    pyramid = _DistortionPyramid(model, cfg.coarse_to_fine) if model.m_r is not None else None
    if pyramid is not None:  # the texture is m_r(init) + Σ upsampled levels, coarse levels switched on first
        m_lr = next(g["lr"] for g in groups if g["name"] == "m_r")
        groups = [g for g in groups if g["name"] != "m_r"] + [
            {"params": [lev], "lr": m_lr, "name": f"m_r_level{i}"} for i, lev in enumerate(pyramid.levels)]
    optimizer = torch.optim.Adam(groups, lr=cfg.lr)
    rows = []
    start = time.perf_counter()
    try:
        from tqdm import tqdm
        bar = tqdm(total=cfg.epochs + cfg.color_epochs + (cfg.photometric_epochs if cfg.photometric else 0),
                   disable=not progress, desc="fit_wood", unit="ep")
    except ImportError:  # pragma: no cover
        bar = None
    for epoch in range(cfg.epochs + 1):
        if pyramid is not None:
            m_r = pyramid.texture()
            out = torch.func.functional_call(model, {"m_r": m_r}, (h, w, cfg.pixel_size_mm))
        else:
            m_r, out = None, model.render_board(h, w, cfg.pixel_size_mm)
        loss = phase_loss(out["phase"], target_phase, weight)
        if cfg.smoothness > 0 and model.m_r is not None:
            loss = loss + cfg.smoothness * distortion_prior(model, m_r)
        rms = float(torch.sqrt((wrap(target_phase - out["phase"].detach()) ** 2).mean()))
        rows.append({"stage": 1, "epoch": epoch, "wall_s": time.perf_counter() - start,
                     "phase_loss": loss.item(), "phase_rms": rms})
        if epoch == cfg.epochs:
            break
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        if pyramid is not None:
            pyramid.freeze_inactive(epoch, cfg.epochs)
        optimizer.step()
        if bar is not None:
            bar.update(1)
            bar.set_postfix(phase_loss=f"{loss.item():.4f}")
    if pyramid is not None:
        with torch.no_grad():
            model.m_r.copy_(pyramid.texture())
    timings["stage1_s"] = time.perf_counter() - start

    # ---- stage 2: colour map with the geometry frozen (linear RGB MSE)
    for p in geometry:
        p.requires_grad_(False)
    with torch.no_grad():  # start from the photo's mean colour per (ring, lateness bin)
        out = model.render_board(h, w, cfg.pixel_size_mm)
        _init_color_map(model, out, target_rgb)
    optimizer = torch.optim.Adam([model.color_map], lr=cfg.color_lr)
    t1 = time.perf_counter()
    for epoch in range(cfg.color_epochs + 1):
        out = model.render_board(h, w, cfg.pixel_size_mm)
        loss = ((out["image"] - target_rgb) ** 2).mean()
        rows.append({"stage": 2, "epoch": epoch, "wall_s": time.perf_counter() - start, "color_loss": loss.item()})
        if epoch == cfg.color_epochs:
            break
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        with torch.no_grad():
            model.color_map.clamp_(0, 1)
        if bar is not None:
            bar.update(1)
            bar.set_postfix(color_loss=f"{loss.item():.5f}")
    contrast = None
    if cfg.contrast_match:  # fit metrics before and after the remap go into the summary
        before = fit_metrics(model, h, w, cfg.pixel_size_mm, rgb, photo_phase)
        with torch.no_grad():
            match_luminance_histogram(model, torch.as_tensor(before.pop("fit_rgb")), target_rgb)
        after = fit_metrics(model, h, w, cfg.pixel_size_mm, rgb, photo_phase)
        after.pop("fit_rgb")
        contrast = {"before": before, "after": after}
    timings["stage2_s"] = time.perf_counter() - t1

    # ---- stage 3 (optional): photometric refinement through the reparameterised render
    photometric = None
    if cfg.photometric:
        before = fit_metrics(model, h, w, cfg.pixel_size_mm, rgb, photo_phase)
        _save_png(os.path.join(folder, "fit_before_photometric.png"), before.pop("fit_rgb"))
        copy.deepcopy(model).cpu().save(os.path.join(folder, "model_before_photometric"))
        t2 = time.perf_counter()
        photometric_stage(model, target_rgb, target_phase, h, w, cfg, rows, start, bar, phase_weight=weight)
        timings["stage3_s"] = time.perf_counter() - t2
        after = fit_metrics(model, h, w, cfg.pixel_size_mm, rgb, photo_phase)
        after.pop("fit_rgb")
        photometric = {"before": before, "after": after, "seconds": timings["stage3_s"],
                       "epochs": cfg.photometric_epochs, "levels": list(cfg.photometric_levels),
                       "spp": cfg.photometric_spp}
    if bar is not None:
        bar.close()
    ta_io.write_csv(os.path.join(folder, "log.csv"), rows, LOG_FIELDS)

    # ---- outputs
    with torch.no_grad():
        out = model.render_board(h, w, cfg.pixel_size_mm)
    fit_rgb = out["image"].clamp(0, 1).cpu().numpy()
    g_fit = out["G"].cpu()
    visible_rings = int(math.floor(float(g_fit.max())) - math.ceil(float(g_fit.min())) + 1)
    fit_phase = out["phase"].cpu().numpy().astype(np.float32)
    err = np.angle(np.exp(1j * (photo_phase - fit_phase)))
    final_rms = float(np.sqrt((err.astype(np.float64) ** 2).mean()))
    _save_png(os.path.join(folder, "fit.png"), fit_rgb)
    np.save(os.path.join(folder, "fit_phase.npy"), fit_phase)
    model.cpu().save(os.path.join(folder, "model"))
    ring_width, boundary = effective_ring_width(model, h, w, cfg.pixel_size_mm), boundary_lateness(model)
    params = {"rotation_axis_angle_rad": model.rotation.tolist(), "translation_mm": model.translation.tolist(),
              "ring_scale_mm": float(model.ring_scale),
              "mean_ring_width_mm": ring_width, "boundary_lateness": boundary, "distortion": cfg.distortion,
              "distortion_rms_mm": float(model.m_r.pow(2).mean().sqrt()) if model.m_r is not None else 0.0,
              "pixel_size_mm": cfg.pixel_size_mm, "image_hw": [h, w]}
    ta_io.write_json(os.path.join(folder, "params.json"), params)
    ssim = float(ssim_2d(fit_rgb, rgb))
    _figures(folder, rows, rgb, fit_rgb, err)
    if cfg.preview:
        try:
            _cube_preview(model, (h, w), cfg.pixel_size_mm, os.path.join(folder, "cube_preview.png"))
        except Exception as exc:  # rendering backends vary; the fit itself is complete
            log(f"fit_wood: cube preview skipped ({type(exc).__name__}: {exc})")
    summary = {
        "photo": os.path.abspath(cfg.photo), "image_hw": [h, w], "rings_traced": len(rings),
        "ring_scale_mm": float(model.ring_scale),
        "mean_ring_width_mm": ring_width, "boundary_lateness": boundary, "initial_phase_rms": rows[0]["phase_rms"],
        "stage1_phase_rms": rows[cfg.epochs]["phase_rms"], "final_phase_rms": final_rms,
        "mean_abs_wrapped_phase_error": float(np.abs(err).mean()),
        "fraction_initial_error_below_half_pi": info.get("fraction_below_half_pi"),
        "ssim_fit_vs_photo": ssim, "timings_s": timings, "epochs": cfg.epochs, "color_epochs": cfg.color_epochs,
        # a wrapped-phase RMS near π/√3 ≈ 1.8 rad is chance level; above ~0.8 rad the rings are not followed
        "fit_ok": bool(final_rms < POOR_FIT_PHASE_RMS),
        # stage 3: phase RMS, SSIM and latewood contrast before and after (None without --photometric)
        "photometric": photometric,
        # --contrast-match: phase RMS, SSIM and latewood contrast before and after the luminance remap (else None)
        "contrast_match": contrast,
        "latewood_contrast": latewood_contrast(fit_rgb, rgb),
        # ring boundaries (integer G) crossing the board; below MIN_RINGS_FOR_SCALE the scale is a rough guess
        "visible_rings": visible_rings,
        "ring_scale_reliable": bool(visible_rings >= MIN_RINGS_FOR_SCALE),
        # growth-direction check (choose_pith_side): R² of one lateness profile, and whether the centre moved
        "pith_side": {k: pith_info[k] for k in ("score_initial", "score_chosen", "moved")},
    }
    ta_io.write_json(os.path.join(folder, "summary.json"), summary)
    if not summary["fit_ok"]:
        log(f"fit_wood: warning: the fitted rings do not follow the photo (phase RMS {summary['final_phase_rms']:.2f} "
            f"rad > {POOR_FIT_PHASE_RMS}); is this a tangential board face (rings as arches or bands), not an end "
            f"grain or radial face?")
    if not summary["ring_scale_reliable"]:
        log(f"fit_wood: warning: only {visible_rings} ring boundaries cross the board; the ring scale "
            f"({summary['ring_scale_mm']:.3f} mm) is poorly determined below {MIN_RINGS_FOR_SCALE} (the number of "
            f"rings between the pith and the board trades against the axis distance); the ring pattern on the "
            f"board itself is still fitted")
    log(f"fit_wood: {len(rings)} rings, s_r {summary['ring_scale_mm']:.3f} mm, phase RMS "
        f"{summary['initial_phase_rms']:.3f} -> {summary['final_phase_rms']:.3f} rad, SSIM {ssim:.3f}; Gabor "
        f"{timings['gabor_s']:.1f} s, fit {timings['stage1_s'] + timings['stage2_s'] + timings.get('stage3_s', 0):.1f}"
        f" s -> {folder}")
    return summary


def effective_ring_width(model, h, w, pixel_size_mm):
    """Mean ring width over the board (mm): 1 / mean ∂G/∂r = s_r / mean(1 + ∂m_r/∂r).

    The ring scale s_r alone is not identifiable: a radial distortion growing linearly with r rescales the rings
    exactly like s_r does. The mean width of the rings the board actually shows is, and it is what is reported.
    """
    with torch.no_grad():
        u = (torch.arange(w, dtype=model.rotation.dtype) + 0.5) * pixel_size_mm
        v = (torch.arange(h, dtype=model.rotation.dtype) + 0.5) * pixel_size_mm
        uu, vv = torch.meshgrid(u, v, indexing="xy")
        q = model.board_to_tree(torch.stack([uu.reshape(-1), vv.reshape(-1)], 1))
        r = q[:, :2].norm(dim=1, keepdim=True).clamp_min(1e-9)
        eps = 1e-3 * float(model.ring_scale)
        q2 = q.clone()
        q2[:, :2] = q[:, :2] * (1 + eps / r)
        dgdr = (model.evaluate(q2)["G"] - model.evaluate(q)["G"]) / eps
        return float(1.0 / dgdr.mean())


def boundary_lateness(model):
    """Lateness at which the fitted colour profile changes fastest (the latewood → earlywood transition).

    The Gabor phase, and so the fitted G, is aligned with the intensity's fundamental, not with the sharp
    boundary; the stage-2 colour map (mean over rings) puts the boundary where its luminance jumps most.

    Returns:
        lateness ℓ* in [0, 1): ring boundaries are where G = k + ℓ*.
    """
    with torch.no_grad():
        lum = model.color_map.mean(0) @ torch.tensor([0.2126, 0.7152, 0.0722], dtype=model.color_map.dtype)
        jump = (torch.roll(lum, -1) - lum).abs()  # jump between bin i and i+1 (cyclic: last → first)
        k = lum.numel()
        i = int(jump.argmax())
        return float(((i + 0.5) / (k - 1)) % 1.0) if i < k - 1 else 0.0


def model_boundaries(G, offset):
    """Ring-boundary polylines of a fitted model: contours of G = k + offset, (x, y) pixel arrays."""
    import contourpy

    g = np.asarray(G, np.float64) - offset
    gen = contourpy.contour_generator(z=g)
    lines = []
    for k in range(int(np.floor(g.min())) + 1, int(np.ceil(g.max()))):
        for line in gen.lines(float(k)):
            if len(line) >= 2:
                lines.append(np.asarray(line, np.float64))  # contourpy gives (x, y) = (column, row)
    return lines


class _DistortionPyramid:
    """Coarse-to-fine parametrisation of the distortion texture for stage 1: m_r = m_r(initial) + Σ_l U(P_l), with
    levels P_l of (Hd, Wd)/2^(n−1−l) texels (at least 2) bilinearly upsampled (align_corners, as the texture is
    sampled) to the full grid. Level l is trained from epoch l·E/n on: the coarse levels first move whole ring
    groups, so the cyclic loss cannot pull single texel cells into the neighbouring ring (a 2π slip, seen as blocky
    rectangles along the texel grid) before the large-scale distortion is in place."""

    def __init__(self, model, n_levels):
        hd, wd = model.distortion_shape
        self.base = model.m_r.detach().clone()
        self.shape = (hd, wd)
        shapes = []
        for lev in range(max(int(n_levels), 1)):
            f = 2 ** (max(int(n_levels), 1) - 1 - lev)
            shapes.append((max(2, hd // f), max(2, wd // f)))
        self.levels = [torch.zeros((1, 1) + s, dtype=self.base.dtype, device=self.base.device, requires_grad=True)
                       for s in shapes]

    def texture(self):
        import torch.nn.functional as F
        m = self.base
        for lev in self.levels:
            m = m + (lev if tuple(lev.shape[-2:]) == self.shape else
                     F.interpolate(lev, size=self.shape, mode="bilinear", align_corners=True))
        return m

    def freeze_inactive(self, epoch, epochs):
        n = len(self.levels)
        for i, lev in enumerate(self.levels):
            if epoch < i * epochs / n and lev.grad is not None:
                lev.grad.zero_()


def distortion_prior(model, m_r=None):
    """Smoothness prior of the radial distortion texture: mean squared change between neighbouring texels, in
    ring widths² (dimensionless). It keeps m_r from imitating a different ring scale or axis distance (a
    distortion growing with r is indistinguishable from a ring-scale change) and from fitting noise.
    ``m_r`` (``(1, 1, Hd, Wd)`` mm) replaces the model's own texture when given."""
    m = (model.m_r if m_r is None else m_r) / model.ring_scale
    return (m[..., 1:, :] - m[..., :-1, :]).pow(2).mean() + (m[..., :, 1:] - m[..., :, :-1]).pow(2).mean()


def _phase_normalised_groups(model, h, w, cfg):
    """Adam parameter groups whose learning rates make ``cfg.lr`` mean "ring widths per step" for every parameter.

    Adam moves each parameter by about its learning rate per step, whatever the gradient's scale, so one rate for
    all would move a rotation by 0.03 rad (≈ 0.5 mm at 15 mm from the axis: a third of a ring) and the ring scale
    by 3 % (a third of a ring at the 12th ring) in the first step. Each group's rate is therefore the change that
    shifts the rings by ``cfg.lr`` ring widths: translation and distortion (mm) by lr·s_r, rotation (rad) by
    lr·s_r / r̄, log ring scale by lr / Ḡ, where r̄ and Ḡ are the mean radius and growth value over the board.
    """
    with torch.no_grad():
        g_mean = float(model.render_board(h, w, cfg.pixel_size_mm)["G"].abs().mean().clamp_min(1.0))
    s_r = float(model.ring_scale.detach())
    r_mean = g_mean * s_r
    scale = {"translation": s_r, "rotation": s_r / r_mean, "log_ring_scale": 1.0 / g_mean, "m_r": s_r, "m_t": s_r}
    groups = []
    for name, param in model.named_parameters():
        if name == "color_map":
            continue
        groups.append({"params": [param], "lr": cfg.lr * scale.get(name, 1.0), "name": name})
    return groups


def _init_color_map(model, out, target_rgb):
    """Colour map = mean photo colour per (ring index mod n, lateness bin), falling back to the per-bin mean."""
    n, k, _ = model.color_map.shape
    ring = torch.remainder(out["ring_index"].long(), n).reshape(-1)
    lb = torch.clamp((out["lateness"] * (k - 1)).round().long(), 0, k - 1).reshape(-1)
    cell = ring * k + lb
    col = target_rgb.reshape(-1, 3)
    sums = torch.zeros(n * k, 3, dtype=col.dtype, device=col.device).index_add_(0, cell, col)
    cnt = torch.zeros(n * k, dtype=col.dtype, device=col.device).index_add_(0, cell, torch.ones_like(cell, dtype=col.dtype))
    bin_sums = torch.zeros(k, 3, dtype=col.dtype, device=col.device).index_add_(0, lb, col)
    bin_cnt = torch.zeros(k, dtype=col.dtype, device=col.device).index_add_(0, lb, torch.ones_like(lb, dtype=col.dtype))
    bin_mean = torch.where(bin_cnt[:, None] > 0, bin_sums / bin_cnt.clamp_min(1)[:, None], col.mean(0))
    fallback = bin_mean.repeat(n, 1)
    mean = torch.where(cnt[:, None] > 0, sums / cnt.clamp_min(1)[:, None], fallback)
    model.color_map.copy_(mean.reshape(n, k, 3).to(model.color_map.dtype))


_LUMA = (0.2126, 0.7152, 0.0722)  # linear Rec. 709 luminance weights


def match_luminance_histogram(model, fit_rgb, target_rgb):
    """Rescale every colour-map entry (keeping its chromaticity) by T(Y)/Y, with T the monotone map that sends the
    fit's pixel luminance distribution to the photo's (quantile matching: T = F_photo⁻¹ ∘ F_fit).

    Stage 2 takes per-bin means of photo colours; wherever the fitted phase is off by part of a ring, a thin dark
    latewood line is averaged with earlywood, and the fit comes out with less early/late contrast than the photo.
    The rendered pixels take their luminance from the colour map, so remapping the entries restores the photo's
    luminance spread; the geometry is unchanged. Entries are clamped to [0, 1] afterwards.

    Args:
        model: a :class:`~torch_appearance.nn.WoodModel` (its ``color_map`` (n, K, 3) is changed in place).
        fit_rgb: (H, W, 3) linear RGB render of the model at the photo's pixels.
        target_rgb: (H, W, 3) linear RGB photo.

    Returns:
        (2, M) array: the quantile map's knots (fit luminance, photo luminance).
    """
    y = torch.tensor(_LUMA, dtype=torch.float64)
    y_fit = (fit_rgb.detach().double().reshape(-1, 3) @ y).cpu().numpy()
    y_photo = (target_rgb.detach().double().reshape(-1, 3) @ y).cpu().numpy()
    qs = np.linspace(0.0, 1.0, 257)
    knots_fit, knots_photo = np.quantile(y_fit, qs), np.quantile(y_photo, qs)
    knots_fit = np.maximum.accumulate(knots_fit)
    cmap = model.color_map.detach().double()
    y_map = (cmap @ y.to(cmap.device)).cpu().numpy()
    mapped = np.interp(y_map, knots_fit, knots_photo)
    scale = np.where(y_map > 1e-6, mapped / np.maximum(y_map, 1e-6), 1.0)
    new = (cmap * torch.as_tensor(scale, dtype=cmap.dtype, device=cmap.device)[..., None]).clamp(0, 1)
    model.color_map.copy_(new.to(model.color_map.dtype))
    return np.stack([knots_fit, knots_photo])


def _figures(folder, rows, rgb, fit_rgb, err):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    s1 = [r for r in rows if r["stage"] == 1]
    s2 = [r for r in rows if r["stage"] == 2]
    s3 = [r for r in rows if r["stage"] == 3]
    fig, ax = plt.subplots(1, 3 if s3 else 2, figsize=(15 if s3 else 10, 3.6))
    ax[0].plot([r["wall_s"] for r in s1], [r["phase_loss"] for r in s1])
    ax[0].set(xlabel="wall-clock time [s]", ylabel="cyclic phase loss [rad²]", yscale="log", title="stage 1: geometry")
    ax[1].plot([r["wall_s"] for r in s2], [r["color_loss"] for r in s2], color="C1")
    ax[1].set(xlabel="wall-clock time [s]", ylabel="colour MSE (linear RGB)", yscale="log", title="stage 2: colour map")
    if s3:
        ax[2].plot([r["wall_s"] for r in s3], [r["photometric_loss"] for r in s3], color="C2")
        ax[2].set(xlabel="wall-clock time [s]", ylabel="weighted ΔE²/100 + phase anchor + prior", yscale="log",
                  title="stage 3: photometric (reparameterised)")
    fig.tight_layout()
    ta_io.save_figure(fig, os.path.join(folder, "convergence.png"), dpi=110)

    fig, ax = plt.subplots(1, 3, figsize=(12, 4))
    ax[0].imshow(np.clip(rgb, 0, 1) ** (1 / 2.2))
    ax[0].set_title("photo")
    ax[1].imshow(np.clip(fit_rgb, 0, 1) ** (1 / 2.2))
    ax[1].set_title("fitted procedural wood")
    im = ax[2].imshow(np.abs(err), cmap="magma", vmin=0, vmax=math.pi)
    ax[2].set_title(f"|wrapped phase error|, mean {np.abs(err).mean():.2f} rad")
    fig.colorbar(im, ax=ax[2], fraction=0.046)
    for a in ax:
        a.axis("off")
    fig.tight_layout()
    ta_io.save_figure(fig, os.path.join(folder, "fit_vs_photo.png"), dpi=110)
    _save_gray(os.path.join(folder, "phase_error.png"), np.abs(err), 0, math.pi, cmap="magma")


def latewood_contrast(fit_rgb, photo_rgb):
    """Latewood contrast of a fitted texture against the photo: the 5–95 % spread of luminance (linear Y, Rec. 709
    weights) of each, and their ratio fit/photo (1: the fit keeps the photo's early/late contrast; < 1: washed out).

    Args:
        fit_rgb, photo_rgb: (H, W, 3) linear RGB arrays.

    Returns:
        dict ``fit_spread``, ``photo_spread``, ``ratio``.
    """
    y = np.array(_LUMA)
    spread = [float(np.subtract(*np.percentile(np.asarray(x, np.float64) @ y, [95, 5]))) for x in (fit_rgb, photo_rgb)]
    return {"fit_spread": spread[0], "photo_spread": spread[1], "ratio": spread[0] / max(spread[1], 1e-12)}


def fit_metrics(model, h, w, pixel_size_mm, photo_rgb, photo_phase):
    """Phase RMS against the photo's (sign-resolved) Gabor phase (rad, unweighted), SSIM of the fit vs the photo, the
    colour RMSE (linear RGB) and the latewood contrast (:func:`latewood_contrast`) of the model rendered at the photo's
    size; also ``fit_rgb`` (H, W, 3) linear RGB."""
    from ..metrics import ssim_2d

    with torch.no_grad():
        out = model.render_board(h, w, pixel_size_mm)
    fit_rgb = out["image"].clamp(0, 1).cpu().numpy()
    err = np.angle(np.exp(1j * (np.asarray(photo_phase, np.float64) - out["phase"].cpu().numpy())))
    rmse = float(np.sqrt(((fit_rgb.astype(np.float64) - np.asarray(photo_rgb, np.float64)) ** 2).mean()))
    return {"phase_rms": float(np.sqrt((err ** 2).mean())), "ssim": float(ssim_2d(fit_rgb, photo_rgb)),
            "colour_rmse": rmse, "latewood_contrast": latewood_contrast(fit_rgb, photo_rgb), "fit_rgb": fit_rgb}


def photometric_stage(model, target_rgb, target_phase, h, w, cfg, rows=None, start=None, bar=None, phase_weight=None):
    """Stage 3: refine the geometry (rotation, translation, ring scale, distortion) and the colour map jointly
    against the photo's colours, through :func:`torch_appearance.nn.wood_reparam.reparam_render` so that the moving
    ring boundaries get their (reparameterised, unbiased) gradient.

    Loss: mean squared CIELAB difference (kornia, D65; the linear render is sRGB-encoded first) / 100 between a
    Gaussian-filtered render (σ = ½ pixel, ``cfg.photometric_spp`` fresh samples per pixel and step) and the photo
    area-averaged to the level's resolution, times ``cfg.photometric_weight``, plus ``cfg.smoothness`` × the
    distortion prior and ``cfg.photometric_anchor`` × the stage-1 cyclic phase loss against ``target_phase``
    (weights ``phase_weight``, (H, W), default 1), which keeps the rings on the photo's Gabor phase where the colours
    alone are ambiguous. Coarse to fine over
    ``cfg.photometric_levels`` (downsampling factors), ``cfg.photometric_epochs`` Adam steps in all; the geometry's
    learning rates are in ring widths per step (``cfg.photometric_lr``, see ``_phase_normalised_groups``), the colour
    map's ``cfg.photometric_color_lr`` (clamped to [0, 1]). Pixel (y, x) of the photo is the board point
    (x·p, y·p) as in :meth:`WoodModel.render_board`; a level-f pixel averages f×f photo pixels and is centred on
    the mean of their positions. Levels coarser than 4×4 pixels are skipped (with their share of the steps).

    Args:
        model: the fitted WoodModel (modified in place).
        target_rgb: (H, W, 3) photo, linear RGB tensor. target_phase: (H, W) its Gabor phase (rad).
        h, w: photo size; cfg: :class:`WoodFitConfig`; rows: log rows to append to (stage 3); start: the fit's
            start time (perf_counter); bar: tqdm bar or None.

    Returns:
        the list of stage-3 log rows.
    """
    import kornia
    import torch.nn.functional as F

    from ..color import linear_to_srgb
    from ..nn.wood_reparam import pixel_samples, reparam_render

    rows = [] if rows is None else rows
    start = time.perf_counter() if start is None else start
    if phase_weight is None:
        phase_weight = torch.ones_like(target_phase)
    for p in model.parameters():
        p.requires_grad_(True)
    step_cfg = dataclasses.replace(cfg, lr=cfg.photometric_lr)
    groups = _phase_normalised_groups(model, h, w, step_cfg)
    if cfg.photometric_color_lr > 0:
        groups.append({"params": [model.color_map], "lr": cfg.photometric_color_lr, "name": "color_map"})
    optimizer = torch.optim.Adam(groups)
    p_mm = cfg.pixel_size_mm
    levels = list(cfg.photometric_levels)
    counts = [cfg.photometric_epochs // len(levels) + (i < cfg.photometric_epochs % len(levels))
              for i in range(len(levels))]
    photo = target_rgb.permute(2, 0, 1)[None].to(model.dtype)
    step = 0
    own = []
    for f, n_steps in zip(levels, counts):
        hc, wc = h // f, w // f
        if hc < 4 or wc < 4:
            continue
        target = F.avg_pool2d(photo[..., :hc * f, :wc * f], f) if f > 1 else photo
        target_lab = kornia.color.rgb_to_lab(linear_to_srgb(target.clamp(0, 1)))
        px = p_mm * f
        for _ in range(n_steps):
            pts, centres = pixel_samples(hc, wc, px, cfg.photometric_spp, cfg.seed * 100003 + step, 0.5,
                                         dtype=model.dtype)
            shift = torch.full((2,), -0.5 * p_mm, dtype=model.dtype)  # coarse centre = mean of the photo pixels
            image = reparam_render(model, hc, wc, px, spp=cfg.photometric_spp, samples=(pts + shift, centres + shift),
                                   estimator=cfg.photometric_estimator)
            lab = kornia.color.rgb_to_lab(linear_to_srgb(image.clamp(1e-6, 1)).permute(2, 0, 1)[None])
            loss = cfg.photometric_weight * ((lab - target_lab) ** 2).mean() / 100.0
            if cfg.photometric_anchor > 0:
                loss = loss + cfg.photometric_anchor * phase_loss(model.render_board(h, w, p_mm)["phase"],
                                                                  target_phase, phase_weight)
            if cfg.smoothness > 0 and model.m_r is not None:
                loss = loss + cfg.smoothness * distortion_prior(model)
            row = {"stage": 3, "epoch": step, "wall_s": time.perf_counter() - start, "photometric_loss": loss.item()}
            rows.append(row)
            own.append(row)
            optimizer.zero_grad(set_to_none=True)
            if torch.isfinite(loss):
                loss.backward()
                optimizer.step()
            with torch.no_grad():
                model.color_map.clamp_(0, 1)
            step += 1
            if bar is not None:
                bar.update(1)
                bar.set_postfix(photometric_loss=f"{loss.item():.4f}", level=f)
    with torch.no_grad():
        out = model.render_board(h, w, p_mm)
        rms = float(torch.sqrt((wrap(target_phase - out["phase"]) ** 2).mean()))
    if own:
        own[-1]["phase_rms"] = rms
    return own
