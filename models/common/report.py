"""``metrics.json``: the one schema every family's evaluation writes (``clsplat train|eval FAMILY``).

Layout (``METRICS_SCHEMA`` = 1)::

    {
      "schema": 1,
      "family": "drivingforward" | "pgt" | "autosplat",
      "preset": "small",
      "step": 1000,                       # training steps behind the numbers
      "protocol": {                       # what was measured, how: enough to reproduce it
        "data": "synthetic", "split": "test", "images": 12, "cameras": [...],
        "psnr": PSNR_PROTOCOL, "ssim": SSIM_PROTOCOL, "lpips": "on" | "off (...)", ...
      },
      "all": {"psnr": ..., "ssim": ..., ["lpips"], [depth: "abs_rel", "sq_rel", "rmse", "delta1",
              "scale_ratio"], ...},      # over every evaluated image
      "per_camera": {"CAM_FRONT": {"psnr": ..., "ssim": ..., ...}, ...},
      ...                                 # family sections (AutoSplat "train", "lane_change", ...)
    }

The same key means the same quantity in every family: ``psnr`` is the mean over images of
per-image PSNR (dB, both images clipped to [0, 1]), ``ssim`` the mean over images of SSIM (11-px
Gaussian window, 'valid' padding), ``lpips`` present only when LPIPS weights were given; depth
keys as :func:`~.metrics.depth_metrics` defines them. The file is written atomically.
"""
from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from clsplat.io.atomic import write_text_atomic

from .metrics import psnr, ssim

__all__ = ["METRICS_SCHEMA", "PSNR_PROTOCOL", "SSIM_PROTOCOL", "REQUIRED_KEYS", "image_scores", "mean_scores",
           "camera_blocks", "metrics_report", "check_report", "write_metrics"]

METRICS_SCHEMA = 1
PSNR_PROTOCOL = "mean over images of per-image PSNR in dB (both images clipped to [0, 1])"
SSIM_PROTOCOL = "mean over images of SSIM (11-px Gaussian window, sigma 1.5, 'valid' padding)"
#: the keys every metrics.json has at the top level, and in "all" and each "per_camera" entry
REQUIRED_KEYS = ("schema", "family", "preset", "step", "protocol", "all", "per_camera")
IMAGE_KEYS = ("psnr", "ssim")


def image_scores(pred: Tensor, target: Tensor, lpips=None) -> dict[str, Tensor]:
    """Per-image scores of ``pred``/``target`` ``[N, 3, H, W]``: ``{"psnr": [N], "ssim": [N],
    ["lpips": [N]]}``."""
    out = {"psnr": psnr(pred, target).double(), "ssim": ssim(pred, target).double()}
    if lpips is not None:
        out["lpips"] = lpips(pred, target).reshape(-1).double()
    return out


def mean_scores(scores: Mapping[str, Tensor], select: Tensor | slice | None = None) -> dict[str, float]:
    """The mean of each per-image score over ``select`` (default every image)."""
    sel = slice(None) if select is None else select
    return {k: float(v[sel].mean()) for k, v in scores.items()}


def camera_blocks(scores: Mapping[str, Tensor], cameras: Sequence[str]) -> tuple[dict, dict]:
    """``(all, per_camera)`` from per-image scores whose image ``i`` was seen by ``cameras[i]``."""
    if any(len(v) != len(cameras) for v in scores.values()):
        raise ValueError(f"cameras: expected one name per scored image ({len(next(iter(scores.values())))}), "
                         f"got {len(cameras)}")
    per_camera = {}
    for name in dict.fromkeys(cameras):
        idx = torch.tensor([i for i, c in enumerate(cameras) if c == name])
        per_camera[name] = mean_scores(scores, idx)
    return mean_scores(scores), per_camera


def metrics_report(family: str, preset: str, step: int, protocol: Mapping[str, Any], all: Mapping[str, Any],
                   per_camera: Mapping[str, Mapping[str, Any]], **sections: Any) -> dict:
    """A ``metrics.json`` dict in the schema above (``protocol`` gains the PSNR/SSIM definitions)."""
    report = {"schema": METRICS_SCHEMA, "family": family, "preset": preset, "step": int(step),
              "protocol": {"psnr": PSNR_PROTOCOL, "ssim": SSIM_PROTOCOL, **protocol},
              "all": dict(all), "per_camera": {k: dict(v) for k, v in per_camera.items()}, **sections}
    check_report(report)
    return report


def check_report(report: Mapping[str, Any]) -> None:
    """ValueError naming what a ``metrics.json`` dict lacks against the schema."""
    missing = [k for k in REQUIRED_KEYS if k not in report]
    if missing:
        raise ValueError(f"metrics.json: missing keys {missing}")
    for where, block in [("all", report["all"]), *((f"per_camera.{k}", v) for k, v in report["per_camera"].items())]:
        lack = [k for k in IMAGE_KEYS if k not in block]
        if lack:
            raise ValueError(f"metrics.json: {where} lacks {lack}")


def write_metrics(out_dir: str | Path, report: Mapping[str, Any], name: str = "metrics.json") -> Path:
    """Write ``report`` as ``out_dir/name`` atomically (a reader never sees half a file)."""
    check_report(report)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    return write_text_atomic(out / name, json.dumps(report, indent=2, default=float))
