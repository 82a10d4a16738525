"""What a wood fit is measured by: ring width, ring boundaries, latewood contrast, phase RMS and SSIM."""
import numpy as np
import torch

from .colour_stage import _LUMA

__all__ = ["effective_ring_width", "boundary_lateness", "model_boundaries", "latewood_contrast", "fit_metrics"]


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


def boundary_lateness(model, G=None, photo_rgb=None, bins=64):
    """Lateness at which the ring colour changes fastest (the latewood → earlywood transition).

    The Gabor phase, and so the fitted G, is aligned with the intensity's fundamental, not with the sharp
    boundary. With ``G`` and ``photo_rgb`` the boundary is read from the photo itself: its luminance averaged over
    the pixels of each of ``bins`` lateness bins of frac(G), lightly smoothed (cyclic), and the largest jump between
    neighbouring bins, refined between bins by a parabola through the three largest |jumps| around it. A shift of
    G by a constant moves this estimate by the same constant (to about a tenth of a bin). Without them, the stage-2
    colour map (mean over rings) is read instead: the jump between its bins, on its 16-bin grid.

    Args:
        model: the fitted :class:`~torch_appearance.nn.WoodModel`.
        G: optional ``(H, W)`` fitted growth field of the photo's pixels (tensor or array).
        photo_rgb: optional ``(H, W, 3)`` the photo (linear RGB).
        bins: lateness bins of the photo profile.

    Returns:
        lateness ℓ* in [0, 1): ring boundaries are where G = k + ℓ*.
    """
    if G is not None and photo_rgb is not None:
        g = np.asarray(G.detach().cpu().numpy() if torch.is_tensor(G) else G, np.float64)
        y = np.asarray(photo_rgb, np.float64) @ np.array(_LUMA)
        if g.shape != y.shape:
            raise ValueError(f"G and photo_rgb: expected the same (H, W), got {g.shape} and {y.shape}")
        lat = g - np.floor(g)
        idx = np.minimum((lat * bins).astype(np.int64), bins - 1).ravel()
        count = np.bincount(idx, minlength=bins)
        prof = np.bincount(idx, weights=y.ravel(), minlength=bins) / np.maximum(count, 1)
        full = count > 0
        if full.sum() >= 3 and not full.all():  # empty bins: interpolated cyclically from their neighbours
            x = np.nonzero(full)[0]
            prof = np.interp(np.arange(bins), np.r_[x - bins, x, x + bins], np.r_[prof[x], prof[x], prof[x]])
        prof = 0.25 * np.roll(prof, 1) + 0.5 * prof + 0.25 * np.roll(prof, -1)
        jump = np.abs(np.roll(prof, -1) - prof)  # between bin i and i + 1, at lateness (i + 1) / bins
        i = int(np.argmax(jump))
        a, b, c = jump[(i - 1) % bins], jump[i], jump[(i + 1) % bins]
        den = a - 2 * b + c
        delta = 0.5 * (a - c) / den if den < 0 else 0.0
        return float(((i + 1 + delta) / bins) % 1.0)
    with torch.no_grad():
        lum = model.color_map.mean(0) @ torch.tensor(_LUMA, dtype=model.color_map.dtype)
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
    from ...metrics import ssim_2d

    with torch.no_grad():
        out = model.render_board(h, w, pixel_size_mm)
    fit_rgb = out["image"].clamp(0, 1).cpu().numpy()
    err = np.angle(np.exp(1j * (np.asarray(photo_phase, np.float64) - out["phase"].cpu().numpy())))
    rmse = float(np.sqrt(((fit_rgb.astype(np.float64) - np.asarray(photo_rgb, np.float64)) ** 2).mean()))
    return {"phase_rms": float(np.sqrt((err ** 2).mean())), "ssim": float(ssim_2d(fit_rgb, photo_rgb)),
            "colour_rmse": rmse, "latewood_contrast": latewood_contrast(fit_rgb, photo_rgb), "fit_rgb": fit_rgb}
