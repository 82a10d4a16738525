"""The 2.5D "remapped" baseline of a textured object (thesis part II §3.2; Elek et al. 2017 extended to 3D).

The planar pipeline optimises a slab of the object's texture in UV space; the slab is then wrapped around the
object: every shell voxel looks its mixture up in the slab column of the UV coordinates of its nearest surface
point, at the layer of its depth below the surface. Stretch of the UV map changes the scattering distances, and
thin parts see light from both sides, which the planar solution never modelled; the thesis measures CIEDE2000 15
for the remapped vase against 10 for the native 3D solution.

Steps (:func:`prepare_uv_slab`, the print loop, :func:`wrap_slab_weights`; the loop's
:func:`~torch_appearance.pipelines.print.loop.remap_baseline` runs them in turn):

1. **UV-space target.** The mesh's base-colour texture (linear RGB) resampled so that one slab texel covers about
   one voxel pitch square of surface (:func:`slab_size`). Pixels no UV triangle covers take the colour of the
   nearest covered pixel (the thesis "fills the borders using an inpainting algorithm": the planar optimisation
   should not see artificial contrast between islands and background, which it would compensate at the island
   borders).
2. **Planar optimisation.** :func:`~torch_appearance.pipelines.print.optimize_print` of a slab as
   thick as the shell (``cfg.shell_mm``) with the run's inks, spp, iterations, seed and fixed ink fractions,
   written to ``work_dir/slab``; its ``mixture.npz`` holds the slab's weights (N, D_s, H_s, W_s).
3. **Remap.** Per shell voxel: the closest surface point (libigl AABB tree), its UV by barycentric interpolation,
   the slab column ``row = ⌊(1 − v)·H_s⌋, col = ⌊u·W_s⌋`` (v up, as image files store textures; UVs outside
   [0, 1] wrap), the layer ``D_s − 1 − ⌊depth / h⌋`` clipped to the slab; every other voxel holds the core ink.
"""
import dataclasses
import math
import os
import time

import numpy as np
import torch

from ... import io as ta_io
from ...geometry.surface import barycentric

__all__ = ["prepare_uv_slab", "wrap_slab_weights", "slab_size", "uv_target_image", "remap_slab", "MAX_SLAB_TEXELS"]

#: Largest slab (texels, H_s·W_s) :func:`slab_size` asks for before it coarsens the slab (4 Mi ≈ 2048²: a 300-DPI
#: slab of that size spans about 30 000 mm² of surface, e.g. a 15 cm vase).
MAX_SLAB_TEXELS = 2 ** 22


# ------------------------------------------------------------------------------------------------ UV layout
def _uv_layout(mesh):
    """Per-vertex UVs (n, 2) float64 of a mesh; a ValueError naming why when it has none."""
    visual = getattr(mesh, "visual", None)
    kind = getattr(visual, "kind", None)
    uv = getattr(visual, "uv", None) if kind == "texture" else None
    if uv is None or len(uv) != len(mesh.vertices):
        what = {"vertex": "vertex colours", "face": "face colours"}.get(kind, "no texture")
        raise ValueError(f"mesh: has {what} but no UV layout (texture coordinates); the 2.5D remapped baseline "
                         f"optimises a slab in UV space and looks its columns up by UV, so it needs a UV-mapped, "
                         f"textured mesh (the native 3D optimisation takes vertex-coloured meshes)")
    uv = np.asarray(uv, dtype=np.float64)
    if not np.isfinite(uv).all():
        raise ValueError("mesh: has non-finite texture coordinates")
    return uv


