"""Image and result I/O: linear EXR, sRGB PNG, JSON — every writer is atomic.

Conventions:

* Images are ``(H, W, 3)`` RGB, channels last, row 0 at the top, as :func:`torch_appearance.render_texels`
  returns for one face. Writers accept a :class:`numpy.ndarray` or a :class:`torch.Tensor` (detached and
  moved to the CPU); readers return :class:`numpy.ndarray` ``float32``.
* EXR files hold **linear** RGB as 32-bit float channels ``R``, ``G``, ``B`` (ZIP compression, lossless).
* PNG files hold **sRGB**-encoded values: :func:`write_png` takes linear RGB, encodes it with the sRGB
  transfer function, clips to ``[0, 1]`` and quantises to 8 or 16 bits; :func:`read_png` decodes back to
  linear RGB (or returns the sRGB values with ``linear=False``).
* Reading images: :func:`read_image` is the package's one image reader (targets, photos, textures, masks,
  environment maps; :func:`read_png`, :func:`read_exr` and :func:`read_mask` are built on it). It decodes the
  whole file and refuses a truncated or corrupt PNG, JPEG, TIFF, BMP, WebP or EXR with a ``ValueError`` naming
  the file, and converts colour encodings explicitly: 8/16-bit images are sRGB, EXR (and float TIFF) linear;
  grey is repeated over R, G, B, palettes are expanded, alpha is dropped or returned as a mask.
* Atomic writes: the bytes are encoded in memory, written to a temporary file in the destination folder,
  flushed to disk and moved over ``path`` with :func:`os.replace`. A failed write leaves neither a partial
  ``path`` nor a temporary file behind, and an existing ``path`` keeps its old content.
* Bad arguments raise :class:`TypeError` / :class:`ValueError` naming the argument, before anything is
  written.
"""
import contextlib
import functools
import io as _stdio
import json
import logging
import math
import os
import pathlib
import re
import shutil
import tempfile
import threading
import warnings

import cv2
import numpy as np
import OpenEXR
import torch

from .checks import check_choice, check_finite, check_path, describe
from .color import linear_to_srgb, srgb_to_linear

__all__ = ["read_image", "read_image_bytes", "read_mask", "decode_image", "strict_pillow", "IMAGE_FORMATS",
           "write_exr", "read_exr", "write_png", "read_png", "write_json", "write_csv", "save_figure",
           "atomic_write_bytes", "atomic_output", "read_json", "nan_to_none", "markdown_table"]

# Permissions that a plain open() would give a new file (mkstemp creates 0600 files).
_UMASK = os.umask(0)
os.umask(_UMASK)
_FILE_MODE = 0o666 & ~_UMASK
_DIR_MODE = 0o777 & ~_UMASK


# --------------------------------------------------------------------------------------------------------------
# argument checks
# --------------------------------------------------------------------------------------------------------------
def _as_rgb_image(name, image):
    """Return ``image`` as a float64 ``(H, W, 3)`` NumPy array after checking type, shape and finiteness."""
    if isinstance(image, torch.Tensor):
        if image.is_complex() or image.dtype == torch.bool or not image.is_floating_point():
            raise TypeError(f"{name}: expected a floating-point dtype, got {image.dtype}")
        array = image.detach().to(device="cpu", dtype=torch.float64).numpy()
    elif isinstance(image, np.ndarray):
        if not np.issubdtype(image.dtype, np.floating):
            raise TypeError(f"{name}: expected a floating-point dtype, got {image.dtype}")
        array = image.astype(np.float64, copy=False)
    else:
        raise TypeError(f"{name}: expected a numpy.ndarray or torch.Tensor of shape (H, W, 3), got {describe(image)}")
    if array.ndim != 3 or array.shape[2] != 3:
        raise ValueError(f"{name}: expected shape (H, W, 3), got {tuple(array.shape)}")
    if array.shape[0] == 0 or array.shape[1] == 0:
        raise ValueError(f"{name}: expected a non-empty image, got shape {tuple(array.shape)}")
    return check_finite(name, array)


