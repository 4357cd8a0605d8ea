"""DrivingForward's three networks (pose.py, depth.py, gaussian.py): shapes, activation ranges,
and the paper preset's parameter counts against the architecture's own arithmetic."""
import math

import pytest
import torch

from clsplat.models.common.data import parse_data
from clsplat.models.common.presets import get_preset
from clsplat.models.drivingforward.data import load_triplet
from clsplat.models.drivingforward.depth import DepthNetwork
from clsplat.models.drivingforward.gaussian import GaussianNetwork
from clsplat.models.drivingforward.pose import PoseNetwork

TINY = get_preset("drivingforward", "tiny")


@pytest.fixture(scope="module")
def sample():
    return load_triplet(parse_data("synthetic"), 0, TINY)


# ----------------------------------------------------------------------------- arithmetic
def conv(cin, cout, k, bias=True):
    return cin * cout * k * k + (cout if bias else 0)


def resnet18(cin):
    def block(i, o, s=1):
        n = conv(i, o, 3, False) + 2 * o + conv(o, o, 3, False) + 2 * o
        return n + (conv(i, o, 1, False) + 2 * o if s != 1 or i != o else 0)
    n = conv(cin, 64, 7, False) + 2 * 64
    for i, o, s in ((64, 64, 1), (64, 128, 2), (128, 256, 2), (256, 512, 2)):
        n += block(i, o, s) + block(o, o)
    return n


def residual_block(i, o, s=1):
    """GPS-Gaussian's residual block: two 3x3 convs with bias, each followed by a GroupNorm
    (weight + bias), and a 1x1 conv + GroupNorm shortcut when the shape changes."""
    n = conv(i, o, 3) + 2 * o + conv(o, o, 3) + 2 * o
    return n + (conv(i, o, 1) + 2 * o if s != 1 or i != o else 0)


def residual_unet_encoder(cin, channels):
    """5x5 stride-2 stem conv + GroupNorm, then stages of two residual blocks (1/2, 1/4, 1/8)."""
    c0, c1, c2 = channels
    R = residual_block
    return (conv(cin, c0, 5) + 2 * c0 + 2 * R(c0, c0) + R(c0, c1, 2) + R(c1, c1)
            + R(c1, c2, 2) + R(c2, c2))


def paper_counts(p):
    X, Y, Z = p.voxel_shape
    reduce = conv(128 + 256 + 512, 256, 1)
    c1 = 256 + 1
    depth_fusion = (c1 * 64 + 64) + (2 * c1 * 64 + 64) + conv(p.depth_bins * 64, 256, 3) + conv(256, 128, 3)
    decoder, cin = 0, 128
    for c in (256, 128, 64, 32, 16):
        decoder += conv(cin, c, 3) + conv(c, c, 3)
        cin = c
    decoder += conv(16, 1, 3)
    depth = resnet18(3) + reduce + depth_fusion + decoder
    pose = (resnet18(6) + reduce + conv(c1 * Z, 256, 3) + conv(256, 128, 3)
            + conv(128, 256, 1) + 2 * conv(256, 256, 3) + conv(256, 6, 1))
    R = residual_block
    K = (p.sh_degree + 1) ** 2
    gauss = (residual_unet_encoder(1, (32, 48, 96))
             + R(128 + 96, 96) + R(96 + 64 + 48, 64) + R(64 + 64 + 32, 48) + conv(48 + 3 + 1, 32, 3)
             + sum(conv(32, 32, 3) + conv(32, o, 1) for o in (4, 3, 1, 3 * K)))
    return {"pose": pose, "depth": depth, "gaussian": gauss}