def slab_size(mesh, voxel_size, max_texels=MAX_SLAB_TEXELS):
    """Slab texels (H_s, W_s) for the unit UV square such that one slab texel ≈ one voxel pitch square of surface.

    Rule: the UV square stands for ``S / U`` mm² of surface, S the surface area and U the UV area (both summed
    over the faces whose UV triangles are not degenerate: the area-weighted stretch, which counts overlapping or
    tiled UV islands as often as they are used). The split between W_s and H_s follows the mean lengths that one
    unit of u and of v spans on the surface, L_u and L_v (RMS over the faces, weighted by UV area; their ratio
    is clipped to [1/8, 8]), scaled so that L_u·L_v = S / U:  W_s = L_u / h, H_s = L_v / h. A slab beyond
    ``max_texels`` is coarsened uniformly (``scale`` < 1).

    The voxelised surface's texel count would overestimate the area on oblique faces (a plane at normal n exposes
    about (|n_x| + |n_y| + |n_z|)·S / h² voxels, up to √3 times S / h²), so the mesh area is used.

    Args:
        mesh: a ``trimesh.Trimesh`` with UVs, mm. voxel_size: h, mm.
        max_texels: cap on H_s·W_s.

    Returns:
        ((H_s, W_s), info dict: surface_area_mm2, uv_area, mm_per_u, mm_per_v, scale, degenerate_area_fraction).
    """
    uv = _uv_layout(mesh)
    V = np.asarray(mesh.vertices, dtype=np.float64)
    F = np.asarray(mesh.faces, dtype=np.int64)
    tri, tuv = V[F], uv[F]
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]                    # (M, 3)
    d1, d2 = tuv[:, 1] - tuv[:, 0], tuv[:, 2] - tuv[:, 0]                    # (M, 2)
    area3 = 0.5 * np.linalg.norm(np.cross(e1, e2), axis=1)
    det = d1[:, 0] * d2[:, 1] - d2[:, 0] * d1[:, 1]
    area2 = 0.5 * np.abs(det)
    ok = area2 > 1e-12 * max(float(area2.max(initial=0.0)), 1e-300)
    if not ok.any() or not area3[ok].sum() > 0:
        raise ValueError("mesh: its UV triangles have no area (degenerate texture coordinates)")
    surface, uv_area = float(area3[ok].sum()), float(area2[ok].sum())
    # Jacobian of UV → surface: [e1 e2] = [∂P/∂u ∂P/∂v]·[d1 d2]
    inv = np.stack([np.stack([d2[:, 1], -d2[:, 0]], 1), np.stack([-d1[:, 1], d1[:, 0]], 1)], 1)  # (M, 2, 2)·det
    inv = inv[ok] / det[ok, None, None]
    E = np.stack([e1[ok], e2[ok]], axis=2)                                    # (M, 3, 2)
    J = E @ inv                                                               # (M, 3, 2): ∂P/∂u, ∂P/∂v
    w = area2[ok] / uv_area
    lu = math.sqrt(float((w * (J[:, :, 0] ** 2).sum(1)).sum()))
    lv = math.sqrt(float((w * (J[:, :, 1] ** 2).sum(1)).sum()))
    aspect = min(8.0, max(1.0 / 8.0, lv / lu)) if lu > 0 and lv > 0 else 1.0
    unit = math.sqrt(surface / uv_area)                                       # mm per UV unit, isotropic mean
    mm_u, mm_v = unit / math.sqrt(aspect), unit * math.sqrt(aspect)
    ws, hs = mm_u / voxel_size, mm_v / voxel_size
    scale = min(1.0, math.sqrt(max_texels / (ws * hs)))
    size = (max(1, int(round(hs * scale))), max(1, int(round(ws * scale))))
    info = {"surface_area_mm2": surface, "uv_area": uv_area, "mm_per_u": mm_u, "mm_per_v": mm_v, "scale": scale,
            "degenerate_area_fraction": float(area3[~ok].sum() / max(area3.sum(), 1e-300))}
    return size, info


def _uv_coverage(mesh, size):
    """(H, W) bool: texels whose centre lies in a (non-collapsed) UV triangle, tiled layouts included."""
    from ...geometry.bake import uv_face_image

    return uv_face_image(mesh, size) >= 0


def _base_colour_texture(mesh, texture=None):
    """The mesh's base-colour texture as linear RGB (h, w, 3) float32 (``texture``: an image file for a mesh with
    UVs but no material image)."""
    from ...color import srgb_to_linear

    material = getattr(mesh.visual, "material", None)
    image = getattr(material, "image", None)
    if image is None:
        image = getattr(material, "baseColorTexture", None)
    if image is None:
        if texture is None:
            raise ValueError("mesh: has UVs but no base-colour texture; attach one (texture=..., --texture)")
        from .target_images import load_target
        return load_target(texture, name="texture")
    srgb = np.asarray(image.convert("RGB"), dtype=np.float64) / 255.0
    return np.asarray(srgb_to_linear(torch.from_numpy(srgb)), dtype=np.float32)


