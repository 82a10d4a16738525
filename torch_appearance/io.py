"""Image and result I/O: linear EXR, sRGB PNG, JSON — every writer is atomic.

Conventions:

* Images are ``(H, W, 3)`` RGB, channels last, row 0 at the top, as :func:`torch_appearance.render_texels`
  returns for one face. Writers accept a :class:`numpy.ndarray` or a :class:`torch.Tensor` (detached and
  moved to the CPU); readers return :class:`numpy.ndarray` ``float32``.
* EXR files hold **linear** RGB as 32-bit float channels ``R``, ``G``, ``B`` (ZIP compression, lossless).
* PNG files hold **sRGB**-encoded values: :func:`write_png` takes linear RGB, encodes it with the sRGB
  transfer function, clips to ``[0, 1]`` and quantises to 8 or 16 bits; :func:`read_png` decodes back to
  linear RGB (or returns the sRGB values with ``linear=False``).
* Atomic writes: the bytes are encoded in memory, written to a temporary file in the destination folder,
  flushed to disk and moved over ``path`` with :func:`os.replace`. A failed write leaves neither a partial
  ``path`` nor a temporary file behind, and an existing ``path`` keeps its old content.
* Bad arguments raise :class:`TypeError` / :class:`ValueError` naming the argument, before anything is
  written.
"""
import contextlib
import io as _stdio
import json
import math
import os
import pathlib
import tempfile

import cv2
import numpy as np
import OpenEXR
import torch

from .color import linear_to_srgb, srgb_to_linear

__all__ = ["write_exr", "read_exr", "write_png", "read_png", "write_json", "write_csv", "save_figure",
           "atomic_write_bytes", "nan_to_none", "markdown_table"]

# Permissions that a plain open() would give a new file (mkstemp creates 0600 files).
_UMASK = os.umask(0)
os.umask(_UMASK)
_FILE_MODE = 0o666 & ~_UMASK


# --------------------------------------------------------------------------------------------------------------
# argument checks
# --------------------------------------------------------------------------------------------------------------
def _check_path(name, path, suffixes=None):
    if not isinstance(path, (str, os.PathLike)):
        raise TypeError(f"{name} must be a str or os.PathLike, got {type(path).__name__}")
    path = os.fspath(path)
    if isinstance(path, bytes):
        raise TypeError(f"{name} must be a str path, got bytes")
    if not path:
        raise ValueError(f"{name} must not be empty")
    if suffixes is not None and not path.lower().endswith(suffixes):
        raise ValueError(f"{name} must end with {' or '.join(suffixes)}, got {path!r}")
    return path


def _as_rgb_image(name, image):
    """Return ``image`` as a float64 ``(H, W, 3)`` NumPy array after checking type, shape and finiteness."""
    if isinstance(image, torch.Tensor):
        if image.is_complex() or image.dtype == torch.bool or not image.is_floating_point():
            raise TypeError(f"{name} must have a floating-point dtype, got {image.dtype}")
        array = image.detach().to(device="cpu", dtype=torch.float64).numpy()
    elif isinstance(image, np.ndarray):
        if not np.issubdtype(image.dtype, np.floating):
            raise TypeError(f"{name} must have a floating-point dtype, got {image.dtype}")
        array = image.astype(np.float64, copy=False)
    else:
        raise TypeError(f"{name} must be a numpy.ndarray or torch.Tensor, got {type(image).__name__}")
    if array.ndim != 3 or array.shape[2] != 3:
        raise ValueError(f"{name} must have shape (H, W, 3), got {tuple(array.shape)}")
    if array.shape[0] == 0 or array.shape[1] == 0:
        raise ValueError(f"{name} must not be empty, got shape {tuple(array.shape)}")
    finite = np.isfinite(array)
    if not finite.all():
        bad = int(array.size - np.count_nonzero(finite))
        raise ValueError(f"{name} must be finite, got {bad} NaN/inf value(s)")
    return array


# --------------------------------------------------------------------------------------------------------------
# atomic writing
# --------------------------------------------------------------------------------------------------------------
def atomic_write_bytes(path, data):
    """Write ``data`` to ``path`` atomically (temporary file in the same folder, fsync, :func:`os.replace`).

    Readers see either the old file or the complete new one, never a partial file; on any error the
    temporary file is removed and the error is re-raised. The folder must exist.

    Args:
        path: destination file (``str`` or ``os.PathLike``).
        data: the complete file content (``bytes``, ``bytearray`` or ``memoryview``).
    """
    path = _check_path("path", path)
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise TypeError(f"data must be bytes, got {type(data).__name__}")
    directory = os.path.dirname(os.path.abspath(path))
    fd, tmp = tempfile.mkstemp(prefix=f".{os.path.basename(path)}.", suffix=".tmp", dir=directory)
    try:
        with os.fdopen(fd, "wb") as handle:
            handle.write(data)
            handle.flush()
            os.fsync(handle.fileno())
        os.chmod(tmp, _FILE_MODE)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    # Make the rename itself durable where the platform allows it.
    with contextlib.suppress(OSError, AttributeError):
        dir_fd = os.open(directory, os.O_RDONLY)
        try:
            os.fsync(dir_fd)
        finally:
            os.close(dir_fd)


