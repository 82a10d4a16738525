"""Scene relocation (csrc/volpath/relocate.h, scene_device.cpp): the built core::Scene<T> copied into buffers
placed elsewhere, every pointer member following, handed over as the struct's bytes (how a scene reaches a CUDA
kernel). Checked on the CPU: the scene relocated into fresh host buffers, every original buffer then overwritten with
poison (the caller's grids too), the CPU forward run over the relocated bytes gives the normal render's image bit
for bit; and leaving any one pointer that the scene uses behind changes the image (the test notices a forgotten
pointer). Also the layout the bytes are read with, and the refusals."""
import pytest
import torch

from torch_appearance._ext import _C
from torch_appearance.autograd.volpath import reference_medium, walk_options
from torch_appearance.geometry import sphere_sdf
from torch_appearance.render import (EnvironmentMap, OrthographicCamera, Scene, SDFBoundary, SurfaceTexels,
                                     TraceJob)

N = 12
H = 0.1
ORIGIN = (-0.6, -0.6, -0.6)


def _sdf():
    return sphere_sdf((N,) * 3, H, ORIGIN, (0.01, -0.02, 0.0), 0.45)


def _texels(count=24):
    """Points on the sphere of _sdf and their outward normals."""
    gen = torch.Generator().manual_seed(5)
    n = torch.randn((count, 3), generator=gen, dtype=torch.float64)
    n = n / n.norm(dim=1, keepdim=True)
    return torch.tensor([0.01, -0.02, 0.0], dtype=torch.float64) + 0.45 * n, n


def _scenes():
    """(name, scene, grid shape (D, H, W)): a slab's face texels (box, dielectric, constant), an SDF object with
    surface texels and an environment map, a camera seeing it (index matched)."""
    envmap = torch.rand((6, 12, 3), generator=torch.Generator().manual_seed(9)) + 0.2
    pts, nrm = _texels()
    return [
        ("slab", Scene.slab(0.1, face="both", ior=1.4), (5, 7, 6)),
        ("texels", Scene(voxel_size=H, origin=ORIGIN, boundary=SDFBoundary(_sdf(), ior=1.5),
                         sensor=SurfaceTexels(pts, nrm, footprint_mm=0.05), g=0.3,
                         emitter=EnvironmentMap(envmap)), (N, N, N)),
        ("camera", Scene(voxel_size=H, origin=ORIGIN, boundary=SDFBoundary(_sdf(), ior=None),
                         sensor=OrthographicCamera(origin=(0.05, 0.0, 2.0), target=(0, 0, 0), up=(0, 1, 0),
                                                   extent_mm=(1.2, 1.2), resolution=(6, 5))), (N, N, N)),
    ]


def _medium(shape, dtype, chromatic, seed=1):
    """σ_t random in a shell, one value deeper inside (the homogeneous core of an SDF scene), albedo random."""
    gen = torch.Generator().manual_seed(seed)
    sigma_t = torch.rand((3,) + shape, generator=gen, dtype=torch.float64) * 20 + 2
    if not chromatic:
        sigma_t = sigma_t[:1].expand(3, -1, -1, -1)
    sigma_t = sigma_t.clone()
    if shape == (N, N, N):
        sigma_t[:, 3:9, 3:9, 3:9] = 9.0
    albedo = torch.rand((3,) + shape, generator=gen, dtype=torch.float64) * 0.2 + 0.79
    if shape == (N, N, N):
        albedo[:, 3:9, 3:9, 3:9] = 0.999
    return sigma_t.to(dtype).contiguous(), albedo.to(dtype).contiguous()


def _inputs(scene, shape, dtype, chromatic, ratio):
    sigma_t, albedo = _medium(shape, dtype, chromatic)
    samp = (sigma_t * 1.3).contiguous() if ratio else None
    ref_s, ref_a, is_ratio = reference_medium(sigma_t, albedo, samp, None)
    job = TraceJob(scene, spp=3, seed=11)
    options = walk_options(job, ref_s, job.seed, shape, dtype)
    return sigma_t, albedo, ref_s, ref_a, is_ratio, options


CASES = [pytest.param(name, dtype, chromatic, ratio, id=f"{name}-{str(dtype)[6:]}-{'l1' if chromatic else 'l3'}"
                      f"{'-ratio' if ratio else ''}")
         for name, dtype, chromatic, ratio in [("slab", torch.float32, True, False),
                                               ("slab", torch.float64, False, True),
                                               ("texels", torch.float32, True, True),
                                               ("texels", torch.float64, False, False),
                                               ("camera", torch.float32, False, False)]]


def _case(name):
    return next((scene, shape) for n, scene, shape in _scenes() if n == name)


@pytest.mark.parametrize("name, dtype, chromatic, ratio", CASES)
def test_relocated_scene_renders_bit_for_bit_with_its_originals_poisoned(name, dtype, chromatic, ratio):
    scene, shape = _case(name)
    sigma_t, albedo, ref_s, ref_a, is_ratio, options = _inputs(scene, shape, dtype, chromatic, ratio)
    expected, counts = _C.scene_forward(sigma_t, albedo, ref_s, ref_a, is_ratio, options)
    assert torch.isfinite(expected).all() and expected.abs().sum() > 0
    scene_bytes, keep = _C._relocate_scene(sigma_t.clone(), albedo.clone(), ref_s.clone(), ref_a.clone(), options)
    assert scene_bytes.dtype == torch.uint8 and scene_bytes.numel() == _C.scene_layout(dtype).size
    image, counts2 = _C._scene_forward_from_bytes(scene_bytes, dtype, is_ratio, options)
    assert torch.equal(image, expected)
    assert counts2.scatter_events == counts.scatter_events


