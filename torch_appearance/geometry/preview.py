"""Preview pictures of a :class:`~torch_appearance.geometry.VoxelObject`: its texels rendered offscreen with pyvista
(coloured by their target colour or their normals, three views side by side) and a slice through its SDF.

The pyvista rendering needs an offscreen OpenGL context. Without an X display VTK (>= 9.4 wheels) can render
through EGL or OSMesa; whether that works is found out once per process in a throw-away child process (a missing
or broken OpenGL library can abort the whole process, which ``try`` cannot catch). Where it does not work, or the
rendering fails for any other reason, the same pictures are drawn as matplotlib 3-D scatter plots instead, with a
one-line warning on stderr. ``TA_PREVIEW_BACKEND=matplotlib`` in the environment forces the fallback.

Example::

    from torch_appearance.geometry import voxelize
    from torch_appearance.geometry.preview import write_previews
    backend = write_previews(voxelize(mesh, 0.1), "results/vox")["backend"]   # "pyvista" or "matplotlib"
"""
import contextlib
import math
import os
import re
import subprocess
import sys
import time
import uuid

import numpy as np

from ..checks import is_int
from ..interrupts import sigint_deferred

__all__ = ["texel_rgb8", "render_texels", "render_texels_pyvista", "render_texels_matplotlib", "sdf_slice",
           "write_previews", "offscreen_rendering"]

BACKGROUND, BACKGROUND_TOP = (0.80, 0.80, 0.80), (0.93, 0.93, 0.93)  # neutral grey gradient (sRGB)
TEXT_COLOR = (0.1, 0.1, 0.1)
LABEL_PX = 26  # pixels kept at the top of each view for its label, and at the bottom for notes
FILL_PAD = 1.03  # the object fills the view up to this margin
SURFEL_SIDE = 1.75  # surfel squares' side in voxels (closes the gaps between neighbouring texels' points)
# camera lights (position in camera coordinates: +x right, +y up, +z towards the viewer; intensity)
LIGHTS = (((0.0, 0.0, 1.0), 0.6), ((-1.0, 1.2, 1.5), 0.45))
MATERIAL = dict(ambient=0.5, diffuse=0.6, specular=0.05, specular_power=15.0)  # lit faces ≈ their own colour
# (label, azimuth from the front (-y) towards +x in degrees, elevation in degrees): together they show all six sides.
VIEWS = (("front-left, from above", -35.0, 25.0),
         ("back-right, from above", 145.0, 25.0),
         ("front-right, from below", 55.0, -30.0))
CUBES_UP_TO = 30000  # texels drawn as voxel cubes up to this many, as surfels beyond

_PROBE = r"""
import sys
import pyvista as pv
p = pv.Plotter(off_screen=True, window_size=(64, 48))
p.add_mesh(pv.Sphere(radius=0.5), color="red")
img = p.screenshot(return_img=True)
name = type(p.render_window).__name__
p.close()
ok = img is not None and img.shape[:2] == (48, 64) and float(img.std()) > 1.0
print("TA_PROBE", "ok" if ok else "blank", name, pv.__version__, pv.vtk_version_info)
"""
_probe_result = None  # cached (ok, detail)
_warned = set()  # fallback reasons already reported
_ANSI = re.compile(r"\x1b\[[0-9;]*m")


def _clean(text):
    """One line without terminal colours; VTK log lines reduced to their message."""
    lines = [_ANSI.sub("", line).strip() for line in str(text).splitlines()]
    lines = [line.split("| ", 1)[1] if re.search(r"(WARN|ERR|INFO)\s*\| ", line) else line for line in lines]
    return " ".join(line for line in lines if line)


def _warn(message):
    print(f"torch_appearance.geometry.preview: {message}", file=sys.stderr, flush=True)


def _prepare_environment():
    """Without an X display, ask VTK for its EGL window directly (it would try X first and warn)."""
    if not os.environ.get("DISPLAY") and not os.environ.get("WAYLAND_DISPLAY") and sys.platform.startswith("linux"):
        os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")


