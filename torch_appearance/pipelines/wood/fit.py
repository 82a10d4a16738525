"""Wood appearance matching (thesis ch. 2): fit a procedural solid-wood texture to one photograph of a board.

photo → curved Gabor filter (orientation, magnitude, phase J_φ) → ring tracing at J_φ = π/2 → board location
(projected tree centre, ring scale, transform) → growth direction: the centre line placed where one lateness
profile explains both sides (``choose_pith_side``), the two sides of that line filtered apart where the rings run
along it (``split_at_pith_line``; ``pith_split``), phase sign resolved → initial ``WoodModel`` (radial distortion
from the traced rings and the unwrapped phase residual) → stage 1 (:mod:`.geometry_stage`): cyclic phase loss
E = wrap(J_φ − I_φ)² with Adam (lr 0.03, 500 epochs) over the board transform, ring scale and distortion, the
distortion coarse to fine (3 levels, so no texel cell slips by a ring) → stage 2 (:mod:`.colour_stage`): colour map
(32 lateness bins) with the geometry frozen → optional stage 3 (:mod:`.photometric_stage`) → run folder
(:mod:`.report`, :mod:`.measures`). :mod:`torch_appearance.cli.fit_wood` is the command line (``ta-fit-wood``).
"""
import copy
import math
import os
import time

import numpy as np
import torch

from ... import io as ta_io
from ...rings.gabor import curved_gabor_memory_bytes, curved_gabor_seconds
from ..runs import check_memory
from .colour_stage import fit_colour_map, match_luminance_histogram
from .config import LOG_FIELDS, MIN_RINGS_FOR_SCALE, POOR_FIT_PHASE_RMS, WoodFitConfig
from .geometry_stage import fit_geometry
from .measures import boundary_lateness, effective_ring_width, fit_metrics, latewood_contrast
from .photo import load_photo
from .photometric_stage import photometric_stage
from .report import cube_preview, figures, ring_overlay, save_gray, save_png

__all__ = ["fit_wood", "detect_board", "check_against_photo", "PHOTOMETRIC_BYTES_PER_SAMPLE", "SAY_GABOR_S"]

#: bytes per filter sample of one stage-3 step (the samples, their warp, colours and autograd graph): 2.8 kB measured
#: on a 48² px float32 board with 16 and 64 spp (peak RSS), with a margin
PHOTOMETRIC_BYTES_PER_SAMPLE = 4096
#: the curved Gabor filter's estimated time is logged before it starts when it is at least this long (seconds)
SAY_GABOR_S = 10.0


def detect_board(cfg, rgb, gray):
    """The rings of the photo and the board they place: curved Gabor filtering, ring tracing, the board estimate,
    the growth direction and the initial :class:`~torch_appearance.nn.WoodModel`.

    Returns:
        (gabor result, traced rings, board estimate, pith-side info, initial model, its info dict, timings dict).

    Raises:
        ValueError: fewer than 2 rings traced, or rings that fit no tree axis behind a planar board (then
        ``ring_overlay.png`` in ``cfg.out`` shows the traced rings).
    """
    from ...rings.board import choose_pith_side, estimate_board, initial_wood_model, split_at_pith_line
    from ...rings.gabor import curved_gabor
    from ...rings.tracing import trace_rings

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
        ring_overlay(cfg.out, rgb, rings, None)
        raise ValueError(
            f"photo: the {len(rings)} ring lines traced in {cfg.photo!r} fit no tree axis behind a planar board "
            f"({exc}). The fit needs a tangential or radial face, whose rings are nested arches or parallel bands "
            f"around one projected axis; end grain (rings closed around the pith), a knot or several stems in view "
            f"break that. Crop the photo to a knot-free region of one face (ring_overlay.png in {cfg.out!r} shows "
            f"the traced rings)") from None
    # growth direction: the projected centre where one lateness profile explains both sides (mirror-free)
    estimate, pith_info = choose_pith_side(estimate, gab.phase, gray, magnitude=gab.magnitude, rings=rings)
    if cfg.pith_split:  # the two sides of the pith line filtered apart (the target phase and its weights)
        gab, split_info = split_at_pith_line(gray, estimate, gab, p=cfg.p, q=cfg.q, device=cfg.device)
        pith_info.update(split_info)
    model, info = initial_wood_model(estimate, gab.phase, magnitude=gab.magnitude, rings=rings,
                                     distortion=cfg.distortion, distortion_shape=tuple(cfg.distortion_shape),
                                     dtype=torch.float32, return_info=True, color_bins=cfg.color_bins,
                                     lobe_shape=None if cfg.lobe_shape is None else tuple(cfg.lobe_shape),
                                     lobe_radius_rings=cfg.lobe_radius_rings)
    timings["board_estimate_s"] = time.perf_counter() - t0
    return gab, rings, estimate, pith_info, model, info, timings