def _used_pointers(scene_bytes, dtype):
    layout = _C.scene_layout(dtype)
    words = {name: int.from_bytes(bytes(scene_bytes[off:off + 8].tolist()), "little")
             for name, off in layout.pointers}
    return [name for name, value in words.items() if value != 0]


@pytest.mark.parametrize("name, dtype, chromatic, ratio", CASES)
def test_a_pointer_left_behind_is_noticed(name, dtype, chromatic, ratio):
    """The break-once check of the test above, for every pointer the scene uses: left pointing at its poisoned
    original, the image changes."""
    scene, shape = _case(name)
    sigma_t, albedo, ref_s, ref_a, is_ratio, options = _inputs(scene, shape, dtype, chromatic, ratio)
    expected, _ = _C.scene_forward(sigma_t, albedo, ref_s, ref_a, is_ratio, options)
    scene_bytes, keep = _C._relocate_scene(sigma_t.clone(), albedo.clone(), ref_s.clone(), ref_a.clone(), options)
    used = _used_pointers(scene_bytes, dtype)
    assert "medium.sigma_t.data" in used and "tally" not in used
    if name != "slab":
        assert {"sdf.sdf", "sdf.cell", "sdf.skip"} <= set(used)
        assert ("medium.core" in used) == (not ratio)  # a core needs the reference equal to the parameters
    if name == "texels":
        assert {"sensor.points", "sensor.normals", "sensor.radius", "emitter.map"} <= set(used)
    for skip in used:
        if not ratio and skip in ("medium.sigma_t.data", "medium.albedo.data"):
            continue  # without ratio weights the walk reads the sampling medium only (in a render, the same buffer)
        bad_bytes, bad_keep = _C._relocate_scene(sigma_t.clone(), albedo.clone(), ref_s.clone(), ref_a.clone(),
                                                 options, skip=skip)
        image, _ = _C._scene_forward_from_bytes(bad_bytes, dtype, is_ratio, options)
        assert not torch.equal(image, expected), f"{skip} left behind, yet the image did not change"


def test_the_replay_scene_and_the_palette_scene_relocate():
    """The replay's scene (floors, the core outside grad_support) relocates with its floors; the palette scene
    (index and tables) renders from its bytes as scene_forward_indexed."""
    scene, shape = _case("texels")
    sigma_t, albedo = _medium(shape, torch.float32, True)
    job = TraceJob(scene, spp=2, seed=4)
    options = walk_options(job, sigma_t, job.seed, shape, torch.float32)
    scene_bytes, keep = _C.scene_to_device(sigma_t, albedo, sigma_t, albedo, options, 0.5, 0.05, True,
                                           torch.device("cpu"))
    assert scene_bytes.numel() == _C.scene_layout(torch.float32).size
    # the grids already on the target device are used in place, not copied
    words = dict(_C.scene_layout(torch.float32).pointers)
    word = int.from_bytes(bytes(scene_bytes[words["medium.sigma_t.data"]:][:8].tolist()), "little")
    assert word == sigma_t.data_ptr()

    index = torch.randint(0, 4, shape, dtype=torch.uint8, generator=torch.Generator().manual_seed(3))
    st_table = torch.tensor([[5.0, 6.0, 7.0], [10.0, 2.0, 3.0], [1.0, 1.0, 1.0], [20.0, 15.0, 9.0]])
    al_table = torch.tensor([[0.9, 0.8, 0.7], [0.5, 0.95, 0.9], [0.99, 0.99, 0.99], [0.3, 0.6, 0.9]])
    options = job.scene_options(1, job.seed, shape, torch.float32)
    expected, _ = _C.scene_forward_indexed(index, st_table.t().contiguous(), al_table.t().contiguous(), options)
    scene_bytes, keep = _C.scene_to_device_indexed(index.clone(), st_table.t().contiguous(),
                                                   al_table.t().contiguous(), options, torch.device("cpu"))
    image, _ = _C._scene_forward_from_bytes(scene_bytes, torch.float32, False, options)
    assert torch.equal(image, expected)


def test_layout_and_refusals():
    for dtype, size in ((torch.float32, 632), (torch.float64, 784)):
        layout = _C.scene_layout(dtype)
        assert layout.size == size and layout.align == 8
        names = [n for n, _ in layout.pointers]
        assert len(names) == len(set(names)) == 22  # 4 channels × 3, core, 3 SDF, 3 texel, map, 2 tally
        offsets = sorted(off for _, off in layout.pointers)
        assert all(b - a >= 8 for a, b in zip(offsets, offsets[1:])) and offsets[-1] + 8 <= size
    scene, shape = _case("slab")
    sigma_t, albedo, ref_s, ref_a, is_ratio, options = _inputs(scene, shape, torch.float32, True, False)
    with pytest.raises(ValueError, match="skip: expected the name of a pointer member"):
        _C._relocate_scene(sigma_t, albedo, ref_s, ref_a, options, skip="medium.nothing")
    with pytest.raises(ValueError, match="scene_bytes: expected 632 bytes"):
        _C._scene_forward_from_bytes(torch.zeros(16, dtype=torch.uint8), torch.float32, False, options)
    with pytest.raises(ValueError, match="expected the four grids on one device"):
        _C.scene_to_device(sigma_t, albedo, ref_s, ref_a.to("meta"), options, 0.0, 0.0, False, torch.device("cpu"))
    with pytest.raises(RuntimeError, match="sigma_t: expected finite values"):
        bad = sigma_t.clone()
        bad[0, 0, 0, 0] = float("nan")
        _C.scene_to_device(bad, albedo, bad, ref_a, options, 0.0, 0.0, False, torch.device("cpu"))
