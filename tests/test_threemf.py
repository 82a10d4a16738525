"""Tests of the 3MF writer and reader (torch_appearance.fabrication.threemf): round trips, the file structure read
independently with zipfile + ElementTree + OpenCV, the volumetric sampling convention, bad input, atomic writes."""
import os
import xml.etree.ElementTree as ET
import zipfile

import cv2
import numpy as np
import pytest

pytest.importorskip("lib3mf")

from torch_appearance.fabrication import threemf  # noqa: E402
from torch_appearance.fabrication.threemf import iter_3mf_layers, read_3mf, write_3mf  # noqa: E402

NS = {"c": "http://schemas.microsoft.com/3dmanufacturing/core/2015/02",
      "m": "http://schemas.microsoft.com/3dmanufacturing/material/2015/02",
      "v": "http://schemas.3mf.io/3dmanufacturing/volumetric/2022/01"}
PITCH = (25.4 / 600, 25.4 / 300, 0.027)        # anisotropic, mm
SHAPE = (7, 5, 9)                              # (Dz, Hy, Wx)
MATERIALS = [("cyan", (0, 255, 255, 255)), ("magenta", (255, 0, 255, 200)), ("yellow", (255, 255, 0, 255)),
             ("white", (250, 250, 245, 128))]
CUBE_FACES = np.array([[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4], [1, 2, 6], [1, 6, 5],
                       [2, 3, 7], [2, 7, 6], [3, 0, 4], [3, 4, 7]])


def _cube():
    """The grid's box [0, Wx·sx] × [0, Hy·sy] × [0, Dz·sz] (mm) as 8 vertices and 12 outward triangles."""
    size = np.array([SHAPE[2] * PITCH[0], SHAPE[1] * PITCH[1], SHAPE[0] * PITCH[2]])
    corners = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]], float)
    return corners * size, CUBE_FACES.copy()


def _volume(seed=3, shape=SHAPE, n=len(MATERIALS)):
    rng = np.random.default_rng(seed)
    indices = rng.integers(0, n, shape).astype(np.uint8)
    indices[rng.random(shape) < 0.25] = 255
    indices[0, 0, 0], indices[-1, -1, -1] = 255, 0
    return indices


def _assert_float32_close(actual, expected):
    """Equal to float32 precision (3MF stores float32 coordinates; lib3mf prints them to within one step)."""
    step = np.spacing(np.float32(np.abs(expected).max()))
    np.testing.assert_allclose(actual, expected, rtol=0, atol=2 * float(step))


def _write_volume(path, indices, **kwargs):
    vertices, faces = _cube()
    write_3mf(path, vertices, faces, layers=(layer for layer in indices), grid_shape=indices.shape,
              pitch_mm=PITCH, materials=MATERIALS, **kwargs)


def _model_xml(path):
    with zipfile.ZipFile(path) as archive:
        return ET.fromstring(archive.read("3D/3dmodel.model"))


def _part(path, name):
    with zipfile.ZipFile(path) as archive:
        return archive.read(name.lstrip("/"))


# ----------------------------------------------------------------------------------------------------------------
# round trips
# ----------------------------------------------------------------------------------------------------------------
def test_round_trip_vertex_colours(tmp_path):
    vertices, faces = _cube()
    rgb = np.random.default_rng(0).integers(0, 3, (8, 3)).astype(np.uint8) * 120
    path = tmp_path / "cube.3mf"
    write_3mf(path, vertices, faces, vertex_rgb=rgb)
    data = read_3mf(path)
    _assert_float32_close(data["vertices"], vertices)
    assert data["vertices"].dtype == np.float64 and data["faces"].dtype == np.int64
    np.testing.assert_array_equal(data["faces"], faces)
    np.testing.assert_array_equal(data["vertex_rgb"], rgb)
    assert data["vertex_rgb"].dtype == np.uint8
    assert data["face_rgb"] is None
    np.testing.assert_array_equal(data["corner_rgb"], rgb[faces])
    assert data["indices"] is None and data["pitch_mm"] is None and data["grid_shape"] is None
    assert data["materials"] == [] and data["unit"] == "millimeter"


