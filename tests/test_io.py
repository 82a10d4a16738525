"""Tests of torch_appearance.color (sRGB transfer, CIELAB) and torch_appearance.io (EXR, PNG, JSON, atomicity)."""
import json
import os

import cv2
import numpy as np
import OpenEXR
import pytest
import torch

from torch_appearance import color
from torch_appearance import io as ta_io


# ----------------------------------------------------------------------------------------------------------------
# references written out from IEC 61966-2-1 (no kornia)
# ----------------------------------------------------------------------------------------------------------------
def _srgb_encode_reference(x):
    x = np.asarray(x, dtype=np.float64)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(np.maximum(x, 0.0031308), 1.0 / 2.4) - 0.055)


def _srgb_decode_reference(v):
    v = np.asarray(v, dtype=np.float64)
    return np.where(v <= 0.04045, v / 12.92, np.power((np.maximum(v, 0.04045) + 0.055) / 1.055, 2.4))


def _lab_reference(rgb_linear):
    """CIE 1976 L*a*b* of linear sRGB, D65, with the same matrix and white point as kornia."""
    m = np.array([[0.412453, 0.357580, 0.180423], [0.212671, 0.715160, 0.072169], [0.019334, 0.119193, 0.950227]])
    xyz = rgb_linear @ m.T / np.array([0.95047, 1.0, 1.08883])
    f = np.where(xyz > 0.008856, np.cbrt(np.maximum(xyz, 0.008856)), 7.787 * xyz + 4.0 / 29.0)
    return np.stack([116.0 * f[..., 1] - 16.0, 500.0 * (f[..., 0] - f[..., 1]), 200.0 * (f[..., 1] - f[..., 2])], -1)


def _leftovers(folder):
    return sorted(os.listdir(folder))


# ----------------------------------------------------------------------------------------------------------------
# colour
# ----------------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "linear, encoded",
    [
        (0.0, 0.0),
        (0.0031308, 0.04045),  # the breakpoint (the standard's two branches agree to 1e-7 there)
        (0.001, 0.01292),
        (0.5, 0.7353569830524495),
        (0.18, 0.4613561295004544),
        (0.21404114048223255, 0.5),
        (1.0, 1.0),
    ],
)
def test_srgb_known_values(linear, encoded):
    x = torch.tensor([linear], dtype=torch.float64)
    assert color.linear_to_srgb(x).item() == pytest.approx(encoded, abs=1e-6, rel=1e-9)
    assert color.srgb_to_linear(torch.tensor([encoded], dtype=torch.float64)).item() == pytest.approx(
        linear, abs=1e-7, rel=1e-9
    )


