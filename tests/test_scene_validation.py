"""Bad input to the general-scene API is refused with a clear error naming the argument; the C++ side checks again
and never crashes the interpreter."""
import math

import pytest
import torch

import torch_appearance as ta
from torch_appearance._ext import _C
from torch_appearance.geometry import sphere_sdf
from torch_appearance.nn import SceneRenderer
from torch_appearance.render import (BoxBoundary, ConstantEnvironment, DiscLight, EnvironmentMap, FaceTexels,
                                     OrthographicCamera, PerspectiveCamera, Scene, SDFBoundary, SurfaceTexels,
                                     TraceJob)

N, H, ORIGIN = 6, 0.1, (-0.3, -0.3, -0.3)
SDF = sphere_sdf((N,) * 3, H, ORIGIN, (0, 0, 0), 0.2)
CAM = dict(origin=(0, 0, 2), target=(0, 0, 0), up=(0, 1, 0))


def medium(n=N):
    return torch.full((3, n, n, n), 5.0), torch.full((3, n, n, n), 0.5)


@pytest.mark.parametrize("make,exc,match", [
    (lambda: SDFBoundary([[1.0]]), TypeError, "sdf: expected a torch.Tensor"),
    (lambda: SDFBoundary(torch.ones(3, 3, dtype=torch.int32)), TypeError,
     "sdf: expected a floating-point dtype, got torch.int32"),
    (lambda: SDFBoundary(torch.ones(3, 3)), ValueError, r"sdf: expected shape \(D\+1, H\+1, W\+1\)"),
    (lambda: SDFBoundary(torch.ones(1, 3, 3)), ValueError, "sdf: expected shape"),
    (lambda: SDFBoundary(torch.where(SDF < 0, math.nan, SDF)), ValueError, "sdf: expected finite values"),
    (lambda: SDFBoundary(SDF - 1.0), ValueError, "sdf: expected > 0 on the grid's outer corners"),
    (lambda: SDFBoundary(SDF + 1.0), ValueError, "sdf: expected some negative"),
    (lambda: SDFBoundary(SDF, ior=0.5), ValueError, "ior: expected"),
    (lambda: BoxBoundary(ior=math.nan), ValueError, "ior: expected"),
    (lambda: FaceTexels("side"), ValueError, "face: expected one of"),
    (lambda: SurfaceTexels(torch.zeros(4, 2), torch.zeros(4, 2)), ValueError, r"points: expected shape \(N, 3\)"),
    (lambda: SurfaceTexels(torch.zeros(4, 3), torch.zeros(3, 3)), ValueError, "normals: expected shape"),
    (lambda: SurfaceTexels(torch.zeros(2, 3), torch.tensor([[0, 0, 1.0], [0, 0, 2.0]])), ValueError,
     "normals: expected unit vectors"),
    (lambda: SurfaceTexels(torch.zeros(2, 3), torch.tensor([[0, 0, 1.0], [0, 0, math.nan]])), ValueError,
     "normals: expected finite"),
    (lambda: SurfaceTexels(torch.zeros(2, 3), torch.tensor([[0, 0, 1.0]] * 2), footprint_mm=-1.0), ValueError,
     "footprint_mm: expected"),
    (lambda: SurfaceTexels(torch.zeros(2, 3), torch.tensor([[0, 0, 1.0]] * 2), footprint_mm=torch.ones(3)),
     ValueError, "footprint_mm: expected a scalar or shape"),
    (lambda: OrthographicCamera(origin=(0, 0, 2), target=(0, 0, 0), up=(0, 0, 1)), ValueError,
     "up: expected a direction not parallel"),
    (lambda: OrthographicCamera(origin=(0, 0, 0), target=(0, 0, 0), up=(0, 1, 0)), ValueError,
     "target: expected a point other than"),
    (lambda: OrthographicCamera(**CAM, extent_mm=(1.0, 0.0)), ValueError, "extent_mm: expected"),
    (lambda: OrthographicCamera(**CAM, resolution=(0, 4)), ValueError, "resolution: expected an int >= 1"),
    (lambda: OrthographicCamera(**CAM, resolution=(4,)), ValueError, r"resolution: expected \(rows, cols\)"),
    (lambda: OrthographicCamera(origin=(0, math.inf, 2), target=(0, 0, 0), up=(0, 1, 0)), ValueError,
     "origin: expected a finite"),
    (lambda: PerspectiveCamera(**CAM, fov_y_deg=180.0), ValueError, "fov_y_deg: expected"),
    (lambda: PerspectiveCamera(origin=(0, 0, 2), target=(0, 0, 0), up=(0, 0, 0)), ValueError,
     "up: expected a non-zero direction"),
    (lambda: ConstantEnvironment(-1.0), ValueError, "environment: expected"),
    (lambda: ConstantEnvironment((1.0, 2.0)), ValueError, "environment: expected a scalar or 3 RGB values"),
    (lambda: EnvironmentMap(torch.ones(4, 8)), ValueError, r"image: expected shape \(H, W, 3\)"),
    (lambda: EnvironmentMap(torch.ones(4, 8, 4)), ValueError, r"image: expected shape \(H, W, 3\)"),
    (lambda: EnvironmentMap(-torch.ones(4, 8, 3)), ValueError, "image: expected radiance >= 0"),
    (lambda: EnvironmentMap(torch.full((4, 8, 3), math.inf)), ValueError, "image: expected finite"),
    (lambda: DiscLight((0, 0, 1), 5.0, radiance=-2.0), ValueError, "radiance: expected"),
    (lambda: DiscLight((0, 0, 1), 5.0, ambient=(1, 1)), ValueError, "ambient: expected"),
    (lambda: DiscLight((0, 0, 0), 5.0), ValueError, "direction: expected a non-zero direction"),
    (lambda: DiscLight((0, 0, 1), 0.0), ValueError, "angular_radius_deg: expected"),
    (lambda: Scene(voxel_size=0.0), ValueError, "voxel_size: expected"),
    (lambda: Scene(voxel_size=0.1, origin=(0, 0)), ValueError, "origin: expected 3 numbers"),
    (lambda: Scene(voxel_size=0.1, g=1.0), ValueError, "g: expected"),
    (lambda: Scene(voxel_size=0.1, boundary="box"), TypeError, "boundary: expected one of"),
    (lambda: Scene(voxel_size=0.1, sensor=None), TypeError, "sensor: expected one of"),
    (lambda: Scene(voxel_size=0.1, emitter=1.0), TypeError, "emitter: expected one of"),
    (lambda: Scene(voxel_size=0.1, boundary=SDFBoundary(SDF)), ValueError, "FaceTexels read the faces"),
    (lambda: Scene(voxel_size=0.1, max_depth=0), ValueError, "max_depth: expected"),
])
def test_pieces_refuse_bad_input(make, exc, match):
    with pytest.raises(exc, match=match):
        make()


