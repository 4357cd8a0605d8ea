"""PSNR and SSIM (the engine's, re-exported), depth metrics and LPIPS from local weight files."""
from __future__ import annotations

import math

import pytest
import torch

from clsplat.models.common.backbones import VGG16
from clsplat.models.common.metrics import LPIPS, LPIPS_OFF_MESSAGE, depth_metrics, lpips_or_none, psnr, ssim


def test_psnr_and_ssim_are_the_engines():
    """The models report the engine's image metrics (values tested in tests/test_image_metrics.py),
    so the oracle-depth baseline's figures are comparable with theirs."""
    import clsplat.image_metrics as im
    from clsplat.models.common import metrics

    assert metrics.psnr is im.psnr and metrics.ssim is im.ssim and metrics.SSIM_WINDOW == im.SSIM_WINDOW == 11
    img = torch.rand(1, 3, 16, 16)
    torch.testing.assert_close(ssim(img, img), torch.ones(1))
    assert math.isinf(float(psnr(img, img)))
    with pytest.raises(ValueError, match="11x11"):
        ssim(torch.rand(1, 3, 8, 16), torch.rand(1, 3, 8, 16))


def test_depth_metrics_hand_values_and_sky():
    gt = torch.tensor([[10.0, 20.0, float("inf"), 40.0, 100.0]])  # inf = sky, 100 m beyond max_depth
    pred = torch.tensor([[11.0, 20.0, 5.0, 30.0, 50.0]])
    m = depth_metrics(pred, gt)
    assert m["n_pixels"] == 3
    assert m["abs_rel"] == pytest.approx((0.1 + 0 + 0.25) / 3)
    assert m["sq_rel"] == pytest.approx((1 / 10 + 0 + 100 / 40) / 3)
    assert m["rmse"] == pytest.approx(math.sqrt((1 + 0 + 100) / 3))
    assert m["delta1"] == pytest.approx(2 / 3)  # 40/30 = 1.33 fails
    assert m["scale_ratio"] == pytest.approx(20.0 / 20.0)
    # no median scaling: a pred at half the depth is reported as such
    half = depth_metrics(gt[:, :2] / 2, gt[:, :2])
    assert half["abs_rel"] == pytest.approx(0.5) and half["scale_ratio"] == pytest.approx(2.0)
    assert half["delta1"] == 0.0
    # predictions are clamped to [min_depth, max_depth]
    assert depth_metrics(torch.tensor([500.0]), torch.tensor([79.0]))["rmse"] == pytest.approx(1.0)
    # mask, and the empty case
    masked = depth_metrics(pred, gt, mask=torch.tensor([[True, False, True, False, True]]))
    assert masked["n_pixels"] == 1 and masked["abs_rel"] == pytest.approx(0.1)
    empty = depth_metrics(pred, torch.full_like(gt, float("inf")))
    assert empty["n_pixels"] == 0 and all(math.isnan(empty[k]) for k in ("abs_rel", "rmse", "delta1", "scale_ratio"))
    with pytest.raises(ValueError, match="shapes differ"):
        depth_metrics(pred, gt[:, :3])
    with pytest.raises(ValueError, match="pred: contains NaN"):
        depth_metrics(torch.tensor([float("nan")]), torch.tensor([5.0]))


CHANNELS = (64, 128, 256, 512, 512)


def write_lin(path, keys=None, channels=CHANNELS):
    """An lpips v0.1 vgg.pth-layout file: lin{k}.model.1.weight [1, C_k, 1, 1], random non-negative."""
    g = torch.Generator().manual_seed(3)
    keys = keys or [f"lin{k}.model.1.weight" for k in range(5)]
    lin = {k: torch.rand(1, c, 1, 1, generator=g) for k, c in zip(keys, channels)}
    torch.save(lin, path)
    return lin


@pytest.fixture(scope="module")
def vgg_file(tmp_path_factory):
    """A torchvision-layout VGG-16 file (random features, plus a classifier entry), written once."""
    g = torch.Generator().manual_seed(5)
    vgg = {k: torch.randn(v.shape, generator=g) * 0.05 for k, v in VGG16().state_dict().items()}
    vgg["classifier.6.bias"] = torch.zeros(1000)
    path = tmp_path_factory.mktemp("lpips") / "vgg16.pth"
    torch.save(vgg, path)
    return path