def uv_target_image(mesh, voxel_size, *, texture=None, fill=True, max_texels=MAX_SLAB_TEXELS, crop=False):
    """The slab target in UV space: the base-colour texture (linear RGB) resampled to :func:`slab_size` (area
    averaging when shrinking, bilinear when enlarging); with ``fill`` the pixels outside every UV island take the
    colour of the nearest covered pixel.

    With ``crop`` only the bounding box of the covered pixels is kept (a texture atlas whose islands use part of
    the UV square costs no slab texels elsewhere); ``info["window"]`` = (row0, col0, H_s, W_s) places the crop in
    the full (H_s, W_s) grid (:func:`remap_slab` takes it).

    Returns:
        ((H_s, W_s, 3) float32 linear RGB, row 0 = v 1, or its crop; info dict of :func:`slab_size` +
        covered_fraction (of the returned image), texture_hw, window).
    """
    import cv2

    (hs, ws), info = slab_size(mesh, voxel_size, max_texels)
    tex = _base_colour_texture(mesh, texture)
    th, tw = tex.shape[:2]
    interp = cv2.INTER_AREA if hs * ws < th * tw else cv2.INTER_LINEAR
    image = cv2.resize(np.ascontiguousarray(tex, dtype=np.float32), (ws, hs), interpolation=interp)
    image = np.clip(image.reshape(hs, ws, 3), 0.0, 1.0)
    covered = _uv_coverage(mesh, (hs, ws))
    if fill and covered.any() and not covered.all():
        from scipy import ndimage
        _, (ri, ci) = ndimage.distance_transform_edt(~covered, return_indices=True)
        image = image[ri, ci]
    window = (0, 0, hs, ws)
    if crop and covered.any():
        rows, cols = np.flatnonzero(covered.any(1)), np.flatnonzero(covered.any(0))
        r0, r1, c0, c1 = int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1
        image, covered, window = image[r0:r1, c0:c1], covered[r0:r1, c0:c1], (r0, c0, hs, ws)
    info.update(covered_fraction=float(covered.mean()), texture_hw=[int(th), int(tw)], window=list(window))
    return np.ascontiguousarray(image, dtype=np.float32), info


# ------------------------------------------------------------------------------------------------ remap
def _wrap(t):
    """Texture coordinates outside [0, 1] wrap (repeat); [0, 1] itself is kept, so an island's edge at 1 stays."""
    return np.where((t < 0) | (t > 1), t - np.floor(t), t)


def remap_slab(target, slab_weights, core, *, window=None, chunk=1 << 20):
    """Wrap slab weights (N, D_s, H_s, W_s) around an object: every shell voxel takes the slab column of its
    nearest surface point's UV at the layer of its depth (see the module docstring); other voxels ``core`` (N,).
    ``window`` = (row0, col0, H_full, W_full): the slab is that crop of a slab spanning the whole UV square (see
    :func:`uv_target_image`); None: the slab spans it.

    Returns:
        ((N, D, H, W) float32 weights, info dict: counts and seconds).
    """
    import igl

    t0 = time.perf_counter()
    slab = np.asarray(slab_weights, dtype=np.float32)
    if slab.ndim != 4:
        raise ValueError(f"slab_weights: expected (N, D, H, W), got shape {slab.shape}")
    n, ds, hc, wc = slab.shape
    r0, c0, hs, ws = (0, 0, hc, wc) if window is None else (int(x) for x in window)
    if not (0 <= r0 and 0 <= c0 and r0 + hc <= hs and c0 + wc <= ws):
        raise ValueError(f"window: a {hc}×{wc} slab at row {r0}, column {c0} does not fit in {hs}×{ws}")
    core = np.asarray(core, dtype=np.float32)
    if core.shape != (n,):
        raise ValueError(f"core: expected {n} ink weights, got shape {core.shape}")
    mesh = target.mesh
    uv = _uv_layout(mesh)
    V = np.ascontiguousarray(mesh.vertices, dtype=np.float64)
    F = np.ascontiguousarray(mesh.faces, dtype=np.int64)
    obj = target.obj
    h = float(obj.voxel_size)
    origin = np.asarray(obj.origin, dtype=np.float64)
    d, hh, w = obj.grid_shape
    shell = target.support.numpy().reshape(-1)
    flat = np.flatnonzero(shell)
    depth_all = obj.depth.numpy().reshape(-1)
    out = np.empty((n, d * hh * w), dtype=np.float32)
    out[:] = core[:, None]
    clipped = 0
    for s in range(0, len(flat), chunk):
        idx = flat[s:s + chunk]
        k, rem = np.divmod(idx, hh * w)
        j, i = np.divmod(rem, w)
        centres = origin + (np.stack([i, j, k], axis=1) + 0.5) * h
        _, fid, closest = igl.point_mesh_squared_distance(np.ascontiguousarray(centres), V, F)
        tri = V[F[fid]]
        bary = barycentric(closest, tri[:, 0], tri[:, 1], tri[:, 2])
        p_uv = (uv[F[fid]] * bary[:, :, None]).sum(1)
        u, v = _wrap(p_uv[:, 0]), _wrap(p_uv[:, 1])
        row = np.clip(np.floor((1.0 - v) * hs).astype(np.int64) - r0, 0, hc - 1)
        col = np.clip(np.floor(u * ws).astype(np.int64) - c0, 0, wc - 1)
        below = np.floor(depth_all[idx].astype(np.float64) / h).astype(np.int64)
        layer = ds - 1 - below
        clipped += int((layer < 0).sum())
        layer = np.clip(layer, 0, ds - 1)
        out[:, idx] = slab[:, layer, row, col]
    info = {"shell_voxels": int(len(flat)), "deeper_than_slab": clipped, "remap_s": time.perf_counter() - t0}
    return torch.from_numpy(out.reshape(n, d, hh, w)), info


