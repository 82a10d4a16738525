"""Tests of the procedural wood model (torch_appearance.nn.wood) and the synthetic boards (rings.synthetic)."""
import copy
import json
import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation
from torch.func import functional_call

from torch_appearance.nn import WoodModel
from torch_appearance.nn.wood import axis_angle_to_matrix, matrix_to_axis_angle
from torch_appearance.rings import synthetic_board

F64 = torch.float64


def _flat_sawn(model, rotation=(1.45, 0.08, -0.05), translation=(-3.0, 9.0, -2.0)):
    """Put a board roughly flat-sawn ~9 mm from the axis (rings as arches)."""
    return model.set_parameters(rotation=torch.tensor(rotation, dtype=F64),
                                translation=torch.tensor(translation, dtype=F64))


def _board_points(height, width, pixel_size):
    ys, xs = np.mgrid[0:height, 0:width].astype(np.float64) * pixel_size
    return np.stack([xs.ravel(), ys.ravel(), np.zeros(xs.size)], -1)


def _tree_points(model, height, width, pixel_size):
    """Independent board → tree transform through scipy's rotation."""
    rot = Rotation.from_rotvec(model.rotation.detach().double().numpy()).as_matrix()
    return _board_points(height, width, pixel_size) @ rot.T + model.translation.detach().double().numpy()


# ------------------------------------------------------------------------------------------------------------------
# Rotations
# ------------------------------------------------------------------------------------------------------------------
def test_axis_angle_matches_scipy_and_is_smooth_at_zero():
    rng = np.random.default_rng(0)
    vecs = np.concatenate([rng.normal(size=(20, 3)), 1e-5 * rng.normal(size=(5, 3)), np.zeros((1, 3)),
                           np.array([[math.pi, 0, 0], [0, 0, -3.0]])])
    ours = axis_angle_to_matrix(torch.from_numpy(vecs)).numpy()
    np.testing.assert_allclose(ours, Rotation.from_rotvec(vecs).as_matrix(), atol=1e-12)
    for v in (np.zeros(3), 3e-4 * np.ones(3), np.array([0.3, -1.2, 0.5])):
        w = torch.tensor(v, dtype=F64, requires_grad=True)
        assert torch.autograd.gradcheck(axis_angle_to_matrix, (w,), eps=1e-7, atol=1e-8)
    back = matrix_to_axis_angle(Rotation.from_rotvec([0.2, -0.4, 1.1]).as_matrix())
    np.testing.assert_allclose(back, [0.2, -0.4, 1.1], atol=1e-12)
    with pytest.raises(ValueError, match="matrix"):
        matrix_to_axis_angle(np.diag([1.0, 1.0, -1.0]))


# ------------------------------------------------------------------------------------------------------------------
# Closed forms
# ------------------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("distortion", [None, "radial", "azimuthal"])
def test_zero_distortion_matches_closed_form(distortion):
    model = WoodModel(ring_scale_mm=1.7, n_rings=8, distortion=distortion, dtype=F64)
    _flat_sawn(model)
    h, w, ps = 24, 30, 0.37
    out = model.render_board(h, w, ps)
    q = _tree_points(model, h, w, ps)
    g_true = np.hypot(q[:, 0], q[:, 1]).reshape(h, w) / 1.7
    np.testing.assert_allclose(out["G"].detach().numpy(), g_true, rtol=1e-12)
    np.testing.assert_array_equal(out["ring_index"].numpy(), np.floor(g_true).astype(np.int64))
    np.testing.assert_allclose(out["lateness"].detach().numpy(), g_true - np.floor(g_true), atol=1e-12)
    np.testing.assert_allclose(out["phase"].detach().numpy(), 2 * np.pi * (g_true - np.floor(g_true)), atol=1e-11)
    assert 0 <= float(out["lateness"].detach().min()) and float(out["lateness"].detach().max()) < 1
    # undistorted fibres follow the stem: ẑ in tree space, Rᵀẑ on the board
    fib = out["fiber"].detach().numpy().reshape(-1, 3)
    np.testing.assert_allclose(fib, np.tile([0.0, 0.0, 1.0], (h * w, 1)), atol=1e-12)
    rot = Rotation.from_rotvec(model.rotation.detach().numpy()).as_matrix()
    np.testing.assert_allclose(out["fiber_board"].detach().numpy().reshape(-1, 3), np.tile(rot[2], (h * w, 1)),
                               atol=1e-12)
    assert out["image"].shape == (h, w, 3) and out["fiber"].shape == (h, w, 3)


