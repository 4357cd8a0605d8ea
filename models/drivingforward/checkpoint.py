"""DrivingForward models built for a preset or read back from a checkpoint (``clsplat train
drivingforward``'s, with the preset changes it stored): what the commands, the evaluation and
the viewer share."""
from __future__ import annotations

from ..common.presets import get_preset

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
    saved = ck.get("preset") or {}
    preset = get_preset(FAMILY, preset_name or saved.get("name", "?"))
    # a run's --pose / --set changes travel in the checkpoint; the registered preset's other
    # fields must match it
    import dataclasses
    fields = {f.name for f in dataclasses.fields(preset)}
    changed = {k: tuple(v) if isinstance(v, list) else v for k, v in saved.items()
               if k in fields and k != "name" and v != preset.to_dict().get(k)}
    if changed and (preset_name is None or preset_name == saved.get("name")):
        preset = preset.replace(**changed)
    load_checkpoint(path, FAMILY, preset)  # refuses a checkpoint of another preset
    model = build_model(preset, None, device)
    model.load_state_dict(ck["model"])
    return model, preset
