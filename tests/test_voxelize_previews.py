"""Previews of a voxelised object (torch_appearance.geometry.preview): offscreen pyvista renders of the texels where
this machine can render, the matplotlib fallback otherwise (and always when pyvista fails), the SDF slice, and
ta-voxelize writing them with --texture and "preview_backend" in its summary."""
import json
import os

import numpy as np
import pytest
import trimesh
from PIL import Image

from torch_appearance.geometry import voxelize
from torch_appearance.geometry import preview

ORANGE, BLUE = (230, 120, 20), (20, 90, 220)


@pytest.fixture(scope="module")
def ball():
    """An icosphere (R = 3 mm) at 0.3 mm voxels, orange below z = 1.5 mm and blue above (vertex colours)."""
    mesh = trimesh.creation.icosphere(radius=3)
    colours = np.tile(np.array([[*ORANGE, 255]], np.uint8), (len(mesh.vertices), 1))
    colours[mesh.vertices[:, 2] > 1.5, :3] = BLUE
    mesh.visual.vertex_colors = colours
    obj = voxelize(mesh, 0.3)
    assert obj.texel_colors is not None and len(obj.texel_points) > 500
    return obj


def _pixels(path, size):
    image = Image.open(path)
    assert image.size == size
    return np.asarray(image.convert("RGB"), dtype=np.float64).reshape(-1, 3)


def _share_with_hue_of(pixels, rgb, tol=0.04):
    """Fraction of pixels whose chromaticity (r, g, b) / (r + g + b) is within tol of rgb's (shading-invariant)."""
    total = pixels.sum(1, keepdims=True)
    ok = total[:, 0] > 60
    chroma = pixels[ok] / total[ok]
    target = np.asarray(rgb, np.float64) / sum(rgb)
    return float(np.mean(np.abs(chroma - target).max(1) < tol)) * ok.mean()


def test_texel_rgb8(ball):
    colours = preview.texel_rgb8(ball, "color")
    normals = preview.texel_rgb8(ball, "normal")
    assert colours.dtype == np.uint8 and colours.shape == normals.shape == (len(ball.texel_points), 3)
    # sRGB encoding of the linear colours brings back the vertex colours' 8-bit values.
    assert np.abs(colours.astype(int) - np.array(ORANGE)).max(1).min() <= 2
    n = ball.texel_normals.numpy()
    assert np.allclose(normals / 255.0, 0.5 + 0.5 * n, atol=1 / 255.0)
    with pytest.raises(ValueError):
        preview.render_texels(ball, colours[:-1], "x.png")


def test_render_texels_auto(ball, tmp_path):
    """The colour picture has the object's two colours in it and is not blank; pyvista where offscreen rendering
    works here, else the fallback."""
    ok, detail = preview.offscreen_rendering()
    path = tmp_path / "texels_color.png"
    backend = preview.render_texels(ball, preview.texel_rgb8(ball, "color"), str(path), size=(600, 200),
                                    title="target colour")
    assert backend == ("pyvista" if ok else "matplotlib"), detail
    pixels = _pixels(path, (600, 200))
    assert pixels.std(0).max() > 20.0
    assert _share_with_hue_of(pixels, ORANGE) > 0.03 and _share_with_hue_of(pixels, BLUE) > 0.005
    assert not [p for p in os.listdir(tmp_path) if p != "texels_color.png"]  # no temporary file left


def test_render_texels_pyvista_views(ball, tmp_path):
    ok, detail = preview.offscreen_rendering()
    if not ok:
        pytest.skip(f"no offscreen rendering here: {detail}")
    path = tmp_path / "one.png"
    assert preview.render_texels_pyvista(ball, preview.texel_rgb8(ball, "normal"), str(path), views=1,
                                         size=(300, 240)) == "pyvista"
    pixels = _pixels(path, (300, 240)).reshape(240, 300, 3)
    background = pixels[0, -1]
    covered = np.abs(pixels - background).max(2) > 30
    rows, cols = np.nonzero(covered[30:-30])  # between the label bands
    # The ball fills the view: its extent spans most of the height left between the text bands.
    assert rows.max() - rows.min() > 0.8 * (240 - 2 * 30 - 2 * 26)


