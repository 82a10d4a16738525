"""Reparameterised image gradients of the ring discontinuity (issue 14, second half) against central finite
differences of the filtered image; the naive (fixed-sample autograd) gradient as the negative control."""
import pytest
import torch

from torch_appearance.nn import WoodModel
from torch_appearance.nn.wood_reparam import (compare_ring_scale_gradients, ring_scale_gradient,
                                              ring_scale_gradient_fd)

from torch_appearance.testing import assert_z, seed_stats


def board(cmap=None):
    """A flat-sawn board: stem tilted 0.2 rad out of the plane, s_r = 0.8 mm, ~3 rings across the image."""
    m = WoodModel(ring_scale_mm=0.8, n_rings=4, distortion=None, dtype=torch.float64, color_bins=4)
    if cmap is None:
        cmap = torch.tensor([[0.62, 0.44, 0.27], [0.58, 0.40, 0.24], [0.40, 0.25, 0.12], [0.27, 0.14, 0.06]],
                            dtype=torch.float64)
    m.set_parameters(rotation=torch.tensor([1.7708, 0.0, 0.0]), translation=torch.tensor([-6.0, 3.0, 0.0]),
                     color_map=cmap.expand(4, cmap.shape[0], 3))
    return m.requires_grad_(False)


H, W, PX = 5, 6, 0.4


def fd_reference(model):
    return ring_scale_gradient_fd(model, H, W, PX, spp=16384, seed=99, h_rel=0.002)


def test_reparameterised_gradient_matches_finite_differences():
    m = board()
    fd, fd_se = fd_reference(m)
    assert float(fd.abs().max()) > 1.0                       # boundaries do move through the pixels
    mean, se = seed_stats(lambda s: ring_scale_gradient(m, H, W, PX, spp=64, seed=s), range(32))
    assert_z(mean - fd, (se ** 2 + fd_se ** 2).sqrt(), 0.0, what="reparameterised dI/ds_r")
    # without the control variate too: there the divergence term's share (≈ div V · I_p) is not cancelled by the
    # baseline, so this also checks div V (the comparison above hardly sees it: div V is nearly constant per pixel)
    mean, se = seed_stats(lambda s: ring_scale_gradient(m, H, W, PX, spp=64, seed=s, baseline=False), range(32))
    err = (se ** 2 + fd_se ** 2).sqrt()
    assert_z(mean - fd, err, 0.0, what="reparameterised dI/ds_r, no baseline")
    assert_z((mean - fd).mean(dim=(0, 1)), (err ** 2).sum(dim=(0, 1)).sqrt() / (H * W), 0.0,
             what="image mean of dI/ds_r, no baseline")


def test_naive_gradient_misses_the_boundary_term():
    m = board()
    fd, fd_se = fd_reference(m)
    naive = ring_scale_gradient(m, H, W, PX, spp=1024, seed=0, estimator="naive")
    rel = float((naive - fd).abs().sum() / fd.abs().sum())
    assert rel > 0.5, rel                                     # wrong, not just noisy
    # the true derivative changes sign across the image (the boundary terms), the naive one does not here
    assert float(fd.min()) < 0 < float(fd.max())
    assert float(naive.min()) > 0


def test_without_a_discontinuity_both_estimators_agree_with_finite_differences():
    """A colour map that is the same at lateness 0 and 1 has no jump: the naive estimator is unbiased then, and
    the reparameterised one must agree too."""
    cmap = torch.tensor([[0.6, 0.4, 0.3], [0.3, 0.2, 0.1], [0.3, 0.2, 0.1], [0.6, 0.4, 0.3]], dtype=torch.float64)
    m = board(cmap)
    fd, fd_se = fd_reference(m)
    for estimator in ("naive", "reparam"):
        mean, se = seed_stats(lambda s: ring_scale_gradient(m, H, W, PX, spp=64, seed=s, estimator=estimator),
                              range(32))
        assert_z(mean - fd, (se ** 2 + fd_se ** 2).sqrt(), 0.0, what=f"{estimator} without jump")


