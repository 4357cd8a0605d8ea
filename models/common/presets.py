"""Presets: one frozen dataclass per model family, registered by name.

A preset holds every size and constant of a run (resolution, channels, loss weights, schedule).
It is printed in full at the start of a run (:meth:`Preset.describe`) and stored in every
checkpoint (:meth:`Preset.to_dict`); :func:`check_preset_matches` refuses a checkpoint made with
another preset. Families declare theirs as::

    @dataclass(frozen=True)
    class DFPreset(Preset):
        name: str
        height: int
        ...

    register("drivingforward", DFPreset(name="tiny", height=32, ...))
"""
from __future__ import annotations

import dataclasses
import json
from typing import Any

__all__ = ["Preset", "register", "get_preset", "preset_names", "check_preset_matches", "apply_sets",
           "preset_from_saved"]

_REGISTRY: dict[str, dict[str, "Preset"]] = {}  # family -> name -> preset (filled at import)


class Preset:
    """Mixin for ``@dataclass(frozen=True)`` presets; the first field must be ``name: str``.

    A class may map fields it renamed to their new names in ``RENAMED`` (a ClassVar): the preset
    record of a checkpoint written before the rename is read with the new names."""

    RENAMED: dict[str, str] = {}

    @classmethod
    def upgrade(cls, saved: dict) -> dict:
        """A checkpoint's preset record with renamed fields under their current names."""
        if not isinstance(saved, dict) or not cls.RENAMED:
            return saved
        return {cls.RENAMED.get(k, k): v for k, v in saved.items()}

    def to_dict(self) -> dict[str, Any]:
        """Every field as plain Python values (tuples become lists), for checkpoints and JSON."""
        return json.loads(json.dumps(dataclasses.asdict(self)))  # type: ignore[arg-type]

    def describe(self) -> str:
        """Every field, one per line, to print at the start of a run."""
        d = dataclasses.asdict(self)  # type: ignore[arg-type]
        w = max(map(len, d))
        lines = [f"preset {type(self).__name__}({d.get('name', '?')!r}):"]
        lines += [f"  {k:<{w}} = {v!r}" for k, v in d.items()]
        return "\n".join(lines)

    def replace(self, **changes: Any) -> "Preset":
        """A copy with some fields changed (unknown fields are a ValueError naming them)."""
        fields = {f.name for f in dataclasses.fields(self)}  # type: ignore[arg-type]
        bad = sorted(set(changes) - fields)
        if bad:
            raise ValueError(f"{type(self).__name__}: unknown fields {bad}; known: {sorted(fields)}")
        return dataclasses.replace(self, **changes)  # type: ignore[type-var]


def register(family: str, preset: Preset) -> Preset:
    """Add ``preset`` to ``family``'s registry under ``preset.name``; returns it."""
    if not dataclasses.is_dataclass(preset) or not getattr(preset, "__dataclass_params__").frozen:
        raise TypeError(f"register: {type(preset).__name__} must be a frozen dataclass")
    _REGISTRY.setdefault(family, {})[preset.name] = preset  # type: ignore[attr-defined]
    return preset


def preset_names(family: str) -> list[str]:
    """Names registered for ``family`` (importing the family's package registers them)."""
    return list(_registered(family))


def get_preset(family: str, name: str) -> Preset:
    """The preset ``name`` of ``family``; ValueError listing the known names otherwise."""
    known = _registered(family)
    if name not in known:
        raise ValueError(f"preset: unknown preset {name!r} for {family}; known: {sorted(known)}")
    return known[name]


def check_preset_matches(saved: dict, preset: Preset, where: str) -> None:
    """Raise ValueError if the preset stored in a checkpoint (``saved``) differs from ``preset``.

    Args:
        saved: the ``preset`` dict stored in the checkpoint.
        preset: the preset the caller runs with.
        where: the checkpoint path, for the message.
    """
    mine = preset.to_dict()
    if not isinstance(saved, dict):
        raise ValueError(f"{where}: checkpoint has no preset record")
    saved = type(preset).upgrade(saved)
    if saved == mine:
        return
    # a field added to the preset class after the checkpoint was written matches while it keeps
    # its default: the run that wrote the checkpoint behaved as that default does
    defaults = json.loads(json.dumps({f.name: f.default for f in dataclasses.fields(preset)  # type: ignore[arg-type]
                                      if f.default is not dataclasses.MISSING}))
    diff = sorted(k for k in set(saved) | set(mine) if saved.get(k) != mine.get(k)
                  and not (k not in saved and k in defaults and mine.get(k) == defaults[k]))
    if not diff:
        return
    shown = ", ".join(f"{k}: {saved.get(k)!r} != {mine.get(k)!r}" for k in diff[:5])
    more = ", ..." if len(diff) > 5 else ""
    if saved.get("name") == mine.get("name"):   # same name, other fields: --set changes, or an older code's
        raise ValueError(f"{where}: checkpoint's preset {mine.get('name')!r} differs from the one asked for "
                         f"(checkpoint != now: {shown}{more})")
    raise ValueError(f"{where}: checkpoint was made with preset {saved.get('name')!r}, not "
                     f"{mine.get('name')!r} ({shown}{more})")


