"""One way into the tracer: render_texels is render_scene of the slab scene with seed_grad = seed, the renderer
modules are render_scene with a seed sequence, and one TraceJob builds the C++ options. The package itself loads
them on first use (``import torch_appearance`` imports only the standard library)."""
import subprocess
import sys

import pytest
import torch

import torch_appearance as ta
from torch_appearance.nn import SceneRenderer, VolumeRenderer
from torch_appearance.render import Scene, TraceJob, derive_seed_grad


def _medium(chromatic=True, seed=0):
    g = torch.Generator().manual_seed(seed)
    sigma_t = 2.0 + 10.0 * torch.rand(3 if chromatic else 1, 3, 5, 4, generator=g, dtype=torch.float64)
    sigma_t = sigma_t.expand(3, -1, -1, -1).contiguous().requires_grad_()
    albedo = (0.3 + 0.65 * torch.rand(3, 3, 5, 4, generator=g, dtype=torch.float64)).requires_grad_()
    return sigma_t, albedo


def _image_and_grads(render, sigma_t, albedo):
    sigma_t.grad = albedo.grad = None
    image = render(sigma_t, albedo)
    w = torch.linspace(0.5, 1.5, image.numel(), dtype=image.dtype).view_as(image)
    (image * w).sum().backward()
    return image.detach(), sigma_t.grad.clone(), albedo.grad.clone()


@pytest.mark.parametrize("kw", [
    dict(),
    dict(face="both", ior=None, environment=(1.0, 0.5, 0.25), g=-0.2, chromatic="hero", partition=(1, 2)),
    dict(face="bottom", ior=1.33, seed_grad=17, max_depth=40, rr_depth=3, sigma_t_floor=1.0, albedo_floor=0.2),
])
def test_render_texels_is_render_scene_of_the_slab(kw):
    sigma_t, albedo = _medium()
    kw = dict(kw)
    scene_kw = {k: kw.pop(k) for k in ("face", "ior", "environment", "g", "max_depth", "rr_depth", "sigma_t_floor",
                                       "albedo_floor") if k in kw}
    texels = _image_and_grads(lambda s, a: ta.render_texels(s, a, voxel_size=0.1, spp=3, seed=5, **scene_kw, **kw),
                              sigma_t, albedo)
    kw.setdefault("seed_grad", 5)  # render_texels' documented default: the forward's own seed
    scene = _image_and_grads(lambda s, a: ta.render_scene(Scene.slab(0.1, **scene_kw), s, a, spp=3, seed=5, **kw),
                             sigma_t, albedo)
    for x, y in zip(texels, scene):
        assert torch.equal(x, y)


def test_volume_renderer_steps_the_seed_and_replays_its_own_paths():
    sigma_t, albedo = _medium()
    renderer = VolumeRenderer(voxel_size=0.1, face="both", spp=2, seed=7)
    slab = SceneRenderer.slab(0.1, face="both", spp=2, seed=7)
    for seed in (7, 8):
        got = _image_and_grads(renderer, sigma_t, albedo)
        assert set(renderer.last_stats) >= {"forward_s", "scatter_events", "backward_s"}
        want = _image_and_grads(lambda s, a: ta.render_texels(s, a, voxel_size=0.1, face="both", spp=2, seed=seed),
                                sigma_t, albedo)
        same = _image_and_grads(slab, sigma_t, albedo)
        for x, y, z in zip(got, want, same):
            assert torch.equal(x, y) and torch.equal(x, z)
    assert renderer.next_seed == slab.next_seed == 9 and isinstance(renderer, SceneRenderer)


def test_scene_renderer_replays_independent_paths_by_default():
    sigma_t, albedo = _medium(chromatic=False)
    scene = Scene.slab(0.1)
    got = _image_and_grads(SceneRenderer(scene, spp=2, seed=3), sigma_t, albedo)
    want = _image_and_grads(lambda s, a: ta.render_scene(scene, s, a, spp=2, seed=3, seed_grad=derive_seed_grad(3)),
                            sigma_t, albedo)
    for x, y in zip(got, want):
        assert torch.equal(x, y)


def test_trace_job_builds_the_options():
    job = TraceJob(Scene.slab((0.1, 0.2, 0.3), face="bottom", ior=None, max_depth=9), spp=5, seed=2 ** 64 - 1,
                   seed_grad=4, chromatic="hero", partition=(2, 3))
    opt = job.scene_options(1, job.seed, (2, 3, 4), torch.float32)
    assert (opt.spp, opt.seed, opt.max_depth, opt.part_rank, opt.part_world) == (5, -1, 9, 2, 3)
    assert opt.voxel_size == pytest.approx([0.1, 0.2, 0.3]) and opt.sensor.face == 1 and opt.boundary.ior == -1.0
    assert job.seed_grad == 4 and TraceJob(job.scene, seed=4).seed_grad == derive_seed_grad(4)
    whole = TraceJob(job.scene, partition=(0, 1)).scene_options(3, 0, (2, 3, 4), torch.float32)
    assert (whole.part_rank, whole.part_world) == (0, 1)
    with pytest.raises(AttributeError):
        job.spp = 1  # frozen


def test_the_package_loads_its_names_on_first_use():
    """``ta.render_scene``, ``from torch_appearance import render_texels``, ``ta.nn.X`` and ``ta._C`` are the
    package's pieces, loaded when first used; an unknown name is an AttributeError."""
    import torch_appearance.render
    from torch_appearance import _C, render_texels  # noqa: F401

    assert ta.render_scene is torch_appearance.render.render_scene and render_texels is ta.render.render_texels
    assert ta.nn.SceneRenderer is SceneRenderer and ta._C is _C and ta._C is torch_appearance._ext._C
    assert set(ta.__all__) <= set(dir(ta)) and "_C" in dir(ta)
    with pytest.raises(AttributeError, match="'torch_appearance' has no attribute 'render_scenes'"):
        ta.render_scenes


def test_a_missing_build_is_refused_on_first_use_with_the_fix():
    """In a fresh interpreter whose extension does not load: ``import torch_appearance`` loads nothing (no torch),
    and the first use of a name raises the ImportError that says how to build."""
    code = """
import sys
class NoExtension:
    def find_spec(self, name, path=None, target=None):
        if name == "torch_appearance._C":
            raise ImportError("no such file (made by the test)")
sys.meta_path.insert(0, NoExtension())
import torch_appearance as ta
print("torch" in sys.modules)
try:
    ta.render_scene
except ImportError as error:
    print(error)
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    loaded, message = out.stdout.splitlines()
    assert loaded == "False", out.stdout
    assert message.startswith("torch_appearance: the C++ extension torch_appearance._C is missing or does not load "
                              "(no such file (made by the test)). Build it from the repository root with `make build`"), \
        message