def test_fallback_when_pyvista_cannot_render(ball, tmp_path, monkeypatch, capsys):
    """A failing probe or a failing render falls back to matplotlib with one warning line, never raises."""
    monkeypatch.setattr(preview, "_probe_result", (False, "no offscreen OpenGL context (test)"))
    monkeypatch.setattr(preview, "_warned", set())
    path = tmp_path / "fallback.png"
    rgb = preview.texel_rgb8(ball, "color")
    assert preview.render_texels(ball, rgb, str(path), size=(600, 200)) == "matplotlib"
    assert preview.render_texels(ball, rgb, str(path), size=(600, 200)) == "matplotlib"
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "matplotlib" in err[0] and "no offscreen OpenGL context (test)" in err[0]
    pixels = _pixels(path, (600, 200))
    assert pixels.std(0).max() > 20.0 and _share_with_hue_of(pixels, ORANGE) > 0.01

    def broken(*args, **kwargs):
        raise MemoryError("boom")

    monkeypatch.setattr(preview, "render_texels_pyvista", broken)
    assert preview.render_texels(ball, rgb, str(path), size=(600, 200)) == "matplotlib"
    assert "MemoryError: boom" in capsys.readouterr().err


def test_write_previews_and_cli(ball, tmp_path):
    """write_previews writes all three pictures; the script passes --texture to load_mesh, reports the backend."""
    result = preview.write_previews(ball, str(tmp_path / "ball"), size=(450, 150))
    assert result["backend"] in ("pyvista", "matplotlib")
    assert result["files"] == ["texels_color.png", "texels_normal.png", "sdf_slice.png"]
    assert _pixels(tmp_path / "ball" / "texels_normal.png", (450, 150)).std(0).max() > 20.0
    assert Image.open(tmp_path / "ball" / "sdf_slice.png").size[0] > 300

    # A box with UVs and no material, coloured by a one-colour texture given on the command line.
    box = trimesh.creation.box((2.0, 2.0, 2.0))
    uv = (box.vertices[:, :2] + 1.0) / 2.0
    lines = [f"v {x} {y} {z}" for x, y, z in box.vertices] + [f"vt {u} {v}" for u, v in uv]
    lines += ["f " + " ".join(f"{i + 1}/{i + 1}" for i in face) for face in box.faces]
    (tmp_path / "box.obj").write_text("\n".join(lines) + "\n")
    Image.new("RGB", (4, 4), BLUE).save(tmp_path / "blue.png")
    from torch_appearance.cli import voxelize as cli
    out = tmp_path / "out"
    assert cli.main([str(tmp_path / "box.obj"), "--texture", str(tmp_path / "blue.png"), "--height-mm", "3",
                     "--dpi", "80", "--out", str(out), "--quiet"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["preview_backend"] in ("pyvista", "matplotlib") and summary["colour"] == "texture"
    pixels = _pixels(out / "texels_color.png", (1200, 400))
    assert _share_with_hue_of(pixels, BLUE) > 0.1


def test_optimiser_after_an_offscreen_render_does_not_crash(tmp_path):
    """A pyvista render (Mesa's LLVM) followed by the first torch.optim optimiser (which imports torch._dynamo and
    Triton's LLVM) in one process: this used to end in a segfault, e.g. scripts/voxelize.py then optimize_print in
    one pytest worker. Run in a child process so that a crash fails this test instead of the whole session."""
    import subprocess
    import sys

    ok, detail = preview.offscreen_rendering()
    if not ok:
        pytest.skip(f"no offscreen rendering here: {detail}")
    code = (
        "import sys, trimesh, torch\n"
        "from torch_appearance.geometry import voxelize, preview\n"
        "obj = voxelize(trimesh.creation.box(extents=(1, 1, 1)), 0.1)\n"
        "preview.write_previews(obj, sys.argv[1], backend='pyvista')\n"
        "torch.optim.Adagrad([torch.zeros(2, requires_grad=True)])\n"
        "print('survived')\n")
    run = subprocess.run([sys.executable, "-c", code, str(tmp_path / "previews")], capture_output=True, text=True,
                         timeout=300, cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    assert run.returncode == 0 and "survived" in run.stdout, (run.returncode, run.stderr[-2000:])
