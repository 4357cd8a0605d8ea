"""The base class of the densification strategies: gsplat's callbacks and the sanity check of
parameters against optimizers."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Dict

import torch

from .ops import Params

__all__ = ["Strategy"]


@dataclass
class Strategy:
    """Base class: a densification strategy with gsplat's callbacks."""

    def check_sanity(self, params: Params, optimizers: Dict[str, torch.optim.Optimizer]) -> None:
        """Trainable parameters and optimizers must match one to one, one param group each,
        and means, scales, quats, opacities must be present."""
        trainable = {k for k, p in params.items() if p.requires_grad}
        if trainable != set(optimizers):
            raise ValueError(f"optimizers: keys {sorted(optimizers)} must equal the trainable "
                             f"parameters {sorted(trainable)}")
        for k, opt in optimizers.items():
            if len(opt.param_groups) != 1:
                raise ValueError(f"optimizers: {k!r} must have exactly one param group, got "
                                 f"{len(opt.param_groups)}")
        for k in ("means", "scales", "quats", "opacities"):
            if k not in params:
                raise ValueError(f"params: {k!r} is required")

    def step_pre_backward(self, *args, **kwargs) -> None:
        pass

    def step_post_backward(self, *args, **kwargs) -> None:
        pass