def test_compare_reports_the_block_statistics():
    res = compare_ring_scale_gradients(board(), 4, 4, PX, spp=64, seeds=4, fd_spp=2048, block=2)
    for name in ("reparam", "naive"):
        s = res["stats"][name]
        assert s["blocks"] == [2, 2] and s["z"].shape == (2, 2, 3) and s["z_threshold"] > 3
    assert res["stats"]["naive"]["relative_l1_error"] > res["stats"]["reparam"]["relative_l1_error"]


def test_baseline_keeps_the_mean_and_cuts_the_variance():
    m = board()
    with_b = torch.stack([ring_scale_gradient(m, H, W, PX, spp=32, seed=s) for s in range(24)])
    without = torch.stack([ring_scale_gradient(m, H, W, PX, spp=32, seed=s, baseline=False) for s in range(24)])
    diff = with_b - without                                   # same samples: the difference has mean 0
    assert_z(diff.mean(0), diff.std(0) / 24 ** 0.5, 0.0, what="baseline shift")
    assert float(with_b.var(0).mean()) < 0.2 * float(without.var(0).mean())


def test_bad_inputs_are_refused():
    m = board()
    with pytest.raises(ValueError, match="estimator"):
        ring_scale_gradient(m, 2, 2, PX, estimator="autograd")
    with pytest.raises(ValueError, match="spp"):
        ring_scale_gradient(m, 2, 2, PX, spp=0)
    with pytest.raises(ValueError, match="h_rel"):
        ring_scale_gradient_fd(m, 2, 2, PX, h_rel=0.0)


def test_reparameterised_gradient_on_a_cylinder_with_its_silhouette_in_view():
    """The lamp shade's curved surface (a cylinder seen from the side, Lambert shade, black background) with both
    silhouettes inside the image: the warp follows G∘S, the shade's own change along the warp is added, and the
    silhouette (fixed, where the shade falls to 0) is not crossed. Reparameterised = finite differences; naive not."""
    from torch_appearance.nn.wood_reparam import CylinderView

    m, cyl = board(), CylinderView(radius_mm=1.0, axis_mm=1.2)          # covers x in [0.2, 2.2] of [0, 2.4] mm
    fd, fd_se = ring_scale_gradient_fd(m, H, W, PX, spp=16384, seed=99, h_rel=0.002, surface=cyl)
    mean, se = seed_stats(lambda s: ring_scale_gradient(m, H, W, PX, spp=64, seed=s, surface=cyl), range(32))
    assert_z(mean - fd, (se ** 2 + fd_se ** 2).sqrt(), 0.0, what="reparameterised dI/ds_r on a cylinder")
    naive = ring_scale_gradient(m, H, W, PX, spp=1024, seed=0, estimator="naive", surface=cyl)
    assert float((naive - fd).abs().sum() / fd.abs().sum()) > 0.5
    with pytest.raises(ValueError, match="radius_mm"):
        CylinderView(radius_mm=0.0, axis_mm=1.0)


# ------------------------------------------------------------------------------------------------------------------
# reparam_render: the boundary term of every parameter by autograd (loss.backward())
# ------------------------------------------------------------------------------------------------------------------
from torch_appearance.nn.wood_reparam import (parameter_gradient, parameter_gradient_fd,  # noqa: E402
                                              render_filtered, reparam_render)

GEOMETRY = ["ring_scale", "rotation[0]", "translation[0]", "m_r[1,1]"]


def distorted_board():
    """The board above with a radial distortion texture (4×4 texels over r ∈ [0, 12] mm, z ∈ [−2, 8] mm)."""
    m = WoodModel(ring_scale_mm=0.8, n_rings=4, distortion="radial", distortion_shape=(4, 4), r_max_mm=12.0,
                  z_range_mm=(-2.0, 8.0), dtype=torch.float64, color_bins=4)
    cmap = torch.tensor([[0.62, 0.44, 0.27], [0.58, 0.40, 0.24], [0.40, 0.25, 0.12], [0.27, 0.14, 0.06]],
                        dtype=torch.float64)
    m_r = torch.randn(4, 4, dtype=torch.float64, generator=torch.Generator().manual_seed(1)) * 0.3
    m.set_parameters(rotation=torch.tensor([1.7708, 0.0, 0.0]), translation=torch.tensor([-6.0, 3.0, 0.0]),
                     color_map=cmap.expand(4, 4, 3), m_r=m_r)
    return m


