"""DrivingForward model (model.py): gradient paths, reconstruction from any subset of cameras and
frames, SF/MF training losses, .ply export, and errors that name the bad argument."""
import pytest
import torch

from clsplat.models.common.data import parse_data
from clsplat.models.common.gaussians import GaussianSet
from clsplat.models.common.geometry import unproject
from clsplat.models.common.presets import get_preset
from clsplat.models.drivingforward.data import colour_jitter, gt_ego_motion, load_triplet
from clsplat.models.drivingforward.losses import smoothness_loss
from clsplat.models.drivingforward.model import DrivingForward

TINY = get_preset("drivingforward", "tiny")
HW = TINY.height * TINY.width


@pytest.fixture(scope="module")
def sample():
    return load_triplet(parse_data("synthetic"), 1, TINY)


@pytest.fixture(scope="module")
def model():
    torch.manual_seed(0)
    return DrivingForward(TINY)


def _without_grad(m, prefix=""):
    return [n for n, q in m.named_parameters() if n.startswith(prefix) and (q.grad is None or not q.grad.abs().sum() > 0)]


def test_gradients_reach_every_parameter_through_render_and_through_warps(model, sample):
    net = colour_jitter(sample["images"], torch.Generator().manual_seed(0))
    terms = model.training_losses(sample["images"], net, sample["Ks"], sample["cam_to_ego"])
    assert set(terms) == {"loss", "reproj", "smooth", "spatial", "spatio_temporal", "render", "mse",
                          "diag_depth_median", "diag_translation"}  # no lpips
    assert all(torch.isfinite(v) for v in terms.values())
    model.zero_grad()
    terms["render"].backward(retain_graph=True)       # renderer alone: depth (means), pose (viewmats), Gaussians
    assert _without_grad(model) == []
    model.zero_grad()
    terms["reproj"].backward()                        # warps alone: depth and pose; the Gaussian net takes no part
    assert _without_grad(model, "depth_net") == [] and _without_grad(model, "pose_net") == []
    assert len(_without_grad(model, "gaussian_net")) == len(list(model.gaussian_net.parameters()))
    model.zero_grad()


def test_warmup_trains_the_pose_network_only_through_the_temporal_terms(sample):
    torch.manual_seed(0)
    m = DrivingForward(TINY.replace(warmup_steps=2))
    for step, depth_trained in ((1, False), (2, True)):
        terms = m.training_losses(sample["images"], sample["images"], sample["Ks"], sample["cam_to_ego"],
                                  step=step)
        m.zero_grad()
        (terms["reproj"] + terms["spatio_temporal"]).backward()
        assert _without_grad(m, "pose_net") == []
        assert (_without_grad(m, "depth_net") == []) == depth_trained, step
    with pytest.raises(ValueError, match="warmup_steps"):
        TINY.replace(warmup_steps=-1)


def test_mf_mode_renders_frame_t_from_its_neighbours(sample):
    torch.manual_seed(0)
    m = DrivingForward(TINY.replace(mode="MF"))
    terms = m.training_losses(sample["images"], sample["images"], sample["Ks"], sample["cam_to_ego"])
    terms["render"].backward()
    assert torch.isfinite(terms["loss"]) and _without_grad(m) == []


@pytest.mark.parametrize("cams", [[0], [2, 4], [0, 1, 2, 3, 4, 5]])
def test_reconstruct_any_camera_subset_one_gaussian_per_pixel(model, sample, cams):
    I, Ks, E = sample["images"][1, cams], sample["Ks"][cams], sample["cam_to_ego"][cams]
    g = model.reconstruct(I, Ks, E)
    assert isinstance(g, GaussianSet) and len(g) == len(cams) * HW
    g.validate()
    # means are the pixel centres lifted with the predicted depth, in the ego frame
    with torch.no_grad():
        d = model.depth_net(I, Ks, E)["depth"][:, 0]
    assert torch.allclose(g.means, unproject(d, Ks, E).reshape(-1, 3), atol=1e-4)


