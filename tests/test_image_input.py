"""Image input everywhere (issue 15): one reader, torch_appearance.io.read_image, that decodes every pixel, refuses
truncated or corrupt files with a message naming the file, and converts colour encodings explicitly; and every
command that reads images refuses a truncated PNG or JPEG before writing anything.

Test images are written here with Pillow / OpenEXR (a different encoder from the OpenCV decoder the reader uses)
from known integer values; the expected floats are those integers over 2**bits - 1 and their sRGB decoding written
out from IEC 61966-2-1.
"""
import contextlib
import importlib
import io
import os
import warnings

import cv2
import numpy as np
import OpenEXR
import pytest
from PIL import Image, ImageCms, ImageFile

from torch_appearance import io as ta_io

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _decode_reference(v):
    """sRGB → linear, IEC 61966-2-1, in float64."""
    v = np.asarray(v, dtype=np.float64)
    return np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)


def _encode_reference(x):
    x = np.asarray(x, dtype=np.float64)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.abs(x) ** (1 / 2.4) - 0.055)


def _noise(h, w, seed=0):
    return np.random.default_rng(seed).integers(0, 256, (h, w, 3), dtype=np.uint8)


def _write_exr(path, planes):
    OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}, planes).write(str(path))


def _cut(src, dst, n):
    """Copy the first n bytes of src to dst (n < 0: all but the last -n bytes)."""
    with open(src, "rb") as handle:
        data = handle.read()
    with open(dst, "wb") as handle:
        handle.write(data[:n])
    return str(dst)


# ----------------------------------------------------------------------------------------------------------------
# conversions against known pixel values
# ----------------------------------------------------------------------------------------------------------------
RGB8 = np.array([[[0, 128, 255], [10, 20, 30]], [[255, 255, 255], [1, 2, 254]]], dtype=np.uint8)


def test_8bit_png_is_srgb(tmp_path):
    Image.fromarray(RGB8).save(tmp_path / "a.png")
    srgb = ta_io.read_image(tmp_path / "a.png", space="srgb")
    assert srgb.dtype == np.float32 and srgb.shape == (2, 2, 3)
    np.testing.assert_array_equal(srgb, (RGB8 / 255.0).astype(np.float32))
    linear = ta_io.read_image(tmp_path / "a.png")
    np.testing.assert_allclose(linear, _decode_reference(RGB8 / 255.0), rtol=1e-6, atol=1e-7)
    np.testing.assert_array_equal(ta_io.read_png(tmp_path / "a.png"), linear)  # read_png is the same reader


@pytest.mark.parametrize("fmt", ["PNG", "TIFF"])
def test_16bit_rgb_keeps_16_bits(tmp_path, fmt):
    """Pillow alone would reduce 16-bit RGB to 8 bits: 40000/65535 and 40100/65535 round to the same byte."""
    values = np.array([[[40000, 40100, 65535], [0, 1, 300]]], dtype=np.uint16)
    path = str(tmp_path / ("a.png" if fmt == "PNG" else "a.tif"))
    cv2.imwrite(path, values[..., ::-1])  # OpenCV is the one encoder here that writes 16-bit RGB
    pixels, info = ta_io.decode_image(path)
    assert info == {"format": fmt, "bits": 16, "encoding": "srgb", "alpha": False, "icc_profile": False}
    np.testing.assert_array_equal(pixels, values)
    srgb = ta_io.read_image(path, space="srgb")
    np.testing.assert_array_equal(srgb, (values / 65535.0).astype(np.float32))
    assert srgb[0, 0, 1] - srgb[0, 0, 0] > 1e-3
    np.testing.assert_allclose(ta_io.read_image(path), _decode_reference(values / 65535.0), rtol=1e-6, atol=1e-9)