def test_constant_and_linear_distortion_closed_forms():
    s = 1.3
    z_range, r_max = (-20.0, 20.0), 40.0
    # tangential + radial constants: r' = sqrt((r + c)^2 + d^2)
    model = WoodModel(ring_scale_mm=s, n_rings=8, distortion="radial", distortion_shape=(6, 7), r_max_mm=r_max,
                      z_range_mm=z_range, tangential=True, dtype=F64)
    _flat_sawn(model)
    model.set_parameters(m_r=torch.full((6, 7), 0.4, dtype=F64), m_t=torch.full((6, 7), -0.9, dtype=F64))
    q = _tree_points(model, 10, 12, 0.5)
    r = np.hypot(q[:, 0], q[:, 1])
    G = model.render_board(10, 12, 0.5)["G"].detach().numpy().ravel()
    np.testing.assert_allclose(G, np.sqrt((r + 0.4) ** 2 + 0.9 ** 2) / s, rtol=1e-12)

    # a texture linear in (z, r) is reproduced exactly by bilinear interpolation: m = a·z + b·r
    a, b = 0.03, -0.1
    model = WoodModel(ring_scale_mm=s, n_rings=8, distortion="radial", distortion_shape=(6, 7), r_max_mm=r_max,
                      z_range_mm=z_range, dtype=F64)
    _flat_sawn(model)
    tex = model.texel_coordinates()
    model.set_parameters(m_r=a * tex[..., 0] + b * tex[..., 1])
    out = model.render_board(10, 12, 0.5)
    q = _tree_points(model, 10, 12, 0.5)
    r = np.hypot(q[:, 0], q[:, 1])
    assert r.max() < r_max and z_range[0] < q[:, 2].min() and q[:, 2].max() < z_range[1]
    np.testing.assert_allclose(out["G"].detach().numpy().ravel(), (r + a * q[:, 2] + b * r) / s, rtol=1e-12)
    np.testing.assert_allclose(out["m_r"].detach().numpy().ravel(), a * q[:, 2] + b * r, atol=1e-12)
    # fibre ∝ (1 + ∂m/∂r)·ẑ − (∂m/∂z)·r̂
    rhat = np.stack([q[:, 0] / r, q[:, 1] / r, np.zeros_like(r)], -1)
    f = (1 + b) * np.array([0.0, 0.0, 1.0]) - a * rhat
    f /= np.linalg.norm(f, axis=-1, keepdims=True)
    np.testing.assert_allclose(out["fiber"].detach().numpy().reshape(-1, 3), f, atol=1e-12)


def test_azimuthal_texture_is_periodic_and_matches_texels():
    hd = 8
    model = WoodModel(ring_scale_mm=1.0, n_rings=4, distortion="azimuthal", distortion_shape=(hd, 3), dtype=F64)
    tex = model.texel_coordinates()
    theta_rows = tex[:, 0, 1]
    np.testing.assert_allclose(theta_rows.numpy(), -np.pi + 2 * np.pi * np.arange(hd) / hd, atol=1e-15)
    values = torch.arange(hd, dtype=F64)[:, None].expand(hd, 3) * 0.1  # row i holds 0.1·i
    model.set_parameters(m_r=values)
    radius = 10.0
    # exactly at the texel rows (θ = −π is represented by atan2 as +π → wraps onto row 0)
    thetas = torch.cat([theta_rows[1:], torch.tensor([math.pi], dtype=F64)])
    pts = torch.stack([radius * torch.cos(thetas), radius * torch.sin(thetas), torch.zeros_like(thetas)], -1)
    got = model.evaluate(pts)["m_r"]
    np.testing.assert_allclose(got.detach().numpy(), np.r_[0.1 * np.arange(1, hd), 0.0], atol=1e-12)
    # between the last row (θ = π − 2π/hd) and θ = π the texture interpolates back towards row 0
    th = torch.tensor([math.pi - math.pi / hd], dtype=F64)
    pt = torch.stack([radius * torch.cos(th), radius * torch.sin(th), torch.zeros_like(th)], -1)
    np.testing.assert_allclose(model.evaluate(pt)["m_r"].detach().numpy(), [0.5 * 0.1 * (hd - 1)], atol=1e-12)
    # continuity across the seam θ = ±π
    eps = 1e-9
    th = torch.tensor([math.pi - eps, -math.pi + eps], dtype=F64)
    pt = torch.stack([radius * torch.cos(th), radius * torch.sin(th), torch.zeros_like(th)], -1)
    seam = model.evaluate(pt)["G"].detach().numpy()
    assert abs(seam[0] - seam[1]) < 1e-6


