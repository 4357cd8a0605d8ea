"""The pose source "geometric": a window's rig motion measured from its own images (issue 32).

No learning and no ground truth. :func:`~.ground_motion.fit_ground_motion_direct` aligns frame t
with frames t-1 and t+1 of every camera at once, on the pixels where the calibration's ground
plane (intrinsics, extrinsics, the ego frame standing on the road: the named prior of
:func:`~.depth.ground_prior_depth`) lies within the preset's ``ground_prior_cap`` (20 m without one).
It reads the frames at ``geometric_size``: at ``small``'s 64x112 a road pixel 10 m ahead covers
~0.8 m and the road's texture carries no motion, while at 176x320 the fit measured validation
windows to a median of 1-3 % per moving speed bin (bench/notes/drivingforward_varied_world.md, "A
geometric pose from the road's flow"). Its motions replace the pose network's in the temporal
warps and the render, as the data's own do under "dataset"; the pose network is not trained.

The fit's forward-translation search spans ``+- geometric_max_speed x`` the frame interval (the
sample's timestamps) in ``geometric_search`` steps: a generic bound on a car's motion, not the data's.
``geometric_keep`` < 1 makes the search's cost least-trimmed (the lowest share of the ground pixels'
residuals): without it a crawling window (0.6-1.2 m/s) reads as standing, since the pixels the
plane wrongly claims (cars, kerbs) cost more at the true motion than the road gains.

A window read from a street cache (``synthetic-cache:DIR``) keeps its fitted motions beside the
street (``DIR/geometric/``, keyed by the street's file, the cameras, the fit's preset fields and this
code): the fit is a function of the images alone, it takes ~5 CPU s a window against ~1.4 s for a
training step, and runs of other seeds draw the same streets (street = run seed + index).

Like the ground prior, the fit needs the ego frame standing on the road (z = 0 the ground, z up):
with a frame elsewhere (real PandaSet's roof LiDAR) its plane, and so its motion's scale, is wrong.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import math
from pathlib import Path
from typing import Sequence

import torch
from torch import Tensor

from .data import load_triplet
from .ground_motion import fit_ground_motion_direct

__all__ = ["GROUND_CAP_DEFAULT", "geometric_size", "window_motions", "load_window_motions"]

#: metres of ground the fit reads when the preset has no ground_prior_cap (the probe's setting)
GROUND_CAP_DEFAULT = 20.0
#: yaw values the fit tries when the preset's ``geometric_max_yaw_rate`` > 0
YAW_SEARCH = 41


def geometric_size(preset) -> tuple[int, int]:
    """``(H, W)`` of the images the fit reads: the preset's ``geometric_size``, else its own size."""
    return tuple(preset.geometric_size) if preset.geometric_size is not None else (preset.height, preset.width)


def window_motions(sample: dict, preset, true_depth: bool = False) -> list[Tensor]:
    """The rig's motion from frame t to t-1 and to t+1 of a triplet, from its images.

    Args:
        sample: :func:`~.data.load_triplet`'s dict (``images [3, V, 3, H, W]``, ``Ks``,
            ``cam_to_ego``, ``timestamps [3]``), at any size.
        preset: gives ``ground_prior_cap``, ``geometric_search``, ``geometric_max_speed``,
            ``geometric_keep``, ``geometric_max_yaw_rate``.
        true_depth: place the ground pixels with the sample's own depth of frame t (``depths``)
            instead of the calibrated plane: a probe's upper bound, never a run's pose.
    Returns:
        ``[M_{t->t-1}, M_{t->t+1}]``, each ``[4, 4]`` in the images' dtype: ego coordinates at t to
        ego coordinates at the other frame (:func:`~.data.gt_ego_motion`'s convention).
    """
    if true_depth and "depths" not in sample:
        raise ValueError("true_depth: the data has no depth maps (the generator's streets have; recordings do not)")
    images, ts = sample["images"], sample["timestamps"].double()
    cap = preset.ground_prior_cap if preset.ground_prior_cap is not None else GROUND_CAP_DEFAULT
    E = sample["cam_to_ego"].double()
    out = []
    for other in (0, 2):
        dt = abs(float(ts[other] - ts[1]))
        if not dt > 0:
            raise ValueError(f"timestamps: frames t-1, t, t+1 must have distinct times, got {ts.tolist()}")
        bound = preset.geometric_max_speed * dt
        yaw = math.radians(float(preset.geometric_max_yaw_rate)) * dt
        M = fit_ground_motion_direct(images[1], images[other], sample["Ks"], E, cap,
                                     search=(-bound, bound, preset.geometric_search),
                                     yaw_search=(-yaw, yaw, YAW_SEARCH) if yaw > 0 else None,
                                     keep=float(preset.geometric_keep),
                                     depth=_finite_depth(sample["depths"][1][:, None]) if true_depth else None)
        out.append(M.to(images.dtype))
    return out


