"""Densification strategies in plain torch, with gsplat's interface, for clsplat's outputs.

gsplat's ``DefaultStrategy`` (3DGS: clone, split, prune, opacity reset) and ``MCMCStrategy``
(3DGS-as-MCMC: relocate dead Gaussians, add new ones, perturb positions) read only
``meta["means2d"].grad`` / ``.absgrad``, ``radii``, ``gaussian_ids``, ``width``, ``height``
and ``n_cameras``, which :func:`clsplat.rasterization` provides in gsplat's layouts. gsplat
itself is not a clsplat dependency, and its MCMC path calls two CUDA ops; this module is a
torch implementation of the same strategies, with the same constructor arguments, state and
callbacks, so that a gsplat training loop runs on the CPU unchanged apart from its imports.

For users who keep gsplat's own strategy classes on a machine without CUDA,
:func:`compute_relocation` and :func:`quat_scale_to_covar_preci` have the signatures of
gsplat's CUDA-backed ops and can be passed in in their place (``gsplat.strategy.ops``
looks both names up at call time)::

    import gsplat.strategy.ops as ops, clsplat.strategy as cs
    ops.compute_relocation, ops.quat_scale_to_covar_preci = cs.compute_relocation, cs.quat_scale_to_covar_preci

Parameters follow gsplat's convention: ``params`` maps names to [N, ...] leaves holding
``means``, raw log ``scales``, raw ``quats`` and logit ``opacities``; ``optimizers`` maps
each trainable name to an optimizer with one param group.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Callable, Dict, Optional, Union

import torch
from torch import Tensor

from .quaternion import quat_to_rotmat

__all__ = ["Strategy", "swap_parameter", "DefaultStrategy", "MCMCStrategy", "compute_relocation",
           "quat_scale_to_covar_preci", "duplicate", "split", "remove", "reset_opa",
           "relocate", "sample_add", "inject_noise_to_position"]

Params = Union[Dict[str, torch.nn.Parameter], torch.nn.ParameterDict]


# ---- geometry and relocation ----------------------------------------------------------------

def quat_scale_to_covar_preci(quats: Tensor, scales: Tensor, compute_covar: bool = True,
                              compute_preci: bool = True, triu: bool = False):
    """Covariances R S S R^T and precisions (their inverses) of Gaussians, in torch.

    quats [..., 4] wxyz, scales [..., 3] -> (covars, precis), each [..., 3, 3] or, with
    ``triu``, the upper triangle [..., 6] (xx, xy, xz, yy, yz, zz); None where not asked for.
    """
    R = quat_to_rotmat(quats)
    out = []
    for want, s in ((compute_covar, scales), (compute_preci, 1.0 / scales)):
        if not want:
            out.append(None)
            continue
        M = R * s[..., None, :]
        m = M @ M.transpose(-1, -2)
        out.append(m[..., [0, 0, 0, 1, 1, 2], [0, 1, 2, 1, 2, 2]] if triu else m)
    return tuple(out)


def compute_relocation(opacities: Tensor, scales: Tensor, ratios: Tensor,
                       binoms: Tensor) -> tuple[Tensor, Tensor]:
    """New opacity and scale for a Gaussian that is split into ``ratio`` copies (3DGS-MCMC,
    Eq. 9), so that the copies together render like the original.

    opacities [N], scales [N, 3], ratios [N] (clamped to [1, n_max]), binoms [n_max, n_max]
    binomial coefficients -> (new_opacities [N] = 1 - (1 - o)^(1/n),
    new_scales [N, 3] = o / sum_{i<=n} sum_{k<i} C(i-1, k) (-1)^k o'^(k+1) / sqrt(k+1) * s).
    Evaluated in float64 (the alternating sum cancels badly in float32).
    """
    n_max = binoms.shape[0]
    n = ratios.clamp(1, n_max).long()
    o = opacities.double()
    new_o = 1 - (1 - o).pow(1.0 / n.double())
    b = binoms.double().to(o.device)
    # W[n, k] = sum_{i=k+1..n} C(i-1, k): the coefficient of o'^(k+1) in the double sum
    W = torch.cat([torch.zeros_like(b[:1]), torch.cumsum(b, 0)])[:n_max + 1]   # [n_max+1, n_max]
    k = torch.arange(n_max, dtype=torch.float64, device=o.device)
    term = (-1.0) ** k / torch.sqrt(k + 1) * new_o[:, None] ** (k + 1)          # [N, n_max]
    denom = (W[n] * term).sum(-1)
    new_s = (o / denom)[:, None] * scales.double()
    return new_o.to(opacities.dtype), new_s.to(scales.dtype)


# ---- parameter surgery that keeps the optimizers in step ---------------------------------

def swap_parameter(optimizer: torch.optim.Optimizer, old: Tensor, new: Tensor,
                   state_fn: Callable[[str, Tensor], Tensor]) -> None:
    """Put ``new`` wherever ``old`` is in ``optimizer``'s parameter groups and carry ``old``'s
    state over, each per-element tensor (not ``step``) replaced by ``state_fn(key, v)``.

    The one piece of optimiser surgery every densifier needs (the strategies below, AutoSplat's
    ``densify_and_prune``): an optimiser holding several parameters in several groups works as
    well as gsplat's one optimiser per parameter."""
    for group in optimizer.param_groups:
        group["params"] = [new if p is old else p for p in group["params"]]
    st = optimizer.state.pop(old, {})
    for key, v in list(st.items()):
        if key != "step" and isinstance(v, Tensor) and v.dim() > 0:
            st[key] = state_fn(key, v)
    optimizer.state[new] = st


@torch.no_grad()
def _rebuild(params: Params, optimizers: Dict[str, torch.optim.Optimizer],
             param_fn: Callable[[str, Tensor], Tensor], state_fn: Callable[[str, Tensor], Tensor],
             names: Optional[list] = None) -> None:
    """Replace each named parameter by param_fn(name, p) and each of its optimizer's per-
    element state tensors (not ``step``) by state_fn(key, v)."""
    for name in (list(params.keys()) if names is None else names):
        old = params[name]
        new = torch.nn.Parameter(param_fn(name, old), requires_grad=old.requires_grad)
        params[name] = new
        opt = optimizers.get(name)
        if opt is None:
            if old.requires_grad:
                raise ValueError(f"optimizers: parameter {name!r} is trainable but has no optimizer")
            continue
        swap_parameter(opt, old, new, state_fn)


def _edit_state(state: Dict[str, Any], fn: Callable[[Tensor], Tensor]) -> None:
    for k, v in list(state.items()):
        if isinstance(v, Tensor) and v.dim() > 0:
            state[k] = fn(v)


@torch.no_grad()
def duplicate(params: Params, optimizers, state: Dict[str, Any], mask: Tensor) -> None:
    """Append a copy of every Gaussian in ``mask`` [N] (fresh optimizer moments)."""
    sel = mask.nonzero()[:, 0]
    _rebuild(params, optimizers, lambda n, p: torch.cat([p, p[sel]]),
             lambda k, v: torch.cat([v, v.new_zeros((len(sel),) + v.shape[1:])]))
    _edit_state(state, lambda v: torch.cat([v, v[sel]]))


@torch.no_grad()
def split(params: Params, optimizers, state: Dict[str, Any], mask: Tensor,
          revised_opacity: bool = False) -> None:
    """Replace every Gaussian in ``mask`` by two, sampled from it, with scales / 1.6; the
    survivors keep their order and the new pairs are appended."""
    sel, rest = mask.nonzero()[:, 0], (~mask).nonzero()[:, 0]
    s = torch.exp(params["scales"][sel])
    R = quat_to_rotmat(params["quats"][sel])
    offsets = (R[None] @ (s[None] * torch.randn(2, len(sel), 3, device=s.device,
                                                 dtype=s.dtype))[..., None])[..., 0]  # [2, n, 3]

    def new_values(name: str, p: Tensor) -> Tensor:
        if name == "means":
            return (p[sel][None] + offsets).reshape(-1, 3)
        if name == "scales":
            return torch.log(s / 1.6).repeat(2, 1)
        if name == "opacities" and revised_opacity:
            return torch.logit(1 - torch.sqrt(1 - torch.sigmoid(p[sel]))).repeat(2, *[1] * (p.dim() - 1))
        return p[sel].repeat(2, *[1] * (p.dim() - 1))

    _rebuild(params, optimizers, lambda n, p: torch.cat([p[rest], new_values(n, p)]),
             lambda k, v: torch.cat([v[rest], v.new_zeros((2 * len(sel),) + v.shape[1:])]))
    _edit_state(state, lambda v: torch.cat([v[rest], v[sel].repeat(2, *[1] * (v.dim() - 1))]))


@torch.no_grad()
def remove(params: Params, optimizers, state: Dict[str, Any], mask: Tensor) -> None:
    """Drop every Gaussian in ``mask``."""
    keep = (~mask).nonzero()[:, 0]
    _rebuild(params, optimizers, lambda n, p: p[keep], lambda k, v: v[keep])
    _edit_state(state, lambda v: v[keep])


@torch.no_grad()
def reset_opa(params: Params, optimizers, state: Dict[str, Any], value: float) -> None:
    """Clamp every opacity to at most ``value`` and clear its optimizer moments."""
    cap = math.log(value / (1 - value))
    _rebuild(params, optimizers, lambda n, p: p.clamp_max(cap), lambda k, v: torch.zeros_like(v),
             names=["opacities"])


def _sample(weights: Tensor, n: int) -> Tensor:
    """n indices drawn with replacement, proportional to ``weights`` [M]."""
    if weights.numel() <= 2 ** 24:
        return torch.multinomial(weights, n, replacement=True)
    cdf = torch.cumsum(weights.double(), 0)
    return torch.searchsorted(cdf, torch.rand(n, dtype=torch.float64, device=weights.device) * cdf[-1])


def _relocated(params: Params, src: Tensor, binoms: Tensor, min_opacity: float,
               relocation: Callable) -> tuple[Tensor, Tensor]:
    """New (logit opacities, log scales) of the sampled sources ``src``, each shared by the
    number of times it was drawn plus one."""
    o = torch.sigmoid(params["opacities"].flatten())[src]
    s = torch.exp(params["scales"])[src]
    ratios = torch.bincount(src)[src] + 1
    new_o, new_s = relocation(o, s, ratios, binoms)
    eps = torch.finfo(torch.float32).eps
    new_o = new_o.clamp(min_opacity, 1 - eps)
    return torch.logit(new_o).reshape(params["opacities"][src].shape), torch.log(new_s)


def _live(params: Params, min_opacity: float, what: str) -> Tensor:
    o = torch.sigmoid(params["opacities"].flatten())
    live = (o > min_opacity).nonzero()[:, 0]
    if len(live) == 0:
        raise RuntimeError(f"{what}: no live Gaussians to sample from (every opacity is <= "
                           f"min_opacity={min_opacity})")
    return live


def _draw_and_share(params: Params, n: int, binoms: Tensor, min_opacity: float, relocation: Callable,
                    what: str) -> tuple[Tensor, Callable[[str, Tensor], Tensor]]:
    """Draw ``n`` live sources by opacity; returns them and ``shared(name, p)``: a copy of the
    parameter ``p`` with each source's opacity and scale already reduced for its copies."""
    live = _live(params, min_opacity, what)
    o = torch.sigmoid(params["opacities"].flatten())
    src = live[_sample(o[live], n)]
    logit_o, log_s = _relocated(params, src, binoms, min_opacity, relocation)

    def shared(name: str, p: Tensor) -> Tensor:
        p = p.clone()
        if name == "opacities":
            p[src] = logit_o
        elif name == "scales":
            p[src] = log_s
        return p
    return src, shared


@torch.no_grad()
def relocate(params: Params, optimizers, state: Dict[str, Any], mask: Tensor, binoms: Tensor,
             min_opacity: float = 0.005, relocation: Callable = compute_relocation) -> None:
    """Move every dead Gaussian (``mask``) onto a live one drawn by opacity; the source and
    its copies share its opacity and scale (``relocation``, default :func:`compute_relocation`)."""
    dead = mask.nonzero()[:, 0]
    src, shared = _draw_and_share(params, len(dead), binoms, min_opacity, relocation, "relocate")

    def param_fn(name: str, p: Tensor) -> Tensor:
        p = shared(name, p)
        p[dead] = p[src]
        return p

    def state_fn(key: str, v: Tensor) -> Tensor:
        v = v.clone()
        v[src] = 0
        return v

    _rebuild(params, optimizers, param_fn, state_fn)
    _edit_state(state, lambda v: v.index_fill(0, src, 0))


@torch.no_grad()
def sample_add(params: Params, optimizers, state: Dict[str, Any], n: int, binoms: Tensor,
               min_opacity: float = 0.005, relocation: Callable = compute_relocation) -> None:
    """Append n Gaussians, copies of live ones drawn by opacity (sharing as in :func:`relocate`)."""
    src, shared = _draw_and_share(params, n, binoms, min_opacity, relocation, "sample_add")

    def param_fn(name: str, p: Tensor) -> Tensor:
        p = shared(name, p)
        return torch.cat([p, p[src]])

    _rebuild(params, optimizers, param_fn,
             lambda k, v: torch.cat([v, v.new_zeros((n,) + v.shape[1:])]))
    _edit_state(state, lambda v: torch.cat([v, v.new_zeros((n,) + v.shape[1:])]))


@torch.no_grad()
def inject_noise_to_position(params: Params, optimizers, state: Dict[str, Any],
                             scaler: float, t: float = 0.005, k: float = 100.0) -> None:
    """means += Sigma * noise * sigmoid(k ((1 - o) - (1 - t))) * scaler: transparent Gaussians
    wander along their own covariance (3DGS-MCMC's SGLD step)."""
    o = torch.sigmoid(params["opacities"].flatten())
    covars, _ = quat_scale_to_covar_preci(params["quats"], torch.exp(params["scales"]),
                                          compute_preci=False)
    gate = torch.sigmoid(k * ((1 - o) - (1 - t)))
    noise = torch.randn_like(params["means"]) * gate[:, None] * scaler
    params["means"].add_((covars @ noise[..., None])[..., 0])


# ---- strategies -----------------------------------------------------------------------------

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