@pytest.mark.parametrize("distortion,tangential", [("radial", False), ("radial", True), ("azimuthal", True)])
def test_fiber_is_stem_projected_onto_growth_surface(distortion, tangential):
    """Analytic texture derivatives vs autograd: f ∝ ẑ − (ẑ·n)n with n = ∇G/|∇G| (autograd through grid_sample)."""
    torch.manual_seed(1)
    model = WoodModel(ring_scale_mm=1.5, n_rings=8, distortion=distortion, distortion_shape=(5, 6), r_max_mm=30.0,
                      z_range_mm=(-15.0, 15.0), tangential=tangential, dtype=F64)
    model.set_parameters(m_r=0.8 * torch.randn(5, 6, dtype=F64))
    if tangential:
        model.set_parameters(m_t=0.5 * torch.randn(5, 6, dtype=F64))
    pts = torch.randn(200, 3, dtype=F64) * torch.tensor([9.0, 9.0, 8.0], dtype=F64)
    pts = pts[torch.hypot(pts[:, 0], pts[:, 1]) > 1.0].requires_grad_(True)
    out = model.evaluate(pts)
    (grad,) = torch.autograd.grad(out["G"].sum(), pts)
    n = grad / grad.norm(dim=-1, keepdim=True)
    z = torch.tensor([0.0, 0.0, 1.0], dtype=F64)
    f = z - n[:, 2:3] * n
    f = f / f.norm(dim=-1, keepdim=True)
    np.testing.assert_allclose(out["fiber"].detach().numpy(), f.numpy(), atol=1e-10)
    np.testing.assert_allclose(out["fiber"].norm(dim=-1).detach().numpy(), 1.0, atol=1e-12)
    assert float((out["fiber"].detach() * grad).sum(-1).abs().max()) < 1e-10  # tangent to the growth surface


def test_pith_taper_keeps_the_pith_at_zero_and_the_fibre_exact():
    # a displacement texture that is large at r = 0: without the taper G is negative around the axis; with it G
    # starts at 0 on the axis, rises like r / s_r there and keeps the untapered field beyond a few taper lengths;
    # the analytic derivatives (the fibre) still match autograd
    torch.manual_seed(2)
    kw = dict(ring_scale_mm=1.5, n_rings=8, distortion="radial", distortion_shape=(5, 6), r_max_mm=30.0,
              z_range_mm=(-15.0, 15.0), tangential=True, dtype=F64)
    tex, tex_t = -1.0 + 0.3 * torch.randn(5, 6, dtype=F64), 0.2 * torch.randn(5, 6, dtype=F64)
    plain, tapered = WoodModel(**kw), WoodModel(pith_taper_mm=1.5, **kw)
    for m in (plain, tapered):
        m.set_parameters(m_r=tex, m_t=tex_t)
    r = torch.tensor([0.0, 0.05, 0.2, 12.0, 20.0], dtype=F64)
    axis = torch.stack([r, torch.zeros_like(r), torch.zeros_like(r)], -1)
    g_plain, g_tap = plain.evaluate(axis)["G"].detach(), tapered.evaluate(axis)["G"].detach()
    assert float(g_plain[0]) > 0.5  # sqrt((r + m_r)² + m_t²) / s_r: a ring's worth at the pith itself
    assert float(g_tap[0]) < 1e-12 and abs(float(g_tap[1]) - 0.05 / 1.5) < 1e-3
    np.testing.assert_allclose(g_tap[3:].numpy(), g_plain[3:].numpy(), rtol=1e-12)  # exp(-64): no taper left
    pts = torch.randn(200, 3, dtype=F64) * torch.tensor([3.0, 3.0, 8.0], dtype=F64)
    pts = pts[torch.hypot(pts[:, 0], pts[:, 1]) > 0.3].requires_grad_(True)
    out = tapered.evaluate(pts)
    (grad,) = torch.autograd.grad(out["G"].sum(), pts)
    n = grad / grad.norm(dim=-1, keepdim=True)
    f = torch.tensor([0.0, 0.0, 1.0], dtype=F64) - n[:, 2:3] * n
    np.testing.assert_allclose(out["fiber"].detach().numpy(), (f / f.norm(dim=-1, keepdim=True)).numpy(), atol=1e-10)
    with pytest.raises(ValueError, match="pith_taper_mm"):
        WoodModel(pith_taper_mm=-1.0)