def test_reparam_render_has_the_filtered_render_as_its_value():
    m = distorted_board()
    img = reparam_render(m, H, W, PX, spp=16, seed=5)
    assert torch.allclose(img.detach(), render_filtered(m, H, W, PX, spp=16, seed=5), atol=1e-12, rtol=0)
    img.sum().backward()                                       # every parameter that moves boundaries gets a gradient
    for name in ("log_ring_scale", "rotation", "translation", "m_r", "color_map"):
        assert getattr(m, name).grad is not None and bool(getattr(m, name).grad.abs().sum() > 0), name


def test_autograd_through_reparam_render_matches_finite_differences_for_every_geometry_parameter():
    """s_r, a rotation and a translation component and a distortion texel, all from the same backward passes,
    z-tested per pixel and channel against central finite differences (the same per-pixel Bonferroni test as the
    ring-scale tests above)."""
    m = distorted_board()
    reference = {spec: parameter_gradient_fd(m, spec, H, W, PX, spp=16384, seed=99) for spec in GEOMETRY}
    runs = torch.stack([parameter_gradient(m, GEOMETRY, H, W, PX, spp=32, seed=s) for s in range(16)])
    mean, se = runs.mean(0), runs.std(0) / 16 ** 0.5
    for k, spec in enumerate(GEOMETRY):
        fd, fd_se = reference[spec]
        assert float(fd.abs().max()) > 0.2, spec               # the boundaries do move through the pixels
        assert_z(mean[k] - fd, (se[k] ** 2 + fd_se ** 2).sqrt(), 0.0, what=f"reparameterised dI/d{spec}")
    # without the control variate the divergence term is not cancelled by the baseline: this checks div V
    runs = torch.stack([parameter_gradient(m, GEOMETRY, H, W, PX, spp=64, seed=100 + s, baseline=False)
                        for s in range(32)])
    mean, se = runs.mean(0), runs.std(0) / 32 ** 0.5
    for k, spec in enumerate(GEOMETRY):
        fd, fd_se = reference[spec]
        err = (se[k] ** 2 + fd_se ** 2).sqrt()
        assert_z(mean[k] - fd, err, 0.0, what=f"dI/d{spec}, no baseline")
        assert_z((mean[k] - fd).mean(dim=(0, 1)), (err ** 2).sum(dim=(0, 1)).sqrt() / (H * W), 0.0,
                 what=f"image mean of dI/d{spec}, no baseline")


def test_naive_autograd_misses_the_boundary_term_of_every_geometry_parameter():
    m = distorted_board()
    naive = parameter_gradient(m, GEOMETRY, H, W, PX, spp=256, seed=0, estimator="naive")
    for k, spec in enumerate(GEOMETRY):
        fd, _ = parameter_gradient_fd(m, spec, H, W, PX, spp=16384, seed=99)
        rel = float((naive[k] - fd).abs().sum() / fd.abs().sum())
        assert rel > 0.5, (spec, rel)


def test_colour_map_gradient_is_the_plain_average():
    """The colour map does not move boundaries: its reparameterised gradient is exactly the mean of the samples'
    interpolation weights, the same as naive autograd on the same samples."""
    m = distorted_board()
    specs = ["color_map[1,2,0]", "color_map[2,3,1]"]
    rep = parameter_gradient(m, specs, H, W, PX, spp=32, seed=3)
    naive = parameter_gradient(m, specs, H, W, PX, spp=32, seed=3, estimator="naive")
    assert float(naive.abs().max()) > 0.05
    assert torch.allclose(rep, naive, atol=1e-10, rtol=0)