def apply_sets(preset: Preset, sets: list[str] | None, **fields: Any) -> Preset:
    """``preset`` with every ``--set FIELD=VALUE`` (VALUE a Python literal) and every non-None
    keyword field applied; ValueError naming ``--set`` on an unknown field or a value of the wrong
    kind (an int is accepted where the default is a float; lists become tuples)."""
    import ast

    changes: dict[str, Any] = {k: v for k, v in fields.items() if v is not None}
    for item in sets or []:
        field, sep, text = item.partition("=")
        field = field.strip()
        if not sep or not field:
            raise ValueError(f"--set: expected FIELD=VALUE, got {item!r}")
        if field == "name":
            raise ValueError("--set: the preset's name cannot be changed")
        try:
            value = ast.literal_eval(text.strip())
        except (ValueError, SyntaxError):
            raise ValueError(f"--set {field}: {text!r} is not a Python literal (number, True/False, None, "
                             f"tuple, quoted string)") from None
        changes[field] = tuple(value) if isinstance(value, list) else value
    if not changes:
        return preset
    known = {f.name for f in dataclasses.fields(preset)}  # type: ignore[arg-type]
    bad = sorted(k for k in changes if k not in known)
    if bad:
        raise ValueError(f"--set: unknown preset fields {bad}; known: {sorted(known)}")
    for k, v in changes.items():
        d = getattr(preset, k)
        if d is not None and v is not None and not isinstance(v, type(d)) and not (
                isinstance(d, float) and isinstance(v, int) and not isinstance(v, bool)):
            raise ValueError(f"--set {k}: expected a {type(d).__name__} like {d!r}, got {v!r}")
        if isinstance(d, float) and isinstance(v, int):
            changes[k] = float(v)
    return preset.replace(**changes)


def preset_from_saved(family: str, saved: dict, name: str | None = None) -> Preset:
    """The preset a checkpoint was written with: its registered preset (or ``name``, when the
    caller expects one) with the fields its run changed (``--set``) applied. A field added to the
    preset class after the checkpoint was written takes the class default, which is how the run
    that wrote it behaved, even where the registered preset has since adopted another value."""
    if not isinstance(saved, dict):
        raise ValueError("checkpoint has no preset record")
    base = get_preset(family, name or saved.get("name", "?"))
    if name is not None and name != saved.get("name"):
        return base     # another preset: check_preset_matches names the difference
    saved = type(base).upgrade(saved)
    names = {f.name for f in dataclasses.fields(base)}  # type: ignore[arg-type]
    mine = base.to_dict()
    changes = {k: tuple(v) if isinstance(mine.get(k), list) and isinstance(v, list) else v
               for k, v in saved.items() if k in names and k != "name" and v != mine.get(k)}
    for f in dataclasses.fields(base):  # type: ignore[arg-type]
        if f.name not in saved and f.default is not dataclasses.MISSING and f.default != getattr(base, f.name):
            changes[f.name] = f.default
    return base.replace(**changes) if changes else base


def _registered(family: str) -> dict[str, Preset]:
    """``family``'s registered presets; ValueError for a family nothing registered (the family
    package registers its presets when it is imported: ``import clsplat.models.<family>``, or
    :mod:`clsplat.models.registry` for all of them)."""
    from .. import FAMILIES
    if family not in _REGISTRY:
        if family not in FAMILIES:
            raise ValueError(f"family: unknown model family {family!r}; known: {list(FAMILIES)}")
        raise ValueError(f"family: no {family} preset is registered yet; import clsplat.models.{family} first")
    return _REGISTRY[family]
