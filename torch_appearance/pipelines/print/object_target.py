"""A voxelised textured object as a print target (TOG 2021 §3.3, thesis part II): what the print-optimisation loop
needs of an object: the same methods as the slab target of :mod:`.slab_target`.

The object's surface is a smooth dielectric given by its SDF grid; the texel sensor shoots from the surface texels
along the inward normal; only a shell of voxels within ``shell_mm`` of the surface carries mixture logits, deeper
voxels hold the core ink. The appearance losses see the texel colours at their voxel positions through the sparse
texel path (:class:`~torch_appearance.nn.texel_losses.TexelFilters`): the same E1/E2/E3 as on the voxel grid
(:meth:`VoxelObject.texels_to_grid`, masked to the texels) at a cost that follows the texels, not the bounding box.
"""
import dataclasses
import functools
import io
import os
import time
import typing

import numpy as np
import torch

from ... import distributed
from ... import io as ta_io
from ...fabrication.export import VOID
from ...fabrication.quantize import micro_grid_pitch
from ...render import ConstantEnvironment, EnvironmentMap, Scene, SDFBoundary, SurfaceTexels
from ...render.volpath import render_scene_indexed
from ..runs import check_memory
from .baselines import naive_extrusion
from .config import iteration_seed
from .rendering import on_device, render, replay_seed
from .run_folder import save_image

__all__ = ["ObjectTarget", "PreparedPrint", "object_memory_bytes", "fill_void_at_surface", "outside_micro_centres"]

#: peak memory of an object run against its voxel grid (the bounding box at the voxel pitch): Spot at 40 mm
#: (475×467×262 voxels) peaked at 7.65 GB and at 25 mm at 3.2 GB (docs/bench_log.md, "Memory of a whole object
#: run"); 1 GiB + 140 bytes per grid voxel covers both (9.2 and 3.1 GB)
OBJECT_FIXED_BYTES = 1 << 30
OBJECT_BYTES_PER_VOXEL = 140


def object_memory_bytes(grid_voxels):
    """Expected peak memory in bytes of a print run on an object whose voxel grid has ``grid_voxels`` voxels.

    Example:
        >>> round(object_memory_bytes(475 * 467 * 262) / 2**30, 1)   # Spot at 40 mm, 300 DPI
        8.6
    """
    return OBJECT_FIXED_BYTES + OBJECT_BYTES_PER_VOXEL * int(grid_voxels)


class PreparedPrint(typing.NamedTuple):
    """A printer-resolution print prepared for rendering (:meth:`ObjectTarget.prepare_quantized`)."""
    index: torch.Tensor       #: (Dz, Hy, Wx) uint8 ink indices, no VOID (cut voxels filled, outside ink 0)
    sdf: torch.Tensor         #: (Dz+1, Hy+1, Wx+1) float32 corner SDF of the micro grid
    edges: tuple              #: the micro voxel's (x, y, z) edge lengths, mm
    printer_dpi: tuple        #: the (x, y, z) resolution it was prepared for


_CHUNK = 1 << 22  # micro-voxels per chunk of the quantised-volume passes (bounds their temporaries to ~100 MB)


