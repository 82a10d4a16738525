"""``VolumeRenderer``: an ``nn.Module`` holding the tracer settings; ``forward(sigma_t, albedo)``."""
import torch

from ..render.scene import SlabScene
from ..render.volpath import render_texels

__all__ = ["VolumeRenderer"]


class VolumeRenderer(torch.nn.Module):
    """Texel renderer of a voxel slab with fixed settings (see :func:`torch_appearance.render_texels`).

    Training loops should decorrelate steps: by default each call uses the next seed (``seed``, ``seed + 1``, …),
    so consecutive iterations see independent noise while a run stays reproducible. Pass ``seed=`` to
    ``forward`` to pin one.

    Args:
        voxel_size: voxel edge in mm.
        face, g, ior, environment, spp, max_depth, rr_depth, sigma_t_floor, albedo_floor: as in render_texels.
        seed: first seed of the sequence.

    Example:
        >>> renderer = VolumeRenderer(voxel_size=0.085, face="both", spp=8)
        >>> image = renderer(sigma_t, albedo)   # (2, H, W, 3)
    """

    def __init__(self, voxel_size, face="top", g=0.4, ior=1.5, environment=1.0, spp=16, seed=0, max_depth=None,
                 rr_depth=None, sigma_t_floor=None, albedo_floor=0.05):
        super().__init__()
        self.kwargs = dict(voxel_size=voxel_size, face=face, g=g, ior=ior, environment=environment, spp=spp,
                           max_depth=max_depth, rr_depth=rr_depth, sigma_t_floor=sigma_t_floor,
                           albedo_floor=albedo_floor)
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
