"""Target appearances for print optimisation: built-in test targets and loading user images.

All targets are linear-RGB texel images (H, W, 3) float32 in [0, 1], texel [j, i] = voxel column (j, i).
"""
import os

import numpy as np

from ... import io as ta_io

__all__ = ["zebra_target", "colorchecker_target", "load_target", "BUILTIN_TARGETS", "ZEBRA_STRIPES"]

#: Stripe heights of the paper's resolution test (Fig. 7), in voxels.
ZEBRA_STRIPES = (30, 15, 10, 5, 3, 1)


def zebra_target(height=64, band_width=8, black=0.06, white=0.75):
    """The paper's "zebra" resolution test: six vertical bands of black/white horizontal stripes.

    Band k (left to right) alternates black and white stripes :data:`ZEBRA_STRIPES`\\ [k] texels high.

    Args:
        height: texels along y.
        band_width: texels along x per band (the image is 6·band_width wide).
        black, white: neutral linear-RGB levels of the stripes (default: inside the printable gamut of the
            Vero CMYKW inks on a 1 mm slab, so a perfect result is reachable in colour and only sharpness is tested).

    Returns:
        (height, 6·band_width, 3) float32 linear RGB.
    """
    if height < 1 or band_width < 1:
        raise ValueError(f"zebra_target: expected height, band_width >= 1, got {height}, {band_width}")
    rows = np.arange(height)
    image = np.empty((height, band_width * len(ZEBRA_STRIPES), 3), np.float32)
    for k, stripe in enumerate(ZEBRA_STRIPES):
        level = np.where((rows // stripe) % 2 == 0, black, white).astype(np.float32)
        image[:, k * band_width:(k + 1) * band_width, :] = level[:, None, None]
    return image


def colorchecker_patches():
    """The 24 ColorChecker patches as linear sRGB (D65), (24, 3) float32, from colour-science's data set
    "ColorChecker24 - After November 2014" (xyY under D50, chromatically adapted to D65 with CAT02)."""
    import colour

    checker = colour.CCS_COLOURCHECKERS["ColorChecker24 - After November 2014"]
    xyy = np.array(list(checker.data.values()), dtype=np.float64)
    xyz = colour.xyY_to_XYZ(xyy)
    rgb = colour.XYZ_to_RGB(xyz, colour.RGB_COLOURSPACES["sRGB"], illuminant=checker.illuminant,
                            chromatic_adaptation_transform="CAT02", apply_cctf_encoding=False)
    return np.clip(rgb, 0.0, 1.0).astype(np.float32)


def colorchecker_target(patch=8, border=2):
    """The 24 ColorChecker patches in the usual 4 × 6 layout, ``patch`` texels square, on a dark grey frame.

    Returns:
        (4·patch + 5·border, 6·patch + 7·border, 3) float32 linear RGB.
    """
    if patch < 1 or border < 0:
        raise ValueError(f"colorchecker_target: expected patch >= 1 and border >= 0, got {patch}, {border}")
    patches = colorchecker_patches()
    h, w = 4 * patch + 5 * border, 6 * patch + 7 * border
    image = np.full((h, w, 3), 0.03, np.float32)
    for n in range(24):
        r, c = divmod(n, 6)
        y0, x0 = border + r * (patch + border), border + c * (patch + border)
        image[y0:y0 + patch, x0:x0 + patch] = patches[n]
    return image


BUILTIN_TARGETS = {"zebra": zebra_target, "colorchecker": colorchecker_target}


def load_target(spec, *, size=None, name="target"):
    """A target image as linear RGB (H, W, 3) float32.

    Args:
        spec: a built-in name ("zebra", "colorchecker") or a path to an image that
            :func:`torch_appearance.io.read_image` reads: 8/16-bit sRGB PNG/JPEG/TIFF (decoded to linear) or a linear
            EXR; grey is repeated over R, G, B, alpha dropped. Truncated or corrupt files are refused.
        size: optional (H, W) in texels to resample to (area averaging in linear RGB).
        name: argument name for error messages.
    """
    if not isinstance(spec, (str, os.PathLike)):
        raise TypeError(f"{name}: expected a path or one of {sorted(BUILTIN_TARGETS)}, got {type(spec).__name__}")
    spec = os.fspath(spec)
    if spec in BUILTIN_TARGETS:
        image = BUILTIN_TARGETS[spec]()
    else:
        if not os.path.isfile(spec):
            raise ValueError(f"{name}: expected a built-in target {sorted(BUILTIN_TARGETS)} or an image file, "
                             f"got {spec!r} (no such file)")
        image = ta_io.read_image(spec, space="linear", name=name)  # decoded fully; sRGB or linear EXR
    image = np.asarray(image, np.float32)
    if image.ndim != 3 or image.shape[2] != 3 or min(image.shape[:2]) < 1:
        raise ValueError(f"{name}: expected an RGB image (H, W, 3), got shape {image.shape}")
    if not np.isfinite(image).all():
        raise ValueError(f"{name}: expected finite values, got NaN/Inf in {spec!r}")
    if size is not None and tuple(size) != image.shape[:2]:
        import cv2
        h, w = int(size[0]), int(size[1])
        if h < 1 or w < 1:
            raise ValueError(f"{name}: expected a target size >= 1 texel, got {size}")
        image = cv2.resize(image, (w, h), interpolation=cv2.INTER_AREA)
    return np.clip(image, 0.0, 1.0).astype(np.float32)
