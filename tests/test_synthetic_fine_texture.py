"""The generator's fine texture (``SyntheticConfig.fine_texture``) and per-point LiDAR classes:
detail that blur costs SSIM on, geometry unchanged, vehicles still left-right symmetric, lamps
untouched, bad values a one-line error; ``StreetScene.lidar(with_semantics=True)``."""
import numpy as np
import pytest
import torch
import torch.nn.functional as F

from clsplat.data.scene import SEMANTIC_CLASSES
from clsplat.data.synthetic import SyntheticConfig, StreetScene, generate_sequence
from clsplat.data.synthetic.textures import _box_albedo
from clsplat.image_metrics import ssim

H, W = 90, 160


def _blurred_ssim(img: np.ndarray) -> float:
    """SSIM of ``img`` [H,W,3] against itself blurred by a 1-pixel Gaussian."""
    x = torch.from_numpy(np.ascontiguousarray(img, dtype=np.float32)).permute(2, 0, 1)[None]
    k = torch.exp(-torch.arange(-3, 4, dtype=torch.float32) ** 2 / 2)
    k = k / k.sum()
    b = F.conv2d(F.pad(x, (3, 3, 0, 0), mode="reflect"), k.view(1, 1, 1, -1).repeat(3, 1, 1, 1), groups=3)
    b = F.conv2d(F.pad(b, (0, 0, 3, 3), mode="reflect"), k.view(1, 1, -1, 1).repeat(3, 1, 1, 1), groups=3)
    return float(ssim(b, x))


@pytest.fixture(scope="module")
def pair():
    kw = dict(height=H, width=W, num_frames=1, seed=2, cameras=("CAM_FRONT", "CAM_FRONT_LEFT"), lidar=False)
    return generate_sequence(**kw), generate_sequence(**kw, fine_texture=0.3)


def test_fine_texture_makes_blur_cost_ssim_and_keeps_geometry(pair):
    plain, fine = pair
    for cam in ("CAM_FRONT", "CAM_FRONT_LEFT"):
        a, b = plain.frames[0], fine.frames[0]
        assert np.array_equal(a.depths[cam], b.depths[cam])
        assert np.array_equal(a.semantics[cam], b.semantics[cam])
        assert np.array_equal(a.instances[cam], b.instances[cam])
        assert not np.array_equal(a.images[cam], b.images[cam])
        s_plain, s_fine = _blurred_ssim(a.images[cam]), _blurred_ssim(b.images[cam])
        # the default street's texture barely notices a 1-pixel blur; the grain does
        assert s_fine < s_plain - 0.03, (cam, s_plain, s_fine)
        sky = a.semantics[cam] == SEMANTIC_CLASSES.index("sky")
        assert np.array_equal(a.images[cam][sky], b.images[cam][sky])   # no grain on the sky


def test_fine_texture_keeps_vehicles_symmetric_and_lamps_untouched():
    scene = StreetScene(seed=5, signals=True, fine_texture=0.4)
    plain = StreetScene(seed=5, signals=True)
    v = scene.vehicles[0]
    rng = np.random.default_rng(0)
    for part, part0 in zip(scene.vehicle_parts(v, 0.0), plain.vehicle_parts(v, 0.0)):
        pl = rng.uniform(-1, 1, (800, 3)) * part.half
        ax = rng.integers(0, 3, 800)
        pl[np.arange(800), ax] = np.sign(pl[np.arange(800), ax]) * part.half[ax]
        a1, e1 = _box_albedo(part, pl, scene.seed, scene.fine_texture)
        a2, e2 = _box_albedo(part, pl * [1, -1, 1], scene.seed, scene.fine_texture)
        assert np.array_equal(a1, a2) and np.array_equal(e1, e2)
        a0, e0 = _box_albedo(part0, pl, plain.seed)
        assert np.array_equal(a1[e1], a0[e0])   # emissive lamps keep their colour
        if part.kind == "body":
            assert not np.allclose(a1[~e1], a0[~e0])


def test_fine_texture_bad_value_is_one_line_error():
    for bad in (-0.1, 1.5, True, "0.3"):
        with pytest.raises(ValueError, match=r"^SyntheticConfig\.fine_texture must be a number in \[0, 1\]"):
            SyntheticConfig(fine_texture=bad).validate()


def test_lidar_semantics_one_class_per_point():
    scene = StreetScene(seed=1)
    E = np.eye(4)
    lp, sem = scene.lidar(E, 0.0, with_semantics=True)
    assert sem.shape == (lp.points.shape[0],) and sem.dtype == np.uint8
    assert np.array_equal(scene.lidar(E, 0.0).points, lp.points)
    road = sem == SEMANTIC_CLASSES.index("road")
    assert road.sum() > 1000
    assert np.abs(lp.points[road, 2]).max() < 1e-4      # ego frame = world here: road points on z = 0
    assert np.abs(lp.points[road, 1]).max() <= 7.0 + 1e-4   # inside the road's half width
    assert (sem != SEMANTIC_CLASSES.index("sky")).all()
