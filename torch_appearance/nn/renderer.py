"""Renderer modules: ``VolumeRenderer`` (a slab's face texels) and ``SceneRenderer`` (any scene); each holds its
settings and a seed sequence, ``forward(sigma_t, albedo)`` renders."""
import torch

from ..render.checks import check_seed, check_spp
from ..render.scene import Scene, SlabScene, check_chromatic
from ..render.volpath import render_scene, render_texels

__all__ = ["VolumeRenderer", "SceneRenderer"]


class VolumeRenderer(torch.nn.Module):
    """Texel renderer of a voxel slab with fixed settings (see :func:`torch_appearance.render_texels`).

    Training loops should decorrelate steps: by default each call uses the next seed (``seed``, ``seed + 1``, …),
    so consecutive iterations see independent noise while a run stays reproducible. Pass ``seed=`` to
    ``forward`` to pin one.

    Args:
        voxel_size: voxel edge in mm.
        face, g, ior, environment, spp, max_depth, rr_depth, sigma_t_floor, albedo_floor, chromatic: as in
            render_texels.
        seed: first seed of the sequence.

    Example:
        >>> import torch
        >>> renderer = VolumeRenderer(voxel_size=0.085, face="both", spp=8)
        >>> renderer(torch.full((3, 4, 8, 8), 10.0), torch.full((3, 4, 8, 8), 0.9)).shape
        torch.Size([2, 8, 8, 3])
    """

    def __init__(self, voxel_size, face="top", g=0.4, ior=1.5, environment=1.0, spp=16, seed=0, max_depth=None,
                 rr_depth=None, sigma_t_floor=None, albedo_floor=0.05, chromatic="per_channel"):
        super().__init__()
        self.kwargs = dict(voxel_size=voxel_size, face=face, g=g, ior=ior, environment=environment, spp=spp,
                           max_depth=max_depth, rr_depth=rr_depth, sigma_t_floor=sigma_t_floor,
                           albedo_floor=albedo_floor, chromatic=chromatic)
        SlabScene.create(seed=seed, **self.kwargs)  # validate now, not at the first forward
        self.next_seed = int(seed)
        self.last_stats = {}

    def forward(self, sigma_t, albedo, seed=None, sampling_sigma_t=None, sampling_albedo=None):
        """(3, D, H, W) σ_t [mm⁻¹] and albedo → (H, W, 3) or (2, H, W, 3) linear RGB texel radiance."""
        if seed is None:
            seed = self.next_seed
            self.next_seed += 1
        self.last_stats = {}
        return render_texels(sigma_t, albedo, seed=seed, sampling_sigma_t=sampling_sigma_t,
                             sampling_albedo=sampling_albedo, stats=self.last_stats, **self.kwargs)

    def extra_repr(self):
        return ", ".join(f"{k}={v}" for k, v in self.kwargs.items() if v is not None)


class SceneRenderer(torch.nn.Module):
    """Renderer of a :class:`torch_appearance.render.Scene` with fixed settings (see
    :func:`torch_appearance.render_scene`).

    Each call uses the next seed (``seed``, ``seed + 1``, …) and, for the gradient replay, the seed derived from it
    (:func:`torch_appearance.render.derive_seed_grad`), so training steps see independent noise and a run stays
    reproducible. Pass ``seed=`` (and ``seed_grad=``) to ``forward`` to pin them.

    Args:
        scene: the scene (boundary, sensor, emitter, placement).
        spp: samples per sensor element.
        seed: first seed of the sequence.
        chromatic: "per_channel" or "hero", the estimator for chromatic media (see render_scene).

    Example:
        >>> import torch
        >>> from torch_appearance.render import Scene, BoxBoundary, OrthographicCamera
        >>> cam = OrthographicCamera(origin=(0.2, 0.2, 2), target=(0.2, 0.2, 0), up=(0, 1, 0),
        ...                          extent_mm=(0.4, 0.4), resolution=(4, 4))
        >>> renderer = SceneRenderer(Scene(voxel_size=0.1, boundary=BoxBoundary(1.5), sensor=cam), spp=4)
        >>> renderer(torch.full((3, 2, 4, 4), 5.0), torch.full((3, 2, 4, 4), 0.8)).shape
        torch.Size([4, 4, 3])
    """

    def __init__(self, scene, spp=16, seed=0, chromatic="per_channel"):
        super().__init__()
        if not isinstance(scene, Scene):
            raise TypeError(f"scene: expected a torch_appearance.render.Scene, got {type(scene).__name__}")
        self.scene = scene
        self.spp = check_spp(spp)
        self.next_seed = check_seed("seed", seed)
        self.chromatic = check_chromatic(chromatic)
        self.last_stats = {}

    def forward(self, sigma_t, albedo, seed=None, seed_grad=None, sampling_sigma_t=None, sampling_albedo=None):
        """(3, D, H, W) σ_t [mm⁻¹] and albedo → the sensor's linear RGB image (see render_scene)."""
        if seed is None:
            seed = self.next_seed
            self.next_seed += 1
        self.last_stats = {}
        return render_scene(self.scene, sigma_t, albedo, spp=self.spp, seed=seed, seed_grad=seed_grad,
                            sampling_sigma_t=sampling_sigma_t, sampling_albedo=sampling_albedo,
                            stats=self.last_stats, chromatic=self.chromatic)

    def extra_repr(self):
        return (f"sensor={type(self.scene.sensor).__name__}, boundary={type(self.scene.boundary).__name__}, "
                f"emitter={type(self.scene.emitter).__name__}, spp={self.spp}")