def _duration(seconds):
    """``seconds`` in words: "40 s", "12 min", "3.5 h", "2.1 days"."""
    if seconds < 90:
        return f"{seconds:.0f} s"
    if seconds < 5400:
        return f"{seconds / 60:.0f} min"
    if seconds < 2 * 86400:
        return f"{seconds / 3600:.1f} h"
    return f"{seconds / 86400:.1f} days"


def check_against_photo(cfg, h, w):
    """Refuse (ValueError naming the field) the settings that a photo of ``h`` × ``w`` pixels makes pointless, before
    any work: curves (``p``, ``q``) longer than the photo's height + width (every step beyond leaves the photo: only
    work), more ``color_bins`` than that (no ring crosses more pixels, so further lateness samples hold none), a lobe
    texture with more texels than the photo has pixels, and stage-3 levels that would leave fewer than 4 pixels a
    side (stage 3 skipped them without a word)."""
    side = h + w
    for name in ("p", "q"):
        v = getattr(cfg, name)
        if v > side:
            seconds = curved_gabor_seconds((h, w), cfg.p, cfg.q, cfg.device)
            took = "" if seconds is None else f"; the filter would take about {_duration(seconds)}"
            raise ValueError(f"{name}: expected at most {side} (the {h} × {w} px photo's height + width: a curve of "
                             f"2{name}+1 = {2 * v + 1} px leaves the photo, so the steps beyond add only work{took}), "
                             f"got {v}")
    if cfg.color_bins > side:
        raise ValueError(f"color_bins: expected at most {side} (the {h} × {w} px photo's height + width: no ring "
                         f"crosses more pixels, so further lateness samples hold none), got {cfg.color_bins}")
    if cfg.lobe_shape is not None and cfg.lobe_shape[0] * cfg.lobe_shape[1] > h * w:
        raise ValueError(f"lobe_shape: expected at most {h * w} texels (the {h} × {w} px photo's pixels: the texels "
                         f"beyond are held by the prior alone), got {cfg.lobe_shape[0]} × {cfg.lobe_shape[1]} = "
                         f"{cfg.lobe_shape[0] * cfg.lobe_shape[1]}")
    if cfg.photometric:
        small = [f for f in cfg.photometric_levels if min(h // f, w // f) < 4]
        if small:
            largest = min(h, w) // 4
            raise ValueError(f"photometric_levels: expected downsampling factors of at most {largest} (the {h} × {w} "
                             f"px photo downsampled by more is under 4 px a side), got {' '.join(map(str, small))}")


def fit_wood(cfg: WoodFitConfig, progress=True, log=print):
    """Fit a WoodModel to one board photo and write the run folder ``cfg.out``.

    Run folder (fixed names): ``fit.png`` (rendered fit at the photo's size), ``phase.npy`` (the photo's Gabor phase,
    sign-resolved, less the constant ``phase_offset_rad`` of the summary, rad), ``fit_phase.npy`` (the fitted
    model's phase), ``params.json`` (fitted parameters),
    ``log.csv`` (stage, epoch, wall_s, phase_loss, color_loss, phase_rms), ``convergence.png``; also
    ``orientation.png``, ``magnitude.png``, ``phase.png``, ``ring_overlay.png``, ``board_estimate.json``,
    ``model.json`` + ``model.pt`` (WoodModel.save), ``fit_vs_photo.png``, ``phase_error.png``, ``cube_preview.png``,
    ``summary.json``; with ``cfg.photometric`` also ``fit_before_photometric.png`` and
    ``model_before_photometric.json`` + ``.pt`` (the fit after stages 1-2), and ``summary["photometric"]``.

    Returns:
        the summary dict.
    """
    cfg.validate()
    torch.manual_seed(cfg.seed)
    rgb, gray = load_photo(cfg.photo, cfg.max_size)
    h, w = gray.shape
    check_against_photo(cfg, h, w)
    # the filter's curves fit the memory the process may use (on the fit's device too), before any work
    check_memory("p/q", curved_gabor_memory_bytes((h, w), cfg.p, cfg.q, cfg.device),
                 f"the curved Gabor filter of a {h} × {w} photo with curves of 2p+1 = {2 * cfg.p + 1} and 2q+1 = "
                 f"{2 * cfg.q + 1} px", "lower p and q (the curves' half lengths across and along the rings)",
                 device=cfg.device)
    if cfg.photometric and cfg.photometric_epochs > 0:  # the finest level's samples of one step
        f = min(cfg.photometric_levels)
        samples = (h // f) * (w // f) * cfg.photometric_spp
        check_memory("photometric_spp", samples * PHOTOMETRIC_BYTES_PER_SAMPLE,
                     f"stage 3's {samples} filter samples per step ({cfg.photometric_spp} per pixel of the "
                     f"{h // f} × {w // f} px level)", "lower photometric_spp", device=cfg.device)
    seconds = curved_gabor_seconds((h, w), cfg.p, cfg.q, cfg.device)
    if seconds is not None and seconds >= SAY_GABOR_S:  # before the work: a long filter is not a silent one
        log(f"fit_wood: the curved Gabor filter of the {h} × {w} px photo with p = {cfg.p}, q = {cfg.q} takes about "
            f"{_duration(seconds)} on {torch.get_num_threads()} thread(s) (shorter curves or a smaller photo take "
            f"less)")
    os.makedirs(cfg.out, exist_ok=True)  # only once the photo has been read: a refused photo leaves no run folder
    gab, rings, estimate, pith_info, model, info, timings = detect_board(cfg, rgb, gray)
    photo_phase = info["resolved_phase"].astype(np.float32)

    folder = cfg.out
    np.save(os.path.join(folder, "phase.npy"), photo_phase)
    save_gray(os.path.join(folder, "orientation.png"), gab.orientation, 0, math.pi, cmap="twilight")
    save_gray(os.path.join(folder, "magnitude.png"), gab.magnitude)
    save_gray(os.path.join(folder, "phase.png"), photo_phase, 0, 2 * math.pi, cmap="twilight")
    ring_overlay(folder, rgb, rings, estimate)
    ta_io.write_json(os.path.join(folder, "board_estimate.json"), estimate.to_dict())

    device = torch.device(cfg.device)
    model = model.to(device)
    target_phase = torch.as_tensor(photo_phase, device=device)
    mag = torch.as_tensor(gab.magnitude, device=device)
    weight = (mag / mag.mean().clamp_min(1e-12)).clamp(max=3.0)  # confidence: Gabor amplitude
    target_rgb = torch.as_tensor(rgb, device=device)

    rows = []
    start = time.perf_counter()
    from ...progress import progress_bar
    bar = progress_bar(total=cfg.epochs + cfg.color_epochs + (cfg.photometric_epochs if cfg.photometric else 0),
                       disable=not progress, desc="fit_wood", unit="ep")
    # ---- stage 1: geometry from the cyclic phase loss
    fit_geometry(model, target_phase, weight, h, w, cfg, rows, start, bar)
    timings["stage1_s"] = time.perf_counter() - start

    # ---- stage 2: colour map with the geometry frozen (linear RGB MSE)
    t1 = time.perf_counter()
    fit_colour_map(model, target_rgb, h, w, cfg, rows, start, bar)
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
        save_png(os.path.join(folder, "fit_before_photometric.png"), before.pop("fit_rgb"))
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
    return _outputs(cfg, model, rgb, photo_phase, rows, rings, info, pith_info, timings, photometric, contrast, log)


def _outputs(cfg, model, rgb, photo_phase, rows, rings, info, pith_info, timings, photometric, contrast, log):
    """The fitted model's renders, parameters, figures and summary in ``cfg.out``; returns the summary."""
    from ...metrics import ssim_2d

    folder = cfg.out
    h, w = photo_phase.shape
    with torch.no_grad():
        out = model.render_board(h, w, cfg.pixel_size_mm)
    fit_rgb = out["image"].clamp(0, 1).cpu().numpy()
    g_fit = out["G"].cpu()
    visible_rings = int(math.floor(float(g_fit.max())) - math.ceil(float(g_fit.min())) + 1)
    fit_phase = out["phase"].cpu().numpy().astype(np.float32)
    err = np.angle(np.exp(1j * (photo_phase - fit_phase)))
    final_rms = float(np.sqrt((err.astype(np.float64) ** 2).mean()))
    save_png(os.path.join(folder, "fit.png"), fit_rgb)
    np.save(os.path.join(folder, "fit_phase.npy"), fit_phase)
    model.cpu().save(os.path.join(folder, "model"))
    ring_width = effective_ring_width(model, h, w, cfg.pixel_size_mm)
    boundary = boundary_lateness(model, g_fit, rgb)  # read from the photo along the fitted G
    params = {"rotation_axis_angle_rad": model.rotation.tolist(), "translation_mm": model.translation.tolist(),
              "ring_scale_mm": float(model.ring_scale.detach()),
              "mean_ring_width_mm": ring_width, "boundary_lateness": boundary, "distortion": cfg.distortion,
              "distortion_rms_mm": float(model.m_r.detach().pow(2).mean().sqrt()) if model.m_r is not None else 0.0,
              "pixel_size_mm": cfg.pixel_size_mm, "image_hw": [h, w]}
    ta_io.write_json(os.path.join(folder, "params.json"), params)
    ssim = float(ssim_2d(fit_rgb, rgb))
    figures(folder, rows, rgb, fit_rgb, err)
    if cfg.preview:
        try:
            cube_preview(model, (h, w), cfg.pixel_size_mm, os.path.join(folder, "cube_preview.png"))
        except Exception as exc:  # rendering backends vary; the fit itself is complete
            log(f"fit_wood: cube preview skipped ({type(exc).__name__}: {exc})")
    summary = {
        "photo": os.path.abspath(cfg.photo), "image_hw": [h, w], "rings_traced": len(rings),
        "ring_scale_mm": float(model.ring_scale.detach()),
        "mean_ring_width_mm": ring_width, "boundary_lateness": boundary, "initial_phase_rms": rows[0]["phase_rms"],
        "stage1_phase_rms": rows[cfg.epochs]["phase_rms"], "final_phase_rms": final_rms,
        "mean_abs_wrapped_phase_error": float(np.abs(err).mean()),
        "fraction_initial_error_below_half_pi": info.get("fraction_below_half_pi"),
        "phase_offset_rad": info.get("phase_offset"),
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
        # split_at_pith_line: whether the centre line crosses the photo, share of pixels whose response it changed
        "pith_split": {k: pith_info[k] for k in ("split", "fraction_split") if k in pith_info} or None,
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
