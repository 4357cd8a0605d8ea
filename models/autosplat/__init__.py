"""clsplat.models.autosplat: AutoSplat (Khan et al., ICRA 2025), constrained per-scene
reconstruction of a driving sequence from cameras, LiDAR and tracked boxes.

One module per stage: :mod:`.init` (LiDAR background, labels, sky dome), :mod:`.background`
(phase losses, flatness), :mod:`.objects` (templates, mirror maps, residual SH), :mod:`.fusion`
(pose corrections), :mod:`.densify` (gsplat-style densification), :mod:`.model` (the scene),
:mod:`.trainer` (the staged loop, checkpoints, evaluation), :mod:`.presets`, :mod:`.cli`
(``clsplat train autosplat``) and :mod:`.demo` (``make demo``).
"""
from . import presets as _presets  # noqa: F401  (registers the presets under "autosplat")
