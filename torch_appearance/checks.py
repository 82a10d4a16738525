"""Argument checks for the whole package, with one message style: ``name: expected X, got Y``.

Every public function of ``render``, ``nn``, ``geometry``, ``rings``, ``fabrication`` and the I/O and colour modules
refuses bad input here, before any work (and before C++). A check names the argument, says what was expected and
what was received, raises :class:`TypeError` for the wrong kind of object (not a number, not a tensor, wrong dtype)
and :class:`ValueError` for the right kind with a wrong value (shape, range, non-finite entries, device), and
returns the value normalised (a float, an int, a tuple, a detached CPU tensor) so callers keep what it returns.

This module sits at the bottom of the layering, beside :mod:`torch_appearance.color`: it imports nothing from the
package. Domain checks (a loss pair of one shape, an ink set, a glTF texture) stay beside their code, built on these.

>>> check_real("g", 0.5, lo=-1.0, hi=1.0, lo_open=True, hi_open=True)
0.5
>>> check_int("spp", 0, lo=1)
Traceback (most recent call last):
...
ValueError: spp: expected an int >= 1, got 0
"""
import math
import numbers
import os

import numpy as np
import torch

__all__ = ["is_real", "is_int", "all_finite", "describe", "check_real", "check_positive", "check_int",
           "check_odd_int", "check_seed", "check_spp", "check_choice", "check_path", "check_rgb", "check_vector3",
           "check_direction", "check_device", "check_tensor", "check_float_tensor", "check_finite",
           "check_image_shape", "check_point_in_image"]


def describe(value):
    """How a message shows a received object: its type name (``describe([1]) == 'list'``)."""
    return type(value).__name__


def is_real(x):
    """Whether ``x`` is a real number (Python, NumPy scalar), not a bool."""
    return isinstance(x, numbers.Real) and not isinstance(x, bool)


def is_int(x):
    """Whether ``x`` is an integer (Python, NumPy scalar), not a bool."""
    return isinstance(x, numbers.Integral) and not isinstance(x, bool)


def check_real(name, value, *, lo=-math.inf, hi=math.inf, lo_open=False, hi_open=False):
    """A finite real number in [lo, hi] (open ends on request), returned as a float.

    One-element tensors and NumPy scalars are accepted.

    Raises:
        TypeError: not a real number (a bool, a string, None, a sequence).
        ValueError: NaN, ±inf, or outside the interval.

    >>> check_real("sigma", 1)
    1.0
    >>> check_real("sigma", 0.0, lo=0.0, lo_open=True)
    Traceback (most recent call last):
    ...
    ValueError: sigma: expected a finite value in (0, inf], got 0.0
    """
    if isinstance(value, torch.Tensor) and value.numel() == 1:
        value = value.item()
    if isinstance(value, np.generic):
        value = value.item()
    if not is_real(value):
        raise TypeError(f"{name}: expected a real number, got {type(value).__name__}")
    value = float(value)
    bad_lo = value <= lo if lo_open else value < lo
    bad_hi = value >= hi if hi_open else value > hi
    if not math.isfinite(value) or bad_lo or bad_hi:
        lo_s = ("(" if lo_open else "[") + f"{lo:g}"
        hi_s = f"{hi:g}" + (")" if hi_open else "]")
        raise ValueError(f"{name}: expected a finite value in {lo_s}, {hi_s}, got {value!r}")
    return value


def check_int(name, value, *, lo, hi=None):
    """An int in [lo, hi] (``hi`` None: no upper bound), returned as a Python int; NumPy integers are accepted.

    Raises:
        TypeError: not an integer (a bool and a float such as 3.0 are refused too).
        ValueError: below ``lo`` or above ``hi``.

    >>> check_int("views", 7, lo=1, hi=6)
    Traceback (most recent call last):
    ...
    ValueError: views: expected an int in [1, 6], got 7
    """
    if not is_int(value):
        raise TypeError(f"{name}: expected an int, got {describe(value)}")
    if hi is None and value < lo:
        raise ValueError(f"{name}: expected an int >= {lo}, got {value}")
    if hi is not None and not lo <= value <= hi:
        raise ValueError(f"{name}: expected an int in [{lo}, {hi}], got {value}")
    return int(value)


def check_positive(name, value):
    """A finite real number > 0 (a size, a scale, a standard deviation), returned as a float.

    >>> check_positive("pixel_size_mm", 0.1)
    0.1
    """
    return check_real(name, value, lo=0.0, lo_open=True)