# --------------------------------------------------------------------------------------------------------------
# atomic writing
# --------------------------------------------------------------------------------------------------------------
@contextlib.contextmanager
def atomic_output(path, *, folder=False):
    """Write ``path`` atomically through a temporary name beside it: the context yields that name (a file, or with
    ``folder=True`` an empty folder) to write to; when the block ends normally its content is made durable, it gets
    the permissions a plain ``open()`` / ``mkdir`` would give, and it is renamed over ``path`` (an existing folder
    is replaced); when the block raises, it is removed and ``path`` keeps its old content. The parent folder must
    exist.

    Example:
        >>> import tempfile
        >>> target = os.path.join(tempfile.mkdtemp(), "a.txt")
        >>> with atomic_output(target) as tmp:
        ...     with open(tmp, "w") as handle:
        ...         _ = handle.write("done")
        >>> open(target).read()
        'done'
    """
    path = check_path("path", path)
    directory = os.path.dirname(os.path.abspath(path))
    prefix = f".{os.path.basename(path)}."
    if folder:
        tmp = tempfile.mkdtemp(prefix=prefix, suffix=".tmp", dir=directory)
    else:
        fd, tmp = tempfile.mkstemp(prefix=prefix, suffix=".tmp", dir=directory)
        os.close(fd)
    try:
        yield tmp
        if folder:
            os.chmod(tmp, _DIR_MODE)                       # mkdtemp makes a private (0700) folder
            if os.path.isdir(path):
                shutil.rmtree(path)
        else:
            with open(tmp, "rb+") as handle:
                os.fsync(handle.fileno())
            os.chmod(tmp, _FILE_MODE)                      # mkstemp makes a private (0600) file
        os.replace(tmp, path)
    except BaseException:
        if folder:
            shutil.rmtree(tmp, ignore_errors=True)
        else:
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


def atomic_write_bytes(path, data):
    """Write ``data`` to ``path`` atomically (:func:`atomic_output`: temporary file in the same folder, fsync,
    :func:`os.replace`).

    Readers see either the old file or the complete new one, never a partial file; on any error the
    temporary file is removed and the error is re-raised. The folder must exist.

    Args:
        path: destination file (``str`` or ``os.PathLike``).
        data: the complete file content (``bytes``, ``bytearray`` or ``memoryview``).
    """
    path = check_path("path", path)
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise TypeError(f"data: expected bytes, got {describe(data)}")
    with atomic_output(path) as tmp:
        with open(tmp, "wb") as handle:
            handle.write(data)


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
    path = check_path("path", path, (".exr",))
    array = _as_rgb_image("image", image)
    largest = float(np.abs(array).max())
    if largest > float(np.finfo(np.float32).max):
        raise ValueError(f"image has values outside the float32 range (largest magnitude {largest:.3g})")
    array = array.astype(np.float32)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    buffer = _stdio.BytesIO()
    OpenEXR.File(header, {"RGB": np.ascontiguousarray(array)}).write(buffer)
    atomic_write_bytes(path, buffer.getvalue())


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
    path = check_path("path", path, (".png",))
    if isinstance(bits, bool) or not isinstance(bits, (int, np.integer)):
        raise TypeError(f"bits: expected the int 8 or 16, got {describe(bits)}")
    if bits not in (8, 16):
        raise ValueError(f"bits: expected 8 or 16, got {bits}")
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
    """Read an 8- or 16-bit PNG (or any image :func:`read_image` reads) as RGB ``float32``.

    ``read_image(path, space="linear" if linear else "srgb")``: greyscale is repeated over the three channels,
    alpha is dropped, palette images are expanded; truncated or corrupt files are refused.

    Args:
        path: an existing image file.
        linear: return linear RGB (decoded with :func:`~torch_appearance.color.srgb_to_linear`); with
            ``False`` return the stored sRGB values scaled to ``[0, 1]``.

    Returns:
        ``numpy.ndarray`` of shape ``(H, W, 3)``, dtype ``float32``, values in ``[0, 1]``.

    Raises:
        FileNotFoundError: ``path`` does not exist.
        ValueError: the file cannot be decoded completely (truncated, corrupt, not an image).
    """
    if not isinstance(linear, bool):
        raise TypeError(f"linear: expected a bool, got {describe(linear)}")
    return read_image(path, space="linear" if linear else "srgb")


