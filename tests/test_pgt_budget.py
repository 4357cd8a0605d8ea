"""EcoSplat's stage-2 pieces (models/pgt/budget.py): per-view budgets that sum to round(κ·V·H·W)
and follow the high-frequency weighting, top-K and random masks, the importance target from
merged low-gradient patches, L_io, the κ schedule and the κ checks."""
from __future__ import annotations

import math

import pytest
import torch

from clsplat.models.pgt.budget import (
    BudgetHeads, check_kappa, high_frequency_energy, importance_target, io_loss, per_view_budgets, random_mask,
    sample_kappa, topk_mask, view_weights)
from clsplat.models.pgt.heads import GaussianHeads

H, W = 32, 48


def _textured_views(amplitudes=(0.0, 0.15, 0.3)):
    """Views of the same smooth ramp plus checkerboard noise of growing amplitude."""
    g = torch.Generator().manual_seed(0)
    ramp = torch.linspace(0.2, 0.8, W).expand(3, H, W)
    return torch.stack([(ramp + a * (torch.rand(3, H, W, generator=g) - 0.5)).clamp(0, 1) for a in amplitudes])


@pytest.mark.parametrize("V", [1, 2, 3, 6])
def test_budgets_sum_exactly_for_every_kappa(V):
    w = torch.softmax(torch.randn(V, generator=torch.Generator().manual_seed(V)), 0)
    for kappa in [i / 200 for i in range(1, 201)] + [1e-5, 0.3333, 0.999999]:
        k = per_view_budgets(kappa, w, H, W)
        assert int(k.sum()) == round(kappa * V * H * W), kappa
        assert (k >= 0).all() and (k <= H * W).all()


def test_budgets_follow_the_high_frequency_weighting():
    images = _textured_views()
    e = high_frequency_energy(images)
    assert e[0] < e[1] < e[2]
    w = view_weights(images, 0.3)
    torch.testing.assert_close(w, torch.softmax(e / e.max() / 0.3, 0))
    for kappa in (0.05, 0.1, 0.2):
        k = per_view_budgets(kappa, w, H, W)
        assert k[0] < k[1] < k[2]
        # proportional to the weights up to rounding
        assert (k.double() - kappa * 3 * H * W * w.double()).abs().max() <= 1.0
    # a lower temperature concentrates the budget on the textured view
    assert view_weights(images, 0.05)[2] > w[2]


def test_full_views_pass_their_excess_on():
    w = torch.tensor([0.9, 0.05, 0.05])
    k = per_view_budgets(0.6, w, H, W)  # view 0 would get 1.62·H·W
    assert k[0] == H * W and int(k.sum()) == round(0.6 * 3 * H * W)
    assert abs(int(k[1]) - int(k[2])) <= 1
    assert per_view_budgets(1.0, w, H, W).tolist() == [H * W] * 3


def test_topk_and_random_masks():
    g = torch.Generator().manual_seed(0)
    scores = torch.rand(2, H, W, generator=g)
    k = torch.tensor([100, 7])
    m = topk_mask(scores, k)
    assert m.sum(dim=(1, 2)).tolist() == [100, 7]
    for v in range(2):
        assert scores[v][m[v]].min() > scores[v][~m[v]].max()
    r = random_mask(k, H, W, torch.Generator().manual_seed(1))
    assert r.sum(dim=(1, 2)).tolist() == [100, 7]
    assert not torch.equal(r, random_mask(k, H, W, torch.Generator().manual_seed(2)))


def test_importance_target_merges_low_gradient_patches():
    images = _textured_views((0.0, 0.0))
    images[:, :, :, W // 2:] = _textured_views((0.5, 0.5))[:, :, :, W // 2:]  # right half textured
    P = H * W
    for K in (P, P // 2, P // 4, P // 10, P // 16, P // 40):
        t = importance_target(images, torch.tensor([K, K]), patch=4)
        assert t.shape == (2, H, W) and set(t.unique().tolist()) <= {0.0, 1.0}
        n = t.sum(dim=(1, 2))
        assert (n <= K).all() and (n >= min(K, P) - 15).all()  # merging moves in steps of 15 pixels
        if K < P and K != P // 16:  # the flat half is merged (or dropped) first
            assert t[:, :, :W // 2].sum() < t[:, :, W // 2:].sum()
    # every merged 4x4 patch keeps exactly one pixel
    t = importance_target(images, torch.tensor([P // 8, P // 8]), patch=4)
    per_patch = t.reshape(2, H // 4, 4, W // 4, 4).sum(dim=(2, 4))
    assert set(per_patch.unique().tolist()) <= {1.0, 16.0}


def test_io_loss():
    op = torch.full((2, H, W), 0.5, requires_grad=True)
    target = torch.zeros(2, H, W)
    alpha = torch.ones(1, H, W, 1)
    got = io_loss(op, target, alpha, 0.1, 0.1)
    torch.testing.assert_close(got, torch.tensor(0.1 * 0.1 * math.log(2.0)))
    got = io_loss(op, target, torch.full((1, H, W, 1), 0.5), 0.1, 0.1)
    torch.testing.assert_close(got, torch.tensor(0.1 * (0.1 * math.log(2.0) + math.log(2.0))))
    got.backward()
    assert (op.grad > 0).all()  # the target is 0: push opacity down


def test_kappa_schedule_is_progressive():
    g = torch.Generator().manual_seed(0)
    for step, lo in ((0, 0.85), (999, 0.85), (1000, 0.80), (5500, 0.60), (100000, 0.05)):
        ks = [sample_kappa(step, g) for _ in range(200)]
        assert min(ks) >= lo - 1e-12 and max(ks) <= 0.95
        assert min(ks) < lo + 0.05
    a = sample_kappa(3, torch.Generator().manual_seed(5), interval=1)
    assert a == sample_kappa(3, torch.Generator().manual_seed(5), interval=1)


def test_budget_heads_start_as_exact_copies():
    heads = GaussianHeads(8, 4)
    bh = BudgetHeads(heads, 8, 7)
    feat = torch.randn(2, 8, 16, 16)
    a, b = heads(feat), bh(feat, 0.3)
    for f in ("rotation", "scale", "opacity", "colour"):
        assert torch.equal(getattr(a, f), getattr(b, f))
    assert bh.rate.kernel_size == (7, 7)
    assert all(p is not q for p, q in zip(heads.parameters(), bh.heads.parameters()))


@pytest.mark.parametrize("bad", [0, 0.0, -0.1, 1.0001, math.nan, math.inf, "0.5", None, True, torch.ones(2)])
def test_kappa_outside_range_is_a_value_error(bad):
    with pytest.raises(ValueError, match="kappa"):
        check_kappa(bad)
    with pytest.raises(ValueError, match="kappa"):
        per_view_budgets(bad, torch.ones(2) / 2, H, W)
    assert check_kappa(torch.tensor(0.25)) == 0.25
