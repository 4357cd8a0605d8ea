"""The model families by name: what ``clsplat train|eval FAMILY`` and ``clsplat view RUN`` reach
them through.

:data:`REGISTRY` maps each name of :data:`clsplat.models.FAMILIES` to the family's
:class:`~clsplat.models.common.command.Family` (its ``cli.COMMANDS``), imported by name here and
nowhere else: :mod:`clsplat.models.common` never imports a family, a family never imports
another, and this module sits above them all. Importing it imports the three families' command
modules (and registers their presets).
"""
from __future__ import annotations

import sys
from pathlib import Path

from . import FAMILIES
from .autosplat.cli import COMMANDS as _AUTOSPLAT
from .common.command import Family, eval_main, restore, train_main
from .drivingforward.cli import COMMANDS as _DRIVINGFORWARD
from .pgt.cli import COMMANDS as _PGT

__all__ = ["REGISTRY", "family", "train_command", "eval_command", "scene_from_checkpoint"]

REGISTRY: dict[str, Family] = {f.name: f for f in (_DRIVINGFORWARD, _PGT, _AUTOSPLAT)}
assert tuple(REGISTRY) == FAMILIES, "clsplat.models.FAMILIES and the registry list the same families"


def family(name: str, arg: str = "family") -> Family:
    """The family called ``name``; ValueError naming ``arg`` for an unknown one."""
    if name not in REGISTRY:
        raise ValueError(f"{arg}: unknown model family {name!r}; known: {', '.join(REGISTRY)}")
    return REGISTRY[name]


def _dispatch(command: str, argv: list[str]) -> int:
    usage = f"usage: clsplat {command} {{{','.join(REGISTRY)}}} [options]   (--help after the family for its options)"
    if not argv or argv[0] in ("-h", "--help"):
        print(usage)
        return 0 if argv else 2
    if argv[0] not in REGISTRY:
        print(f"clsplat {command}: unknown model family {argv[0]!r}; known: {', '.join(REGISTRY)}", file=sys.stderr)
        return 2
    run = train_main if command == "train" else eval_main
    return run(REGISTRY[argv[0]], argv[1:])


def train_command(argv: list[str]) -> int:
    """train a model: clsplat train {drivingforward,pgt,autosplat} --help"""
    return _dispatch("train", argv)


def eval_command(argv: list[str]) -> int:
    """evaluate a trained model: clsplat eval {drivingforward,pgt,autosplat} --help"""
    return _dispatch("eval", argv)


def scene_from_checkpoint(path: str | Path, data: str | None = None, device=None, sample: int = 0,
                          trust_pickle: bool = False):
    """The :class:`~clsplat.viewer.scene.ViewScene` of a checkpoint file or run folder (the
    engine's ``clsplat.scene_readers`` entry point, for ``clsplat view`` / ``clsplat render``):

    * AutoSplat (a per-scene optimisation): the model is rebuilt from the checkpoint and the run's
      data (``metrics.json``'s ``data`` and ``scale``, else ``data``), and the scene carries the
      recording's cameras with their images, the ego trajectory, the LiDAR points, the tracked
      boxes and a time slider that places the moving objects (with their residual SH) at each frame.
    * DrivingForward and PGT (feed-forward): the network runs on held-out sample ``sample`` of
      ``data`` (default: the run's, where its ``metrics.json`` records it, else synthetic); the
      scene is its predicted Gaussians with the input cameras (and their images) and the
      predicted depth maps, built in eval mode with the RNG restored
      (:func:`~clsplat.models.common.view.model_snapshot`), as ``clsplat train FAMILY --view``
      shows a model as it trains.
    * A run folder without a checkpoint but with ``scene.ply`` shows the ``.ply``.

    ``trust_pickle`` (``--trust-pickle``) unpickles ``data``'s PandaSet files without the
    allow-list. Every failure is a ValueError naming PATH (unknown family, not a checkpoint,
    mismatched data) or ``--sample``."""
    from clsplat.viewer.scene import scene_from_ply

    from .common.runfolder import STAGING
    from .common.train import load_checkpoint

    p = Path(path)
    run = p if p.is_dir() else p.parent
    ck_path = p
    if p.is_dir():  # a finished run's checkpoint, else an unfinished one's, else the run's .ply
        found = [c for c in (p / "checkpoint.pt", p / STAGING / "checkpoint.pt") if c.is_file()]
        if not found:
            if (p / "scene.ply").is_file():
                return scene_from_ply(p / "scene.ply")
            raise ValueError(f"PATH {str(path)!r}: a folder without checkpoint.pt (finished or in {STAGING}/) or "
                             "scene.ply; expected an INRIA .ply, a checkpoint.pt written by clsplat train, or a run "
                             "folder holding one")
        ck_path = found[0]
        run = ck_path.parent
    try:
        ck = load_checkpoint(ck_path)
    except ValueError as e:
        raise ValueError(f"PATH {str(path)!r} is not a scene: {e}; expected an INRIA .ply, a checkpoint.pt "
                         "written by clsplat train, or a run folder holding one") from None
    if ck.get("family") not in REGISTRY:
        raise ValueError(f"PATH {str(path)!r}: a checkpoint of an unknown model family {ck.get('family')!r}; "
                         f"known: {', '.join(REGISTRY)}")
    fam = REGISTRY[ck["family"]]
    if not isinstance(sample, int) or sample < 0:
        raise ValueError(f"--sample: expected an integer >= 0, got {sample!r}")
    restored = restore(fam, ck_path, device, checkpoint=ck, data=data, safe_pickle=not trust_pickle)
    return fam.checkpoint_scene(restored, run, data, sample=sample, safe_pickle=not trust_pickle)
