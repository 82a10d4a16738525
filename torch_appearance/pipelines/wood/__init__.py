"""Wood appearance matching (thesis ch. 2) as a package: fit a procedural solid-wood texture to one board photo.

* :mod:`.config`: :class:`WoodFitConfig`; :mod:`.photo`: :func:`load_photo`;
* :mod:`.fit`: :func:`fit_wood` (ring detection and board estimate, the stages in turn, the run folder);
* :mod:`.geometry_stage` (stage 1, cyclic phase loss), :mod:`.colour_stage` (stage 2, colour map),
  :mod:`.photometric_stage` (stage 3, reparameterised colour fit);
* :mod:`.measures`: ring width, ring boundaries, latewood contrast, fit metrics;
* :mod:`.report`: the run folder's images and figures (:class:`matplotlib.figure.Figure`);
* the command line is :mod:`torch_appearance.cli.fit_wood` (``ta-fit-wood``), with the fit flags the wood commands share.
"""
from .colour_stage import match_luminance_histogram
from .config import LOG_FIELDS, WoodFitConfig
from .fit import fit_wood
from .geometry_stage import phase_loss, wrap
from .measures import boundary_lateness, effective_ring_width, fit_metrics, latewood_contrast, model_boundaries
from .photo import load_photo
from .photometric_stage import photometric_stage

__all__ = ["WoodFitConfig", "fit_wood", "load_photo", "phase_loss", "wrap", "effective_ring_width",
           "boundary_lateness", "model_boundaries", "LOG_FIELDS", "photometric_stage", "fit_metrics",
           "latewood_contrast", "match_luminance_histogram"]