# --------------------------------------------------------------------------------------------------------------
# EXR
# --------------------------------------------------------------------------------------------------------------
def write_exr(path, image):
    """Write linear RGB to an OpenEXR file (32-bit float ``R``, ``G``, ``B`` channels, ZIP, scanline).

    Args:
        path: destination, must end with ``.exr``.
        image: linear RGB, shape ``(H, W, 3)``, floating point, finite (values are stored as ``float32``,
            unclipped: the EXR keeps negative and > 1 radiance as it is).

    Raises:
        TypeError: ``path`` or ``image`` of the wrong type or dtype.
        ValueError: wrong shape, non-finite values, a value that overflows ``float32``, a wrong suffix.

    Example:
        >>> write_exr("render.exr", torch.rand(4, 5, 3))  # doctest: +SKIP
    """
    path = _check_path("path", path, (".exr",))
    array = _as_rgb_image("image", image)
    largest = float(np.abs(array).max())
    if largest > float(np.finfo(np.float32).max):
        raise ValueError(f"image has values outside the float32 range (largest magnitude {largest:.3g})")
    array = array.astype(np.float32)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    buffer = _stdio.BytesIO()
    OpenEXR.File(header, {"RGB": np.ascontiguousarray(array)}).write(buffer)
    atomic_write_bytes(path, buffer.getvalue())


def read_exr(path):
    """Read the ``R``, ``G``, ``B`` channels of an OpenEXR file (first part) as linear ``float32``.

    Half-float channels are widened to ``float32``; other channels (alpha, depth, ...) are ignored.

    Args:
        path: an existing ``.exr`` file.

    Returns:
        ``numpy.ndarray`` of shape ``(H, W, 3)``, dtype ``float32``.

    Raises:
        FileNotFoundError: ``path`` does not exist.
        ValueError: the file is not a readable EXR or lacks one of the ``R``, ``G``, ``B`` channels.
    """
    path = _check_path("path", path)
    with open(path, "rb") as handle:
        try:
            exr = OpenEXR.File(handle, separate_channels=True)
        except RuntimeError as error:
            raise ValueError(f"path {path!r} is not a readable OpenEXR file: {error}") from None
        channels = exr.channels()
    missing = [name for name in "RGB" if name not in channels]
    if missing:
        raise ValueError(
            f"EXR file {path!r} lacks channel(s) {', '.join(missing)}; it has {sorted(channels)}"
        )
    planes = []
    for name in "RGB":
        pixels = np.asarray(channels[name].pixels)
        if not np.issubdtype(pixels.dtype, np.floating):
            raise ValueError(f"EXR file {path!r}: channel {name} has dtype {pixels.dtype}, expected half or float")
        planes.append(pixels.astype(np.float32, copy=False))
    return np.stack(planes, axis=-1)


# --------------------------------------------------------------------------------------------------------------
# PNG
# --------------------------------------------------------------------------------------------------------------
def write_png(path, image_linear, bits=8):
    """Write linear RGB as an sRGB-encoded 8- or 16-bit PNG.

    ``linear_to_srgb(image_linear)`` is clipped to ``[0, 1]``, scaled by ``2**bits - 1`` and rounded to the
    nearest integer (so a 16-bit round trip is exact to within half a quantisation step in sRGB).

    Args:
        path: destination, must end with ``.png``.
        image_linear: linear RGB, shape ``(H, W, 3)``, floating point, finite. Values outside ``[0, 1]`` are
            clipped (after the sRGB encoding) — use :func:`write_exr` to keep them.
        bits: 8 or 16.

    Raises:
        TypeError: wrong argument types or dtypes.
        ValueError: wrong shape, non-finite values, ``bits`` not 8 or 16, a wrong suffix.

    Example:
        >>> write_png("render.png", torch.rand(4, 5, 3), bits=16)  # doctest: +SKIP
    """
    path = _check_path("path", path, (".png",))
    if isinstance(bits, bool) or not isinstance(bits, (int, np.integer)):
        raise TypeError(f"bits must be the int 8 or 16, got {type(bits).__name__}")
    if bits not in (8, 16):
        raise ValueError(f"bits must be 8 or 16, got {bits}")
    array = _as_rgb_image("image_linear", image_linear)
    srgb = linear_to_srgb(torch.from_numpy(array)).numpy()
    scale = float(2**bits - 1)
    quantised = np.rint(np.clip(srgb, 0.0, 1.0) * scale).astype(np.uint8 if bits == 8 else np.uint16)
    bgr = np.ascontiguousarray(quantised[..., ::-1])  # OpenCV stores channels as B, G, R
    ok, encoded = cv2.imencode(".png", bgr)
    if not ok:
        raise RuntimeError(f"OpenCV failed to encode a PNG of shape {bgr.shape}")
    atomic_write_bytes(path, encoded.tobytes())


