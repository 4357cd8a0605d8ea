"""EcoSplat's stage 2: keep only the Gaussians a budget κ allows, and learn which ones.

* :class:`BudgetHeads`: copies of the parameter heads plus a zero-initialised 7x7 "rate
  embedding" of the κ map added into their input features (at initialisation the copies return
  exactly what the base heads return).
* :func:`high_frequency_energy` -> :func:`view_weights` (softmax of the max-normalised energy at
  temperature 0.3) -> :func:`per_view_budgets`: integers K_v <= H·W summing to exactly
  round(κ·V·H·W) (overflow of a full view goes to the others; rounding by largest remainder).
* :func:`topk_mask`: keep the top-K_v per view by a score (the copied head's opacity, or for
  the baselines the base opacity); :func:`random_mask`: the random-pruning baseline.
* :func:`importance_target`: the 0/1 mask of pixels that survive when the lowest-gradient 4x4
  patches are merged into one pixel each, as many as K_v needs.
* :func:`fill_gain`: how much a kept Gaussian grows to cover its pruned neighbours (not in
  EcoSplat; applied to every pruning method alike, see :meth:`~.model.PGTOutput.gaussians`).
* :func:`io_loss`: w_io·(w_op·BCE(opacity, target) + BCE(rendered alpha, 1)).
* :func:`sample_kappa`: the progressive schedule κ ~ U(max(0.85 - 0.05·⌊step/interval⌋, 0.05), 0.95).
"""
from __future__ import annotations

import copy
import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from .heads import GaussianHeads, RawGaussians

__all__ = ["BudgetHeads", "check_kappa", "high_frequency_energy", "view_weights", "per_view_budgets",
           "topk_mask", "random_mask", "fill_gain", "importance_target", "io_loss", "sample_kappa"]


def check_kappa(kappa) -> float:
    """κ as a float in (0, 1]; ValueError naming ``kappa`` otherwise."""
    if isinstance(kappa, Tensor):
        if kappa.numel() != 1:
            raise ValueError(f"kappa: expected a single number, got a tensor of shape {list(kappa.shape)}")
        kappa = kappa.item()
    if isinstance(kappa, bool) or not isinstance(kappa, (int, float)):
        raise ValueError(f"kappa: expected a number in (0, 1], got {kappa!r}")
    if not (math.isfinite(kappa) and 0.0 < kappa <= 1.0):
        raise ValueError(f"kappa: the budget ratio must be in (0, 1], got {kappa!r}")
    return float(kappa)