def test_colour_map_lookup_closed_form():
    n_rings, k = 5, 4
    model = WoodModel(ring_scale_mm=1.0, n_rings=n_rings, distortion=None, dtype=F64, color_bins=k)
    cmap = torch.rand(n_rings, k, 3, dtype=F64, generator=torch.Generator().manual_seed(0))
    model.set_parameters(color_map=cmap)
    G = torch.tensor([0.0, 0.2, 1.5, 4.99, 5.25, 13.0 + 2 / 3, 7.999999], dtype=F64)
    pts = torch.stack([G, torch.zeros_like(G), torch.zeros_like(G)], -1)  # r = G·s_r with s_r = 1
    out = model.evaluate(pts)
    expected = []
    for g in G.tolist():
        ring, late = math.floor(g), g - math.floor(g)
        pos = late * (k - 1)
        k0 = min(int(math.floor(pos)), k - 2)
        w = pos - k0
        c = cmap[ring % n_rings]
        expected.append(((1 - w) * c[k0] + w * c[k0 + 1]).numpy())
    np.testing.assert_allclose(out["rgb"].detach().numpy(), np.array(expected), atol=1e-12)
    np.testing.assert_array_equal(out["ring_index"].numpy(), np.floor(G.numpy()).astype(np.int64))


# ------------------------------------------------------------------------------------------------------------------
# Gradients
# ------------------------------------------------------------------------------------------------------------------
def _smooth_model(distortion, tangential, seed=0):
    """Distorted flat-sawn float64 model whose colour map is affine in lateness (→ image smooth inside a ring)."""
    gen = torch.Generator().manual_seed(seed)
    model = WoodModel(ring_scale_mm=1.9, n_rings=6, distortion=distortion, distortion_shape=(5, 6), r_max_mm=30.0,
                      z_range_mm=(-12.0, 12.0), tangential=tangential, dtype=F64, color_bins=3)
    _flat_sawn(model)
    if distortion is not None:
        model.set_parameters(m_r=0.3 * torch.randn(5, 6, dtype=F64, generator=gen))
    if tangential:
        model.set_parameters(m_t=0.3 * torch.randn(5, 6, dtype=F64, generator=gen))
    base = torch.rand(6, 1, 3, dtype=F64, generator=gen)
    slope = torch.rand(6, 1, 3, dtype=F64, generator=gen) - 0.5
    model.set_parameters(color_map=base + slope * torch.linspace(0, 1, 3, dtype=F64)[None, :, None])
    return model


@pytest.mark.parametrize("distortion,tangential", [("radial", True), ("azimuthal", False), (None, False)])
def test_gradcheck_render_board_every_parameter(distortion, tangential):
    model = _smooth_model(distortion, tangential)
    h, w, ps = 4, 5, 0.9
    out = model.render_board(h, w, ps)
    frac = out["lateness"].detach()
    margin = torch.minimum(frac, 1 - frac).min()
    assert margin > 1e-3, "test set-up: a pixel sits on a ring boundary"
    names = [n for n, p in model.named_parameters()]
    expected = {"rotation", "translation", "log_ring_scale", "color_map"}
    expected |= {"m_r"} if distortion else set()
    expected |= {"m_t"} if tangential else set()
    assert set(names) == expected
    params = dict(model.named_parameters())
    for name in names:
        def fn(p, name=name):
            o = functional_call(model, {**{k: v.detach() for k, v in params.items()}, name: p}, (h, w, ps))
            # one concatenated output: gradcheck skips tuple members that do not require grad
            return torch.cat([o[k].reshape(-1) for k in ("G", "image", "lateness", "fiber", "fiber_board")])
        p0 = params[name].detach().clone().requires_grad_(True)
        assert torch.autograd.gradcheck(fn, (p0,), eps=1e-6, atol=1e-7, rtol=1e-5), name