def test_reconstruct_any_frame_subset_in_the_reference_ego_frame(model, sample):
    cams = [1, 3]
    I, Ks, E = sample["images"][:, cams], sample["Ks"][cams], sample["cam_to_ego"][cams]
    V = len(cams)
    # frames t and t+1 with the given ego motion: frame t+1's Gaussians move into the ego frame at t
    M = gt_ego_motion(sample)
    to_ref = torch.stack([torch.eye(4), torch.linalg.inv(M[2])])
    g2 = model.reconstruct(I[1:], Ks, E, frame_to_ref=to_ref, ref=0)
    assert len(g2) == 2 * V * HW
    alone = model.reconstruct(I[2], Ks, E)
    assert torch.allclose(g2.means[V * HW:], alone.means @ to_ref[1, :3, :3].T + to_ref[1, :3, 3], atol=1e-4)
    # frames t-1, t+1 (MF's inputs) with the pose network's motion
    assert len(model.reconstruct(I[[0, 2]], Ks, E)) == 2 * V * HW


def test_reconstruction_renders_and_exports(model, sample, tmp_path):
    g = model.reconstruct(sample["images"][1], sample["Ks"], sample["cam_to_ego"])
    viewmats = sample["viewmats"][2] @ sample["ego_to_world"][1]
    colors, alphas = model.render(g, viewmats, sample["Ks"])
    assert colors.shape == (6, 3, TINY.height, TINY.width) and alphas.shape == (6, 1, TINY.height, TINY.width)
    assert torch.isfinite(colors).all() and float(alphas.mean()) > 0.5
    back = GaussianSet.load_ply(g.save_ply(tmp_path / "scene.ply"))
    assert len(back) == len(g) and torch.allclose(back.means, g.means)


def test_bad_inputs_name_the_argument(model, sample):
    I, Ks, E = sample["images"][1], sample["Ks"], sample["cam_to_ego"]
    with pytest.raises(ValueError, match=r"images: preset 'tiny' needs 32x56"):
        model.reconstruct(torch.rand(6, 3, 40, 56), Ks, E)
    with pytest.raises(ValueError, match=r"Ks: expected \[6, 3, 3\]"):
        model.reconstruct(I, Ks[:5], E)
    with pytest.raises(ValueError, match=r"cam_to_ego: expected \[6, 4, 4\]"):
        model.reconstruct(I, Ks, E[:4])
    with pytest.raises(ValueError, match="images: contain NaN"):
        model.reconstruct(torch.where(torch.rand_like(I) < 0.01, torch.nan, I), Ks, E)
    bad = E.clone()
    bad[2, :3, :3] *= 1.2
    with pytest.raises(ValueError, match=r"cam_to_ego\[2\].*rigid"):
        model.reconstruct(I, Ks, bad)
    with pytest.raises(ValueError, match=r"frame 1: images"):
        model.training_losses(torch.stack([I, torch.full_like(I, torch.nan), I]), sample["images"], Ks, E)
    with pytest.raises(ValueError, match=r"frame_to_ref: expected \[1, 4, 4\]"):
        model.reconstruct(I, Ks, E, frame_to_ref=torch.eye(4)[None].expand(2, 4, 4))
    with pytest.raises(ValueError, match="unknown preset 'huge'"):
        get_preset("drivingforward", "huge")
    with pytest.raises(ValueError, match="CAM_TOP"):
        load_triplet(parse_data("synthetic"), 0, TINY, cameras=["CAM_FRONT", "CAM_TOP"])


def test_optimizer_gives_the_pose_network_its_own_learning_rate(model):
    from clsplat.models.drivingforward.cli import make_optimizer

    for pose_lr, expected in ((None, TINY.lr), (1e-3, 1e-3)):
        opt = make_optimizer(model, TINY.replace(pose_lr=pose_lr))
        rest, pose = opt.param_groups
        assert rest["lr"] == TINY.lr and pose["lr"] == expected
        assert {id(q) for q in pose["params"]} == {id(q) for q in model.pose_net.parameters()}
        assert len(rest["params"]) + len(pose["params"]) == len(list(model.parameters()))