def scene(**kw):
    args = dict(voxel_size=H, origin=ORIGIN, boundary=SDFBoundary(SDF, ior=1.5),
                sensor=OrthographicCamera(**CAM, extent_mm=(0.6, 0.6), resolution=(3, 3)))
    args.update(kw)
    return Scene(**args)


@pytest.mark.parametrize("call,exc,match", [
    (lambda s, a: ta.render_scene("scene", s, a), TypeError, "scene: expected a torch_appearance.render.Scene"),
    (lambda s, a: ta.render_scene(scene(), *medium(5)), ValueError, r"sdf: expected shape \(D\+1, H\+1, W\+1\) = "),
    (lambda s, a: ta.render_scene(scene(), s, a, spp=0), ValueError, "spp: expected an int >= 1"),
    (lambda s, a: ta.render_scene(scene(), s, a, seed=1.5), TypeError, "seed: expected an int"),
    (lambda s, a: ta.render_scene(scene(), s, a, seed_grad=-2 ** 64), ValueError, "seed_grad: expected a 64-bit"),
    (lambda s, a: ta.render_scene(scene(), -s, a), ValueError, "sigma_t: expected values in"),
    (lambda s, a: ta.render_scene(scene(), s, a * 3), ValueError, "albedo: expected values in"),
    (lambda s, a: ta.render_scene(scene(), s, a, sampling_sigma_t=torch.zeros_like(s)), ValueError,
     "sampling_sigma_t: expected > 0 wherever"),
    (lambda s, a: ta.render_scene(scene(sensor=SurfaceTexels(torch.tensor([[0, 0, 0.5]]), torch.tensor([[0, 0, 1.0]]))),
                                  s, a), ValueError, "points: expected texels inside the grid"),
    (lambda s, a: ta.render_scene(scene(), s, a, chromatic="spectral"), ValueError, "chromatic: expected one of"),
    (lambda s, a: ta.render_scene(scene(), s, a, partition=(3, 3)), ValueError, "partition: expected 0 <= rank"),
    (lambda s, a: SceneRenderer(scene(), spp=0), ValueError, "spp: expected"),
    (lambda s, a: SceneRenderer("scene"), TypeError, "scene: expected"),
    (lambda s, a: SceneRenderer(scene(), gradient_seed="derived"), ValueError, "gradient_seed: expected one of"),
    (lambda s, a: SceneRenderer.slab(0.1, face="side"), ValueError, "face: expected one of"),
    (lambda s, a: TraceJob("scene"), TypeError, "scene: expected a torch_appearance.render.Scene"),
    (lambda s, a: TraceJob(scene(), spp=2 ** 32), ValueError, "spp: expected < 2"),
    (lambda s, a: TraceJob(scene(), partition=[0, True]), TypeError, r"partition: expected \(rank, world\)"),
    (lambda s, a: ta.autograd.VolumePathTrace.apply(s, a, None, None, scene(), None), TypeError,
     "job: expected a torch_appearance.render.TraceJob"),
])
def test_render_scene_refuses_bad_input(call, exc, match):
    s, a = medium()
    with pytest.raises(exc, match=match):
        call(s, a)