# --------------------------------------------------------------------------------------------------------------
# image input: the one reader (PNG, JPEG, TIFF, BMP, WebP, OpenEXR)
# --------------------------------------------------------------------------------------------------------------
IMAGE_FORMATS = ("PNG", "JPEG", "TIFF", "BMP", "WEBP", "OpenEXR")
_PILLOW_SETTINGS = threading.Lock()


def _sniff_format(head):
    """The image format named by a file's first bytes (its magic number), or None."""
    if head.startswith(b"\x89PNG\r\n\x1a\n"):
        return "PNG"
    if head.startswith(b"\xff\xd8\xff"):
        return "JPEG"
    if head.startswith((b"II*\x00", b"MM\x00*")):
        return "TIFF"
    if head.startswith(b"v/1\x01"):
        return "OpenEXR"
    if head.startswith(b"BM"):
        return "BMP"
    if head.startswith(b"RIFF") and head[8:12] == b"WEBP":
        return "WEBP"
    return None


def _decode_exr(data, path, name):
    """(H, W, C) float32 planes R, G, B(, A) or Y(, A) of the first part of an EXR held in ``data``."""
    try:
        exr = OpenEXR.File(_stdio.BytesIO(data), separate_channels=True)  # reads (decompresses) every pixel
        channels = {key: np.asarray(channel.pixels) for key, channel in exr.channels().items()}
    except Exception as error:  # OpenEXR raises RuntimeError / ValueError for damaged files
        raise ValueError(f"{name}: {path!r} is not a readable OpenEXR file (truncated or corrupt: "
                         f"{type(error).__name__}: {error})") from None
    if all(key in channels for key in "RGB"):
        keys = ["R", "G", "B"]
    elif "Y" in channels:
        keys = ["Y"]
    else:
        missing = [key for key in "RGB" if key not in channels]
        raise ValueError(f"{name}: EXR file {path!r} lacks channel(s) {', '.join(missing)} (or Y for a grey "
                         f"image); it has {sorted(channels)}")
    if "A" in channels:
        keys.append("A")
    planes = []
    for key in keys:
        pixels = channels[key]
        if not np.issubdtype(pixels.dtype, np.floating):
            raise ValueError(f"{name}: EXR file {path!r}: channel {key} has dtype {pixels.dtype}, expected half "
                             f"or float")
        planes.append(pixels.astype(np.float32, copy=False))
    return np.stack(planes, axis=-1)


@contextlib.contextmanager
def strict_pillow():
    """Within this block Pillow refuses truncated files (``ImageFile.LOAD_TRUNCATED_IMAGES = False``, whatever a
    library set globally), has no decompression-bomb limit (a user's own scans may exceed its 179 Mpx guard;
    OpenCV's 2**30-pixel limit still applies to :func:`read_image`) and its warnings are silenced (the errors say
    more). Pillow's settings are globals: they are restored afterwards, and one such block runs at a time."""
    from PIL import Image, ImageFile

    with _PILLOW_SETTINGS:
        truncated, limit = ImageFile.LOAD_TRUNCATED_IMAGES, Image.MAX_IMAGE_PIXELS
        ImageFile.LOAD_TRUNCATED_IMAGES, Image.MAX_IMAGE_PIXELS = False, None
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                yield
        finally:
            ImageFile.LOAD_TRUNCATED_IMAGES, Image.MAX_IMAGE_PIXELS = truncated, limit


def _pillow_message(error):
    """Pillow's error text without the repr of the in-memory buffer it read from."""
    return re.sub(r"\s*<_io\.BytesIO object at 0x[0-9a-fA-F]+>", "", str(error))


