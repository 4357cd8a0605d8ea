"""DrivingForward models built for a preset or read back from a checkpoint (``clsplat train
drivingforward``'s, with the preset changes it stored): what the commands, the evaluation and
the viewer share."""
from __future__ import annotations

from ..common.presets import preset_from_saved

__all__ = ["FAMILY", "build_model", "load_model"]

FAMILY = "drivingforward"


def build_model(preset, weights=None, device=None):
    """A :class:`DrivingForward` for ``preset``; prints which backbone initialisation it used."""
    from .model import DrivingForward

    model = DrivingForward(preset, weights=weights, device=device)
    print(model.init_message, flush=True)
    return model


def load_model(path: str, device=None, preset_name: str | None = None):
    """(model, preset) from a checkpoint written by ``clsplat train drivingforward``."""
    from ..common.train import load_checkpoint

    ck = load_checkpoint(path, FAMILY)
    # a run's --pose / --set changes travel in the checkpoint; the registered preset's other
    # fields must match it
    preset = preset_from_saved(FAMILY, ck.get("preset"), preset_name)
    load_checkpoint(path, FAMILY, preset)  # refuses a checkpoint of another preset
    model = build_model(preset, None, device)
    model.load_state_dict(ck["model"])
    model.trained_steps = int(ck.get("step", 0))   # recorded in metrics.json by eval
    return model, preset