@pytest.mark.parametrize("detach", [False, True])
def test_render_loss_reaches_the_pose_network_only_when_the_preset_allows(sample, detach):
    # detach_render_pose: the render's viewmats carry the motion as a constant (issue 17, lead 2)
    torch.manual_seed(0)
    m = DrivingForward(TINY.replace(detach_render_pose=detach))
    terms = m.training_losses(sample["images"], sample["images"], sample["Ks"], sample["cam_to_ego"])
    m.zero_grad()
    terms["render"].backward(retain_graph=True)
    pose_params = len(list(m.pose_net.parameters()))
    assert len(_without_grad(m, "pose_net")) == (pose_params if detach else 0)
    assert _without_grad(m, "depth_net") == [] and _without_grad(m, "gaussian_net") == []
    m.zero_grad()
    terms["reproj"].backward()                        # the temporal warp still trains the pose
    assert _without_grad(m, "pose_net") == []


def test_dataset_pose_drives_the_warps_and_leaves_the_pose_network_untrained(sample):
    torch.manual_seed(0)
    m = DrivingForward(TINY.replace(pose_source="dataset"))
    M = gt_ego_motion(sample)
    terms = m.training_losses(sample["images"], sample["images"], sample["Ks"], sample["cam_to_ego"],
                              ego_motion_gt=[M[0], M[2]])
    m.zero_grad()
    terms["loss"].backward()
    assert len(_without_grad(m, "pose_net")) == len(list(m.pose_net.parameters()))
    assert _without_grad(m, "depth_net") == []
    E0 = sample["cam_to_ego"][0]
    t_true = (torch.linalg.inv(E0) @ M[2] @ E0)[:3, 3].norm()
    assert float(terms["diag_translation"]) == pytest.approx(float(t_true), rel=1e-5)
    assert 0.7 < float(t_true) < 0.9                    # the generator's 8 m/s at 0.1 s
    # the given motion is what the warps use: no motion gives other warped errors
    with torch.no_grad():
        still = m.training_losses(sample["images"], sample["images"], sample["Ks"], sample["cam_to_ego"],
                                  ego_motion_gt=[torch.eye(4), torch.eye(4)])
    for k in ("reproj", "spatio_temporal"):
        assert float(still[k]) != pytest.approx(float(terms[k].detach()), rel=1e-4), k
    with pytest.raises(ValueError, match="ego_motion_gt"):
        m.training_losses(sample["images"], sample["images"], sample["Ks"], sample["cam_to_ego"])
    with pytest.raises(ValueError, match="pose_source"):
        TINY.replace(pose_source="lidar")


def test_pose_translation_init_starts_the_pose_network_at_that_motion(sample):
    torch.manual_seed(0)
    m = DrivingForward(TINY.replace(pose_translation_init=(0.0, 0.0, -0.8)))
    with torch.no_grad():
        T = m.pose_net(sample["images"][1], sample["images"][2], sample["Ks"], sample["cam_to_ego"])
    assert torch.allclose(T[:3, 3], torch.tensor([0.0, 0.0, -0.8]), atol=0.02)
    torch.manual_seed(0)
    with torch.no_grad():
        T0 = DrivingForward(TINY).pose_net(sample["images"][1], sample["images"][2], sample["Ks"], sample["cam_to_ego"])
    assert float(T0[:3, 3].norm()) < 0.02                 # the paper's initialisation: about no motion
    with pytest.raises(ValueError, match="pose_translation_init"):
        TINY.replace(pose_translation_init=(0.0, 0.0, -9.0))


def test_pose_zero_init_starts_at_no_motion_and_still_learns(sample):
    """``pose_zero_init``: the untrained pose network predicts exactly the identity (no random motion
    of a few degrees), and its output layer still gets a gradient (its inputs are not zero)."""
    torch.manual_seed(0)
    m = DrivingForward(TINY.replace(pose_zero_init=True, pose_scale=0.1))
    T = m.pose_net(sample["images"][1], sample["images"][2], sample["Ks"], sample["cam_to_ego"])
    assert torch.equal(T.detach(), torch.eye(4, dtype=T.dtype))
    T[:3, 3].sum().backward()
    assert float(m.pose_net.decoder.pose_2.weight.grad.abs().sum()) > 0
    with pytest.raises(ValueError, match="pose_zero_init"):
        TINY.replace(pose_zero_init=1)