def _finite_depth(d: Tensor) -> Tensor:
    """A depth map with its sky (infinite, or 0 where nothing was hit) set far: the fit reads only
    the ground prior's pixels, which are never sky, but checks the whole map."""
    far = torch.full_like(d, 1e4)
    return torch.where(torch.isfinite(d) & (d > 0), d, far)


def load_window_motions(source, index: int, preset, split: str = "train", cameras: Sequence[str] | None = None,
                        sample: dict | None = None, true_depth: bool = False) -> list[Tensor]:
    """:func:`window_motions` of window ``index``, its frames read at :func:`geometric_size`.

    ``sample``: the window already loaded at the preset's size, reused when that is the fit's size
    (else the window is read again at the fit's size: a synthetic street is rendered there).
    """
    size = geometric_size(preset)
    if sample is None or size != (preset.height, preset.width):
        sample = load_triplet(source, index, dataclasses.replace(preset, height=size[0], width=size[1]),
                              split, cameras)
    path = None if true_depth or not sample.get("street_file") else _fit_path(sample, preset)
    if path is not None:
        kept = _read_fits(path, sample["images"].dtype)
        if kept is not None:
            return kept
    out = window_motions(sample, preset, true_depth)
    if path is not None:
        from clsplat.io.atomic import atomic_write
        try:
            path.parent.mkdir(exist_ok=True)
            atomic_write(path, lambda tmp: torch.save(out, tmp))
        except OSError:                 # (a read-only or full cache: the motions are the same, only not kept)
            pass
    return out


#: the fit's preset fields: a kept motion is reused only where all of them are the same
_FIT_FIELDS = ("geometric_size", "ground_prior_cap", "geometric_search", "geometric_max_speed",
               "geometric_keep", "geometric_max_yaw_rate")


def _code_fingerprint() -> str:
    """The fit's code (this module and :mod:`.ground_motion`): a kept motion of other code is not reused."""
    from . import ground_motion
    h = hashlib.sha256()
    for mod_file in (__file__, ground_motion.__file__):
        h.update(Path(mod_file).read_bytes())
    return h.hexdigest()[:16]


def _fit_path(sample: dict, preset) -> Path:
    """Where the fitted motions of a street-cache window are kept: ``<cache>/geometric/<key>.pt``."""
    street = Path(sample["street_file"])
    blob = json.dumps({"street": street.name, "cameras": list(sample["names"]), "code": _code_fingerprint(),
                       **{f: getattr(preset, f) for f in _FIT_FIELDS}}, sort_keys=True, default=list)
    return street.parent / "geometric" / f"{street.stem}-{hashlib.sha256(blob.encode()).hexdigest()[:16]}.pt"


def _read_fits(path: Path, dtype: torch.dtype) -> list[Tensor] | None:
    """The kept motions at ``path``, or None when absent or unreadable (then fitted again and rewritten)."""
    if not path.is_file():
        return None
    try:
        got = torch.load(path, weights_only=True)
    except Exception:                   # (a damaged or foreign file: a miss, never an error)
        return None
    ok = isinstance(got, list) and len(got) == 2 and all(
        isinstance(m, Tensor) and m.shape == (4, 4) and m.dtype == dtype and bool(torch.isfinite(m).all()) for m in got)
    return got if ok else None