def check_odd_int(name, value, *, lo=1):
    """An odd int >= ``lo`` (a filter window side), returned as a Python int.

    >>> check_odd_int("window", 4)
    Traceback (most recent call last):
    ...
    ValueError: window: expected an odd int >= 1, got 4
    """
    if not is_int(value):
        raise TypeError(f"{name}: expected an odd int, got {describe(value)}")
    if value < lo or value % 2 == 0:
        raise ValueError(f"{name}: expected an odd int >= {lo}, got {value}")
    return int(value)


def check_seed(name, seed):
    """A 64-bit seed: an int in [−2⁶³, 2⁶⁴)."""
    if not is_int(seed):
        raise TypeError(f"{name}: expected an int, got {type(seed).__name__}")
    if not -2 ** 63 <= seed < 2 ** 64:
        raise ValueError(f"{name}: expected a 64-bit integer, got {seed}")
    return int(seed)


def check_spp(spp):
    """Samples per sensor element: an int in [1, 2³²)."""
    spp = check_int("spp", spp, lo=1)
    if spp >= 2 ** 32:
        raise ValueError(f"spp: expected < 2**32, got {spp}")
    return spp


def check_choice(name, value, choices, *, kind=None):
    """One of ``choices`` (names, usually strings), returned unchanged.

    Args:
        kind: optional type (e.g. ``str``) that ``value`` must have; without it every wrong value is a ValueError.

    Raises:
        TypeError: ``kind`` is given and ``value`` is not an instance of it.
        ValueError: ``value`` is not among the choices.

    >>> check_choice("space", "srgb", ("linear", "srgb"))
    'srgb'
    >>> check_choice("space", "rgb", ("linear", "srgb"))
    Traceback (most recent call last):
    ...
    ValueError: space: expected one of ('linear', 'srgb'), got 'rgb'
    """
    choices = tuple(choices)
    if kind is not None and not isinstance(value, kind):
        raise TypeError(f"{name}: expected one of {choices}, got {describe(value)}")
    if value not in choices:
        raise ValueError(f"{name}: expected one of {choices}, got {value!r}")
    return value


def check_device(name, value):
    """A device the tracer runs on: ``"cpu"``, ``"cuda"``, ``"cuda:N"`` or such a :class:`torch.device`, returned as
    a :class:`torch.device` (whether a GPU is there is the caller's question: this checks the spelling).

    >>> check_device("device", "cuda:1")
    device(type='cuda', index=1)
    >>> check_device("device", "tpu")
    Traceback (most recent call last):
    ...
    ValueError: device: expected 'cpu', 'cuda' or 'cuda:N', got 'tpu'
    """
    if not isinstance(value, (str, torch.device)):
        raise TypeError(f"{name}: expected 'cpu', 'cuda' or 'cuda:N', got {describe(value)}")
    try:
        device = torch.device(value)
    except (RuntimeError, TypeError, ValueError):
        device = None
    if device is None or device.type not in ("cpu", "cuda"):
        raise ValueError(f"{name}: expected 'cpu', 'cuda' or 'cuda:N', got {str(value)!r}")
    return device


def check_path(name, path, suffixes=None):
    """A file-system path (``str`` or ``os.PathLike`` of str, non-empty), returned as a ``str``.

    Args:
        suffixes: optional tuple of accepted endings, compared case-insensitively (e.g. ``(".png", ".exr")``).

    Raises:
        TypeError: not a str or os.PathLike, or a bytes path.
        ValueError: empty, or a wrong ending.

    >>> check_path("path", "out.EXR", (".exr",))
    'out.EXR'
    """
    if not isinstance(path, (str, os.PathLike)):
        raise TypeError(f"{name}: expected a str or os.PathLike, got {describe(path)}")
    path = os.fspath(path)
    if isinstance(path, bytes):
        raise TypeError(f"{name}: expected a str path, got bytes")
    if not path:
        raise ValueError(f"{name}: expected a non-empty path, got ''")
    if suffixes is not None and not path.lower().endswith(tuple(suffixes)):
        raise ValueError(f"{name}: expected a path ending with {' or '.join(suffixes)}, got {path!r}")
    return path


def _as_list(name, value, what):
    if isinstance(value, (torch.Tensor, np.ndarray)):
        return [float(v) for v in value.reshape(-1).tolist()]
    if isinstance(value, (tuple, list)):
        return list(value)
    raise TypeError(f"{name}: expected {what}, got {type(value).__name__}")