def test_depth_skips_feed_the_encoders_half_and_quarter_features_to_the_depth_decoder(sample):
    torch.manual_seed(0)
    m = DrivingForward(TINY.replace(depth_skips=True))
    assert [s["upconv_1"][0].in_channels for s in m.depth_net.decoder.stages] == [256, 128, 64 + 64, 32 + 64, 16]
    d = m.depth_net(sample["images"][1], sample["Ks"], sample["cam_to_ego"])
    assert d["depth"].shape == (sample["Ks"].shape[0], 1, TINY.height, TINY.width)
    m.zero_grad()
    d["depth"].mean().backward()
    # the skips carry gradient into the encoder's first stages by a path the fused 1/8 feature has not
    assert m.depth_net.encoder.conv1.weight.grad.abs().sum() > 0
    with pytest.raises(ValueError, match="skips"):
        m.depth_net.decoder(d["f8"])


def test_photometric_pyramid_averages_the_terms_over_its_levels(model, sample):
    args = (sample["images"], sample["images"], sample["Ks"], sample["cam_to_ego"])
    one = model.training_losses(*args)
    model.preset = TINY.replace(photometric_scales=2)
    try:
        two = model.training_losses(*args)
    finally:
        model.preset = TINY
    for k in ("reproj", "spatial", "spatio_temporal"):
        assert torch.isfinite(two[k]) and not torch.equal(one[k], two[k]), k
    # level 0 of the pyramid is the full-resolution term: 2 * two - one is level 1 alone, a valid error
    assert 0 <= float(2 * two["reproj"] - one["reproj"]) < 1
    assert torch.equal(one["smooth"], two["smooth"]) and torch.equal(one["render"], two["render"])
    with pytest.raises(ValueError, match="photometric_scales"):
        TINY.replace(photometric_scales=5)         # 2^4 does not divide 32x56


def test_automask_steps_keep_the_auto_mask_for_the_first_steps_only(sample):
    torch.manual_seed(0)
    m = DrivingForward(TINY.replace(automask_steps=2))
    args = (sample["images"], sample["images"], sample["Ks"], sample["cam_to_ego"])
    with torch.no_grad():
        r = {s: float(m.training_losses(*args, step=s)["reproj"]) for s in (0, 1, 2)}
        m.preset = TINY                                  # the paper: the auto-mask at every step
        paper = {s: float(m.training_losses(*args, step=s)["reproj"]) for s in (0, 2)}
    assert r[0] == r[1] == paper[0] == paper[2]
    assert r[2] > r[0]            # without the identity errors in the minimum the error cannot be lower
    with pytest.raises(ValueError, match="automask_steps"):
        TINY.replace(automask_steps=-1)


def test_smooth_order_selects_the_smoothness_term(sample):
    torch.manual_seed(0)
    m = DrivingForward(TINY)
    args = (sample["images"], sample["images"], sample["Ks"], sample["cam_to_ego"])
    with torch.no_grad():
        first = m.training_losses(*args)
        m.preset = TINY.replace(smooth_order=2)
        second = m.training_losses(*args)
    depth = m.depth_net(sample["images"][1], sample["Ks"], sample["cam_to_ego"])["depth"].detach()
    torch.testing.assert_close(second["smooth"], smoothness_loss(depth, sample["images"][1], order=2))
    assert float(first["smooth"]) != float(second["smooth"])
    torch.testing.assert_close(first["reproj"], second["reproj"])
    with pytest.raises(ValueError, match="smooth_order"):
        TINY.replace(smooth_order=3)


def test_ground_prior_trains_finite_and_passes_gradient_to_the_decoder(sample):
    torch.manual_seed(0)
    m = DrivingForward(TINY.replace(ground_prior_cap=20.0))
    t = m.training_losses(sample["images"], sample["images"], sample["Ks"], sample["cam_to_ego"])
    assert torch.isfinite(t["loss"])
    t["loss"].backward()
    g = m.depth_net.decoder.dispconv.weight.grad
    assert g is not None and torch.isfinite(g).all() and g.abs().sum() > 0