def test_round_trip_face_colours_deduplicated(tmp_path):
    vertices, faces = _cube()
    palette = np.array([[255, 0, 0], [0, 128, 255], [10, 20, 30]], np.uint8)
    face_rgb = palette[np.arange(len(faces)) % 3]
    path = tmp_path / "cube.3mf"
    write_3mf(path, vertices, faces, face_rgb=face_rgb)
    data = read_3mf(path)
    np.testing.assert_array_equal(data["face_rgb"], face_rgb)
    assert data["vertex_rgb"] is None
    colours = _model_xml(path).findall(".//m:colorgroup/m:color", NS)
    assert sorted(c.get("color") for c in colours) == ["#0080FFFF", "#0A141EFF", "#FF0000FF"]


def test_uniform_face_colours_stay_face_colours(tmp_path):
    # Every vertex has one colour across its triangles here, but the writer recorded face colours.
    vertices, faces = _cube()
    face_rgb = np.full((len(faces), 3), 77, np.uint8)
    write_3mf(tmp_path / "a.3mf", vertices, faces, face_rgb=face_rgb)
    data = read_3mf(tmp_path / "a.3mf")
    np.testing.assert_array_equal(data["face_rgb"], face_rgb)
    assert data["vertex_rgb"] is None


def test_no_colours_and_other_units(tmp_path):
    vertices, faces = _cube()
    vertices = vertices * 100 + 3.0
    path = tmp_path / "inch.3mf"
    write_3mf(path, vertices, faces, unit="inch")
    data = read_3mf(path)
    assert data["vertex_rgb"] is None and data["face_rgb"] is None and data["corner_rgb"] is None
    assert data["unit"] == "inch"
    _assert_float32_close(data["vertices"], vertices)
    root = _model_xml(path)
    assert root.get("unit") == "inch"
    stored = np.array([[float(v.get(a, 0)) for a in "xyz"] for v in root.findall(".//c:vertex", NS)])
    np.testing.assert_allclose(stored, vertices / 25.4, rtol=1e-6)
    assert "requiredextensions" not in root.attrib          # no volume: a plain core + materials file


@pytest.mark.parametrize("as_generator", [True, False], ids=["generator", "list"])
def test_round_trip_volume(tmp_path, as_generator):
    indices = _volume()
    vertices, faces = _cube()
    rgb = np.arange(24, dtype=np.uint8).reshape(8, 3) * 10
    seen = []
    layers = (layer.copy() for layer in indices) if as_generator else list(indices)
    path = tmp_path / "object.3mf"
    write_3mf(path, vertices, faces, vertex_rgb=rgb, layers=layers, grid_shape=indices.shape, pitch_mm=PITCH,
              materials=MATERIALS, progress=seen.append)
    assert seen == list(range(SHAPE[0]))
    data = read_3mf(path)
    assert data["indices"].dtype == np.uint8 and data["indices"].shape == SHAPE
    np.testing.assert_array_equal(data["indices"], indices)
    assert data["materials"] == MATERIALS
    assert data["pitch_mm"] == PITCH and data["grid_shape"] == SHAPE
    np.testing.assert_array_equal(data["vertex_rgb"], rgb)
    _assert_float32_close(data["vertices"], vertices)
    layers_back = list(iter_3mf_layers(path))
    assert len(layers_back) == SHAPE[0]
    np.testing.assert_array_equal(np.stack(layers_back), indices)


def test_volume_in_centimetres(tmp_path):
    indices = _volume(seed=5)
    _write_volume(tmp_path / "cm.3mf", indices, unit="centimeter")
    data = read_3mf(tmp_path / "cm.3mf")
    np.testing.assert_array_equal(data["indices"], indices)
    assert data["pitch_mm"] == PITCH


