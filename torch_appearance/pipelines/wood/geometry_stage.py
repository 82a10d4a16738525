"""Stage 1 of the wood fit (thesis §2.2): the board transform, ring scale and distortion from the cyclic phase loss
E = Σ w·wrap(J_φ − I_φ)² / Σ w, with Adam steps measured in ring widths and the distortion coarse to fine."""
import math
import time

import torch

__all__ = ["wrap", "phase_loss", "distortion_prior", "fit_geometry"]


def wrap(x):
    """Wrap angles to (−π, π] (differentiable almost everywhere)."""
    return x - 2 * math.pi * torch.floor((x + math.pi) / (2 * math.pi))


def phase_loss(model_phase, photo_phase, weight):
    """Cyclic phase loss E = Σ w·wrap(J_φ − I_φ)² / Σ w."""
    d = wrap(photo_phase - model_phase)
    return (weight * d * d).sum() / weight.sum()


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
    distortion growing with r is indistinguishable from a ring-scale change) and from fitting noise. The lobe
    texture near the pith (``model.m_p``), when the model has one, is held smooth the same way.
    ``m_r`` (``(1, 1, Hd, Wd)`` mm) replaces the model's own texture when given."""
    m = (model.m_r if m_r is None else m_r) / model.ring_scale
    prior = (m[..., 1:, :] - m[..., :-1, :]).pow(2).mean() + (m[..., :, 1:] - m[..., :, :-1]).pow(2).mean()
    if getattr(model, "m_p", None) is not None:   # the lobe texture: rows periodic in θ_t, columns over r
        p = model.m_p / model.ring_scale
        prior = prior + (p - torch.roll(p, 1, dims=2)).pow(2).mean() + (p[..., 1:] - p[..., :-1]).pow(2).mean()
    return prior


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
    scale = {"translation": s_r, "rotation": s_r / r_mean, "log_ring_scale": 1.0 / g_mean, "m_r": s_r, "m_t": s_r, "m_p": s_r}
    groups = []
    for name, param in model.named_parameters():
        if name == "color_map":
            continue
        groups.append({"params": [param], "lr": cfg.lr * scale.get(name, 1.0), "name": name})
    return groups


def fit_geometry(model, target_phase, weight, h, w, cfg, rows, start, bar=None):
    """Stage 1: ``cfg.epochs`` Adam steps on the cyclic phase loss (+ ``cfg.smoothness`` × the distortion prior)
    over every parameter but the colour map; the distortion texture coarse to fine (``cfg.coarse_to_fine`` levels).

    Args:
        model: the initial WoodModel (modified in place). target_phase: (H, W) the photo's sign-resolved Gabor phase.
        weight: (H, W) confidence of each pixel. h, w: photo size. cfg: WoodFitConfig.
        rows: log rows to append to (stage 1, one per epoch and the last). start: the fit's start (perf_counter).
        bar: tqdm bar or None.
    """
    groups = _phase_normalised_groups(model, h, w, cfg)
    pyramid = _DistortionPyramid(model, cfg.coarse_to_fine) if model.m_r is not None else None
    if pyramid is not None:  # the texture is m_r(init) + Σ upsampled levels, coarse levels switched on first
        m_lr = next(g["lr"] for g in groups if g["name"] == "m_r")
        groups = [g for g in groups if g["name"] != "m_r"] + [
            {"params": [lev], "lr": m_lr, "name": f"m_r_level{i}"} for i, lev in enumerate(pyramid.levels)]
    optimizer = torch.optim.Adam(groups, lr=cfg.lr)
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
