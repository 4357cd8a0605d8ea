"""DrivingForward geometry and losses (pose.py carrying, losses.py) on the synthetic generator's
ground truth: the carried pose equals every camera's true motion, the warp with true depth and
pose reproduces the target where visible, and the losses prefer the true depth and scale."""
import numpy as np
import pytest
import torch

from clsplat.models.common.data import parse_data, to_torch_frame
from clsplat.models.common.geometry import invert_rigid, warp
from clsplat.models.common.losses import photometric_error
from clsplat.models.drivingforward import losses as L
from clsplat.models.drivingforward.pose import carry_pose, ego_motion

H, W = 64, 112


@pytest.fixture(scope="module")
def seq():
    s = parse_data("synthetic").sequence(3, num_frames=3, height=H, width=W, dt=0.1)
    frames = [to_torch_frame(s, f) for f in range(3)]
    # static, finite-depth pixels of frame t (moving vehicles are not explained by ego motion)
    moving = [v.track_id for v in s.metadata["scene"].vehicles if v.speed > 0]
    f1 = s.frames[1]
    static = np.stack([~np.isin(f1.instances[c], moving) & np.isfinite(f1.depths[c]) for c in s.camera_names])
    return {"frames": frames, "static": torch.from_numpy(static)[:, None].float(), "names": s.camera_names}


def _true_camera_motion(frames, src):
    """Every camera's true motion t -> src: p_src = viewmat_src cam_to_world_t p_t."""
    return frames[src]["viewmats"].double() @ frames[1]["cam_to_world"].double()


def test_carried_pose_is_every_cameras_true_motion(seq):
    fr = seq["frames"]
    E = fr[1]["cam_to_ego"].double()
    for src in (0, 2):
        T = _true_camera_motion(fr, src)
        assert torch.allclose(carry_pose(T[0], E), T, atol=1e-6)
        # the ego motion from the front camera's is the true ego motion ego_t -> ego_src
        M = torch.linalg.inv(fr[src]["ego_to_world"].double()) @ fr[1]["ego_to_world"].double()
        assert torch.allclose(ego_motion(T[0], E[0]), M, atol=1e-6)
    # and the formula is not trivially satisfied: the side cameras' motion differs from the front's
    T = _true_camera_motion(fr, 2)
    assert (T[1, :3, 3] - T[0, :3, 3]).norm() > 0.3


def test_warp_with_true_depth_and_pose_reproduces_the_target(seq):
    fr, static = seq["frames"], seq["static"]
    tgt, depth, Ks = fr[1]["images"], fr[1]["depths"].clamp(max=1e3), fr[1]["Ks"]
    for src in (0, 2):
        T = _true_camera_motion(fr, src).float()
        warped, valid = warp(fr[src]["images"], depth, Ks, Ks, T)
        m = valid * static
        l1 = ((warped - tgt).abs().mean(1, keepdim=True) * m).sum() / m.sum()
        pe = (photometric_error(warped, tgt) * m).sum() / m.sum()
        ident = (photometric_error(fr[src]["images"], tgt) * m).sum() / m.sum()
        print(f"temporal warp t{src - 1:+d} -> t: L1 {l1:.4f}, photometric {pe:.4f} "
              f"(unwarped {ident:.4f}) over {float(m.mean()):.0%} of pixels")
        assert l1 < 0.03 and pe < 0.5 * ident
    # spatial: the neighbouring cameras at t through the rig extrinsics
    E = fr[1]["cam_to_ego"]
    pairs = L.rig_neighbours(E)
    c, n = [a for a, _ in pairs], [b for _, b in pairs]
    warped, valid = warp(tgt[n], depth[c], Ks[c], Ks[n], invert_rigid(E[n]) @ E[c])
    m = valid * static[c]
    l1 = ((warped - tgt[c]).abs().mean(1, keepdim=True) * m).sum() / m.sum()
    print(f"spatial warp neighbour -> camera: L1 {l1:.4f} over {float(m.mean()):.0%} of pixels")
    assert l1 < 0.03 and m.mean() > 0.05