# ----------------------------------------------------------------------------------------------------------------
# the file, read independently of lib3mf
# ----------------------------------------------------------------------------------------------------------------
def _sheets(path, root):
    """{material index: (Dz, Hy, Wx) uint8 sheet images decoded with OpenCV}, via the property names."""
    stacks = {image.get("id"): image for image in root.findall(".//v:image3d", NS)}
    functions = {f.get("id"): f for f in root.findall(".//v:functionfromimage3d", NS)}
    sheets, transforms = {}, {}
    for prop in root.findall(".//v:volumedata/v:property", NS):
        m = int(prop.get("name").split("_")[1])
        image = stacks[functions[prop.get("functionid")].get("image3did")]
        pngs = [_part(path, s.get("path")) for s in image.findall("v:imagestack/v:imagesheet", NS)]
        sheets[m] = np.stack([cv2.imdecode(np.frombuffer(p, np.uint8), cv2.IMREAD_UNCHANGED) for p in pngs])
        values = [float(v) for v in prop.get("transform").split()]
        transforms[m] = np.array(values).reshape(4, 3)      # rows: x, y, z coefficients, then the offset
    return sheets, transforms


def test_file_structure(tmp_path):
    indices = _volume()
    vertices, faces = _cube()
    rgb = np.random.default_rng(1).integers(0, 256, (8, 3)).astype(np.uint8)
    path = tmp_path / "object.3mf"
    write_3mf(path, vertices, faces, vertex_rgb=rgb, layers=iter(indices), grid_shape=SHAPE, pitch_mm=PITCH,
              materials=MATERIALS)
    root = _model_xml(path)
    assert root.get("unit") == "millimeter"
    meta = {m.get("name"): m.text for m in root.findall("c:metadata", NS)}
    assert meta["Application"] == "torch_appearance" and meta["Title"] == "object"
    assert len(root.findall(".//c:mesh/c:vertices/c:vertex", NS)) == 8
    # colours: triangle p1, p2, p3 point into the colour group, giving each corner its vertex colour
    group = root.find(".//m:colorgroup", NS)
    colours = [c.get("color") for c in group.findall("m:color", NS)]
    assert len(colours) == len({tuple(c) for c in rgb.tolist()})
    for f, tri in enumerate(root.findall(".//c:triangles/c:triangle", NS)):
        assert tri.get("pid") == group.get("id")
        for corner, key in enumerate(("p1", "p2", "p3")):
            assert colours[int(tri.get(key))] == "#%02X%02X%02XFF" % tuple(rgb[faces[f, corner]])
    # base materials
    bases = root.findall(".//c:basematerials/c:base", NS)
    assert [b.get("name") for b in bases] == [name for name, _ in MATERIALS]
    assert [b.get("displaycolor") for b in bases] == ["#%02X%02X%02X%02X" % rgba for _, rgba in MATERIALS]
    # one image stack per material: Dz sheets of Hy rows and Wx columns, nearest filter, clamped
    stacks = root.findall(".//v:image3d/v:imagestack", NS)
    assert len(stacks) == len(MATERIALS)
    for stack in stacks:
        assert (stack.get("sheetcount"), stack.get("rowcount"), stack.get("columncount")) == tuple(map(str, SHAPE))
        assert len(stack.findall("v:imagesheet", NS)) == SHAPE[0]
    for function in root.findall(".//v:functionfromimage3d", NS):
        assert function.get("filter") == "nearest"
        assert {function.get(f"tilestyle{a}") for a in "uvw"} == {"clamp"}
    sheets, transforms = _sheets(path, root)
    assert sorted(sheets) == list(range(len(MATERIALS)))
    for m, stack in sheets.items():
        assert stack.shape == SHAPE and stack.dtype == np.uint8
        # the 3MF image convention puts row 0 at v = 1: a sheet is the layer seen from above, +y up
        np.testing.assert_array_equal(stack, np.where(indices == m, 255, 0)[:, ::-1, :])
        expected = np.diag([1 / (SHAPE[2] * PITCH[0]), 1 / (SHAPE[1] * PITCH[1]), 1 / (SHAPE[0] * PITCH[2])])
        np.testing.assert_allclose(transforms[m][:3], expected, rtol=1e-5)
        np.testing.assert_array_equal(transforms[m][3], 0)
    # 1-bit greyscale PNGs (IHDR: bit depth 1, colour type 0)
    first = root.find(".//v:imagesheet", NS).get("path")
    png = _part(path, first)
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and png[24] == 1 and png[25] == 0