def test_a_loss_term_of_weight_zero_is_left_out(sample, monkeypatch):
    import clsplat.models.drivingforward.model as dfm

    torch.manual_seed(0)
    m = DrivingForward(TINY)
    args = (sample["images"], sample["images"], sample["Ks"], sample["cam_to_ego"])
    with torch.no_grad():
        full = m.training_losses(*args)

        def never(*a, **k):
            raise AssertionError("a term of weight 0 was computed")
        monkeypatch.setattr(dfm, "spatio_temporal_loss", never)
        m.preset = TINY.replace(w_spatio_temporal=0.0)
        no_st = m.training_losses(*args)
        monkeypatch.setattr(dfm, "spatial_loss", never)
        m.preset = TINY.replace(w_spatio_temporal=0.0, w_spatial=0.0)
        neither = m.training_losses(*args)
    assert "spatio_temporal" not in no_st and "spatial" in no_st
    assert "spatial" not in neither and "spatio_temporal" not in neither
    for k in ("reproj", "smooth", "spatial", "render"):
        torch.testing.assert_close(no_st[k], full[k])
    # the total is the paper's sum without the dropped terms
    torch.testing.assert_close(no_st["loss"], full["loss"] - TINY.w_spatio_temporal * full["spatio_temporal"])
    torch.testing.assert_close(neither["loss"], no_st["loss"] - TINY.w_spatial * full["spatial"])
    for bad in (-0.1, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="w_spatio_temporal must be a finite number >= 0"):
            TINY.replace(w_spatio_temporal=bad)


def test_local_correlation_finds_a_known_shift():
    """The correlation cue (issue 32): a later image that is the earlier one moved 8 px right and
    4 px down reads, at 1/4 resolution, as a displacement of (2, 1): the score is highest there and
    the soft-argmax flow says so, away from the borders; the channels are (2r+1)^2 scores + 2."""
    from clsplat.models.drivingforward.pose import local_correlation
    g = torch.Generator().manual_seed(0)
    earlier = torch.rand(2, 3, 32, 56, generator=g)
    later = torch.roll(earlier, shifts=(4, 8), dims=(2, 3))
    cue = local_correlation(earlier, later, 3, 4)
    assert cue.shape == (2, 49 + 2, 8, 14)
    inner = (slice(None), slice(None), slice(2, -2), slice(3, -3))
    best = cue[:, :49][inner].argmax(dim=1)
    assert bool((best == (1 + 3) * 7 + (2 + 3)).all())       # row-major (dy, dx) from (-3, -3)
    flow = cue[:, 49:][inner].mean(dim=(0, 2, 3))
    assert torch.allclose(flow, torch.tensor([2.0, 1.0]), atol=0.1)
    assert float(cue[:, :49].abs().max()) <= 1.0 + 1e-5


@pytest.mark.parametrize("mode", ["bev", "camera", "camera_only"])
def test_pose_correlation_cue_starts_at_no_motion_and_is_trained(sample, mode):
    """pose_corr_radius > 0: with the zero-initialised outputs the untrained network still predicts
    exactly no motion, and the temporal loss trains the cue's own layers (in "bev" mode once the
    decoder's output layer is no longer zero, as after a first step)."""
    torch.manual_seed(0)
    m = DrivingForward(TINY.replace(pose_corr_radius=2, pose_corr_mode=mode, pose_zero_init=True,
                                    pose_translation_scale=1.0))
    T = m.pose_net(sample["images"][1], sample["images"][2], sample["Ks"], sample["cam_to_ego"])
    assert torch.equal(T.detach(), torch.eye(4, dtype=T.dtype))
    if mode == "bev":
        with torch.no_grad():
            m.pose_net.decoder.pose_2.weight.normal_(0.0, 1e-3)
    terms = m.training_losses(sample["images"], sample["images"], sample["Ks"], sample["cam_to_ego"])
    terms["reproj"].backward()
    head = m.pose_net.corr_proj if mode == "bev" else m.pose_net.odometry.out
    assert float(head.weight.grad.abs().sum()) > 0
    assert (m.pose_net.odometry is None) == (mode == "bev") and (m.pose_net.corr_proj is None) == (mode != "bev")
    if mode == "camera_only":     # the decoder's translation takes no part: only its rotation outputs learn
        assert float(m.pose_net.decoder.pose_2.weight.grad[3:].abs().sum()) == 0
        assert float(m.pose_net.decoder.pose_2.weight.grad[:3].abs().sum()) > 0


