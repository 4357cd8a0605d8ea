"""clsplat/quaternion.py: the torch quaternion -> rotation shared by reference, strategy and
models, against known rotations and the numpy data-layer implementation."""
from __future__ import annotations

import math

import numpy as np
import torch

from clsplat.data.scene import quat_to_rotmat as np_quat_to_rotmat
from clsplat.quaternion import quat_to_rotmat


def test_known_rotations():
    c, s = math.cos(math.pi / 4), math.sin(math.pi / 4)
    q = torch.tensor([[1.0, 0, 0, 0], [c, 0, 0, s], [c, s, 0, 0], [0.0, 0, 1, 0]], dtype=torch.float64)
    R = quat_to_rotmat(q)
    assert torch.allclose(R[0], torch.eye(3, dtype=torch.float64))
    assert torch.allclose(R[1] @ torch.tensor([1.0, 0, 0], dtype=torch.float64),
                          torch.tensor([0.0, 1, 0], dtype=torch.float64))   # 90 deg about z
    assert torch.allclose(R[2] @ torch.tensor([0.0, 1, 0], dtype=torch.float64),
                          torch.tensor([0.0, 0, 1], dtype=torch.float64))   # 90 deg about x
    assert torch.allclose(R[3], torch.diag(torch.tensor([-1.0, 1, -1], dtype=torch.float64)))


def test_any_norm_batch_shape_and_numpy_agreement():
    q = torch.randn(5, 7, 4, generator=torch.Generator().manual_seed(0), dtype=torch.float64) * 3
    R = quat_to_rotmat(q)
    assert R.shape == (5, 7, 3, 3)
    eye = torch.eye(3, dtype=torch.float64).expand_as(R)
    assert torch.allclose(R.transpose(-1, -2) @ R, eye, atol=1e-12)
    assert torch.allclose(torch.linalg.det(R), torch.ones(5, 7, dtype=torch.float64))
    assert torch.allclose(quat_to_rotmat(-q), R)                       # q and -q: one rotation
    np.testing.assert_allclose(R.numpy(), np_quat_to_rotmat(q.numpy().reshape(-1, 4)).reshape(5, 7, 3, 3),
                               atol=1e-12)


def test_gradient_is_tangent_to_the_norm():
    """Normalised inside: the gradient has no component along q (scaling q changes nothing)."""
    q = torch.tensor([0.3, -0.2, 0.9, 0.1], dtype=torch.float64, requires_grad=True)
    (quat_to_rotmat(q) * torch.arange(9.0, dtype=torch.float64).reshape(3, 3)).sum().backward()
    assert torch.isfinite(q.grad).all() and abs(float(q.grad @ q.detach())) < 1e-12
