"""gsplat programs run on clsplat: the image-fitting example with its raw, unactivated
parameters, and the trainer's rasterize_splats call (every keyword) in a training loop with
DefaultStrategy densification, packed and unpacked, and the sparse-gradient path."""
from __future__ import annotations

import math

import pytest
import torch

import clsplat
from clsplat.strategy import DefaultStrategy


def look_at(eye) -> torch.Tensor:
    """World-to-camera [4,4] (OpenCV axes) from ``eye`` towards the origin, y down."""
    eye = torch.tensor(eye, dtype=torch.float64)
    z = -eye / eye.norm()
    x = torch.linalg.cross(z, torch.tensor([0.0, -1.0, 0.0], dtype=torch.float64))
    x = x / x.norm()
    vm = torch.eye(4, dtype=torch.float64)
    vm[:3, :3] = torch.stack([x, torch.linalg.cross(z, x), z])
    vm[:3, 3] = -vm[:3, :3] @ eye
    return vm


def test_image_fitting_with_raw_parameters():
    """gsplat's examples/image_fitting.py, shrunk: scales are passed raw to rasterization
    (not exp'd), so Adam drives some negative; the covariance uses s^2 and fitting goes on."""
    torch.manual_seed(0)
    H = W = 24
    gt = torch.zeros(H, W, 3)
    gt[: H // 2, : W // 2] = torch.tensor([1.0, 0.0, 0.0])
    gt[H // 2:, W // 2:] = torch.tensor([0.0, 0.0, 1.0])
    n = 150
    means = (2 * (torch.rand(n, 3) - 0.5)).requires_grad_()
    scales = torch.rand(n, 3).requires_grad_()
    rgbs = torch.rand(n, 3).requires_grad_()
    u, v, w = torch.rand(n, 1), torch.rand(n, 1), torch.rand(n, 1)
    quats = torch.cat([torch.sqrt(1 - u) * torch.sin(2 * math.pi * v), torch.sqrt(1 - u) * torch.cos(2 * math.pi * v),
                       torch.sqrt(u) * torch.sin(2 * math.pi * w), torch.sqrt(u) * torch.cos(2 * math.pi * w)], -1).requires_grad_()
    opacities = torch.ones(n).requires_grad_()
    viewmat = torch.tensor([[1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 8.0], [0, 0, 0, 1]])
    focal = 0.5 * W / math.tan(0.5 * math.pi / 2.0)
    K = torch.tensor([[focal, 0, W / 2], [0, focal, H / 2], [0, 0, 1]])
    opt = torch.optim.Adam([rgbs, means, scales, opacities, quats], 0.01)
    losses = []
    for _ in range(300):
        img, _, _ = clsplat.rasterization(means, quats / quats.norm(dim=-1, keepdim=True), scales,
                                          torch.sigmoid(opacities), torch.sigmoid(rgbs),
                                          viewmat[None], K[None], W, H, packed=False)
        loss = torch.nn.functional.mse_loss(img[0], gt)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert (scales < 0).any()  # the case that used to stop the example at its second step
    assert losses[-1] < 0.5 * losses[0]


def scene_and_targets(seed: int, C: int = 2, W: int = 32, H: int = 24):
    g = torch.Generator().manual_seed(seed)
    vms = torch.stack([look_at((3.5 * math.cos(a), 0.3, 3.5 * math.sin(a))) for a in (0.3, 1.1)][:C]).float()
    f = 0.5 * W / math.tan(math.radians(30.0))
    Ks = torch.tensor([[f, 0, W / 2], [0, f, H / 2], [0, 0, 1]]).expand(C, 3, 3)
    n = 60
    gt = dict(means=(torch.rand(n, 3, generator=g) - 0.5) * 2, quats=torch.randn(n, 4, generator=g),
              scales=torch.rand(n, 3, generator=g) * 0.2 + 0.05, opacities=torch.rand(n, generator=g) * 0.5 + 0.5,
              colors=torch.rand(n, 3, generator=g))
    with torch.no_grad():
        targets = clsplat.rasterization(**gt, viewmats=vms, Ks=Ks, width=W, height=H)[0]
    return torch.linalg.inv(vms), Ks, targets


def init_splats(n: int, sh_degree: int, seed: int) -> torch.nn.ParameterDict:
    g = torch.Generator().manual_seed(seed)
    K = (sh_degree + 1) ** 2
    return torch.nn.ParameterDict({
        "means": (torch.rand(n, 3, generator=g) - 0.5) * 2,
        "scales": torch.log(torch.full((n, 3), 0.15)),
        "quats": torch.rand(n, 4, generator=g),
        "opacities": torch.logit(torch.full((n,), 0.1)),
        "sh0": (torch.rand(n, 1, 3, generator=g) - 0.5) / 0.28209479177387814,
        "shN": torch.zeros(n, K - 1, 3)})


def rasterize_splats(splats, camtoworlds, Ks, width, height, packed, sparse_grad=False,
                     absgrad=False, antialiased=False, **kwargs):
    """gsplat simple_trainer's Runner.rasterize_splats, with every keyword it passes."""
    means = splats["means"]
    quats = splats["quats"]
    scales = torch.exp(splats["scales"])
    opacities = torch.sigmoid(splats["opacities"])
    colors = torch.cat([splats["sh0"], splats["shN"]], 1)
    rasterize_mode = "antialiased" if antialiased else "classic"
    return clsplat.rasterization(
        means=means, quats=quats, scales=scales, opacities=opacities, colors=colors,
        viewmats=torch.linalg.inv(camtoworlds), Ks=Ks, width=width, height=height,
        packed=packed, absgrad=absgrad, sparse_grad=sparse_grad, rasterize_mode=rasterize_mode,
        distributed=False, camera_model="pinhole", with_ut=False, with_eval3d=False, **kwargs)


@pytest.mark.parametrize("packed", [True, False])
def test_trainer_loop_with_default_strategy(packed):
    torch.manual_seed(1)
    c2w, Ks, targets = scene_and_targets(5)
    W, H = targets.shape[2], targets.shape[1]
    splats = init_splats(80, 1, seed=2)
    optimizers = {k: torch.optim.Adam([v], lr=lr) for k, v, lr in (
        (k, splats[k], {"means": 1.6e-3, "scales": 5e-3, "quats": 1e-3, "opacities": 5e-2,
                        "sh0": 2.5e-3, "shN": 2.5e-3 / 20}[k]) for k in splats)}
    strategy = DefaultStrategy(refine_start_iter=40, refine_every=40, reset_every=160,
                               refine_stop_iter=240, grow_grad2d=2e-5, absgrad=False)
    strategy.check_sanity(splats, optimizers)
    state = strategy.initialize_state(scene_scale=1.0)
    n0, losses = len(splats["means"]), []
    for step in range(300):
        img, alphas, info = rasterize_splats(splats, c2w, Ks, W, H, packed, sh_degree=min(1, step // 50),
                                             near_plane=0.01, far_plane=1e10, render_mode="RGB+ED")
        strategy.step_pre_backward(splats, optimizers, state, step, info)
        loss = torch.nn.functional.l1_loss(img[..., :3], targets)
        loss.backward()
        for opt in optimizers.values():
            opt.step()
            opt.zero_grad(set_to_none=True)
        strategy.step_post_backward(splats, optimizers, state, step, info, packed=packed)
        losses.append(loss.item())
    assert len(splats["means"]) != n0  # densification ran on clsplat's meta
    assert len({v.shape[0] for v in splats.values()}) == 1
    assert sum(losses[-10:]) < 0.6 * sum(losses[:10])


def test_trainer_sparse_grad_path():
    """sparse_grad=True (packed): means, quats and scales get sparse gradients for SparseAdam;
    the trainer turns the others sparse through info["gaussian_ids"]; losses fall."""
    torch.manual_seed(4)
    c2w, Ks, targets = scene_and_targets(6, C=1)
    W, H = targets.shape[2], targets.shape[1]
    splats = init_splats(80, 0, seed=3)
    optimizers = {k: torch.optim.SparseAdam([v], lr=2e-2) for k, v in splats.items()}
    losses = []
    for step in range(40):
        img, _, info = rasterize_splats(splats, c2w, Ks, W, H, packed=True, sparse_grad=True, sh_degree=0)
        loss = torch.nn.functional.l1_loss(img, targets)
        loss.backward()
        assert splats["means"].grad.is_sparse and splats["scales"].grad.is_sparse
        ids = info["gaussian_ids"]
        for k in splats:
            g = splats[k].grad
            if g is not None and not g.is_sparse:
                splats[k].grad = torch.sparse_coo_tensor(ids[None], g[ids], g.shape, is_coalesced=True)
        for opt in optimizers.values():
            opt.step()
            opt.zero_grad(set_to_none=True)
        losses.append(loss.item())
    assert losses[-1] < 0.8 * losses[0]
