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
    """Measured at 32x64: PSNR 17.7 dB, SSIM 0.58 (176x320: 18.2 dB / 0.80)."""
    m = main(tmp_path / "out", height=32, width=64, seed=0, progress=False)
    assert m["psnr"] > 16.0 and m["ssim"] > 0.45
    assert len(m["psnr_per_camera"]) == 6 and m["num_gaussians"] > 0.7 * 6 * 32 * 64
    assert 0.6 < m["coverage"] <= 1.0
    for name in ["contact_sheet.png", "metrics.json", "renders/CAM_FRONT.png", "renders/CAM_BACK.png",
                 "ground_truth/CAM_BACK_LEFT.png"]:
        assert (tmp_path / "out" / name).is_file(), name
    assert json.loads((tmp_path / "out" / "metrics.json").read_text())["psnr"] == pytest.approx(m["psnr"])
    assert set(m["timings_s"]) == {"generate scene", "lift pixels", "rasterize", "metrics", "write outputs"}
