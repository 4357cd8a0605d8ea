"""Volumetric fusion of DrivingForward (models/drivingforward/fusion.py) against a per-voxel reference."""
import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from clsplat.data.synthetic import make_rig
from clsplat.models.drivingforward.fusion import VolumetricFusion, sample_pairs, scale_intrinsics

GRID = dict(voxel_origin=(-12.0, -12.0, -3.0), voxel_size=(4.0, 4.0, 3.0), voxel_shape=(6, 6, 2))


def _rig(h=16, w=28):
    cams = make_rig(width=w * 8, height=h * 8)
    Ks = scale_intrinsics(torch.tensor(np.stack([c.K for c in cams]), dtype=torch.float32), 1 / 8)
    E = torch.tensor(np.stack([c.cam_to_ego for c in cams]), dtype=torch.float32)
    return Ks, E


def _reference_samples(feats, Ks, E, centre):
    """Per camera: (sample [C+1] or None) for one voxel centre, by grid_sample on one point."""
    V, C, h, w = feats.shape
    out = []
    for v in range(V):
        p = torch.linalg.inv(E[v]) @ torch.cat([centre, torch.ones(1)])
        z = float(p[2])
        if z <= 0.1:
            out.append(None)
            continue
        uv = (Ks[v] @ p[:3])[:2] / z
        if not (0 <= uv[0] <= w and 0 <= uv[1] <= h):
            out.append(None)
            continue
        # bilinear with border replication at pixel centres == grid_sample(border, align_corners=False)
        g = torch.stack([2 * uv[0] / w - 1, 2 * uv[1] / h - 1]).view(1, 1, 1, 2)
        s = F.grid_sample(feats[v:v + 1], g, mode="bilinear", padding_mode="border", align_corners=False).view(C)
        out.append(torch.cat([s, torch.tensor([z / 100.0])]))
    return out


def test_sample_pairs_matches_grid_sample():
    torch.manual_seed(0)
    feats = torch.randn(3, 5, 7, 9)
    cam = torch.tensor([0, 1, 2, 2, 1])
    uv = torch.tensor([[0.0, 0.0], [9.0, 7.0], [4.3, 2.2], [0.5, 6.9], [8.7, 0.1]])
    got = sample_pairs(feats, cam, uv)
    for i in range(5):
        g = torch.stack([2 * uv[i, 0] / 9 - 1, 2 * uv[i, 1] / 7 - 1]).view(1, 1, 1, 2)
        want = F.grid_sample(feats[cam[i]:cam[i] + 1], g, padding_mode="border", align_corners=False).view(5)
        assert torch.allclose(got[i], want, atol=1e-5)


def test_pose_mode_averages_the_cameras_that_see_a_voxel():
    torch.manual_seed(1)
    Ks, E = _rig()
    fus = VolumetricFusion(4, "pose", out_channels=(8, 8), **GRID)
    feats = torch.randn(6, 4, 16, 28)
    vol = fus.image_to_voxel(feats, Ks, E)                         # [C+1, Z, Y, X]
    X, Y, Z = GRID["voxel_shape"]
    assert vol.shape == (5, Z, Y, X)
    seen = {0: 0, 1: 0, 2: 0, 3: 0}
    for i, c in enumerate(fus.centres):
        ix, iy, iz = np.unravel_index(i, (X, Y, Z))
        ref = [s for s in _reference_samples(feats, Ks, E, c) if s is not None]
        seen[min(len(ref), 3)] += 1
        want = torch.stack(ref).mean(0) if ref else torch.zeros(5)
        assert torch.allclose(vol[:, iz, iy, ix], want, atol=1e-5), (i, len(ref))
    assert seen[1] and seen[2], seen  # the grid has one- and two-camera voxels


def test_depth_mode_one_two_and_three_camera_voxels():
    torch.manual_seed(2)
    Ks, E = _rig()
    fus = VolumetricFusion(4, "depth", voxel_channels=3, out_channels=(8, 6), depth_bins=5, bin_near=2.0,
                           bin_far=20.0, **GRID)
    feats = torch.randn(6, 4, 16, 28)
    vol = fus.image_to_voxel(feats, Ks, E)
    X, Y, Z = GRID["voxel_shape"]
    counts = {}
    for i, c in enumerate(fus.centres):
        ix, iy, iz = np.unravel_index(i, (X, Y, Z))
        ref = [s for s in _reference_samples(feats, Ks, E, c) if s is not None]
        counts[len(ref)] = counts.get(len(ref), 0) + 1
        if len(ref) == 1:
            want = fus.one_camera(ref[0])
        elif len(ref) == 2:
            want = fus.two_camera(torch.cat(ref))
        else:
            want = torch.zeros(3)
        assert torch.allclose(vol[:, iz, iy, ix], want, atol=1e-5), (i, len(ref))
    assert counts.get(0) and counts.get(1) and counts.get(2), counts


def test_voxel_to_image_samples_along_each_ray():
    """A volume whose features are the voxel's own x coordinate is read back as the ray points' x."""
    Ks, E = _rig(4, 7)
    fus = VolumetricFusion(4, "depth", voxel_channels=1, out_channels=(8, 6), depth_bins=3, bin_near=2.0,
                           bin_far=6.0, voxel_origin=(-20.0, -20.0, -10.0), voxel_size=(1.0, 1.0, 1.0),
                           voxel_shape=(40, 40, 20))
    X, Y, Z = fus.voxel_shape
    vol = fus.centres[:, 0].reshape(X, Y, Z, 1).permute(3, 2, 1, 0).contiguous()
    img = fus.voxel_to_image(vol, Ks, E, 4, 7)                     # [V, 3 * 1, 4, 7]
    v, u = 2, 5
    for cam in (0, 3):
        ray = torch.linalg.inv(Ks[cam]) @ torch.tensor([u + 0.5, v + 0.5, 1.0])
        for k, z in enumerate((2.0, 4.0, 6.0)):
            x = (E[cam, :3, :3] @ (ray * z) + E[cam, :3, 3])[0]
            assert math.isclose(float(img[cam, k, v, u]), float(x), abs_tol=1e-4)


def test_fusion_forward_shapes_and_bad_mode():
    Ks, E = _rig()
    fus = VolumetricFusion(4, "depth", voxel_channels=3, out_channels=(8, 6), depth_bins=5, **GRID)
    assert fus(torch.randn(6, 4, 16, 28), Ks, E).shape == (6, 6, 16, 28)
    pose = VolumetricFusion(4, "pose", out_channels=(8, 5), **GRID)
    assert pose(torch.randn(6, 4, 16, 28), Ks, E).shape == (1, 5, 2, 2)
    with pytest.raises(ValueError, match="mode"):
        VolumetricFusion(4, "bev", **GRID)