def _decode_raster(data, path, name, fmt):
    """(pixels, header size (W, H), ICC profile bytes or None) of a PNG/JPEG/TIFF/BMP/WebP held in ``data``.

    Pillow checks the file first, with truncated loading off whatever the global setting: ``verify()`` (for PNG:
    every chunk's CRC up to the IEND chunk) and ``load()`` (decodes every pixel; a truncated or broken data stream
    raises). OpenCV then decodes the pixels, since Pillow reduces 16-bit RGB to 8 bits; its size must match the
    header's.
    """
    from PIL import Image

    try:
        with strict_pillow():
            with Image.open(_stdio.BytesIO(data)) as image:
                size, icc = tuple(image.size), image.info.get("icc_profile")
                image.verify()
            with Image.open(_stdio.BytesIO(data)) as image:
                image.load()
    except Exception as error:  # Pillow raises OSError, SyntaxError, UnidentifiedImageError, ... for broken files
        tiff = _decode_tiff(data) if fmt == "TIFF" else None  # Pillow reads no RGB float TIFF: tifffile does
        if tiff is None:
            raise ValueError(f"{name}: {path!r} is a truncated or corrupt {fmt} file; it cannot be decoded "
                             f"completely ({type(error).__name__}: {_pillow_message(error)})") from None
        return tiff
    pixels = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    if pixels is None:
        raise ValueError(f"{name}: cannot decode {path!r}: OpenCV refuses this {fmt} file (truncated or corrupt?)")
    if pixels.shape[:2] != (size[1], size[0]):
        raise ValueError(f"{name}: {path!r}: decoded {pixels.shape[1]}×{pixels.shape[0]} pixels, but the {fmt} "
                         f"header says {size[0]}×{size[1]}")
    if pixels.ndim == 2:
        pixels = pixels[..., None]
    elif pixels.shape[2] in (3, 4):
        pixels = np.concatenate([pixels[..., 2::-1], pixels[..., 3:]], axis=2)  # B, G, R(, A) -> R, G, B(, A)
    return pixels, size, icc


def _decode_tiff(data):
    """(pixels, (W, H), ICC profile or None) of the first page of a TIFF that tifffile decodes completely (every strip
    or tile read, the shape its header promises), else None. Pillow opens no multi-channel floating-point TIFF (as
    written by OpenCV, ImageJ, microscopy software), tifffile does."""
    import tifffile

    quiet = logging.getLogger("tifffile")
    level = quiet.level
    quiet.setLevel(logging.CRITICAL)  # a broken file is reported once, by the caller, not also by tifffile's log
    try:
        with tifffile.TiffFile(_stdio.BytesIO(data)) as tif:
            page = tif.pages[0]
            expected, pixels = tuple(page.shape), page.asarray()
            icc = page.tags.get("InterColorProfile")
            icc = bytes(icc.value) if icc is not None else None
    except Exception:  # tifffile raises ValueError, TiffFileError, IndexError, ... for broken files
        return None
    finally:
        quiet.setLevel(level)
    if pixels.size == 0 or tuple(pixels.shape) != expected or pixels.ndim not in (2, 3):
        return None
    if pixels.ndim == 2:
        pixels = pixels[..., None]
    if pixels.shape[2] > 4:
        return None
    return np.ascontiguousarray(pixels), (pixels.shape[1], pixels.shape[0]), icc