def test_srgb_matches_formula_on_a_dense_range():
    x = np.concatenate([np.linspace(-0.1, 2.0, 2001), np.geomspace(1e-6, 1.0, 500)])
    enc = color.linear_to_srgb(torch.from_numpy(x)).numpy()
    np.testing.assert_allclose(enc, _srgb_encode_reference(x), rtol=1e-12, atol=1e-12)
    v = np.linspace(-0.1, 1.5, 1601)
    dec = color.srgb_to_linear(torch.from_numpy(v)).numpy()
    np.testing.assert_allclose(dec, _srgb_decode_reference(v), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(color.srgb_to_linear(torch.from_numpy(enc)).numpy(), x, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("shape", [(), (1,), (5,), (4, 3), (2, 3, 4, 5), (7, 6, 3)])
def test_srgb_is_elementwise_for_any_shape(shape):
    x = torch.rand(shape, dtype=torch.float64)
    out = color.linear_to_srgb(x)
    assert out.shape == x.shape and out.dtype == x.dtype
    np.testing.assert_allclose(out.numpy(), _srgb_encode_reference(x.numpy()), rtol=1e-12)
    assert color.linear_to_srgb(x.float()).dtype == torch.float32


def test_srgb_gradient():
    x = (torch.rand(6, 3, dtype=torch.float64) * 0.9 + 0.05).requires_grad_()
    assert torch.autograd.gradcheck(color.linear_to_srgb, (x,))
    assert torch.autograd.gradcheck(color.srgb_to_linear, (x,))


def test_lab_against_formula_and_layouts():
    rgb = torch.rand(5, 4, 3, dtype=torch.float64)
    rgb[0, 0] = 1.0
    rgb[0, 1] = 0.0
    rgb[0, 2] = 1e-4  # below the L*a*b* threshold
    lab = color.rgb_to_lab(rgb)
    np.testing.assert_allclose(lab.numpy(), _lab_reference(rgb.numpy()), rtol=1e-9, atol=1e-9)
    assert lab[0, 0, 0].item() == pytest.approx(100.0, abs=1e-9)  # linear white
    assert lab[0, 1].abs().max().item() < 1e-9  # black
    # the same conversion with kornia's (*, 3, H, W) layout
    chw = rgb.permute(2, 0, 1)[None]
    np.testing.assert_allclose(color.rgb_to_lab(chw, dim=-3).numpy(), lab.permute(2, 0, 1)[None].numpy(), rtol=1e-12)
    # (N, 3) texel sets and a single colour
    assert color.rgb_to_lab(rgb.reshape(-1, 3)).shape == (20, 3)
    assert color.rgb_to_lab(rgb[0, 0]).shape == (3,)


def test_lab_round_trip():
    rgb = torch.rand(3, 8, 3, dtype=torch.float64)
    np.testing.assert_allclose(color.lab_to_rgb(color.rgb_to_lab(rgb)).numpy(), rgb.numpy(), atol=1e-10)
    chw = torch.rand(2, 3, 4, 5, dtype=torch.float64)
    back = color.lab_to_rgb(color.rgb_to_lab(chw, dim=-3), dim=-3)
    np.testing.assert_allclose(back.numpy(), chw.numpy(), atol=1e-10)
    clipped = color.lab_to_rgb(torch.tensor([50.0, 120.0, -120.0], dtype=torch.float64), clip=True)
    assert clipped.min() >= 0 and clipped.max() <= 1


@pytest.mark.parametrize(
    "call, error, match",
    [
        (lambda: color.linear_to_srgb(np.zeros(3)), TypeError, "image"),
        (lambda: color.linear_to_srgb(torch.zeros(3, dtype=torch.int64)), TypeError, "floating"),
        (lambda: color.rgb_to_lab(torch.zeros(4, 5)), ValueError, "3 colour channels"),
        (lambda: color.rgb_to_lab(torch.zeros(3, 4, 5)), ValueError, "dim=-3"),
        (lambda: color.rgb_to_lab(torch.zeros(4, 3), dim=2), ValueError, "out of range"),
        (lambda: color.rgb_to_lab(torch.zeros(4, 3), dim=1.0), TypeError, "dim"),
        (lambda: color.lab_to_rgb(torch.zeros(4, 3), clip=1), TypeError, "clip"),
    ],
)
def test_color_bad_inputs(call, error, match):
    with pytest.raises(error, match=match):
        call()


# ----------------------------------------------------------------------------------------------------------------
# EXR
# ----------------------------------------------------------------------------------------------------------------
def test_exr_round_trip_is_exact(tmp_path):
    rng = np.random.default_rng(0)
    image = rng.normal(size=(7, 11, 3)).astype(np.float32) * np.float32(10.0)
    image[0, 0] = [0.0, 1e-30, 3.0e38]
    path = tmp_path / "a.exr"
    ta_io.write_exr(path, image)
    back = ta_io.read_exr(path)
    assert back.dtype == np.float32 and back.shape == (7, 11, 3)
    np.testing.assert_array_equal(back, image)
    # the file has the usual R, G, B float channels (readable by other tools)
    with open(path, "rb") as handle:
        header = OpenEXR.File(handle, header_only=True).header()
    assert sorted(c.name for c in header["channels"]) == ["B", "G", "R"]
    assert header["compression"] == OpenEXR.ZIP_COMPRESSION
    assert _leftovers(tmp_path) == ["a.exr"]


def test_exr_accepts_tensors_and_float64(tmp_path):
    tensor = torch.rand(4, 5, 3, dtype=torch.float64, requires_grad=True)
    ta_io.write_exr(str(tmp_path / "t.exr"), tensor * 2)
    np.testing.assert_array_equal(ta_io.read_exr(tmp_path / "t.exr"), (tensor * 2).detach().numpy().astype(np.float32))


def test_exr_reads_half_channels(tmp_path):
    planes = {c: np.full((3, 2), v, dtype=np.float16) for c, v in zip("RGBA", (0.25, 0.5, 2.0, 1.0))}
    OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}, planes).write(
        str(tmp_path / "h.exr")
    )
    back = ta_io.read_exr(tmp_path / "h.exr")
    assert back.dtype == np.float32 and back.shape == (3, 2, 3)
    np.testing.assert_array_equal(back[0, 0], [0.25, 0.5, 2.0])


