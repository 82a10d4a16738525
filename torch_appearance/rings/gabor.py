"""Curved Gabor filters for growth-ring detection (thesis ch. 2, §3.2; Gottschlich, IEEE TIP 2012).

For every pixel a curved ``(2p+1) x (2q+1)`` patch is sampled that follows the ring orientation field: ``2p+1``
points along the curve through the pixel that runs *across* the rings (following the ring normal field, step 1 px),
and from each of them a contour of ``2q+1`` points traced *along* the rings (following the orientation field, step
1 px). In that patch the rings run horizontally, so a complex Gabor kernel (paper eqs. 1-4) with its carrier across
and a Gaussian envelope along the rings gives the local phase.

Only the response at the patch centre is needed and the kernel is separable, so the filter is evaluated in two
vectorised passes instead of sampling ``(2p+1)(2q+1)`` values per pixel:

1. *Along* (line-integral convolution): for every pixel ``x`` the Gaussian-weighted mean ``A(x)`` of the image over
   the ``2q+1`` points of the streamline of the orientation field through ``x`` (RK2, 1 px steps, both directions).
   The contour through each patch row is exactly the streamline through that row's start point, so the along-sum of
   row ``j`` equals ``A`` at that point.
2. *Across*: trace the normal curve of every pixel (RK2, ``p`` steps of 1 px both ways) and sample ``A`` there
   (bilinear), giving the along-averaged profile ``P_j``, ``j = -p..p``. The local frequency is the peak of its
   windowed spectrum; the complex response is ``R = 2 sum_j u_j (P_j - mean) exp(-2 pi i f j) / sum_j u_j`` with
   ``u_j`` the Gaussian across-envelope (times a validity weight near the image border).

``R`` is normalised so that for rings ``s(t) = a cos(2 pi f t + phi0)`` along the signed normal coordinate ``t``,
``R ~= a exp(i (2 pi f t + phi0))``: the magnitude is the ring amplitude in image units and the phase
``I_phi = atan2(Im R, Re R)`` in ``(-pi, pi]`` grows along the oriented normal (``GaborResult.normal``). Ring
boundaries (negative zero crossings of the cosine) are where ``I_phi = pi / 2``.

Normal sign: orientation is only defined mod pi, so the normal ``+-(-sin theta, cos theta)`` of every pixel is
oriented to have a non-negative dot product with one reference direction (by default the normal of the dominant ring
orientation of the image, pointing towards ``+y``). The sign is therefore continuous except where the rings are
exactly perpendicular to the dominant direction (e.g. at the tips of elongated arches). It is not enforced that the
phase grows outwards from the tree axis; for tangential boards the phase sign flips beyond the projected tree centre
(resolved by board estimation, :mod:`torch_appearance.rings.board`).
"""
from __future__ import annotations

import contextlib
import math
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from ..checks import check_tensor
from .orientation import _as_image, _check_params, _tensor_orientation, orientation_from_phase

__all__ = ["GaborResult", "curved_gabor", "curved_gabor_memory_bytes", "curved_gabor_seconds", "curved_gabor_response",
           "CurvedGaborFilter"]


@dataclass
class GaborResult:
    """Per-pixel output of :func:`curved_gabor`; every field is a float32 numpy array (``orientation`` None when not
    refined).

    Attributes:
        magnitude: ``(H, W)`` ``|R|``, the local ring amplitude in image intensity units.
        phase: ``(H, W)`` ``I_phi = atan2(Im R, Re R)`` in radians, in ``(-pi, pi]``; increases by ``2 pi`` per ring
            along ``normal``.
        frequency: ``(H, W)`` local ring frequency across the rings in cycles per pixel (ring spacing ``1/f`` px).
        curvature: ``(H, W)`` absolute ring curvature in radians per pixel (``1/R`` for circles of radius ``R`` px):
            turn of the orientation between the centre and the two ends of the along-contour, divided by ``q``.
        orientation: ``(H, W)`` refined ring orientation in ``[0, pi)`` computed from the phase image (None when
            :func:`curved_gabor` was asked not to, ``refine_orientation=False``).
        theta: ``(H, W)`` input ring orientation in ``[0, pi)`` used to build the curved patches.
        normal: ``(H, W, 2)`` unit ``(x, y)`` normal along which ``phase`` increases (the sign convention used).
    """

    magnitude: np.ndarray
    phase: np.ndarray
    frequency: np.ndarray
    curvature: np.ndarray
    orientation: np.ndarray
    theta: np.ndarray
    normal: np.ndarray


def _positive(value, name: str, *, allow_none: bool = False) -> float | None:
    if value is None and allow_none:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)) \
            or not math.isfinite(float(value)) or value <= 0:
        expected = "a finite number > 0 or None" if allow_none else "a finite number > 0"
        raise ValueError(f"{name} must be {expected} (pixels); got {value!r}")
    return float(value)


def _int_at_least(value, name: str, minimum: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum}; got {value!r}")
    return int(value)


