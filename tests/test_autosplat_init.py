"""AutoSplat background initialisation from LiDAR: labels, colours, box removal, sky dome."""
import numpy as np
import pytest

from clsplat.data.scene import project_points
from clsplat.data.synthetic import generate_sequence
from clsplat.models.autosplat.init import BG_CLASSES, OTHER, ROAD, SKY, _SEM_TO_BG, init_background
from clsplat.models.autosplat.presets import PRESETS


@pytest.fixture(scope="module")
def street():
    seq = generate_sequence(height=44, width=80, num_frames=3, seed=2, dt=0.2)
    init, sky = init_background(seq, [0, 1, 2], seq.camera_names, PRESETS["tiny"], np.random.default_rng(0))
    return seq, init, sky


def test_every_background_gaussian_projects_onto_a_pixel_of_its_own_class(street):
    """Each LiDAR Gaussian, projected (independently, with clsplat.data's camera model) into the
    view its colour came from, lands on a pixel of its own class; in every other view where the
    generator's depth says it is visible, at least 97% do."""
    seq, init, _ = street
    lidar = init.source[:, 0] >= 0
    assert lidar.sum() > 500 and set(np.unique(init.labels[lidar])) >= {ROAD, OTHER}
    assert not np.any(init.labels[lidar] == SKY)
    for k in np.nonzero(lidar)[0]:
        i, ci, lin = init.source[k]
        cam = seq.cameras[ci]
        uv, z = project_points(init.means[k].astype(np.float64), cam.K, np.linalg.inv(seq.cam_to_world(i, cam.name)))
        u, v = int(np.floor(uv[0])), int(np.floor(uv[1]))
        assert v * cam.width + u == lin
        assert _SEM_TO_BG[seq.frames[i].semantics[cam.name][v, u]] == init.labels[k]
        assert np.allclose(seq.frames[i].images[cam.name][v, u], init.colors[k])
    agree = total = 0
    for i in range(3):
        for cam in seq.cameras:
            uv, z = project_points(init.means[lidar].astype(np.float64), cam.K,
                                   np.linalg.inv(seq.cam_to_world(i, cam.name)))
            ok = np.isfinite(uv).all(1) & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
            u, v = np.floor(uv[ok]).astype(int).T
            depth = seq.frames[i].depths[cam.name][v, u]
            vis = np.abs(depth - z[ok]) < 0.03 * z[ok] + 0.05
            cls = _SEM_TO_BG[seq.frames[i].semantics[cam.name][v[vis], u[vis]]]
            agree += int((cls == init.labels[lidar][ok][vis]).sum())
            total += int(vis.sum())
    assert total > 1000 and agree / total > 0.97, agree / total


def test_points_in_tracked_boxes_are_removed(street):
    seq, init, _ = street
    lidar = init.source[:, 0] >= 0
    for i, f in enumerate(seq.frames):
        frame_pts = init.source[:, 0] == i
        for b in f.boxes:
            assert not b.contains(init.means[lidar & frame_pts].astype(np.float64)).any()


def test_sky_dome_is_far_coloured_and_radial(street):
    seq, init, sky = street
    dome = init.labels == SKY
    assert dome.sum() == PRESETS["tiny"].dome_points
    assert np.all(np.linalg.norm(init.normals[dome], axis=1) > 0.99)
    assert sky.shape == (3,) and 0.5 < sky.mean() < 1.0  # the generator's sky is bright
    assert init.scales[dome][:, 2].max() < init.scales[dome][:, 0].min()


def test_init_needs_lidar():
    seq = generate_sequence(height=16, width=32, num_frames=1, seed=0, lidar=False)
    with pytest.raises(ValueError, match="LiDAR"):
        init_background(seq, [0], seq.camera_names, PRESETS["tiny"], np.random.default_rng(0))