# ------------------------------------------------------------------------------------------------ the baseline
def _slab_fixed(specs, size, work_dir, window=None, mesh=None):
    """The object run's ``INK=FRACTION:MASK`` constraints for the UV-space slab: ``all`` and ``depth:A-B`` (depth
    below the surface = below the slab's top face) stay; a texture-space PNG mask is resampled (nearest) to the
    full UV slab and cropped to ``window`` (see :func:`uv_target_image`), and ``material:NAME`` becomes the slab
    texels inside the UV triangles of that material's faces (``mesh``); both are written to ``work_dir`` as PNGs."""
    import cv2

    from .fixed_fractions import parse_fixed

    r0, c0, hs, ws = window if window is not None else (0, 0, *size)
    out = []
    for n, spec in enumerate(specs):
        ink, fraction, terms = parse_fixed(spec)
        slab_terms = []
        for t, term in enumerate(terms):
            if term.lower().endswith(".png"):
                mask = ta_io.read_mask(term, name="fixed: mask image").astype(np.uint8) * 255
                mask = cv2.resize(mask, (ws, hs), interpolation=cv2.INTER_NEAREST)
            elif term.startswith("material:"):
                from ...geometry.bake import uv_face_image

                name = term[len("material:"):].strip()
                names = list(mesh.metadata.get("material_names", [])) if mesh is not None else []
                if name not in names:
                    raise ValueError(f"fixed: {spec!r}: the mesh has no material {name!r}; its materials are {names}")
                faces = uv_face_image(mesh, (hs, ws))
                of_material = np.asarray(mesh.metadata["face_materials"]) == names.index(name)
                mask = np.where(faces >= 0, of_material[np.maximum(faces, 0)], False).astype(np.uint8) * 255
            else:
                slab_terms.append(term)
                continue
            mask = np.ascontiguousarray(mask[r0:r0 + size[0], c0:c0 + size[1]])
            term = os.path.join(work_dir, f"fixed_{n}_{t}.png")
            _, png = cv2.imencode(".png", mask)
            ta_io.atomic_write_bytes(term, png.tobytes())
            slab_terms.append(term)
        out.append(f"{ink}={fraction!r}:{'&'.join(slab_terms)}")
    return tuple(out)


