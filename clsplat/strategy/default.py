"""gsplat's ``DefaultStrategy`` in plain torch: the original 3DGS schedule (clone, split, prune,
opacity reset) driven by the screen-space gradients that :func:`clsplat.rasterization` returns."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Dict

import torch

from .base import Strategy
from .ops import duplicate, remove, reset_opa, split

__all__ = ["DefaultStrategy"]


@dataclass
class DefaultStrategy(Strategy):
    """The original 3DGS schedule, with gsplat's arguments and defaults.

    Every ``refine_every`` steps between ``refine_start_iter`` and ``refine_stop_iter``:
    Gaussians whose mean screen-space gradient (or absgrad) exceeds ``grow_grad2d`` are
    duplicated when small (max scale <= grow_scale3d * scene_scale) and split otherwise;
    those with opacity < prune_opa (and, after the first reset, too large) are removed.
    Every ``reset_every`` steps the opacities are clamped to 2 * prune_opa. (gsplat 1.5.3
    writes that last condition as ``step % reset_every == 0 & step > 0``, which Python reads
    as never true; this port resets as documented.)
    """

    prune_opa: float = 0.005
    grow_grad2d: float = 0.0002
    grow_scale3d: float = 0.01
    grow_scale2d: float = 0.05
    prune_scale3d: float = 0.1
    prune_scale2d: float = 0.15
    refine_scale2d_stop_iter: int = 0
    refine_start_iter: int = 500
    refine_stop_iter: int = 15_000
    reset_every: int = 3000
    refine_every: int = 100
    pause_refine_after_reset: int = 0
    absgrad: bool = False
    revised_opacity: bool = False
    verbose: bool = False
    key_for_gradient: str = "means2d"

    def initialize_state(self, scene_scale: float = 1.0) -> Dict[str, Any]:
        state: Dict[str, Any] = {"grad2d": None, "count": None, "scene_scale": scene_scale}
        if self.refine_scale2d_stop_iter > 0:
            state["radii"] = None
        return state

    def step_pre_backward(self, params, optimizers, state, step: int, info: Dict[str, Any]) -> None:
        if self.key_for_gradient not in info:
            raise ValueError(f"info: {self.key_for_gradient!r} is required")
        info[self.key_for_gradient].retain_grad()

    def step_post_backward(self, params, optimizers, state, step: int, info: Dict[str, Any],
                           packed: bool = False) -> None:
        if step >= self.refine_stop_iter:
            return
        self._update_state(params, state, info, packed)
        if (step > self.refine_start_iter and step % self.refine_every == 0
                and step % self.reset_every >= self.pause_refine_after_reset):
            n_dup, n_split = self._grow(params, optimizers, state, step)
            n_prune = self._prune(params, optimizers, state, step)
            if self.verbose:
                print(f"Step {step}: {n_dup} duplicated, {n_split} split, {n_prune} pruned; "
                      f"now {len(params['means'])} Gaussians.")
            state["grad2d"].zero_()
            state["count"].zero_()
            if self.refine_scale2d_stop_iter > 0:
                state["radii"].zero_()
        if step > 0 and step % self.reset_every == 0:
            reset_opa(params, optimizers, state, value=self.prune_opa * 2.0)

    @torch.no_grad()
    def _update_state(self, params, state, info, packed: bool) -> None:
        for k in ("width", "height", "n_cameras", "radii", "gaussian_ids", self.key_for_gradient):
            if k not in info:
                raise ValueError(f"info: {k!r} is required")
        m2d = info[self.key_for_gradient]
        g = m2d.absgrad if self.absgrad else m2d.grad
        if g is None:
            raise ValueError(f"info: {self.key_for_gradient}.{'absgrad' if self.absgrad else 'grad'} "
                             "is None; call step_pre_backward before backward"
                             + (" and render with absgrad=True" if self.absgrad else ""))
        g = g.clone()
        g[..., 0] *= info["width"] / 2.0 * info["n_cameras"]
        g[..., 1] *= info["height"] / 2.0 * info["n_cameras"]
        n = len(params["means"])
        dev = g.device
        for k in ("grad2d", "count") + (("radii",) if self.refine_scale2d_stop_iter > 0 else ()):
            if state[k] is None:
                state[k] = torch.zeros(n, device=dev)
        if packed:
            ids, radii = info["gaussian_ids"], info["radii"].max(-1).values
        else:
            sel = (info["radii"] > 0).all(-1)            # [C, N]
            ids, g, radii = sel.nonzero()[:, 1], g[sel], info["radii"][sel].max(-1).values
        state["grad2d"].index_add_(0, ids, g.norm(dim=-1).to(state["grad2d"].dtype))
        state["count"].index_add_(0, ids, torch.ones(len(ids), device=dev, dtype=state["count"].dtype))
        if self.refine_scale2d_stop_iter > 0:
            r = radii.to(state["radii"].dtype) / float(max(info["width"], info["height"]))
            state["radii"][ids] = torch.maximum(state["radii"][ids], r)

    @torch.no_grad()
    def _grow(self, params, optimizers, state, step: int) -> tuple[int, int]:
        grads = state["grad2d"] / state["count"].clamp_min(1)
        high = grads > self.grow_grad2d
        small = torch.exp(params["scales"]).max(-1).values <= self.grow_scale3d * state["scene_scale"]
        dup = high & small
        spl = high & ~small
        if step < self.refine_scale2d_stop_iter:
            spl |= state["radii"] > self.grow_scale2d
        n_dup, n_split = int(dup.sum()), int(spl.sum())
        if n_dup:
            duplicate(params, optimizers, state, dup)
        spl = torch.cat([spl, torch.zeros(n_dup, dtype=torch.bool, device=spl.device)])
        if n_split:
            split(params, optimizers, state, spl, self.revised_opacity)
        return n_dup, n_split

    @torch.no_grad()
    def _prune(self, params, optimizers, state, step: int) -> int:
        prune = torch.sigmoid(params["opacities"].flatten()) < self.prune_opa
        if step > self.reset_every:
            big = torch.exp(params["scales"]).max(-1).values > self.prune_scale3d * state["scene_scale"]
            if step < self.refine_scale2d_stop_iter:
                big |= state["radii"] > self.prune_scale2d
            prune |= big
        n = int(prune.sum())
        if n:
            remove(params, optimizers, state, prune)
        return n