def test_loss_backward_through_reparam_render_is_unbiased():
    """loss.backward() into the model's .grad: for the L2 loss Σ(I − T)² linearised at the expected image (weights
    2(E[I] − T), fixed), the mean over seeds matches the same weighted sum of central finite differences."""
    m = distorted_board()
    target = torch.rand(H, W, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(2))
    ref = render_filtered(m, H, W, PX, spp=16384, seed=7)
    grads = []
    for s in range(24):
        m.zero_grad()
        img = reparam_render(m, H, W, PX, spp=32, seed=s)
        ((img - target) * 2 * (ref - target)).sum().backward()   # d/dθ of Σ(I − T)² linearised at the mean image
        grads.append(torch.stack([m.translation.grad[1], m.m_r.grad[0, 0, 1, 1]]).clone())
    grads = torch.stack(grads)
    fd = []
    for spec in ("translation[1]", "m_r[1,1]"):
        d, d_se = parameter_gradient_fd(m, spec, H, W, PX, spp=16384, seed=7)
        w = 2 * (ref - target)
        fd.append(((d * w).sum(), ((d_se * w) ** 2).sum().sqrt()))
    est, est_se = grads.mean(0), grads.std(0) / 24 ** 0.5
    assert_z(est - torch.stack([f[0] for f in fd]), (est_se ** 2 + torch.stack([f[1] for f in fd]) ** 2).sqrt(),
             0.0, what="loss gradient")


def test_reparam_render_refuses_bad_parameters():
    m = distorted_board()
    with pytest.raises(ValueError, match="parameters"):
        reparam_render(m, 2, 2, PX, parameters={"m_q": torch.zeros(1, 1, 4, 4)})
    with pytest.raises(ValueError, match="parameters"):
        reparam_render(m, 2, 2, PX, parameters={"m_r": torch.zeros(4, 4)})
    with pytest.raises(ValueError, match="param"):
        parameter_gradient(m, "rotation[3]", 2, 2, PX)
    with pytest.raises(ValueError, match="param"):
        parameter_gradient(m, "scale", 2, 2, PX)
    with pytest.raises(ValueError, match="samples"):
        reparam_render(m, 2, 2, PX, spp=4, samples=(torch.zeros(3, 2), torch.zeros(3, 2)))


def test_every_geometry_parameter_on_the_cylinder_by_autograd():
    """reparam_render on the lamp shade's cylinder (silhouettes in view): s_r, rotation, translation and a
    distortion texel against central finite differences; the shade's change along the warp comes from evaluating
    it at the warped point, the warp is 0 off the surface, and no NaN reaches the gradients of the missed samples."""
    from torch_appearance.nn.wood_reparam import CylinderView

    m, cyl = distorted_board(), CylinderView(radius_mm=1.0, axis_mm=1.2)
    img = reparam_render(m, H, W, PX, spp=16, seed=5, surface=cyl)
    assert torch.allclose(img.detach(), render_filtered(m, H, W, PX, spp=16, seed=5, surface=cyl), atol=1e-12, rtol=0)
    runs = torch.stack([parameter_gradient(m, GEOMETRY, H, W, PX, spp=32, seed=s, surface=cyl) for s in range(16)])
    assert bool(torch.isfinite(runs).all())
    mean, se = runs.mean(0), runs.std(0) / 16 ** 0.5
    naive = parameter_gradient(m, GEOMETRY, H, W, PX, spp=256, seed=0, estimator="naive", surface=cyl)
    for k, spec in enumerate(GEOMETRY):
        fd, fd_se = parameter_gradient_fd(m, spec, H, W, PX, spp=16384, seed=99, surface=cyl)
        assert float(fd.abs().max()) > 0.2, spec
        assert_z(mean[k] - fd, (se[k] ** 2 + fd_se ** 2).sqrt(), 0.0, what=f"dI/d{spec} on the cylinder")
        assert float((naive[k] - fd).abs().sum() / fd.abs().sum()) > 0.5, spec
