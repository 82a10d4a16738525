"""Lobed innermost rings (issue 48 item 4): the independent board generator and the growth field's lobe texture.

The fit test starts from the true board transform and the (z, r) distortion the ring-based initial guess gives at
best (least squares of the true radius), and runs stage 1 of the wood fit against the true phase of a lobed-pith
board of ``testing.synthetic_boards``: with the lobe texture the phase RMS falls to 0.15 rad; without it (m_r over
(z, r) has no azimuth) it stays at 0.40 rad, 0.58 over the two innermost rings.
"""
import math
import time

import numpy as np
import pytest
import torch
from scipy import sparse
from scipy.sparse import linalg as sparse_linalg

from torch_appearance.nn.wood import WoodModel, matrix_to_axis_angle
from torch_appearance.pipelines.wood.config import WoodFitConfig
from torch_appearance.pipelines.wood.geometry_stage import fit_geometry
from torch_appearance.rings.board_init import _texture_weights
from torch_appearance.testing.synthetic_boards import RECIPES, BoardRecipe, independent_board, phase_scores


def _true_model(board, n, ps, lobes):
    """WoodModel placed on the generator's stem line, its m_r the least-squares fit of the true radius."""
    a, d = board["params"]["pith_point_mm"], board["params"]["stem_direction"]
    up = np.array([0.0, 0.0, -1.0])
    e1 = up - (up @ d) * d
    e1 /= np.linalg.norm(e1)
    rot = np.stack([e1, np.cross(d, e1), d])
    t = -rot @ a
    s = board["recipe"].ring_width_mm
    yy, xx = np.mgrid[0:n, 0:n] * ps
    q = np.stack([xx.ravel(), yy.ravel(), np.zeros(n * n)], 1) @ rot.T + t
    r, z = np.hypot(q[:, 0], q[:, 1]), q[:, 2]
    model = WoodModel(ring_scale_mm=s, distortion_shape=(16, 16), r_max_mm=float(r.max() + 2 * s),
                      z_range_mm=(float(z.min() - 1), float(z.max() + 1)), pith_taper_mm=s,
                      lobe_shape=(16, 8) if lobes else None, lobe_radius_mm=4 * s if lobes else None)
    model.set_parameters(rotation=matrix_to_axis_angle(rot), translation=t)
    a_tex = _texture_weights(model, q)
    lhs = (a_tex.T @ a_tex + 1e-3 * sparse.identity(a_tex.shape[1])).tocsc()
    tex = sparse_linalg.spsolve(lhs, a_tex.T @ (s * board["G"].ravel() - r))
    model.set_parameters(m_r=torch.as_tensor(tex.reshape(16, 16)))
    return model


@pytest.fixture
def one_thread():
    """Small renders run fastest on one thread (and do not fight other processes for the cores)."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def _fit_lobed(lobes, n=64, ps=0.4, epochs=150):
    board = independent_board("lobed_pith", n, n, ps, seed=0)
    model = _true_model(board, n, ps, lobes)
    cfg = WoodFitConfig(photo="", pixel_size_mm=ps, epochs=epochs)
    fit_geometry(model, torch.as_tensor(board["phase"], dtype=torch.float32), torch.ones(n, n), n, n, cfg, [],
                 time.perf_counter())
    with torch.no_grad():
        return phase_scores(model.render_board(n, n, ps)["phase"].double().numpy(), board["G"])


def test_lobed_pith_fit_needs_the_lobe_texture(one_thread):
    scores = _fit_lobed(lobes=True)
    assert scores["phase_rms"] < 0.25, scores              # 0.153 with lobes, 0.395 without
    assert scores["phase_rms_inner"] < 0.35, scores        # 0.203 with lobes, 0.581 without
    assert scores["boundary_circular_std"] < 0.3, scores   # 0.157 with lobes, 0.372 without


def test_lobe_texture_zero_is_the_plain_model():
    g = torch.Generator().manual_seed(0)
    kw = dict(ring_scale_mm=1.0, distortion_shape=(8, 8), r_max_mm=10.0, z_range_mm=(-5.0, 5.0), dtype=torch.float64)
    plain, lobed = WoodModel(**kw), WoodModel(**kw, lobe_shape=(8, 4), lobe_radius_mm=3.0)
    tex = 0.1 * torch.randn(8, 8, generator=g, dtype=torch.float64)
    plain.set_parameters(m_r=tex)
    lobed.set_parameters(m_r=tex)
    q = (torch.rand(300, 3, generator=g, dtype=torch.float64) - 0.5) * 8
    assert torch.equal(plain.evaluate(q)["G"], lobed.evaluate(q)["G"])
    lobed.set_parameters(m_p=0.3 * torch.randn(8, 4, generator=g, dtype=torch.float64))
    q.requires_grad_(True)
    out = lobed.evaluate(q)
    (grad,) = torch.autograd.grad(out["G"].sum(), q)
    # the fibre lies in the growth surface: its analytic gradient agrees with autograd's
    assert ((out["fiber"].detach() * grad).sum(-1).abs() / grad.norm(dim=-1)).max() < 1e-9
    far = torch.tensor([[3.5, 0.0, 0.0], [0.0, -5.0, 1.0]], dtype=torch.float64)   # r >= R_p: no lobes
    assert torch.allclose(lobed.evaluate(far)["G"], plain.evaluate(far)["G"], atol=1e-12)


def test_generator_truth_and_refusals():
    for name in RECIPES:
        b = independent_board(name, 48, 40, 0.2, seed=3)
        assert b["image"].shape == (48, 40, 3) and b["image"].dtype == np.float32
        assert np.isfinite(b["G"]).all() and b["G"].min() >= 0
        assert np.allclose(b["phase"], 2 * math.pi * (b["G"] - np.floor(b["G"])))
    again = independent_board("lobed_pith", 48, 40, 0.2, seed=3)
    assert np.array_equal(again["image"], independent_board("lobed_pith", 48, 40, 0.2, seed=3)["image"])
    for kwargs, name in [(dict(recipe="nope"), "recipe"), (dict(height=4), "height"),
                         (dict(pixel_size_mm=0.0), "pixel_size_mm"), (dict(seed=-1), "seed"),
                         (dict(noise=float("nan")), "noise"),
                         (dict(recipe=BoardRecipe(lobe_amplitude=0.9)), "recipe.lobe_amplitude"),
                         (dict(recipe=BoardRecipe(profile="x")), "recipe.profile")]:
        with pytest.raises(ValueError, match=name):
            independent_board(**kwargs)
    with pytest.raises(ValueError, match="fit_phase"):
        phase_scores(np.zeros((3, 3)), np.zeros((3, 4)))
    with pytest.raises(ValueError, match="lobe_shape"):
        WoodModel(lobe_shape=(2, 2))
    with pytest.raises(ValueError, match="lobe_radius_mm"):
        WoodModel(lobe_shape=(8, 4), lobe_radius_mm=-1.0)
    with pytest.raises(ValueError, match="lobe_shape"):
        WoodFitConfig(photo="x.png", lobe_shape=(8, 1)).validate()
    with pytest.raises(ValueError, match="m_p"):
        WoodModel().set_parameters(m_p=torch.zeros(8, 4))
