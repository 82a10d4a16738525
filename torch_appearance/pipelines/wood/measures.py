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