def test_voxel_centres_sample_their_own_pixel(tmp_path):
    """Evaluate the file as the volumetric specification says (object position -> transform -> nearest voxel,
    column j at u = (j + ½)/columns, row i at v = 1 - (i + ½)/rows, sheet k at w = (k + ½)/sheets) at every voxel
    centre, independently of read_3mf."""
    indices = _volume(seed=11)
    path = tmp_path / "object.3mf"
    _write_volume(path, indices)
    sheets, transforms = _sheets(path, _model_xml(path))
    k, j, i = np.meshgrid(*(np.arange(n) for n in SHAPE), indexing="ij")
    centres = np.stack([(i + 0.5) * PITCH[0], (j + 0.5) * PITCH[1], (k + 0.5) * PITCH[2]], axis=-1)
    rebuilt = np.full(SHAPE, 255, np.uint8)
    for m, stack in sheets.items():
        u, v, w = np.moveaxis(centres @ transforms[m][:3] + transforms[m][3], -1, 0)
        column = np.clip(np.floor(u * SHAPE[2]), 0, SHAPE[2] - 1).astype(int)
        row = np.clip(np.floor((1 - v) * SHAPE[1]), 0, SHAPE[1] - 1).astype(int)
        sheet = np.clip(np.floor(w * SHAPE[0]), 0, SHAPE[0] - 1).astype(int)
        hit = stack[sheet, row, column] == 255
        assert not (hit & (rebuilt != 255)).any()
        rebuilt[hit] = m
    np.testing.assert_array_equal(rebuilt, indices)


def test_reader_follows_the_transform_orientation(tmp_path):
    """A file whose v axis runs the other way (v = 1 - y / (Hy·sy)) with unflipped sheets holds the same volume."""
    indices = _volume(seed=7)
    path = tmp_path / "object.3mf"
    _write_volume(path, indices)
    with zipfile.ZipFile(path) as old, zipfile.ZipFile(tmp_path / "v_reversed.3mf", "w", zipfile.ZIP_DEFLATED) as new:
        for info in old.infolist():
            content = old.read(info.filename)
            if info.filename.endswith(".png"):
                image = cv2.imdecode(np.frombuffer(content, np.uint8), cv2.IMREAD_UNCHANGED)
                content = cv2.imencode(".png", np.ascontiguousarray(image[::-1]))[1].tobytes()
            elif info.filename == "3D/3dmodel.model":
                root_text = content.decode()
                for value in {t.get("transform") for t in ET.fromstring(content).iter() if t.get("transform")}:
                    entries = value.split()
                    if len(entries) == 12 and entries[4] != "0":
                        entries[4], entries[10] = "-" + entries[4], "1"
                        root_text = root_text.replace(f'transform="{value}"', f'transform="{" ".join(entries)}"')
                assert root_text.count(" 0 1 0\"") == len(MATERIALS)
                content = root_text.encode()
            new.writestr(info, content)
    data = read_3mf(tmp_path / "v_reversed.3mf")
    np.testing.assert_array_equal(data["indices"], indices)
    assert data["pitch_mm"] == PITCH