def test_grey_palette_alpha_and_one_bit(tmp_path):
    grey = np.array([[0, 64], [200, 255]], dtype=np.uint8)
    Image.fromarray(grey).save(tmp_path / "g.png")
    np.testing.assert_array_equal(ta_io.read_image(tmp_path / "g.png", space="srgb"),
                                  np.repeat((grey / 255.0)[..., None], 3, axis=2).astype(np.float32))
    grey16 = np.array([[0, 1000], [50000, 65535]], dtype=np.uint16)
    Image.fromarray(grey16).save(tmp_path / "g16.png")
    np.testing.assert_array_equal(ta_io.read_image(tmp_path / "g16.png", space="srgb")[..., 1],
                                  (grey16 / 65535.0).astype(np.float32))

    rgba = np.zeros((2, 2, 4), np.uint8)
    rgba[..., :3] = RGB8
    rgba[..., 3] = [[255, 0], [128, 7]]
    Image.fromarray(rgba).save(tmp_path / "a.png")
    np.testing.assert_array_equal(ta_io.read_image(tmp_path / "a.png", space="srgb"), RGB8 / np.float32(255))
    rgb, alpha = ta_io.read_image(tmp_path / "a.png", space="srgb", alpha="mask")
    np.testing.assert_array_equal(rgb, RGB8 / np.float32(255))  # alpha is not multiplied in
    np.testing.assert_array_equal(alpha, rgba[..., 3] / np.float32(255))
    _, alpha = ta_io.read_image(tmp_path / "g.png", alpha="mask")
    np.testing.assert_array_equal(alpha, np.ones((2, 2), np.float32))  # no alpha: all ones

    la = np.stack([grey, np.array([[9, 255], [0, 100]], np.uint8)], -1)
    Image.fromarray(la).save(tmp_path / "la.png")
    rgb, alpha = ta_io.read_image(tmp_path / "la.png", space="srgb", alpha="mask")
    np.testing.assert_array_equal(rgb[..., 2], grey / np.float32(255))
    np.testing.assert_array_equal(alpha, la[..., 1] / np.float32(255))

    palette = Image.new("P", (3, 1))
    palette.putpalette([255, 0, 0, 0, 0, 255, 17, 34, 51] + [0] * (256 * 3 - 9))
    palette.putdata([2, 0, 1])
    palette.save(tmp_path / "p.png")
    np.testing.assert_array_equal(np.rint(ta_io.read_image(tmp_path / "p.png", space="srgb") * 255),
                                  [[[17, 34, 51], [255, 0, 0], [0, 0, 255]]])
    palette.save(tmp_path / "pt.png", transparency=1)  # index 1 (blue) transparent: tRNS → alpha
    rgb, alpha = ta_io.read_image(tmp_path / "pt.png", space="srgb", alpha="mask")
    np.testing.assert_array_equal(alpha, [[1.0, 1.0, 0.0]])
    np.testing.assert_array_equal(np.rint(rgb[0, 1] * 255), [255, 0, 0])

    Image.fromarray(np.array([[True, False, True]])).convert("1").save(tmp_path / "b.png")
    np.testing.assert_array_equal(ta_io.read_image(tmp_path / "b.png", space="srgb")[0, :, 0], [1.0, 0.0, 1.0])


def test_jpeg_flat_colours(tmp_path):
    """JPEG is lossy, but flat 8×8-aligned blocks come back within a couple of levels; grey JPEGs → RGB."""
    image = np.zeros((16, 32, 3), np.uint8)
    image[:, :16] = [200, 30, 90]
    image[:, 16:] = [20, 180, 240]
    Image.fromarray(image).save(tmp_path / "a.jpg", quality=100, subsampling=0)
    srgb = ta_io.read_image(tmp_path / "a.jpg", space="srgb")
    assert srgb.shape == (16, 32, 3)
    np.testing.assert_allclose(srgb[4, 4] * 255, [200, 30, 90], atol=2)
    np.testing.assert_allclose(srgb[4, 28] * 255, [20, 180, 240], atol=2)
    Image.fromarray(np.full((8, 8), 77, np.uint8)).save(tmp_path / "g.jpg", quality=100)
    np.testing.assert_allclose(ta_io.read_image(tmp_path / "g.jpg", space="srgb") * 255, 77, atol=1)


