"""Looking at a reconstruction: ``clsplat view`` (a browser viewer on viser) and ``clsplat render``
(batch renders of a list of cameras).

* :mod:`.scene`: :class:`ViewScene`, what a viewer shows (Gaussians, recorded cameras with their
  images, trajectory, LiDAR, boxes, time-dependent objects), and reading one from an INRIA ``.ply``.
* :mod:`.cameras`: camera files (clsplat's JSON, INRIA's ``cameras.json``, nerfstudio's
  ``transforms.json``) -> :class:`~.scene.ViewCamera` lists.
* :mod:`.render`: the exact render of one camera through :func:`clsplat.rasterization`, and the
  batch renderer behind ``clsplat render``.
* :mod:`.server`: the viser server (needs the ``view`` extra).
* :mod:`.cli`: the ``view`` and ``render`` commands.

The engine never imports a model: checkpoints and run folders of the model families become a
:class:`ViewScene` through the readers registered in the ``clsplat.scene_readers`` entry-point
group (``clsplat.models.common.view`` registers this distribution's).
"""
from .scene import ViewCamera, ViewScene, scene_from_ply

__all__ = ["ViewCamera", "ViewScene", "scene_from_ply"]
