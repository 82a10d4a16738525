"""Stage 2 of the wood fit (thesis §2.2): the colour map with the geometry frozen, from the photo's mean colour
per (ring, lateness bin) refined by Adam on the linear-RGB error; optionally its luminance matched to the photo's."""
import time

import numpy as np
import torch

__all__ = ["fit_colour_map", "match_luminance_histogram"]


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


def fit_colour_map(model, target_rgb, h, w, cfg, rows, start, bar=None):
    """Stage 2: the geometry frozen, the colour map initialised from the photo's mean colours and refined by
    ``cfg.color_epochs`` Adam steps on the linear-RGB MSE (clamped to [0, 1]); log rows appended to ``rows``."""
    for name, p in model.named_parameters():
        if name != "color_map":
            p.requires_grad_(False)
    with torch.no_grad():  # start from the photo's mean colour per (ring, lateness bin)
        out = model.render_board(h, w, cfg.pixel_size_mm)
        _init_color_map(model, out, target_rgb)
    optimizer = torch.optim.Adam([model.color_map], lr=cfg.color_lr)
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
