"""Densification on clsplat's outputs: every case of gsplat's tests/test_strategy.py, run
with clsplat.strategy (the torch port of gsplat's DefaultStrategy and MCMCStrategy), plus the
torch relocation against the 3DGS-MCMC formula and the packed / absgrad paths."""
from __future__ import annotations

import math

import pytest
import torch

import clsplat
from clsplat.data.scene import quat_to_rotmat as scene_quat_to_rotmat
from clsplat.strategy import (DefaultStrategy, MCMCStrategy, compute_relocation, duplicate, swap_parameter,
                              quat_scale_to_covar_preci, remove, split)


def test_mcmc_strategy_positional_constructor():
    strategy = MCMCStrategy(123, 4.5, 6, 7, 8, 9, 0.1, True, 0.2, 30.0)
    assert strategy.cap_max == 123
    assert strategy.noise_lr == 4.5
    assert strategy.refine_start_iter == 6
    assert strategy.refine_stop_iter == 7
    assert strategy.noise_injection_stop_iter == 8
    assert strategy.refine_every == 9
    assert strategy.min_opacity == 0.1
    assert strategy.verbose is True
    assert strategy.noise_opacity_t == 0.2
    assert strategy.noise_opacity_k == 30.0


@pytest.mark.parametrize("operation", ["relocate", "add"])
def test_mcmc_strategy_rejects_empty_live_set(operation):
    n = 20
    params = torch.nn.ParameterDict({
        "means": torch.zeros(n, 3), "scales": torch.zeros(n, 3), "quats": torch.zeros(n, 4),
        "opacities": torch.logit(torch.full((n,), 0.001))})
    strategy = MCMCStrategy(cap_max=n + 1, min_opacity=0.005)
    binoms = strategy.initialize_state()["binoms"]
    with pytest.raises(RuntimeError, match=r"no live Gaussians.*min_opacity=0\.005"):
        if operation == "relocate":
            strategy._relocate_gs(params, {}, binoms)
        else:
            strategy._add_new_gs(params, {}, binoms)
    assert len(params["means"]) == n


def make_params(N: int = 100, extra: bool = False) -> torch.nn.ParameterDict:
    p = {"means": torch.randn(N, 3), "scales": torch.rand(N, 3), "quats": torch.randn(N, 4),
         "opacities": torch.rand(N), "colors": torch.rand(N, 3)}
    if extra:
        p["non_trainable_features"] = torch.rand(N, 3)
    return torch.nn.ParameterDict(p)


def render(params, packed=False, absgrad=False):
    return clsplat.rasterization(
        means=params["means"], quats=params["quats"], scales=torch.exp(params["scales"]),
        opacities=torch.sigmoid(params["opacities"]), colors=params["colors"],
        viewmats=torch.eye(4).unsqueeze(0), Ks=torch.eye(3).unsqueeze(0), width=10, height=10,
        packed=packed, absgrad=absgrad)


@pytest.mark.parametrize("requires_grad_case", [False, True])
def test_strategy(requires_grad_case):
    """gsplat's test_strategy and test_strategy_requires_grad: one dummy render, then both
    strategies' callbacks at step 600; sizes stay consistent and frozen tensors stay frozen."""
    torch.manual_seed(42)
    params = make_params(extra=requires_grad_case)
    if requires_grad_case:
        params["non_trainable_features"].requires_grad = False
    requires = {k: v.requires_grad for k, v in params.items()}
    optimizers = {k: torch.optim.Adam([v], lr=1e-3) for k, v in params.items() if v.requires_grad}
    render_colors, render_alphas, info = render(params)

    strategy = DefaultStrategy(verbose=True)
    strategy.check_sanity(params, optimizers)
    state = strategy.initialize_state()
    strategy.step_pre_backward(params, optimizers, state, step=600, info=info)
    render_colors.mean().backward(retain_graph=True)
    strategy.step_post_backward(params, optimizers, state, step=600, info=info)
    strategy = MCMCStrategy(verbose=True)
    strategy.check_sanity(params, optimizers)
    state = strategy.initialize_state()
    render_colors.mean().backward(retain_graph=True)
    strategy.step_post_backward(params, optimizers, state, step=600, info=info, lr=1e-3)
    for k, v in params.items():
        assert v.requires_grad == requires[k]
    assert len({v.shape[0] for v in params.values()}) == 1
    if requires_grad_case:
        assert params["non_trainable_features"].grad is None
    for k, opt in optimizers.items():  # each optimizer follows its (replaced) parameter
        assert opt.param_groups[0]["params"][0] is params[k]


def relocation_by_the_formula(o: float, s: float, n: int) -> tuple[float, float]:
    new_o = 1 - (1 - o) ** (1 / n)
    denom = sum(math.comb(i - 1, k) * (-1) ** k / math.sqrt(k + 1) * new_o ** (k + 1)
                for i in range(1, n + 1) for k in range(i))
    return new_o, o / denom * s


