"""Writing a print run folder: images, arrays, the checkpoint, the log's columns and the scores."""
import io
import os

import numpy as np
import torch

from ... import io as ta_io
from ...metrics import color_report

__all__ = ["LOG_FIELDS", "CHECKPOINT", "save_image", "save_torch", "npz_bytes", "score"]

LOG_FIELDS = ["iteration", "wall_s", "loss", "E1", "E2", "E3", "dE00_mean", "dE00_p95", "dE76_mean", "seed"]
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


def score(image, target):
    """CIEDE2000 mean/p95 and ΔE76 of (..., 3) linear RGB colours against the target's."""
    rep = color_report(torch.as_tensor(image).reshape(-1, 3).double(), torch.as_tensor(target).reshape(-1, 3).double())
    return {k: float(v) for k, v in rep.items()}
