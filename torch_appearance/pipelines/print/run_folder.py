"""Writing a print run folder: images, arrays, the checkpoint, the log's columns and the scores."""
import io
import os

import numpy as np
import torch

from ... import io as ta_io
from ...print_error import ERROR_FIELDS, noise_free_error

__all__ = ["LOG_FIELDS", "CHECKPOINT", "save_image", "save_torch", "npz_bytes", "score"]

#: log.csv's columns: the training loss and its parts at every iteration; at evaluations the print's error free of
#: render noise with its standard errors, the raw figures of the evaluation render and its noise
#: (:data:`~torch_appearance.print_error.ERROR_FIELDS`)
LOG_FIELDS = ["iteration", "wall_s", "loss", "E1", "E2", "E3", *ERROR_FIELDS, "seed"]
CHECKPOINT = "checkpoint.pt"


def save_image(folder, stem, rgb):
    """``stem.exr`` (linear RGB, float32) and ``stem.png`` (sRGB preview, clipped to [0, 1]) of (H, W, 3) ``rgb``."""
    rgb = np.ascontiguousarray(np.asarray(rgb, np.float32))
    ta_io.write_exr(os.path.join(folder, f"{stem}.exr"), rgb)
    ta_io.write_png(os.path.join(folder, f"{stem}.png"), np.clip(rgb, 0, 1))


def save_torch(obj, path):
    """``torch.save`` written atomically (an interrupted run keeps its previous checkpoint)."""
    buffer = io.BytesIO()
    torch.save(obj, buffer)
    ta_io.atomic_write_bytes(path, buffer.getvalue())


def npz_bytes(**arrays):
    """The bytes of a compressed ``.npz`` holding ``arrays``."""
    buffer = io.BytesIO()
    np.savez_compressed(buffer, **arrays)
    return buffer.getvalue()


def score(renders, target, texels=False, population=None):
    """The print's CIEDE2000 free of render noise (:func:`~torch_appearance.print_error.noise_free_error`) from
    ``renders`` (K, ..., 3), independent renders of the print, against ``target`` (..., 3) or against K renders of
    another print (K, ..., 3); with ``texels=True`` a pair (scores, per-texel estimates (M,)). ``population``: the
    texels are a random sample of that many (the standard errors include the sampling error)."""
    renders, target = torch.as_tensor(renders).double(), torch.as_tensor(target).double()
    k = renders.shape[0]
    target = target.reshape(k, -1, 3) if target.dim() == renders.dim() else target.reshape(-1, 3)
    return noise_free_error(renders.reshape(k, -1, 3), target, texels=texels, population=population)
