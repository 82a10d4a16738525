"""Whole rings of a disc as closed polygons, chained from the ring curves traced between neighbouring transects.

:func:`~torch_appearance.rings.consistency.link_transects` follows every boundary of every transect (helper
transects included) along its ring's ridge to both neighbouring transects. Chaining those curves round the disc
gives whole rings (the representation of CS-TRD): from a boundary on the first transect, the curve towards the next
transect (in angle order) arrives near one of the boundaries that transect's own curves start from (within 0.3 of
the narrower ring beside it, at least 3 px), whose curve continues to the next, and so on; the ring *closes* when the chain comes
back to the boundary it started from. A boundary whose chain breaks or comes back on another ring closes nowhere
and gives no polygon. The polygon is the concatenation of the curves (one vertex per traced ray).

Written as labelme-style JSON (as CS-TRD and TRAS write their rings): ``shapes`` of ``shape_type`` ``"polygon"``
with ``label`` the ring's index from the pith, ``points`` ``[[x, y], ...]`` in pixels of the photo.
"""
from __future__ import annotations

import json
import math

import numpy as np

__all__ = ["draw_ring_polygons", "labelme_json", "ring_polygons"]


def _match(radii, x, tol_rings=0.3, min_px=3.0):
    """Index of the boundary of ``radii`` (sorted) matching a curve arriving at ``x``, or -1."""
    if not len(radii):
        return -1
    k = int(np.argmin(np.abs(radii - x)))
    gaps = np.diff(radii)
    near = [g for g in (gaps[k - 1] if k > 0 else None, gaps[k] if k < len(gaps) else None) if g is not None]
    tol = max(min_px, tol_rings * min(near)) if near else min_px
    return k if abs(radii[k] - x) <= tol else -1


def ring_polygons(res) -> list[dict]:
    """Closed rings of a :class:`~torch_appearance.rings.disc.DiscBoundaries` (module docstring).

    Returns:
        list (sorted by mean radius) of dicts: ``points`` ``(N, 2)`` ``(x, y)`` pixels, ``radius_px`` the mean
        distance from the pith, ``start_radius_px`` the boundary on the first transect it was chained from. Empty
        when the transects were not linked (``link=False`` or fewer than three transects).

    Raises:
        ValueError: ``res`` is not a disc result.
    """
    info = getattr(res, "info", None)
    if not isinstance(info, dict) or "rings_polar" not in info or not hasattr(res, "pith"):
        raise ValueError(f"res: expected a DiscBoundaries (detect_disc_boundaries' result), got {type(res).__name__}")
    rp = info["rings_polar"]
    if rp is None:
        return []
    ang = np.asarray(rp["angles_deg"], np.float64) % 360.0
    order = [int(i) for i in np.argsort(ang, kind="stable")]
    T = len(order)
    pith = np.asarray(res.pith, np.float64)
    # the curves leave each transect from its own (1D) boundaries: the ring is followed from curve start to curve
    # start (a boundary inferred or moved by the linking has no curve of its own)
    starts = []
    for step in range(T):
        k, nxt = order[step], order[(step + 1) % T]
        c = rp["curves"][k].get(nxt)
        if c is None:  # a sector was not traced (two transects at one angle): no ring goes round
            return []
        starts.append(np.asarray(c[1][:, 0] if len(c[1]) else np.zeros(0), np.float64))
    out = []
    for i0, r0 in enumerate(starts[0]):
        idx, thetas, rs, ok = i0, [], [], True
        for step in range(T):
            k, nxt = order[step], order[(step + 1) % T]
            th, paths = rp["curves"][k][nxt]
            th = np.asarray(th, np.float64)
            if step + 1 == T and th[-1] < th[0]:
                th = th + 2 * math.pi
            thetas.append(th[:-1])
            rs.append(paths[idx, :-1])
            idx = _match(starts[(step + 1) % T], float(paths[idx, -1]))
            if idx < 0:
                ok = False
                break
        if not ok or idx != i0:
            continue
        th, r = np.concatenate(thetas), np.concatenate(rs)
        pts = pith[None, :] + r[:, None] * np.stack([np.cos(th), np.sin(th)], 1)
        out.append(dict(points=pts, radius_px=float(r.mean()), start_radius_px=float(r0)))
    out.sort(key=lambda p: p["radius_px"])
    kept = []
    for p in out:  # two starts that chained onto the same ring: keep one
        if not kept or np.abs(p["radius_px"] - kept[-1]["radius_px"]) > 1.0:
            kept.append(p)
    return kept


def labelme_json(polygons, image_path: str, image_shape, pith=None) -> str:
    """labelme-style JSON text of ring polygons (module docstring); ``image_shape`` ``(H, W)``; ``pith`` ``(x, y)``
    is written as ``"center"`` ``[row, col]`` as CS-TRD does."""
    H, W = (int(v) for v in image_shape[:2])
    shapes = [dict(label=str(i), points=np.round(p["points"], 2).tolist(), group_id=None, shape_type="polygon",
                   flags={}) for i, p in enumerate(polygons)]
    blob = dict(version="5.0.1", flags={}, shapes=shapes, imagePath=str(image_path), imageData=None, imageHeight=H,
                imageWidth=W)
    if pith is not None:
        blob["center"] = [float(pith[1]), float(pith[0])]
    return json.dumps(blob, indent=1)


def draw_ring_polygons(bgr, polygons, thickness=None):
    """Draw the polygons on a ``(H, W, 3)`` uint8 BGR image in place (alternating colours, so that neighbouring rings
    tell apart); returns it."""
    import cv2
    t = thickness or max(1, round(max(bgr.shape[:2]) / 1500))
    colours = ((0, 255, 255), (255, 0, 255))
    for i, p in enumerate(polygons):
        pts = np.round(p["points"]).astype(np.int32).reshape(-1, 1, 2)
        cv2.polylines(bgr, [pts], True, colours[i % 2], t, cv2.LINE_AA)
    return bgr