def test_compute_relocation_matches_the_paper():
    binoms = MCMCStrategy().initialize_state()["binoms"]
    o = torch.tensor([0.9, 0.5, 0.05, 0.99, 0.3])
    s = torch.rand(5, 3) + 0.1
    ratios = torch.tensor([1, 2, 5, 20, 51])
    new_o, new_s = compute_relocation(o, s, ratios, binoms)
    for i in range(5):
        eo, es = relocation_by_the_formula(float(o[i]), 1.0, int(ratios[i]))
        assert abs(float(new_o[i]) - eo) < 1e-6
        assert torch.allclose(new_s[i], s[i] * es, rtol=1e-4)
    assert torch.allclose(1 - (1 - new_o) ** ratios, o, atol=1e-6)  # n copies composite to o
    assert torch.equal(new_o[0], o[0]) and torch.allclose(new_s[0], s[0])  # ratio 1: unchanged


def test_covariance_helper_matches_reference():
    q, s = torch.randn(10, 4, dtype=torch.float64), torch.rand(10, 3, dtype=torch.float64) + 0.1
    cov, prec = quat_scale_to_covar_preci(q, s)
    R = torch.from_numpy(scene_quat_to_rotmat(q.numpy()))  # the numpy data-layer implementation
    assert torch.allclose(cov, R @ torch.diag_embed(s ** 2) @ R.transpose(-1, -2))
    assert torch.allclose(prec @ cov, torch.eye(3, dtype=torch.float64).expand(10, 3, 3), atol=1e-9)
    tri, _ = quat_scale_to_covar_preci(q, s, compute_preci=False, triu=True)
    assert tri.shape == (10, 6) and torch.equal(tri[:, 3], cov[:, 1, 1])


def test_ops_keep_optimizer_state_in_step():
    torch.manual_seed(0)
    params = make_params(N=10)
    optimizers = {k: torch.optim.Adam([v], lr=1e-2) for k, v in params.items()}
    sum(v.sum() for v in params.values()).backward()
    for o in optimizers.values():
        o.step()
    state = {"grad2d": torch.arange(10.0), "scene_scale": 1.0}
    mask = torch.zeros(10, dtype=torch.bool)
    mask[[1, 4]] = True
    duplicate(params, optimizers, state, mask)
    assert len(params["means"]) == 12 and torch.equal(state["grad2d"][10:], torch.tensor([1.0, 4.0]))
    assert optimizers["means"].state[params["means"]]["exp_avg"].shape == (12, 3)
    split(params, optimizers, state, torch.arange(12) == 0)
    assert len(params["means"]) == 13
    assert torch.allclose(params["scales"][-1], params["scales"][-2])
    remove(params, optimizers, state, torch.arange(13) < 3)
    assert len(params["quats"]) == 10 and len(state["grad2d"]) == 10
    for k, opt in optimizers.items():
        assert opt.state[params[k]]["exp_avg_sq"].shape[0] == 10


@pytest.mark.parametrize("packed", [True, False])
@pytest.mark.parametrize("absgrad", [False, True])
def test_default_strategy_statistics_packed_and_unpacked(packed, absgrad):
    """The accumulated screen-space gradient norms are the same from packed and unpacked meta."""
    torch.manual_seed(3)
    stats = []
    for pk in (packed, not packed):
        params = make_params(N=50)
        params["means"].data[:, 2] += 3.0
        strategy = DefaultStrategy(absgrad=absgrad)
        state = strategy.initialize_state()
        img, _, info = render(params, packed=pk, absgrad=absgrad)
        strategy.step_pre_backward(params, {}, state, step=1, info=info)
        img.square().sum().backward()
        strategy.step_post_backward(params, {}, state, step=1, info=info, packed=pk)
        stats.append((state["grad2d"], state["count"]))
        torch.manual_seed(3)
    assert stats[0][1].sum() > 0 and torch.equal(stats[0][1], stats[1][1])
    assert torch.allclose(stats[0][0], stats[1][0], rtol=1e-5, atol=1e-9)


def _hand_info(grad_norms: list[float], width: int = 2, height: int = 2) -> dict:
    """Unpacked meta for one camera whose means2d gradient has the given norms (x only); with
    width = height = 2 the strategy's pixel scaling (W/2, H/2) is 1, so a norm is the statistic."""
    n = len(grad_norms)
    m2d = torch.zeros(1, n, 2, requires_grad=True)
    m2d.grad = torch.zeros(1, n, 2)
    m2d.grad[0, :, 0] = torch.tensor(grad_norms)
    return {"width": width, "height": height, "n_cameras": 1, "means2d": m2d,
            "radii": torch.ones(1, n, 2, dtype=torch.int32), "gaussian_ids": None}


