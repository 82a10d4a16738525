"""A closed (or nearly closed) triangle mesh becomes a voxel object: occupancy, an exact SDF band at the voxel
corners, surface texels with points, normals and colours, depth below the surface (TOG 2021, thesis part II §3.3).

Libraries (issue 11): libigl's AABB tree for exact point–triangle distances (``igl.signed_distance`` with distance
bounds, so far points are pruned; pseudonormal signs for closed meshes), the fast generalised winding number for
the sign where a mesh is open, duplicated or self-intersecting, and embree rays (via trimesh/embreex) for the
inside/outside parity of everything far from the surface of closed meshes. ``igl.point_mesh_squared_distance``
gives the texels' closest surface points and faces.

Units: mm. Axes: x ↔ W, y ↔ H, z ↔ D; corner (k, j, i) of the SDF grid sits at ``origin + (i, j, k)·voxel_size``
and voxel (k, j, i) spans [origin + (i, j, k)·h, … + h].
"""
from dataclasses import dataclass, fields
import contextlib
import json
import math
import os
from typing import Optional, Tuple

import numpy as np
import torch

from ..checks import check_int, check_real
from .surface import surface_attributes

__all__ = ["VoxelObject", "voxelize", "check_grid_size", "MAX_GRID_BYTES"]

#: Refuse grids whose SDF corners and per-voxel arrays would need more than this (bytes); ``voxelize`` names the
#: size it would need.
MAX_GRID_BYTES = 8 * 2 ** 30


@dataclass
class VoxelObject:
    """A voxelised object (see :func:`voxelize`).

    Attributes:
        origin: (x, y, z) world position of the grid corner, mm.
        voxel_size: voxel edge, mm (isotropic).
        occupancy: (D, H, W) bool, voxel centre inside the mesh.
        sdf: (D+1, H+1, W+1) float32 signed distance at the voxel corners, mm, < 0 inside: exact within
            ``band_mm`` of the surface, clamped to ±band_mm beyond (the sign stays right).
        band_mm: half-width of the exact band.
        texel_voxels: (N, 3) int64 (k, j, i) of the inside voxels with an outside 6-neighbour.
        texel_points: (N, 3) float64 closest surface point of each texel's voxel centre, mm.
        texel_normals: (N, 3) float64 outward unit normals there: smooth corner normals (faces within a 30°
            crease angle) interpolated barycentrically; hard edges stay sharp.
        texel_colors: (N, 3) float32 linear RGB target colours, or None when the mesh has no colour.
        texel_uv: (N, 2) float32 texture coordinates of the closest points, or None.
        depth: (D, H, W) float32 distance below the surface of inside voxels' centres (0 outside), mm; exact up to
            max(band_mm, shell_mm + 2 voxels), that value beyond.
        shell: (D, H, W) bool voxels with depth < shell_mm, or None.
        info: how it was made (closed mesh or not, inverted, counts of queries, timings per step in s), or None.
    """
    origin: Tuple[float, float, float]
    voxel_size: float
    occupancy: torch.Tensor
    sdf: torch.Tensor
    band_mm: float
    texel_voxels: torch.Tensor
    texel_points: torch.Tensor
    texel_normals: torch.Tensor
    texel_colors: Optional[torch.Tensor] = None
    texel_uv: Optional[torch.Tensor] = None
    depth: Optional[torch.Tensor] = None
    shell: Optional[torch.Tensor] = None
    info: Optional[dict] = None

    @property
    def grid_shape(self):
        return tuple(self.occupancy.shape)

    def texels_to_grid(self, values, fill=0.0):
        """Place per-texel values (N, C) on the voxel grid: (C, D, H, W), ``fill`` elsewhere (differentiable)."""
        if not isinstance(values, torch.Tensor) or values.dim() != 2 or values.shape[0] != len(self.texel_voxels):
            raise ValueError(f"values: expected a tensor of shape ({len(self.texel_voxels)}, C), got "
                             f"{tuple(values.shape) if isinstance(values, torch.Tensor) else type(values).__name__}")
        d, h, w = self.grid_shape
        grid = torch.full((values.shape[1], d * h * w), float(fill), dtype=values.dtype)
        k, j, i = self.texel_voxels.unbind(1)
        grid = grid.index_copy(1, (k * h + j) * w + i, values.t())
        return grid.view(values.shape[1], d, h, w)

    def save(self, path):
        """Write an ``.npz`` (atomically: a temporary file, then rename)."""
        arrays = {}
        for f in fields(self):
            v = getattr(self, f.name)
            if v is None:
                continue
            if f.name == "info":
                arrays["info_json"] = np.array(json.dumps(v))
                continue
            arrays[f.name] = v.numpy() if isinstance(v, torch.Tensor) else np.asarray(v)
        tmp = f"{path}.partial.npz"
        try:
            np.savez_compressed(tmp, **arrays)
            os.replace(tmp, path)
        except BaseException:  # Ctrl-C or a full disk: no partial file left beside the folder's others
            with contextlib.suppress(OSError):
                os.unlink(tmp)
            raise

    @staticmethod
    def load(path):
        """Read an ``.npz`` written by :meth:`save`; truncated or foreign files are refused."""
        try:
            with np.load(path, allow_pickle=False) as data:
                arrays = {k: data[k] for k in data.files}
        except Exception as error:  # zipfile/ValueError/OSError: corrupt, truncated or not an npz
            raise ValueError(f"path: {path!r} is not a readable voxel-object .npz ({error})") from None
        required = ("origin", "voxel_size", "occupancy", "sdf", "band_mm", "texel_voxels", "texel_points",
                    "texel_normals")
        missing = [k for k in required if k not in arrays]
        if missing:
            raise ValueError(f"path: {path!r} lacks {missing}: not a voxel object")
        kw = {}
        if "info_json" in arrays:
            kw["info"] = json.loads(str(arrays["info_json"]))
        for f in fields(VoxelObject):
            if f.name not in arrays or f.name == "info":
                continue
            v = arrays[f.name]
            if f.name == "origin":
                kw[f.name] = tuple(float(x) for x in v)
            elif f.name in ("voxel_size", "band_mm"):
                kw[f.name] = float(v)
            else:
                kw[f.name] = torch.from_numpy(v)
        obj = VoxelObject(**kw)
        d, h, w = obj.grid_shape
        if tuple(obj.sdf.shape) != (d + 1, h + 1, w + 1):
            raise ValueError(f"path: {path!r} holds an sdf of shape {tuple(obj.sdf.shape)} for a {d, h, w} grid")
        return obj