def check_rgb(name, value, *, lo=0.0):
    """A scalar (grey) or 3 linear-RGB values, each finite and >= lo; returned as a 3-tuple of floats."""
    if is_real(value) or (isinstance(value, (torch.Tensor, np.ndarray)) and np.size(value) == 1):
        v = check_real(name, value if is_real(value) else float(np.asarray(value).reshape(-1)[0]), lo=lo)
        return (v, v, v)
    values = _as_list(name, value, "a scalar or 3 RGB values")
    if len(values) != 3:
        raise ValueError(f"{name}: expected a scalar or 3 RGB values, got {len(values)} values")
    return tuple(check_real(name, v, lo=lo) for v in values)


def check_vector3(name, value):
    """Three finite reals (a point or a vector in mm); returned as a 3-tuple of floats."""
    values = _as_list(name, value, "3 numbers (x, y, z)")
    if len(values) != 3:
        raise ValueError(f"{name}: expected 3 numbers (x, y, z), got {len(values)} values")
    return tuple(check_real(name, v) for v in values)


def check_direction(name, value):
    """A non-zero 3-vector, returned normalised to unit length."""
    v = check_vector3(name, value)
    norm = math.sqrt(sum(c * c for c in v))
    if not norm > 1e-12:
        raise ValueError(f"{name}: expected a non-zero direction, got {v}")
    return tuple(c / norm for c in v)


_DTYPE_KINDS = {"floating": "a floating-point dtype", "integer": "an integer dtype"}


def _dtype_ok(dtype, dtypes):
    if dtypes == "floating":
        return dtype.is_floating_point
    if dtypes == "integer":
        return not dtype.is_floating_point and not dtype.is_complex and dtype != torch.bool
    return dtype in dtypes


def check_tensor(name, value, shape_desc, *, ndim=None, last=None, dtypes=None, numpy=False, cpu=False,
                 nonempty=False):
    """A tensor of the given number of dimensions, last dimension and dtypes, returned as given (not detached).

    Args:
        shape_desc: the expected shape in words, for messages, e.g. ``"(N, 3)"`` or ``"(H, W) or (B, H, W)"``.
        ndim: the accepted number(s) of dimensions: an int, a tuple of ints, or None (any).
        last: the expected size of the last dimension, or None.
        dtypes: None (any), ``"floating"`` (real floating point), ``"integer"`` (no bool), or a tuple of
            ``torch.dtype``.
        numpy: accept a ``numpy.ndarray`` too (converted with :func:`torch.from_numpy`, no copy).
        cpu: refuse tensors on other devices.
        nonempty: refuse tensors with no element.

    Raises:
        TypeError: not a tensor (or array, with ``numpy``), or a dtype outside ``dtypes``.
        ValueError: the wrong number of dimensions or last size, another device, no element.

    >>> check_tensor("points", torch.zeros(4, 3), "(N, 3)", ndim=2, last=3).shape
    torch.Size([4, 3])
    >>> check_tensor("points", torch.zeros(4, 2), "(N, 3)", ndim=2, last=3)
    Traceback (most recent call last):
    ...
    ValueError: points: expected shape (N, 3), got (4, 2)
    """
    if numpy and isinstance(value, np.ndarray):
        value = torch.from_numpy(np.ascontiguousarray(value))
    if not isinstance(value, torch.Tensor):
        kind = "a torch.Tensor or numpy.ndarray" if numpy else "a torch.Tensor"
        raise TypeError(f"{name}: expected {kind} of shape {shape_desc}, got {describe(value)}")
    if dtypes is not None and not _dtype_ok(value.dtype, dtypes):
        want = _DTYPE_KINDS.get(dtypes) if isinstance(dtypes, str) else \
            "dtype " + " or ".join(str(d) for d in dtypes)
        raise TypeError(f"{name}: expected {want}, got {value.dtype}")
    if cpu and value.device.type != "cpu":
        raise ValueError(f"{name}: expected a CPU tensor (a scene's own tensors stay on the CPU; a render on a GPU "
                         f"copies them there), got device {value.device}")
    ndims = (ndim,) if isinstance(ndim, int) else ndim
    if (ndims is not None and value.dim() not in ndims) or \
            (last is not None and (value.dim() == 0 or value.shape[-1] != last)):
        raise ValueError(f"{name}: expected shape {shape_desc}, got {tuple(value.shape)}")
    if nonempty and value.numel() == 0:
        raise ValueError(f"{name}: expected a non-empty tensor of shape {shape_desc}, got {tuple(value.shape)}")
    return value


