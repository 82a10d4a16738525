"""Reading the board photo of a wood fit."""
import math
import os

import numpy as np

from ... import io as ta_io

__all__ = ["load_photo"]


def load_photo(path, max_size=None):
    """A photo as linear RGB (H, W, 3) float32 and its luminance (H, W) in [0, 1] (sRGB decoded).

    Read with :func:`torch_appearance.io.read_image`: 8/16-bit sRGB images are decoded to linear, EXR is linear,
    grey is repeated over R, G, B, alpha is dropped; truncated or corrupt files are refused.

    Raises:
        ValueError: missing, unreadable, truncated or corrupt file, or smaller than 8×8 pixels (also once
            downscaled to ``max_size``).
    """
    import cv2

    if not isinstance(path, (str, os.PathLike)) or not os.path.isfile(path):
        raise ValueError(f"photo: expected an image file, got {path!r} (no such file)")
    rgb = ta_io.read_image(path, space="linear", name="photo")
    if min(rgb.shape[:2]) < 8:
        raise ValueError(f"photo: expected at least 8×8 pixels, got {rgb.shape[:2]}")
    if max_size is not None and max(rgb.shape[:2]) > max_size:
        f = max_size / max(rgb.shape[:2])
        size = (round(rgb.shape[1] * f), round(rgb.shape[0] * f))
        if min(size) < 8:
            raise ValueError(f"max_size: {max_size} px makes the {rgb.shape[0]} × {rgb.shape[1]} px photo "
                             f"{size[1]} × {size[0]} px; expected at least 8 px a side, so at least "
                             f"{math.ceil(8 * max(rgb.shape[:2]) / min(rgb.shape[:2]))}")
        rgb = cv2.resize(rgb, size, interpolation=cv2.INTER_AREA)
    gray = rgb @ np.array([0.2126, 0.7152, 0.0722], np.float32)
    return rgb.astype(np.float32), gray.astype(np.float32)
