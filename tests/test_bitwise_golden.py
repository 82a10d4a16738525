"""Images and gradients equal to the bit across refactors: SHA-256 of every case's image, σ_t gradient and albedo
gradient against hashes stored from a known-good build (tests/data/golden_hashes.json).

The cases cover each way into the tracer that the test suite uses: the slab (render_texels: chromatic, achromatic,
hero, index matched, one face and both), an object (SDF dielectric, surface texels), cameras (orthographic and
perspective; constant, map and disc emitters), the wood volume of a veneer, the palette render of a quantised
print, a partitioned share and the two-pass replay. Each case pins the thread count (gradient sums are
deterministic for a given thread count) and the walk (scalar, and AVX2 where the CPU has it).

A refactor that is meant to change no behaviour must keep every hash. A change that is meant to change the numbers
(a new estimator, another summation order) regenerates them, on purpose and in its own commit::

    python tests/test_bitwise_golden.py --update
"""
import hashlib
import json
import math
import os
import sys

import pytest
import torch

import torch_appearance as ta
from torch_appearance._ext import _C
from torch_appearance.geometry import sphere_sdf
from torch_appearance.render import (BoxBoundary, ConstantEnvironment, DiscLight, EnvironmentMap,
                                     OrthographicCamera, PerspectiveCamera, Scene, SDFBoundary, SurfaceTexels)
from torch_appearance.render.volpath import render_scene_indexed

HERE = os.path.dirname(os.path.abspath(__file__))
GOLDEN = os.path.join(HERE, "data", "golden_hashes.json")
THREADS = 2


def _digest(x):
    if x is None:
        return None
    x = x.detach().contiguous()
    return f"{x.dtype}:{tuple(x.shape)}:" + hashlib.sha256(x.numpy().tobytes()).hexdigest()[:32]


def _medium(shape, dtype, *, chromatic=True, seed=3):
    """A heterogeneous medium with exact zeros (σ_t = 0 exercises the floored reference, α = 0 the zero-safe
    weights)."""
    gen = torch.Generator().manual_seed(seed)
    sigma_t = torch.rand((3, *shape), generator=gen, dtype=torch.float64) * 20 + 1
    albedo = torch.rand((3, *shape), generator=gen, dtype=torch.float64) * 0.3 + 0.7
    if not chromatic:
        sigma_t = sigma_t[:1].expand(3, *shape).clone()
    sigma_t[:, 0, 0, :2] = 0.0
    albedo[:, -1, 1, 1:3] = 0.0
    return sigma_t.to(dtype), albedo.to(dtype)


def _differentiate(render, sigma_t, albedo):
    """(image, ∂E/∂σ_t, ∂E/∂albedo) for E = Σ image · fixed weights."""
    s = sigma_t.clone().requires_grad_()
    a = albedo.clone().requires_grad_()
    image = render(s, a)
    weights = torch.linspace(-1.0, 2.0, image.numel(), dtype=image.dtype).reshape(image.shape)
    (image * weights).sum().backward()
    return image, s.grad, a.grad


def _slab(dtype, chromatic_medium, **kwargs):
    sigma_t, albedo = _medium((4, 6, 7), dtype, chromatic=chromatic_medium)
    return _differentiate(lambda s, a: ta.render_texels(s, a, voxel_size=0.1, spp=4, seed=11, **kwargs),
                          sigma_t, albedo)


def _sphere_scene(n_texels=40, ior=1.5):
    shape, h, origin = (10, 10, 10), 0.1, (-0.5, -0.5, -0.5)
    sdf = sphere_sdf(shape, h, origin, (0.0, 0.0, 0.0), 0.4)
    k = torch.arange(n_texels, dtype=torch.float64) + 0.5
    z = 1 - 2 * k / n_texels
    phi = k * math.pi * (3 - math.sqrt(5))
    n = torch.stack([(1 - z ** 2).sqrt() * phi.cos(), (1 - z ** 2).sqrt() * phi.sin(), z], 1)
    sensor = SurfaceTexels(n * 0.4, n, footprint_mm=0.05)
    return Scene(voxel_size=h, origin=origin, boundary=SDFBoundary(sdf, ior=ior), sensor=sensor), shape


def _object(dtype):
    scene, shape = _sphere_scene()
    sigma_t, albedo = _medium(shape, dtype)
    return _differentiate(lambda s, a: ta.render_scene(scene, s, a, spp=4, seed=5), sigma_t, albedo)


def _object_hero():
    scene, shape = _sphere_scene()
    sigma_t, albedo = _medium(shape, torch.float32)
    return _differentiate(lambda s, a: ta.render_scene(scene, s, a, spp=4, seed=5, chromatic="hero"),
                          sigma_t, albedo)