def with_piece(piece, **fields):
    """A SceneOptions whose `piece` (boundary, sensor, emitter) has `fields` changed."""
    opt = TraceJob(scene(), spp=1).scene_options(3, 0, (N, N, N), torch.float32)
    sub = getattr(opt, piece)
    for k, v in fields.items():
        setattr(sub, k, v)
    setattr(opt, piece, sub)
    return opt


@pytest.mark.parametrize("opt,match", [
    (lambda: with_piece("boundary", sdf=torch.ones(3, 3, 3)), "sdf: expected size"),
    (lambda: with_piece("boundary", sdf=torch.full((N + 1,) * 3, math.nan)), "sdf: expected finite"),
    (lambda: with_piece("boundary", sdf=SDF.float() - 1), "sdf: expected > 0 on the grid's outer corners"),
    (lambda: with_piece("boundary", kind=5), "boundary: expected kind"),
    (lambda: with_piece("boundary", ior=0.5), "ior: expected"),
    (lambda: with_piece("sensor", kind=0), "sensor: face texels need the box boundary"),
    (lambda: with_piece("sensor", forward=[0.0, 0.0, 0.5]), "camera forward: expected a unit vector"),
    (lambda: with_piece("sensor", rows=0), "resolution: expected"),
    (lambda: with_piece("sensor", width=-1.0), "extent_mm: expected"),
    (lambda: with_piece("sensor", kind=1, points=torch.zeros(2, 3), normals=torch.zeros(2, 3),
                        radius=torch.zeros(2)), "normals: expected unit vectors"),
    (lambda: with_piece("sensor", kind=1, points=torch.zeros(2, 3), normals=torch.tensor([[0, 0, 1.0]] * 2),
                        radius=torch.zeros(3)), "footprint: expected size"),
    (lambda: with_piece("emitter", kind=1, map=torch.ones(2, 2)), "image: expected 3 dimensions"),
    (lambda: with_piece("emitter", kind=1, map=-torch.ones(2, 2, 3)), "image: expected radiance >= 0"),
    (lambda: with_piece("emitter", kind=2, direction=[0.0, 0.0, 0.5]), "direction: expected a unit vector"),
    (lambda: with_piece("emitter", radiance=[1.0, -1.0, 1.0]), "radiance: expected finite values"),
    (lambda: with_piece("emitter", kind=7), "emitter: expected kind"),
])
def test_cpp_checks_again(opt, match):
    """The C++ glue refuses what the Python layer would have refused, with a RuntimeError, never a crash."""
    s, a = medium()
    with pytest.raises(RuntimeError, match=match):
        _C.scene_forward(s, a, s, a, False, opt())
    with pytest.raises(RuntimeError, match=match):
        _C.scene_backward(torch.ones(3, 3, 3), s, a, s, a, True, True, opt())


def test_cpp_grad_output_checked():
    s, a = medium()
    opt = TraceJob(scene(), spp=1).scene_options(3, 0, (N, N, N), torch.float32)
    with pytest.raises(RuntimeError, match="grad_output: expected 27 elements"):
        _C.scene_backward(torch.ones(5), s, a, s, a, True, True, opt)
    with pytest.raises(RuntimeError, match="grad_output: expected finite"):
        _C.scene_backward(torch.full((3, 3, 3), math.nan), s, a, s, a, True, True, opt)


def test_environment_map_from_exr(tmp_path):
    """An EXR written by io.write_exr is read back as the map; a truncated file is refused."""
    from torch_appearance import io as ta_io
    image = torch.rand(4, 8, 3, generator=torch.Generator().manual_seed(0))
    path = tmp_path / "sky.exr"
    ta_io.write_exr(str(path), image)
    env = EnvironmentMap.from_exr(str(path), scale=2.0)
    assert env.image.shape == (4, 8, 3) and env.scale == 2.0
    assert torch.allclose(torch.as_tensor(env.image).float(), image, atol=1e-3)
    data = path.read_bytes()
    (tmp_path / "cut.exr").write_bytes(data[: len(data) // 2])
    with pytest.raises((ValueError, OSError)):
        EnvironmentMap.from_exr(str(tmp_path / "cut.exr"))


def test_huge_coordinates_do_not_crash():
    """A camera so far away that float32 overflows gives finite emitter values or NaN, never a crash."""
    s, a = medium()
    cam = OrthographicCamera(origin=(1e30, 0, 0), target=(0, 0, 0), up=(0, 0, 1), extent_mm=(1e30, 1e30),
                             resolution=(2, 2))
    for emitter in (EnvironmentMap(torch.ones(3, 4, 3)), DiscLight((1, 0, 0), 10.0)):
        image = ta.render_scene(scene(sensor=cam, emitter=emitter), s, a, spp=2)
        assert image.shape == (2, 2, 3)