def test_camera_odometry_head_reads_each_camera_in_its_own_frame(sample):
    """pose_corr_mode "camera": camera c's translation t_c (its own frame) enters camera 0's as
    R_0^T R_c t_c, averaged over the cameras. A head that says "1 m along my own optical axis" for
    every camera gives camera 0 the mean of the rig's optical axes, seen from camera 0."""
    torch.manual_seed(0)
    m = DrivingForward(TINY.replace(pose_corr_radius=1, pose_corr_mode="camera", pose_zero_init=True,
                                    pose_translation_scale=1.0))
    V = sample["Ks"].shape[0]
    m.pose_net.odometry.forward = lambda cue: torch.tensor([[0.0, 0.0, 1.0]]).expand(V, 3)
    with torch.no_grad():
        T = m.pose_net(sample["images"][1], sample["images"][2], sample["Ks"], sample["cam_to_ego"])
    R = sample["cam_to_ego"][:, :3, :3]
    expected = R[0].T @ R[:, :, 2].mean(0)
    assert torch.allclose(T[:3, 3], expected, atol=1e-5)
    assert float(expected.norm()) < 0.99                     # the rig's cameras do not all look one way


def test_pose_translation_scale_sets_the_translations_own_multiplier(sample):
    """pose_translation_scale: the translation outputs are multiplied by it, the rotation keeps
    pose_scale; pose_translation_init goes through the same multiplier."""
    torch.manual_seed(0)
    m = DrivingForward(TINY.replace(pose_zero_init=True, pose_translation_scale=2.0))
    with torch.no_grad():
        m.pose_net.decoder.pose_2.bias.copy_(torch.tensor([0.0, 0.0, 0.0, 0.0, 0.0, -0.25]))
        T = m.pose_net(sample["images"][1], sample["images"][2], sample["Ks"], sample["cam_to_ego"])
    assert torch.allclose(T[:3, 3], torch.tensor([0.0, 0.0, -0.5])) and torch.equal(T[:3, :3], torch.eye(3))
    m = DrivingForward(TINY.replace(pose_translation_scale=2.0, pose_translation_init=(0.0, 0.0, -0.6)))
    assert float(m.pose_net.decoder.pose_2.bias[5]) == pytest.approx(-0.3)
    for bad in ({"pose_translation_scale": 0.0}, {"pose_translation_scale": True}, {"pose_corr_radius": -1},
                {"pose_corr_radius": 1.5}, {"pose_corr_level": 3}, {"pose_corr_mode": "flow"},
                {"pose_corr_mode": "camera_only"}):
        with pytest.raises(ValueError, match=next(iter(bad))):
            TINY.replace(**bad)


def test_flow_statistics_read_a_known_flow_field():
    """pose_corr_head "flow": a uniform flow (1, -2) px gives mean dx 1 and dy -2 in both halves; a
    pure expansion (flow = 0.5 x the offset from the principal point) gives expansion 0.5 (x^2 + y^2)
    summed over the half, i.e. > 0, and mean dx, dy 0 over a symmetric image."""
    from clsplat.models.drivingforward.pose import flow_statistics
    K = torch.tensor([[[4.0, 0.0, 4.0], [0.0, 4.0, 4.0], [0.0, 0.0, 1.0]]])
    flow = torch.tensor([1.0, -2.0]).reshape(1, 2, 1, 1).expand(1, 2, 8, 8)
    st = flow_statistics(flow, K)
    assert torch.allclose(st[0, [0, 1, 3, 4]], torch.tensor([1.0, -2.0, 1.0, -2.0]))
    c = torch.arange(8, dtype=torch.float32) + 0.5 - 4.0
    grow = 0.5 * torch.stack([c.reshape(1, 8).expand(8, 8), c.reshape(8, 1).expand(8, 8)]).unsqueeze(0)
    st = flow_statistics(grow, K)
    assert torch.allclose(st[0, [0, 3]], torch.zeros(2), atol=1e-6)
    assert float(st[0, 2]) > 0 and torch.allclose(st[0, 2], st[0, 5])


def test_flow_head_starts_at_no_motion_and_learns_from_the_photometric_terms(sample):
    torch.manual_seed(0)
    m = DrivingForward(TINY.replace(pose_corr_radius=2, pose_corr_mode="camera_only", pose_corr_head="flow",
                                    pose_zero_init=True, pose_translation_scale=10.0))
    assert sum(q.numel() for q in m.pose_net.odometry.parameters()) == 6 * 3 + 3
    T = m.pose_net(sample["images"][1], sample["images"][2], sample["Ks"], sample["cam_to_ego"])
    assert torch.equal(T.detach(), torch.eye(4, dtype=T.dtype))
    m.training_losses(sample["images"], sample["images"], sample["Ks"], sample["cam_to_ego"])["reproj"].backward()
    assert float(m.pose_net.odometry.out.weight.grad.abs().sum()) > 0
    with pytest.raises(ValueError, match="pose_corr_head"):
        TINY.replace(pose_corr_head="mlp")