def test_exr_is_linear(tmp_path):
    r, g, b = (np.array([[v, -0.5], [2.0, 0.0]], np.float32) for v in (0.25, 0.5, 1.0))
    _write_exr(tmp_path / "a.exr", {"R": r, "G": g, "B": b, "A": np.full((2, 2), 0.5, np.float16)})
    linear, alpha = ta_io.read_image(tmp_path / "a.exr", alpha="mask")
    np.testing.assert_array_equal(linear, np.stack([r, g, b], -1))  # as stored: not clipped
    np.testing.assert_array_equal(alpha, np.full((2, 2), 0.5, np.float32))
    srgb = ta_io.read_image(tmp_path / "a.exr", space="srgb")
    np.testing.assert_allclose(srgb[0, 0], _encode_reference([0.25, 0.5, 1.0]), rtol=1e-6)
    _write_exr(tmp_path / "y.exr", {"Y": np.array([[0.125, 4.0]], np.float32)})
    np.testing.assert_array_equal(ta_io.read_exr(tmp_path / "y.exr"), [[[0.125] * 3, [4.0] * 3]])  # grey → RGB
    Image.fromarray(np.array([[0.5, 0.25, 3.0]], np.float32)).save(tmp_path / "f.tif")  # float TIFF: linear
    assert ta_io.decode_image(tmp_path / "f.tif")[1]["encoding"] == "linear"
    np.testing.assert_array_equal(ta_io.read_image(tmp_path / "f.tif")[0], [[0.5] * 3, [0.25] * 3, [3.0] * 3])


def test_masks(tmp_path):
    grey = np.array([[0, 127, 128, 255]], np.uint8)
    Image.fromarray(grey).save(tmp_path / "m.png")
    np.testing.assert_array_equal(ta_io.read_mask(tmp_path / "m.png"), [[False, False, True, True]])
    np.testing.assert_array_equal(ta_io.read_mask(tmp_path / "m.png", threshold=0.0), [[False, True, True, True]])
    rgb = np.array([[[255, 0, 0], [0, 255, 0], [0, 0, 255], [255, 255, 255]]], np.uint8)  # luma .299 .587 .114 1
    Image.fromarray(rgb).save(tmp_path / "c.png")
    np.testing.assert_array_equal(ta_io.read_mask(tmp_path / "c.png"), [[False, True, False, True]])


def test_colour_profiles(tmp_path):
    """An embedded non-sRGB profile is not applied, and a warning says so; an sRGB profile is silent."""
    image = Image.fromarray(RGB8)
    srgb_icc = ImageCms.ImageCmsProfile(ImageCms.createProfile("sRGB")).tobytes()
    other_icc = ImageCms.ImageCmsProfile(ImageCms.createProfile("XYZ")).tobytes()
    image.save(tmp_path / "s.png", icc_profile=srgb_icc)
    image.save(tmp_path / "x.png", icc_profile=other_icc)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        ta_io.read_image(tmp_path / "s.png")
    with pytest.warns(UserWarning, match=r"x\.png.*XYZ identity built-in.*not sRGB"):
        out = ta_io.read_image(tmp_path / "x.png", space="srgb")
    np.testing.assert_array_equal(out, RGB8 / np.float32(255))