def test_exr_read_errors(tmp_path):
    with pytest.raises(FileNotFoundError):
        ta_io.read_exr(tmp_path / "missing.exr")
    (tmp_path / "junk.exr").write_bytes(b"not an exr")
    with pytest.raises(ValueError, match="not a readable OpenEXR"):
        ta_io.read_exr(tmp_path / "junk.exr")
    OpenEXR.File({"type": OpenEXR.scanlineimage}, {"Z": np.zeros((2, 2), np.float32)}).write(str(tmp_path / "z.exr"))
    with pytest.raises(ValueError, match="lacks channel"):
        ta_io.read_exr(tmp_path / "z.exr")
    (tmp_path / "p.exr").write_bytes(cv2.imencode(".png", np.zeros((2, 2, 3), np.uint8))[1].tobytes())
    with pytest.raises(ValueError, match="not a readable OpenEXR"):
        ta_io.read_exr(tmp_path / "p.exr")  # a PNG by content: read_exr reads EXR only


# ----------------------------------------------------------------------------------------------------------------
# PNG
# ----------------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("bits", [8, 16])
def test_png_round_trip_within_quantisation(tmp_path, bits):
    rng = np.random.default_rng(1)
    image = rng.uniform(0.0, 1.0, size=(9, 13, 3)) ** 2
    path = tmp_path / "p.png"
    ta_io.write_png(path, image, bits=bits)
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert raw.dtype == (np.uint8 if bits == 8 else np.uint16) and raw.shape == (9, 13, 3)
    step = 1.0 / (2**bits - 1)
    srgb = ta_io.read_png(path, linear=False)
    assert srgb.dtype == np.float32 and srgb.shape == (9, 13, 3)
    np.testing.assert_allclose(srgb, _srgb_encode_reference(image), atol=0.5 * step + 1e-7, rtol=0)
    linear = ta_io.read_png(path)
    np.testing.assert_allclose(linear, _srgb_decode_reference(srgb.astype(np.float64)), atol=1e-7, rtol=1e-6)
    # linear error bounded by the slope of the decoding (<= 2.4 / 1.055 * ((1 + 0.055)/1.055)^1.4 ~ 2.28) * step / 2
    np.testing.assert_allclose(linear, image, atol=1.2 * step, rtol=0)
    assert _leftovers(tmp_path) == ["p.png"]


def test_png_channel_order_and_clipping(tmp_path):
    image = np.zeros((2, 3, 3))
    image[0, 0] = [1.0, 0.0, 0.0]  # red
    image[0, 1] = [0.0, 0.0, 5.0]  # blue, clipped
    image[0, 2] = [-1.0, 0.5, 0.0]  # negative red clipped to 0
    ta_io.write_png(tmp_path / "c.png", image, bits=8)
    raw_bgr = cv2.imread(str(tmp_path / "c.png"), cv2.IMREAD_UNCHANGED)
    assert raw_bgr[0, 0].tolist() == [0, 0, 255]  # OpenCV reads B, G, R
    assert raw_bgr[0, 1].tolist() == [255, 0, 0]
    assert raw_bgr[0, 2].tolist() == [0, round(255 * 0.7353569830524495), 0]
    back = ta_io.read_png(tmp_path / "c.png")
    np.testing.assert_array_equal(back[0, 0], [1.0, 0.0, 0.0])
    np.testing.assert_array_equal(back[0, 1], [0.0, 0.0, 1.0])