def decode_image(path, *, name="path"):
    """Decode an image file completely, refusing truncated or corrupt files; the pixels as stored.

    The format is taken from the file's first bytes, not its suffix: PNG, JPEG, TIFF, BMP, WebP (via Pillow's
    integrity checks and OpenCV's decoder) and OpenEXR. Only the first page / frame / part is read; EXIF orientation
    is not applied (pixels as stored). This is the package's one image decoder; most callers want
    :func:`read_image`, which converts colour spaces.

    Args:
        path: an existing image file (``str`` or ``os.PathLike``).
        name: the argument name used in error messages (e.g. ``"target"``, ``"--fixed mask"``).

    Returns:
        ``(pixels, info)``: ``pixels`` of shape ``(H, W, C)``, C = 1 (grey), 2 (grey + alpha), 3 (RGB) or 4
        (RGBA), channels in that order, dtype ``uint8`` / ``uint16`` as stored for integer images or ``float32``
        for EXR and floating-point TIFF; palette images come expanded to RGB(A). ``info``: dict with ``format``
        (one of :data:`IMAGE_FORMATS`), ``bits`` (8, 16 or 32), ``encoding`` (``"srgb"`` for integer images,
        ``"linear"`` for floating-point ones), ``alpha`` (bool) and ``icc_profile`` (True when the file embeds
        one; it is not applied).

    Raises:
        TypeError: ``path`` is not a ``str`` / ``os.PathLike``.
        FileNotFoundError: ``path`` does not exist.
        ValueError: not one of the formats above, truncated or corrupt (naming the file), an EXR without R, G,
            B (or Y) channels, an unsupported sample type (e.g. 32-bit integer).
    """
    pixels, info, _ = _decode(path, name)
    return pixels, info


def _decode(path, name):
    """:func:`decode_image`, plus the embedded ICC profile (bytes or None)."""
    if not isinstance(name, str):
        raise TypeError(f"name: expected a str, got {describe(name)}")
    path = check_path(name, path)
    if not os.path.exists(path):
        raise FileNotFoundError(f"{name}: no such file {path!r}")
    if os.path.isdir(path):
        raise ValueError(f"{name}: expected an image file, got the folder {path!r}")
    with open(path, "rb") as handle:
        data = handle.read()
    return _decode_data(data, path, name)


def _decode_data(data, path, name):
    """:func:`_decode` of the file content ``data``; ``path`` names it in messages."""
    fmt = _sniff_format(data[:16])
    if fmt is None:
        what = "an empty file" if not data else f"a file that starts with {data[:8]!r}"
        raise ValueError(f"{name}: cannot decode {path!r}: expected a {', '.join(IMAGE_FORMATS)} image, got {what}")
    icc = None
    if fmt == "OpenEXR":
        pixels = _decode_exr(data, path, name)
    else:
        pixels, _, icc = _decode_raster(data, path, name, fmt)
    if pixels.dtype == np.uint8:
        bits, encoding = 8, "srgb"
    elif pixels.dtype == np.uint16:
        bits, encoding = 16, "srgb"
    elif pixels.dtype in (np.float32, np.float16, np.float64):
        pixels, bits, encoding = pixels.astype(np.float32, copy=False), 32, "linear"
    else:
        raise ValueError(f"{name}: {path!r} has {pixels.dtype} samples; expected 8- or 16-bit integers or floats")
    if pixels.shape[0] == 0 or pixels.shape[1] == 0 or pixels.shape[2] not in (1, 2, 3, 4):
        raise ValueError(f"{name}: {path!r} decodes to an unsupported shape {tuple(pixels.shape)}")
    info = {"format": fmt, "bits": bits, "encoding": encoding, "alpha": pixels.shape[2] in (2, 4),
            "icc_profile": bool(icc)}
    return np.ascontiguousarray(pixels), info, icc