def read_png(path, linear=True):
    """Read an 8- or 16-bit PNG (or any image OpenCV decodes) as RGB ``float32``.

    Greyscale images are repeated over the three channels; an alpha channel is dropped.

    Args:
        path: an existing image file.
        linear: return linear RGB (decoded with :func:`~torch_appearance.color.srgb_to_linear`); with
            ``False`` return the stored sRGB values scaled to ``[0, 1]``.

    Returns:
        ``numpy.ndarray`` of shape ``(H, W, 3)``, dtype ``float32``, values in ``[0, 1]``.

    Raises:
        FileNotFoundError: ``path`` does not exist.
        ValueError: the file cannot be decoded or has an unsupported bit depth.
    """
    path = _check_path("path", path)
    if not isinstance(linear, bool):
        raise TypeError(f"linear must be a bool, got {type(linear).__name__}")
    with open(path, "rb") as handle:
        raw = np.frombuffer(handle.read(), dtype=np.uint8)
    decoded = cv2.imdecode(raw, cv2.IMREAD_UNCHANGED) if raw.size else None
    if decoded is None:
        raise ValueError(f"path {path!r} is not an image that OpenCV can decode")
    if decoded.dtype == np.uint8:
        scale = 255.0
    elif decoded.dtype == np.uint16:
        scale = 65535.0
    else:
        raise ValueError(f"image {path!r} has dtype {decoded.dtype}; expected 8- or 16-bit integers")
    if decoded.ndim == 2:
        rgb = np.repeat(decoded[..., None], 3, axis=-1)
    elif decoded.shape[2] in (3, 4):
        rgb = decoded[..., 2::-1]  # B, G, R(, A) -> R, G, B
    elif decoded.shape[2] == 1:
        rgb = np.repeat(decoded, 3, axis=-1)
    else:
        raise ValueError(f"image {path!r} has {decoded.shape[2]} channels; expected 1, 3 or 4")
    srgb = rgb.astype(np.float64) / scale
    out = srgb_to_linear(torch.from_numpy(srgb)).numpy() if linear else srgb
    return np.ascontiguousarray(out, dtype=np.float32)


# --------------------------------------------------------------------------------------------------------------
# JSON
# --------------------------------------------------------------------------------------------------------------
def _json_default(value):
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, torch.Tensor):
        return value.detach().cpu().tolist()
    if isinstance(value, (pathlib.PurePath, torch.dtype, torch.device)):
        return str(value)
    raise TypeError(f"obj contains a value of type {type(value).__name__} that is not JSON serialisable")


def write_json(path, obj, *, indent=2):
    """Write ``obj`` as strict JSON (UTF-8, trailing newline), atomically.

    NumPy scalars and arrays, tensors, paths, dtypes and devices are converted; NaN and infinity are refused
    because strict JSON has no spelling for them.

    Args:
        path: destination file.
        obj: a JSON-serialisable object.
        indent: indentation (``None`` for one line).

    Raises:
        TypeError: ``obj`` holds a value that cannot be serialised.
        ValueError: ``obj`` holds NaN or infinity.
    """
    path = _check_path("path", path)
    try:
        text = json.dumps(obj, indent=indent, default=_json_default, allow_nan=False)
    except ValueError as error:
        raise ValueError(f"obj cannot be written as strict JSON (NaN or infinity?): {error}") from None
    atomic_write_bytes(path, (text + "\n").encode("utf-8"))



def nan_to_none(obj):
    """``obj`` with every NaN / infinite float replaced by None, recursively through dicts, lists and tuples (for
    :func:`write_json`, which refuses non-finite values; e.g. metrics that are undefined for a refused run)."""
    if isinstance(obj, dict):
        return {k: nan_to_none(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [nan_to_none(v) for v in obj]
    if isinstance(obj, (float, np.floating)) and not math.isfinite(float(obj)):
        return None
    return obj


def markdown_table(rows, fields):
    """A Markdown table of ``rows`` (dicts) with columns ``fields``: ``(key, header, format)`` triples, e.g.
    ``("err", "s_r err", "{:+.1%}")``. Missing or None values print as "–"; "|" in a cell becomes "/"."""
    lines = ["| " + " | ".join(h for _, h, _ in fields) + " |", "|" + "|".join("---" for _ in fields) + "|"]
    for r in rows:
        cells = ["–" if r.get(key) is None else fmt.format(r[key]).replace("|", "/") for key, _, fmt in fields]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def write_csv(path, rows, fields):
    """Atomically write ``rows`` (dicts) as CSV with the header ``fields``; missing or None values are empty."""
    import csv

    buffer = _stdio.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=list(fields))
    writer.writeheader()
    for row in rows:
        writer.writerow({k: ("" if row.get(k) is None else row[k]) for k in fields})
    atomic_write_bytes(path, buffer.getvalue().encode())


def save_figure(fig, path, dpi=120):
    """Atomically save a matplotlib figure as PNG and close it."""
    import matplotlib.pyplot as plt

    buffer = _stdio.BytesIO()
    fig.savefig(buffer, format="png", dpi=dpi)
    plt.close(fig)
    atomic_write_bytes(path, buffer.getvalue())
