"""Stage 3 of the wood fit (optional): geometry and colour map against the photo's colours through the
reparameterised render (:mod:`torch_appearance.nn.wood_reparam`), coarse to fine."""
import dataclasses
import time

import torch

from .geometry_stage import _phase_normalised_groups, distortion_prior, phase_loss, wrap

__all__ = ["photometric_stage"]


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

    from ...color import linear_to_srgb
    from ...nn.wood_reparam import pixel_samples, reparam_render

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
