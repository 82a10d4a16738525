"""The ``ta-…`` commands (installed as console scripts by setup.cfg); each module has ``main(argv=None) -> int``, and
:mod:`.entry` the console scripts' entry points. This package imports nothing (the entry points must start before
torch loads); ``python -m torch_appearance.cli.NAME`` runs a command too, with the differences :mod:`.entry` names.

=========================  ============================================================================
command                    what it does
=========================  ============================================================================
``ta-voxelize``            a textured mesh → voxel object (occupancy, SDF band, texels), previews
``ta-render-object``       a built-in translucent SDF object rendered by the tracer
``ta-render-wood-volume``  a fitted wood model as a translucent volume (veneer, lamp shade)
``ta-detect-rings``        tree-ring boundaries on a core, a transect, a disc or a section
``ta-eval-rings``          detected ring boundaries against labels (precision, recall, F1)
=========================  ============================================================================
"""
