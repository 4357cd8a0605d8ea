"""Operations of the densification strategies, each keeping the optimizers in step with the
parameters: the geometry (:func:`quat_scale_to_covar_preci`) and 3DGS-MCMC's relocation rule
(:func:`compute_relocation`), both with the signatures of gsplat's CUDA-backed ops;
:func:`swap_parameter`, the one piece of optimiser surgery every densifier needs, and
:func:`rebuild`, the parameter surgery on top of it (each named parameter replaced, its moments
carried over); and the strategies' operations built on those (:func:`duplicate`, :func:`split`,
:func:`remove`, :func:`reset_opa`, :func:`relocate`, :func:`sample_add`,
:func:`inject_noise_to_position`). AutoSplat's ``densify_and_prune`` uses :func:`rebuild` too.
"""
from __future__ import annotations

import math
from typing import Any, Callable, Dict, Optional, Union

import torch
from torch import Tensor

from ..quaternion import quat_to_rotmat

__all__ = ["Params", "quat_scale_to_covar_preci", "compute_relocation", "swap_parameter", "rebuild", "duplicate",
           "split",
           "remove", "reset_opa", "relocate", "sample_add", "inject_noise_to_position"]

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

    The one piece of optimiser surgery every densifier needs (this package's strategies, AutoSplat's
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
def rebuild(params: Params, optimizers: Dict[str, torch.optim.Optimizer],
            param_fn: Callable[[str, Tensor], Tensor], state_fn: Callable[[str, Tensor], Tensor],
            names: Optional[list] = None) -> None:
    """Replace each named parameter (all of ``params``, or ``names``) by a new leaf
    ``param_fn(name, p)`` in ``params`` and in its optimizer, and each of the optimizer's
    per-element state tensors (not ``step``) by ``state_fn(key, v)``. ``optimizers`` maps each
    trainable name to the optimizer that holds it (one optimizer may hold several names, in
    several groups); a trainable name without one is a ValueError."""
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
    rebuild(params, optimizers, lambda n, p: torch.cat([p, p[sel]]),
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

    rebuild(params, optimizers, lambda n, p: torch.cat([p[rest], new_values(n, p)]),
             lambda k, v: torch.cat([v[rest], v.new_zeros((2 * len(sel),) + v.shape[1:])]))
    _edit_state(state, lambda v: torch.cat([v[rest], v[sel].repeat(2, *[1] * (v.dim() - 1))]))


@torch.no_grad()
def remove(params: Params, optimizers, state: Dict[str, Any], mask: Tensor) -> None:
    """Drop every Gaussian in ``mask``."""
    keep = (~mask).nonzero()[:, 0]
    rebuild(params, optimizers, lambda n, p: p[keep], lambda k, v: v[keep])
    _edit_state(state, lambda v: v[keep])


@torch.no_grad()
def reset_opa(params: Params, optimizers, state: Dict[str, Any], value: float) -> None:
    """Clamp every opacity to at most ``value`` and clear its optimizer moments."""
    cap = math.log(value / (1 - value))
    rebuild(params, optimizers, lambda n, p: p.clamp_max(cap), lambda k, v: torch.zeros_like(v),
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

    rebuild(params, optimizers, param_fn, state_fn)
    _edit_state(state, lambda v: v.index_fill(0, src, 0))


@torch.no_grad()
def sample_add(params: Params, optimizers, state: Dict[str, Any], n: int, binoms: Tensor,
               min_opacity: float = 0.005, relocation: Callable = compute_relocation) -> None:
    """Append n Gaussians, copies of live ones drawn by opacity (sharing as in :func:`relocate`)."""
    src, shared = _draw_and_share(params, n, binoms, min_opacity, relocation, "sample_add")

    def param_fn(name: str, p: Tensor) -> Tensor:
        p = shared(name, p)
        return torch.cat([p, p[src]])

    rebuild(params, optimizers, param_fn,
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
