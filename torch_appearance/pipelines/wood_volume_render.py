"""Volumetric wood scenes (wood paper §4.2, Figs. 6 and 7): a backlit veneer sheet, fitted vs extruded, and a lamp
shade cut from the model, rendered by the volume path tracer; the run behind ``scripts/render_wood_volume.py``.

World frames (mm):

- **Veneer**: the world is the board frame (u, v, w) of the photo (:mod:`torch_appearance.nn.wood`): x = u (photo
  columns), y = v (photo rows), z = w into the wood. The sheet is the grid box [0, U]×[0, V]×[0, T] (T = thickness,
  the photographed face at z = 0), a smooth dielectric; the camera looks at the photographed face from z < 0
  (orthographic, image rows follow v like the photo); a distant disc light shines from behind (+z). The side view
  looks at the sheet's edge y = 0 along +y (image rows = depth, the light side at the top).
- **Lamp shade**: an open conical shell around the world z axis (``conical_shell_sdf``), index 1.5. It is cut from
  the tree so that its axis runs along the board's v axis (along the stem of a flat-sawn board) and its wall
  facing the camera (y = −R at mid height) touches the photographed surface: board point b = R·x + t with
  u = x + U/2, v = V/2 − z, w = y + R_mid. The tracer's lights are distant (no point lights), so "lit from inside"
  is a disc light shining *up into the wide lower opening* (direction −z): it lights the inner wall, while the
  outer wall faces away from it and receives that light only through the wood (plus a weak ambient); the
  perspective camera looks from the side, slightly from above.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field
import math
import os
import time
from typing import Optional, Tuple

import numpy as np
import torch

from .. import io as ta_io
from ..geometry.primitives import conical_shell_sdf
from ..nn.wood_volume import SIGMA_EARLY, SIGMA_LATE, load_wood_fit, wood_volume
from ..checks import check_device, check_int, check_real
from ..render import (BoxBoundary, DiscLight, OrthographicCamera, PerspectiveCamera, Scene, SDFBoundary,
                      render_scene)

__all__ = ["VeneerGeometry", "LampshadeGeometry", "veneer_scenes", "lampshade_scene", "lampshade_world_to_board",
           "WoodVolumeConfig", "render_wood_volume"]


def _check_thickness(value, name="thickness_mm"):
    value = check_real(name, value)
    if not value > 0:
        raise ValueError(f"{name}: expected a thickness > 0 mm, got {value:g}")
    return value


def _angle_deg(a, b):
    a, b = np.asarray(a, float), np.asarray(b, float)
    return math.degrees(math.acos(float(np.clip(a @ b / (np.linalg.norm(a) * np.linalg.norm(b)), -1, 1))))


@dataclass(frozen=True)
class VeneerGeometry:
    """A veneer sheet of ``extent_mm`` = (U, V) and ``thickness_mm`` (> 0), voxels of ``voxel_mm`` = (lateral, depth)."""
    extent_mm: Tuple[float, float]
    thickness_mm: float = 1.8
    voxel_mm: Tuple[float, float] = (0.15, 0.15)

    def __post_init__(self):
        u, v = (check_real("extent_mm", e, lo=0.0, lo_open=True) for e in self.extent_mm)
        object.__setattr__(self, "extent_mm", (u, v))
        object.__setattr__(self, "thickness_mm", _check_thickness(self.thickness_mm))
        lat, dep = (check_real("voxel_mm", e, lo=0.0, lo_open=True) for e in self.voxel_mm)
        object.__setattr__(self, "voxel_mm", (lat, dep))

    @property
    def grid_shape(self):
        """(D, H, W): depth layers, rows (v), columns (u); the sheet is rounded to whole voxels."""
        lat, dep = self.voxel_mm
        return (max(1, round(self.thickness_mm / dep)), max(1, round(self.extent_mm[1] / lat)),
                max(1, round(self.extent_mm[0] / lat)))

    @property
    def voxel_size(self):
        """(x, y, z) voxel edges in mm: the grid spans exactly U × V × T."""
        d, h, w = self.grid_shape
        return (self.extent_mm[0] / w, self.extent_mm[1] / h, self.thickness_mm / d)


def veneer_scenes(geometry: VeneerGeometry, light: DiscLight, *, resolution, side_rows=None, g=0.4, ior=1.5):
    """The backlit sheet seen from the front and from its edge.

    Args:
        geometry: the sheet.
        light: distant disc light; it must lie behind the sheet (the whole disc in the half-space z > 0 seen from
            the sheet), else the camera would see a sheet with nothing behind it.
        resolution: (rows, cols) of the front view (covering the sheet exactly).
        side_rows: rows of the side view across the thickness (default: square pixels of the front view's
            column pitch, at least 8).
        g, ior: phase function and boundary index (None: index matched).

    Returns:
        (front Scene, side Scene).

    Raises:
        ValueError: the light is not behind the sheet, or bad sizes.
    """
    if not isinstance(geometry, VeneerGeometry):
        raise TypeError(f"geometry: expected a VeneerGeometry, got {type(geometry).__name__}")
    if not isinstance(light, DiscLight):
        raise TypeError(f"light: expected a DiscLight, got {type(light).__name__}")
    behind = 90.0 - _angle_deg(light.direction, (0.0, 0.0, 1.0))
    if behind <= light.angular_radius_deg:
        raise ValueError(f"light: expected a disc light behind the sheet (direction within "
                         f"{90.0 - light.angular_radius_deg:.1f}° of +z, the side away from the camera), got "
                         f"direction {tuple(round(c, 4) for c in light.direction)} with radius "
                         f"{light.angular_radius_deg:g}°: (part of) the light is behind nothing")
    u, v = geometry.extent_mm
    t = geometry.thickness_mm
    rows, cols = resolution
    front = OrthographicCamera(origin=(u / 2, v / 2, -10.0 * t - 1.0), target=(u / 2, v / 2, 0.0), up=(0, -1, 0),
                               extent_mm=(u, v), resolution=(rows, cols))
    if side_rows is None:
        side_rows = max(8, round(t / (u / front.resolution[1])))
    side_rows = check_int("side_rows", side_rows, lo=1)
    side = OrthographicCamera(origin=(u / 2, -10.0 * t - 1.0, t / 2), target=(u / 2, 0.0, t / 2), up=(0, 0, 1),
                              extent_mm=(u, t), resolution=(side_rows, front.resolution[1]))
    common = dict(voxel_size=geometry.voxel_size, origin=(0.0, 0.0, 0.0), boundary=BoxBoundary(ior), emitter=light,
                  g=g)
    return Scene(sensor=front, **common), Scene(sensor=side, **common)


@dataclass(frozen=True)
class LampshadeGeometry:
    """An open conical shell: radii at the bottom and top, height, wall thickness (mm), voxel edge (mm)."""
    bottom_radius_mm: float = 18.0
    top_radius_mm: float = 9.0
    height_mm: float = 18.0
    thickness_mm: float = 1.0
    voxel_mm: float = 0.25

    def __post_init__(self):
        for name in ("bottom_radius_mm", "top_radius_mm", "height_mm", "voxel_mm"):
            object.__setattr__(self, name, check_real(name, getattr(self, name), lo=0.0, lo_open=True))
        object.__setattr__(self, "thickness_mm", _check_thickness(self.thickness_mm))
        if self.thickness_mm >= 2 * min(self.bottom_radius_mm, self.top_radius_mm):
            limit = 2 * min(self.bottom_radius_mm, self.top_radius_mm)
            raise ValueError(f"thickness_mm: expected < 2·min(radii) = {limit:g} mm, got {self.thickness_mm:g}")

    @property
    def wall_tilt_deg(self):
        """Angle of the wall from the vertical (> 0: wider at the bottom)."""
        return math.degrees(math.atan2(self.bottom_radius_mm - self.top_radius_mm, self.height_mm))

    @property
    def mid_radius_mm(self):
        return 0.5 * (self.bottom_radius_mm + self.top_radius_mm)

    def grid(self):
        """(grid_shape (D, H, W), origin): a cube-voxel grid around the shell with two voxels of padding."""
        h = self.voxel_mm
        r = max(self.bottom_radius_mm, self.top_radius_mm) + self.thickness_mm
        n_xy = int(math.ceil(2 * r / h)) + 4
        n_z = int(math.ceil((self.height_mm + self.thickness_mm) / h)) + 4
        return (n_z, n_xy, n_xy), (-n_xy * h / 2, -n_xy * h / 2, -n_z * h / 2)


def lampshade_world_to_board(geometry: LampshadeGeometry, board_extent_mm):
    """(R, t) of the board point b = R·x + t of a world point x (see the module docstring)."""
    u, v = board_extent_mm
    rot = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
    return rot, (u / 2, v / 2, geometry.mid_radius_mm)


def lampshade_scene(geometry: LampshadeGeometry, light: DiscLight, *, resolution=(160, 160), elevation_deg=12.0,
                    distance_mm=None, fov_y_deg=None, ior=1.5, g=0.4):
    """The lamp shade with a light shining into its lower opening, seen by a perspective camera.

    Args:
        geometry: the shell.
        light: distant disc light; the whole disc must lie below the shade's lower rim plane (direction within
            90° − radius of −z), else it is behind nothing but the shade's outside, and within the wall's tilt from
            −z (:attr:`LampshadeGeometry.wall_tilt_deg`), so that it lights the inner wall only: the outer wall
            faces away from every direction of the disc.
        resolution: (rows, cols).
        elevation_deg: camera elevation above the horizontal (it looks at the shade's centre from −y).
        distance_mm: camera distance (default 4 × height).
        fov_y_deg: vertical field of view (default: the shade fills ~80 % of the frame).

    Returns:
        (Scene, grid_shape, origin).
    """
    if not isinstance(geometry, LampshadeGeometry):
        raise TypeError(f"geometry: expected a LampshadeGeometry, got {type(geometry).__name__}")
    if not isinstance(light, DiscLight):
        raise TypeError(f"light: expected a DiscLight, got {type(light).__name__}")
    below = 90.0 - _angle_deg(light.direction, (0.0, 0.0, -1.0))
    if below <= light.angular_radius_deg:
        raise ValueError(f"light: expected a disc light below the shade shining into its lower opening (direction "
                         f"within {90.0 - light.angular_radius_deg:.1f}° of −z), got direction "
                         f"{tuple(round(c, 4) for c in light.direction)} with radius {light.angular_radius_deg:g}°: "
                         f"(part of) the light is behind nothing but the shade's outside")
    if 90.0 - below + light.angular_radius_deg >= geometry.wall_tilt_deg:
        raise ValueError(f"light: expected a disc light that lights only the inside of the shade (the disc within the "
                         f"wall tilt {geometry.wall_tilt_deg:.1f}° of −z), got direction "
                         f"{tuple(round(c, 4) for c in light.direction)} with radius {light.angular_radius_deg:g}°: "
                         f"it would light the outer wall directly")
    elevation = check_real("elevation_deg", elevation_deg, lo=-80.0, hi=80.0)
    shape, origin = geometry.grid()
    sdf = conical_shell_sdf(shape, geometry.voxel_mm, origin, (0.0, 0.0, 0.0), geometry.bottom_radius_mm,
                            geometry.top_radius_mm, geometry.height_mm, geometry.thickness_mm)
    dist = 4.0 * geometry.height_mm if distance_mm is None else check_real("distance_mm", distance_mm, lo=0.0,
                                                                            lo_open=True)
    e = math.radians(elevation)
    cam = (0.0, -dist * math.cos(e), dist * math.sin(e))
    if fov_y_deg is None:
        half = 0.5 * max(geometry.height_mm + 2 * geometry.bottom_radius_mm * abs(math.sin(e)),
                         2 * geometry.bottom_radius_mm)
        fov_y_deg = 2 * math.degrees(math.atan(half / 0.8 / dist))
    sensor = PerspectiveCamera(origin=cam, target=(0.0, 0.0, 0.0), up=(0, 0, 1), fov_y_deg=fov_y_deg,
                               resolution=resolution)
    scene = Scene(voxel_size=geometry.voxel_mm, origin=origin, boundary=SDFBoundary(sdf, ior=ior), sensor=sensor,
                  emitter=light, g=g)
    return scene, shape, origin


# --------------------------------------------------------------------------------------------------------------
# The run
# --------------------------------------------------------------------------------------------------------------
@dataclass
class WoodVolumeConfig:
    """Settings of :func:`render_wood_volume` (``fit_dir`` or ``synthetic_seed``, not both)."""
    out: str = "results/wood_volume"
    fit_dir: Optional[str] = None
    synthetic_seed: Optional[int] = None
    synthetic_hw: Tuple[int, int] = (128, 160)
    synthetic_pixel_mm: float = 0.15
    thickness_mm: float = 1.8
    veneer_voxel_mm: Tuple[float, float] = (0.15, 0.15)
    veneer_max_extent_mm: float = 24.0
    veneer_resolution_mm: float = 0.15
    shade: LampshadeGeometry = field(default_factory=LampshadeGeometry)
    shade_resolution: Tuple[int, int] = (150, 150)
    sigma_early: float = SIGMA_EARLY
    sigma_late: float = SIGMA_LATE
    mapping: str = "table"
    g: float = 0.4
    ior: float = 1.5
    veneer_light_deg: float = 60.0
    veneer_radiance: float = 10.0
    shade_light_deg: Optional[float] = None   # default: 0.9 × the wall tilt (lights only the inside)
    shade_radiance: float = 10.0
    ambient: float = 0.02
    spp: int = 32
    shade_spp: int = 96
    passes: int = 4
    seed: int = 0
    threads: int = 0
    device: str = "cpu"  # where the tracer runs: "cpu", "cuda" or "cuda:N" (the images come back to the CPU)

    def validate(self):
        if (self.fit_dir is None) == (self.synthetic_seed is None):
            raise ValueError("fit_dir, synthetic_seed: expected exactly one (a fit run folder or a synthetic seed), "
                             f"got fit_dir={self.fit_dir!r}, synthetic_seed={self.synthetic_seed!r}")
        _check_thickness(self.thickness_mm)
        check_int("spp", self.spp, lo=1)
        check_int("shade_spp", self.shade_spp, lo=1)
        check_int("passes", self.passes, lo=1)
        check_int("threads", self.threads, lo=0)
        check_device("device", self.device)
        if self.mapping not in ("table", "elek"):
            raise ValueError(f"mapping: expected 'table' or 'elek', got {self.mapping!r}")
        if self.shade_light_deg is None and not self.shade.wall_tilt_deg > 0:
            # the default light is a disc of 0.9 × the wall's tilt below the shade: a shade no wider at the bottom
            # leaves it no room to light the inside only
            raise ValueError(f"shade: expected a bottom radius larger than the top radius (the default light, 0.9 × "
                             f"the wall's tilt, lights the inside through the lower opening), got bottom "
                             f"{self.shade.bottom_radius_mm:g} mm and top {self.shade.top_radius_mm:g} mm")
        return self


def _render(scene, vol, spp, passes, seed, bar, device="cpu"):
    """Mean of ``passes`` renders of ``spp`` samples (independent seeds) on ``device``, advancing the progress bar;
    the image on the CPU."""
    acc, stats_all, t0 = None, [], time.perf_counter()
    sigma_t, albedo = vol.sigma_t.to(device), vol.albedo.to(device)
    for k in range(passes):
        stats = {}
        img = render_scene(scene, sigma_t, albedo, spp=spp, seed=seed + k, stats=stats).cpu()
        acc = img if acc is None else acc + img
        stats_all.append(stats)
        bar.update(1)
    return acc / passes, {"seconds": round(time.perf_counter() - t0, 2),
                          "scatter_events": int(sum(s.get("scatter_events", 0) for s in stats_all)),
                          "spp": spp * passes}


def _exposure(*images, percentile=99.0, white=0.9):
    """One exposure factor for several linear images: their common ``percentile`` maps to ``white``."""
    values = np.concatenate([np.asarray(i, np.float64).max(-1).ravel() for i in images])
    p = float(np.percentile(values, percentile))
    return white / p if p > 0 else 1.0


def _write_image(folder, name, image, exposure):
    ta_io.write_exr(os.path.join(folder, name + ".exr"), image.numpy().astype(np.float32))
    ta_io.write_png(os.path.join(folder, name + ".png"), np.clip(image.numpy() * exposure, 0, 1).astype(np.float32))


def _figure(folder, photo, views, side_views, sections, shade, exposures):
    from matplotlib.figure import Figure
    from ..color import linear_to_srgb

    def show(ax, img, title, exposure=1.0, aspect="equal"):
        x = np.clip(np.asarray(img, np.float64) * exposure, 0, 1)
        ax.imshow(linear_to_srgb(torch.from_numpy(x)).numpy(), interpolation="nearest", aspect=aspect)
        ax.set_title(title, fontsize=9)
        ax.set_xticks([])
        ax.set_yticks([])

    fig = Figure(figsize=(13, 7.2))
    grid = fig.add_gridspec(3, 4, height_ratios=[3.0, 0.55, 0.55], width_ratios=[1, 1, 1, 1.25])
    show(fig.add_subplot(grid[0, 0]), photo, "board surface (model colour)")
    show(fig.add_subplot(grid[0, 1]), views["extruded"], "backlit veneer: extruded", exposures["veneer"])
    show(fig.add_subplot(grid[0, 2]), views["fit"], "backlit veneer: fitted volume", exposures["veneer"])
    show(fig.add_subplot(grid[:, 3]), shade, "lamp shade (light inside, from below)", exposures["shade"])
    stretch = 4.0   # depth drawn 4× taller than it is (voxels and side-view pixels are square)
    for col, key in ((1, "extruded"), (2, "fit")):
        show(fig.add_subplot(grid[1, col]), side_views[key], f"{key}: edge v = 0, light side up, depth ×{stretch:g}",
             exposures["side"], aspect=stretch)
        ax = fig.add_subplot(grid[2, col])
        ax.imshow(sections[key], cmap="magma", vmin=SIGMA_EARLY * 0.9, vmax=SIGMA_LATE, interpolation="nearest",
                  aspect=stretch)
        ax.set_title(f"{key}: σ_t at v = 0, front face up, depth ×{stretch:g}", fontsize=9)
        ax.set_xticks([])
        ax.set_yticks([])
    fig.subplots_adjust(left=0.01, right=0.99, top=0.95, bottom=0.01, wspace=0.04, hspace=0.25)
    ta_io.save_figure(fig, os.path.join(folder, "figure.png"), dpi=110)


def _load_model(cfg):
    if cfg.fit_dir is not None:
        model, board = load_wood_fit(cfg.fit_dir)
        return model, board["extent_mm"], {"source": "fit", "fit_dir": os.path.abspath(cfg.fit_dir), **board}
    from ..rings.synthetic import synthetic_board
    h, w = cfg.synthetic_hw
    b = synthetic_board(h, w, pixel_size_mm=cfg.synthetic_pixel_mm, seed=cfg.synthetic_seed, noise=0.0)
    model = b["model"]
    for p in model.parameters():
        p.requires_grad_(False)
    params = {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in b["params"].items()}
    return model, (w * cfg.synthetic_pixel_mm, h * cfg.synthetic_pixel_mm), {"source": "synthetic",
                                                                             "seed": cfg.synthetic_seed, **params}


def render_wood_volume(cfg: WoodVolumeConfig, progress=True, log=print):
    """Render the veneer (fitted and extruded, front and side) and the lamp shade; write the run folder.

    Writes ``veneer_fit.exr/.png``, ``veneer_extruded.exr/.png``, ``veneer_side_fit.exr/.png``,
    ``veneer_side_extruded.exr/.png``, ``lampshade.exr/.png`` (EXR: linear radiance; PNG: one exposure per scene
    kind, the same for fit and extruded, stated in the summary), ``figure.png`` and ``summary.json`` (settings,
    volume statistics, timings). Returns the summary dict.
    """
    from ..progress import progress_bar

    cfg.validate()
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    folder = cfg.out
    os.makedirs(folder, exist_ok=True)
    timings, t_all = {}, time.perf_counter()
    t0 = time.perf_counter()
    model, extent, source = _load_model(cfg)
    timings["load_model_s"] = round(time.perf_counter() - t0, 2)
    # the veneer: the board's centre, at most veneer_max_extent_mm on a side
    u_full, v_full = extent
    u = min(u_full, cfg.veneer_max_extent_mm)
    v = min(v_full, cfg.veneer_max_extent_mm)
    u0, v0 = (u_full - u) / 2, (v_full - v) / 2
    geometry = VeneerGeometry((u, v), cfg.thickness_mm, cfg.veneer_voxel_mm)
    light = DiscLight((0.0, 0.0, 1.0), cfg.veneer_light_deg, cfg.veneer_radiance, cfg.ambient)
    res = (max(1, round(v / cfg.veneer_resolution_mm)), max(1, round(u / cfg.veneer_resolution_mm)))
    front, side = veneer_scenes(geometry, light, resolution=res, g=cfg.g, ior=cfg.ior)
    shade_deg = 0.9 * cfg.shade.wall_tilt_deg if cfg.shade_light_deg is None else cfg.shade_light_deg
    shade_light = DiscLight((0.0, 0.0, -1.0), shade_deg, cfg.shade_radiance, cfg.ambient)
    shade_scene, shade_shape, shade_origin = lampshade_scene(cfg.shade, shade_light, resolution=cfg.shade_resolution,
                                                             ior=cfg.ior, g=cfg.g)
    common = dict(sigma_early=cfg.sigma_early, sigma_late=cfg.sigma_late, mapping=cfg.mapping, g=cfg.g, ior=cfg.ior)
    vols, volume_info = {}, {}
    t0 = time.perf_counter()
    for key in ("fit", "extruded"):
        vols[key] = wood_volume(model, geometry.grid_shape, geometry.voxel_size, (0.0, 0.0, 0.0),
                                world_to_board=(np.eye(3), (u0, v0, 0.0)), extruded=key == "extruded",
                                supersample=2, **common)
        volume_info["veneer_" + key] = vols[key].info
    rot, trans = lampshade_world_to_board(cfg.shade, extent)
    vols["shade"] = wood_volume(model, shade_shape, cfg.shade.voxel_mm, shade_origin, world_to_board=(rot, trans),
                                **common)
    volume_info["lampshade"] = vols["shade"].info
    timings["build_volumes_s"] = round(time.perf_counter() - t0, 2)

    renders, stats = {}, {}
    with progress_bar(total=5 * cfg.passes, desc="render_wood_volume", unit="pass", disable=not progress) as bar:
        for key in ("fit", "extruded"):
            renders["veneer_" + key], stats["veneer_" + key] = _render(front, vols[key], cfg.spp, cfg.passes,
                                                                      cfg.seed, bar, device=cfg.device)
            renders["side_" + key], stats["veneer_side_" + key] = _render(side, vols[key], cfg.spp, cfg.passes,
                                                                         cfg.seed + 1000, bar, device=cfg.device)
        renders["shade"], stats["lampshade"] = _render(shade_scene, vols["shade"], cfg.shade_spp, cfg.passes,
                                                       cfg.seed + 2000, bar, device=cfg.device)
    exposures = {"veneer": _exposure(renders["veneer_fit"], renders["veneer_extruded"]),
                 "side": _exposure(renders["side_fit"], renders["side_extruded"]),
                 "shade": _exposure(renders["shade"], percentile=99.5)}
    for key in ("fit", "extruded"):
        _write_image(folder, f"veneer_{key}", renders["veneer_" + key], exposures["veneer"])
        _write_image(folder, f"veneer_side_{key}", renders["side_" + key], exposures["side"])
    _write_image(folder, "lampshade", renders["shade"], exposures["shade"])
    with torch.no_grad():
        photo = model.evaluate(torch.stack(torch.meshgrid(
            u0 + (torch.arange(res[1], dtype=torch.float64) + 0.5) * (u / res[1]),
            v0 + (torch.arange(res[0], dtype=torch.float64) + 0.5) * (v / res[0]), indexing="xy"), -1)
            .reshape(-1, 2).to(model.color_map.dtype), board=True)["rgb"].reshape(res[0], res[1], 3)
    sections = {k: vols[k].sigma_t[0, :, 0, :].numpy() for k in ("fit", "extruded")}
    _figure(folder, photo.clamp(0, 1).double().numpy(),
            {k: renders["veneer_" + k] for k in ("fit", "extruded")},
            {k: renders["side_" + k] for k in ("fit", "extruded")}, sections, renders["shade"], exposures)
    diff = (renders["veneer_fit"] - renders["veneer_extruded"]).abs().mean() / renders["veneer_extruded"].mean()
    timings.update({f"render_{k}_s": v["seconds"] for k, v in stats.items()})
    timings["total_s"] = round(time.perf_counter() - t_all, 2)
    cfg_dict = asdict(cfg)
    summary = {"config": cfg_dict, "source": source, "board_extent_mm": list(extent),
               "veneer": {"extent_mm": [u, v], "offset_mm": [u0, v0], "thickness_mm": geometry.thickness_mm,
                          "grid_shape": list(geometry.grid_shape), "voxel_size_mm": list(geometry.voxel_size),
                          "resolution": list(res), "light": asdict(light),
                          "mean_radiance_fit": renders["veneer_fit"].mean(dim=(0, 1)).tolist(),
                          "mean_radiance_extruded": renders["veneer_extruded"].mean(dim=(0, 1)).tolist(),
                          "relative_mean_abs_difference_fit_vs_extruded": float(diff)},
               "lampshade": {"geometry": asdict(cfg.shade), "grid_shape": list(shade_shape),
                             "origin_mm": list(shade_origin), "light": asdict(shade_light),
                             "world_to_board": {"R": rot.tolist(), "t": list(trans)},
                             "resolution": list(cfg.shade_resolution)},
               "volumes": volume_info, "render_stats": stats, "png_exposure": exposures, "timings_s": timings}
    ta_io.write_json(os.path.join(folder, "summary.json"), summary)
    log(f"render_wood_volume: wrote {folder} in {timings['total_s']:.1f} s")
    return summary
