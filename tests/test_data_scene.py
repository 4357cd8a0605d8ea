"""Data model: geometry helpers and validation of Camera / Frame / Box3D / DrivingSequence."""
import numpy as np
import pytest

from clsplat.data.scene import (
    Box3D, Camera, DrivingSequence, Frame, LidarPoints, invert_transform, make_transform,
    project_points, quat_to_rotmat, rotmat_to_quat, unproject_depth,
)

K = np.array([[50.0, 0, 32], [0, 50.0, 16], [0, 0, 1]])


def _cam(name="CAM_FRONT", w=64, h=32):
    return Camera(name, K, np.eye(4), w, h)


def test_quaternion_roundtrip_and_convention():
    rng = np.random.default_rng(0)
    for _ in range(20):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        q = q if q[0] >= 0 else -q
        R = quat_to_rotmat(q)
        assert np.allclose(R @ R.T, np.eye(3), atol=1e-12)
        assert np.allclose(rotmat_to_quat(R), q, atol=1e-10)
    # wxyz: 90 deg about z maps x to y
    q = [np.cos(np.pi / 4), 0, 0, np.sin(np.pi / 4)]
    assert np.allclose(quat_to_rotmat(q) @ [1, 0, 0], [0, 1, 0])
    with pytest.raises(ValueError, match="q must"):
        quat_to_rotmat([0, 0, 0, 0])


def test_transform_inverse_and_projection_roundtrip():
    T = make_transform(quat=[0.9, 0.1, -0.2, 0.3], t=[1, 2, 3])
    assert np.allclose(invert_transform(T) @ T, np.eye(4), atol=1e-12)
    depth = np.random.default_rng(1).uniform(1, 50, (32, 64)).astype(np.float32)
    pts = unproject_depth(depth, K, T)
    uv, z = project_points(pts, K, invert_transform(T))
    u, v = np.meshgrid(np.arange(64) + 0.5, np.arange(32) + 0.5)
    assert np.allclose(uv[..., 0], u, atol=1e-6) and np.allclose(uv[..., 1], v, atol=1e-6)
    assert np.allclose(z, depth, rtol=1e-6)
    uv, _ = project_points(np.array([[0, 0, -1.0]]), K)
    assert np.isnan(uv).all()


def test_camera_validation_messages():
    with pytest.raises(ValueError, match="K must have shape"):
        Camera("c", np.eye(2), np.eye(4), 4, 4)
    with pytest.raises(ValueError, match="width must be a positive int"):
        Camera("c", K, np.eye(4), 0, 4)
    with pytest.raises(ValueError, match="orthonormal"):
        Camera("c", K, np.diag([2.0, 1, 1, 1]), 4, 4)
    with pytest.raises(ValueError, match="focal"):
        Camera("c", np.diag([-1.0, 1, 1]), np.eye(4), 4, 4)
    assert abs(_cam().hfov_deg - np.degrees(2 * np.arctan(32 / 50))) < 1e-9


def test_frame_and_sequence_validation():
    img = np.zeros((32, 64, 3), np.float32)
    with pytest.raises(ValueError, match=r"images\['CAM_FRONT'\] must have shape"):
        Frame(0.0, np.eye(4), {"CAM_FRONT": np.zeros((32, 64))})
    with pytest.raises(ValueError, match=r"lie in \[0, 1\]"):
        Frame(0.0, np.eye(4), {"CAM_FRONT": img + 2})
    with pytest.raises(ValueError, match="must be 32x64"):
        Frame(0.0, np.eye(4), {"CAM_FRONT": img}, depths={"CAM_FRONT": np.zeros((8, 8))})
    with pytest.raises(ValueError, match="no matching entry"):
        Frame(0.0, np.eye(4), {"CAM_FRONT": img}, depths={"CAM_BACK": np.zeros((32, 64))})
    with pytest.raises(ValueError, match="timestamp"):
        Frame("soon", np.eye(4), {"CAM_FRONT": img})
    f = Frame(0.5, np.eye(4), {"CAM_FRONT": img}, depths={"CAM_FRONT": np.full((32, 64), np.inf)})
    with pytest.raises(ValueError, match="no image for camera 'CAM_BACK'"):
        DrivingSequence([_cam(), _cam("CAM_BACK")], [f])
    seq = DrivingSequence([_cam()], [f])
    assert seq.viewmats(0).shape == (1, 4, 4) and seq.images(0).shape == (1, 32, 64, 3)
    with pytest.raises(ValueError, match="frame index 3 out of range"):
        seq.viewmats(3)
    with pytest.raises(ValueError, match="camera 'X' not in sequence"):
        seq.camera("X")
    # per-camera pose override wins over the rig
    T = make_transform(t=[1, 2, 3])
    f2 = Frame(0.5, np.eye(4), {"CAM_FRONT": img}, camera_poses={"CAM_FRONT": T})
    assert np.allclose(DrivingSequence([_cam()], [f2]).cam_to_world(0, "CAM_FRONT"), T)


def test_box_and_lidar():
    b = Box3D(3, "car", [4, 2, 1.5], [10, 0, 0.75], [np.cos(0.3), 0, 0, np.sin(0.3)])
    c = b.corners()
    assert c.shape == (8, 3) and b.contains(c, margin=1e-9).all()
    assert b.contains(np.array([10, 0, 0.75])) and not b.contains(np.array([13, 0, 0.75]))
    with pytest.raises(ValueError, match="track_id must be a positive int"):
        Box3D(0, "car", [1, 1, 1], [0, 0, 0], [1, 0, 0, 0])
    with pytest.raises(ValueError, match="size must be positive"):
        Box3D(1, "car", [1, -1, 1], [0, 0, 0], [1, 0, 0, 0])
    E = make_transform(quat=[np.cos(0.2), 0, 0, np.sin(0.2)], t=[5, 1, 0])
    lp = LidarPoints(np.random.default_rng(0).normal(size=(100, 3)), np.zeros(100), "ego")
    back = lp.to_world(E).to_ego(E)
    assert back.frame == "ego" and np.allclose(back.points, lp.points, atol=1e-5)
    with pytest.raises(ValueError, match="frame must be 'ego' or 'world'"):
        LidarPoints(np.zeros((1, 3)), np.zeros(1), "lidar")
    with pytest.raises(ValueError, match=r"intensity must have shape \[1\]"):
        LidarPoints(np.zeros((1, 3)), np.zeros(2))