def _object_shell(one_walk):
    """A print's case: a sphere whose gradients are asked for in a shell only (grad_support) round a homogeneous core
    (crossed in bricks) and with mixed surface cells outside the shell (their deposits are dropped); with
    ``one_walk`` the render and its gradient in one walk (the adjoint known first). A zero's sign outside the shell
    is not part of the result (+0 and −0 are hashed alike)."""
    shape, h, origin = (24, 24, 24), 0.1, (-1.2, -1.2, -1.2)
    sdf = sphere_sdf(shape, h, origin, (0.0, 0.0, 0.0), 1.1)
    k = torch.arange(60, dtype=torch.float64) + 0.5
    z = 1 - 2 * k / 60
    phi = k * math.pi * (3 - math.sqrt(5))
    n = torch.stack([(1 - z ** 2).sqrt() * phi.cos(), (1 - z ** 2).sqrt() * phi.sin(), z], 1)
    scene = Scene(voxel_size=h, origin=origin, boundary=SDFBoundary(sdf, ior=1.5),
                  sensor=SurfaceTexels(n * 1.1, n, footprint_mm=0.05))
    centre = (torch.arange(24, dtype=torch.float64) + 0.5) * h - 1.2
    r = (centre.view(-1, 1, 1) ** 2 + centre.view(1, -1, 1) ** 2 + centre.view(1, 1, -1) ** 2).sqrt()
    core, shell = r < 0.85, (r >= 0.85) & (r < 1.02)
    sigma_t, albedo = _medium(shape, torch.float32)
    sigma_t[:, core] = torch.tensor([6.0, 9.0, 12.0]).view(3, 1)
    albedo[:, core] = torch.tensor([0.99, 0.98, 0.97]).view(3, 1)
    weights = torch.linspace(-1.0, 2.0, 60 * 3, dtype=torch.float32).reshape(60, 3)
    kw = dict(spp=4, seed=5, grad_support=shell)
    s = sigma_t.clone().requires_grad_()
    a = albedo.clone().requires_grad_()
    image = ta.render_scene(scene, s, a, adjoint=weights, **kw) if one_walk else ta.render_scene(scene, s, a, **kw)
    (image * weights).sum().backward()
    return image, s.grad + 0.0, a.grad + 0.0


def _perspective_map():
    shape, h, origin = (10, 10, 10), 0.1, (-0.5, -0.5, -0.5)
    sdf = sphere_sdf(shape, h, origin, (0.0, 0.0, 0.0), 0.45)
    gen = torch.Generator().manual_seed(2)
    env = EnvironmentMap(torch.rand((8, 16, 3), generator=gen, dtype=torch.float64) * 2)
    cam = PerspectiveCamera(origin=(0.3, -1.8, 0.6), target=(0, 0, 0), up=(0, 0, 1), fov_y_deg=35.0,
                            resolution=(6, 7))
    scene = Scene(voxel_size=h, origin=origin, boundary=SDFBoundary(sdf, ior=1.33), sensor=cam, emitter=env, g=-0.3)
    sigma_t, albedo = _medium(shape, torch.float64, chromatic=False)
    return _differentiate(lambda s, a: ta.render_scene(scene, s, a, spp=3, seed=9), sigma_t, albedo)


def _orthographic_disc():
    cam = OrthographicCamera(origin=(0.35, 0.3, 2.0), target=(0.35, 0.3, 0.0), up=(0, 1, 0), extent_mm=(0.8, 0.7),
                             resolution=(5, 6))
    light = DiscLight((0.3, 0.2, -1.0), 20.0, radiance=(4.0, 3.0, 2.0), ambient=0.2)
    scene = Scene(voxel_size=0.1, boundary=BoxBoundary(1.5), sensor=cam, emitter=light)
    sigma_t, albedo = _medium((4, 6, 7), torch.float32)
    return _differentiate(lambda s, a: ta.render_scene(scene, s, a, spp=4, seed=13), sigma_t, albedo)


def _wood_veneer():
    from torch_appearance.nn import WoodModel
    from torch_appearance.nn.wood_volume import wood_volume
    from torch_appearance.pipelines.wood_volume_render import VeneerGeometry, veneer_scenes
    m = WoodModel(ring_scale_mm=0.25, n_rings=8, distortion=None, dtype=torch.float64, color_bins=4)
    cmap = torch.tensor([[0.62, 0.44, 0.27], [0.55, 0.38, 0.22], [0.40, 0.25, 0.12], [0.27, 0.14, 0.06]],
                        dtype=torch.float64)
    m.set_parameters(rotation=torch.tensor([0.5, 0.0, 0.0]), translation=torch.tensor([3.0, 2.0, 0.0]),
                     color_map=cmap.expand(8, 4, 3))
    m.requires_grad_(False)
    geometry = VeneerGeometry((0.4, 0.3), thickness_mm=0.3, voxel_mm=(0.1, 0.1))
    light = DiscLight((0.2, 0.1, 1.0), 30.0, radiance=(4.0, 3.0, 2.0), ambient=0.1)
    front, _ = veneer_scenes(geometry, light, resolution=(3, 4), side_rows=2)
    vol = wood_volume(m, geometry.grid_shape, geometry.voxel_size, dtype=torch.float64)
    return _differentiate(lambda s, a: ta.render_scene(front, s, a, spp=8, seed=1), vol.sigma_t, vol.albedo)


