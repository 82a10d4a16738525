"""Bad input is refused with a clear error naming the argument; the C++ side checks again without crashing."""
import math

import pytest
import torch

import torch_appearance as ta
from torch_appearance._ext import _C, check_build


def good(dtype=torch.float32):
    return torch.full((3, 2, 3, 4), 5.0, dtype=dtype), torch.full((3, 2, 3, 4), 0.5, dtype=dtype)


def render(**overrides):
    sigma, albedo = good()
    kw = dict(voxel_size=0.1, spp=1)
    kw.update(overrides)
    return ta.render_texels(kw.pop("sigma_t", sigma), kw.pop("albedo", albedo), **kw)


@pytest.mark.parametrize("overrides,exc,match", [
    (dict(sigma_t=[[1.0]]), TypeError, "sigma_t: expected a torch.Tensor"),
    (dict(sigma_t=torch.ones(3, 2, 3, 4, dtype=torch.int32)), TypeError, "sigma_t: expected dtype"),
    (dict(sigma_t=torch.ones(2, 3, 4)), ValueError, r"sigma_t: expected shape \(3, D, H, W\)"),
    (dict(sigma_t=torch.ones(4, 2, 3, 4)), ValueError, r"sigma_t: expected shape \(3, D, H, W\)"),
    (dict(sigma_t=torch.ones(3, 0, 3, 4)), ValueError, "sigma_t: expected shape"),
    (dict(albedo=torch.ones(3, 2, 3, 5)), ValueError, r"albedo: expected shape \(3, 2, 3, 4\)"),
    (dict(albedo=torch.ones(3, 2, 3, 4, dtype=torch.float64)), ValueError, "albedo: expected dtype torch.float32"),
    (dict(sigma_t=torch.full((3, 2, 3, 4), -1.0)), ValueError, r"sigma_t: expected values in \[0, inf\]"),
    (dict(sigma_t=torch.full((3, 2, 3, 4), math.nan)), ValueError, "sigma_t: expected finite values"),
    (dict(sigma_t=torch.full((3, 2, 3, 4), math.inf)), ValueError, "sigma_t: expected finite values"),
    (dict(albedo=torch.full((3, 2, 3, 4), 1.5)), ValueError, r"albedo: expected values in \[0, 1\]"),
    (dict(albedo=torch.full((3, 2, 3, 4), -0.1)), ValueError, r"albedo: expected values in \[0, 1\]"),
    (dict(g=1.0), ValueError, "g: expected"),
    (dict(g=-1.0), ValueError, "g: expected"),
    (dict(g=math.nan), ValueError, "g: expected"),
    (dict(g="0.4"), TypeError, "g: expected a real number"),
    (dict(ior=0.9), ValueError, "ior: expected"),
    (dict(ior=math.inf), ValueError, "ior: expected"),
    (dict(spp=0), ValueError, "spp: expected an int >= 1"),
    (dict(spp=2.5), TypeError, "spp: expected an int"),
    (dict(voxel_size=0.0), ValueError, "voxel_size: expected"),
    (dict(voxel_size=-1.0), ValueError, "voxel_size: expected"),
    (dict(voxel_size=(0.1, 0.1)), ValueError, "voxel_size: expected one edge or three edges"),
    (dict(voxel_size=(0.1, 0.0, 0.1)), ValueError, "voxel_size: expected"),
    (dict(face="side"), ValueError, "face: expected one of"),
    (dict(environment=(1.0, 2.0)), ValueError, "environment: expected"),
    (dict(environment=-1.0), ValueError, "environment: expected"),
    (dict(max_depth=0), ValueError, "max_depth: expected an int >= 1"),
    (dict(rr_depth=-1), ValueError, "rr_depth: expected an int >= 0"),
    (dict(seed=1.5), TypeError, "seed: expected an int"),
    (dict(seed=2 ** 64), ValueError, "seed: expected a 64-bit integer"),
    (dict(albedo_floor=2.0), ValueError, "albedo_floor: expected"),
    (dict(sigma_t_floor=-1.0), ValueError, "sigma_t_floor: expected"),
    (dict(sampling_sigma_t=torch.ones(3, 2, 3, 3)), ValueError, "sampling_sigma_t: expected shape"),
    (dict(sampling_sigma_t=torch.zeros(3, 2, 3, 4)), ValueError, "sampling_sigma_t: expected > 0 wherever"),
    (dict(sampling_albedo=torch.zeros(3, 2, 3, 4)), ValueError, "sampling_albedo: expected > 0 wherever"),
    (dict(stats=[]), TypeError, "stats: expected a dict"),
])
def test_bad_input_named_error(overrides, exc, match):
    with pytest.raises(exc, match=match):
        render(**overrides)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device to build a CUDA tensor")
def test_mixed_devices_refused():
    sigma, albedo = good()
    with pytest.raises(ValueError, match=r"^albedo: expected the device of sigma_t \(cuda:0\), got cpu$"):
        ta.render_texels(sigma.cuda(), albedo, voxel_size=0.1)


def test_meta_tensor_refused():
    sigma, albedo = good()
    with pytest.raises(ValueError, match="sigma_t: expected a CPU or CUDA tensor"):
        ta.render_texels(sigma.to("meta"), albedo.to("meta"), voxel_size=0.1)
    with pytest.raises(ValueError, match=r"albedo: expected the device of sigma_t \(cpu\), got meta"):
        ta.render_texels(sigma, albedo.to("meta"), voxel_size=0.1)


