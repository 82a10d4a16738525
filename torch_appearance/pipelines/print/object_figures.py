"""Figures of an object print: the target texture on the mesh, the rendered quantised print and the per-texel
CIEDE2000 on the mesh, from the same cameras (pyvista offscreen for the mesh pictures; the tracer for the print).
"""
import sys

import numpy as np

from ... import io as ta_io
from ...color import linear_to_srgb8

__all__ = ["mesh_views", "views_figure"]


def _polydata(mesh):
    import pyvista as pv

    faces = np.hstack([np.full((len(mesh.faces), 1), 3), np.asarray(mesh.faces)]).astype(np.int64).ravel()
    return pv.PolyData(np.asarray(mesh.vertices, dtype=np.float64), faces)


def mesh_views(mesh, cams, *, scalars=None, cmap="magma", clim=None):
    """Pictures of a mesh seen by the tracer's cameras: its base-colour texture (or vertex colours) unlit, i.e.
    the surface colour a print under uniform white light should show, or per-vertex ``scalars`` through ``cmap``.

    Args:
        mesh: ``trimesh.Trimesh`` (mm). cams: :class:`~torch_appearance.render.PerspectiveCamera` list.
        scalars: optional (V,) per-vertex values. clim: (lo, hi) of the colour map.

    Returns:
        List of (rows, cols, 3) uint8 sRGB images, or None when offscreen rendering fails here (reason on stderr).
    """
    from ...geometry.preview import offscreen_rendering

    ok, why = offscreen_rendering()  # checked once in a child process: a VTK crash cannot end this run
    if not ok:
        print(f"object figures: no mesh pictures, pyvista cannot render offscreen here ({why})", file=sys.stderr)
        return None
    try:
        import pyvista as pv

        poly = _polydata(mesh)
        kwargs = dict(lighting=False, show_scalar_bar=False)
        visual = mesh.visual
        image = getattr(getattr(visual, "material", None), "image", None)
        if image is None:
            image = getattr(getattr(visual, "material", None), "baseColorTexture", None)
        if scalars is not None:
            poly.point_data["values"] = np.asarray(scalars, dtype=np.float64)
            kwargs.update(scalars="values", cmap=cmap, clim=clim)
        elif getattr(visual, "kind", None) == "texture" and image is not None and getattr(visual, "uv", None) is not None:
            poly.active_texture_coordinates = np.asarray(visual.uv, dtype=np.float64)
            kwargs.update(texture=pv.numpy_to_texture(np.asarray(image.convert("RGB"))))
        elif getattr(visual, "kind", None) == "vertex":
            poly.point_data["rgb"] = np.asarray(visual.vertex_colors)[:, :3]
            kwargs.update(scalars="rgb", rgb=True)
        out = []
        rows, cols = cams[0].resolution
        plotter = pv.Plotter(off_screen=True, window_size=(cols, rows))  # one window for every view
        try:
            plotter.set_background("white")
            plotter.add_mesh(poly, **kwargs)
            for cam in cams:
                plotter.window_size = (cam.resolution[1], cam.resolution[0])
                plotter.camera.position = cam.origin
                plotter.camera.focal_point = cam.target
                plotter.camera.up = cam.up
                plotter.camera.view_angle = cam.fov_y_deg
                plotter.camera.clipping_range = (1e-3, 1e6)
                plotter.render()  # without it the screenshot shows the previous camera's frame
                out.append(np.asarray(plotter.screenshot(return_img=True))[..., :3].copy())
        finally:
            plotter.close()
        return out
    except Exception as error:  # offscreen OpenGL missing or broken: figures go on without the mesh pictures
        print(f"object figures: pyvista could not render offscreen ({type(error).__name__}: {error})", file=sys.stderr)
        return None


def views_figure(path, target, cams, renders, *, texel_de=None, log=print, texel_index=None):
    """``views.png``: the target texture on the mesh (top), the rendered quantised print (middle) and, with
    ``texel_de`` (M,) of the texels ``texel_index`` (M,) (None: all N), its per-texel CIEDE2000 on the mesh
    (bottom), one column per camera."""
    from matplotlib.figure import Figure
    from scipy.spatial import cKDTree

    rows = [("target (texture on the mesh, unlit)", mesh_views(target.mesh, cams) if target.mesh is not None
             else None),
            ("print (quantised, rendered)", [linear_to_srgb8(r) for r in renders])]
    clim = None
    if texel_de is not None and target.mesh is not None:
        # each vertex shows the mean of its 16 nearest texels' estimates: a texel's own estimate is free of the render
        # noise's bias but not of its spread, which would draw swirls of noise at a vertex's scale
        points = target.obj.texel_points.numpy()
        texels = cKDTree(points if texel_index is None else points[np.asarray(texel_index)])
        _, nearest = texels.query(np.asarray(target.mesh.vertices), k=min(16, len(texel_de)), workers=-1)
        per_vertex = np.asarray(texel_de, np.float64)[nearest.reshape(len(nearest), -1)].mean(1)
        clim = (0.0, max(1.0, float(np.percentile(texel_de, 99))))
        rows.append(("CIEDE2000 of the print (render noise taken out; 16 texels averaged)",
                     mesh_views(target.mesh, cams, scalars=per_vertex, clim=clim)))
    rows = [(name, images) for name, images in rows if images is not None]
    n = len(cams)
    fig = Figure(figsize=(3.2 * n, 3.3 * len(rows)))
    for r, (name, images) in enumerate(rows):
        for c, image in enumerate(images):
            ax = fig.add_subplot(len(rows), n, r * n + c + 1)
            ax.imshow(image)
            ax.set_axis_off()
            if c == 0:
                ax.set_title(name, fontsize=9, loc="left")
    if clim is not None:
        import matplotlib.cm as cm
        import matplotlib.colors as mcolors
        mappable = cm.ScalarMappable(norm=mcolors.Normalize(*clim), cmap="magma")
        fig.colorbar(mappable, ax=fig.axes[-n:], fraction=0.03, pad=0.02, label="CIEDE2000")
    ta_io.save_figure(fig, path)
    log(f"optimize_print: views -> {path}")
    return len(rows)