def test_pose_road_anchor_trains_the_pose_on_the_road_with_the_prior_and_the_depth_on_its_own(sample):
    """pose_road_anchor: the pose network's gradient comes from ``reproj_pose`` (road pixels, ground
    prior depth) alone, which gives the depth network none; ``reproj`` trains the depth only."""
    torch.manual_seed(0)
    m = DrivingForward(TINY.replace(pose_road_anchor=True, ground_prior_cap=20.0, pose_zero_init=True,
                                    pose_translation_scale=1.0))
    terms = m.training_losses(sample["images"], sample["images"], sample["Ks"], sample["cam_to_ego"])
    assert "reproj_pose" in terms and torch.isfinite(terms["reproj_pose"])
    terms["reproj_pose"].backward(retain_graph=True)
    assert _without_grad(m, "pose_net.decoder.pose_2") == []
    assert len(_without_grad(m, "depth_net")) == len(list(m.depth_net.parameters()))
    m.zero_grad()
    terms["loss"].backward(retain_graph=True)
    pose_grad = m.pose_net.decoder.pose_2.weight.grad.clone()
    m.zero_grad()
    (terms["loss"] - terms["reproj_pose"]).backward()
    assert m.pose_net.decoder.pose_2.weight.grad is None or float(m.pose_net.decoder.pose_2.weight.grad.abs().sum()) == 0
    assert float(pose_grad.abs().sum()) > 0 and _without_grad(m, "depth_net") == []
    with pytest.raises(ValueError, match="pose_road_anchor"):
        TINY.replace(pose_road_anchor=True)                    # tiny has no ground prior


def test_pose_road_cap_sets_the_anchors_road_apart_from_the_depths_prior(sample):
    """pose_road_cap: the pose's road term is the one a model with ground_prior_cap at that value
    computes (same weights), whatever the depth's cap; None keeps the depth's cap."""
    kw = dict(pose_road_anchor=True, pose_zero_init=True, pose_translation_scale=1.0)
    torch.manual_seed(0)
    m20 = DrivingForward(TINY.replace(ground_prior_cap=20.0, **kw))
    m10 = DrivingForward(TINY.replace(ground_prior_cap=10.0, **kw))
    split = DrivingForward(TINY.replace(ground_prior_cap=10.0, pose_road_cap=20.0, **kw))
    m10.load_state_dict(m20.state_dict())
    split.load_state_dict(m20.state_dict())
    args = (sample["images"], sample["images"], sample["Ks"], sample["cam_to_ego"])
    r20, r10, rs = (float(m.training_losses(*args)["reproj_pose"]) for m in (m20, m10, split))
    assert rs == r20 and r10 != r20
    with pytest.raises(ValueError, match="pose_road_cap"):
        TINY.replace(ground_prior_cap=10.0, pose_road_cap=20.0)          # no anchor: nothing to set
    with pytest.raises(ValueError, match="pose_road_cap"):
        TINY.replace(ground_prior_cap=10.0, pose_road_cap=1.0, **kw)     # below min_depth


@pytest.mark.parametrize("anchor", [True, False])
def test_pose_sign_test_picks_the_branch_of_lower_loss(sample, anchor):
    """pose_sign_test: a pose network started at the reversed true motion flips its translation's
    sign at the first decision (the objective is lower with it negated) and then predicts the true
    direction; one started at the true motion keeps its sign. The truth only sets up the case."""
    M = gt_ego_motion(sample)
    E = sample["cam_to_ego"]
    t = (torch.linalg.inv(E[0]) @ M[2] @ E[0])[:3, 3]
    kw = dict(pose_road_anchor=True, ground_prior_cap=20.0) if anchor else {}
    for start, flips in ((-1.0, True), (1.0, False)):
        torch.manual_seed(0)
        m = DrivingForward(TINY.replace(pose_zero_init=True, pose_translation_init=tuple(float(x) * start for x in t),
                                        pose_sign_test=4, pose_sign_test_window=1, **kw))
        first = m.training_losses(sample["images"], sample["images"], sample["Ks"], E, step=0)
        assert (float(first["diag_sign_delta"]) > 0) == flips          # L(t) - L(-t): > 0, negated is lower
        second = m.training_losses(sample["images"], sample["images"], sample["Ks"], E, step=1)
        assert float(second["diag_translation_sign"]) == (-1.0 if flips else 1.0)
        assert float(second["diag_sign_delta"]) < 0                       # now the lower branch
        T = m.pose_net(sample["images"][1], sample["images"][2], sample["Ks"], E).detach()
        assert torch.allclose(T[:3, 3], t, atol=1e-5)


