"""models/common/geometry.py: SE(3)/SO(3) helpers, unprojection and projection, inverse warp."""
from __future__ import annotations

import math

import pytest
import torch

from clsplat.models.common import geometry as G
from clsplat.models.common.data import parse_data, to_torch_frame

F64 = torch.float64


def test_rotation_round_trips_and_small_angles():
    torch.manual_seed(0)
    aa = torch.randn(50, 3, dtype=F64)
    aa = aa / aa.norm(dim=-1, keepdim=True) * torch.rand(50, 1, dtype=F64) * 3.0
    R = G.axis_angle_to_matrix(aa)
    assert torch.allclose(R.transpose(-1, -2) @ R, torch.eye(3, dtype=F64).expand(50, 3, 3), atol=1e-12)
    assert torch.allclose(G.matrix_to_axis_angle(R), aa, atol=1e-9)
    assert torch.allclose(G.quat_to_matrix(G.matrix_to_quat(R)), R, atol=1e-12)
    tiny = torch.tensor([1e-9, -2e-9, 0.0], dtype=F64, requires_grad=True)
    Rt = G.axis_angle_to_matrix(tiny)
    Rt.sum().backward()
    assert torch.isfinite(tiny.grad).all()
    assert torch.allclose(G.matrix_to_axis_angle(Rt.detach()), tiny.detach(), atol=1e-15)


def test_se3_inverse_and_quaternion_product():
    T = G.se3_exp(torch.tensor([[0.1, 0.2, -0.3]], dtype=F64), torch.tensor([[1.0, -2.0, 3.0]], dtype=F64))
    assert torch.allclose(T @ G.invert_rigid(T), torch.eye(4, dtype=F64)[None], atol=1e-12)
    q = torch.nn.functional.normalize(torch.randn(2, 4, dtype=F64), dim=-1)
    prod = G.quat_to_matrix(G.quat_multiply(q[0], q[1]))
    assert torch.allclose(prod, G.quat_to_matrix(q[0]) @ G.quat_to_matrix(q[1]), atol=1e-12)


def test_unproject_project_are_inverse_on_pixel_centres():
    g = torch.Generator().manual_seed(1)
    depth = 1 + 10 * torch.rand(2, 6, 9, generator=g, dtype=F64)
    K = torch.tensor([[20.0, 0, 4.5], [0, 21.0, 3.0], [0, 0, 1]], dtype=F64).expand(2, 3, 3)
    c2w = G.se3_exp(torch.randn(2, 3, generator=g, dtype=F64), torch.randn(2, 3, generator=g, dtype=F64))
    pts = G.unproject(depth, K, c2w)
    uv, z = G.project(pts, K, G.invert_rigid(c2w))
    assert torch.allclose(uv, G.pixel_centres(6, 9, dtype=F64).expand(2, 6, 9, 2), atol=1e-9)
    assert torch.allclose(z, depth, atol=1e-12)


def test_warp_with_ground_truth_reproduces_the_target():
    """Frame 1 of the front camera warped into frame 0 with the generator's depth and poses
    matches frame 0 wherever it is visible (static scene parts; moving cars excluded)."""
    seq = parse_data("synthetic", synthetic={"num_moving": 0}).sequence(
        0, num_frames=2, height=64, width=112, cameras=["CAM_FRONT"])
    f0, f1 = to_torch_frame(seq, 0), to_torch_frame(seq, 1)
    T01 = G.invert_rigid(f1["cam_to_world"]) @ f0["cam_to_world"]
    sky = ~torch.isfinite(f0["depths"])
    warped, valid = G.warp(f1["images"], f0["depths"].masked_fill(sky, 1e4), f0["Ks"], f1["Ks"], T01)
    m = valid[:, 0].bool() & ~sky
    err = (warped - f0["images"]).abs().mean(1)[m]
    identity = (f1["images"] - f0["images"]).abs().mean(1)[m]
    assert m.float().mean() > 0.5
    # texture aliasing at 64x112 leaves a small residual; the unwarped frame is far worse
    assert err.median() < 0.02 and err.mean() < 0.4 * identity.mean()


def test_warp_marks_points_outside_or_behind_invalid():
    src = torch.rand(1, 3, 4, 4)
    K = torch.tensor([[[4.0, 0, 2], [0, 4.0, 2], [0, 0, 1]]])
    behind = torch.eye(4)[None].clone()
    behind[0, 2, 3] = -5.0  # everything ends up behind the source camera
    _, valid = G.warp(src, torch.ones(1, 4, 4), K, K, behind)
    assert valid.sum() == 0


def test_errors_name_the_argument():
    with pytest.raises(ValueError, match="depth"):
        G.unproject(torch.ones(2, 3), torch.eye(3)[None], None)
    with pytest.raises(ValueError, match="K"):
        G.unproject(torch.ones(2, 3, 3), torch.eye(3)[None].expand(3, 3, 3), None)
    bad = torch.eye(4)
    bad[0, 0] = 2
    with pytest.raises(ValueError, match="extr: not a rigid"):
        G.check_rigid(bad, "extr")
    nan = torch.eye(4)
    nan[0, 3] = math.nan
    with pytest.raises(ValueError, match="extr: contains NaN"):
        G.check_rigid(nan, "extr")