def _load_triton_before_mesa():
    """Import torch._dynamo (and with it Triton's LLVM) before VTK renders in this process.

    Offscreen rendering goes through Mesa's llvmpipe, which loads its own LLVM; Triton loaded after it crashes the
    interpreter (a segfault inside ``import triton``, e.g. at the first ``torch.optim`` optimiser, which imports
    torch._dynamo). The other order works, so every in-process render calls this first."""
    try:
        import torch._dynamo  # noqa: F401
    except Exception:  # pragma: no cover - a torch without dynamo cannot crash this way
        pass


def offscreen_rendering(timeout=90.0):
    """Whether pyvista can render offscreen in this process's environment (checked once, in a child process).

    Returns:
        (ok, detail): ``ok`` bool; ``detail`` names the render window class and versions when ok, else why not.
    """
    global _probe_result
    _load_triton_before_mesa()  # every in-process render asks this first
    if _probe_result is not None:
        return _probe_result
    forced = os.environ.get("TA_PREVIEW_BACKEND", "").strip().lower()
    if forced and forced != "pyvista":
        _probe_result = (False, f"TA_PREVIEW_BACKEND={forced}")
        return _probe_result
    import importlib.util

    if importlib.util.find_spec("pyvista") is None or importlib.util.find_spec("vtk") is None:
        _probe_result = (False, "pyvista/vtk not installed")
        return _probe_result
    _prepare_environment()
    candidates = [os.environ.get("VTK_DEFAULT_OPENGL_WINDOW")]
    if candidates[0] == "vtkEGLRenderWindow":
        candidates.append("vtkOSOpenGLRenderWindow")  # OSMesa, where EGL is missing
    reasons = []
    for window in candidates:
        env = dict(os.environ)
        if window:
            env["VTK_DEFAULT_OPENGL_WINDOW"] = window
        try:
            run = subprocess.run([sys.executable, "-c", _PROBE], env=env, capture_output=True, text=True,
                                 timeout=timeout)
        except (OSError, subprocess.SubprocessError) as error:
            reasons.append(f"{window or 'default window'}: {type(error).__name__}: {error}")
            continue
        line = next((l for l in run.stdout.splitlines() if l.startswith("TA_PROBE")), "")
        if run.returncode == 0 and line.split()[1:2] == ["ok"]:
            if window:
                os.environ["VTK_DEFAULT_OPENGL_WINDOW"] = window
            _probe_result = (True, " ".join(line.split()[2:]))
            return _probe_result
        tail = [_clean(l) for l in (run.stderr or "").splitlines() if _clean(l)]
        errors = [l for l in tail if "rror" in l or "not found" in l or "ailed" in l]
        why = line or (errors[-1] if errors else tail[-1] if tail else f"exit status {run.returncode}")
        if run.returncode < 0:
            why = f"killed by signal {-run.returncode}; " + why
        reasons.append(f"{window or 'default window'}: {why[-200:]}")
    _probe_result = (False, "no offscreen OpenGL context (" + " | ".join(reasons) + ")")
    return _probe_result


# ----------------------------------------------------------------------------------------------------------------
# colours
# ----------------------------------------------------------------------------------------------------------------
def texel_rgb8(obj, what="color"):
    """Per-texel display colours as (N, 3) uint8: ``"color"`` sRGB-encodes the linear target colours (None when the
    object has none), ``"normal"`` maps the normals to 0.5 + 0.5 n."""
    if what == "color":
        if obj.texel_colors is None:
            return None
        lin = np.clip(np.asarray(obj.texel_colors.detach().cpu().numpy(), dtype=np.float64), 0.0, 1.0)
        srgb = np.where(lin <= 0.0031308, 12.92 * lin, 1.055 * lin ** (1 / 2.4) - 0.055)
    elif what == "normal":
        srgb = 0.5 + 0.5 * np.asarray(obj.texel_normals.detach().cpu().numpy(), dtype=np.float64)
    else:
        raise ValueError(f"what: expected 'color' or 'normal', got {what!r}")
    return np.rint(np.clip(srgb, 0.0, 1.0) * 255.0).astype(np.uint8)


def _check_render_args(obj, values, views, size):
    n = int(len(obj.texel_points))
    if n == 0:
        raise ValueError("obj: expected a voxel object with texels to render, got one with 0 texels")
    if not is_int(views) or not 1 <= views <= len(VIEWS):  # a ValueError for a wrong type too, as ever here
        raise ValueError(f"views: expected an int in [1, {len(VIEWS)}], got {views!r}")
    if len(size) != 2 or not all(16 <= int(v) <= 8192 for v in size):
        raise ValueError(f"size: expected (width, height) in pixels, 16..8192, got {size!r}")
    return n, _as_rgb8(values, n), int(views)