def test_png_reads_grey_and_alpha(tmp_path):
    cv2.imwrite(str(tmp_path / "g.png"), np.full((2, 2), 255, np.uint8))
    np.testing.assert_array_equal(ta_io.read_png(tmp_path / "g.png"), np.ones((2, 2, 3), np.float32))
    bgra = np.zeros((2, 2, 4), np.uint8)
    bgra[..., 0] = 255  # blue
    bgra[..., 3] = 7
    cv2.imwrite(str(tmp_path / "a.png"), bgra)
    np.testing.assert_array_equal(ta_io.read_png(tmp_path / "a.png")[0, 0], [0.0, 0.0, 1.0])
    with pytest.raises(FileNotFoundError):
        ta_io.read_png(tmp_path / "missing.png")
    (tmp_path / "junk.png").write_bytes(b"junk")
    with pytest.raises(ValueError, match="decode"):
        ta_io.read_png(tmp_path / "junk.png")


# ----------------------------------------------------------------------------------------------------------------
# JSON
# ----------------------------------------------------------------------------------------------------------------
def test_json_round_trip_and_conversions(tmp_path):
    obj = {"a": 1, "b": [1.5, "x"], "n": np.float32(0.5), "arr": np.arange(3), "t": torch.tensor([1.0, 2.0])}
    ta_io.write_json(tmp_path / "r.json", obj)
    text = (tmp_path / "r.json").read_text()
    assert text.endswith("\n")
    assert json.loads(text) == {"a": 1, "b": [1.5, "x"], "n": 0.5, "arr": [0, 1, 2], "t": [1.0, 2.0]}


def test_written_files_have_normal_permissions(tmp_path):
    ta_io.write_json(tmp_path / "m.json", {})
    umask = os.umask(0)
    os.umask(umask)
    assert (tmp_path / "m.json").stat().st_mode & 0o777 == 0o666 & ~umask


# ----------------------------------------------------------------------------------------------------------------
# atomicity
# ----------------------------------------------------------------------------------------------------------------
_WRITERS = {
    "exr": lambda p: ta_io.write_exr(p / "out.exr", np.ones((2, 2, 3))),
    "png": lambda p: ta_io.write_png(p / "out.png", np.ones((2, 2, 3)), bits=16),
    "json": lambda p: ta_io.write_json(p / "out.json", {"a": 1}),
}


@pytest.mark.parametrize("kind", sorted(_WRITERS))
@pytest.mark.parametrize("failing", ["replace", "fsync"])
def test_failed_write_leaves_no_file(tmp_path, monkeypatch, kind, failing):
    def boom(*args, **kwargs):
        raise OSError("disk full (simulated)")

    monkeypatch.setattr(ta_io.os, failing, boom)
    with pytest.raises(OSError, match="simulated"):
        _WRITERS[kind](tmp_path)
    assert _leftovers(tmp_path) == []


def test_failed_write_keeps_the_old_file(tmp_path, monkeypatch):
    target = tmp_path / "out.json"
    ta_io.write_json(target, {"version": 1})
    monkeypatch.setattr(ta_io.os, "replace", lambda *a: (_ for _ in ()).throw(OSError("simulated")))
    with pytest.raises(OSError):
        ta_io.write_json(target, {"version": 2})
    assert json.loads(target.read_text()) == {"version": 1}
    assert _leftovers(tmp_path) == ["out.json"]


def test_overwrite_replaces_content(tmp_path):
    ta_io.write_exr(tmp_path / "o.exr", np.zeros((2, 2, 3)))
    ta_io.write_exr(tmp_path / "o.exr", np.ones((3, 1, 3)))
    np.testing.assert_array_equal(ta_io.read_exr(tmp_path / "o.exr"), np.ones((3, 1, 3), np.float32))
    assert _leftovers(tmp_path) == ["o.exr"]


