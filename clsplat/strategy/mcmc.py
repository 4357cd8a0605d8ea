"""gsplat's ``MCMCStrategy`` in plain torch: 3DGS as Markov chain Monte Carlo (relocate dead
Gaussians onto live ones, add new ones, perturb transparent ones along their covariance)."""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Callable, Dict

import torch
from torch import Tensor

from .base import Strategy
from .ops import compute_relocation, inject_noise_to_position, relocate, sample_add

__all__ = ["MCMCStrategy"]


@dataclass
class MCMCStrategy(Strategy):
    """3DGS as Markov chain Monte Carlo, with gsplat's arguments and defaults.

    Every ``refine_every`` steps between ``refine_start_iter`` and ``refine_stop_iter``: dead
    Gaussians (opacity <= min_opacity) are relocated onto live ones and 5% more are added (up
    to ``cap_max``), both by :func:`relocate` / :func:`sample_add` with ``relocation``
    (default :func:`compute_relocation`). After every step before ``noise_injection_stop_iter``
    (-1: always), positions get noise scaled by lr * noise_lr, gated to Gaussians with opacity
    below about ``noise_opacity_t`` with sharpness ``noise_opacity_k``
    (:func:`inject_noise_to_position`). Fields in the order of gsplat's current constructor.
    """

    cap_max: int = 1_000_000
    noise_lr: float = 5e5
    refine_start_iter: int = 500
    refine_stop_iter: int = 25_000
    noise_injection_stop_iter: int = -1
    refine_every: int = 100
    min_opacity: float = 0.005
    verbose: bool = False
    noise_opacity_t: float = 0.005
    noise_opacity_k: float = 100.0
    relocation: Callable = compute_relocation

    def initialize_state(self) -> Dict[str, Any]:
        n_max = 51
        binoms = torch.zeros((n_max, n_max))
        for n in range(n_max):
            for k in range(n + 1):
                binoms[n, k] = math.comb(n, k)
        return {"binoms": binoms}

    def step_post_backward(self, params, optimizers, state, step: int, info: Dict[str, Any],
                           lr: float) -> None:
        state["binoms"] = state["binoms"].to(params["means"].device)
        if self.refine_start_iter < step < self.refine_stop_iter and step % self.refine_every == 0:
            n_rel = self._relocate_gs(params, optimizers, state["binoms"])
            n_new = self._add_new_gs(params, optimizers, state["binoms"])
            if self.verbose:
                print(f"Step {step}: relocated {n_rel}, added {n_new}; now {len(params['means'])} Gaussians.")
        if self.noise_injection_stop_iter < 0 or step < self.noise_injection_stop_iter:
            inject_noise_to_position(params, optimizers, {}, scaler=lr * self.noise_lr,
                                     t=self.noise_opacity_t, k=self.noise_opacity_k)

    @torch.no_grad()
    def _relocate_gs(self, params, optimizers, binoms: Tensor) -> int:
        dead = torch.sigmoid(params["opacities"].flatten()) <= self.min_opacity
        n = int(dead.sum())
        if n:
            relocate(params, optimizers, {}, dead, binoms, self.min_opacity, self.relocation)
        return n

    @torch.no_grad()
    def _add_new_gs(self, params, optimizers, binoms: Tensor) -> int:
        cur = len(params["means"])
        n = max(0, min(self.cap_max, int(1.05 * cur)) - cur)
        if n:
            sample_add(params, optimizers, {}, n, binoms, self.min_opacity, self.relocation)
        return n