def _as_rgb8(values, n):
    if hasattr(values, "detach"):
        values = values.detach().cpu().numpy()
    values = np.asarray(values)
    if values.shape != (n, 3):
        raise ValueError(f"values: expected shape ({n}, 3) (one RGB per texel), got {values.shape}")
    if values.dtype == np.uint8:
        return values
    if not np.issubdtype(values.dtype, np.number) or not np.isfinite(values).all():
        raise ValueError("values: expected uint8 or finite floats in [0, 1] (display-encoded)")
    return np.rint(np.clip(values, 0.0, 1.0) * 255.0).astype(np.uint8)


# ----------------------------------------------------------------------------------------------------------------
# rendering
# ----------------------------------------------------------------------------------------------------------------
def _view_basis(azimuth, elevation):
    """Unit vector from the object towards the camera, and the camera's up vector (z up)."""
    a, e = math.radians(azimuth), math.radians(elevation)
    towards = np.array([math.cos(e) * math.sin(a), -math.cos(e) * math.cos(a), math.sin(e)])
    up = np.array([0.0, 0.0, 1.0])
    up = up - towards * (up @ towards)
    return towards, up / np.linalg.norm(up)


def _atomic_target(path):
    """(path, temporary name next to it): the picture is written to the latter (with the umask's permissions,
    unlike mkstemp's 0600) and renamed."""
    path = os.fspath(path)
    folder = os.path.dirname(os.path.abspath(path))
    os.makedirs(folder, exist_ok=True)
    return path, os.path.join(folder, f".{os.path.basename(path)}.{os.getpid()}.{uuid.uuid4().hex[:12]}.tmp.png")


