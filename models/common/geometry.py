"""Camera geometry for the models, in torch: batched, differentiable, clsplat's conventions.

Cameras are OpenCV (x right, y down, z forward); depth is z-depth; the centre of pixel (u, v)
is at (u + 0.5, v + 0.5), as in the engine (``K @ [X/Z, Y/Z, 1]`` gives continuous pixel
coordinates with that convention). Rigid transforms are [..., 4, 4]; quaternions are wxyz;
axis-angle vectors are rotation axis × angle (radians).

    pixel_centres, unproject, project, warp          image <-> 3D
    axis_angle_to_matrix, matrix_to_axis_angle, se3_exp, invert_rigid, check_rigid
    quat_to_matrix, matrix_to_quat, quat_multiply
"""
from __future__ import annotations

import torch
import torch.nn.functional as F

from clsplat.quaternion import quat_to_rotmat

__all__ = ["pixel_centres", "unproject", "project", "warp", "axis_angle_to_matrix",
           "matrix_to_axis_angle", "se3_exp", "invert_rigid", "check_rigid", "quat_to_matrix",
           "matrix_to_quat", "quat_multiply"]

_SMALL_ANGLE = 1e-6  # below it, Rodrigues' coefficients use their Taylor series


def _check(t: torch.Tensor, name: str, tail: tuple[int, ...]) -> None:
    if not isinstance(t, torch.Tensor):
        raise ValueError(f"{name}: expected a torch.Tensor, got {type(t).__name__}")
    if t.dim() < len(tail) or tuple(t.shape[t.dim() - len(tail):]) != tail:
        raise ValueError(f"{name}: expected shape [..., {', '.join(map(str, tail))}], got {list(t.shape)}")


def pixel_centres(height: int, width: int, device=None, dtype=torch.float32) -> torch.Tensor:
    """[H, W, 2] pixel-centre coordinates (u + 0.5, v + 0.5)."""
    v, u = torch.meshgrid(torch.arange(height, device=device, dtype=dtype),
                          torch.arange(width, device=device, dtype=dtype), indexing="ij")
    return torch.stack([u, v], -1) + 0.5


def unproject(depth: torch.Tensor, K: torch.Tensor, cam_to_world: torch.Tensor | None = None) -> torch.Tensor:
    """Lift every pixel centre to 3D: cam_to_world · K⁻¹ · [u+½, v+½, 1] · depth.

    Args:
        depth: [B, H, W] z-depth.
        K: [B, 3, 3] intrinsics.
        cam_to_world: [B, 4, 4] or None (camera frame).
    Returns:
        [B, H, W, 3] points.
    """
    if depth.dim() != 3:
        raise ValueError(f"depth: expected shape [B, H, W], got {list(depth.shape)}")
    B, H, W = depth.shape
    _check(K, "K", (3, 3))
    if K.shape[0] != B:
        raise ValueError(f"K: expected {B} intrinsics to match depth, got {K.shape[0]}")
    uv1 = F.pad(pixel_centres(H, W, depth.device, depth.dtype), (0, 1), value=1.0)  # [H,W,3]
    rays = torch.einsum("bij,hwj->bhwi", torch.linalg.inv(K.to(depth.dtype)), uv1)
    pts = rays * depth[..., None]
    if cam_to_world is not None:
        _check(cam_to_world, "cam_to_world", (4, 4))
        T = cam_to_world.to(depth.dtype)
        pts = torch.einsum("bij,bhwj->bhwi", T[:, :3, :3], pts) + T[:, None, None, :3, 3]
    return pts


def project(points: torch.Tensor, K: torch.Tensor, world_to_cam: torch.Tensor | None = None,
            eps: float = 1e-6) -> tuple[torch.Tensor, torch.Tensor]:
    """Project points to continuous pixel coordinates.

    Args:
        points: [B, ..., 3].
        K: [B, 3, 3].
        world_to_cam: [B, 4, 4] or None (points already in the camera frame).
        eps: smallest |z| used in the division (points behind or on the camera get z <= 0;
            check ``z`` before using ``uv``).
    Returns:
        uv [B, ..., 2] and z [B, ...].
    """
    _check(points, "points", (3,))
    B = points.shape[0]
    shape = points.shape
    p = points.reshape(B, -1, 3)
    if world_to_cam is not None:
        _check(world_to_cam, "world_to_cam", (4, 4))
        T = world_to_cam.to(p.dtype)
        p = p @ T[:, :3, :3].transpose(1, 2) + T[:, None, :3, 3]
    z = p[..., 2]
    zs = torch.where(z.abs() < eps, torch.full_like(z, eps), z)
    q = p @ K.to(p.dtype).transpose(1, 2)
    uv = q[..., :2] / zs[..., None]
    return uv.reshape(*shape[:-1], 2), z.reshape(shape[:-1])


