"""AutoSplat background: the flatness term C, its fit, the masked photometric loss."""
import math

import pytest
import torch

from clsplat.models.autosplat.background import flatness, masked_photometric, reference_frames
from clsplat.models.common.gaussians import GaussianSet, rgb_to_sh
from clsplat.models.common.geometry import axis_angle_to_matrix, matrix_to_quat


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


@pytest.mark.slow   # fits a road patch by gradient descent (60 Adam steps)
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


def _box_mask_brute(seq, frame, cam_name):
    """Every pixel's centre ray against every box over the whole image (the reference)."""
    import numpy as np
    f, cam = seq.frames[frame], seq.camera(cam_name)
    T = seq.cam_to_world(frame, cam_name)
    u, v = np.meshgrid(np.arange(cam.width) + 0.5, np.arange(cam.height) + 0.5)
    d = np.stack([(u - cam.K[0, 2]) / cam.K[0, 0], (v - cam.K[1, 2]) / cam.K[1, 1], np.ones_like(u)], -1)
    d = d @ T[:3, :3].T
    m = np.zeros((cam.height, cam.width), bool)
    for b in f.boxes:
        B = np.linalg.inv(b.box_to_world)
        ol = B[:3, :3] @ T[:3, 3] + B[:3, 3]
        dl = d @ B[:3, :3].T
        with np.errstate(divide="ignore", invalid="ignore"):
            t1, t2 = (-b.size / 2 - ol) / dl, (b.size / 2 - ol) / dl
        m |= (np.nanmax(np.minimum(t1, t2), -1) <= np.nanmin(np.maximum(t1, t2), -1)) & (
            np.nanmin(np.maximum(t1, t2), -1) > 0)
    return m


def test_foreground_mask_from_boxes_equals_whole_image_ray_test():
    """The box mask tests only each box's projected rectangle: the same pixels as testing
    every ray against every box, including boxes beside, behind and around the camera."""
    import dataclasses

    import numpy as np

    from clsplat.data.synthetic import SyntheticConfig, generate_sequence
    from clsplat.models.autosplat.background import foreground_mask
    seq = generate_sequence(SyntheticConfig(height=40, width=72, num_frames=3, seed=1, lidar=False))
    for f in seq.frames:
        f.instances.clear()  # force the ray-box path
    f0 = seq.frames[0]
    around = dataclasses.replace(f0.boxes[0], center=f0.ego_to_world[:3, 3].copy(),
                                 size=np.array([10.0, 10.0, 10.0]))  # holds the cameras
    f0.boxes.append(around)
    cams = seq.camera_names
    for i in range(len(seq.frames)):
        got = foreground_mask(seq, i, cams)
        want = np.stack([_box_mask_brute(seq, i, c) for c in cams])
        assert np.array_equal(got, want), i
        assert want.any()
    assert foreground_mask(seq, 0, cams).all()  # inside a box: every ray hits it