def test_gradients_flow_to_points_and_all_parameters():
    model = _smooth_model("radial", True)
    pts = (torch.rand(16, 2, dtype=F64, generator=torch.Generator().manual_seed(3)) * 4).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda p: model.evaluate(p, board=True)["G"], (pts,), eps=1e-6, atol=1e-7)
    out = model.render_board(6, 7, 0.5)
    (out["image"].sum() + out["G"].sum() + out["fiber_board"][..., 0].sum()).backward()
    for name, p in model.named_parameters():
        assert p.grad is not None and bool(p.grad.abs().sum() > 0), name


# ------------------------------------------------------------------------------------------------------------------
# Persistence
# ------------------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("distortion,tangential,dtype", [("radial", True, F64), ("azimuthal", False, torch.float32),
                                                         (None, False, F64)])
def test_save_load_round_trip(tmp_path, distortion, tangential, dtype):
    model = _smooth_model(distortion, tangential).to(dtype)
    model.set_parameters(ring_scale_mm=2.345)
    json_path, pt_path = model.save(tmp_path / "wood")
    assert json_path.name == "wood.json" and pt_path.name == "wood.pt"
    meta = json.loads(json_path.read_text())
    assert meta["format"] == "torch_appearance.WoodModel" and meta["config"]["distortion"] == distortion
    loaded = WoodModel.load(tmp_path / "wood")
    assert loaded.dtype == dtype and loaded.distortion == distortion and loaded.tangential == tangential
    assert loaded.r_max_mm == model.r_max_mm and loaded.z_range_mm == model.z_range_mm
    for (n1, p1), (n2, p2) in zip(model.state_dict().items(), loaded.state_dict().items()):
        assert n1 == n2 and torch.equal(p1, p2), n1
    a, b = model.render_board(5, 6, 0.4), loaded.render_board(5, 6, 0.4)
    for key in a:
        assert torch.equal(a[key], b[key]), key

    meta["format"] = "something else"
    json_path.write_text(json.dumps(meta))
    with pytest.raises(ValueError, match="format"):
        WoodModel.load(tmp_path / "wood")
    with pytest.raises(FileNotFoundError):
        WoodModel.load(tmp_path / "missing")


# ------------------------------------------------------------------------------------------------------------------
# Bad inputs
# ------------------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("kwargs,exc,match", [
    ({"ring_scale_mm": 0.0}, ValueError, "ring_scale_mm"),
    ({"ring_scale_mm": -1.0}, ValueError, "ring_scale_mm"),
    ({"ring_scale_mm": float("nan")}, ValueError, "ring_scale_mm"),
    ({"ring_scale_mm": "2"}, TypeError, "ring_scale_mm"),
    ({"n_rings": 0}, ValueError, "n_rings"),
    ({"n_rings": 2.5}, TypeError, "n_rings"),
    ({"distortion": "helical"}, ValueError, "distortion"),
    ({"distortion_shape": (1, 8)}, ValueError, "distortion_shape"),
    ({"distortion_shape": (4,)}, TypeError, "distortion_shape"),
    ({"r_max_mm": 0}, ValueError, "r_max_mm"),
    ({"z_range_mm": (5.0, -5.0)}, ValueError, "z_range_mm"),
    ({"z_range_mm": 5.0}, TypeError, "z_range_mm"),
    ({"distortion": None, "tangential": True}, ValueError, "tangential"),
    ({"dtype": torch.int32}, TypeError, "dtype"),
    ({"color_bins": 1}, ValueError, "color_bins"),
])
def test_bad_constructor_arguments(kwargs, exc, match):
    with pytest.raises(exc, match=match):
        WoodModel(**kwargs)


