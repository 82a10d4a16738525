"""Print appearance optimisation (Nindel et al., TOG 2021; thesis part II) as a package.

* :mod:`.config`: :class:`PrintConfig`, the ink set it names, the run's seeds;
* :mod:`.slab_target`, :mod:`.object_target`: the two print targets, with the same methods (render, appearance,
  scores, naive baseline, quantised render, masks, outputs, views), so the loop never asks which it holds;
  :mod:`.target_images` the built-in and user target images; :mod:`.fixed_fractions` ``INK=FRACTION:MASK``;
* :mod:`.rendering`: how a target renders (a :class:`~torch_appearance.nn.SceneRenderer` per call, data-parallel
  under ``torch.distributed``) and the slab's scene;
* :mod:`.baselines`: naive extrusion, quantisation and the slab's quantised render; :mod:`.remap25d` the 2.5D
  remapped baseline's two halves (a UV-space slab target, a slab's weights wrapped onto the object);
* :mod:`.loop`: :func:`optimize_print`, :func:`build_target`, :func:`remap_baseline`;
* :mod:`.report`: the run folder's figures (:class:`matplotlib.figure.Figure`), :mod:`.object_figures` the
  object's views; :mod:`.run_folder` its files and scores;
* the command line is :mod:`torch_appearance.cli.optimize_print` (``ta-optimize-print``).
"""
from .config import PrintConfig, iteration_seed, load_inks
from .loop import build_target, optimize_print, remap_baseline
from .object_target import ObjectTarget
from .run_folder import LOG_FIELDS
from .slab_target import SlabTarget, slab_texel_grid
from .target_images import colorchecker_target, load_target, zebra_target

__all__ = ["PrintConfig", "optimize_print", "build_target", "remap_baseline", "SlabTarget", "ObjectTarget",
           "slab_texel_grid", "load_inks", "iteration_seed", "LOG_FIELDS", "load_target", "zebra_target",
           "colorchecker_target"]
