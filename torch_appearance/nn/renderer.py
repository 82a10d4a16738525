"""The renderer module: ``SceneRenderer`` holds a scene and its settings and a seed sequence,
``forward(sigma_t, albedo)`` renders through :func:`torch_appearance.render_scene`. ``SceneRenderer.slab`` (and
``VolumeRenderer``, the same as a class) is the renderer of a slab's face texels, as
:func:`torch_appearance.render_texels`."""
import torch

from ..checks import check_seed, check_spp
from ..render.scene import Scene, check_chromatic
from ..render.volpath import render_scene

__all__ = ["SceneRenderer", "VolumeRenderer", "GRADIENT_SEEDS"]

#: How a renderer picks the gradient replay's seed from the forward's: "independent" = :func:`derive_seed_grad`
#: (seed), the replay's paths independent of the forward's noise (render_scene's default); "same" = the seed itself,
#: the replay retraces the forward's own paths (render_texels' default).
GRADIENT_SEEDS = ("independent", "same")


class SceneRenderer(torch.nn.Module):
    """Renderer of a :class:`torch_appearance.render.Scene` with fixed settings (see
    :func:`torch_appearance.render_scene`).

    Each call uses the next seed (``seed``, ``seed + 1``, …) and, for the gradient replay, the seed derived from it
    (:func:`torch_appearance.render.derive_seed_grad`) or, with ``gradient_seed="same"``, the seed itself, so
    training steps see independent noise and a run stays reproducible. Pass ``seed=`` (and ``seed_grad=``) to
    ``forward`` to pin them. ``last_stats`` holds the stats of the last call (see render_scene).

    Args:
        scene: the scene (boundary, sensor, emitter, placement).
        spp: samples per sensor element.
        seed: first seed of the sequence.
        chromatic: "per_channel" or "hero", the estimator for chromatic media (see render_scene).
        gradient_seed: "independent" (default) or "same" (see :data:`GRADIENT_SEEDS`).

    Example:
        >>> import torch
        >>> from torch_appearance.render import Scene, BoxBoundary, OrthographicCamera
        >>> cam = OrthographicCamera(origin=(0.2, 0.2, 2), target=(0.2, 0.2, 0), up=(0, 1, 0),
        ...                          extent_mm=(0.4, 0.4), resolution=(4, 4))
        >>> renderer = SceneRenderer(Scene(voxel_size=0.1, boundary=BoxBoundary(1.5), sensor=cam), spp=4)
        >>> renderer(torch.full((3, 2, 4, 4), 5.0), torch.full((3, 2, 4, 4), 0.8)).shape
        torch.Size([4, 4, 3])
    """

    def __init__(self, scene, spp=16, seed=0, chromatic="per_channel", gradient_seed="independent"):
        super().__init__()
        if not isinstance(scene, Scene):
            raise TypeError(f"scene: expected a torch_appearance.render.Scene, got {type(scene).__name__}")
        if not isinstance(gradient_seed, str) or gradient_seed not in GRADIENT_SEEDS:
            raise ValueError(f"gradient_seed: expected one of {GRADIENT_SEEDS}, got {gradient_seed!r}")
        self.scene = scene
        self.spp = check_spp(spp)
        self.next_seed = check_seed("seed", seed)
        self.chromatic = check_chromatic(chromatic)
        self.gradient_seed = gradient_seed
        self.last_stats = {}

    @staticmethod
    def slab(voxel_size, *, face="top", g=0.4, ior=1.5, environment=1.0, spp=16, seed=0, max_depth=None,
             rr_depth=None, sigma_t_floor=None, albedo_floor=0.05, chromatic="per_channel", gradient_seed="same"):
        """The renderer of :func:`torch_appearance.render_texels`' slab (:meth:`Scene.slab`), its arguments with
        the same meaning; the gradient replay retraces each call's forward paths (``seed_grad = seed``), as
        render_texels does by default.

        Example:
            >>> import torch
            >>> renderer = SceneRenderer.slab(voxel_size=0.085, face="both", spp=8)
            >>> renderer(torch.full((3, 4, 8, 8), 10.0), torch.full((3, 4, 8, 8), 0.9)).shape
            torch.Size([2, 8, 8, 3])
        """
        scene = Scene.slab(voxel_size, face=face, g=g, ior=ior, environment=environment, max_depth=max_depth,
                           rr_depth=rr_depth, sigma_t_floor=sigma_t_floor, albedo_floor=albedo_floor)
        return SceneRenderer(scene, spp=spp, seed=seed, chromatic=chromatic, gradient_seed=gradient_seed)

    def forward(self, sigma_t, albedo, seed=None, seed_grad=None, sampling_sigma_t=None, sampling_albedo=None,
                grad_support=None, adjoint=None):
        """(3, D, H, W) σ_t [mm⁻¹] and albedo → the sensor's linear RGB image (see render_scene; ``grad_support``:
        the (D, H, W) voxels whose gradients are wanted; ``adjoint``: the image's gradient when known before the
        render, so that forward and backward share one walk)."""
        if seed is None:
            seed = self.next_seed
            self.next_seed += 1
        if seed_grad is None and self.gradient_seed == "same":
            seed_grad = seed  # else render_scene derives an independent one
        self.last_stats = {}
        return render_scene(self.scene, sigma_t, albedo, spp=self.spp, seed=seed, seed_grad=seed_grad,
                            sampling_sigma_t=sampling_sigma_t, sampling_albedo=sampling_albedo,
                            stats=self.last_stats, chromatic=self.chromatic, grad_support=grad_support,
                            adjoint=adjoint)

    def extra_repr(self):
        return (f"sensor={type(self.scene.sensor).__name__}, boundary={type(self.scene.boundary).__name__}, "
                f"emitter={type(self.scene.emitter).__name__}, spp={self.spp}, gradient_seed={self.gradient_seed}")


class VolumeRenderer(SceneRenderer):
    """Texel renderer of a voxel slab with fixed settings: :meth:`SceneRenderer.slab` as a class (see
    :func:`torch_appearance.render_texels`).

    Training loops should decorrelate steps: by default each call uses the next seed (``seed``, ``seed + 1``, …),
    so consecutive iterations see independent noise while a run stays reproducible, and its gradient replay
    retraces that call's forward paths (``seed_grad = seed``, as render_texels). Pass ``seed=`` to ``forward`` to
    pin one. ``last_stats`` holds the stats of the last call.

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
        scene = Scene.slab(voxel_size, face=face, g=g, ior=ior, environment=environment, max_depth=max_depth,
                           rr_depth=rr_depth, sigma_t_floor=sigma_t_floor, albedo_floor=albedo_floor)
        super().__init__(scene, spp=spp, seed=seed, chromatic=chromatic, gradient_seed="same")