class ObjectTarget:
    """Texel colours of a voxelised object as the optimisation target.

    Args:
        obj: a :class:`~torch_appearance.geometry.VoxelObject` with ``texel_colors`` and ``shell``.
        ior: refractive index of the object's surface (None: index matched).
        g: Henyey–Greenstein g of the inks.
        gradient_seed: ``"same"`` (the replay retraces the forward's paths) or ``"independent"``.
        emitter: the lighting (default: uniform white, :class:`ConstantEnvironment`); an
            :class:`~torch_appearance.render.EnvironmentMap` bakes display lighting into the optimisation (§4.8).

    Attributes:
        shape: (D, H, W) of the voxel grid. support: (D, H, W) bool, the optimised shell. target: (N, 3) float32
        linear RGB texel colours. positions: (N, 3) int64 voxel indices of the texels (rows of ``target``).
        target_grid, mask: the target on the voxel grid (built lazily; the optimisation's loss uses the sparse
        texel path, :meth:`appearance`, and never builds them).
    """
    kind = "object"
    depth_reference = "the surface (shell voxels)"
    mesh_report = None  # load_mesh's report of the mesh (set by from_config)

    def __init__(self, obj, *, ior=1.5, g=0.4, gradient_seed="same", emitter=None):
        if obj.texel_colors is None:
            raise ValueError("mesh: has neither a texture nor vertex/face colours, so there is no target appearance "
                             "(attach a texture with --texture or use a coloured PLY/GLB)")
        if obj.shell is None:
            raise ValueError("obj: expected a voxel object made with shell_mm (voxelize(..., shell_mm=...))")
        self.obj = obj
        self.shape = obj.grid_shape
        self.support = obj.shell.clone()
        if not bool(self.support.any()):
            raise ValueError("shell_mm: the shell holds no voxels")
        self.target = obj.texel_colors.float().clamp(0, 1)
        self.positions = obj.texel_voxels  # (N, 3) voxel indices (k, j, i) of the texels, rows of ``target``
        self.g, self.ior, self.gradient_seed = g, ior, gradient_seed
        self.emitter = ConstantEnvironment() if emitter is None else emitter
        self.scene = self._scene(obj.voxel_size, obj.sdf.float())

    @functools.cached_property
    def target_grid(self):
        """(3, D, H, W) the target on the voxel grid (built on first use: 3 floats per bounding-box voxel)."""
        return self.obj.texels_to_grid(self.target)

    @functools.cached_property
    def mask(self):
        """(D, H, W) bool texel mask on the voxel grid (built on first use)."""
        return self.obj.texels_to_grid(torch.ones(len(self.target), 1, dtype=torch.bool))[0]

    def appearance(self, criterion, texels):
        """``(E, {"E1", "E2", "E3"})`` of (N, 3) texel colours against the target with the
        :class:`~torch_appearance.nn.AppearanceLoss` ``criterion``, on the sparse texel path
        (:meth:`~torch_appearance.nn.AppearanceLoss.forward_parts_texels`): no voxel grid is built, the filter
        matrices are cached in ``criterion`` per device; equal to the grid path ``criterion.forward_parts(
        to_grid(texels), target_grid, mask)`` to float rounding. On the texels' device (the target copied there
        once)."""
        return criterion.forward_parts_texels(texels, on_device(self, texels.device, "target"), self.positions)

    @classmethod
    def from_config(cls, cfg, inks, log=print):
        """The object of ``cfg``: the mesh loaded, scaled to ``height_mm`` and voxelised with a shell of
        ``shell_mm``, lit by ``envmap`` (default uniform white)."""
        from ...geometry import load_mesh, voxelize

        mesh, report = load_mesh(cfg.mesh, height_mm=cfg.height_mm, texture=cfg.texture)
        # an object too large for the memory this process may use is refused before it is voxelised
        extent = np.asarray(mesh.bounds[1] - mesh.bounds[0], dtype=np.float64)
        dims = [int(np.ceil(e / cfg.voxel_size)) + 4 for e in extent]  # + the SDF band's margin
        check_memory("height_mm", object_memory_bytes(np.prod(dims, dtype=np.float64)),
                     f"a {' × '.join(map(str, dims))}-voxel object ({extent[0]:.1f} × {extent[1]:.1f} × "
                     f"{extent[2]:.1f} mm at {cfg.dpi:g} DPI)",
                     "print it smaller (height_mm, --height-mm) or optimise at a lower dpi (--dpi)",
                     device=cfg.device)  # on a GPU its free memory too
        t0 = time.perf_counter()
        obj = voxelize(mesh, cfg.voxel_size, shell_mm=cfg.shell_mm)
        inside, shell = int(obj.occupancy.sum()), int(obj.shell.sum())
        if shell >= inside:
            raise ValueError(f"shell_mm: a {cfg.shell_mm} mm shell takes every one of the object's {inside} voxels "
                             f"(it is thicker than half the object's thickness); use a thinner shell")
        log(f"optimize_print: {cfg.mesh}: {report['triangles']} triangles, grid {obj.grid_shape}, {inside} inside "
            f"voxels, {shell} in the {cfg.shell_mm} mm shell, {len(obj.texel_voxels)} texels "
            f"({time.perf_counter() - t0:.1f} s)")
        emitter = None if cfg.envmap is None else EnvironmentMap.from_exr(cfg.envmap)
        target = cls(obj, ior=cfg.ior, g=cfg.phase_g(inks), gradient_seed=cfg.gradient_seed, emitter=emitter)
        target.mesh, target.mesh_report = mesh, report
        return target

    def use_g(self, g):
        """Render with Henyey–Greenstein ``g`` (a run with another ink set may have another common g)."""
        if g != self.g:
            self.g = g
            self.scene = self._scene(self.obj.voxel_size, self.obj.sdf.float())

    def use(self, inks, cfg):
        """Render with the run's inks' common g (or ``cfg.g``): a target may be shared by runs with other inks."""
        self.use_g(cfg.phase_g(inks))

    # ------------------------------------------------------------------------------------------ rendering
    def _scene(self, voxel_size, sdf):
        sensor = SurfaceTexels(self.obj.texel_points.double(), self.obj.texel_normals.double(),
                               footprint_mm=0.5 * self.obj.voxel_size)
        return Scene(voxel_size=voxel_size, origin=self.obj.origin, boundary=SDFBoundary(sdf.contiguous(), ior=self.ior),
                     sensor=sensor, emitter=self.emitter, g=self.g)

    def render(self, sigma_t, albedo, spp, seed, scene=None, adjoint=None):
        """(N, 3) texel colours (linear RGB) of the medium (3, D, H, W), differentiable (``adjoint``: the texels'
        gradient when known before the render; see :func:`.rendering.render`)."""
        scene = self.scene if scene is None else scene
        # only the shell carries parameters: the replay crosses the fixed white core without gradient bookkeeping
        return render(scene, sigma_t, albedo, spp=spp, seed=seed, seed_grad=replay_seed(seed, self.gradient_seed),
                      grad_support=self.support, adjoint=adjoint)  # on the CPU: the tracer's front door keeps it there

    def to_grid(self, texels):
        return self.obj.texels_to_grid(texels)

    def evaluation_subset(self, count, seed):
        """(M,) sorted int64 indices of the texels an evaluation scores: ``count`` of them drawn uniformly without
        replacement with ``seed``; None (every texel) when ``count`` is 0 or at least the number of texels."""
        n = len(self.target)
        if not count or count >= n:
            return None
        generator = torch.Generator().manual_seed(int(seed) % (1 << 63))
        return torch.randperm(n, generator=generator)[:count].sort().values

    def subset_scene(self, index):
        """The object's scene with a sensor of the texels ``index`` (M,) only (their rows of :attr:`target`)."""
        sensor = self.scene.sensor
        return dataclasses.replace(self.scene, sensor=SurfaceTexels(
            sensor.points[index], sensor.normals[index], footprint_mm=sensor.footprint_mm[index]))

    def scored(self, texels, index=None):
        """(prediction, target) pairs of (M, 3) colours that are scored: every texel, or the texels ``index``
        (:meth:`evaluation_subset`) of which ``texels`` are the renders."""
        return texels, (self.target if index is None else self.target[index])

    def extra_scores(self, texels):
        """Every texel is scored (:meth:`scored`): nothing more."""
        return {}

    # ------------------------------------------------------------------------------------------ baselines
    def naive_weights(self, inks, cfg):
        """The naive extrusion (N, D, H, W): the table of homogeneous slabs as thick as the shell matched per texel,
        every shell voxel the mixture of its nearest texel, deeper voxels ``cfg.core_ink``; and the table's
        description."""
        table_cfg = dataclasses.replace(cfg, thickness_mm=cfg.shell_mm)
        column, table = naive_extrusion(self.target.numpy()[:, None, :], inks, table_cfg)
        core = np.zeros(len(inks))
        core[inks.index(cfg.core_ink)] = 1.0
        return self.extrude(column[:, 0, :, 0].numpy(), core), table

    def nearest_texel(self):
        """(S,) index of the texel nearest to each shell voxel (voxel centres, C order of the shell), cached."""
        if getattr(self, "_nearest", None) is None:
            from scipy.spatial import cKDTree

            tree = cKDTree(self.obj.texel_voxels.numpy().astype(np.float64))
            _, self._nearest = tree.query(np.argwhere(self.support.numpy()).astype(np.float64), workers=-1)
        return self._nearest

    def extrude(self, texel_weights, core):
        """Per-texel mixtures (N_inks, N) → (N_inks, D, H, W): every shell voxel takes the mixture of its nearest
        texel (by voxel centre), other voxels ``core`` (N_inks,)."""
        d, h, w = self.shape
        shell = self.support.numpy()
        # float32 from the start (the float64 values rounded once, as before): 4 bytes per ink and voxel, not 12
        out = np.empty((len(core), d * h * w), np.float32)
        out[:] = np.asarray(core, np.float64).astype(np.float32)[:, None]
        out[:, np.flatnonzero(shell)] = np.asarray(texel_weights, np.float64).astype(np.float32)[:, self.nearest_texel()]
        return torch.from_numpy(out.reshape(len(core), d, h, w))

    # ------------------------------------------------------------------------------------------ masks
    def voxel_depth(self):
        """(D, H, W) float depth of the voxel centres below the surface, mm (0 outside)."""
        return self.obj.depth.numpy()

    def image_mask(self, image, name, spec):
        """(D, H, W) bool: shell voxels whose nearest texel's UV falls on a white pixel of a texture-space mask."""
        if self.obj.texel_uv is None:
            raise ValueError(f"fixed: {spec!r}: the mesh has no UVs, so a texture-space mask cannot be placed")
        texture = getattr(getattr(getattr(self.mesh, "visual", None), "material", None), "image", None)
        if texture is not None and tuple(texture.size) != (image.shape[1], image.shape[0]):
            raise ValueError(f"fixed: {spec!r}: the mask {name!r} is {image.shape[1]}×{image.shape[0]} pixels, the "
                             f"mesh's texture {texture.size[0]}×{texture.size[1]}; expected the same size")
        uv = self.obj.texel_uv.numpy().astype(np.float64)[self.nearest_texel()]
        h, w = image.shape
        col = np.clip(np.floor((uv[:, 0] % 1.0) * w), 0, w - 1).astype(np.int64)
        row = np.clip(np.floor((1.0 - uv[:, 1] % 1.0) * h), 0, h - 1).astype(np.int64)
        out = np.zeros(self.shape, dtype=bool)
        out[self.support.numpy()] = image[row, col]
        return out

    def material_mask(self, name, spec):
        """(D, H, W) bool: shell voxels whose nearest texel lies on a face of the mesh's material ``name``."""
        mesh = getattr(self, "mesh", None)
        names = [] if mesh is None else list(mesh.metadata.get("material_names", []))
        if name not in names:
            raise ValueError(f"fixed: {spec!r}: the mesh has no material {name!r}; its materials are {names}")
        import igl

        points = self.obj.texel_points.numpy().astype(np.float64)
        _, face, _ = igl.point_mesh_squared_distance(points, np.asarray(mesh.vertices, np.float64),
                                                     np.asarray(mesh.faces, np.int64))
        on = np.asarray(mesh.metadata["face_materials"])[np.asarray(face, np.int64)] == names.index(name)
        out = np.zeros(self.shape, dtype=bool)
        out[self.support.numpy()] = on[self.nearest_texel()]
        return out

    # ------------------------------------------------------------------------------------------ quantisation
    def quantized_void(self, indices):
        """Mark the printer micro-voxels whose centres lie outside the object (:func:`outside_micro_centres`) as
        VOID."""
        out = indices.copy()
        outside = outside_micro_centres(self.obj.sdf, indices.shape)
        step = max(1, _CHUNK // (indices.shape[1] * indices.shape[2]))
        for z0 in range(0, indices.shape[0], step):  # chunks of micro layers: temporaries of ~_CHUNK floats
            z1 = min(indices.shape[0], z0 + step)
            out[z0:z1][outside(z0, z1)] = VOID
        return out

    def micro_sdf(self, micro_shape):
        """The corner SDF trilinearly resampled onto the corners of a micro grid covering the same box."""
        dz, hy, wx = micro_shape
        sdf = self.obj.sdf.float()[None, None]
        return torch.nn.functional.interpolate(sdf, size=(dz + 1, hy + 1, wx + 1), mode="trilinear",
                                               align_corners=True)[0, 0].contiguous()

    def quantized_medium(self, indices, inks, printer_dpi):
        """σ_t and albedo (3, Dz, Hy, Wx) of a printer-resolution index volume (an ink table lookup) and the scene
        pieces at the micro pitch: (sigma_t, albedo, edges, sdf).

        The renderer's surface is the smooth SDF, while the printer prints whole micro-voxels (those whose centre is
        inside; the others are VOID). A VOID micro-voxel that straddles the surface still has a part inside the
        smooth boundary that light crosses first: it takes the ink of its most interior printed neighbour
        (:func:`fill_void_at_surface`), i.e. the printed material continues to the smooth surface. VOID voxels
        wholly outside are never entered and take ink 0."""
        dz, hy, wx = indices.shape
        sdf = self.micro_sdf((dz, hy, wx))
        filled = fill_void_at_surface(indices, sdf)
        # an ink table lookup a chunk of micro layers at a time (no int64 index or transposed copy of the volume)
        tables = [inks.sigma_t(torch.float32).t().contiguous(), inks.albedo(torch.float32).t().contiguous()]  # (3, N)
        sigma_t, albedo = (torch.empty(3, dz, hy, wx, dtype=torch.float32) for _ in range(2))
        step = max(1, _CHUNK // (hy * wx))
        for z0 in range(0, dz, step):
            idx = torch.from_numpy(filled[z0:z0 + step].astype(np.int64))
            idx[idx == VOID] = 0
            for out, table in zip((sigma_t, albedo), tables):
                out[:, z0:z0 + step] = table[:, idx]
        edges = micro_grid_pitch(self.shape, self.obj.voxel_size, printer_dpi)
        return sigma_t, albedo, edges, sdf

    def prepare_quantized(self, indices, printer_dpi):
        """What every render of one printer-resolution index volume needs, prepared once: the volume with the VOID
        voxels cut by the surface given a printed neighbour's ink and the others ink 0 (as in
        :meth:`quantized_medium`), the micro grid's corner SDF and pitch. Pass it to :meth:`render_quantized` in
        place of ``indices`` to render one print many times (an evaluation's renders, its picture, the views):
        the preparation costs about 0.75 s per call on Spot at 10 mm, four to seven times per print otherwise.

        Args:
            indices: (Dz, Hy, Wx) uint8 ink indices, :data:`VOID` outside.
            printer_dpi: the printer's (x, y, z) resolution, dots per inch.

        Returns:
            a :class:`PreparedPrint` (the caller's ``indices`` are not changed)."""
        indices = np.asarray(indices)
        if indices.ndim != 3 or indices.dtype != np.uint8:
            raise ValueError(f"indices: expected a (Dz, Hy, Wx) uint8 volume, got {indices.dtype} of shape "
                             f"{indices.shape}")
        dz, hy, wx = indices.shape
        sdf = self.micro_sdf((dz, hy, wx))
        index = fill_void_at_surface(indices, sdf)  # see quantized_medium
        step = max(1, _CHUNK // (hy * wx))
        for z0 in range(0, dz, step):
            chunk = index[z0:z0 + step]
            chunk[chunk == VOID] = 0
        edges = micro_grid_pitch(self.shape, self.obj.voxel_size, printer_dpi)
        return PreparedPrint(torch.from_numpy(index), sdf, edges, tuple(float(x) for x in printer_dpi))

    def render_quantized(self, indices, inks, printer_dpi, spp, seed, sensor=None):
        """(N, 3) texel colours (or the image of ``sensor``, e.g. a camera) of a printer-resolution index volume
        (VOID outside), rendered with the object's boundary resampled to the micro grid. The tracer reads the
        uint8 volume and the ink table (:func:`~torch_appearance.render.render_scene_indexed`; VOID voxels cut by
        the surface take a printed neighbour's ink, those wholly outside ink 0, as in :meth:`quantized_medium`):
        the same image as the dense σ_t/albedo of :meth:`quantized_medium` without their 24 bytes per micro voxel.
        ``indices`` may be a :class:`PreparedPrint` of :meth:`prepare_quantized` (prepared for ``printer_dpi``)."""
        if isinstance(indices, PreparedPrint):
            prepared = indices
            if prepared.printer_dpi != tuple(float(x) for x in printer_dpi):
                raise ValueError(f"printer_dpi: the prepared print is for {prepared.printer_dpi}, got "
                                 f"{tuple(printer_dpi)}")
        else:
            prepared = self.prepare_quantized(indices, printer_dpi)
        scene = Scene(voxel_size=prepared.edges, origin=self.obj.origin,
                      boundary=SDFBoundary(prepared.sdf, ior=self.ior), sensor=self.scene.sensor if sensor is None else sensor, emitter=self.emitter, g=self.g)
        with torch.no_grad():
            return distributed.render(render_scene_indexed, scene, prepared.index,
                                      inks.sigma_t(torch.float32), inks.albedo(torch.float32), spp=spp, seed=seed)

    def camera_views(self, n=3, size=256, fov_y_deg=30.0, elevation_deg=20.0):
        """``n`` perspective cameras around the object (azimuths 360°/n apart, looking at its centre, z up), far
        enough that its bounding sphere fills the frame."""
        import math

        from ...render import PerspectiveCamera

        d, h, w = self.shape
        s = self.obj.voxel_size
        lo = np.array(self.obj.origin)
        centre = lo + 0.5 * s * np.array([w, h, d])
        occ = np.argwhere(self.obj.occupancy.numpy())
        radius = float(np.linalg.norm((occ[:, ::-1] + 0.5) * s + lo - centre, axis=1).max()) + s
        distance = 1.05 * radius / math.sin(math.radians(fov_y_deg) / 2)
        cams = []
        for k in range(n):
            az, el = 2 * math.pi * k / n - math.pi / 2, math.radians(elevation_deg)
            eye = centre + distance * np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az),
                                                math.sin(el)])
            cams.append(PerspectiveCamera(tuple(eye), tuple(centre), (0.0, 0.0, 1.0), fov_y_deg=fov_y_deg,
                                          resolution=(size, size)))
        return cams

    # ------------------------------------------------------------------------------------------ outputs
    mesh = None  # the trimesh mesh that was voxelised (set by the pipeline; enables the UV-space bake)

    def save_texels(self, folder, stem, texels, index=None):
        """Write the texel colours as a coloured point cloud ``stem.ply`` (sRGB bytes), ``stem.npy`` (linear) and,
        when the mesh has a UV layout, ``stem_uv.png`` baked into it. ``index`` (M,): ``texels`` are those texels
        only (an evaluation subset): the point cloud holds them, ``stem.npy`` is NaN elsewhere, no bake."""
        import trimesh

        from ...color import linear_to_srgb8
        from ...geometry.bake import bake_texels

        rgb = np.asarray(texels, np.float32).reshape(-1, 3)
        points = self.obj.texel_points.numpy()
        if index is not None:
            full = np.full((len(points), 3), np.nan, np.float32)
            full[np.asarray(index)] = rgb
            points = points[np.asarray(index)]
        buffer = io.BytesIO()
        np.save(buffer, rgb if index is None else full)
        ta_io.atomic_write_bytes(os.path.join(folder, f"{stem}.npy"), buffer.getvalue())
        if index is None and self._has_uv_layout():
            image, _ = bake_texels(self.mesh, points, np.clip(rgb, 0, 1), size=self._bake_size())
            ta_io.write_png(os.path.join(folder, f"{stem}_uv.png"), image)
        colours = np.concatenate([linear_to_srgb8(rgb), np.full((len(rgb), 1), 255, np.uint8)], axis=1)
        cloud = trimesh.PointCloud(points, colors=colours)
        ta_io.atomic_write_bytes(os.path.join(folder, f"{stem}.ply"), cloud.export(file_type="ply"))

    def load_texels(self, folder, stem):
        """(N, 3) float32 texels that :meth:`save_texels` wrote (``stem.npy``)."""
        return np.load(os.path.join(folder, f"{stem}.npy"))

    def _has_uv_layout(self):
        """Whether the mesh's UV triangles cover pixels of the bake image (cached). A mesh coloured by materials
        only (an OBJ with Kd colours and no ``vt``) gets degenerate UVs from trimesh's material atlas: no layout."""
        if getattr(self, "_uv_layout", None) is None:
            from ...geometry.bake import uv_face_image

            self._uv_layout = (self.mesh is not None and getattr(self.mesh.visual, "uv", None) is not None
                               and bool((uv_face_image(self.mesh, self._bake_size()) >= 0).any()))
        return self._uv_layout

    def _bake_size(self):
        """The mesh's texture size (capped at 1024 a side), else 512²."""
        image = getattr(getattr(self.mesh.visual, "material", None), "image", None)
        if image is None:
            return (512, 512)
        w, h = image.size
        scale = min(1.0, 1024.0 / max(w, h))
        return (max(1, round(h * scale)), max(1, round(w * scale)))

    def ink_usage_by_depth(self, weights, bins=None):
        """Mean ink fractions (N, B) of the shell voxels binned by depth below the surface; bin centres (B,) mm."""
        depth = self.obj.depth.numpy()[self.support.numpy()]
        w = weights.detach().reshape(weights.shape[0], -1)[:, self.support.reshape(-1)].double().numpy()
        h = self.obj.voxel_size
        edges = np.arange(0.0, depth.max() + h, h) if bins is None else bins
        which = np.clip(np.digitize(depth, edges) - 1, 0, len(edges) - 2)
        count = np.bincount(which, minlength=len(edges) - 1).astype(np.float64)
        usage = np.stack([np.bincount(which, weights=row, minlength=len(edges) - 1) for row in w])
        keep = count > 0
        return usage[:, keep] / count[keep], (0.5 * (edges[:-1] + edges[1:]))[keep]

    def describe(self):
        return {"grid_dhw": list(self.shape), "texels": int(len(self.target)), "shell_voxels": int(self.support.sum()),
                "inside_voxels": int(self.obj.occupancy.sum()), "voxel_size_mm": self.obj.voxel_size}

    def inputs(self):
        """What config.json records of the inputs beyond :meth:`describe`: the mesh's report."""
        return {"mesh_report": self.mesh_report}

    def save_inputs(self, folder):
        """``object.npz``: the voxelisation (:meth:`VoxelObject.save`)."""
        self.obj.save(os.path.join(folder, "object.npz"))

    def figures(self, final):
        """The object's figure is ``views.png`` (:meth:`views`): nothing more."""
        return []

    def views(self, folder, indices, inks, cfg, seed, texel_de, log=print, texel_index=None):
        """``cfg.views`` camera renders of the quantised object ``indices`` (or its :class:`PreparedPrint`) at
        ``cfg.view_spp`` (``view_k.exr``/``.png``) and ``views.png`` beside the target texture on the mesh, coloured
        by the final texels' CIEDE2000 ``texel_de`` (M,) (free of render noise on average) of the texels
        ``texel_index`` (M,) (None: all); returns the seconds spent."""
        if cfg.views == 0:
            return 0.0
        from .object_figures import views_figure

        t0 = time.perf_counter()
        cams = self.camera_views(cfg.views, cfg.view_size)
        if not isinstance(indices, PreparedPrint):
            indices = self.prepare_quantized(indices, cfg.printer_dpi)
        renders = []
        for k, cam in enumerate(cams):
            image = self.render_quantized(indices, inks, cfg.printer_dpi, cfg.view_spp, iteration_seed(seed, -10 - k),
                                          sensor=cam)
            save_image(folder, f"view_{k}", image.numpy())
            renders.append(image.numpy())
        views_figure(os.path.join(folder, "views.png"), self, cams, renders, texel_de=texel_de, log=log,
                     texel_index=texel_index)
        return time.perf_counter() - t0