# ----------------------------------------------------------------------------------------------------------------
# bad input, atomic writes, refused files
# ----------------------------------------------------------------------------------------------------------------
def _bad_cases():
    v, f = _cube()
    idx = _volume()
    vol = dict(layers=list(idx), grid_shape=SHAPE, pitch_mm=PITCH, materials=MATERIALS)
    too_high = idx.copy()
    too_high[2, 1, 3] = len(MATERIALS)
    return [
        ("vertices", dict(vertices=v[:, :2]), ValueError),
        ("vertices", dict(vertices=v.astype(int)), TypeError),
        ("vertices", dict(vertices=v.tolist()), TypeError),
        ("vertices", dict(vertices=np.where(v == 0, np.nan, v)), ValueError),
        ("faces", dict(faces=f.astype(float)), TypeError),
        ("faces", dict(faces=np.where(f == 7, 8, f)), ValueError),
        ("faces", dict(faces=np.vstack([f, [[1, 1, 2]]])), ValueError),
        ("vertex_rgb, face_rgb", dict(vertex_rgb=np.zeros((8, 3), np.uint8), face_rgb=np.zeros((12, 3), np.uint8)),
         ValueError),
        ("vertex_rgb", dict(vertex_rgb=np.zeros((7, 3), np.uint8)), ValueError),
        ("vertex_rgb", dict(vertex_rgb=np.zeros((8, 3))), TypeError),
        ("vertex_rgb", dict(vertex_rgb=np.full((8, 3), 256, np.int16)), ValueError),
        ("face_rgb", dict(face_rgb=np.full((12, 3), -1, np.int32)), ValueError),
        ("layers", dict(vol, layers=list(too_high)), ValueError),
        ("layers", dict(vol, layers=[layer.T for layer in idx]), ValueError),
        ("layers", dict(vol, layers=[layer.astype(np.int64) for layer in idx]), TypeError),
        ("layers", dict(vol, layers=list(idx[:-1])), ValueError),
        ("layers", dict(vol, layers=list(idx) + [idx[0]]), ValueError),
        ("layers", dict(vol, layers=5), TypeError),
        ("grid_shape", dict(vol, grid_shape=None), ValueError),
        ("grid_shape", dict(vol, grid_shape=(7, 5, 0)), ValueError),
        ("pitch_mm", dict(vol, pitch_mm=(0.1, -0.1, 0.1)), ValueError),
        ("materials", dict(vol, materials=MATERIALS[:3] + [("white", (255, 255, 256, 255))]), ValueError),
        ("materials", dict(vol, materials=MATERIALS[:3] + [(4, (255, 255, 255, 255))]), TypeError),
        ("materials", dict(materials=MATERIALS), ValueError),
        ("unit", dict(unit="furlong"), ValueError),
        ("progress", dict(vol, progress=3), TypeError),
    ]


@pytest.mark.parametrize("name, kwargs, error", _bad_cases(), ids=lambda c: c if isinstance(c, str) else "")
def test_bad_input_names_the_argument(tmp_path, name, kwargs, error):
    vertices, faces = _cube()
    arguments = dict(vertices=vertices, faces=faces)
    arguments.update(kwargs)
    with pytest.raises(error, match=f"^{name}"):
        write_3mf(tmp_path / "bad.3mf", arguments.pop("vertices"), arguments.pop("faces"), **arguments)
    assert os.listdir(tmp_path) == []


def test_bad_path():
    vertices, faces = _cube()
    with pytest.raises(ValueError, match="^path"):
        write_3mf("object.stl", vertices, faces)
    with pytest.raises(TypeError, match="^path"):
        write_3mf(3, vertices, faces)


def test_failed_write_leaves_no_file(tmp_path):
    indices = _volume()

    def failing_layers():
        yield from indices[:3]
        raise RuntimeError("simulated failure in layer 3")

    vertices, faces = _cube()
    path = tmp_path / "object.3mf"
    with pytest.raises(RuntimeError, match="simulated"):
        write_3mf(path, vertices, faces, layers=failing_layers(), grid_shape=SHAPE, pitch_mm=PITCH,
                  materials=MATERIALS)
    assert os.listdir(tmp_path) == []
    # an existing file keeps its content when a rewrite fails
    write_3mf(path, vertices, faces)
    before = path.read_bytes()
    with pytest.raises(RuntimeError, match="simulated"):
        write_3mf(path, vertices, faces, layers=failing_layers(), grid_shape=SHAPE, pitch_mm=PITCH,
                  materials=MATERIALS)
    assert os.listdir(tmp_path) == ["object.3mf"] and path.read_bytes() == before


def test_failed_replace_cleans_up(tmp_path, monkeypatch):
    vertices, faces = _cube()
    path = tmp_path / "object.3mf"
    write_3mf(path, vertices, faces)
    before = path.read_bytes()

    def failing_replace(source, target):
        raise OSError("simulated failure of os.replace")

    monkeypatch.setattr(threemf.os, "replace", failing_replace)
    with pytest.raises(OSError, match="simulated"):
        write_3mf(path, vertices, faces, face_rgb=np.zeros((12, 3), np.uint8))
    assert os.listdir(tmp_path) == ["object.3mf"] and path.read_bytes() == before