def test_paper_parameter_counts():
    p = get_preset("drivingforward", "paper")
    assert (p.height, p.width, p.voxel_shape, p.voxel_size, p.voxel_origin, p.depth_bins) == \
        (352, 640, (100, 100, 20), (1.0, 1.0, 1.5), (-50.0, -50.0, -15.0), 50)
    want = paper_counts(p)
    nets = {"pose": PoseNetwork(p), "depth": DepthNetwork(p), "gaussian": GaussianNetwork(p)}
    for name, net in nets.items():
        got = sum(q.numel() for q in net.parameters())
        print(f"paper {name} network: {got:,} parameters (arithmetic: {want[name]:,})")
        assert got == want[name], name


# ----------------------------------------------------------------------------- shapes and ranges
def test_pose_network_output_is_a_bounded_rigid_motion(sample):
    torch.manual_seed(0)
    net = PoseNetwork(TINY)
    with torch.no_grad():
        net.decoder.pose_2.bias.copy_(torch.tensor([0.0, 0, 0, 900.0, -900.0, 0.0]))  # +-9 m before the clamp
        T = net(sample["images"][0], sample["images"][1], sample["Ks"], sample["cam_to_ego"])
    assert T.shape == (4, 4)
    R = T[:3, :3]
    assert torch.allclose(R.T @ R, torch.eye(3), atol=1e-5) and torch.allclose(T[3], torch.tensor([0.0, 0, 0, 1]))
    assert T[:3, 3].abs().max() <= TINY.max_translation + 1e-6
    assert math.isclose(float(T[0, 3]), 4.0, abs_tol=1e-6) and math.isclose(float(T[1, 3]), -4.0, abs_tol=1e-6)