def test_lpips_from_local_files(tmp_path, vgg_file):
    lin = write_lin(tmp_path / "lin.pth")
    model, msg = lpips_or_none(vgg_file, tmp_path / "lin.pth")
    assert isinstance(model, LPIPS) and msg.startswith("LPIPS on") and str(tmp_path / "lin.pth") in msg
    assert torch.equal(model.lin4.model[1].weight, lin["lin4.model.1.weight"])
    g = torch.Generator().manual_seed(4)
    a = torch.rand(2, 3, 16, 16, generator=g)  # relu5_3 at 1x1
    b = (a + 0.2 * torch.randn(a.shape, generator=g)).clamp(0, 1)
    assert torch.equal(model(a, a), torch.zeros(2))
    d = model(a, b)
    assert d.shape == (2,) and torch.all(d > 0)
    torch.testing.assert_close(model(b, a), d)  # symmetric
    # linear in the calibration weights
    with torch.no_grad():
        for k in range(5):
            getattr(model, f"lin{k}").model[1].weight.mul_(2.0)
    torch.testing.assert_close(model(a, b), 2 * d)
    with pytest.raises(ValueError, match="H, W >= 16"):
        model(a[..., :8, :], b[..., :8, :])
    # frozen, stays in eval mode, gradients reach the inputs
    model.train()
    assert not model.training and not any(p.requires_grad for p in model.parameters())
    x = b.clone().requires_grad_(True)
    model(x, a).sum().backward()
    assert x.grad.abs().sum() > 0


def test_lpips_off_and_bad_files(tmp_path, vgg_file):
    assert lpips_or_none(None, None) == (None, LPIPS_OFF_MESSAGE)
    assert LPIPS_OFF_MESSAGE == "LPIPS off: no VGG-16 / LPIPS weights given (nothing is downloaded)"
    write_lin(tmp_path / "lin.pth")
    with pytest.raises(ValueError, match="lin_weights"):
        lpips_or_none(vgg_file, None)
    with pytest.raises(ValueError, match="does not exist"):
        LPIPS(vgg_file, tmp_path / "missing.pth")
    write_lin(tmp_path / "wrong.pth", keys=[f"lin{k}.weight" for k in range(5)])
    with pytest.raises(ValueError, match=r"wrong.pth.*not lpips v0.1 vgg.pth layout.*missing"):
        LPIPS(vgg_file, tmp_path / "wrong.pth")
    write_lin(tmp_path / "shape.pth", channels=(3,) * 5)
    with pytest.raises(ValueError, match=r"lin0.model.1.weight of shape \[1, 3, 1, 1\]"):
        LPIPS(vgg_file, tmp_path / "shape.pth")
    # a ResNet file is not a VGG-16
    torch.save({"conv1.weight": torch.zeros(64, 3, 7, 7)}, tmp_path / "resnet.pth")
    with pytest.raises(ValueError, match=r"VGG16 weights: .*resnet.pth.*missing keys"):
        LPIPS(tmp_path / "resnet.pth", tmp_path / "lin.pth")


def test_pose_errors_against_a_known_motion():
    import math

    from clsplat.models.common.geometry import se3_exp
    from clsplat.models.common.metrics import pose_errors

    true = se3_exp(torch.tensor([0.0, 0.0, 0.0], dtype=torch.float64), torch.tensor([0.0, 0.0, -0.8], dtype=torch.float64))
    pred = se3_exp(torch.tensor([0.0, math.radians(2.0), 0.0], dtype=torch.float64),
                   torch.tensor([0.06, 0.0, -0.72], dtype=torch.float64))
    e = pose_errors(pred, true)
    assert e["t_err_m"] == pytest.approx(0.1) and e["t_err_pct"] == pytest.approx(12.5)
    assert e["r_err_deg"] == pytest.approx(2.0, abs=1e-6)
    assert e["t_true_m"] == pytest.approx(0.8) and e["t_pred_m"] == pytest.approx(math.hypot(0.06, 0.72))
    assert pose_errors(true, true) == pytest.approx({"t_err_m": 0.0, "t_err_pct": 0.0, "r_err_deg": 0.0,
                                                     "t_pred_m": 0.8, "t_true_m": 0.8}, abs=1e-6)
    assert pose_errors(torch.eye(4), torch.eye(4))["t_err_pct"] is None      # no true motion: no percentage
    with pytest.raises(ValueError, match="pred"):
        pose_errors(torch.eye(3), true)
    with pytest.raises(ValueError, match="true"):
        pose_errors(true, torch.full((4, 4), float("nan")))