def warp(src: torch.Tensor, depth_tgt: torch.Tensor, K_tgt: torch.Tensor, K_src: torch.Tensor,
         T_tgt_to_src: torch.Tensor, min_depth: float = 1e-3) -> tuple[torch.Tensor, torch.Tensor]:
    """Inverse warp: sample ``src`` at where each target pixel's 3D point lands in the source.

    Args:
        src: [B, C, Hs, Ws] source image.
        depth_tgt: [B, H, W] target z-depth.
        K_tgt, K_src: [B, 3, 3] intrinsics of the target and source images.
        T_tgt_to_src: [B, 4, 4] maps target-camera coordinates to source-camera coordinates.
        min_depth: points at source depth below it are invalid.
    Returns:
        warped [B, C, H, W] (bilinear, zeros outside) and valid [B, 1, H, W] (1 where the point
        is in front of the source camera and inside its image).
    """
    if src.dim() != 4:
        raise ValueError(f"src: expected shape [B, C, H, W], got {list(src.shape)}")
    pts = unproject(depth_tgt, K_tgt)
    uv, z = project(pts, K_src, T_tgt_to_src)
    Hs, Ws = src.shape[-2:]
    # grid_sample with align_corners=False: -1 and +1 are the outer edges of the image, so the
    # pixel-centre convention maps u -> 2u/W - 1 exactly.
    grid = torch.stack([2 * uv[..., 0] / Ws - 1, 2 * uv[..., 1] / Hs - 1], -1)
    valid = (z > min_depth) & (grid.abs() <= 1).all(-1)
    grid = torch.where(valid[..., None], grid, torch.full_like(grid, 2.0))  # park invalid outside
    warped = F.grid_sample(src, grid.to(src.dtype), mode="bilinear", padding_mode="zeros", align_corners=False)
    return warped, valid[:, None].to(src.dtype)


def axis_angle_to_matrix(aa: torch.Tensor) -> torch.Tensor:
    """Rodrigues: [..., 3] axis-angle -> [..., 3, 3] rotation (smooth at zero)."""
    _check(aa, "aa", (3,))
    theta2 = (aa * aa).sum(-1, keepdim=True)[..., None]  # [...,1,1]
    theta = theta2.clamp_min(_SMALL_ANGLE ** 2).sqrt()
    small = theta2 < _SMALL_ANGLE ** 2
    a = torch.where(small, 1 - theta2 / 6, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta2 / 24, (1 - torch.cos(theta)) / theta.pow(2))
    x, y, z = aa.unbind(-1)
    o = torch.zeros_like(x)
    Kx = torch.stack([o, -z, y, z, o, -x, -y, x, o], -1).reshape(*aa.shape[:-1], 3, 3)
    eye = torch.eye(3, dtype=aa.dtype, device=aa.device).expand_as(Kx)
    return eye + a * Kx + b * (Kx @ Kx)


def matrix_to_axis_angle(R: torch.Tensor) -> torch.Tensor:
    """[..., 3, 3] rotation -> [..., 3] axis-angle (angle in [0, π]), via the quaternion."""
    q = matrix_to_quat(R)
    q = torch.where(q[..., :1] < 0, -q, q)
    s = q[..., 1:].norm(dim=-1, keepdim=True)
    angle = 2 * torch.atan2(s, q[..., :1])
    scale = torch.where(s < _SMALL_ANGLE, 2 / q[..., :1].clamp_min(_SMALL_ANGLE), angle / s.clamp_min(_SMALL_ANGLE))
    return q[..., 1:] * scale