def read_image(path, *, space="linear", alpha="drop", name="path"):
    """Read an image file as RGB ``float32``, converting its colour encoding explicitly.

    The one image reader of the package: targets, photos, textures, masks and environment maps go through it
    (via :func:`decode_image`), so a truncated or corrupt file is refused with a ``ValueError`` naming it, never
    half-read.

    Conversions:

    * 8- and 16-bit images (PNG, JPEG, TIFF, BMP, WebP) are taken as **sRGB**-encoded: the stored value ``v`` is
      scaled to ``v / (2**bits - 1)`` and, for ``space="linear"``, decoded with
      :func:`~torch_appearance.color.srgb_to_linear`. An embedded ICC profile is not applied (a warning says so
      when it is not an sRGB profile).
    * EXR and floating-point TIFF files are taken as **linear** RGB and returned as stored (not clipped); for
      ``space="srgb"`` they are encoded with :func:`~torch_appearance.color.linear_to_srgb`.
    * Grey images are repeated over R, G, B; palette images are expanded to their colours.
    * Alpha is never multiplied in: ``alpha="drop"`` ignores it, ``alpha="mask"`` returns it as a second array
      (stored value scaled to ``[0, 1]``; all ones for an image without alpha).

    Args:
        path: an existing image file (``str`` or ``os.PathLike``).
        space: ``"linear"`` (linear RGB) or ``"srgb"`` (sRGB-encoded values in ``[0, 1]`` for integer images).
        alpha: ``"drop"`` or ``"mask"``.
        name: the argument name used in error messages.

    Returns:
        RGB of shape ``(H, W, 3)``, ``float32`` (in ``[0, 1]`` for integer images); with ``alpha="mask"`` the pair
        ``(rgb, alpha)`` with ``alpha`` of shape ``(H, W)``, ``float32``.

    Raises:
        TypeError: wrong argument types.
        FileNotFoundError: ``path`` does not exist.
        ValueError: a bad ``space`` / ``alpha``, or any reason of :func:`decode_image`.

    Example:
        >>> rgb = read_image("photo.jpg")                       # doctest: +SKIP
        >>> srgb, a = read_image("logo.png", space="srgb", alpha="mask")  # doctest: +SKIP
    """
    _check_conversion(space, alpha)
    return _convert(*_decode(path, name), path, name, space, alpha)


def read_image_bytes(data, *, source, space="linear", alpha="drop", name="image"):
    """:func:`read_image` of an image file held in memory (e.g. a texture embedded in a GLB).

    Args:
        data: the complete file content (``bytes``, ``bytearray`` or ``memoryview``).
        source: where the bytes came from (a ``str`` used in error messages, e.g. ``"'cube.glb' (texture 0)"``).
        space, alpha, name: as :func:`read_image`.

    Returns, Raises:
        as :func:`read_image`.
    """
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise TypeError(f"data: expected bytes, got {describe(data)}")
    for arg, value in (("source", source), ("name", name)):
        if not isinstance(value, str):
            raise TypeError(f"{arg}: expected a str, got {describe(value)}")
    _check_conversion(space, alpha)
    return _convert(*_decode_data(bytes(data), source, name), source, name, space, alpha)


def _profile_description(icc):
    """The description of an embedded ICC profile ("?" when it cannot be parsed)."""
    try:
        from PIL import ImageCms

        return str(ImageCms.ImageCmsProfile(_stdio.BytesIO(icc)).profile.profile_description or "?")
    except Exception:  # a damaged or unusual profile: say so in the warning rather than fail the read
        return "?"


def _check_conversion(space, alpha):
    check_choice("space", space, ("linear", "srgb"))
    check_choice("alpha", alpha, ("drop", "mask"))


@functools.lru_cache(maxsize=4)
def _integer_table(bits, space):
    """``float32`` value of every ``bits``-bit level ``k``: ``k / (2**bits - 1)`` (``"srgb"``) or its sRGB decoding
    (``"linear"``, :func:`~torch_appearance.color.srgb_to_linear`), computed in float64."""
    levels = np.arange(2 ** bits, dtype=np.float64) / float(2 ** bits - 1)
    if space == "linear":
        levels = srgb_to_linear(torch.from_numpy(levels)).numpy()
    table = levels.astype(np.float32)
    table.flags.writeable = False
    return table