def _corner_lerp(n_in, n_out):
    """Linear interpolation of ``n_in`` corner values onto ``n_out`` corners over the same interval (the ends
    aligned): for each output corner the two input corners and the weight of the second, in float32."""
    scale = np.float32(n_in - 1) / np.float32(n_out - 1) if n_out > 1 else np.float32(0)
    src = scale * np.arange(n_out, dtype=np.float32)
    i0 = np.minimum(src.astype(np.int64), n_in - 1)
    return i0, np.minimum(i0 + 1, n_in - 1), torch.from_numpy((src - i0).astype(np.float32))


def outside_micro_centres(sdf, micro_shape):
    """Which printer micro-voxels lie outside an object, a block of micro layers at a time.

    The object's corner SDF (D+1, H+1, W+1) on the macro grid is interpolated trilinearly onto the corners of the
    micro grid ``(Dz, Hy, Wx)`` covering the same box, and a micro-voxel is outside where the mean of its eight
    corners is > 0. Only the corner layers of the block asked for are interpolated, so the memory does not grow
    with the number of layers.

    Returns:
        ``outside(z0, z1)`` → bool ``(z1 - z0, Hy, Wx)`` ndarray.
    """
    sdf = torch.as_tensor(sdf).float()
    dz, hy, wx = micro_shape
    (z0s, z1s, lz), (y0s, y1s, ly), (x0s, x1s, lx) = (
        _corner_lerp(n_in, n_out + 1) for n_in, n_out in zip(sdf.shape, (dz, hy, wx)))
    ly, lx = ly.view(1, -1, 1), lx.view(1, 1, -1)

    def outside(z0, z1):
        k = slice(z0, z1 + 1)
        t = lz[k].view(-1, 1, 1)
        c = sdf[z0s[k]] * (1 - t) + sdf[z1s[k]] * t                     # (k+1, H+1, W+1)
        c = c[:, y0s] * (1 - ly) + c[:, y1s] * ly                       # (k+1, Hy+1, W+1)
        c = c[:, :, x0s] * (1 - lx) + c[:, :, x1s] * lx                 # (k+1, Hy+1, Wx+1)
        centre = (c[:-1, :-1, :-1] + c[1:, 1:, 1:] + c[1:, :-1, :-1] + c[:-1, 1:, :-1] + c[:-1, :-1, 1:]
                  + c[1:, 1:, :-1] + c[1:, :-1, 1:] + c[:-1, 1:, 1:]) / 8
        return (centre > 0).numpy()

    return outside