def _indexed():
    cam = OrthographicCamera(origin=(0.35, 0.3, 2.0), target=(0.35, 0.3, 0.0), up=(0, 1, 0), extent_mm=(0.8, 0.7),
                             resolution=(5, 6))
    scene = Scene(voxel_size=0.1, boundary=BoxBoundary(1.5), sensor=cam, emitter=ConstantEnvironment((1, 0.9, 0.8)))
    index = (torch.arange(4 * 6 * 7) % 5).to(torch.uint8).reshape(4, 6, 7)
    st = torch.tensor([[5.0, 5, 5], [20, 10, 5], [1, 1, 1], [0, 0, 0], [40, 40, 40]])
    al = torch.tensor([[0.9, 0.9, 0.9], [0.8, 0.5, 0.2], [1, 1, 1], [0.5, 0.5, 0.5], [0.99, 0.3, 0.6]])
    return render_scene_indexed(scene, index, st, al, spp=8, seed=4), None, None


def _partitioned():
    sigma_t, albedo = _medium((4, 6, 7), torch.float32)
    return _differentiate(lambda s, a: ta.render_texels(s, a, voxel_size=0.1, spp=4, seed=11, partition=(1, 3)),
                          sigma_t, albedo)


def _two_pass_replay():
    old = _C._set_tape_capacity(0)
    try:
        return _slab(torch.float32, True, face="both")
    finally:
        _C._set_tape_capacity(old)


CASES = {
    "slab_f32_chromatic_both": lambda: _slab(torch.float32, True, face="both"),
    "slab_f32_achromatic_top": lambda: _slab(torch.float32, False),
    "slab_f32_hero_bottom": lambda: _slab(torch.float32, True, face="bottom", chromatic="hero"),
    "slab_f32_seed_grad_env": lambda: _slab(torch.float32, True, seed_grad=77, environment=(1.0, 0.5, 2.0), g=-0.2),
    "slab_f64_index_matched": lambda: _slab(torch.float64, True, ior=None),
    "slab_f64_floors_sampling": lambda: _slab(torch.float64, False, sigma_t_floor=3.0, albedo_floor=0.2),
    "object_f32_surface_texels": lambda: _object(torch.float32),
    "object_f64_surface_texels": lambda: _object(torch.float64),
    "object_f32_hero": _object_hero,
    "object_f32_shell_two_walks": lambda: _object_shell(False),
    "object_f32_shell_one_walk": lambda: _object_shell(True),
    "camera_perspective_map_f64": _perspective_map,
    "camera_orthographic_disc_f32": _orthographic_disc,
    "wood_veneer_f64": _wood_veneer,
    "indexed_palette_f32": _indexed,
    "partition_1_of_3_f32": _partitioned,
    "two_pass_replay_f32": _two_pass_replay,
}


def _walks():
    _C._set_simd(-1)
    level = int(_C._set_simd(-1))
    return ["scalar"] + (["avx2"] if level >= 1 else [])


def compute(case, walk):
    """The three digests of ``case`` with the walk ``walk`` ("scalar" or "avx2") on THREADS threads."""
    threads = torch.get_num_threads()
    old = _C._set_simd({"scalar": 0, "avx2": 1}[walk])
    torch.set_num_threads(THREADS)
    try:
        image, grad_s, grad_a = CASES[case]()
    finally:
        torch.set_num_threads(threads)
        _C._set_simd(-1 if old < 0 else old)
        _C._set_simd(-1)
    return {"image": _digest(image), "grad_sigma_t": _digest(grad_s), "grad_albedo": _digest(grad_a)}


def _stored():
    with open(GOLDEN) as f:
        return json.load(f)


@pytest.mark.parametrize("walk", ["scalar", "avx2"])
@pytest.mark.parametrize("case", sorted(CASES))
def test_images_and_gradients_equal_to_the_bit(case, walk):
    if walk not in _walks():
        pytest.skip("needs a CPU with AVX2 (or TA_SIMD is 0)")
    expected = _stored()[case][walk]
    got = compute(case, walk)
    for key in ("image", "grad_sigma_t", "grad_albedo"):
        assert got[key] == expected[key], f"{case} ({walk}): {key} changed: {got[key]} != stored {expected[key]}"


def test_the_hashes_see_one_bit():
    """The digest is of every bit: one ulp in one texel changes it."""
    image = _slab(torch.float32, True)[0]
    bumped = image.clone()
    bumped.view(-1)[17] = torch.nextafter(bumped.view(-1)[17], torch.tensor(math.inf))
    assert _digest(image) != _digest(bumped)


if __name__ == "__main__":
    if "--update" not in sys.argv[1:]:
        sys.exit("usage: python tests/test_bitwise_golden.py --update   (rewrites tests/data/golden_hashes.json)")
    table = {case: {walk: compute(case, walk) for walk in _walks()} for case in sorted(CASES)}
    tmp = GOLDEN + ".tmp"
    with open(tmp, "w") as f:
        json.dump(table, f, indent=1, sort_keys=True)
        f.write("\n")
    os.replace(tmp, GOLDEN)
    print(f"wrote {len(table)} cases × {len(_walks())} walks to {GOLDEN}")