def _oriented(mesh):
    """(mesh with outward faces, merged vertices V (n, 3), faces F (m, 3), closed, fixes): faces wound against
    their neighbours are flipped (trimesh.repair.fix_winding; the textured mesh gets the same flips, so face ids
    and UVs stay valid), and the whole mesh is inverted when its signed volume is negative (wound inward).
    ``closed`` (watertight with consistent winding after merging seam-split vertices) allows the pseudonormal sign
    and ray parity; otherwise the winding number decides. ``fixes``: {"flipped_faces", "inverted"}."""
    import trimesh

    merged = mesh.copy()
    merged.merge_vertices(merge_tex=True, merge_norm=True)
    flipped = 0
    if not merged.is_winding_consistent:
        before = np.asarray(merged.faces).copy()
        trimesh.repair.fix_winding(merged)
        changed = np.flatnonzero((np.asarray(merged.faces) != before).any(1))
        if len(changed):
            faces = np.asarray(mesh.faces).copy()
            faces[changed] = faces[changed][:, ::-1]
            mesh = mesh.copy()
            mesh.faces = faces
            flipped = int(len(changed))
    inverted = bool(merged.volume < 0)
    if inverted:
        mesh = mesh.copy()
        mesh.invert()
        merged.invert()
    closed = bool(merged.is_watertight and merged.is_winding_consistent)
    V = np.ascontiguousarray(merged.vertices, dtype=np.float64)
    F = np.ascontiguousarray(merged.faces, dtype=np.int64)
    return mesh, V, F, closed, {"flipped_faces": flipped, "inverted": inverted}


def _signed_band(P, V, F, closed, band):
    """Signed distances (mm) of points P (n, 3) within ``band`` of the surface, NaN beyond (igl prunes those)."""
    import igl

    P = np.ascontiguousarray(P)
    if closed:  # angle-weighted pseudonormals give the exact sign of a closed, consistently wound mesh
        S, _, _, _ = igl.signed_distance(P, V, F, sign_type=igl.SIGNED_DISTANCE_TYPE_PSEUDONORMAL,
                                         lower_bound=-band, upper_bound=band)
        return S
    S, _, _, _ = igl.signed_distance(P, V, F, sign_type=igl.SIGNED_DISTANCE_TYPE_UNSIGNED, lower_bound=-band,
                                     upper_bound=band)
    near = np.isfinite(S)
    if near.any():
        S[near] = np.where(_inside_winding(P[near], V, F), -S[near], S[near])
    return S


