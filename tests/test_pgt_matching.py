"""Epipolar matching (models/pgt/matching.py): the ray samples land where the geometry says, the
cost volume peaks at the true depth, and both matchers return distributions and u0 in range."""
from __future__ import annotations

import pytest
import torch

from clsplat.models.common.geometry import warp
from clsplat.models.pgt.matching import (
    EpipolarAttentionMatcher, PlaneSweepMatcher, depth_hypotheses, depth_to_u, sample_along_rays, u_to_depth)

h, w = 6, 10


def _pair():
    Ks = torch.tensor([[8.0, 0, w / 2], [0, 8.0, h / 2], [0, 0, 1]]).expand(2, 3, 3).clone()
    c2w = torch.eye(4).expand(2, 4, 4).clone()
    c2w[1, 0, 3] = 0.6  # stereo baseline along x
    return Ks, c2w


def test_depth_parametrisation_round_trips():
    u = torch.linspace(0, 1, 11)
    d = u_to_depth(u, 1.0, 80.0)
    assert d[0] == pytest.approx(80.0) and d[-1] == pytest.approx(1.0)
    torch.testing.assert_close(depth_to_u(d, 1.0, 80.0), u)
    assert depth_to_u(torch.tensor([float("inf"), 0.5]), 1.0, 80.0).tolist() == [0.0, 1.0]


def test_samples_match_an_inverse_warp_at_each_hypothesis():
    Ks, c2w = _pair()
    feats = torch.randn(2, 5, h, w, generator=torch.Generator().manual_seed(0))
    u_hyp = depth_hypotheses(4)
    s, valid = sample_along_rays(feats, Ks, c2w, u_hyp, 1.0, 80.0)
    assert s.shape == (2, 1, 4, 5, h, w) and valid.shape == (2, 1, 4, h, w)
    for i, j in ((0, 1), (1, 0)):
        T = torch.linalg.inv(c2w[j]) @ c2w[i]
        for k, d in enumerate(u_to_depth(u_hyp, 1.0, 80.0)):
            ref, ok = warp(feats[j:j + 1], torch.full((1, h, w), float(d)), Ks[i:i + 1], Ks[j:j + 1], T[None])
            # where all four bilinear taps are inside (warp blends zero padding in at the edge)
            ones, _ = warp(torch.ones(1, 1, h, w), torch.full((1, h, w), float(d)), Ks[i:i + 1], Ks[j:j + 1], T[None])
            inner = ok * (ones > 1 - 1e-6)
            torch.testing.assert_close(s[i, 0, k] * inner[0], ref[0] * inner[0], atol=1e-5, rtol=1e-5)
            assert (s[i, 0, k][(ok[0] == 0).expand_as(s[i, 0, k])] == 0).all()
            torch.testing.assert_close(valid[i, 0, k], ok[0, 0])


def test_cost_volume_peaks_at_the_true_depth():
    """Both views see a fronto-parallel plane at hypothesis k* whose features are sinusoids of the
    3D point (period 1 m): the correlation along each ray is highest at k*."""
    from clsplat.models.common.geometry import unproject
    Ks, c2w = _pair()
    D, k_true = 8, 5
    u_hyp = depth_hypotheses(D)
    depth = float(u_to_depth(u_hyp[k_true], 1.0, 80.0))
    pts = unproject(torch.full((2, h, w), depth), Ks, c2w)  # [2, h, w, 3] world points on the plane
    a = 2 * torch.pi
    feats = torch.stack([torch.sin(a * pts[..., 0]), torch.cos(a * pts[..., 0]),
                         torch.sin(a * pts[..., 1]), torch.cos(a * pts[..., 1])], 1)
    s, valid = sample_along_rays(feats, Ks, c2w, u_hyp, 1.0, 80.0)
    corr = ((s * feats[:, None, None]).sum(3) * valid)[:, 0]  # [2, D, h, w]
    seen = valid[:, 0, k_true] > 0
    assert seen.sum() > 0.5 * seen.numel()
    assert (corr.argmax(1)[seen] == k_true).float().mean() > 0.9


@pytest.mark.parametrize("V", [2, 3])
def test_both_matchers_give_distributions_and_u0_in_range(V):
    torch.manual_seed(0)
    C, D = 16, 6
    Ks = torch.tensor([[8.0, 0, w / 2], [0, 8.0, h / 2], [0, 0, 1]]).expand(V, 3, 3).clone()
    c2w = torch.eye(4).expand(V, 4, 4).clone()
    c2w[:, 0, 3] = torch.arange(V) * 0.5
    feats = torch.randn(V, C, h, w, requires_grad=True)
    for m in (PlaneSweepMatcher(C, D, 8, 1.0, 80.0), EpipolarAttentionMatcher(C, D, 2, 4, 1.0, 80.0)):
        matched, prob, u0 = m(feats, Ks, c2w)
        assert matched.shape == (V, C, h, w) and prob.shape == (V, D, h, w) and u0.shape == (V, h, w)
        torch.testing.assert_close(prob.sum(1), torch.ones(V, h, w))
        assert ((u0 >= 0) & (u0 <= 1)).all()
        (u0.sum() + matched.square().mean()).backward()
        assert feats.grad is not None and feats.grad.abs().sum() > 0
        feats.grad = None