def render_texels_pyvista(obj, values, path, *, views=3, size=(1200, 400), title=None, shading=1.0):
    """Render the texels offscreen with pyvista, coloured per texel, from ``views`` sides next to each other.

    Up to :data:`CUBES_UP_TO` texels are drawn as their voxels' cubes (at the voxel centres); more as surfels:
    squares of :data:`SURFEL_SIDE` voxels at the texels' surface points, facing along their normals (so they are
    lit like the surface; points-as-spheres sprites would each be shaded like a ball and look grainy). Orthographic
    cameras with z up, each fitted to the object (see :data:`VIEWS`); two camera-attached lights (a headlight and a
    key light from the upper left); a neutral grey background; the view's name on top of each view, ``title``,
    the voxel size and the axes below. Written atomically (a temporary file in the same folder, renamed).

    Args:
        obj: a VoxelObject.
        values: (N, 3) per-texel display colours: uint8, or floats in [0, 1] (already display-encoded, e.g.
            sRGB); see :func:`texel_rgb8`.
        path: PNG file to write.
        views: 1 to 3 views, the first ones of :data:`VIEWS`.
        size: (width, height) of the whole picture in pixels.
        title: a note under the first view.
        shading: 1 lights the texels fully (faces towards the lights show about their own colour, others are
            darker); 0 shows the colours unlit; in between mixes.

    Returns:
        ``"pyvista"``.

    Raises:
        ValueError: bad arguments.
        RuntimeError: offscreen rendering is not available here (see :func:`offscreen_rendering`); or anything
            that pyvista/VTK raises. :func:`render_texels` catches these and falls back to matplotlib.
    """
    n, rgb, views = _check_render_args(obj, values, views, size)
    width, height = int(size[0]), int(size[1])
    shading = float(np.clip(shading, 0.0, 1.0))
    material = dict(MATERIAL, ambient=1.0 - shading * (1.0 - MATERIAL["ambient"]),
                    diffuse=shading * MATERIAL["diffuse"], specular=shading * MATERIAL["specular"])
    ok, detail = offscreen_rendering()
    if not ok:
        raise RuntimeError(detail)
    import pyvista as pv

    h = float(obj.voxel_size)
    if n <= CUBES_UP_TO:  # the voxels themselves
        pts = (obj.texel_voxels.detach().cpu().numpy()[:, ::-1].astype(np.float64) + 0.5) * h
        pts += np.asarray(obj.origin, dtype=np.float64)
        cloud = pv.PolyData(pts)
        cloud["rgb"] = rgb
        mesh = cloud.glyph(geom=pv.Cube(x_length=h, y_length=h, z_length=h), scale=False, orient=False)
    else:  # surfels: squares of SURFEL_SIDE voxels at the surface points, facing along the normals
        pts = obj.texel_points.detach().cpu().numpy().astype(np.float64)
        cloud = pv.PolyData(pts)
        cloud["rgb"] = rgb
        cloud["normal"] = obj.texel_normals.detach().cpu().numpy().astype(np.float64)
        side = SURFEL_SIDE * h
        square = pv.Plane(direction=(1.0, 0.0, 0.0), i_size=side, j_size=side, i_resolution=1, j_resolution=1)
        mesh = cloud.glyph(geom=square, orient="normal", scale=False)  # the glyph's x axis → the normal
    del cloud
    margin = 0.5 * h * (1.0 if n <= CUBES_UP_TO else SURFEL_SIDE)
    vw, vh = width / views, float(height)
    font = float(np.clip(min(vw / 40.0, vh / 25.0), 5.0, 10.0))  # 10 pt in views of 400 px; smaller ones shrink it
    label_px = int(round(LABEL_PX * font / 10.0))
    band = min(0.2, label_px / vh)  # top and bottom parts of each view kept for text
    notes = [title or "", f"voxel {h:.4g} mm, {n} texels", "z up, front = -y"]
    notes = notes[:views - 1] + [", ".join(note for note in notes[views - 1:] if note)]  # one per view

    plotter = pv.Plotter(off_screen=True, shape=(1, views), window_size=(width, height), border=False,
                         lighting="none")
    try:
        plotter.set_background(BACKGROUND, top=BACKGROUND_TOP)
        for k in range(views):
            label, azimuth, elevation = VIEWS[k]
            plotter.subplot(0, k)
            plotter.add_mesh(mesh, scalars="rgb", rgb=True, show_scalar_bar=False, **material)
            towards, up = _view_basis(azimuth, elevation)
            right = np.cross(up, towards)
            u, v = pts @ right, pts @ up
            half_w = 0.5 * (u.max() - u.min()) + margin
            half_h = 0.5 * (v.max() - v.min()) + margin
            scale = FILL_PAD * max(half_h / (1.0 - 2.0 * band), half_w * vh / vw)  # half the view height, mm
            focal = 0.5 * (pts.max(0) + pts.min(0))  # then moved to the middle of the projected extent
            focal = focal + (0.5 * (u.max() + u.min()) - focal @ right) * right
            focal = focal + (0.5 * (v.max() + v.min()) - focal @ up) * up
            distance = 2.0 * float(np.linalg.norm(pts.max(0) - pts.min(0))) + 10.0 * h
            camera = plotter.camera
            camera.SetParallelProjection(True)
            camera.SetFocalPoint(*focal)
            camera.SetPosition(*(focal + distance * towards))
            camera.SetViewUp(*up)
            camera.SetParallelScale(scale)
            plotter.renderer.ResetCameraClippingRange()
            for position, intensity in LIGHTS:
                plotter.renderer.add_light(pv.Light(position=position, focal_point=(0.0, 0.0, 0.0),
                                                    intensity=intensity, light_type="camera light"))
            plotter.add_text(label, position=(int(0.8 * font), int(vh) - label_px + int(0.3 * font)),
                             font_size=int(round(font)), color=TEXT_COLOR)
            if notes[k]:
                plotter.add_text(notes[k], position=(int(0.8 * font), int(0.5 * font)),
                                 font_size=int(round(0.8 * font)), color=TEXT_COLOR)
        final, tmp = _atomic_target(path)
        try:
            plotter.screenshot(tmp)
            if not os.path.getsize(tmp):
                raise RuntimeError("the screenshot came back empty")
            os.replace(tmp, final)
        except BaseException:
            with contextlib.suppress(OSError):
                os.unlink(tmp)
            raise
    finally:
        plotter.close()
    return "pyvista"