def _inside_winding(P, V, F):
    """Inside by the fast generalised winding number (|w| > 1/2: holes, duplicated faces and flipped parts too)."""
    import igl

    return np.abs(igl.fast_winding_number(V, F, np.ascontiguousarray(P))) > 0.5


def _parity_inside(mesh_merged, xs, ys, z0, z_step, nz, rng):
    """Inside/outside at the points (xs[i] + δx, ys[j] + δy, z0 + k·z_step) of a closed mesh by the parity of
    embree ray hits along +z, one ray per (j, i) column; δ is a tiny random offset (≤ 1e-4 of a step) so rays do
    not run along grid-aligned edges. Points closer to the surface than the offset may be wrong: callers use it
    only farther out. Returns (inside (nz, ny, nx) bool, bad (ny, nx) bool: columns with an odd hit count)."""
    from trimesh.ray.ray_pyembree import RayMeshIntersector

    ny, nx = len(ys), len(xs)
    intersector = RayMeshIntersector(mesh_merged)
    toggles = np.zeros((nz + 1, ny, nx), dtype=np.uint8)
    todo = np.ones((ny, nx), dtype=bool)
    for _ in range(3):
        jj, ii = np.nonzero(todo)
        if not len(jj):
            break
        jitter = (rng.random((len(jj), 2)) - 0.5) * 2e-4 * z_step
        origins = np.stack([xs[ii] + jitter[:, 0], ys[jj] + jitter[:, 1], np.full(len(jj), z0 - z_step)], axis=1)
        directions = np.broadcast_to(np.array([0.0, 0.0, 1.0]), origins.shape)
        hits, ray, _ = intersector.intersects_location(origins, directions, multiple_hits=True)
        counts = np.bincount(ray, minlength=len(jj))
        even = counts % 2 == 0
        keep = even[ray]
        first_above = np.clip(np.ceil((hits[keep, 2] - z0) / z_step).astype(np.int64), 0, nz)
        np.add.at(toggles, (first_above, jj[ray[keep]], ii[ray[keep]]), 1)
        todo[jj[even], ii[even]] = False
    inside = np.bitwise_xor.accumulate(toggles[:-1] & 1, axis=0).astype(bool)
    return inside, todo


def check_grid_size(mesh, voxel_size, *, padding=1, max_bytes=MAX_GRID_BYTES):
    """The (W, H, D) voxel counts of ``mesh``'s grid at ``voxel_size`` (mm) with ``padding`` empty voxels round it;
    ValueError naming ``voxel_size`` when voxelising it would need more than ``max_bytes`` (what :func:`voxelize`
    allocates: the corners' float32 SDF, masks and labels, the voxels' occupancy, masks, depth and shell). Cheap: a
    command asks it before any work.

    Example:
        >>> import trimesh
        >>> check_grid_size(trimesh.creation.box((3.0, 2.0, 1.0)), 0.2).tolist()
        [17, 12, 7]
    """
    V = np.asarray(mesh.vertices, dtype=np.float64)
    lo, hi = V.min(0), V.max(0)
    # (W, H, D); the tolerance keeps an extent of exactly n voxels (3.0 / 0.2 = 15.000000000000002) at n
    dims = np.ceil((hi - lo) / voxel_size - 1e-9).astype(np.int64) + 2 * padding
    w, hh, d = (int(n) for n in dims)
    need = (d + 1) * (hh + 1) * (w + 1) * (4 + 1 + 1 + 4) + d * hh * w * (1 + 1 + 1 + 4 + 1)
    if need > max_bytes:
        raise ValueError(f"voxel_size: {voxel_size:g} mm gives a {d}×{hh}×{w} grid that needs about "
                         f"{need / 2**30:.1f} GiB (limit {max_bytes / 2**30:.1f} GiB); use a larger voxel or a "
                         f"smaller object")
    return dims


