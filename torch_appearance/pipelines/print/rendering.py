"""How the print targets render: a :class:`~torch_appearance.nn.SceneRenderer` per call, its sensor elements split
over the ranks when the run is data-parallel (:mod:`torch_appearance.distributed`), and the slab's scene."""
import torch

from ... import distributed
from ...nn.mixture import mix_inks
from ...nn.renderer import SceneRenderer
from ...render import BoxBoundary, ConstantEnvironment, FaceTexels, Scene
from ...render.scene import derive_seed_grad
from ...render.volpath import render_scene, render_scene_indexed

__all__ = ["replay_seed", "render", "render_indexed", "ink_tables", "slab_scene", "on_device"]


def on_device(owner, device, name):
    """``owner.name`` (a tensor) on ``device``: the attribute itself where it is there already, else a copy made on
    first use and kept in ``owner`` (a target's references for the loss, copied once onto a run's GPU, not every
    iteration).

    Example:
        >>> class T: pass
        >>> t = T(); t.x = torch.ones(2)
        >>> on_device(t, torch.device("cpu"), "x") is t.x
        True
    """
    value = getattr(owner, name)
    device = torch.device(device)
    if value.device == device:
        return value
    copies = owner.__dict__.setdefault("_device_copies", {})
    key = (name, str(device))
    if key not in copies or copies[key][0] is not value:  # the attribute replaced since: copy it again
        copies[key] = (value, value.to(device))
    return copies[key][1]


def replay_seed(seed, gradient_seed):
    """The gradient replay's seed of an iteration's ``seed``: the forward's own (``gradient_seed="same"``, the
    replay retraces its paths) or an independent one (``"independent"``, :func:`derive_seed_grad`)."""
    return seed if gradient_seed == "same" else derive_seed_grad(seed)


def render(scene, sigma_t, albedo, *, spp, seed, seed_grad, grad_support=None, adjoint=None):
    """``SceneRenderer(scene, spp)(sigma_t, albedo, seed=seed, seed_grad=seed_grad)``: the sensor's linear RGB image,
    differentiable (only in the (D, H, W) ``grad_support`` when given). ``adjoint``: the image's gradient when known
    before the render (see :func:`~torch_appearance.render_scene`: one walk for the image and its gradient; a single
    process only). Under ``torch.distributed`` every rank traces its interleaved share of the sensor elements and
    the image and the gradients are summed over the ranks (the same image as one process)."""
    renderer = SceneRenderer(scene, spp=spp)
    if distributed.rank_and_world()[1] == 1:
        return renderer(sigma_t, albedo, seed=seed, seed_grad=seed_grad, grad_support=grad_support, adjoint=adjoint)
    return distributed.render(render_scene, renderer.scene, sigma_t=sigma_t, albedo=albedo, spp=renderer.spp, seed=seed,
                              seed_grad=seed_grad, chromatic=renderer.chromatic, grad_support=grad_support)


def ink_tables(inks, dtype=torch.float32):
    """(N, 3) σ_t and albedo tables of the inks as :func:`~torch_appearance.nn.mix_inks` gives them for a one-hot
    mixture (σ_s + σ_a and σ_s / σ_t rounded as in a mixture), so that a palette render of a quantised volume equals
    the render of its dense one-hot mixture bit for bit."""
    sigma_t, albedo = mix_inks(torch.eye(len(inks), dtype=dtype).view(len(inks), len(inks), 1, 1), inks)
    return sigma_t[:, :, 0, 0].t().contiguous(), albedo[:, :, 0, 0].t().contiguous()


def render_indexed(scene, index, inks, *, spp, seed):
    """The image of a quantised print: ``index`` (D, H, W) uint8 ink indices (< N) read by the tracer with the ink
    tables (:func:`~torch_appearance.render.render_scene_indexed`, 1 byte per voxel instead of 24 for dense σ_t and
    albedo); forward only, split over the ranks under ``torch.distributed``."""
    sigma_t_table, albedo_table = ink_tables(inks)
    with torch.no_grad():
        return distributed.render(render_scene_indexed, scene, torch.as_tensor(index), sigma_t_table, albedo_table,
                                  spp=spp, seed=seed)


def slab_scene(voxel_size, *, faces, g, ior):
    """The scene of a slab print: the grid box (a smooth dielectric of index ``ior``, None: index matched) under
    uniform white light, seen by the texels of its top face (``faces`` = 1) or of both faces (``faces`` = 2).

    Example:
        >>> slab_scene(0.0847, faces=2, g=0.4, ior=1.5).output_shape((12, 8, 6))
        (2, 8, 6, 3)
    """
    return Scene(voxel_size=voxel_size, boundary=BoxBoundary(ior), sensor=FaceTexels("both" if faces == 2 else "top"),
                 emitter=ConstantEnvironment(1.0), g=g)
