"""AutoSplat fusion: the learnt pose correction recovers a synthetic object offset."""
import math

import numpy as np
import pytest
import torch

from clsplat.models.autosplat.fusion import PoseCorrection, axis_angle_to_quat, place
from clsplat.models.autosplat.objects import box_surface_template
from clsplat.models.common.gaussians import GaussianSet, rgb_to_sh
from clsplat.models.common.geometry import axis_angle_to_matrix, matrix_to_axis_angle, quat_to_matrix


def test_axis_angle_to_quat_matches_matrix():
    aa = torch.tensor([[0.0, 0, 0], [0.1, -0.2, 0.3], [1e-7, 0, 0]])
    assert torch.allclose(quat_to_matrix(axis_angle_to_quat(aa)), axis_angle_to_matrix(aa), atol=1e-6)


def test_interpolated_correction_for_untrained_frames():
    pc = PoseCorrection(1, 5, torch.tensor([True, True, False, True, False]))
    with torch.no_grad():
        pc.delta[0, 1] = 1.0
        pc.delta[0, 3] = 3.0
    assert torch.allclose(pc(0, 2), torch.full((6,), 2.0))
    assert torch.allclose(pc(0, 4), torch.full((6,), 3.0))


@pytest.mark.slow   # fits a pose correction by gradient descent (150 Adam steps)
def test_pose_correction_recovers_offset():
    """Object rendered at its true pose; the track is off by 0.3 m and 5 degrees of yaw. Optimising
    only the correction recovers the pose to within 3 cm and 0.5 degrees."""
    rng = np.random.default_rng(0)
    size = (4.2, 1.8, 1.5)
    pts = torch.from_numpy(box_surface_template(size, 700, rng)).float()
    n = pts.shape[0]
    # a texture: colour varies along x and z, so rotation and translation are observable
    col = torch.stack([0.5 + 0.4 * torch.sin(3 * pts[:, 0]), 0.5 + 0.4 * torch.cos(4 * pts[:, 2]),
                       0.5 + 0.3 * torch.sin(2 * pts[:, 1] + pts[:, 0])], -1)
    q = torch.zeros(n, 4)
    q[:, 0] = 1
    obj = GaussianSet(pts, q, torch.full((n, 3), 0.07), torch.full((n,), 0.9), rgb_to_sh(col))
    W, H = 64, 40
    K = torch.tensor([[40.0, 0, W / 2], [0, 40.0, H / 2], [0, 0, 1]]).expand(3, 3, 3)

    def look(eye):
        eye = torch.tensor(eye)
        z = torch.nn.functional.normalize(-eye, dim=0)
        x = torch.nn.functional.normalize(torch.linalg.cross(z, torch.tensor([0.0, 0, 1])), dim=0)
        y = torch.linalg.cross(z, x)
        R = torch.stack([x, y, z])
        V = torch.eye(4)
        V[:3, :3], V[:3, 3] = R, -R @ eye
        return V

    V = torch.stack([look([8.0, 3.0, 2.0]), look([-2.0, 8.0, 3.0]), look([-7.0, -4.0, 2.5])])
    R_true, t_true = torch.eye(3), torch.zeros(3)
    q_id = torch.tensor([1.0, 0, 0, 0])
    with torch.no_grad():
        target, _, _ = place(obj, R_true, t_true, q_id).render(V, K, W, H)
    yaw = math.radians(5.0)
    R_trk = axis_angle_to_matrix(torch.tensor([0, 0, yaw]))
    t_trk = torch.tensor([0.25, -0.15, 0.08])
    t_trk = t_trk / t_trk.norm() * 0.3
    q_trk = axis_angle_to_quat(torch.tensor([0, 0, yaw]))
    pc = PoseCorrection(1, 1, torch.tensor([True]))
    opt = torch.optim.Adam(pc.parameters(), lr=0.01)
    for _ in range(150):
        img, _, _ = place(obj, R_trk, t_trk, q_trk, pc(0, 0)).render(V, K, W, H)
        loss = (img - target).abs().mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    d = pc(0, 0).detach()
    R_est = R_trk @ axis_angle_to_matrix(d[:3])
    t_est = R_trk @ d[3:] + t_trk
    rot_err = math.degrees(float(matrix_to_axis_angle(R_est.T @ R_true).norm()))
    assert float((t_est - t_true).norm()) < 0.03, t_est
    assert rot_err < 0.5, rot_err