class BudgetHeads(nn.Module):
    """A copy of ``heads`` reading features + rate_embed(κ map).

    forward(feat [V, C, H, W], kappa float) -> :class:`RawGaussians`.
    """

    def __init__(self, heads: GaussianHeads, channels: int, kernel: int = 7) -> None:
        super().__init__()
        self.heads = copy.deepcopy(heads)
        self.rate = nn.Conv2d(1, channels, kernel, padding=kernel // 2)
        nn.init.zeros_(self.rate.weight)
        nn.init.zeros_(self.rate.bias)

    def forward(self, feat: Tensor, kappa: float) -> RawGaussians:
        V, _, H, W = feat.shape
        kmap = torch.full((V, 1, H, W), float(kappa), dtype=feat.dtype, device=feat.device)
        return self.heads(feat + self.rate(kmap))


def high_frequency_energy(images: Tensor) -> Tensor:
    """[V, 3, H, W] in [0, 1] -> [V]: mean squared difference between each view's grey image and
    its 5x5 Gaussian blur (σ = 1 px), i.e. the energy above about a quarter of the sampling rate."""
    import kornia
    grey = images.mean(1, keepdim=True)
    blur = kornia.filters.gaussian_blur2d(grey, (5, 5), (1.0, 1.0), border_type="reflect")
    return ((grey - blur) ** 2).mean((1, 2, 3))


def view_weights(images: Tensor, temperature: float = 0.3) -> Tensor:
    """[V] softmax(e_v / max(e) / T) of the high-frequency energies; sums to 1."""
    e = high_frequency_energy(images)
    return torch.softmax(e / e.max().clamp_min(1e-12) / temperature, 0)


def per_view_budgets(kappa: float, weights: Tensor, height: int, width: int) -> Tensor:
    """Integer budgets K_v (long [V]) with Σ K_v = round(κ·V·H·W) and 0 <= K_v <= H·W, split in
    proportion to ``weights`` [V]; a view's share above H·W goes to the others in proportion."""
    kappa = check_kappa(kappa)
    V, P = weights.shape[0], height * width
    total = int(round(kappa * V * P))
    w = weights.detach().double().clamp_min(0)
    share = torch.zeros(V, dtype=torch.float64)
    full = torch.zeros(V, dtype=torch.bool)
    left = float(total)
    for _ in range(V):  # water-filling: at most V rounds
        free = ~full
        share[free] = left * w[free] / w[free].sum().clamp_min(1e-300)
        over = free & (share > P)
        if not over.any():
            break
        full |= over
        share[full] = P
        left = total - P * int(full.sum())
    k = share.floor().long().clamp_max(P)
    rest = total - int(k.sum())
    if rest > 0:  # largest remainders first, among views with room
        frac = (share - k.double()).masked_fill(k >= P, -1.0)
        for i in torch.argsort(frac, descending=True, stable=True)[:rest]:
            k[i] += 1
    return k.to(weights.device)


def topk_mask(scores: Tensor, budgets: Tensor) -> Tensor:
    """bool [V, H, W]: per view, the ``budgets[v]`` pixels with the highest ``scores`` [V, H, W]."""
    V, H, W = scores.shape
    flat = scores.detach().reshape(V, H * W)
    order = torch.argsort(flat, dim=1, descending=True, stable=True)
    rank = torch.empty_like(order)
    rank.scatter_(1, order, torch.arange(H * W, device=scores.device).expand(V, -1))
    return (rank < budgets.to(scores.device)[:, None]).reshape(V, H, W)


def random_mask(budgets: Tensor, height: int, width: int, generator: torch.Generator | None = None) -> Tensor:
    """bool [V, H, W]: ``budgets[v]`` pixels of view v chosen uniformly at random."""
    V = budgets.shape[0]
    scores = torch.rand(V, height, width, generator=generator)
    return topk_mask(scores, budgets.cpu()).to(budgets.device)


def fill_gain(keep: Tensor, window: int) -> Tensor:
    """[V, H, W] scale factor 1/sqrt(d), d = the share of kept pixels in the ``window`` x ``window``
    square around each pixel (at least one pixel's share): a kept Gaussian whose neighbourhood lost
    a share 1 - d of its pixels covers 1/d times the area."""
    d = F.avg_pool2d(keep.to(torch.float32)[:, None], window, stride=1, padding=window // 2,
                     count_include_pad=False)[:, 0]
    return d.clamp_min(1.0 / window ** 2).rsqrt()


def importance_target(images: Tensor, budgets: Tensor, patch: int = 4) -> Tensor:
    """The 0/1 importance target [V, H, W] (float).

    Per view, ``patch`` x ``patch`` patches are ranked by mean Sobel gradient magnitude; the
    lowest are merged (only their highest-gradient pixel survives) until at most K_v pixels
    remain; if merging every patch still leaves more than K_v, the survivors of the
    lowest-gradient patches are dropped too.
    """
    import kornia
    V, _, H, W = images.shape
    p2 = patch * patch
    grad = kornia.filters.sobel(images.mean(1, keepdim=True))[:, 0]  # [V, H, W]
    # [V, P, p2]: pixels of each patch
    cells = grad.reshape(V, H // patch, patch, W // patch, patch).permute(0, 1, 3, 2, 4).reshape(V, -1, p2)
    P = cells.shape[1]
    order = torch.argsort(cells.mean(-1), dim=1, stable=True)  # lowest gradient first
    best = cells.argmax(-1)  # [V, P] survivor of a merged patch
    keep = torch.ones(V, P, p2, dtype=torch.bool, device=images.device)
    for v in range(V):
        K = int(budgets[v])
        merged = min(P, max(0, math.ceil((H * W - K) / max(p2 - 1, 1))))
        idx = order[v, :merged]
        keep[v, idx] = False
        keep[v, idx, best[v, idx]] = True
        if merged == P and P > K:  # one survivor per patch is still too many
            keep[v, order[v, :P - K]] = False
    keep = keep.reshape(V, H // patch, W // patch, patch, patch).permute(0, 1, 3, 2, 4).reshape(V, H, W)
    return keep.to(images.dtype)


def io_loss(opacities: Tensor, target: Tensor, alphas: Tensor, w_io: float = 0.1, w_opacity: float = 0.1) -> Tensor:
    """w_io·(w_opacity·BCE(opacities [V, H, W], target [V, H, W]) + BCE(alphas [C, H, W, 1], 1))."""
    bce_op = F.binary_cross_entropy(opacities.clamp(1e-6, 1 - 1e-6), target)
    bce_alpha = -torch.log(alphas.clamp(1e-6, 1.0)).mean()
    return w_io * (w_opacity * bce_op + bce_alpha)


def sample_kappa(step: int, generator: torch.Generator, start: float = 0.85, decay: float = 0.05,
                 interval: int = 1000, low: float = 0.05, high: float = 0.95) -> float:
    """κ ~ U(max(start - decay·⌊step/interval⌋, low), high), drawn from ``generator``."""
    lo = max(start - decay * (step // interval), low)
    return lo + (high - lo) * float(torch.rand((), generator=generator, dtype=torch.float64))
