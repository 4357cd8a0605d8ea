"""Adam whose chosen parameter groups update only the rows that received a gradient.

Plain Adam moves every entry of a parameter at every step, including entries whose gradient is
exactly zero this step: their first moment keeps the sign of the last gradient they saw and decays
slowly against the second moment, so one gradient impulse moves an entry about ten learning rates
in total, whatever the impulse's size (Adam is scale-free). A table of per-sample parameters (one
row per object and frame, of which a step sees a few) then drifts by that much at every visit, and
keeps drifting between visits. gsplat's ``SelectiveAdam`` updates only the visible Gaussians for the
same reason; TensorFlow calls this "lazy" Adam.

:class:`SelectiveAdam` is ``torch.optim.Adam`` (same state, same checkpoint format) in which the
groups named by ``selective`` keep, for every row (a vector along the last dimension; an entry of a
1-D parameter) whose gradient is all zero, the parameter and its moments exactly as they were
before the step. The step counter stays the group's one count, as in gsplat's. A non-finite
gradient counts as a gradient (the training loop skips such steps before the optimiser).
"""
from __future__ import annotations

from typing import Collection

import torch

__all__ = ["SelectiveAdam"]

#: the per-entry state Adam keeps (amsgrad adds the last), restored with the parameter on idle rows
_MOMENTS = ("exp_avg", "exp_avg_sq", "max_exp_avg_sq")


class SelectiveAdam(torch.optim.Adam):
    """``torch.optim.Adam`` whose groups in ``selective`` (indices into ``param_groups``) update
    only the rows with a nonzero gradient.

    Args:
        params: parameter groups, as for ``torch.optim.Adam``.
        selective: indices of the groups updated row by row; a row of a ``[..., D]`` parameter is
            ``p[i, j, ..., :]`` (a 1-D parameter's rows are its entries).
        **kwargs: Adam's options (``lr``, ``betas``, ``eps``, ...).
    """

    def __init__(self, params, selective: Collection[int] = (), **kwargs) -> None:
        super().__init__(params, **kwargs)
        selective = sorted({int(i) for i in selective})
        for i in selective:
            if not 0 <= i < len(self.param_groups):
                raise ValueError(f"selective: group {i} is out of range (the optimiser has "
                                 f"{len(self.param_groups)} groups)")
        self.selective = tuple(selective)

    @torch.no_grad()
    def step(self, closure=None):
        """One Adam step; rows of the selective groups without gradient are left untouched."""
        kept = []
        for i in self.selective:
            for p in self.param_groups[i]["params"]:
                if p.grad is None:
                    continue
                g = p.grad if p.dim() >= 2 else p.grad.reshape(-1, 1)
                idle = ~(g != 0).any(dim=-1)                      # p.shape[:-1]: rows with no gradient
                if p.dim() < 2:
                    idle = idle.reshape(p.shape)
                if not bool(idle.any()):
                    continue
                st = self.state.get(p, {})
                saved = {k: st[k][idle].clone() for k in _MOMENTS if k in st}
                kept.append((p, idle, p.data[idle].clone(), saved))
        loss = super().step(closure)
        for p, idle, value, saved in kept:
            p.data[idle] = value
            st = self.state[p]
            for k in _MOMENTS:
                if k in saved:
                    st[k][idle] = saved[k]
                elif k in st:                                    # the first step: moments start at 0
                    st[k][idle] = 0
        return loss
