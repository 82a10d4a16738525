"""The shared argument checks (torch_appearance.checks): each accepts good input, returns it normalised, and refuses
each kind of bad input with ``name: expected X, got Y`` and the documented exception type."""
import ast
import math
import pathlib

import numpy as np
import pytest
import torch

from torch_appearance import checks
from torch_appearance.checks import (check_choice, check_direction, check_finite, check_float_tensor,
                                     check_image_shape, check_int, check_odd_int, check_path, check_point_in_image,
                                     check_positive, check_real, check_rgb, check_seed, check_spp, check_tensor,
                                     check_vector3)


def test_good_input_is_returned_normalised():
    assert check_real("x", np.float32(0.5)) == 0.5 and type(check_real("x", 2)) is float
    assert check_real("x", torch.tensor([1.5])) == 1.5
    assert check_positive("s", 3) == 3.0
    assert check_int("n", np.int64(4), lo=1) == 4 and type(check_int("n", np.int64(4), lo=1)) is int
    assert check_int("n", 6, lo=1, hi=6) == 6
    assert check_odd_int("w", 15) == 15
    assert check_seed("seed", 2 ** 64 - 1) == 2 ** 64 - 1 and check_seed("seed", -2 ** 63) == -2 ** 63
    assert check_spp(1) == 1
    assert check_choice("c", "hero", ("per_channel", "hero"), kind=str) == "hero"
    assert check_path("p", pathlib.Path("a/b.PNG"), (".png",)) == "a/b.PNG"
    assert check_rgb("c", 0.5) == (0.5, 0.5, 0.5) and check_rgb("c", torch.tensor([0.1, 0.2, 0.3])) == \
        pytest.approx((0.1, 0.2, 0.3))
    assert check_vector3("p", [1, 2, 3]) == (1.0, 2.0, 3.0)
    assert check_direction("d", (0, 0, 2)) == (0.0, 0.0, 1.0)
    x = torch.zeros(2, 3)
    assert check_tensor("x", x, "(N, 3)", ndim=2, last=3, dtypes="floating") is x
    assert check_tensor("x", x, "(N, 3) or (B, N, 3)", ndim=(2, 3), dtypes=(torch.float32,)) is x
    assert check_tensor("i", torch.zeros(2, 3, dtype=torch.int16), "(N, 3)", dtypes="integer").dtype == torch.int16
    assert isinstance(check_tensor("x", np.zeros((2, 3)), "(N, 3)", numpy=True), torch.Tensor)
    y = torch.ones(2, 3, requires_grad=True)
    out = check_float_tensor("y", y, "(N, 3)", ndim=2, last=3)
    assert not out.requires_grad and torch.equal(out, y.detach())
    assert check_finite("x", np.ones(3)) is not None and check_finite("i", torch.arange(3)) is not None
    assert check_image_shape("s", (4, 5)) == (4, 5)
    assert check_image_shape("s", torch.Size([4, 5, 3]), channels=True) == (4, 5)
    assert check_point_in_image("p", (0, 3), (4, 5)) == (0.0, 3.0)
    assert check_point_in_image("p", np.array([4.0, 0.0]), (4, 5, 3)) == (4.0, 0.0)


