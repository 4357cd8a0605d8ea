"""Quaternion -> rotation matrix in torch: the one implementation the engine's reference, the
densification strategies and the models share (``clsplat.data.scene.quat_to_rotmat`` is the
numpy counterpart for the data layer, which has no torch dependency)."""
from __future__ import annotations

import torch
import torch.nn.functional as F

__all__ = ["quat_to_rotmat"]


def quat_to_rotmat(q: torch.Tensor) -> torch.Tensor:
    """``[..., 4]`` (w, x, y, z), any non-zero norm (normalised here) -> ``[..., 3, 3]``.

    Differentiable; the normalisation is ``F.normalize`` (a zero quaternion gives the zero
    matrix instead of NaN: callers that must refuse it check before, as ``clsplat.validate``
    does for ``rasterization``)."""
    w, x, y, z = F.normalize(q, dim=-1).unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1).reshape(*q.shape[:-1], 3, 3)