def test_rig_neighbours_follow_the_yaw_order(seq):
    E = seq["frames"][1]["cam_to_ego"]
    names = seq["names"]
    nb = {names[c]: sorted(names[n] for cc, n in L.rig_neighbours(E) if cc == c) for c in range(6)}
    assert nb["CAM_FRONT"] == ["CAM_FRONT_LEFT", "CAM_FRONT_RIGHT"]
    assert nb["CAM_BACK"] == ["CAM_BACK_LEFT", "CAM_BACK_RIGHT"]
    assert nb["CAM_FRONT_LEFT"] == ["CAM_BACK_LEFT", "CAM_FRONT"]
    assert L.rig_neighbours(E[:1]) == []
    assert L.rig_neighbours(E[[0, 5]]) == [(0, 1), (1, 0)]


def test_brightness_normalise_undoes_gain_and_offset():
    torch.manual_seed(0)
    tgt = torch.rand(2, 3, 8, 8)
    valid = (torch.rand(2, 1, 8, 8) > 0.3).float()
    out = L.brightness_normalise(0.6 * tgt + 0.2, tgt, valid)
    assert torch.allclose(out * valid, tgt * valid, atol=1e-3)


def test_losses_prefer_true_depth_scale_and_motion(seq):
    fr = seq["frames"]
    tgt, Ks, E = fr[1]["images"], fr[1]["Ks"], fr[1]["cam_to_ego"]
    depth = fr[1]["depths"].clamp(max=200)[:, None]
    srcs = [fr[0]["images"], fr[2]["images"]]
    M = [torch.linalg.inv(fr[s]["ego_to_world"]) @ fr[1]["ego_to_world"] for s in (0, 2)]
    Tc = [_true_camera_motion(fr, s).float() for s in (0, 2)]
    spatial = {k: float(L.spatial_loss(tgt, depth * k, Ks, E)) for k in (0.5, 1.0, 2.0)}
    st = {k: float(L.spatio_temporal_loss(tgt, srcs, depth * k, Ks, E, M)) for k in (0.5, 1.0, 2.0)}
    tmp = float(L.temporal_loss(tgt, srcs, depth, Ks, Tc))
    still = float(L.temporal_loss(tgt, srcs, depth, Ks, [torch.eye(4).expand(6, 4, 4)] * 2))
    print(f"spatial loss at depth x0.5/x1/x2: {spatial}; spatio-temporal: {st}; temporal true/still {tmp:.4f}/{still:.4f}")
    assert spatial[1.0] < min(spatial[0.5], spatial[2.0])  # the rig's baseline fixes metric scale
    assert st[1.0] < min(st[0.5], st[2.0])
    assert tmp < still



def _scale_gradient(loss_fn, depth, k):
    """d loss / d log(scale) at depth * k: negative means descent makes the depth farther."""
    s = torch.zeros((), requires_grad=True)
    loss_fn(depth * k * s.exp()).backward()
    return float(s.grad)


def test_rig_losses_pull_the_depth_scale_towards_the_truth(seq):
    """Not only a minimum at the true scale: from too near and from too far, the rig losses'
    gradient points towards the true scale."""
    fr = seq["frames"]
    tgt, Ks, E = fr[1]["images"], fr[1]["Ks"], fr[1]["cam_to_ego"]
    depth = fr[1]["depths"].clamp(max=200)[:, None]
    srcs = [fr[0]["images"], fr[2]["images"]]
    M = [torch.linalg.inv(fr[s]["ego_to_world"]) @ fr[1]["ego_to_world"] for s in (0, 2)]
    for name, fn in (("spatial", lambda d: L.spatial_loss(tgt, d, Ks, E)),
                     ("spatio-temporal", lambda d: L.spatio_temporal_loss(tgt, srcs, d, Ks, E, M))):
        g = {k: _scale_gradient(fn, depth, k) for k in (0.5, 2.0)}
        print(f"{name}: d/dlog(scale) at x0.5 {g[0.5]:+.3e}, x2 {g[2.0]:+.3e}")
        assert g[0.5] < 0 < g[2.0], name