def voxelize(mesh, voxel_size, *, shell_mm=None, padding=1, band_voxels=3, max_bytes=MAX_GRID_BYTES, seed=0):
    """Voxelise a triangle mesh (mm) at ``voxel_size`` mm.

    How: exact point–triangle distances (libigl, AABB tree) are asked only where they matter. A coarse grid of
    every 4th corner finds the region within the band (plus the coarse half-diagonal); the corners there get exact
    signed distances (pseudonormal sign for closed meshes, fast winding number otherwise). Corners beyond the band
    take their sign from embree ray parity along z (closed meshes) or from one winding-number query per connected
    far region. A voxel centre takes the sign of any of its corners farther from the surface than the half
    diagonal; the few centres without one are asked directly. Depth is exact below the surface up to the shell.

    Args:
        mesh: a ``trimesh.Trimesh`` in mm (:func:`torch_appearance.geometry.load_mesh`); UVs + texture, vertex or
            face colours give the texel colours. Faces wound inward (negative volume) are inverted.
        voxel_size: voxel edge in mm, > 0 (300 DPI: 25.4 / 300).
        shell_mm: optional depth of the printable shell, mm; sets ``shell`` (depth exact to shell_mm + 2 voxels).
        padding: empty voxels around the object's bounding box (>= 1, so the SDF is > 0 on the outer corners).
        band_voxels: half-width of the exact SDF band in voxels (>= 2).
        max_bytes: refuse grids that would need more memory than this (the message names the size).
        seed: seed of the tiny ray offsets of the parity test (results do not depend on it unless a mesh is
            degenerate at that scale).

    Returns:
        A :class:`VoxelObject`; its ``info`` holds timings per step and how the signs were found.

    Example:
        >>> import trimesh
        >>> obj = voxelize(trimesh.creation.box((2.0, 2.0, 1.0)), 0.25)
        >>> obj.grid_shape, int(obj.occupancy.sum()), len(obj.texel_voxels), obj.info["closed"]
        ((6, 10, 10), 256, 184, True)
    """
    import igl
    import time
    import trimesh

    if not isinstance(mesh, trimesh.Trimesh):
        raise TypeError(f"mesh: expected a trimesh.Trimesh, got {type(mesh).__name__}")
    if len(mesh.faces) == 0:
        raise ValueError("mesh: expected triangles, got an empty mesh")
    h = check_real("voxel_size", voxel_size, lo=0.0, lo_open=True)
    padding = check_int("padding", padding, lo=1)
    band_voxels = check_int("band_voxels", band_voxels, lo=2)
    if shell_mm is not None:
        shell_mm = check_real("shell_mm", shell_mm, lo=0.0, lo_open=True)
    if not np.isfinite(np.asarray(mesh.vertices, dtype=np.float64)).all():
        raise ValueError("mesh: expected finite vertex coordinates")
    timings = {}
    clock = time.perf_counter()

    def lap(name):
        nonlocal clock
        now = time.perf_counter()
        timings[name] = now - clock
        clock = now

    V0 = np.asarray(mesh.vertices, dtype=np.float64)
    lo, hi = V0.min(0), V0.max(0)
    dims = check_grid_size(mesh, h, padding=padding, max_bytes=max_bytes)
    origin = lo - padding * h - (dims * h - (hi - lo) - 2 * padding * h) / 2  # centre the object in its grid
    w, hh, d = (int(n) for n in dims)
    mesh, V, F, closed, fixes = _oriented(mesh)
    lap("prepare")
    band = band_voxels * h
    depth_limit = band if shell_mm is None else max(band, shell_mm + 2 * h)
    half_diag = math.sqrt(3.0) / 2.0

    # 1. coarse corners (every 4th): unsigned distance up to the largest bound needed, +2√3·h (the farthest a fine
    #    point is from its nearest coarse corner), so that a fine point within r of the surface always has its
    #    nearest coarse corner within r + 2√3·h
    reach = 2.0 * math.sqrt(3.0) * h * (1 + 1e-9)
    nc = [(n + 2) // 4 + 1 for n in (d, hh, w)]
    cz, cy, cx = (origin[axis] + 4 * h * np.arange(n) for axis, n in zip((2, 1, 0), nc))
    Pc = np.stack(np.meshgrid(cx, cy, cz, indexing="ij"), axis=-1).transpose(2, 1, 0, 3).reshape(-1, 3)
    bound = max(band, depth_limit) + reach
    coarse, _, _, _ = igl.signed_distance(np.ascontiguousarray(Pc), V, F,
                                          sign_type=igl.SIGNED_DISTANCE_TYPE_UNSIGNED,
                                          lower_bound=-bound, upper_bound=bound)
    coarse = np.where(np.isfinite(coarse), coarse, np.inf).reshape(nc)
    lap("coarse")

    def near_corners(limit):
        """(d+1, h+1, w+1) bool: corners whose nearest coarse corner is within ``limit`` + reach."""
        c = coarse <= limit + reach
        return c[np.ix_((np.arange(d + 1) + 2) // 4, (np.arange(hh + 1) + 2) // 4, (np.arange(w + 1) + 2) // 4)]

    # 2. exact signed distances at the candidate corners; those beyond the band come back NaN
    sdf = np.full((d + 1, hh + 1, w + 1), np.nan, dtype=np.float32)
    cand = np.flatnonzero(near_corners(band))
    kji = np.stack(np.unravel_index(cand, sdf.shape), axis=1)
    sdf.ravel()[cand] = _signed_band(origin + kji[:, ::-1] * h, V, F, closed, band)
    del kji
    far = np.isnan(sdf)
    lap("band")

    # 3. the sign of far corners: a 6-connected far region cannot cross the surface
    parity_fallback, far_asked = 0, 0
    try:
        import trimesh.ray.ray_pyembree  # noqa: F401  (embreex; without it the winding number signs the far regions)
        rays = closed
    except ImportError:
        rays = False
    if rays:
        inside, bad = _parity_inside(trimesh.Trimesh(V, F, process=False), origin[0] + h * np.arange(w + 1),
                                     origin[1] + h * np.arange(hh + 1), origin[2], h, d + 1,
                                     np.random.default_rng(seed))
        if bad.any():  # columns whose rays kept an odd hit count: winding number for their far corners
            cols = far & bad[None]
            parity_fallback = int(bad.sum())
            kji = np.argwhere(cols)
            inside[cols] = _inside_winding(origin + kji[:, ::-1] * h, V, F)
        sdf[far] = np.where(inside[far], -band, band)
        del inside
    else:
        # open meshes: the winding number's ½ level may cross space far from the surface (across a hole), so far
        # corners cannot share one sign per connected region. The coarse corners get the winding number; a far
        # corner in a coarse cell whose 8 corners agree takes their sign, the others are asked directly.
        coarse_in = _inside_winding(Pc, V, F).reshape(nc)
        agree = np.ones([n - 1 for n in nc], dtype=bool)
        first = coarse_in[:-1, :-1, :-1]
        for dz in (0, 1):
            for dy in (0, 1):
                for dx in (0, 1):
                    agree &= coarse_in[dz:dz + nc[0] - 1, dy:dy + nc[1] - 1, dx:dx + nc[2] - 1] == first
        cell = [np.minimum(np.arange(n + 1) // 4, m - 2) for n, m in zip((d, hh, w), nc)]
        uniform = agree[np.ix_(*cell)]
        inside = first[np.ix_(*cell)]
        ask = far & ~uniform
        if ask.any():
            kji = np.argwhere(ask)
            inside[ask] = _inside_winding(origin + kji[:, ::-1] * h, V, F)
            far_asked = int(ask.sum())
        sdf[far] = np.where(inside[far], -band, band)
        del inside, uniform
    lap("far_sign")

    # 4. occupancy of the voxel centres. Closed meshes: cells with only far corners share their sign; a near cell
    #    takes the sign of a corner farther than the half diagonal from the surface (no surface can lie between);
    #    the rest ask a signed query at the centre. Open meshes: the winding number at every centre near the
    #    surface or with corners of both signs (the ½ level crossing a hole), the corners' sign elsewhere.
    near_corner = ~far
    del far
    cell_near = np.zeros((d, hh, w), dtype=bool)
    for dz in (0, 1):
        for dy in (0, 1):
            for dx in (0, 1):
                cell_near |= near_corner[dz:dz + d, dy:dy + hh, dx:dx + w]
    del near_corner
    occ = sdf[:-1, :-1, :-1] < 0
    if closed:
        kji = np.argwhere(cell_near)
        flat = (kji[:, 0] * (hh + 1) + kji[:, 1]) * (w + 1) + kji[:, 2]
        offsets = np.array([(dz * (hh + 1) + dy) * (w + 1) + dx
                            for dz in (0, 1) for dy in (0, 1) for dx in (0, 1)])
        corner_values = sdf.ravel()[flat[:, None] + offsets[None, :]]
        decisive = np.abs(corner_values) > half_diag * h * (1 + 1e-6)
        near_occ = corner_values[np.arange(len(flat)), np.argmax(decisive, axis=1)] < 0
        ask = ~decisive.any(1)
        if ask.any():
            S, _, _, _ = igl.signed_distance(np.ascontiguousarray(origin + (kji[ask][:, ::-1] + 0.5) * h), V, F,
                                             sign_type=igl.SIGNED_DISTANCE_TYPE_PSEUDONORMAL)
            near_occ[ask] = S < 0
        occ[cell_near] = near_occ
        asked = int(ask.sum())
        del kji, flat, corner_values, decisive
    else:
        negative = sdf < 0
        ask = cell_near
        for dz in (0, 1):
            for dy in (0, 1):
                for dx in (0, 1):
                    ask |= negative[dz:dz + d, dy:dy + hh, dx:dx + w] != occ
        del negative
        kji = np.argwhere(ask)
        occ[ask] = _inside_winding(origin + (kji[:, ::-1] + 0.5) * h, V, F)
        asked = len(kji)
    del cell_near
    lap("occupancy")

    # 5. texels: inside voxels with an outside 6-neighbour; their closest surface points, normals and colours
    border = np.zeros_like(occ)
    border[0] = border[-1] = True
    border[:, 0] = border[:, -1] = True
    border[:, :, 0] = border[:, :, -1] = True
    border[1:] |= ~occ[:-1]
    border[:-1] |= ~occ[1:]
    border[:, 1:] |= ~occ[:, :-1]
    border[:, :-1] |= ~occ[:, 1:]
    border[:, :, 1:] |= ~occ[:, :, :-1]
    border[:, :, :-1] |= ~occ[:, :, 1:]
    texel_kji = np.argwhere(occ & border)
    del border
    tex_centres = origin + (texel_kji[:, ::-1] + 0.5) * h
    _, fid, closest = igl.point_mesh_squared_distance(np.ascontiguousarray(tex_centres),
                                                      np.ascontiguousarray(mesh.vertices, dtype=np.float64),
                                                      np.ascontiguousarray(mesh.faces, dtype=np.int64))
    normals, colours, uv = surface_attributes(mesh, fid, closest)
    lap("texels")

    # 6. depth of the inside voxel centres: exact (unsigned) up to depth_limit, depth_limit beyond; only centres
    #    whose nearest coarse corner is within depth_limit + reach can be that close
    depth = np.zeros(occ.shape, dtype=np.float32)
    c = coarse <= depth_limit + reach
    maybe = c[np.ix_((2 * np.arange(d) + 5) // 8, (2 * np.arange(hh) + 5) // 8, (2 * np.arange(w) + 5) // 8)]
    maybe &= occ
    depth[occ] = depth_limit
    kji = np.argwhere(maybe)
    dist, _, _, _ = igl.signed_distance(np.ascontiguousarray(origin + (kji[:, ::-1] + 0.5) * h), V, F,
                                        sign_type=igl.SIGNED_DISTANCE_TYPE_UNSIGNED, lower_bound=-depth_limit,
                                        upper_bound=depth_limit)
    depth[maybe] = np.where(np.isfinite(dist), np.minimum(dist, depth_limit), depth_limit)
    shell = None if shell_mm is None else torch.from_numpy(occ & (depth < shell_mm))
    lap("depth")
    info = {"closed": closed, **fixes, "ray_parity": rays, "band_corners": int(len(cand)),
            "parity_fallback_columns": parity_fallback, "far_corners_asked": far_asked, "centres_asked": asked,
            "depth_queries": int(len(kji)), "timings_s": timings}
    return VoxelObject(origin=tuple(float(v) for v in origin), voxel_size=h, occupancy=torch.from_numpy(occ),
                       sdf=torch.from_numpy(sdf), band_mm=float(band), texel_voxels=torch.from_numpy(texel_kji),
                       texel_points=torch.from_numpy(closest), texel_normals=torch.from_numpy(normals),
                       texel_colors=None if colours is None else torch.from_numpy(colours),
                       texel_uv=None if uv is None else torch.from_numpy(uv),
                       depth=torch.from_numpy(depth), shell=shell, info=info)
