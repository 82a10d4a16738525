"""One place for argument checks of the scene pieces, with one message style: ``name: expected X, got Y``."""
import math
import numbers

import numpy as np
import torch

__all__ = ["is_real", "is_int", "check_real", "check_int", "check_seed", "check_spp", "check_rgb", "check_vector3",
           "check_direction",
           "check_float_tensor"]


def is_real(x):
    return isinstance(x, numbers.Real) and not isinstance(x, bool)


def is_int(x):
    return isinstance(x, numbers.Integral) and not isinstance(x, bool)


def check_real(name, value, *, lo=-math.inf, hi=math.inf, lo_open=False, hi_open=False):
    """A finite real number in [lo, hi] (open ends on request); one-element tensors are accepted."""
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


def check_int(name, value, *, lo):
    """An int >= lo."""
    if not is_int(value):
        raise TypeError(f"{name}: expected an int, got {type(value).__name__}")
    if value < lo:
        raise ValueError(f"{name}: expected an int >= {lo}, got {value}")
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


def check_float_tensor(name, value, shape_desc, ndim=None, last=None):
    """A finite floating-point tensor (numpy arrays are converted), detached, on the CPU.

    Args:
        shape_desc: the expected shape in words for messages, e.g. "(N, 3)".
        ndim: expected number of dimensions, or None.
        last: expected size of the last dimension, or None.
    """
    if isinstance(value, np.ndarray):
        value = torch.from_numpy(np.ascontiguousarray(value))
    if not isinstance(value, torch.Tensor):
        raise TypeError(f"{name}: expected a torch.Tensor of shape {shape_desc}, got {type(value).__name__}")
    if not value.is_floating_point():
        raise TypeError(f"{name}: expected a floating-point tensor, got dtype {value.dtype}")
    if value.device.type != "cpu":
        raise ValueError(f"{name}: expected a CPU tensor (the tracer runs on the CPU), got device {value.device}")
    if (ndim is not None and value.dim() != ndim) or (last is not None and (value.dim() == 0 or value.shape[-1] != last)):
        raise ValueError(f"{name}: expected shape {shape_desc}, got {tuple(value.shape)}")
    if value.numel() == 0:
        raise ValueError(f"{name}: expected a non-empty tensor of shape {shape_desc}, got {tuple(value.shape)}")
    value = value.detach()
    if not all_finite(value):
        raise ValueError(f"{name}: expected finite values, got {int((~torch.isfinite(value)).sum())} NaN/Inf entries")
    return value


def all_finite(x, chunk=1 << 22):
    """Whether every value of ``x`` is finite, checked ``chunk`` values at a time (``torch.isfinite`` of a float
    tensor allocates ``|x|`` and a bool tensor of the whole size: 1.8 GB for a 364 M-value float32 grid)."""
    flat = x.reshape(-1)
    return all(bool(torch.isfinite(flat[a:a + chunk]).all()) for a in range(0, flat.numel(), chunk))