def render_texels_matplotlib(obj, values, path, *, views=3, size=(1200, 400), title=None, shading=None):
    """The fallback of :func:`render_texels_pyvista`: matplotlib 3-D scatter plots of the texels' surface points
    (at most 60 000 of them, markers about a voxel across), same views and arguments (``shading`` is ignored).
    Returns ``"matplotlib"``."""
    from matplotlib.figure import Figure

    from .. import io as ta_io

    n, rgb, views = _check_render_args(obj, values, views, size)
    rgb = rgb.astype(np.float64) / 255.0
    pts = obj.texel_points.detach().cpu().numpy().astype(np.float64)
    dpi = 100.0
    fig = Figure(figsize=(size[0] / dpi, size[1] / dpi))
    fig.subplots_adjust(left=0.0, right=1.0, bottom=0.0, top=0.93, wspace=0.0)
    step = max(1, n // 60000)
    extent = float(np.linalg.norm(np.ptp(pts, axis=0))) + float(obj.voxel_size)
    zoom = 1.15
    px_per_mm = 0.75 * zoom * min(size[0] / views, size[1]) / extent
    marker = float(np.clip((1.5 * float(obj.voxel_size) * px_per_mm * 72.0 / dpi) ** 2, 0.3, 40.0))  # points²
    for k in range(views):
        label, azimuth, elevation = VIEWS[k]
        ax = fig.add_subplot(1, views, k + 1, projection="3d")
        ax.scatter(pts[::step, 0], pts[::step, 1], pts[::step, 2], c=rgb[::step], s=marker, depthshade=False,
                   linewidths=0)
        # matplotlib's azimuth is measured from +x towards +y; ours from the front (-y) towards +x.
        ax.view_init(elev=elevation, azim=azimuth - 90.0)
        ax.set_box_aspect(np.ptp(pts, axis=0) + 1e-9, zoom=zoom)
        ax.set_axis_off()
        ax.set_title(label, fontsize=10)
        if k == 0 and title:
            ax.text2D(0.02, 0.02, f"{title} (matplotlib fallback)", transform=ax.transAxes, fontsize=8)
    ta_io.save_figure(fig, path, dpi=dpi)
    return "matplotlib"


def render_texels(obj, values, path, *, views=3, size=(1200, 400), title=None, shading=1.0, backend="auto"):
    """:func:`render_texels_pyvista` where it works, else :func:`render_texels_matplotlib` (with a one-line warning on
    stderr saying why; once per reason). Never raises because of the pyvista rendering.

    Args:
        backend: ``"auto"`` (or ``"pyvista"``, the same) or ``"matplotlib"``; the rest as
            :func:`render_texels_pyvista`.

    Returns:
        The backend used: ``"pyvista"`` or ``"matplotlib"``.
    """
    if backend not in ("auto", "pyvista", "matplotlib"):
        raise ValueError(f"backend: expected 'auto', 'pyvista' or 'matplotlib', got {backend!r}")
    _check_render_args(obj, values, views, size)  # the caller's mistakes are no reason to fall back
    if backend != "matplotlib":
        try:
            with sigint_deferred():  # Ctrl-C raised inside VTK's Python wrapping could crash it (exit 139)
                return render_texels_pyvista(obj, values, path, views=views, size=size, title=title,
                                             shading=shading)
        except Exception as error:  # noqa: BLE001  (any rendering failure falls back)
            why = _clean(f"{type(error).__name__}: {error}")
            if why not in _warned:
                _warned.add(why)
                _warn(f"pyvista rendering failed, drawing matplotlib scatter previews instead ({why[:400]})")
    return render_texels_matplotlib(obj, values, path, views=views, size=size, title=title)


def sdf_slice(obj, path):
    """The SDF through the middle of the object (the xz plane of corner samples nearest the grid's middle in y), on
    a diverging colour scale clamped to the band, with its zero level; beside it a close-up, 30 voxels across, of
    the zero level where it reaches highest (matplotlib, written atomically)."""
    from matplotlib.figure import Figure
    from matplotlib.patches import Rectangle

    from .. import io as ta_io

    d, h, w = obj.grid_shape
    j = (h + 1) // 2
    sdf = obj.sdf.detach().cpu().numpy()[:, j, :].astype(np.float64)
    x0, y0, z0 = (float(c) for c in obj.origin)
    s = float(obj.voxel_size)
    band = float(obj.band_mm)
    xs, zs = x0 + s * np.arange(w + 1), z0 + s * np.arange(d + 1)  # the samples sit on the voxel corners
    inside = np.argwhere(sdf < 0.0)
    aspect = (w + 1) / (d + 1)
    zoom = len(inside) > 0 and min(d, w) > 40
    main_w = float(np.clip(4.6 * aspect, 2.2, 9.0))
    fig = Figure(figsize=(main_w + (4.2 if zoom else 0.0) + 1.3, float(np.clip(4.6 / aspect, 2.6, 5.2)) + 0.9),
                 layout="constrained")
    axes = fig.subplots(1, 2, width_ratios=[main_w, 4.2]) if zoom else [fig.add_subplot(1, 1, 1)]

    def draw(ax, rows, cols):
        sub = sdf[rows, cols]
        extent = (xs[cols][0] - 0.5 * s, xs[cols][-1] + 0.5 * s, zs[rows][0] - 0.5 * s, zs[rows][-1] + 0.5 * s)
        im = ax.imshow(sub, origin="lower", extent=extent, cmap="RdBu", vmin=-band, vmax=band,
                       interpolation="nearest")
        if sub.min() < 0.0 < sub.max():
            ax.contour(xs[cols], zs[rows], sub, levels=[0.0], colors="k", linewidths=0.8)
        ax.set(xlabel="x [mm]", ylabel="z [mm]")
        return im

    im = draw(axes[0], slice(None), slice(None))
    axes[0].set_title(f"SDF, xz slice at y = {y0 + j * s:.2f} mm", fontsize=10)
    if zoom:
        top = inside[np.argmax(inside[:, 0] * (w + 1) + inside[:, 1])]  # highest inside sample (then rightmost)
        half = 15
        r0 = int(np.clip(top[0] - half, 0, max(0, d - 2 * half)))
        c0 = int(np.clip(top[1] - half, 0, max(0, w - 2 * half)))
        rows, cols = slice(r0, r0 + 2 * half + 1), slice(c0, c0 + 2 * half + 1)
        draw(axes[1], rows, cols)
        axes[1].set_title(f"close-up: {2 * half} voxels of {s:.4g} mm, band ±{band:.3g} mm", fontsize=10)
        axes[0].add_patch(Rectangle((xs[c0] - 0.5 * s, zs[r0] - 0.5 * s), 2 * half * s + s, 2 * half * s + s,
                                    fill=False, edgecolor="k", linewidth=0.8, linestyle="--"))
    fig.colorbar(im, ax=list(axes), label="signed distance [mm], clamped to the band", shrink=0.85)
    ta_io.save_figure(fig, path)


def write_previews(obj, folder, *, backend="auto", size=(1200, 400), progress=None):
    """Write ``texels_color.png`` (when the object has colours), ``texels_normal.png`` and ``sdf_slice.png``.

    Args:
        obj: a VoxelObject.
        folder: created when missing.
        backend: for the texel pictures, see :func:`render_texels`.
        size: their (width, height) in pixels.
        progress: optional ``callable(str)``, told about each picture as it starts.

    Returns:
        dict: ``backend`` (the texel pictures' backend: ``"pyvista"``, ``"matplotlib"``, ``"pyvista+matplotlib"``
        when one fell back and the other did not, or None without texels), ``files`` (names written) and
        ``seconds`` (per file).
    """
    os.makedirs(folder, exist_ok=True)
    n = int(len(obj.texel_points))
    used, files, seconds = [], [], {}
    for what, title, shading in (("color", "target colour (sRGB)", 1.0), ("normal", "normal as 0.5 + 0.5 n", 0.4)):
        rgb = texel_rgb8(obj, what)
        if rgb is None or n == 0:
            continue
        name = f"texels_{what}.png"
        if progress:
            progress(f"rendering {name} ({n} texels) …")
        t = time.perf_counter()
        used.append(render_texels(obj, rgb, os.path.join(folder, name), size=size, title=title, shading=shading,
                                  backend=backend))
        seconds[name] = time.perf_counter() - t
        files.append(name)
    if progress:
        progress("drawing sdf_slice.png …")
    t = time.perf_counter()
    sdf_slice(obj, os.path.join(folder, "sdf_slice.png"))
    seconds["sdf_slice.png"] = time.perf_counter() - t
    files.append("sdf_slice.png")
    kinds = sorted(set(used), key=used.index)
    return {"backend": "+".join(sorted(kinds, reverse=True)) if kinds else None, "files": files, "seconds": seconds}
