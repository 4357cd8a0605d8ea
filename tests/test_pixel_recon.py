"""Pixel-aligned reconstruction with oracle depth (the embedded default job), at a small size."""
import json

import numpy as np
import pytest

from clsplat.data.scene import SEMANTIC_CLASSES, project_points
from clsplat.data.synthetic import generate_sequence
from clsplat.pixel_recon import lift_pixels, main


def test_lift_pixels_reprojects_to_pixel_centres():
    seq = generate_sequence(height=16, width=32, num_frames=1, lidar=False)
    g = lift_pixels(seq, 0)
    f = seq.frames[0]
    sky = SEMANTIC_CLASSES.index("sky")
    n = sum(int((f.semantics[c] != sky).sum()) for c in seq.camera_names)
    assert g["means"].shape == (n, 3) and g["colors"].shape == (n, 3) and g["opacities"].shape == (n,)
    cam = seq.cameras[0]
    k = int((f.semantics[cam.name] != sky).sum())
    uv, z = project_points(g["means"][:k].double().numpy(), cam.K, seq.viewmats(0)[0])
    ys, xs = np.nonzero(f.semantics[cam.name] != sky)
    assert np.allclose(uv, np.stack([xs + 0.5, ys + 0.5], 1), atol=2e-3)
    # ~1 pixel footprint: scale * f / depth == 0.5 px
    focal = cam.K[0, 0]
    assert np.allclose(g["scales"][:k, 0].numpy() * focal / z, 0.5, rtol=1e-4)
    with pytest.raises(ValueError, match="opacity must be in"):
        lift_pixels(seq, 0, opacity=0)


def test_main_small(tmp_path):
    """Measured at 32x64: PSNR 18.0 dB, SSIM 0.63 (176x320: 17.9 dB / 0.81; bench/RESULTS.md, issue 20)."""
    m = main(tmp_path / "out", height=32, width=64, seed=0, progress=False)
    assert m["psnr"] > 16.0 and m["ssim"] > 0.45
    assert len(m["psnr_per_camera"]) == 6 and m["num_gaussians"] > 0.7 * 6 * 32 * 64
    assert 0.6 < m["coverage"] <= 1.0
    for name in ["contact_sheet.png", "metrics.json", "renders/CAM_FRONT.png", "renders/CAM_BACK.png",
                 "ground_truth/CAM_BACK_LEFT.png"]:
        assert (tmp_path / "out" / name).is_file(), name
    assert json.loads((tmp_path / "out" / "metrics.json").read_text())["psnr"] == pytest.approx(m["psnr"])
    assert set(m["timings_s"]) == {"generate scene", "lift pixels", "rasterize", "metrics", "write outputs"}


def test_evaluate_uses_the_models_metrics():
    """PSNR pooled over all cameras' pixels and per camera, SSIM per camera: the engine's image
    metrics ('valid' SSIM), the same numbers the model families report."""
    import torch

    from clsplat.image_metrics import psnr, ssim
    from clsplat.pixel_recon import evaluate

    renders = torch.full((2, 16, 20, 3), 0.5)
    targets = renders.clone()
    targets[0] += 0.1                                  # camera 0: MSE 1e-2 -> 20 dB
    targets[1] += 0.01                                 # camera 1: MSE 1e-4 -> 40 dB
    targets[1, :8, :10] = torch.rand(8, 10, 3)         # some structure for SSIM
    m = evaluate(renders, targets)
    a, b = renders.permute(0, 3, 1, 2), targets.permute(0, 3, 1, 2)
    assert m["psnr_per_camera"] == pytest.approx([float(v) for v in psnr(a, b)])
    assert m["psnr_per_camera"][0] == pytest.approx(20.0, abs=1e-4)
    pooled = ((a - b) ** 2).mean()
    assert m["psnr"] == pytest.approx(float(-10 * torch.log10(pooled)), abs=1e-4)
    assert m["ssim_per_camera"] == pytest.approx([float(v) for v in ssim(a, b)])
    assert m["ssim"] == pytest.approx(float(ssim(a, b).mean()))
    mask = torch.zeros(2, 16, 20, dtype=torch.bool)
    mask[0] = True                                     # only camera 0's pixels
    assert evaluate(renders, targets, mask)["psnr_masked"] == pytest.approx(20.0, abs=1e-4)
    with pytest.raises(ValueError, match="mask must have shape"):
        evaluate(renders, targets, mask[:, :, :4])
    with pytest.raises(ValueError, match=r"must both be \[C, H, W, 3\]"):
        evaluate(renders, targets[..., :2])
