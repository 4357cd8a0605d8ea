"""clsplat.models: driving-scene reconstruction networks that render through clsplat.

Families (one sub-package each): :mod:`.drivingforward` (feed-forward surround-view
reconstruction), :mod:`.pgt` (pixel-aligned Gaussian prediction with EcoSplat's budget) and
:mod:`.autosplat` (constrained per-scene optimisation). :mod:`.common` holds what every family
uses and nothing model-specific. Data flows one way: ``clsplat.data`` -> a model ->
:class:`~clsplat.models.common.gaussians.GaussianSet` -> ``clsplat.rasterization`` -> losses and
metrics. The engine never imports a model.
"""
FAMILIES: tuple[str, ...] = ("drivingforward", "pgt", "autosplat")