class _Field:
    """Bilinear (or bicubic) sampling of a ``(C, H, W)`` field at pixel coordinates (pixel centres at integers).

    The field is padded by one pixel: channels listed in ``zero_pad`` with zeros (validity / weight channels, so that
    a sample returns the in-image fraction of its bilinear footprint), the others by replication. Sampling uses
    ``grid_sample(padding_mode="border", align_corners=True)``, i.e. positions far outside see the padded border.
    Positions are kept in normalised grid units ``g = (x + 1) * 2 / (W + 1) - 1`` (likewise ``y``) so that one
    interleaving copy builds the grid; :attr:`step` converts 1 px to grid units per axis.
    """

    def __init__(self, field: torch.Tensor, zero_pad: tuple[int, ...] = (), mode: str = "bilinear"):
        c, h, w = field.shape
        padded = F.pad(field[None], (1, 1, 1, 1), mode="replicate")
        for ch in zero_pad:
            padded[0, ch] = F.pad(field[ch], (1, 1, 1, 1))
        self.field = padded.contiguous()  # (1, C, H + 2, W + 2)
        self.channels = c
        self.mode = mode
        self.step = (2.0 / (w + 1), 2.0 / (h + 1))  # grid units per pixel in x and y

    def to_grid(self, x: torch.Tensor, y: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Pixel coordinates -> normalised grid coordinates of the padded field."""
        return (x + 1.0) * self.step[0] - 1.0, (y + 1.0) * self.step[1] - 1.0

    def __call__(self, gx: torch.Tensor, gy: torch.Tensor) -> torch.Tensor:
        """Grid coordinates ``(N,)``, ``(N,)`` -> ``(C, N)`` samples."""
        # view_as_real(complex(x, y)) interleaves much faster than stack(dim=-1) on CPU.
        grid = torch.view_as_real(torch.complex(gx, gy)).view(1, 1, -1, 2)
        out = F.grid_sample(self.field, grid, mode=self.mode, padding_mode="border", align_corners=True)
        return out.view(self.channels, -1)


def _direction(c2: torch.Tensor, s2: torch.Tensor, px: torch.Tensor, py: torch.Tensor, normal: bool):
    """Unit ring tangent (or normal) from a doubled-angle sample ``(cos 2t, sin 2t)``, sign-aligned with ``(px, py)``.

    The half angle of the (interpolated, not necessarily unit) doubled-angle vector is
    ``(sqrt((1 + c) / 2), sign(s) sqrt((1 - c) / 2))`` with ``c = c2 / |(c2, s2)|``.
    """
    c = c2 / torch.hypot(c2, s2).clamp_min_(1e-12)
    tx = c.mul(0.5).add_(0.5).clamp_(min=0.0).sqrt_()
    ty = torch.copysign(c.mul_(-0.5).add_(0.5).clamp_(min=0.0).sqrt_(), s2)
    if normal:
        tx, ty = ty.neg_(), tx
    sign = torch.copysign(torch.ones_like(tx), torch.addcmul(tx * px, ty, py))
    return tx.mul_(sign), ty.mul_(sign)


def _trace(full: _Field, dirs: _Field, gx, gy, dx, dy, first: torch.Tensor, steps: int, normal: bool):
    """Trace streamlines of the orientation (or normal) field with RK2 (midpoint rule), steps of 1 px arc length.

    Args:
        full: field whose channels 0, 1 are ``(cos 2 theta, sin 2 theta)``; further channels are payload.
        dirs: field of the two direction channels only (sampled at the midpoints).
        gx, gy: ``(N,)`` start points in grid units of ``full``/``dirs`` (same padding, same grid).
        dx, dy: ``(N,)`` unit start directions (pixels); only their sense matters (the walking direction).
        first: ``(C, N)`` ``full`` sampled at the start points.
        steps: number of steps; normal: follow the normal field instead of the tangent field.

    Yields:
        ``(k, samples (C, N), (dx, dy))`` after each step ``k = 1..steps``.
    """
    for k, cur, d, _ in _trace_positions(full, dirs, gx, gy, dx, dy, first, steps, normal):
        yield k, cur, d


def _trace_positions(full: _Field, dirs: _Field, gx, gy, dx, dy, first: torch.Tensor, steps: int, normal: bool):
    """:func:`_trace` that also yields the position reached, ``(k, samples, (dx, dy), (gx, gy))``, grid units."""
    sx, sy = full.step
    cur = first
    for k in range(1, steps + 1):
        d1x, d1y = _direction(cur[0], cur[1], dx, dy, normal)
        mid = dirs(torch.add(gx, d1x, alpha=0.5 * sx), torch.add(gy, d1y, alpha=0.5 * sy))
        dx, dy = _direction(mid[0], mid[1], d1x, d1y, normal)
        gx = torch.add(gx, dx, alpha=sx)
        gy = torch.add(gy, dy, alpha=sy)
        cur = full(gx, gy)
        yield k, cur, (dx, dy), (gx, gy)


@contextlib.contextmanager
def _parallel(device: torch.device, num_workers: int | None):
    """Run chunk functions on ``num_workers`` Python threads with single-threaded torch ops (CPU only).

    The per-step tensors are small (a chunk of pixels), so intra-op OpenMP parallelism is dominated by its
    synchronisation cost - catastrophically so when the cores are shared with other processes. Independent chunks
    on separate threads (torch releases the GIL inside ops) scale better. The global torch thread count is restored
    afterwards.
    """
    if device.type != "cpu":
        yield lambda fn, chunks: [fn(s, e) for s, e in chunks]
        return
    workers = max(1, torch.get_num_threads() if num_workers is None else num_workers)
    saved = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        if workers == 1:
            yield lambda fn, chunks: [fn(s, e) for s, e in chunks]
        else:
            with ThreadPoolExecutor(max_workers=workers) as pool:
                yield lambda fn, chunks: [f.result() for f in [pool.submit(fn, s, e) for s, e in chunks]]
    finally:
        torch.set_num_threads(saved)


def _dominant_period(img: torch.Tensor, f_min: float, f_max: float) -> float:
    """Dominant ring period (px) of an image: peak of its f-weighted, radially binned power spectrum."""
    h, w = img.shape
    win = torch.outer(torch.hann_window(h, periodic=False, device=img.device),
                      torch.hann_window(w, periodic=False, device=img.device))
    power = torch.fft.rfft2((img - img.mean()) * win).abs().square()
    f = torch.hypot(torch.fft.rfftfreq(w, device=img.device)[None, :], torch.fft.fftfreq(h, device=img.device)[:, None])
    edges = torch.logspace(math.log10(f_min), math.log10(f_max), 65, device=img.device)
    idx = torch.bucketize(f, edges) - 1
    ok = (idx >= 0) & (idx < 64)
    total = torch.zeros(64, device=img.device).index_add_(0, idx[ok], (power * f)[ok])
    count = torch.zeros(64, device=img.device).index_add_(0, idx[ok], torch.ones_like(f[ok]))
    k = int(torch.argmax(total / count.clamp_min(1)))
    return 1.0 / math.sqrt(float(edges[k]) * float(edges[k + 1]))


def _dominant_normal(c2: torch.Tensor, s2: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    """Unit normal of the weighted mean doubled-angle orientation, oriented towards +y (or +x)."""
    mc, ms = float((c2 * weight).sum()), float((s2 * weight).sum())
    theta = 0.5 * math.atan2(ms, mc) if (mc * mc + ms * ms) > 0 else 0.0
    n = np.array([-math.sin(theta), math.cos(theta)])
    if n[1] < -1e-12 or (abs(n[1]) <= 1e-12 and n[0] < 0):
        n = -n
    return torch.tensor(n, dtype=c2.dtype, device=c2.device)


#: bytes per element of a chunk's traced curves (``chunk_size * (2p+1)`` across, ``chunk_size * (2q+1)`` along)
CHUNK_BYTES_PER_SAMPLE = 40
#: bytes per image pixel of the results and the orientation field held beside them (about 15 float32 / float64
#: planes), with a margin
BYTES_PER_PIXEL = 160


def curved_gabor_memory_bytes(shape, p, q, device="cpu", chunk_size=16384, num_workers=None):
    """Memory in bytes that :func:`curved_gabor` of an image of ``shape`` (H, W) needs at its peak, estimated before
    the work: every worker's chunk of traced curves, :data:`CHUNK_BYTES_PER_SAMPLE` per sample of the longer of the
    across (``2p+1``) and along (``2q+1``) curves, and :data:`BYTES_PER_PIXEL` per pixel. A ``p`` or ``q`` far
    beyond the image's size makes the chunks, not the image, exhaust the memory.

    Example:
        >>> curved_gabor_memory_bytes((100, 100), p=100000, q=10, num_workers=1) > 50 * 2**30
        True
    """
    h, w = shape
    workers = 1 if torch.device(device).type != "cpu" else max(
        1, torch.get_num_threads() if num_workers is None else int(num_workers))
    pixels = int(h) * int(w)
    chunk = min(int(chunk_size), pixels)
    return workers * chunk * (2 * max(int(p), int(q)) + 1) * CHUNK_BYTES_PER_SAMPLE + pixels * BYTES_PER_PIXEL


#: seconds per pixel and step of the across curves (its trace and spectrum), per pixel and step of the along contours,
#: and per pixel besides, on one CPU thread; measured on synthetic boards of 96² and 192² px with p, q from 8 to 160
#: (within 15 % of the measured times; the cost is O(H W (p + q)), not O(H W p q))
SECONDS_PER_ACROSS_STEP = 0.55e-6
SECONDS_PER_ALONG_STEP = 0.13e-6
SECONDS_PER_PIXEL = 0.9e-6


def curved_gabor_seconds(shape, p, q, device="cpu", num_workers=None):
    """About how long :func:`curved_gabor` of an image of ``shape`` (H, W) takes on the CPU, in seconds, estimated
    before the work: ``H W (a p + b q + c) / workers`` with the constants measured on one thread
    (:data:`SECONDS_PER_ACROSS_STEP`, :data:`SECONDS_PER_ALONG_STEP`, :data:`SECONDS_PER_PIXEL`); None on another
    device (not measured there).

    Example:
        >>> round(curved_gabor_seconds((1000, 1000), p=80, q=80, num_workers=1))
        55
    """
    if torch.device(device).type != "cpu":
        return None
    workers = max(1, torch.get_num_threads() if num_workers is None else int(num_workers))
    h, w = shape
    return int(h) * int(w) * (SECONDS_PER_ACROSS_STEP * int(p) + SECONDS_PER_ALONG_STEP * int(q)
                              + SECONDS_PER_PIXEL) / workers


def curved_gabor(gray, theta=None, p: int = 80, q: int = 80, sigma_along: float | None = None,
                 sigma_across: float | None = None, device="cpu", *, freq_range: tuple[float, float] | None = None,
                 normal_reference=None, sigma_smooth: float | None = None, window: int | None = None, chunk_size: int = 16384,
                 num_workers: int | None = None, barrier=None, refine_orientation: bool = True
                 ) -> GaborResult:
    """Curved Gabor filter of a grayscale wood image: local ring phase, amplitude, frequency and curvature.

    See the module docstring for the algorithm and the phase / normal-sign conventions. Everything is vectorised
    over pixels (chunks of ``chunk_size``) with batched ``grid_sample``; cost is ``O(H W (p + q))``.

    Args:
        gray: ``(H, W)`` grayscale image (numpy or torch, any real dtype, H, W >= 2). Its scale is free; the
            magnitude is returned in the same units.
        theta: optional ``(H, W)`` ring orientation in radians (tangent, mod pi, ``[0, pi)`` by convention). If
            None it is computed with :func:`~torch_appearance.rings.orientation.orientation_field` using
            ``sigma_smooth`` and ``window``.
        p: half-length (pixels = steps) of the curve across the rings; the profile has ``2p+1`` samples.
        q: half-length (pixels = steps) of each contour along the rings (``2q+1`` samples).
        sigma_along: std (pixels, arc length) of the Gaussian envelope along the rings; default ``q / 3``.
        sigma_across: std (pixels) of the Gaussian envelope across the rings; default None: adaptive
            ``0.5 / f`` (half a local ring period), clipped to ``[1, p / 3]``.
        device: torch device for the computation (results are returned as numpy arrays).
        freq_range: ``(f_min, f_max)`` in cycles/px searched for the local frequency; default
            ``(1 / p, 0.25)`` (ring spacings from 4 px to ``p`` px). ``f_max <= 0.5``.
        normal_reference: optional ``(x, y)`` direction; every pixel's normal is oriented to have a non-negative
            dot product with it. Default: normal of the dominant (coherence-weighted) orientation, towards +y.
        sigma_smooth, window: orientation-field parameters (pixels), used for ``theta=None`` and for the refined
            ``orientation`` computed from the phase image. Default None: scaled to the dominant ring period ``P``
            of the image (peak of its radially binned power spectrum within ``freq_range``):
            ``sigma_smooth = clip(P / 20, 1, 4)``, ``window = odd(clip(0.7 P, 15, 61))`` - small windows pick up
            pores and rays instead of the rings on coarse-ringed photos; for ``P <= 20`` px this gives the
            :func:`~torch_appearance.rings.orientation.orientation_field` defaults ``(1, 15)``.
        chunk_size: pixels per chunk (memory per worker ~ ``chunk_size * (2p+1) * 40`` bytes in the across pass).
        num_workers: CPU threads working on separate chunks (each with single-threaded torch ops); default
            ``torch.get_num_threads()``. Ignored on other devices.
        barrier: optional ``(H, W)`` signed field (e.g. the signed distance to a board's projected tree centre
            line) that the across curves may not cross: from the first sample whose sign differs from the
            pixel's own, the rest of that half of the curve gets zero weight. Near a pith line the rings on its
            two sides are mirror images; a symmetric profile makes the response real there (phase 0 or π) and
            bends the phase of the innermost ring on both sides; with the barrier each side is filtered on its
            own. A pixel whose own value is 0 has no barrier (its curves see both sides). Default None: no
            barrier.
        refine_orientation: compute the refined ``orientation`` from the phase image
            (:func:`~torch_appearance.rings.orientation.orientation_from_phase`). False: ``orientation`` is None, and
            with ``theta`` given the dominant period (which only sets ``sigma_smooth`` / ``window``) is not
            estimated either; every other field is the same bit for bit (disc mode reads none of the two).

    Returns:
        :class:`GaborResult` with ``(H, W)`` float32 arrays (``normal`` is ``(H, W, 2)``; ``orientation`` None when
        not ``refine_orientation``).

    Raises:
        TypeError: ``gray`` / ``theta`` are not real numeric arrays or tensors.
        ValueError: wrong shapes (not ``(H, W)``, mismatched ``theta``), empty or tiny images, non-finite values,
            ``p`` or ``q`` < 1, non-positive sigmas or chunk size, invalid ``freq_range`` / ``normal_reference``.

    Example:
        >>> import numpy as np
        >>> y, x = np.mgrid[0:64, 0:64].astype(np.float32)
        >>> res = curved_gabor(np.cos(2 * np.pi * y / 8.0), p=20, q=10)
        >>> bool(abs(res.frequency[32, 32] - 0.125) < 0.005)
        True
    """
    p = _int_at_least(p, "p", 1)
    q = _int_at_least(q, "q", 1)
    chunk_size = _int_at_least(chunk_size, "chunk_size", 1)
    if num_workers is not None:
        num_workers = _int_at_least(num_workers, "num_workers", 1)
    if not isinstance(refine_orientation, bool):
        raise TypeError(f"refine_orientation: expected a bool, got {type(refine_orientation).__name__}")
    sigma_along = _positive(sigma_along, "sigma_along", allow_none=True)
    sigma_across = _positive(sigma_across, "sigma_across", allow_none=True)
    if sigma_along is None:
        sigma_along = q / 3.0
    if freq_range is None:
        freq_range = (1.0 / p, 0.25)
    try:
        f_min, f_max = (float(v) for v in freq_range)
    except (TypeError, ValueError):
        raise ValueError(f"freq_range must be a pair (f_min, f_max) in cycles/px; got {freq_range!r}") from None
    if not (0.0 < f_min < f_max <= 0.5):
        raise ValueError(f"freq_range must satisfy 0 < f_min < f_max <= 0.5 (cycles/px); got {freq_range!r}")
    try:
        device = torch.device(device)
    except (RuntimeError, TypeError) as e:
        raise ValueError(f"device must be a torch device or string like 'cpu'/'cuda'; got {device!r}") from e

    img = _as_image(gray, "gray", device=device)
    H, W = img.shape
    if barrier is not None:
        barrier = _as_image(barrier, "barrier", device=device)
        if barrier.shape != img.shape:
            raise ValueError(f"barrier must have the shape of gray {tuple(img.shape)}; got {tuple(barrier.shape)}")
    # sigma_smooth and window serve the orientation field (theta None) and its refinement only
    if (sigma_smooth is None or window is None) and (theta is None or refine_orientation):
        period = _dominant_period(img, f_min, f_max)
        if sigma_smooth is None:
            sigma_smooth = min(4.0, max(1.0, period / 20.0))
        if window is None:
            window = int(round(min(61.0, max(15.0, 0.7 * period)))) | 1
    if theta is None:
        th, coh = _tensor_orientation(img[None], *_check_params(sigma_smooth, window))
        ref_weight = coh
    else:
        th = _as_image(theta, "theta", device=device)
        if th.shape != img.shape:
            raise ValueError(f"theta must have the shape of gray {tuple(img.shape)}; got {tuple(th.shape)}")
        th = torch.remainder(th, math.pi)
        ref_weight = torch.ones_like(th)
        if refine_orientation:
            _check_params(sigma_smooth, window)  # validate for the refinement step
    c2, s2 = torch.cos(2.0 * th), torch.sin(2.0 * th)

    if normal_reference is None:
        n_ref = _dominant_normal(c2, s2, ref_weight)
    else:
        n_ref = torch.as_tensor(np.asarray(normal_reference, dtype=np.float64).reshape(-1), dtype=torch.float32)
        if n_ref.numel() != 2 or not bool(torch.isfinite(n_ref).all()) or float(n_ref.norm()) == 0:
            raise ValueError(f"normal_reference must be a non-zero finite (x, y) vector; got {normal_reference!r}")
        n_ref = (n_ref / n_ref.norm()).to(device)

    # Per-pixel oriented normal.
    normal = torch.stack([-torch.sin(th), torch.cos(th)], dim=-1)  # (H, W, 2)
    normal = torch.where((normal @ n_ref)[..., None] < 0, -normal, normal)

    npx = H * W
    ys, xs = torch.meshgrid(torch.arange(H, dtype=torch.float32, device=device),
                            torch.arange(W, dtype=torch.float32, device=device), indexing="ij")
    xs, ys = xs.reshape(-1), ys.reshape(-1)
    nx, ny = normal[..., 0].reshape(-1).contiguous(), normal[..., 1].reshape(-1).contiguous()
    c2_flat, s2_flat, img_flat = c2.reshape(-1), s2.reshape(-1), img.reshape(-1)
    barrier_flat = None if barrier is None else barrier.reshape(-1)
    dirs = _Field(torch.stack([c2, s2]))
    gxs, gys = dirs.to_grid(xs, ys)

    # ---- pass 1: Gaussian line-integral convolution along the rings --------------------------------------------
    full1 = _Field(torch.stack([c2, s2, img, torch.ones_like(img)]), zero_pad=(3,))
    w_along = torch.exp(-0.5 * (torch.arange(q + 1, dtype=torch.float64) / sigma_along) ** 2).tolist()
    w_total = w_along[0] + 2.0 * sum(w_along[1:])
    A = torch.empty(npx, device=device)
    A_valid = torch.empty(npx, device=device)
    curvature = torch.empty(npx, device=device)

    def along_chunk(s: int, e: int) -> None:
        n = e - s
        tx, ty = ny[s:e], -nx[s:e]  # tangent = normal rotated by -90 degrees
        # Both walking senses at once: entries [:n] walk along +t, entries [n:] along -t.
        dx0, dy0 = torch.cat([tx, -tx]), torch.cat([ty, -ty])
        first = torch.stack([c2_flat[s:e], s2_flat[s:e]]).repeat(1, 2)
        num = torch.zeros(2 * n, device=device)
        den = torch.zeros(2 * n, device=device)
        d = (dx0, dy0)
        for k, cur, d in _trace(full1, dirs, gxs[s:e].repeat(2), gys[s:e].repeat(2), dx0, dy0, first, q, False):
            num.addcmul_(cur[2], cur[3], value=w_along[k])
            den.add_(cur[3], alpha=w_along[k])
        A[s:e] = (num[:n] + num[n:] + w_along[0] * img_flat[s:e]) / (den[:n] + den[n:] + w_along[0])
        A_valid[s:e] = (den[:n] + den[n:] + w_along[0]) / w_total
        # Turn of the contour between its centre and both ends (the walking sense is kept continuous).
        dx, dy = d
        turn = torch.atan2(dx0 * dy - dy0 * dx, dx0 * dx + dy0 * dy).abs_()
        curvature[s:e] = (turn[:n] + turn[n:]) / (2.0 * q)

    # ---- pass 2: across-profile, frequency and complex Gabor response ------------------------------------------
    n_taps = 2 * p + 1
    j = torch.arange(-p, p + 1, dtype=torch.float32, device=device)
    nfft = 1 << int(math.ceil(math.log2(3 * n_taps)))
    k_lo = max(1, int(math.floor(f_min * nfft)))
    k_hi = max(k_lo, min(nfft // 2 - 1, int(math.ceil(f_max * nfft))))
    hann = 0.5 + 0.5 * torch.cos(math.pi * j / (p + 1))
    magnitude = torch.empty(npx, device=device)
    phase = torch.empty(npx, device=device)
    frequency = torch.empty(npx, device=device)

    def across_chunk(s: int, e: int) -> None:
        n = e - s
        dx0, dy0 = torch.cat([nx[s:e], -nx[s:e]]), torch.cat([ny[s:e], -ny[s:e]])  # [:n]: j > 0, [n:]: j < 0
        first = torch.stack([c2_flat[s:e], s2_flat[s:e]]).repeat(1, 2)
        prof = torch.empty(n_taps, n, device=device)  # along-averaged profile P_j in row p + j
        valid = torch.empty(n_taps, n, device=device)
        prof[p] = A[s:e]
        valid[p] = A_valid[s:e]
        if barrier is not None:
            side = barrier_flat[s:e].repeat(2)
            open_ = torch.ones(2 * n, device=device)  # 0 once this half of the curve has crossed the barrier
        for k, cur, _ in _trace(full2, dirs, gxs[s:e].repeat(2), gys[s:e].repeat(2), dx0, dy0, first, p, True):
            prof[p + k], prof[p - k] = cur[2, :n], cur[2, n:]
            v = cur[3].clamp(0.0, 1.0)  # bicubic may overshoot slightly
            if barrier is not None:
                open_.mul_((cur[4] * side >= 0).to(open_.dtype))
                v = v * open_
            valid[p + k], valid[p - k] = v[:n], v[n:]
        prof, valid = prof.t(), valid.t()  # (n, 2p+1)
        # Local frequency: peak of the Hann-windowed, validity-weighted spectrum; parabolic interpolation of log power.
        wv = valid * hann
        mean = (wv * prof).sum(1, keepdim=True) / wv.sum(1, keepdim=True).clamp_min(1e-12)
        spec = torch.fft.rfft((prof - mean) * wv, n=nfft, dim=1)[:, k_lo - 1:k_hi + 2]
        logp = torch.log(spec.real ** 2 + spec.imag ** 2 + 1e-20)
        kk = torch.argmax(logp[:, 1:-1], dim=1, keepdim=True) + 1
        y0, y1, y2 = logp.gather(1, kk - 1), logp.gather(1, kk), logp.gather(1, kk + 1)
        curv = y0 - 2.0 * y1 + y2
        delta = torch.where(curv < 0, 0.5 * (y0 - y2) / curv.clamp_max(-1e-12), torch.zeros_like(curv))
        f = ((kk - 1 + k_lo).to(torch.float32) + delta.clamp(-0.5, 0.5)) / nfft
        f = f.clamp(f_min, f_max)  # (n, 1)
        # Complex Gabor response at the patch centre: Gaussian envelope times carrier exp(-2 pi i f j) across.
        sig = (0.5 / f).clamp(1.0, max(1.0, p / 3.0)) if sigma_across is None else torch.full_like(f, sigma_across)
        u = torch.exp(-0.5 * (j / sig) ** 2) * valid
        usum = u.sum(1, keepdim=True).clamp_min(1e-12)
        x = u * (prof - (u * prof).sum(1, keepdim=True) / usum)
        arg = (2.0 * math.pi) * f * j
        re = 2.0 * (x * torch.cos(arg)).sum(1) / usum[:, 0]
        im = -2.0 * (x * torch.sin(arg)).sum(1) / usum[:, 0]
        magnitude[s:e] = torch.hypot(re, im)
        phase[s:e] = torch.atan2(im, re)
        frequency[s:e] = f[:, 0]

    chunks = [(s, min(npx, s + chunk_size)) for s in range(0, npx, chunk_size)]
    with _parallel(device, num_workers) as run:
        run(along_chunk, chunks)
        # Bicubic across the rings: bilinear resampling would attenuate the ring signal (~cos(pi f) at half-pixel
        # offsets) and slightly distort its phase.
        channels = [c2, s2, A.view(H, W), A_valid.view(H, W)] + ([] if barrier is None else [barrier])
        full2 = _Field(torch.stack(channels), zero_pad=(3,), mode="bicubic")
        run(across_chunk, chunks)

    phase_np = phase.view(H, W).cpu().numpy()
    mag_np = magnitude.view(H, W).cpu().numpy()
    orientation = orientation_from_phase(phase_np, sigma_smooth, window, magnitude=mag_np)[0] \
        if refine_orientation else None
    return GaborResult(magnitude=mag_np, phase=phase_np, frequency=frequency.view(H, W).cpu().numpy(),
                       curvature=curvature.view(H, W).cpu().numpy(), orientation=orientation,
                       theta=th.cpu().numpy().astype(np.float32), normal=normal.cpu().numpy().astype(np.float32))


# ----------------------------------------------------------------------------------------------------------------
# Differentiable curved Gabor filter with a fixed geometry: curved_gabor_response / CurvedGaborFilter
# ----------------------------------------------------------------------------------------------------------------
def _oriented_normal(th: torch.Tensor, normal, normal_reference) -> torch.Tensor:
    """Per-pixel unit normal ``(H, W, 2)``: ``normal`` as given (normalised), else ``(-sin th, cos th)`` oriented as
    in :func:`curved_gabor` with an explicit ``theta`` (towards ``normal_reference`` or the dominant normal)."""
    H, W = th.shape
    if normal is not None:
        if isinstance(normal, np.ndarray):
            normal = torch.from_numpy(np.ascontiguousarray(normal))
        if not isinstance(normal, torch.Tensor) or normal.is_complex() or not normal.dtype.is_floating_point:
            raise TypeError(f"normal: expected a real floating (H, W, 2) array or tensor, got "
                            f"{type(normal).__name__}{'' if not hasattr(normal, 'dtype') else ' ' + str(normal.dtype)}")
        if tuple(normal.shape) != (H, W, 2):
            raise ValueError(f"normal: expected shape {(H, W, 2)} (the shape of theta plus (x, y)), got "
                             f"{tuple(normal.shape)}")
        n = normal.detach().to(device=th.device, dtype=torch.float32)
        length = n.norm(dim=-1, keepdim=True)
        if not bool(torch.isfinite(n).all()) or bool((length < 1e-6).any()):
            raise ValueError("normal: expected finite, non-zero (x, y) vectors in every pixel")
        return n / length
    c2, s2 = torch.cos(2.0 * th), torch.sin(2.0 * th)
    if normal_reference is None:
        n_ref = _dominant_normal(c2, s2, torch.ones_like(th))
    else:
        n_ref = torch.as_tensor(np.asarray(normal_reference, dtype=np.float64).reshape(-1), dtype=torch.float32)
        if n_ref.numel() != 2 or not bool(torch.isfinite(n_ref).all()) or float(n_ref.norm()) == 0:
            raise ValueError(f"normal_reference must be a non-zero finite (x, y) vector; got {normal_reference!r}")
        n_ref = (n_ref / n_ref.norm()).to(th.device)
    n = torch.stack([-torch.sin(th), torch.cos(th)], dim=-1)
    return torch.where((n @ n_ref)[..., None] < 0, -n, n)


@torch.no_grad()
def _build_geometry(theta, frequency, normal, p: int, q: int, sigma_along, sigma_across, normal_reference,
                    chunk_size: int, device) -> dict:
    """Trace the curved patches of every pixel once and fold the Gabor kernel into per-sample weights.

    Returns a dict of float32 tensors (``N = H W``; grid units of a one-pixel padded ``(H + 2, W + 2)`` field):
    ``along_grid`` ``(2q, N, 2)`` contour points (rows ``0..q-1``: steps ``1..q`` along ``+t``, rows ``q..2q-1``:
    along ``-t``), ``along_weight`` ``(2q, N)`` Gaussian weight times in-image fraction, ``along_scale`` ``(N,)`` the
    reciprocal total weight (the centre pixel has weight ``w0``, stored as ``along_w0`` ``()``); ``across_grid``
    ``(2p, N, 2)`` normal-curve points for ``j = -p..-1, 1..p``; ``coef`` ``(2, 2p + 1, N)`` real and imaginary
    coefficients of the profile samples ``j = -p..p`` (Gaussian envelope, validity, carrier at ``frequency``,
    mean removal and the factor ``2 / sum u`` of :func:`curved_gabor` folded in).
    """
    th = _as_image(theta, "theta", device=device)
    th = torch.remainder(th, math.pi)
    fr = _as_image(frequency, "frequency", device=device)
    H, W = th.shape
    if fr.shape != th.shape:
        raise ValueError(f"frequency: expected the shape of theta {tuple(th.shape)}, got {tuple(fr.shape)}")
    if bool((fr <= 0).any()) or bool((fr > 0.5).any()):
        raise ValueError(f"frequency: expected values in (0, 0.5] cycles/px, got range "
                         f"[{float(fr.min()):.4g}, {float(fr.max()):.4g}]")
    normal = _oriented_normal(th, normal, normal_reference)
    c2, s2 = torch.cos(2.0 * th), torch.sin(2.0 * th)
    npx = H * W
    ys, xs = torch.meshgrid(torch.arange(H, dtype=torch.float32, device=device),
                            torch.arange(W, dtype=torch.float32, device=device), indexing="ij")
    xs, ys = xs.reshape(-1), ys.reshape(-1)
    nx, ny = normal[..., 0].reshape(-1).contiguous(), normal[..., 1].reshape(-1).contiguous()
    c2_flat, s2_flat = c2.reshape(-1), s2.reshape(-1)
    dirs = _Field(torch.stack([c2, s2]))
    gxs, gys = dirs.to_grid(xs, ys)
    chunks = [(s, min(npx, s + chunk_size)) for s in range(0, npx, chunk_size)]

    # along the rings: the contour points of pass 1 and their weights
    full1 = _Field(torch.stack([c2, s2, torch.ones_like(c2)]), zero_pad=(2,))
    w_along = torch.exp(-0.5 * (torch.arange(q + 1, dtype=torch.float64) / sigma_along) ** 2).tolist()
    w_total = w_along[0] + 2.0 * sum(w_along[1:])
    along_grid = torch.empty(2 * q, npx, 2, device=device)
    along_weight = torch.empty(2 * q, npx, device=device)
    for s, e in chunks:
        n = e - s
        tx, ty = ny[s:e], -nx[s:e]
        first = torch.stack([c2_flat[s:e], s2_flat[s:e]]).repeat(1, 2)
        for k, cur, _, (gx, gy) in _trace_positions(full1, dirs, gxs[s:e].repeat(2), gys[s:e].repeat(2),
                                                    torch.cat([tx, -tx]), torch.cat([ty, -ty]), first, q, False):
            along_grid[k - 1, s:e, 0], along_grid[k - 1, s:e, 1] = gx[:n], gy[:n]
            along_grid[q + k - 1, s:e, 0], along_grid[q + k - 1, s:e, 1] = gx[n:], gy[n:]
            along_weight[k - 1, s:e] = cur[2, :n] * w_along[k]
            along_weight[q + k - 1, s:e] = cur[2, n:] * w_along[k]
    den = along_weight.sum(0) + w_along[0]
    a_valid = den / w_total

    # across the rings: the normal-curve points of pass 2, validity, and the complex kernel at `frequency`
    full2 = _Field(torch.stack([c2, s2, a_valid.view(H, W)]), zero_pad=(2,), mode="bicubic")
    across_grid = torch.empty(2 * p, npx, 2, device=device)
    coef = torch.empty(2, 2 * p + 1, npx, device=device)
    j = torch.arange(-p, p + 1, dtype=torch.float64, device=device)[:, None]
    fr_flat = fr.reshape(-1)
    for s, e in chunks:
        n = e - s
        valid = torch.empty(2 * p + 1, n, device=device)
        valid[p] = a_valid[s:e]
        first = torch.stack([c2_flat[s:e], s2_flat[s:e]]).repeat(1, 2)
        for k, cur, _, (gx, gy) in _trace_positions(full2, dirs, gxs[s:e].repeat(2), gys[s:e].repeat(2),
                                                    torch.cat([nx[s:e], -nx[s:e]]), torch.cat([ny[s:e], -ny[s:e]]),
                                                    first, p, True):
            across_grid[p + k - 1, s:e, 0], across_grid[p + k - 1, s:e, 1] = gx[:n], gy[:n]  # j = +k
            across_grid[p - k, s:e, 0], across_grid[p - k, s:e, 1] = gx[n:], gy[n:]  # j = -k
            v = cur[2].clamp(0.0, 1.0)  # bicubic may overshoot slightly
            valid[p + k], valid[p - k] = v[:n], v[n:]
        f = fr_flat[s:e].to(torch.float64)[None, :]
        sig = (0.5 / f).clamp(1.0, max(1.0, p / 3.0)) if sigma_across is None else torch.full_like(f, sigma_across)
        u = torch.exp(-0.5 * (j / sig) ** 2) * valid.to(torch.float64)
        usum = u.sum(0, keepdim=True).clamp_min(1e-12)
        arg = (2.0 * math.pi) * f * j
        cos, sin = torch.cos(arg), torch.sin(arg)
        coef[0, :, s:e] = (2.0 * u * (cos - (u * cos).sum(0, keepdim=True) / usum) / usum).to(torch.float32)
        coef[1, :, s:e] = (-2.0 * u * (sin - (u * sin).sum(0, keepdim=True) / usum) / usum).to(torch.float32)
    return {"along_grid": along_grid, "along_weight": along_weight, "along_scale": 1.0 / den,
            "along_w0": torch.tensor(w_along[0], device=device), "across_grid": across_grid, "coef": coef,
            "theta": th, "normal": normal, "frequency": fr}


def _check_response_image(image, shape: tuple[int, int]) -> tuple[torch.Tensor, bool]:
    """``(H, W)`` or ``(B, H, W)`` floating tensor -> ``(B, H, W)``, and whether a batch axis was given."""
    check_tensor("image", image, "(H, W) or (B, H, W)", dtypes="floating")
    if image.ndim not in (2, 3) or tuple(image.shape[-2:]) != tuple(shape):
        raise ValueError(f"image: expected shape {tuple(shape)} or (B, {shape[0]}, {shape[1]}) (the filter's "
                         f"geometry), got {tuple(image.shape)}")
    return (image if image.ndim == 3 else image[None]), image.ndim == 3


def _apply_geometry(geom: dict, image: torch.Tensor) -> torch.Tensor:
    """Complex response ``(B, H, W)`` of ``image`` ``(B, H, W)`` through a traced geometry (differentiable)."""
    B, H, W = image.shape
    dt = image.dtype
    g1 = geom["along_grid"].to(dt)
    pad = F.pad(image[:, None], (1, 1, 1, 1), mode="replicate")  # as _Field: the image channel is replicated
    samples = F.grid_sample(pad, g1[None].expand(B, -1, -1, -1), mode="bilinear", padding_mode="border",
                            align_corners=True)[:, 0]  # (B, 2q, N)
    A = ((samples * geom["along_weight"].to(dt)).sum(1) + geom["along_w0"].to(dt) * image.reshape(B, -1)) \
        * geom["along_scale"].to(dt)  # (B, N): Gaussian line-integral convolution along the rings
    pad_a = F.pad(A.view(B, 1, H, W), (1, 1, 1, 1), mode="replicate")
    side = F.grid_sample(pad_a, geom["across_grid"].to(dt)[None].expand(B, -1, -1, -1), mode="bicubic",
                         padding_mode="border", align_corners=True)[:, 0]  # (B, 2p, N), j = -p..-1, 1..p
    p = side.shape[1] // 2
    prof = torch.cat([side[:, :p], A[:, None], side[:, p:]], dim=1)  # (B, 2p + 1, N), j = -p..p
    coef = geom["coef"].to(dt)
    re = (prof * coef[0]).sum(1)
    im = (prof * coef[1]).sum(1)
    return torch.complex(re, im).view(B, H, W)


def _geometry_args(p, q, sigma_along, sigma_across, chunk_size, device):
    p = _int_at_least(p, "p", 1)
    q = _int_at_least(q, "q", 1)
    chunk_size = _int_at_least(chunk_size, "chunk_size", 1)
    sigma_along = _positive(sigma_along, "sigma_along", allow_none=True)
    sigma_across = _positive(sigma_across, "sigma_across", allow_none=True)
    try:
        device = torch.device(device)
    except (RuntimeError, TypeError) as e:
        raise ValueError(f"device must be a torch device or string like 'cpu'/'cuda'; got {device!r}") from e
    return p, q, (q / 3.0 if sigma_along is None else sigma_along), sigma_across, chunk_size, device


def curved_gabor_response(image: torch.Tensor, theta, frequency, normal=None, p: int = 80, q: int = 80,
                          sigma_along: float | None = None, sigma_across: float | None = None, *,
                          normal_reference=None, chunk_size: int = 16384) -> torch.Tensor:
    """Complex curved Gabor response of an image through a *given* ring geometry; differentiable in ``image``.

    The same filter as :func:`curved_gabor` (module docstring: along-ring line-integral convolution, then the
    Gabor kernel across the rings), but with the orientation field ``theta``, the normal sign and the carrier
    ``frequency`` fixed instead of estimated from ``image``. The response is then a linear function of the image
    (bilinear / bicubic ``grid_sample`` at traced points with fixed weights), so autograd gives its exact gradient.
    With ``theta``, ``normal`` and ``frequency`` of ``res = curved_gabor(gray)``, ``|R|`` and ``angle(R)`` of
    ``gray`` reproduce ``res.magnitude`` and ``res.phase`` to float32 rounding.

    This traces the patches on every call; :class:`CurvedGaborFilter` traces them once.

    Args:
        image: ``(H, W)`` or ``(B, H, W)`` real float tensor (float32 or float64), intensity in any unit.
        theta: ``(H, W)`` ring (tangent) orientation in radians (mod pi), numpy or torch.
        frequency: ``(H, W)`` carrier frequency across the rings in cycles/px, in ``(0, 0.5]``.
        normal: optional ``(H, W, 2)`` ``(x, y)`` normals along which the phase grows (e.g. ``GaborResult.normal``);
            default: ``(-sin theta, cos theta)`` oriented towards ``normal_reference`` (or the dominant normal).
        p, q: half-lengths (px) across / along the rings, as in :func:`curved_gabor`.
        sigma_along: std (px) of the along-ring envelope; default ``q / 3``.
        sigma_across: std (px) of the across-ring envelope; default ``0.5 / frequency`` clipped to ``[1, p / 3]``.
        normal_reference: ``(x, y)`` used to orient the normals when ``normal`` is None.
        chunk_size: pixels per tracing chunk.

    Returns:
        complex tensor ``(H, W)`` or ``(B, H, W)`` (as ``image``; complex64 for float32, complex128 for float64):
        ``R ~= a exp(i (2 pi f t + phi0))`` for rings ``a cos(2 pi f t + phi0)`` along the signed normal
        coordinate ``t``.

    Raises:
        TypeError / ValueError: non-tensor or non-float ``image``, shapes that do not match ``theta``, frequencies
            outside ``(0, 0.5]``, invalid ``p``, ``q``, sigmas or normals.

    Example:
        >>> import math, torch
        >>> y = torch.arange(48.0)[:, None].expand(48, 48)
        >>> img = torch.cos(2 * math.pi * y / 8.0 + 0.3)
        >>> r = curved_gabor_response(img, torch.zeros(48, 48), torch.full((48, 48), 1 / 8.0), p=12, q=6)
        >>> round(float(r[24, 24].abs()), 2), round(float(r[24, 24].angle()), 2)   # phase 2 pi 24 / 8 + 0.3
        (1.0, 0.3)
    """
    p, q, sigma_along, sigma_across, chunk_size, _ = _geometry_args(p, q, sigma_along, sigma_across, chunk_size,
                                                                    "cpu")
    if not isinstance(image, torch.Tensor):
        raise TypeError(f"image: expected a torch.Tensor of shape (H, W) or (B, H, W), got {type(image).__name__}")
    geom = _build_geometry(theta, frequency, normal, p, q, sigma_along, sigma_across, normal_reference, chunk_size,
                           image.device)
    img, batched = _check_response_image(image, tuple(geom["theta"].shape))
    out = _apply_geometry(geom, img)
    return out if batched else out[0]


class CurvedGaborFilter(torch.nn.Module):
    """:func:`curved_gabor_response` with the curved patches traced once (in ``__init__``) and kept as buffers.

    Memory: about ``(32 p + 24 q) * H * W`` bytes of float32 buffers (sample positions, weights, coefficients;
    p = q = 20 on 256 x 256: 73 MB), so it is meant for loss images of moderate size; a forward pass holds
    ``(2p + 2q + 1) * B * H * W`` more samples.

    Args:
        theta, frequency, normal, p, q, sigma_along, sigma_across, normal_reference, chunk_size: as in
            :func:`curved_gabor_response`.
        device: device of the buffers (``.to()`` moves them later).

    Attributes:
        theta ``(H, W)``, normal ``(H, W, 2)``, frequency ``(H, W)``: the geometry used (buffers);
        reference: the :class:`GaborResult` when built with :meth:`from_image`, else None.

    Example:
        >>> import math, torch
        >>> y = torch.arange(40.0)[:, None].expand(40, 40)
        >>> filt = CurvedGaborFilter.from_image(torch.cos(2 * math.pi * y / 8.0), p=12, q=6)
        >>> img = torch.cos(2 * math.pi * (y - 1.0) / 8.0).requires_grad_()
        >>> phase = filt(img)[20, 20].angle()   # one ring-period/8 behind the reference
        >>> round(float(phase.detach()) - float(filt.reference.phase[20, 20]), 3)
        -0.785
        >>> phase.backward(); img.grad.shape
        torch.Size([40, 40])
    """

    def __init__(self, theta, frequency, normal=None, p: int = 80, q: int = 80, sigma_along: float | None = None,
                 sigma_across: float | None = None, *, normal_reference=None, chunk_size: int = 16384,
                 device="cpu"):
        super().__init__()
        p, q, sigma_along, sigma_across, chunk_size, device = _geometry_args(p, q, sigma_along, sigma_across,
                                                                             chunk_size, device)
        self.p, self.q, self.sigma_along, self.sigma_across = p, q, sigma_along, sigma_across
        geom = _build_geometry(theta, frequency, normal, p, q, sigma_along, sigma_across, normal_reference,
                               chunk_size, device)
        for name, value in geom.items():
            self.register_buffer(name, value)
        self.shape = tuple(geom["theta"].shape)
        self.reference: GaborResult | None = None

    @classmethod
    def from_image(cls, gray, p: int = 80, q: int = 80, sigma_along: float | None = None,
                   sigma_across: float | None = None, *, device="cpu", **kwargs) -> "CurvedGaborFilter":
        """Filter with the geometry (orientation, normal sign, frequency) that :func:`curved_gabor` finds in ``gray``.

        Args:
            gray: ``(H, W)`` grayscale image (numpy or torch).
            p, q, sigma_along, sigma_across, device: as in :func:`curved_gabor` and the constructor.
            **kwargs: further keyword arguments of :func:`curved_gabor` (``freq_range``, ``normal_reference``,
                ``sigma_smooth``, ``window``, ``chunk_size``, ``num_workers``).

        Returns:
            the filter; its ``reference`` attribute holds the :class:`GaborResult` of ``gray``.
        """
        res = curved_gabor(gray, p=p, q=q, sigma_along=sigma_along, sigma_across=sigma_across, device=device,
                           **kwargs)
        filt = cls(res.theta, res.frequency, res.normal, p, q, sigma_along, sigma_across,
                   chunk_size=kwargs.get("chunk_size", 16384), device=device)
        filt.reference = res
        return filt

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        """Complex response ``(H, W)`` / ``(B, H, W)`` of ``image`` ``(H, W)`` / ``(B, H, W)`` (differentiable)."""
        img, batched = _check_response_image(image, self.shape)
        if img.device != self.coef.device:
            raise ValueError(f"image: expected a tensor on the filter's device {self.coef.device}, got {img.device} "
                             "(move one of them with .to())")
        geom = {name: getattr(self, name) for name in ("along_grid", "along_weight", "along_scale", "along_w0",
                                                       "across_grid", "coef")}
        out = _apply_geometry(geom, img)
        return out if batched else out[0]

    def extra_repr(self) -> str:
        return f"shape={self.shape}, p={self.p}, q={self.q}, sigma_along={self.sigma_along:g}, " \
               f"sigma_across={self.sigma_across}"