def test_rig_overlap_counts_only_pixels_whose_ssim_window_is_inside(seq):
    """A thin overlap strip is mostly border: a pixel whose 3x3 SSIM window reaches the warp's
    zero-filled outside must not count (those windows dominated the error and its gradient)."""
    fr = seq["frames"]
    tgt, Ks, E = fr[1]["images"], fr[1]["Ks"], fr[1]["cam_to_ego"]
    depth = fr[1]["depths"].clamp(max=200)[:, None]
    pairs = L.rig_neighbours(E)
    c, n = [a for a, _ in pairs], [b for _, b in pairs]
    T = invert_rigid(E[n]) @ E[c]
    _, raw = warp(tgt[n], depth[c, 0], Ks[c], Ks[n], T)
    _, counted = L._neighbour_errors(tgt, tgt, depth, Ks, T, pairs)
    window_inside = -torch.nn.functional.max_pool2d(-raw, 3, 1, 1)
    assert 0 < counted.sum() < raw.sum()
    assert torch.equal(counted, window_inside)


def test_without_automask_every_seen_pixel_takes_the_warped_minimum(seq):
    fr = seq["frames"]
    tgt, Ks = fr[1]["images"], fr[1]["Ks"]
    depth = fr[1]["depths"].clamp(max=200)[:, None] * 2.0          # the near road twice as far, as trained
    srcs = [fr[0]["images"], fr[2]["images"]]
    Tc = [_true_camera_motion(fr, s).float() for s in (0, 2)]
    masked = float(L.temporal_loss(tgt, srcs, depth, Ks, Tc))
    unmasked = float(L.temporal_loss(tgt, srcs, depth, Ks, Tc, automask=False))
    # by hand: the minimum over the warped frames, over the pixels at least one of them sees
    errs = []
    for src, T in zip(srcs, Tc):
        w, valid = warp(src, depth[:, 0], Ks, Ks, T)
        errs.append(torch.where(valid > 0, photometric_error(w, tgt), torch.full_like(valid, float("inf"))))
    best = torch.cat(errs, 1).min(1).values
    assert unmasked == pytest.approx(float(best[torch.isfinite(best)].mean()), rel=1e-6)
    assert masked < unmasked           # the identity errors join the minimum only with the auto-mask


def test_without_automask_a_frame_no_source_sees_costs_zero_not_nan(seq):
    fr = seq["frames"]
    tgt, Ks = fr[1]["images"], fr[1]["Ks"]
    depth = torch.full_like(fr[1]["depths"][:, None], 5.0)
    behind = torch.eye(4).expand(6, 4, 4).clone()
    behind[:, 2, 3] = -100.0                           # every point lands behind the source camera
    loss = L.temporal_loss(tgt, [fr[0]["images"]], depth, Ks, [behind], automask=False)
    assert float(loss) == 0.0


def test_automask_margin_masks_only_pixels_the_unwarped_frame_wins_by_more_than_it(seq):
    """With a margin m the identity error joins the minimum as e_id + m: a pixel is masked (no
    depth gradient) only where no warp comes within m of the unwarped frame."""
    fr = seq["frames"]
    tgt, Ks = fr[1]["images"], fr[1]["Ks"]
    depth = (fr[1]["depths"].clamp(max=200)[:, None] * 2.0).requires_grad_(True)
    srcs = [fr[0]["images"], fr[2]["images"]]
    Tc = [_true_camera_motion(fr, s).float() for s in (0, 2)]
    ident = torch.cat([photometric_error(s, tgt) for s in srcs], 1).min(1).values
    warped = []
    for src, T in zip(srcs, Tc):
        w, valid = warp(src, depth[:, 0].detach(), Ks, Ks, T)
        warped.append(torch.where(valid > 0, photometric_error(w, tgt), torch.full_like(valid, float("inf"))))
    best = torch.cat(warped, 1).min(1).values
    m = 0.05
    loss = L.temporal_loss(tgt, srcs, depth, Ks, Tc, margin=m)
    assert float(loss) == pytest.approx(float(torch.minimum(ident + m, best).mean()), rel=1e-5)
    (g,) = torch.autograd.grad(loss, depth)
    took_warp = (best < ident + m)[:, None] & (g != 0)
    # a pixel whose warp is worse than no warp but by less than m now gets a gradient ...
    assert bool((took_warp & (best > ident)[:, None]).any())
    # ... and none where the unwarped frame wins by more than m there and at the 3x3 neighbours
    # that share the pixel through SSIM's window
    near_used = torch.nn.functional.max_pool2d((best <= ident + m)[:, None].float(), 3, 1, 1) > 0
    assert bool((~near_used).any()) and not bool((~near_used & (g != 0)).any())
    assert float(L.temporal_loss(tgt, srcs, depth, Ks, Tc, margin=0.0)) < float(loss)