def test_default_strategy_grows_and_prunes_exactly_what_its_rule_names():
    """One refinement step with hand-set statistics: a small high-gradient Gaussian is
    duplicated, a large high-gradient one is split in two smaller ones, a transparent one is
    removed, the others are untouched (a strategy that does nothing fails every assert)."""
    torch.manual_seed(0)
    hi, lo = 1e-3, 1e-5                       # around grow_grad2d = 2e-4
    small, large = math.log(0.005), math.log(0.3)  # around grow_scale3d = 0.01
    params = torch.nn.ParameterDict({
        "means": torch.arange(15.0).reshape(5, 3),
        "scales": torch.tensor([[small] * 3, [large] * 3, [small] * 3, [small] * 3, [large] * 3]),
        "quats": torch.tensor([[1.0, 0, 0, 0]]).repeat(5, 1),
        "opacities": torch.tensor([2.0, 2.0, 2.0, -10.0, 2.0]),   # #3 below prune_opa
        "colors": torch.rand(5, 3)})
    optimizers = {k: torch.optim.Adam([v], lr=1e-3) for k, v in params.items()}
    strategy = DefaultStrategy()
    state = strategy.initialize_state()
    strategy.step_post_backward(params, optimizers, state, step=600,
                                info=_hand_info([hi, hi, lo, lo, lo]))
    # survivors in order (#0, #2, #4; #1 split, #3 pruned), then #0's copy, then #1's two halves
    assert len(params["means"]) == 6
    assert torch.equal(params["means"][:3], torch.tensor([[0.0, 1, 2], [6, 7, 8], [12, 13, 14]]))
    assert torch.equal(params["means"][3], torch.tensor([0.0, 1, 2]))
    assert torch.allclose(params["scales"][4:], torch.full((2, 3), math.log(0.3 / 1.6)))
    assert not torch.equal(params["means"][4], params["means"][5])   # sampled, not copied
    assert (params["means"][4:] - torch.tensor([3.0, 4, 5])).norm(dim=-1).max() < 0.3 * 6
    assert torch.sigmoid(params["opacities"]).min() > strategy.prune_opa
    assert torch.equal(state["grad2d"], torch.zeros(6))                # statistics restart
    for k, opt in optimizers.items():
        assert opt.param_groups[0]["params"][0] is params[k]


def test_default_strategy_below_threshold_changes_nothing():
    params = make_params(N=8)
    params["opacities"].data.fill_(2.0)
    before = {k: v.detach().clone() for k, v in params.items()}
    strategy = DefaultStrategy()
    state = strategy.initialize_state()
    strategy.step_post_backward(params, {}, state, step=600, info=_hand_info([1e-6] * 8))
    assert all(torch.equal(params[k], before[k]) for k in before)


def test_mcmc_strategy_relocates_dead_and_adds_five_percent():
    """Dead Gaussians (opacity <= min_opacity) are moved onto live ones and 5% are added; no
    Gaussian stays dead after the step (noise injection off to compare positions)."""
    torch.manual_seed(0)
    n = 40
    params = make_params(N=n)
    params["opacities"].data = torch.logit(torch.full((n,), 0.6))
    params["opacities"].data[:10] = torch.logit(torch.tensor(0.001))
    params["scales"].data = torch.log(torch.full((n, 3), 0.05))
    optimizers = {k: torch.optim.Adam([v], lr=1e-3) for k, v in params.items()}
    strategy = MCMCStrategy(noise_injection_stop_iter=0)
    state = strategy.initialize_state()
    live_means = params["means"][10:].detach().clone()
    strategy.step_post_backward(params, optimizers, state, step=600, info={}, lr=1e-3)
    assert len(params["means"]) == int(1.05 * n)
    assert torch.sigmoid(params["opacities"]).min() > strategy.min_opacity
    # every relocated Gaussian sits on a live one's position
    moved = params["means"][:10].detach()
    assert torch.cdist(moved, live_means).min(dim=1).values.max() == 0


def test_swap_parameter_in_a_shared_multi_group_optimizer():
    """The surgery AutoSplat's densifier shares: a parameter inside one Adam with several groups
    is replaced in its own group, its moments carried by state_fn, the others untouched."""
    a, b = torch.nn.Parameter(torch.randn(4, 3)), torch.nn.Parameter(torch.randn(4))
    opt = torch.optim.Adam([{"params": [a], "lr": 1e-2}, {"params": [b], "lr": 1e-3}])
    (a.sum() + b.sum()).backward()
    opt.step()
    moments_b = opt.state[b]["exp_avg"].clone()
    new = torch.nn.Parameter(torch.cat([a.data, a.data[:1]]))
    swap_parameter(opt, a, new, lambda key, v: torch.cat([v, torch.zeros_like(v[:1])]))
    assert opt.param_groups[0]["params"] == [new] and opt.param_groups[1]["params"] == [b]
    assert a not in opt.state and opt.state[new]["exp_avg"].shape == (5, 3)
    assert torch.equal(opt.state[new]["exp_avg"][4], torch.zeros(3))
    assert torch.equal(opt.state[new]["step"], torch.tensor(1.0))          # step is not per row
    assert torch.equal(opt.state[b]["exp_avg"], moments_b)
    new.grad = torch.ones_like(new)
    b.grad = torch.ones_like(b)
    opt.step()                                                             # Adam runs on the new set