def test_read_refuses_bad_files(tmp_path):
    indices = _volume()
    path = tmp_path / "object.3mf"
    _write_volume(path, indices)
    data = path.read_bytes()
    truncated = tmp_path / "truncated.3mf"
    truncated.write_bytes(data[:len(data) // 2])
    with pytest.raises(ValueError, match="truncated.3mf"):
        read_3mf(truncated)
    with pytest.raises(ValueError, match="truncated.3mf"):
        iter_3mf_layers(truncated)
    text = tmp_path / "text.3mf"
    text.write_text("solid cube\nendsolid cube\n")
    with pytest.raises(ValueError, match="text.3mf"):
        read_3mf(text)
    missing = tmp_path / "missing.3mf"
    with pytest.raises(ValueError, match="missing.3mf"):
        read_3mf(missing)
    with pytest.raises(FileNotFoundError):
        read_3mf(missing)
    with pytest.raises(ValueError, match="folder"):
        read_3mf(tmp_path)


def _replace_part(source, target, name, content):
    with zipfile.ZipFile(source) as old, zipfile.ZipFile(target, "w", zipfile.ZIP_DEFLATED) as new:
        for info in old.infolist():
            new.writestr(info, content if info.filename == name else old.read(info.filename))


def test_read_refuses_overlapping_and_non_binary_sheets(tmp_path):
    indices = _volume()
    path = tmp_path / "object.3mf"
    _write_volume(path, indices)
    ok, everything = cv2.imencode(".png", np.full(SHAPE[1:], 255, np.uint8))
    _replace_part(path, tmp_path / "overlap.3mf", "3D/volumetric/material_1/sheet_00002.png", everything.tobytes())
    with pytest.raises(ValueError, match="layer 2.*material 1"):
        read_3mf(tmp_path / "overlap.3mf")
    layers = iter_3mf_layers(tmp_path / "overlap.3mf")
    np.testing.assert_array_equal(next(layers), indices[0])           # read lazily: layer 0 is fine
    ok, grey = cv2.imencode(".png", np.full(SHAPE[1:], 128, np.uint8))
    _replace_part(path, tmp_path / "grey.3mf", "3D/volumetric/material_0/sheet_00000.png", grey.tobytes())
    with pytest.raises(ValueError, match="binary"):
        read_3mf(tmp_path / "grey.3mf")


def test_iter_layers_needs_a_volume(tmp_path):
    vertices, faces = _cube()
    write_3mf(tmp_path / "plain.3mf", vertices, faces)
    with pytest.raises(ValueError, match="no volume"):
        iter_3mf_layers(tmp_path / "plain.3mf")


def test_materials_without_void_and_single_material(tmp_path):
    indices = np.zeros((2, 3, 4), np.uint8)
    vertices, faces = _cube()
    path = tmp_path / "one.3mf"
    write_3mf(path, vertices, faces, layers=iter(indices), grid_shape=indices.shape, pitch_mm=(0.1, 0.2, 0.3),
              materials=[("clear", (255, 255, 255, 0))])
    data = read_3mf(path)
    np.testing.assert_array_equal(data["indices"], indices)
    assert data["materials"] == [("clear", (255, 255, 255, 0))]


def test_the_process_locale_is_left_alone(tmp_path):
    """lib3mf sets the C locale; Python's text streams (subprocess output, open()) would then be ASCII."""
    import locale

    before = locale.setlocale(locale.LC_ALL)
    vertices = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float)
    faces = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    write_3mf(tmp_path / "t.3mf", vertices, faces, layers=iter([np.zeros((2, 3), np.uint8)]), grid_shape=(1, 2, 3),
              pitch_mm=(0.1, 0.1, 0.1), materials=[("a", (1, 2, 3, 255))])
    assert locale.setlocale(locale.LC_ALL) == before
    read_3mf(tmp_path / "t.3mf")
    list(iter_3mf_layers(tmp_path / "t.3mf"))
    assert locale.setlocale(locale.LC_ALL) == before