def test_bad_arguments(tmp_path):
    Image.fromarray(RGB8).save(tmp_path / "a.png")
    with pytest.raises(ValueError, match=r"space: expected one of \('linear', 'srgb'\), got 'rgb'"):
        ta_io.read_image(tmp_path / "a.png", space="rgb")
    with pytest.raises(ValueError, match=r"alpha: expected one of \('drop', 'mask'\)"):
        ta_io.read_image(tmp_path / "a.png", alpha="keep")
    with pytest.raises(TypeError, match="target: expected a str or os.PathLike, got int"):
        ta_io.read_image(3, name="target")
    with pytest.raises(FileNotFoundError, match="photo: no such file .*nothing.png"):
        ta_io.read_image(tmp_path / "nothing.png", name="photo")
    with pytest.raises(ValueError, match="expected an image file, got the folder"):
        ta_io.read_image(tmp_path)
    (tmp_path / "empty.png").write_bytes(b"")
    with pytest.raises(ValueError, match="cannot decode .*empty.png.*an empty file"):
        ta_io.read_image(tmp_path / "empty.png")
    (tmp_path / "t.txt").write_text("hello")
    with pytest.raises(ValueError, match=r"cannot decode .*t\.txt.*expected a PNG, JPEG, TIFF"):
        ta_io.read_image(tmp_path / "t.txt")
    with pytest.raises(TypeError, match="data: expected bytes, got str"):
        ta_io.read_image_bytes("x", source="s")


# ----------------------------------------------------------------------------------------------------------------
# truncated and corrupt files
# ----------------------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def good(tmp_path_factory):
    """Valid files of each format, each larger than 10 kB so that a 5 kB prefix is a real truncation."""
    folder = tmp_path_factory.mktemp("good")
    noise = _noise(96, 96)
    Image.fromarray(noise).save(folder / "a.png")
    cv2.imwrite(str(folder / "a16.png"), noise.astype(np.uint16)[..., ::-1] * 257)
    Image.fromarray(noise).save(folder / "a.jpg", quality=95)
    Image.fromarray(noise).save(folder / "a.tif")
    Image.fromarray(noise).save(folder / "a.bmp")
    Image.fromarray(noise).save(folder / "a.webp", lossless=True)
    _write_exr(folder / "a.exr", {c: noise[..., i].astype(np.float32) / 255 for i, c in enumerate("RGB")})
    files = {os.path.splitext(f)[0].replace("a", "") + os.path.splitext(f)[1]: str(folder / f)
             for f in sorted(os.listdir(folder))}
    for path in files.values():
        assert os.path.getsize(path) > 10_000, path
    return files