def check_float_tensor(name, value, shape_desc, ndim=None, last=None):
    """A finite, non-empty floating-point tensor (numpy arrays are converted), detached, on the CPU.

    Args:
        shape_desc: the expected shape in words for messages, e.g. "(N, 3)".
        ndim: expected number of dimensions, or None.
        last: expected size of the last dimension, or None.

    Raises:
        TypeError: not a tensor or array, or not a floating dtype.
        ValueError: another device, the wrong shape, no element, NaN/Inf entries.
    """
    value = check_tensor(name, value, shape_desc, ndim=ndim, last=last, dtypes="floating", numpy=True, cpu=True,
                         nonempty=True).detach()
    return check_finite(name, value)


def check_finite(name, value):
    """Every entry of a tensor or array is finite; returns ``value``.

    Raises:
        ValueError: naming how many entries are NaN or ±inf.

    >>> check_finite("target", torch.tensor([0.0, float("nan")]))
    Traceback (most recent call last):
    ...
    ValueError: target: expected finite values, got 1 NaN/Inf entries
    """
    x = torch.from_numpy(np.asarray(value)) if isinstance(value, np.ndarray) else value.detach()
    if x.is_floating_point() or x.is_complex():
        if not all_finite(x):  # in chunks: no bool copy of a whole volume
            raise ValueError(f"{name}: expected finite values, got {int((~torch.isfinite(x)).sum())} NaN/Inf entries")
    return value


def check_image_shape(name, shape, *, channels=False, min_size=1):
    """An image shape ``(H, W)`` (or ``(H, W, C)`` with ``channels``) of ints >= ``min_size``, returned as (H, W).

    Raises:
        TypeError: not a tuple/list of that length, or entries that are not ints.
        ValueError: a side below ``min_size``.

    >>> check_image_shape("image_shape", (480, 640, 3), channels=True, min_size=2)
    (480, 640)
    >>> check_image_shape("image_shape", (1, 640), min_size=2)
    Traceback (most recent call last):
    ...
    ValueError: image_shape: expected (H, W) with H, W >= 2, got (1, 640)
    """
    want = "(H, W) or (H, W, C)" if channels else "(H, W)"
    if not isinstance(shape, (tuple, list, torch.Size)) or len(shape) not in ((2, 3) if channels else (2,)):
        raise TypeError(f"{name}: expected {want}, got {shape!r}")
    if not all(is_int(v) for v in shape):
        raise TypeError(f"{name}: expected {want} of ints, got {shape!r}")
    h, w = int(shape[0]), int(shape[1])
    if h < min_size or w < min_size:
        raise ValueError(f"{name}: expected {want} with H, W >= {min_size}, got {tuple(shape)}")
    return h, w


def check_point_in_image(name, point, shape):
    """A finite point ``(x, y)`` in pixels inside an image of ``shape`` (H, W, ...): x in [0, W-1], y in [0, H-1].

    Pixel centres sit at integer coordinates; x counts columns, y rows. Returned as a tuple of floats.

    Raises:
        ValueError: not two numbers, non-finite, or outside the image.

    >>> check_point_in_image("pith", (3, 2.5), (4, 5))
    (3.0, 2.5)
    >>> check_point_in_image("pith", (5, 0), (4, 5))
    Traceback (most recent call last):
    ...
    ValueError: pith: expected (x, y) inside the image (x in [0, 4], y in [0, 3]), got (5, 0)
    """
    try:
        x, y = (float(t) for t in point)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: expected two numbers (x, y) in pixels, got {point!r}") from None
    H, W = int(shape[0]), int(shape[1])
    if not (math.isfinite(x) and math.isfinite(y) and 0 <= x <= W - 1 and 0 <= y <= H - 1):
        raise ValueError(f"{name}: expected (x, y) inside the image (x in [0, {W - 1}], y in [0, {H - 1}]), "
                         f"got ({x:g}, {y:g})")
    return x, y


def all_finite(x, chunk=1 << 22):
    """Whether every value of ``x`` is finite, checked ``chunk`` values at a time (``torch.isfinite`` of a float
    tensor allocates ``|x|`` and a bool tensor of the whole size: 1.8 GB for a 364 M-value float32 grid)."""
    flat = x.reshape(-1)
    return all(bool(torch.isfinite(flat[a:a + chunk]).all()) for a in range(0, flat.numel(), chunk))