def se3_exp(aa: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """[..., 4, 4] rigid transform with rotation ``axis_angle_to_matrix(aa)`` and translation t."""
    _check(t, "t", (3,))
    R = axis_angle_to_matrix(aa)
    top = torch.cat([R, t[..., None]], -1)
    bottom = torch.zeros_like(top[..., :1, :])
    bottom[..., 0, 3] = 1
    return torch.cat([top, bottom], -2)


def invert_rigid(T: torch.Tensor) -> torch.Tensor:
    """Inverse of rigid [..., 4, 4] transforms: [Rᵀ, -Rᵀt]."""
    _check(T, "T", (4, 4))
    Rt = T[..., :3, :3].transpose(-1, -2)
    top = torch.cat([Rt, -(Rt @ T[..., :3, 3:])], -1)
    return torch.cat([top, T[..., 3:, :]], -2)


def check_rigid(T: torch.Tensor, name: str, atol: float = 1e-4) -> None:
    """Raise ValueError unless every [4, 4] in T is finite and rigid (orthonormal R, det +1,
    last row 0 0 0 1)."""
    _check(T, name, (4, 4))
    Td = T.detach().double()
    if not torch.isfinite(Td).all():
        raise ValueError(f"{name}: contains NaN or Inf")
    R = Td[..., :3, :3]
    eye = torch.eye(3, dtype=Td.dtype, device=Td.device)
    bottom = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=Td.dtype, device=Td.device)
    if not torch.allclose(Td[..., 3, :], bottom.expand_as(Td[..., 3, :]), atol=1e-6):
        raise ValueError(f"{name}: last row must be [0, 0, 0, 1]")
    if not torch.allclose(R.transpose(-1, -2) @ R, eye.expand_as(R), atol=atol) or (torch.linalg.det(R) < 0).any():
        raise ValueError(f"{name}: not a rigid transform (rotation block must be orthonormal with det +1)")


def quat_to_matrix(q: torch.Tensor) -> torch.Tensor:
    """[..., 4] wxyz (normalised here) -> [..., 3, 3]: :func:`clsplat.quaternion.quat_to_rotmat`
    with this module's input check."""
    _check(q, "q", (4,))
    return quat_to_rotmat(q)


def matrix_to_quat(R: torch.Tensor) -> torch.Tensor:
    """[..., 3, 3] rotation -> [..., 4] unit wxyz, w >= 0 (Shepperd's method: the largest of
    the four candidate pivots is used, so every branch divides by at least 1/2)."""
    _check(R, "R", (3, 3))
    m = R
    t = [1 + m[..., 0, 0] + m[..., 1, 1] + m[..., 2, 2], 1 + m[..., 0, 0] - m[..., 1, 1] - m[..., 2, 2],
         1 - m[..., 0, 0] + m[..., 1, 1] - m[..., 2, 2], 1 - m[..., 0, 0] - m[..., 1, 1] + m[..., 2, 2]]
    cands = torch.stack([
        torch.stack([t[0], m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]], -1),
        torch.stack([m[..., 2, 1] - m[..., 1, 2], t[1], m[..., 0, 1] + m[..., 1, 0], m[..., 0, 2] + m[..., 2, 0]], -1),
        torch.stack([m[..., 0, 2] - m[..., 2, 0], m[..., 0, 1] + m[..., 1, 0], t[2], m[..., 1, 2] + m[..., 2, 1]], -1),
        torch.stack([m[..., 1, 0] - m[..., 0, 1], m[..., 0, 2] + m[..., 2, 0], m[..., 1, 2] + m[..., 2, 1], t[3]], -1),
    ], -2)  # [..., 4, 4]: row k is 4·q·q_k, exact for pivot k
    k = torch.stack(t, -1).argmax(-1)
    q = torch.gather(cands, -2, k[..., None, None].expand(*k.shape, 1, 4))[..., 0, :]
    q = F.normalize(q, dim=-1)
    return torch.where(q[..., :1] < 0, -q, q)


def quat_multiply(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product a ⊗ b of [..., 4] wxyz quaternions (rotation b, then a)."""
    _check(a, "a", (4,))
    _check(b, "b", (4,))
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack([aw * bw - ax * bx - ay * by - az * bz,
                        aw * bx + ax * bw + ay * bz - az * by,
                        aw * by - ax * bz + ay * bw + az * bx,
                        aw * bz + ax * by - ay * bx + az * bw], -1)