def _convert(pixels, info, icc, path, name, space, alpha):
    """The colour conversion of :func:`read_image` applied to decoded pixels."""
    if icc:
        description = _profile_description(icc)
        if "srgb" not in description.lower():
            warnings.warn(f"{name}: {path!r} embeds the colour profile {description!r}, not sRGB; the profile is "
                          f"ignored and the pixels are read as sRGB", stacklevel=3)
    channels = pixels.shape[2]
    colour = pixels[..., :3] if channels >= 3 else np.repeat(pixels[..., :1], 3, axis=2)
    if info["encoding"] == "srgb":
        scale = float(2 ** info["bits"] - 1)
        values = _integer_table(info["bits"], space)[colour]  # exact: one float64 evaluation per integer level
    else:
        values = colour
        if space == "srgb":
            values = linear_to_srgb(torch.from_numpy(colour.astype(np.float64))).numpy()
        scale = 1.0
    rgb = np.ascontiguousarray(values, dtype=np.float32)
    if alpha == "drop":
        return rgb
    if info["alpha"]:
        mask = pixels[..., -1].astype(np.float64) / scale
    else:
        mask = np.ones(pixels.shape[:2])
    return rgb, np.ascontiguousarray(mask, dtype=np.float32)


def read_mask(path, *, name="mask", threshold=0.5):
    """Read a black-and-white mask image as a boolean array.

    The grey value is the stored (sRGB-encoded) value scaled to ``[0, 1]``; an RGB image is reduced to grey with
    the Rec. 601 luma weights ``0.299 R + 0.587 G + 0.114 B`` (what OpenCV's greyscale reading uses), an EXR's
    linear values are used as stored. Alpha is ignored; read it with ``read_image(path, alpha="mask")``.

    Args:
        path: an existing image file (any format :func:`read_image` reads).
        name: the argument name used in error messages.
        threshold: pixels whose grey value is above this are True.

    Returns:
        ``numpy.ndarray`` of shape ``(H, W)``, dtype ``bool``.

    Raises:
        FileNotFoundError, ValueError: as :func:`read_image`.
    """
    if isinstance(threshold, bool) or not isinstance(threshold, (int, float)) or not math.isfinite(threshold):
        raise TypeError(f"threshold: expected a finite number, got {threshold!r}")
    pixels, info = decode_image(path, name=name)
    scale = float(2 ** info["bits"] - 1) if info["encoding"] == "srgb" else 1.0
    if pixels.shape[2] >= 3:
        grey = pixels[..., :3].astype(np.float64) @ np.array([0.299, 0.587, 0.114])
    else:
        grey = pixels[..., 0].astype(np.float64)
    return grey / scale > threshold


def read_exr(path, *, name="path"):
    """Read a linear OpenEXR file (first part) as RGB ``float32``; other formats are refused.

    ``R``, ``G``, ``B`` channels (half floats widened to ``float32``), or a ``Y`` channel repeated over R, G, B;
    alpha and other channels (depth, ...) are ignored. A truncated or corrupt file is refused.

    Args:
        path: an existing ``.exr`` file.
        name: the argument name used in error messages.

    Returns:
        ``numpy.ndarray`` of shape ``(H, W, 3)``, dtype ``float32``.

    Raises:
        FileNotFoundError: ``path`` does not exist.
        ValueError: the file is not a readable EXR or lacks the ``R``, ``G``, ``B`` (or ``Y``) channels.
    """
    path = check_path(name, path)
    if os.path.isfile(path):
        with open(path, "rb") as handle:
            if _sniff_format(handle.read(16)) != "OpenEXR":
                raise ValueError(f"{name}: {path!r} is not a readable OpenEXR file (no EXR magic number)")
    return read_image(path, space="linear", name=name)


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
    path = check_path("path", path)
    try:
        text = json.dumps(obj, indent=indent, default=_json_default, allow_nan=False)
    except ValueError as error:
        raise ValueError(f"obj cannot be written as strict JSON (NaN or infinity?): {error}") from None
    atomic_write_bytes(path, (text + "\n").encode("utf-8"))



def read_json(path, *, name="path"):
    """The JSON value in ``path``; a missing, unreadable or malformed file is a ValueError naming ``name``."""
    try:
        with open(path, encoding="utf-8") as f:
            return json.load(f)
    except FileNotFoundError:
        raise ValueError(f"{name}: no such file {path!r}") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        raise ValueError(f"{name}: {path!r} is not a readable JSON file ({error})") from None


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