def fill_void_at_surface(indices, corner_sdf, passes=4):
    """Give the VOID micro-voxels that straddle the surface the ink of a printed neighbour.

    A micro-voxel is VOID when its centre lies outside the object, but the smooth surface (the zero set of the
    trilinear corner SDF) may still cut it: the part inside is what light meets first below the surface. Each such
    voxel (VOID with a corner SDF ≤ 0) takes the ink of its face neighbour (6-neighbourhood) with the lowest centre
    SDF among those already holding an ink; ``passes`` rounds of this reach voxels whose neighbours were straddling
    too. Straddling voxels still unfilled after that (isolated slivers) take the most common printed ink.

    Args:
        indices: (Dz, Hy, Wx) uint8 ink indices, :data:`VOID` outside.
        corner_sdf: (Dz+1, Hy+1, Wx+1) float SDF at the micro-voxel corners (negative inside).
        passes: neighbour rounds.

    Returns:
        (Dz, Hy, Wx) uint8: a copy of ``indices`` with the straddling VOID voxels filled (the others stay VOID).
    """
    indices = np.asarray(indices)
    sdf = torch.as_tensor(corner_sdf)
    if indices.ndim != 3 or tuple(sdf.shape) != tuple(n + 1 for n in indices.shape):
        raise ValueError(f"corner_sdf: expected shape {tuple(n + 1 for n in indices.shape)} for indices of shape "
                         f"{indices.shape}, got {tuple(sdf.shape)}")
    out = indices.copy()
    dz, hy, wx = indices.shape
    corners = [sdf[a:a + dz, b:b + hy, c:c + wx].numpy() for a in (0, 1) for b in (0, 1) for c in (0, 1)]
    step = max(1, _CHUNK // (hy * wx))
    found = []                                         # straddling VOID voxels, a chunk of micro layers at a time
    for z0 in range(0, dz, step):
        lowest = functools.reduce(np.minimum, [c[z0:z0 + step] for c in corners])
        hits = np.argwhere((out[z0:z0 + step] == VOID) & (lowest <= 0))
        hits[:, 0] += z0
        found.append(hits)
    todo = np.concatenate(found) if found else np.zeros((0, 3), np.int64)         # (M, 3)
    if len(todo) == 0:
        return out

    def centre_sdf(p):                                                           # (M, 3) voxel indices -> (M,)
        return sum(c[tuple(p.T)].astype(np.float64) for c in corners) / 8

    shape = np.array(indices.shape)
    steps = np.array([(1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, 0, 1), (0, 0, -1)])
    for _ in range(passes):
        best = np.full(len(todo), np.inf)
        ink = np.full(len(todo), VOID, dtype=out.dtype)
        for offset in steps:
            nb = todo + offset
            inside = ((nb >= 0) & (nb < shape)).all(1)
            nbi = np.where(inside[:, None], nb, 0)
            cand = out[tuple(nbi.T)]
            score = np.where(inside & (cand != VOID), centre_sdf(nbi), np.inf)
            better = score < best
            best[better], ink[better] = score[better], cand[better]
        done = ink != VOID
        out[tuple(todo[done].T)] = ink[done]
        todo = todo[~done]
        if len(todo) == 0:
            return out
    counts = np.bincount(out.reshape(-1), minlength=256)[:VOID]              # printed inks (VOID = 255 excluded)
    if counts.any():
        out[tuple(todo.T)] = counts.argmax()
    return out
