"""Rigid-transform and camera maths of the data layer (numpy, float64): quaternions (w, x, y, z)
<-> rotation matrices, 4x4 transforms, unprojecting z-depth and projecting points with pinhole
intrinsics, in the conventions :mod:`clsplat.data.scene` states. Inputs are checked and a bad one
is a ValueError naming the argument. (:mod:`clsplat.quaternion` is the torch counterpart used by
the renderer's reference and the models.)"""
from __future__ import annotations

import numpy as np

__all__ = ["quat_to_rotmat", "rotmat_to_quat", "make_transform", "invert_transform", "unproject_depth",
           "project_points"]


def _as_array(value, name: str, shape: tuple, dtype=np.float64) -> np.ndarray:
    """Convert ``value`` to an array of ``dtype`` and check its shape (``-1`` = any)."""
    try:
        arr = np.asarray(value, dtype=dtype)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be numeric array-like, got {type(value).__name__}: {exc}") from None
    if arr.ndim != len(shape) or any(s != -1 and s != a for s, a in zip(shape, arr.shape)):
        want = "[" + ", ".join("*" if s == -1 else str(s) for s in shape) + "]"
        raise ValueError(f"{name} must have shape {want}, got {list(arr.shape)}")
    if np.issubdtype(arr.dtype, np.floating) and not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be finite, got non-finite values")
    return arr


def _check_rigid(T: np.ndarray, name: str, atol: float = 1e-4) -> None:
    """Raise ValueError unless ``T`` is a rigid homogeneous transform."""
    if not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0], atol=1e-9):
        raise ValueError(f"{name} must have last row [0, 0, 0, 1], got {T[3].tolist()}")
    R = T[:3, :3]
    if not np.allclose(R.T @ R, np.eye(3), atol=atol) or np.linalg.det(R) < 0:
        raise ValueError(f"{name} rotation block must be orthonormal with det +1")


def quat_to_rotmat(q) -> np.ndarray:
    """Rotation matrix from quaternion(s) ``(w, x, y, z)``.

    Args:
        q: ``[4]`` or ``[N, 4]``; normalised internally (must be non-zero).
    Returns:
        ``[3, 3]`` or ``[N, 3, 3]`` float64.
    """
    q = np.asarray(q, dtype=np.float64)
    if q.shape[-1] != 4:
        raise ValueError(f"q must have last dimension 4 (w, x, y, z), got shape {list(q.shape)}")
    n = np.linalg.norm(q, axis=-1, keepdims=True)
    if np.any(n < 1e-12):
        raise ValueError("q must be non-zero quaternion(s)")
    w, x, y, z = np.moveaxis(q / n, -1, 0)
    R = np.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        axis=-1,
    )
    return R.reshape(q.shape[:-1] + (3, 3))


def rotmat_to_quat(R) -> np.ndarray:
    """Quaternion ``(w, x, y, z)`` with ``w >= 0`` from rotation matrix ``[3, 3]``."""
    R = _as_array(R, "R", (3, 3))
    tr = np.trace(R)
    if tr > 0:
        s = np.sqrt(tr + 1.0) * 2
        q = [0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = np.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2]) * 2
        q = [(R[2, 1] - R[1, 2]) / s, 0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s]
    elif R[1, 1] > R[2, 2]:
        s = np.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2]) * 2
        q = [(R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s]
    else:
        s = np.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1]) * 2
        q = [(R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s]
    q = np.asarray(q)
    q /= np.linalg.norm(q)
    return -q if q[0] < 0 else q


def make_transform(R=None, t=None, quat=None) -> np.ndarray:
    """Homogeneous ``[4, 4]`` transform from rotation (``R`` [3,3] or ``quat`` wxyz) and translation ``t`` [3]."""
    if R is not None and quat is not None:
        raise ValueError("give either R or quat, not both")
    T = np.eye(4)
    if quat is not None:
        T[:3, :3] = quat_to_rotmat(_as_array(quat, "quat", (4,)))
    elif R is not None:
        T[:3, :3] = _as_array(R, "R", (3, 3))
    if t is not None:
        T[:3, 3] = _as_array(t, "t", (3,))
    return T


def invert_transform(T) -> np.ndarray:
    """Inverse of a rigid ``[4, 4]`` (or batched ``[N, 4, 4]``) transform."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape[-2:] != (4, 4):
        raise ValueError(f"T must have shape [..., 4, 4], got {list(T.shape)}")
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    out = np.zeros_like(T)
    Rt = np.swapaxes(R, -1, -2)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, t)
    out[..., 3, 3] = 1.0
    return out


def unproject_depth(depth, K, cam_to_world=None) -> np.ndarray:
    """Lift a z-depth map to 3D points at the pixel centres ``(x + 0.5, y + 0.5)``.

    Args:
        depth: ``[H, W]`` z-depth in metres (``inf``/``nan`` allowed; they propagate).
        K: ``[3, 3]`` intrinsics.
        cam_to_world: optional ``[4, 4]``; if given, points are returned in world frame.
    Returns:
        ``[H, W, 3]`` float64 points (camera frame, or world frame if ``cam_to_world``).
    """
    depth = np.asarray(depth, dtype=np.float64)
    if depth.ndim != 2:
        raise ValueError(f"depth must have shape [H, W], got {list(depth.shape)}")
    K = _as_array(K, "K", (3, 3))
    H, W = depth.shape
    u, v = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    x = (u - K[0, 2]) / K[0, 0] * depth
    y = (v - K[1, 2]) / K[1, 1] * depth
    pts = np.stack([x, y, depth], axis=-1)
    if cam_to_world is not None:
        T = _as_array(cam_to_world, "cam_to_world", (4, 4))
        with np.errstate(invalid="ignore", over="ignore"):
            pts = pts @ T[:3, :3].T + T[:3, 3]
    return pts


def project_points(points, K, world_to_cam=None) -> tuple[np.ndarray, np.ndarray]:
    """Project 3D points with a pinhole camera.

    Args:
        points: ``[..., 3]`` points (world frame if ``world_to_cam`` is given, else camera frame).
        K: ``[3, 3]`` intrinsics.
        world_to_cam: optional ``[4, 4]``.
    Returns:
        ``(uv, z)``: continuous pixel coordinates ``[..., 2]`` (pixel centres at +0.5) and
        z-depth ``[...]``; points with ``z <= 0`` get ``uv = nan``.
    """
    p = np.asarray(points, dtype=np.float64)
    if p.shape[-1] != 3:
        raise ValueError(f"points must have shape [..., 3], got {list(p.shape)}")
    K = _as_array(K, "K", (3, 3))
    if world_to_cam is not None:
        T = _as_array(world_to_cam, "world_to_cam", (4, 4))
        p = p @ T[:3, :3].T + T[:3, 3]
    z = p[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uvw = p @ K.T
        uv = uvw[..., :2] / uvw[..., 2:3]
    uv[z <= 0] = np.nan
    return uv, z


# --------------------------------------------------------------------------------------
# dataclasses
# --------------------------------------------------------------------------------------
