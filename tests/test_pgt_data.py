"""PGT samples (models/pgt/data.py) and losses (models/pgt/losses.py) on tiny synthetic streets."""
from __future__ import annotations

import pytest
import torch

from clsplat.models.common.data import parse_data
from clsplat.models.pgt.data import SPREAD, make_rig_sample, make_sample, rig_layout
from clsplat.models.pgt.losses import chamfer_term, depth_term, render_terms
from clsplat.models.pgt.presets import TINY


@pytest.fixture(scope="module")
def sample():
    return make_sample(parse_data("synthetic"), TINY, 3, "train", torch.Generator().manual_seed(0))


def test_sample_shapes_and_frames(sample):
    s = sample
    V, H, W = TINY.num_views, TINY.height, TINY.width
    assert s.images.shape == (V, 3, H, W) and s.Ks.shape == (V, 3, 3) and s.cam_to_world.shape == (V, 4, 4)
    assert s.depths.shape == (V, H, W) and s.target_images.shape == (V - 1, 3, H, W)
    assert s.target_viewmats.shape == (V - 1, 4, 4) and s.target_depths.shape == (V - 1, H, W)
    assert all(t.dtype == torch.float32 for t in (s.images, s.Ks, s.cam_to_world, s.target_viewmats))
    # the world frame is source view 0's camera; the target camera sits between the two sources
    torch.testing.assert_close(s.cam_to_world[0], torch.eye(4), atol=1e-6, rtol=0)
    centre = torch.linalg.inv(s.target_viewmats[0])[:3, 3]
    torch.testing.assert_close(centre, 0.5 * (s.cam_to_world[0, :3, 3] + s.cam_to_world[1, :3, 3]), atol=0.05, rtol=0)
    assert 1.0 < s.cam_to_world[1, :3, 3].norm() < 2.5  # two frames at 8 m/s and 10 Hz


def test_samples_are_deterministic_and_splits_differ():
    src = parse_data("synthetic")
    a = make_sample(src, TINY, 1, "test")
    b = make_sample(src, TINY, 1, "test")
    c = make_sample(src, TINY, 1, "train")
    assert torch.equal(a.images, b.images) and not torch.equal(a.images, c.images)


def test_camera_mode_uses_adjacent_rig_cameras():
    p = TINY.replace(views="cameras", num_views=2)
    s = make_sample(parse_data("synthetic"), p, 0, "test")
    assert s.name.endswith("CAM_FRONT+CAM_FRONT_LEFT")
    assert s.target_images.shape == (2, 3, p.height, p.width)  # both cameras, one frame later


def test_losses(sample):
    s = sample
    terms = render_terms(s.images, s.images, TINY)
    assert float(terms["l1"]) == 0 and abs(float(terms["dssim"])) < 1e-5 and float(terms["render"]) < 1e-5
    from clsplat.models.pgt.matching import depth_to_u
    u = depth_to_u(s.depths, TINY.min_depth, TINY.max_depth)
    assert float(depth_term(u, u, s.depths, TINY.min_depth, TINY.max_depth)) == 0
    assert float(depth_term(u + 0.1, u, s.depths, TINY.min_depth, TINY.max_depth)) == pytest.approx(0.1, abs=1e-6)
    ij = torch.stack(torch.meshgrid(torch.arange(8.0), torch.arange(8.0), indexing="ij"), -1)
    pts = torch.cat([2 * ij, torch.zeros(8, 8, 1)], -1)[None]  # a 2 m grid: nearest = its own copy
    assert float(chamfer_term(torch.stack([pts[0], pts[0]]), 64)) == 0
    moved = torch.stack([pts[0], pts[0] + torch.tensor([0.0, 0.0, 0.5])])
    assert float(chamfer_term(moved, 64)) == pytest.approx(0.5, rel=0.01)  # 2 x 0.25 when 0.5 m apart


def test_rig_layout():
    assert [rig_layout(n) for n in (3, 8, 12, 18, 24)] == [(2, 2), (2, 4), (2, 6), (3, 6), (4, 6)]
    for bad in (2, 25, 0, 8.0):
        with pytest.raises(ValueError, match="views"):
            rig_layout(bad)


@pytest.mark.parametrize("views", [8, 18])
def test_multi_view_sample_sources_and_targets_between_them(views):
    """N source frames from several cameras at instants 0, 2, 4, ..; the same cameras at the
    instants between as targets (never a source pose)."""
    T, c = rig_layout(views)
    s = make_rig_sample(parse_data("synthetic"), TINY, 1, views, "test")
    H, W = TINY.height, TINY.width
    assert s.images.shape == (views, 3, H, W) and s.depths.shape == (views, H, W)
    assert s.target_images.shape == (c * (T - 1), 3, H, W) and len(s.target_cameras) == c * (T - 1)
    assert s.target_cameras[:c] == tuple(SPREAD[(1 + k) % 6] for k in range(c))  # start camera: index mod 6
    torch.testing.assert_close(s.cam_to_world[0], torch.eye(4), atol=1e-6, rtol=0)
    src = s.cam_to_world[:, :3, 3]
    tgt = torch.linalg.inv(s.target_viewmats)[:, :3, 3]
    # camera k at instant t+1 (a target) lies half-way between itself at instants t and t+2 (sources)
    for t in range(T - 1):
        for k in range(c):
            a, b = t * c + k, (t + 1) * c + k
            if b < views:
                torch.testing.assert_close(tgt[t * c + k], 0.5 * (src[a] + src[b]), atol=0.05, rtol=0)
    # never a source pose: every target is a frame (0.8 m at 8 m/s) from its camera's sources
    src_cams = [s.target_cameras[k % c] for k in range(views)]
    for j, cam in enumerate(s.target_cameras):
        same = torch.tensor([k for k in range(views) if src_cams[k] == cam])
        assert (tgt[j] - src[same]).norm(dim=1).min() > 0.7