@pytest.mark.parametrize("key", [".png", "16.png", ".jpg", ".tif", ".bmp", ".webp", ".exr"])
@pytest.mark.parametrize("cut", ["5kB", "half", "last byte"])
def test_truncated_files_are_refused(tmp_path, good, key, cut):
    src = good[key]
    ta_io.read_image(src)  # the whole file reads
    size = os.path.getsize(src)
    n = {"5kB": 5000, "half": size // 2, "last byte": size - 1}[cut]
    path = _cut(src, tmp_path / f"cut{key}", n)
    with pytest.raises(ValueError, match=r"path: .*cut.*(truncated or corrupt|not a readable OpenEXR)"):
        ta_io.read_image(path)


def test_opencv_alone_would_accept_a_truncated_jpeg(tmp_path, good, monkeypatch):
    """Why the reader checks with Pillow first: cv2.imread (which the targets and photos used before) decodes a JPEG
    cut in half without an error (the missing rows filled in), and the check holds even when some library has
    switched Pillow's truncated loading on globally."""
    path = _cut(good[".jpg"], tmp_path / "cut.jpg", os.path.getsize(good[".jpg"]) // 2)
    partial = cv2.imread(path, cv2.IMREAD_UNCHANGED)
    assert partial is not None and partial.shape == (96, 96, 3)
    monkeypatch.setattr(ImageFile, "LOAD_TRUNCATED_IMAGES", True)
    with pytest.raises(ValueError, match="cut.jpg' is a truncated or corrupt JPEG file"):
        ta_io.read_image(path)
    assert ImageFile.LOAD_TRUNCATED_IMAGES is True  # the global setting is restored


def test_large_scans_are_not_refused_as_decompression_bombs(good, monkeypatch):
    """Pillow refuses images over 2 × MAX_IMAGE_PIXELS (179 Mpx by default) as a guard against web uploads; a
    user's own disc scan may be that large, so the reader lifts the guard for its check (OpenCV's 2**30-pixel limit
    still applies) and restores it. Shown with the guard lowered to 1000 pixels."""
    from PIL import Image

    monkeypatch.setattr(Image, "MAX_IMAGE_PIXELS", 1000)
    with pytest.raises(Image.DecompressionBombError):
        Image.open(good[".png"])
    assert ta_io.read_image(good[".png"]).shape == (96, 96, 3)
    assert Image.MAX_IMAGE_PIXELS == 1000


def test_corrupt_files_are_refused(tmp_path, good):
    for key in (".png", "16.png", ".exr"):
        with open(good[key], "rb") as handle:
            data = bytearray(handle.read())
        middle = len(data) // 2
        data[middle:middle + 64] = bytes(64)  # same length, damaged data (PNG: CRC/zlib; EXR: chunk)
        path = tmp_path / f"bad{key}"
        path.write_bytes(bytes(data))
        with pytest.raises(ValueError, match=r"bad.*(truncated or corrupt|not a readable OpenEXR)"):
            ta_io.read_image(path)


# ----------------------------------------------------------------------------------------------------------------
# every command that reads images refuses them, before writing anything
# ----------------------------------------------------------------------------------------------------------------
def _load_script(script):
    return importlib.import_module(f"torch_appearance.cli.{script[:-3]}")


@pytest.fixture(scope="module")
def run_script():
    """``run(script, *args) -> (returncode, stderr)`` calling the script's ``main(argv)`` in this process."""
    mods = {}

    def run_(script, *args):
        mod = mods.setdefault(script, _load_script(script))
        out, err = io.StringIO(), io.StringIO()
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                rc = mod.main([str(a) for a in args])
            except SystemExit as e:
                rc = e.code
        return rc, err.getvalue()

    return run_


@pytest.fixture(params=["png-5kB", "jpg-half"])
def damaged(request, tmp_path, good):
    """A truncated PNG (first 5 kB) and a JPEG cut in half, in a folder of their own."""
    kind, cut = request.param.split("-")
    src = good[f".{kind}"]
    folder = tmp_path / "input"
    folder.mkdir()
    n = 5000 if cut == "5kB" else os.path.getsize(src) // 2
    return _cut(src, folder / f"damaged.{kind}", n)


def _quad_obj(folder, texture_name=None):
    """A unit square with UVs (two triangles) as OBJ, with an MTL naming texture_name if given."""
    lines = [] if texture_name is None else ["mtllib quad.mtl", "usemtl skin"]
    lines += ["v 0 0 0", "v 1 0 0", "v 1 1 0", "v 0 1 0", "vt 0 0", "vt 1 0", "vt 1 1", "vt 0 1",
              "f 1/1 2/2 3/3", "f 1/1 3/3 4/4"]
    (folder / "quad.obj").write_text("\n".join(lines) + "\n")
    if texture_name is not None:
        (folder / "quad.mtl").write_text(f"newmtl skin\nKd 1 1 1\nmap_Kd {texture_name}\n")
    return str(folder / "quad.obj")


def _nothing_written(tmp_path, out):
    assert not os.path.exists(out), f"{out} was written"
    leftovers = [f for f in os.listdir(tmp_path) if f != "input"]
    assert leftovers == [], leftovers


def test_optimize_print_refuses_damaged_target(run_script, tmp_path, damaged):
    out = tmp_path / "run"
    rc, err = run_script("optimize_print.py", "--target", damaged, "--iterations", "1", "--out", out, "--quiet")
    assert rc == 2 and "target: " in err and os.path.basename(damaged) in err and "truncated or corrupt" in err
    _nothing_written(tmp_path, out)
    rc, err = run_script("optimize_print.py", "--target", "colorchecker", "--bottom-target", damaged,
                         "--iterations", "1", "--out", out, "--quiet")
    assert rc == 2 and "error: --bottom-target: " in err and "truncated or corrupt" in err
    _nothing_written(tmp_path, out)


def test_optimize_print_refuses_damaged_fixed_mask(run_script, tmp_path, damaged):
    if not damaged.endswith(".png"):
        mask = os.path.join(os.path.dirname(damaged), "mask.png")
        os.replace(damaged, mask)  # --fixed takes .png masks: a JPEG's truncated bytes under a .png name
    else:
        mask = damaged
    out = tmp_path / "run"
    rc, err = run_script("optimize_print.py", "--target", "zebra", "--fixed", f"white=0.5:{mask}",
                         "--iterations", "1", "--out", out, "--quiet")
    assert rc == 2 and "fixed: mask image: " in err and os.path.basename(mask) in err
    assert "truncated or corrupt" in err
    _nothing_written(tmp_path, out)


def test_fit_wood_refuses_damaged_photo(run_script, tmp_path, damaged):
    out = tmp_path / "fit"
    rc, err = run_script("fit_wood.py", damaged, "--out", out, "--epochs", "1", "--color-epochs", "1",
                         "--no-preview", "--quiet")
    assert rc == 2 and "photo: " in err and os.path.basename(damaged) in err and "truncated or corrupt" in err
    _nothing_written(tmp_path, out)


def test_detect_rings_refuses_damaged_image(run_script, tmp_path, damaged):
    out, overlay = tmp_path / "rings.csv", tmp_path / "overlay.png"
    for extra in ([], ["--transect", "0,0,90,90"], ["--mode", "section"]):
        rc, err = run_script("detect_rings.py", damaged, "--out", out, "--overlay", overlay, *extra)
        assert rc == 2 and os.path.basename(damaged) in err and "truncated or corrupt" in err
        _nothing_written(tmp_path, out)


def test_voxelize_refuses_damaged_texture(run_script, tmp_path, damaged):
    """--texture, and a texture named by the OBJ's MTL (which trimesh would otherwise drop without a word)."""
    out = tmp_path / "vox"
    folder = os.path.dirname(damaged)
    obj = _quad_obj(tmp_path / "input")
    rc, err = run_script("voxelize.py", obj, "--texture", damaged, "--height-mm", "1", "--dpi", "50", "--out", out,
                         "--quiet", "--no-previews")
    assert rc == 2 and "texture: " in err and os.path.basename(damaged) in err and "truncated or corrupt" in err
    _nothing_written(tmp_path, out)
    obj = _quad_obj(tmp_path / "input", os.path.basename(damaged))
    assert os.path.dirname(obj) == folder
    rc, err = run_script("voxelize.py", obj, "--height-mm", "1", "--dpi", "50", "--out", out, "--quiet",
                         "--no-previews")
    assert rc == 2 and "names a texture that cannot be read" in err and os.path.basename(damaged) in err
    _nothing_written(tmp_path, out)


def test_load_mesh_reads_mtl_texture_through_the_reader(tmp_path):
    """The good case of the MTL check: a grey 16-bit texture is read as sRGB and reaches trimesh as RGB."""
    from torch_appearance.geometry import load_mesh

    Image.fromarray(np.full((4, 4), 40000, np.uint16)).save(tmp_path / "t.png")
    mesh, report = load_mesh(_quad_obj(tmp_path, "t.png"))
    assert report["colour"] == "texture" and report["texture_size"] == (4, 4)
    texels = np.asarray(mesh.visual.material.image.convert("RGB"))
    np.testing.assert_array_equal(texels, np.full((4, 4, 3), round(40000 / 65535 * 255)))


def test_load_mesh_refuses_corrupt_embedded_glb_texture(tmp_path):
    """A GLB whose embedded PNG is damaged (same length, so the GLB itself parses): load_mesh reads the GLB's images
    through the reader before trimesh sees them and refuses it, naming the file."""
    import trimesh

    from torch_appearance.geometry import load_mesh

    mesh = trimesh.Trimesh(vertices=[[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], faces=[[0, 1, 2], [0, 2, 3]],
                           process=False)
    mesh.visual = trimesh.visual.TextureVisuals(uv=[[0, 0], [1, 0], [1, 1], [0, 1]],
                                                image=Image.fromarray(_noise(64, 64)))
    data = bytearray(mesh.export(file_type="glb"))
    (tmp_path / "good.glb").write_bytes(bytes(data))
    good_mesh, report = load_mesh(str(tmp_path / "good.glb"))
    assert report["colour"] == "texture" and report["texture_size"] == (64, 64)
    start = bytes(data).index(b"\x89PNG")
    end = bytes(data).index(b"IEND", start)
    middle = (start + end) // 2
    data[middle:middle + 256] = bytes(256)
    (tmp_path / "bad.glb").write_bytes(bytes(data))
    with pytest.raises(ValueError, match=r"bad\.glb' holds a texture that cannot be read: texture: .*bad\.glb "
                                         r"\(embedded texture image 0\)' is a truncated or corrupt PNG"):
        load_mesh(str(tmp_path / "bad.glb"))


def test_envmap_refuses_truncated_exr(tmp_path, good):
    from torch_appearance.render.emitter import EnvironmentMap

    assert EnvironmentMap.from_exr(good[".exr"]).image.shape == (96, 96, 3)
    path = _cut(good[".exr"], tmp_path / "sky.exr", os.path.getsize(good[".exr"]) // 2)
    with pytest.raises(ValueError, match=r"envmap: .*sky\.exr.* not a readable OpenEXR file \(truncated or corrupt"):
        EnvironmentMap.from_exr(path)


def test_render_object_refuses_truncated_envmap(run_script, tmp_path, good):
    folder = tmp_path / "input"
    folder.mkdir()
    path = _cut(good[".exr"], folder / "sky.exr", 5000)
    out = tmp_path / "render"
    rc, err = run_script("render_object.py", "--envmap", path, "--size", "8", "--spp", "1", "--out", out)
    # one flag, not the library's name after it (issue 49: "--envmap: envmap:" was doubled)
    assert rc == 2 and "error: --envmap: '" in err and "envmap: envmap" not in err and "sky.exr" in err
    assert "truncated or corrupt" in err and len(err.strip().splitlines()) == 1
    _nothing_written(tmp_path, out)


def test_optimize_print_refuses_truncated_jpeg_as_a_user_runs_it(tmp_path, good):
    """The bug of issue 15 as a user meets it, in a fresh interpreter: main's cv2.imread filled in the missing rows
    of a JPEG cut in half and a whole print optimisation ran on the damaged target (rc 0, a full run folder)."""
    import subprocess
    import sys

    folder = tmp_path / "input"
    folder.mkdir()
    path = _cut(good[".jpg"], folder / "photo.jpg", os.path.getsize(good[".jpg"]) // 2)
    out = tmp_path / "run"
    result = subprocess.run([sys.executable, "-m", "torch_appearance.cli.optimize_print", "--target", path,
                             "--iterations", "1", "--out", str(out), "--quiet"],
                            capture_output=True, text=True, timeout=120, env={**os.environ, "PYTHONPATH": ROOT})
    assert result.returncode == 2, result.stderr[-2000:]
    assert "target: " in result.stderr and "photo.jpg' is a truncated or corrupt JPEG file" in result.stderr
    _nothing_written(tmp_path, out)


def _quad_ply(folder, texture_name):
    """The unit square with per-vertex UVs as an ASCII PLY naming texture_name (``comment TextureFile``)."""
    (folder / "quad.ply").write_text(
        "ply\nformat ascii 1.0\n" f"comment TextureFile {texture_name}\n"
        "element vertex 4\nproperty float x\nproperty float y\nproperty float z\nproperty float s\nproperty float t\n"
        "element face 2\nproperty list uchar int vertex_indices\nend_header\n"
        "0 0 0 0 0\n1 0 0 1 0\n1 1 0 1 1\n0 1 0 0 1\n3 0 1 2\n3 0 2 3\n")
    return str(folder / "quad.ply")


def test_load_mesh_ply_texture(tmp_path, good):
    """A PLY's TextureFile goes through the reader too: a grey 16-bit texture arrives as sRGB, a truncated one is
    refused (trimesh would log a warning and drop it)."""
    from torch_appearance.geometry import load_mesh

    Image.fromarray(np.full((4, 4), 40000, np.uint16)).save(tmp_path / "t.png")
    mesh, report = load_mesh(_quad_ply(tmp_path, "t.png"))
    assert report["colour"] == "texture" and report["texture_size"] == (4, 4)
    np.testing.assert_array_equal(np.asarray(mesh.visual.material.image.convert("RGB")),
                                  np.full((4, 4, 3), round(40000 / 65535 * 255)))
    _cut(good[".png"], tmp_path / "cut.png", 5000)
    with pytest.raises(ValueError, match=r"quad\.ply' names a texture that cannot be read: texture: .*cut\.png' is a "
                                         r"truncated or corrupt PNG"):
        load_mesh(_quad_ply(tmp_path, "cut.png"))
    with pytest.raises(ValueError, match=r"quad\.ply' names texture/material files that are missing: \['gone.png'\]"):
        load_mesh(_quad_ply(tmp_path, "gone.png"))


def test_lazily_opened_texture_is_decoded_strictly(good, monkeypatch):
    """Other formats (DAE, 3DXML, ...): trimesh opens the texture lazily with PIL; load_mesh decodes it with truncated
    loading off (even when switched on globally), so a truncated one is refused rather than filled in later."""
    import trimesh

    from torch_appearance.geometry.mesh import _load_strictly

    with open(good[".png"], "rb") as handle:
        data = handle.read()
    monkeypatch.setattr(ImageFile, "LOAD_TRUNCATED_IMAGES", True)
    mesh = trimesh.Trimesh(vertices=[[0, 0, 0], [1, 0, 0], [1, 1, 0]], faces=[[0, 1, 2]], process=False)
    mesh.visual = trimesh.visual.TextureVisuals(uv=[[0, 0], [1, 0], [1, 1]], image=Image.open(io.BytesIO(data)))
    _load_strictly(mesh, "model.dae")  # the whole file: fine
    mesh.visual = trimesh.visual.TextureVisuals(uv=[[0, 0], [1, 0], [1, 1]], image=Image.open(io.BytesIO(data[:5000])))
    with pytest.raises(ValueError, match=r"model\.dae' holds a texture that cannot be decoded completely"):
        _load_strictly(mesh, "model.dae")


@pytest.mark.parametrize("writer", ["opencv", "tifffile"])
@pytest.mark.parametrize("channels", [1, 3, 4])
def test_float32_tiff_is_linear_as_stored(tmp_path, writer, channels):
    """Floating-point TIFF (RGB as OpenCV, ImageJ and microscopy software write it; Pillow opens none with more
    than one channel) is read as linear values exactly as stored, above 1 too; truncations of it are refused."""
    import tifffile

    rgb = (np.random.default_rng(channels).random((9, 13, channels)) * 3).astype(np.float32)
    path = tmp_path / "float.tif"
    if writer == "opencv":
        stored = rgb if channels == 1 else np.concatenate([rgb[..., 2::-1], rgb[..., 3:]], axis=2)  # BGR(A)
        assert cv2.imwrite(str(path), stored[..., 0] if channels == 1 else stored)
    else:
        tifffile.imwrite(str(path), rgb[..., 0] if channels == 1 else rgb,
                         photometric="minisblack" if channels == 1 else "rgb")
    pixels, _ = ta_io.decode_image(str(path))
    np.testing.assert_array_equal(pixels.reshape(rgb.shape), rgb)
    data = path.read_bytes()
    for cut in (len(data) // 2, len(data) - 64, 16):
        bad = tmp_path / f"cut{cut}.tif"
        bad.write_bytes(data[:cut])
        with pytest.raises(ValueError, match="truncated or corrupt"):
            ta_io.decode_image(str(bad))