def test_pose_sign_test_decides_once_per_window_within_its_steps(sample):
    """The sign flips only at a window's end (steps w, 2w, .. <= pose_sign_test), once per step,
    when the window's summed difference is above 0; the sign negates the translation exactly and
    travels in the state dict; the fields' bad values name themselves."""
    torch.manual_seed(0)
    p = TINY.replace(pose_zero_init=True, pose_translation_init=(0.1, 0.0, -0.5), pose_sign_test=4,
                     pose_sign_test_window=2)
    net = DrivingForward(p).pose_net
    args = (sample["images"][1], sample["images"][2], sample["Ks"], sample["cam_to_ego"])
    before = net(*args).detach()
    net.sign_test_accumulate(0.3)
    assert not net.sign_test_decide(1)                       # not a window's end
    net.sign_test_accumulate(-0.1)
    assert net.sign_test_decide(2) and not net.sign_test_decide(2)   # once per step
    after = net(*args).detach()
    assert torch.equal(after[:3, :3], before[:3, :3]) and torch.allclose(after[:3, 3], -before[:3, 3])
    net.sign_test_accumulate(-0.2)
    assert not net.sign_test_decide(4)                       # the negated branch was not lower
    net.sign_test_accumulate(5.0)
    assert not net.sign_test_decide(6)                       # past pose_sign_test
    state = net.state_dict()
    assert float(state["translation_sign"]) == -1.0 and int(state["sign_test_last"]) == 4
    assert "translation_sign" not in DrivingForward(TINY).pose_net.state_dict()   # off: no new state
    for bad in (0, 1.5, True):
        with pytest.raises(ValueError, match="pose_sign_test must"):
            TINY.replace(pose_sign_test=bad)
    with pytest.raises(ValueError, match="pose_sign_test_window"):
        TINY.replace(pose_sign_test_window=0)


_SIGN_TEST_RANK = """
import json, sys
import clsplat  # noqa: F401  (the thread defaults, as every entry point)
import torch
import torch.distributed as dist
from clsplat.models.common.presets import get_preset
from clsplat.models.drivingforward.model import DrivingForward
rank, init = int(sys.argv[1]), sys.argv[2]
torch.set_num_threads(1)
dist.init_process_group("gloo", init_method=init, rank=rank, world_size=2)
p = get_preset("drivingforward", "tiny").replace(pose_sign_test=4, pose_sign_test_window=2)
net = DrivingForward(p).pose_net
net.sign_test_accumulate((0.3, -0.1)[rank])
flipped = net.sign_test_decide(2)
dist.destroy_process_group()
print(json.dumps({"flipped": flipped, "sign": float(net.translation_sign)}))
"""


@pytest.mark.slow   # spawns two interpreters
def test_pose_sign_test_decides_the_same_in_every_process(tmp_path):
    """Under torchrun the window's sums are added over the processes before the decision: rank 1's
    own sample (-0.1) would keep the sign, the two together (+0.2) flip it, in both processes."""
    import json
    import subprocess
    import sys
    init = f"file://{tmp_path / 'init'}"
    procs = [subprocess.Popen([sys.executable, "-c", _SIGN_TEST_RANK, str(r), init], stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True) for r in (0, 1)]
    outs = [p.communicate(timeout=300) for p in procs]
    assert all(p.returncode == 0 for p in procs), [e[-2000:] for _, e in outs]
    assert [json.loads(o.strip().splitlines()[-1]) for o, _ in outs] == [{"flipped": True, "sign": -1.0}] * 2