def prepare_uv_slab(target, cfg, *, work_dir, log=print, max_texels=MAX_SLAB_TEXELS):
    """Steps 1 and the settings of step 2 of the 2.5D remapped baseline (thesis part II §3.2): the slab target in
    the mesh's UV space, written to ``work_dir/uv_target.exr``, and the slab run's settings.

    Args:
        target: an :class:`~torch_appearance.pipelines.print.ObjectTarget` whose ``mesh`` (the trimesh mesh that
            was voxelised, mm) has UVs and a base-colour texture (or ``cfg.texture``).
        cfg: the object run's :class:`~torch_appearance.pipelines.print.PrintConfig`; the slab run keeps its inks,
            gamma, optimiser, spp, iterations, seed, printer DPI, table and fixed ink fractions (:func:`_slab_fixed`);
            its voxel pitch is the object's, its thickness ``cfg.shell_mm``; an environment map (objects only) is
            dropped: the slab is lit uniformly.
        work_dir: folder for ``uv_target.exr`` and the slab's run folder ``slab/``.
        log: one-line messages. max_texels: cap on the slab's H_s·W_s.

    Returns:
        (the slab run's PrintConfig (``out`` = ``work_dir/slab``), info dict: the slab-size numbers, ``window`` (the
        slab's crop of the UV square, for :func:`wrap_slab_weights`) and ``uv_target``).

    Raises:
        ValueError: the mesh has no UV layout (vertex/face colours) or no texture.
    """
    mesh = _uv_mesh(target)
    h = float(target.obj.voxel_size)
    work_dir = os.fspath(work_dir)
    os.makedirs(work_dir, exist_ok=True)
    image, info = uv_target_image(mesh, h, texture=cfg.texture, max_texels=max_texels, crop=True)
    window = info["window"]
    exr = os.path.join(work_dir, "uv_target.exr")
    ta_io.write_exr(exr, image)
    if info["scale"] < 1.0:
        log(f"remap_baseline: the UV slab is capped at {max_texels} texels: one slab texel spans "
            f"{1 / info['scale']:.2f} voxels of surface")
    log(f"remap_baseline: UV-space slab {image.shape[0]}×{image.shape[1]} texels (the UV islands' bounding box "
        f"in a {window[2]}×{window[3]} UV square; {info['mm_per_u']:.1f} × {info['mm_per_v']:.1f} mm "
        f"per UV unit, {100 * info['covered_fraction']:.0f}% covered), {cfg.shell_mm} mm thick")
    # an environment map lights objects only; fixed fractions carry over (texture-space masks resampled)
    fixed = _slab_fixed(getattr(cfg, "fixed", ()), image.shape[:2], work_dir, window, mesh)
    slab_cfg = dataclasses.replace(cfg, mesh=None, texture=None, envmap=None, fixed=fixed, target=exr,
                                   bottom_target=None, thickness_mm=cfg.shell_mm, dpi=25.4 / h, width_mm=None,
                                   height_mm=None, remap_baseline=False, naive_baseline=False, views=0,
                                   out=os.path.join(work_dir, "slab"))
    return slab_cfg, info


def wrap_slab_weights(target, slab_weights, inks, core_ink, *, window=None, log=print):
    """Step 3 of the 2.5D remapped baseline: a slab's mixture (N, D_s, H_s, W_s) wrapped around the object
    (:func:`remap_slab`), deeper voxels ``core_ink``.

    Args:
        target: the :class:`~torch_appearance.pipelines.print.ObjectTarget` (its ``mesh`` has UVs).
        slab_weights: (N, D_s, H_s, W_s) slab mixture for ``inks``. inks: the run's InkSet. core_ink: ink name.
        window: (row0, col0, H_full, W_full) of a cropped slab (:func:`prepare_uv_slab`'s ``info["window"]``).

    Returns:
        ((N, D, H, W) float32 weights on the object's grid (each voxel's weights sum to 1), info dict: slab_hw,
        slab_depth, texels, remap counts and seconds).

    Raises:
        ValueError: the mesh has no UV layout; slab weights of the wrong inks.
    """
    _uv_mesh(target)
    core = np.zeros(len(inks), dtype=np.float32)
    core[inks.index(core_ink)] = 1.0
    slab_weights = np.asarray(slab_weights, dtype=np.float32)
    if slab_weights.ndim != 4 or slab_weights.shape[0] != len(inks):
        raise ValueError(f"slab_weights: expected ({len(inks)}, D, H, W) for the inks {list(inks.names)}, got shape "
                         f"{slab_weights.shape}")
    weights, remap_info = remap_slab(target, slab_weights, core, window=window)
    info = {**remap_info, "slab_depth": int(slab_weights.shape[1]), "slab_hw": list(slab_weights.shape[2:]),
            "texels": int(len(target.obj.texel_voxels))}
    log(f"remap_baseline: {remap_info['shell_voxels']} shell voxels remapped from a {slab_weights.shape[1]}-layer "
        f"slab in {remap_info['remap_s']:.1f} s")
    return weights, info


def _uv_mesh(target):
    """The target's mesh, refused when it is missing or has no UV layout (before any work)."""
    mesh = getattr(target, "mesh", None)
    if mesh is None:
        raise ValueError("target: the object target keeps no mesh (target.mesh); the 2.5D baseline needs its UVs")
    _uv_layout(mesh)
    return mesh