def test_non_contiguous_input_is_fine():
    sigma, albedo = good()
    big = torch.full((3, 2, 3, 8), 5.0)[..., ::2]
    assert not big.is_contiguous()
    torch.testing.assert_close(ta.render_texels(big, albedo, voxel_size=0.1, spp=4),
                               ta.render_texels(sigma, albedo, voxel_size=0.1, spp=4))


def options(boundary=None, sensor=None, emitter=None, **kw):
    """A SceneOptions of the slab (box boundary, top face texels, constant environment), pieces overridden by dicts."""
    opt = _C.SceneOptions()
    opt.voxel_size, opt.spp, opt.max_depth = [0.1, 0.1, 0.1], 1, 16
    for k, v in kw.items():
        setattr(opt, k, v)
    for name, piece, overrides in (("boundary", _C.BoundaryOptions(), boundary), ("sensor", _C.SensorOptions(), sensor),
                                   ("emitter", _C.EmitterOptions(), emitter)):
        for k, v in (overrides or {}).items():
            setattr(piece, k, v)
        setattr(opt, name, piece)
    return opt


@pytest.mark.parametrize("args,match", [
    (dict(sigma_t=torch.ones(3, 2, 2)), "sigma_t: expected shape"),
    (dict(albedo=torch.full((3, 2, 2, 2), 2.0)), r"albedo: expected finite values in \[0, 1\]"),
    (dict(sigma_t=torch.full((3, 2, 2, 2), math.nan)), "sigma_t: expected finite values"),
    (dict(ref_sigma_t=torch.ones(3, 2, 2, 2, dtype=torch.float64)), "sampling_sigma_t: expected dtype"),
    (dict(ref_albedo=torch.ones(3, 2, 2, 2)[:, :, :, :1].expand(3, 2, 2, 2)), "sampling_albedo: expected a contiguous"),
    (dict(options=options(g=1.0)), "g: expected"),
    (dict(options=options(spp=0)), "spp: expected"),
    (dict(options=options(voxel_size=[0.1, -1.0, 0.1])), "voxel_size: expected finite edges > 0"),
    (dict(options=options(voxel_size=[0.1, 0.1])), "voxel_size: expected 3 edges"),
    (dict(options=options(sensor=dict(face=7))), "face: expected"),
    (dict(options=options(boundary=dict(ior=0.5))), "ior: expected"),
    (dict(options=options(max_depth=0)), "max_depth: expected"),
    (dict(options=options(emitter=dict(radiance=[1.0]))), "radiance: expected 3 values"),
    (dict(options=options(emitter=dict(radiance=[1.0, -1.0, 1.0]))), r"radiance: expected finite values in \[0,"),
    (dict(options=options(lanes=3), ref_sigma_t=torch.rand(3, 2, 2, 2)), "lanes=3"),
])
def test_cpp_checks_again(args, match):
    """Calling the extension directly with bad input raises RuntimeError; the interpreter survives."""
    kw = dict(sigma_t=torch.ones(3, 2, 2, 2), albedo=torch.ones(3, 2, 2, 2) * 0.5, options=options())
    kw.update(args)
    kw.setdefault("ref_sigma_t", kw["sigma_t"])
    kw.setdefault("ref_albedo", kw["albedo"])
    with pytest.raises(RuntimeError, match=match):
        _C.scene_forward(kw["sigma_t"], kw["albedo"], kw["ref_sigma_t"], kw["ref_albedo"], False, kw["options"])


def test_cpp_backward_checks_grad_output():
    s, a = torch.ones(3, 2, 2, 2), torch.ones(3, 2, 2, 2) * 0.5
    with pytest.raises(RuntimeError, match="grad_output: expected 12 elements"):
        _C.scene_backward(torch.ones(5), s, a, s, a, True, True, options())
    with pytest.raises(RuntimeError, match="grad_output: expected finite"):
        _C.scene_backward(torch.full((2, 2, 3), math.nan), s, a, s, a, True, True, options())


def test_cpp_options_are_sound():
    """The default options of the checks above render (so each failure above is the one named)."""
    s, a = torch.ones(3, 2, 2, 2), torch.ones(3, 2, 2, 2) * 0.5
    image, _ = _C.scene_forward(s, a, s, a, False, options())
    assert image.shape == (2, 2, 3) and torch.isfinite(image).all()
    gs, ga, _ = _C.scene_backward(torch.ones(2, 2, 3), s, a, s, a, True, True, options())
    assert gs.shape == s.shape and ga.shape == a.shape


def test_stale_or_mismatched_build_says_how_to_fix(tmp_path):
    (tmp_path / "x.cpp").write_text("int main() {}\n")
    with pytest.raises(ImportError, match="stale.*make build"):
        check_build("0000000000000000", torch.__version__, csrc_dir=str(tmp_path))
    with pytest.raises(ImportError, match="built against torch 0.0.1.*make build"):
        check_build(_C.source_hash, "0.0.1", csrc_dir=str(tmp_path))
    check_build(_C.source_hash, _C.torch_version)  # the real build is current