def test_write_into_a_directory_path_fails_cleanly(tmp_path):
    (tmp_path / "d.png").mkdir()
    with pytest.raises(OSError):
        ta_io.write_png(tmp_path / "d.png", np.zeros((2, 2, 3)))
    assert _leftovers(tmp_path) == ["d.png"]
    assert os.listdir(tmp_path / "d.png") == []


# ----------------------------------------------------------------------------------------------------------------
# bad inputs: refused before anything is written
# ----------------------------------------------------------------------------------------------------------------
_GOOD = np.zeros((2, 2, 3))


@pytest.mark.parametrize(
    "call, error, match",
    [
        (lambda p: ta_io.write_exr(p / "x.exr", np.zeros((2, 2))), ValueError,
         r"image: expected shape \(H, W, 3\), got \(2, 2\)"),
        (lambda p: ta_io.write_exr(p / "x.exr", np.zeros((2, 2, 4))), ValueError, r"\(2, 2, 4\)"),
        (lambda p: ta_io.write_exr(p / "x.exr", np.zeros((0, 2, 3))), ValueError, "empty"),
        (lambda p: ta_io.write_exr(p / "x.exr", np.zeros((2, 2, 3), np.uint8)), TypeError, "floating"),
        (lambda p: ta_io.write_exr(p / "x.exr", [[[0.0] * 3]]), TypeError, "numpy.ndarray or torch.Tensor"),
        (lambda p: ta_io.write_exr(p / "x.exr", np.full((2, 2, 3), np.nan)), ValueError, "finite.*12"),
        (lambda p: ta_io.write_exr(p / "x.exr", np.full((2, 2, 3), 1e300)), ValueError, "float32"),
        (lambda p: ta_io.write_exr(p / "x.png", _GOOD), ValueError,
         r"path: expected a path ending with \.exr, got '.*x\.png'"),
        (lambda p: ta_io.write_exr(42, _GOOD), TypeError, "path"),
        (lambda p: ta_io.write_png(p / "x.png", _GOOD, bits=12), ValueError, "bits: expected 8 or 16, got 12"),
        (lambda p: ta_io.write_png(p / "x.png", _GOOD, bits=8.0), TypeError, "bits"),
        (lambda p: ta_io.write_png(p / "x.png", _GOOD, bits=True), TypeError, "bits"),
        (lambda p: ta_io.write_png(p / "x.png", torch.full((2, 2, 3), float("inf"))), ValueError, "image_linear"),
        (lambda p: ta_io.write_png(p / "x.png", torch.zeros(3, 2, 2, dtype=torch.int32)), TypeError, "image_linear"),
        (lambda p: ta_io.write_png(p / "x.exr", _GOOD), ValueError, r"\.png"),
        (lambda p: ta_io.write_json(p / "x.json", {"a": float("nan")}), ValueError, "strict JSON"),
        (lambda p: ta_io.write_json(p / "x.json", {"a": object()}), TypeError, "obj"),
        (lambda p: ta_io.read_png(p / "x.png", linear="yes"), TypeError, "linear"),
    ],
)
def test_bad_inputs(tmp_path, call, error, match):
    with pytest.raises(error, match=match):
        call(tmp_path)
    assert _leftovers(tmp_path) == []


def test_nan_to_none_recurses():
    obj = {"a": float("nan"), "b": [1.0, np.float32("inf"), (2, -float("inf"))], "c": "x", "d": 3}
    assert ta_io.nan_to_none(obj) == {"a": None, "b": [1.0, None, [2, None]], "c": "x", "d": 3}


def test_markdown_table():
    fields = [("k", "key", "{}"), ("e", "err", "{:+.1%}")]
    text = ta_io.markdown_table([{"k": "a|b", "e": 0.0312}, {"k": 7}], fields)
    assert text.split("\n") == ["| key | err |", "|---|---|", "| a/b | +3.1% |", "| 7 | – |"]