def test_bad_call_arguments():
    model = WoodModel(distortion=None)
    for bad in (0.0, -0.1, float("inf")):
        with pytest.raises(ValueError, match="pixel_size_mm"):
            model.render_board(4, 4, bad)
    with pytest.raises(ValueError, match="height"):
        model.render_board(0, 4, 0.1)
    with pytest.raises(TypeError, match="width"):
        model.render_board(4, 4.0, 0.1)
    with pytest.raises(ValueError, match=r"points: expected shape \(N, 3\)"):
        model.evaluate(torch.zeros(5, 2))
    with pytest.raises(ValueError, match=r"points: expected shape \(N, 2 or 3\)"):
        model.evaluate(torch.zeros(5, 4), board=True)
    with pytest.raises(TypeError, match="points"):
        model.evaluate(torch.zeros(5, 3, dtype=torch.int64))
    with pytest.raises(ValueError, match="finite"):
        model.evaluate(torch.tensor([[0.0, float("nan"), 1.0]]))
    with pytest.raises(ValueError, match="m_r"):
        model.set_parameters(m_r=torch.zeros(32, 64))
    with pytest.raises(ValueError, match="texel"):
        model.texel_coordinates()
    radial = WoodModel()
    with pytest.raises(ValueError, match=r"m_r: expected shape \(1, 1, 32, 64\)"):
        radial.set_parameters(m_r=torch.zeros(3, 3))
    with pytest.raises(ValueError, match="rotation"):
        radial.set_parameters(rotation=torch.zeros(4))
    with pytest.raises(ValueError, match="ring_scale_mm"):
        radial.set_parameters(ring_scale_mm=-2.0)


# ------------------------------------------------------------------------------------------------------------------
# Synthetic boards
# ------------------------------------------------------------------------------------------------------------------
def test_synthetic_board_ground_truth():
    board = synthetic_board(96, 128, pixel_size_mm=0.1, seed=2, noise=0.02)
    again = synthetic_board(96, 128, pixel_size_mm=0.1, seed=2, noise=0.02)
    assert np.array_equal(board["image"], again["image"])  # deterministic per seed
    assert board["image"].shape == (96, 128, 3) and board["image"].dtype == np.float32
    assert board["phase"].shape == board["G"].shape == (96, 128)
    params = board["params"]
    assert 1.0 <= params["ring_scale"] <= 4.0 and 8 <= params["ring_scale"] / 0.1 <= 40
    assert 5.0 <= params["distance_mm"] <= 30.0
    G = board["G"].astype(np.float64)
    np.testing.assert_allclose(board["phase"], 2 * np.pi * (G - np.floor(G)), atol=1e-4)
    resid = board["image"] - board["clean"]
    inside = (board["clean"] > 0.1) & (board["clean"] < 0.9)
    assert abs(resid[inside].std() - 0.02) < 0.002
    # boundaries: one polyline per ring crossing, on the iso-line G = k to numerical precision
    assert len(board["boundaries"]) >= 1 and len(board["boundaries"]) == len(board["boundary_levels"])
    model = copy.deepcopy(board["model"]).double()
    for line, level in zip(board["boundaries"], board["boundary_levels"]):
        assert line.ndim == 2 and line.shape[1] == 2 and len(line) >= 2
        g = model.evaluate(torch.from_numpy(line * 0.1), board=True)["G"].detach().numpy()
        assert np.abs(g - level).max() < 1e-8
    # the stored transform reproduces the board
    rebuilt = WoodModel(**{k: v for k, v in model.config().items() if k != "dtype"}, dtype=F64)
    rebuilt.load_state_dict(model.state_dict())
    rebuilt.set_parameters(rotation=params["rotation"], translation=params["translation"])
    np.testing.assert_allclose(rebuilt.render_board(96, 128, 0.1)["G"].detach().numpy(), G, rtol=1e-5)


def test_synthetic_board_arches_centre_on_projected_axis():
    board = synthetic_board(64, 160, pixel_size_mm=0.1, seed=5, in_plane_deg=0.0, distortion_mm=0.0, noise=0.0)
    G = board["G"]
    axis_x = board["params"]["axis_point_px"][0]
    row = G[32]
    assert abs(int(np.argmin(row)) - axis_x) <= 1.0
    assert np.allclose(board["params"]["axis_direction_px"], [0.0, 1.0], atol=1e-12)
    # arches: along the axis the growth field changes monotonically (axis inclined to the board)
    col = G[:, int(round(axis_x))] if 0 <= axis_x < 160 else G[:, 80]
    d = np.diff(col)
    assert (d > 0).all() or (d < 0).all()


def test_synthetic_board_bad_inputs():
    with pytest.raises(ValueError, match="pixel_size_mm"):
        synthetic_board(32, 32, pixel_size_mm=0.0)
    with pytest.raises(ValueError, match="height"):
        synthetic_board(1, 32)
    with pytest.raises(ValueError, match="noise"):
        synthetic_board(32, 32, noise=-1.0)
    with pytest.raises(TypeError, match="seed"):
        synthetic_board(32, 32, seed=1.5)