def test_depth_network_shapes_and_metric_range(sample):
    torch.manual_seed(0)
    net = DepthNetwork(TINY)
    H, W = TINY.height, TINY.width
    with torch.no_grad():
        out = net(sample["images"][1], sample["Ks"], sample["cam_to_ego"])
    assert out["depth"].shape == (6, 1, H, W) and out["sigma"].shape == (6, 1, H, W)
    assert out["f2"].shape == (6, 64, H // 2, W // 2) and out["f4"].shape == (6, 64, H // 4, W // 4)
    assert out["f8"].shape == (6, TINY.proj_channels[1], H // 8, W // 8)
    assert ((out["sigma"] > 0) & (out["sigma"] < 1)).all()
    # He init after the encoder: the fused feature keeps unit scale and the untrained depth already
    # varies over the image (PyTorch's default init gave ~0.02 and a constant map, which Adam then
    # drove into a saturated sigmoid: every pixel at the far limit)
    assert 0.1 < float(out["f8"].std()) < 10 and float(out["sigma"].std()) > 0.01
    s = (sample["Ks"][:, 0, 0] / TINY.focal_ref).view(-1, 1, 1, 1)
    assert (out["depth"] >= TINY.min_depth * s - 1e-4).all() and (out["depth"] <= TINY.max_depth * s + 1e-3).all()
    # the mapping itself: sigma = 0 -> max depth, sigma = 1 -> min depth, times fx / focal_ref
    from clsplat.models.drivingforward.depth import sigma_to_depth
    d = sigma_to_depth(torch.tensor([0.0, 1.0]).view(2, 1, 1, 1), torch.tensor([300.0, 600.0]), 1.5, 80.0, 300.0)
    assert torch.allclose(d.flatten(), torch.tensor([80.0, 3.0]))


def test_ground_prior_is_the_generators_road_depth_and_the_decoders_zero(sample):
    """ground_prior_depth meets the synthetic street's ground exactly where the camera sees road;
    with the prior on, a decoder whose last conv outputs 0 predicts that depth (capped)."""
    from clsplat.models.drivingforward.depth import depth_to_sigma, ground_prior_depth, sigma_to_depth

    H, W = TINY.height, TINY.width
    Ks, E = sample["Ks"], sample["cam_to_ego"]
    prior = ground_prior_depth(Ks, E, H, W, cap=30.0)
    true = sample["depths"][1][:, None]
    # ground pixels: the true depth's point lies on the ego frame's z = 0 (nearer than the cap)
    v, u = torch.meshgrid(torch.arange(H) + 0.5, torch.arange(W) + 0.5, indexing="ij")
    rays = torch.linalg.inv(Ks) @ torch.stack([u, v, torch.ones_like(u)]).reshape(3, -1)
    z = (E[:, 2:3, :3] @ rays).reshape(-1, 1, H, W) * true.clamp(max=1e3) + E[:, 2, 3].view(-1, 1, 1, 1)
    road = (z.abs() < 1e-3) & (true < 30.0)
    assert road.sum() > 1000
    torch.testing.assert_close(prior[road], true[road].to(prior.dtype), rtol=1e-3, atol=1e-4)
    assert float(prior.max()) == 30.0 and bool((prior[:, :, : H // 2 - 1] == 30.0).all())   # above the horizon
    fx = Ks[:, 0, 0]
    sig = depth_to_sigma(prior, fx, TINY.min_depth, TINY.max_depth, TINY.focal_ref)
    torch.testing.assert_close(sigma_to_depth(sig, fx, TINY.min_depth, TINY.max_depth, TINY.focal_ref), prior)
    torch.manual_seed(0)
    net = DepthNetwork(TINY.replace(ground_prior_cap=30.0))
    with torch.no_grad():
        shifted = net(sample["images"][1], Ks, E)["depth"]
    assert float(((shifted - prior).abs() / prior).max()) > 0.05    # a random output layer moves the start
    # depth_zero_init: the untrained network predicts the prior itself, and its output layer still learns
    torch.manual_seed(0)
    net = DepthNetwork(TINY.replace(ground_prior_cap=30.0, depth_zero_init=True))
    assert not net.decoder.dispconv.weight.any() and not net.decoder.dispconv.bias.any()
    depth = net(sample["images"][1], Ks, E)["depth"]
    torch.testing.assert_close(depth.detach(), prior, rtol=1e-3, atol=1e-3)
    depth.mean().backward()
    assert net.decoder.dispconv.weight.grad.abs().sum() > 0
    with pytest.raises(ValueError, match="depth_zero_init"):
        TINY.replace(depth_zero_init=1)
    with pytest.raises(ValueError, match="ground_prior_cap"):
        TINY.replace(ground_prior_cap=1.0)
    below = E.clone()
    below[:, 2, 3] -= 2.0                              # an ego frame 2 m above the cameras (a roof LiDAR's)
    with pytest.raises(ValueError, match="ground_prior_cap: the ground prior needs the ego frame's z = 0"):
        ground_prior_depth(Ks, below, H, W, cap=30.0)


def test_gaussian_network_heads(sample):
    torch.manual_seed(0)
    dnet, gnet = DepthNetwork(TINY), GaussianNetwork(TINY)
    H, W, K = TINY.height, TINY.width, (TINY.sh_degree + 1) ** 2
    with torch.no_grad():
        d = dnet(sample["images"][1], sample["Ks"], sample["cam_to_ego"])
        gnet.scale_head.out.bias.fill_(5.0)       # push scales into the cap
        out = gnet(sample["images"][1], d["depth"], d["f2"], d["f4"], d["f8"])
    assert out["quats"].shape == (6, H, W, 4) and torch.allclose(out["quats"].norm(dim=-1), torch.ones(6, H, W), atol=1e-5)
    assert out["scales"].shape == (6, H, W, 3) and (out["scales"] > 0).all()
    assert out["scales"].max() == TINY.scale_cap
    assert out["opacities"].shape == (6, H, W) and ((out["opacities"] > 0) & (out["opacities"] < 1)).all()
    assert out["sh"].shape == (6, H, W, K, 3)
    want = [1.0] + [0.1 * 0.25 ** l for l in range(1, TINY.sh_degree + 1) for _ in range(2 * l + 1)]
    assert torch.allclose(gnet.sh_damp, torch.tensor(want))