BAD = [
    # check_real / check_positive
    (lambda: check_real("g", "0.5"), TypeError, "g: expected a real number, got str"),
    (lambda: check_real("g", True), TypeError, "g: expected a real number, got bool"),
    (lambda: check_real("g", None), TypeError, "g: expected a real number, got NoneType"),
    (lambda: check_real("g", torch.zeros(2)), TypeError, "g: expected a real number, got Tensor"),
    (lambda: check_real("g", math.nan), ValueError, r"g: expected a finite value in \[-inf, inf\], got nan"),
    (lambda: check_real("g", 1.0, hi=1.0, hi_open=True), ValueError, r"g: expected a finite value in \[-inf, 1\), "
                                                                     r"got 1.0"),
    (lambda: check_real("g", -2, lo=-1), ValueError, r"g: expected a finite value in \[-1, inf\], got -2.0"),
    (lambda: check_positive("sigma", 0.0), ValueError, r"sigma: expected a finite value in \(0, inf\], got 0.0"),
    (lambda: check_positive("sigma", math.inf), ValueError, r"sigma: expected a finite value in \(0, inf\], got inf"),
    (lambda: check_positive("sigma", [1.0]), TypeError, "sigma: expected a real number, got list"),
    # check_int / check_odd_int / check_seed / check_spp
    (lambda: check_int("n", 2.0, lo=1), TypeError, "n: expected an int, got float"),
    (lambda: check_int("n", False, lo=0), TypeError, "n: expected an int, got bool"),
    (lambda: check_int("n", 0, lo=1), ValueError, "n: expected an int >= 1, got 0"),
    (lambda: check_int("views", 7, lo=1, hi=6), ValueError, r"views: expected an int in \[1, 6\], got 7"),
    (lambda: check_int("views", 0, lo=1, hi=6), ValueError, r"views: expected an int in \[1, 6\], got 0"),
    (lambda: check_odd_int("window", 4), ValueError, "window: expected an odd int >= 1, got 4"),
    (lambda: check_odd_int("window", -1), ValueError, "window: expected an odd int >= 1, got -1"),
    (lambda: check_odd_int("window", 2.5), TypeError, "window: expected an odd int, got float"),
    (lambda: check_seed("seed", 2 ** 64), ValueError, "seed: expected a 64-bit integer, got 18446744073709551616"),
    (lambda: check_seed("seed", 1.0), TypeError, "seed: expected an int, got float"),
    (lambda: check_spp(2 ** 32), ValueError, r"spp: expected < 2\*\*32, got 4294967296"),
    (lambda: check_spp(0), ValueError, "spp: expected an int >= 1, got 0"),
    # check_choice
    (lambda: check_choice("space", "rgb", ("linear", "srgb")), ValueError,
     r"space: expected one of \('linear', 'srgb'\), got 'rgb'"),
    (lambda: check_choice("space", None, ("linear", "srgb")), ValueError,
     r"space: expected one of \('linear', 'srgb'\), got None"),
    (lambda: check_choice("chromatic", 1, ("hero",), kind=str), TypeError,
     r"chromatic: expected one of \('hero',\), got int"),
    # check_path
    (lambda: check_path("path", 42), TypeError, "path: expected a str or os.PathLike, got int"),
    (lambda: check_path("path", b"x.png"), TypeError, "path: expected a str or os.PathLike, got bytes"),
    (lambda: check_path("path", ""), ValueError, "path: expected a non-empty path, got ''"),
    (lambda: check_path("path", "x.png", (".exr", ".hdr")), ValueError,
     r"path: expected a path ending with \.exr or \.hdr, got 'x\.png'"),
    # check_rgb / check_vector3 / check_direction
    (lambda: check_rgb("colour", (1.0, 2.0)), ValueError, "colour: expected a scalar or 3 RGB values, got 2 values"),
    (lambda: check_rgb("colour", (1.0, -2.0, 0.0)), ValueError, r"colour: expected a finite value in \[0, inf\]"),
    (lambda: check_rgb("colour", "red"), TypeError, "colour: expected a scalar or 3 RGB values, got str"),
    (lambda: check_vector3("origin", (1.0, 2.0)), ValueError, r"origin: expected 3 numbers \(x, y, z\), got 2"),
    (lambda: check_vector3("origin", {1, 2, 3}), TypeError, r"origin: expected 3 numbers \(x, y, z\), got set"),
    (lambda: check_direction("up", (0, 0, 0)), ValueError, "up: expected a non-zero direction, got"),
    # check_tensor
    (lambda: check_tensor("points", [[0.0, 0.0, 0.0]], "(N, 3)"), TypeError,
     r"points: expected a torch.Tensor of shape \(N, 3\), got list"),
    (lambda: check_tensor("points", np.zeros((2, 3)), "(N, 3)"), TypeError,
     r"points: expected a torch.Tensor of shape \(N, 3\), got ndarray"),
    (lambda: check_tensor("points", "x", "(N, 3)", numpy=True), TypeError,
     r"points: expected a torch.Tensor or numpy.ndarray of shape \(N, 3\), got str"),
    (lambda: check_tensor("points", torch.zeros(2, 3, dtype=torch.int64), "(N, 3)", dtypes="floating"), TypeError,
     "points: expected a floating-point dtype, got torch.int64"),
    (lambda: check_tensor("points", torch.zeros(2, 3, dtype=torch.complex64), "(N, 3)", dtypes="floating"),
     TypeError, "points: expected a floating-point dtype, got torch.complex64"),
    (lambda: check_tensor("index", torch.zeros(2, 3), "(N, 3)", dtypes="integer"), TypeError,
     "index: expected an integer dtype, got torch.float32"),
    (lambda: check_tensor("index", torch.zeros(2, 3, dtype=torch.bool), "(N, 3)", dtypes="integer"), TypeError,
     "index: expected an integer dtype, got torch.bool"),
    (lambda: check_tensor("x", torch.zeros(2, dtype=torch.float16), "(N,)", dtypes=(torch.float32, torch.float64)),
     TypeError, "x: expected dtype torch.float32 or torch.float64, got torch.float16"),
    (lambda: check_tensor("points", torch.zeros(2, 2), "(N, 3)", ndim=2, last=3), ValueError,
     r"points: expected shape \(N, 3\), got \(2, 2\)"),
    (lambda: check_tensor("points", torch.zeros(2, 3, 1), "(N, 3)", ndim=2), ValueError,
     r"points: expected shape \(N, 3\), got \(2, 3, 1\)"),
    (lambda: check_tensor("points", torch.zeros(()), "(N, 3)", last=3), ValueError,
     r"points: expected shape \(N, 3\), got \(\)"),
    (lambda: check_tensor("x", torch.zeros(5), "(N,) or (B, N)", ndim=(2, 3)), ValueError,
     r"x: expected shape \(N,\) or \(B, N\), got \(5,\)"),
    (lambda: check_tensor("points", torch.zeros(0, 3), "(N, 3)", nonempty=True), ValueError,
     r"points: expected a non-empty tensor of shape \(N, 3\), got \(0, 3\)"),
    (lambda: check_tensor("points", torch.zeros(1, 3, device="meta"), "(N, 3)", cpu=True), ValueError,
     "points: expected a CPU tensor .*, got device meta"),
    # check_float_tensor / check_finite
    (lambda: check_float_tensor("texels", torch.full((2, 3), math.nan), "(N, 3)"), ValueError,
     "texels: expected finite values, got 6 NaN/Inf entries"),
    (lambda: check_float_tensor("texels", torch.zeros(2, 3, dtype=torch.int32), "(N, 3)"), TypeError,
     "texels: expected a floating-point dtype, got torch.int32"),
    (lambda: check_float_tensor("texels", torch.zeros(0, 3), "(N, 3)", last=3), ValueError,
     r"texels: expected a non-empty tensor of shape \(N, 3\)"),
    (lambda: check_finite("target", torch.tensor([0.0, math.inf, -math.inf])), ValueError,
     "target: expected finite values, got 2 NaN/Inf entries"),
    (lambda: check_finite("target", np.array([[math.nan, 1.0]])), ValueError,
     "target: expected finite values, got 1 NaN/Inf entries"),
    # check_image_shape
    (lambda: check_image_shape("image_shape", 64), TypeError, r"image_shape: expected \(H, W\), got 64"),
    (lambda: check_image_shape("image_shape", (4, 5, 3)), TypeError, r"image_shape: expected \(H, W\), got"),
    (lambda: check_image_shape("image_shape", (4, 5, 3, 1), channels=True), TypeError,
     r"image_shape: expected \(H, W\) or \(H, W, C\), got \(4, 5, 3, 1\)"),
    (lambda: check_image_shape("image_shape", (4.0, 5)), TypeError, r"image_shape: expected \(H, W\) of ints"),
    (lambda: check_image_shape("image_shape", (1, 5), min_size=2), ValueError,
     r"image_shape: expected \(H, W\) with H, W >= 2, got \(1, 5\)"),
    # check_point_in_image
    (lambda: check_point_in_image("pith", (1.0, 2.0, 3.0), (4, 5)), ValueError,
     r"pith: expected two numbers \(x, y\) in pixels, got \(1.0, 2.0, 3.0\)"),
    (lambda: check_point_in_image("pith", "ab", (4, 5)), ValueError, "pith: expected two numbers"),
    (lambda: check_point_in_image("pith", (5, 0), (4, 5)), ValueError,
     r"pith: expected \(x, y\) inside the image \(x in \[0, 4\], y in \[0, 3\]\), got \(5, 0\)"),
    (lambda: check_point_in_image("pith", (0, -0.5), (4, 5)), ValueError, r"got \(0, -0.5\)"),
    (lambda: check_point_in_image("pith", (math.nan, 0), (4, 5)), ValueError, r"got \(nan, 0\)"),
]


@pytest.mark.parametrize("index", range(len(BAD)))
def test_bad_input_is_refused_with_the_named_message(index):
    call, exc, match = BAD[index]
    with pytest.raises(exc, match=match) as info:
        call()
    assert type(info.value) is exc
    # one message style: "name: expected X, got Y"
    assert ": expected " in str(info.value) and ", got " in str(info.value)


def test_the_module_imports_nothing_from_the_package():
    """checks.py sits at the bottom of the layering: render/, nn/, geometry/, rings/ import it, never the reverse."""
    tree = ast.parse(pathlib.Path(checks.__file__).read_text())
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            assert node.level == 0 and not (node.module or "").startswith("torch_appearance"), ast.dump(node)
        elif isinstance(node, ast.Import):
            assert not any(a.name.startswith("torch_appearance") for a in node.names)


def test_public_names_exist():
    for name in checks.__all__:
        assert callable(getattr(checks, name)), name
