"""AutoSplat background: the flatness term C, its fit, the masked photometric loss."""
import math

import torch

from clsplat.models.autosplat.background import flatness, masked_photometric, reference_frames
from clsplat.models.common.gaussians import GaussianSet, rgb_to_sh
from clsplat.models.common.geometry import axis_angle_to_matrix, matrix_to_quat, quat_multiply


def _tilted_patch(n_side=12, tilt_deg=12.0):
    """A road patch of discs on a plane tilted about x and y, discs lying in the plane."""
    u, v = torch.meshgrid(torch.linspace(-2, 2, n_side), torch.linspace(-2, 2, n_side), indexing="ij")
    R = axis_angle_to_matrix(torch.tensor([math.radians(tilt_deg), math.radians(tilt_deg / 2), 0.0]))
    pts = torch.stack([u.flatten(), v.flatten(), torch.zeros(n_side * n_side)], -1) @ R.T
    quats = matrix_to_quat(R).expand(pts.shape[0], 4).clone()
    scales = torch.tensor([0.2, 0.2, 0.02]).expand(pts.shape[0], 3).clone()
    return pts, quats, scales


def test_flatness_is_zero_for_flat_discs_and_modulo_pi():
    _, _, scales = _tilted_patch()
    n = scales.shape[0]
    up = torch.tensor([0.0, 0, 1]).expand(n, 3)
    F = reference_frames(up)
    q = torch.zeros(n, 4)
    q[:, 0] = 1
    flip = torch.tensor([0.0, 1.0, 0.0, 0.0]).expand(n, 4)  # 180 deg about x: still flat
    assert float(flatness(q, scales * torch.tensor([1, 1, 0.0]), F)) < 1e-6
    assert float(flatness(flip, scales * torch.tensor([1, 1, 0.0]), F)) < 1e-5
    yaw = matrix_to_quat(axis_angle_to_matrix(torch.tensor([0, 0, 0.7]))).expand(n, 4)
    assert float(flatness(yaw, scales * torch.tensor([1, 1, 0.0]), F)) < 1e-5  # yaw is free


def test_flatness_fit_drives_tilted_road_patch_flat():
    """Fit a tilted patch to a top-down image of a flat grey road with L1 + beta C: C falls by
    more than 10x and every disc's normal ends within 2 degrees of the road normal."""
    pts, quats, scales = _tilted_patch()
    n = pts.shape[0]
    quats = quats.clone().requires_grad_()
    log_s = scales.log().clone().requires_grad_()
    means = pts.clone().requires_grad_()
    sh = rgb_to_sh(torch.full((n, 3), 0.4))
    F = reference_frames(torch.tensor([0.0, 0, 1]).expand(n, 3))
    W = H = 32
    K = torch.tensor([[[12.0, 0, 16], [0, 12.0, 16], [0, 0, 1]]])
    V = torch.tensor([[[1.0, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, 6.0], [0, 0, 0, 1]]])  # looking down
    target = torch.full((1, H, W, 3), 0.4)
    opt = torch.optim.Adam([{"params": [quats], "lr": 0.02}, {"params": [log_s], "lr": 0.02},
                            {"params": [means], "lr": 0.002}])
    c0 = float(flatness(quats, log_s.exp(), F).detach())
    for _ in range(60):
        img, _, _ = GaussianSet(means, quats, log_s.exp(), torch.full((n,), 0.9), sh).render(V, K, W, H)
        c = flatness(quats, log_s.exp(), F)
        loss = (img - target).abs().mean() + 0.5 * c
        opt.zero_grad()
        loss.backward()
        opt.step()
    c1 = float(flatness(quats, log_s.exp(), F).detach())
    assert c0 > 0.3 and c1 < c0 / 10, (c0, c1)
    from clsplat.models.common.geometry import quat_to_matrix
    R = quat_to_matrix(torch.nn.functional.normalize(quats.detach(), dim=-1))
    thin = log_s.detach().argmin(1)
    normal = R[torch.arange(n), :, thin]
    ang = torch.rad2deg(torch.acos(normal[:, 2].abs().clamp(max=1)))
    assert float(ang.max()) < 2.0, float(ang.max())


def test_masked_photometric_ignores_masked_pixels():
    a = torch.rand(2, 16, 16, 3)
    b = a.clone()
    b[:, :4] = 1 - b[:, :4]
    mask = torch.ones(2, 16, 16, dtype=torch.bool)
    mask[:, :8] = False
    loss, l1, _ = masked_photometric(a, b, mask, 0.2)
    full, l1_full, _ = masked_photometric(a, b, None, 0.2)
    assert float(l1) == 0.0 and float(l1_full) > 0.05
    assert float(loss) < 0.02 < float(full)
