"""AutoSplat background initialisation from LiDAR: labels, colours, box removal, sky dome."""
import numpy as np
import pytest

from clsplat.data.scene import project_points
from clsplat.data.synthetic import generate_sequence
from clsplat.models.autosplat.init import OTHER, ROAD, SKY, _SEM_TO_BG, init_background, moving_track_ids
from clsplat.models.common.presets import get_preset


@pytest.fixture(scope="module")
def street():
    seq = generate_sequence(height=44, width=80, num_frames=3, seed=2, dt=0.2)
    init, sky = init_background(seq, [0, 1, 2], seq.camera_names, get_preset("autosplat", "tiny"), np.random.default_rng(0))
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


def test_points_in_moving_tracks_boxes_are_removed_static_ones_stay(street):
    seq, init, _ = street
    lidar = init.source[:, 0] >= 0
    moving = moving_track_ids(seq, get_preset("autosplat", "tiny").dynamic_threshold)
    assert moving == {1, 2}
    parked_points = 0
    for i, f in enumerate(seq.frames):
        frame_pts = init.means[lidar & (init.source[:, 0] == i)].astype(np.float64)
        for b in f.boxes:
            inside = int(b.contains(frame_pts).sum())
            if b.track_id in moving:
                assert inside == 0
            parked_points += inside
    assert parked_points > 0   # parked cars stay in the background (issue 19)


def test_sky_dome_is_far_coloured_and_radial(street):
    seq, init, sky = street
    dome = init.labels == SKY
    assert dome.sum() == get_preset("autosplat", "tiny").dome_points
    assert np.all(np.linalg.norm(init.normals[dome], axis=1) > 0.99)
    assert sky.shape == (3,) and 0.5 < sky.mean() < 1.0  # the generator's sky is bright
    assert init.scales[dome][:, 2].max() < init.scales[dome][:, 0].min()


def test_init_needs_lidar():
    seq = generate_sequence(height=16, width=32, num_frames=1, seed=0, lidar=False)
    with pytest.raises(ValueError, match="LiDAR"):
        init_background(seq, [0], seq.camera_names, get_preset("autosplat", "tiny"), np.random.default_rng(0))


def test_dataset_lidar_labels_are_used_without_image_semantics():
    """PandaSet's path: no image semantics, one label per LiDAR point (here traced from the
    generator); every LiDAR Gaussian takes its point's class, which matches the generator's
    semantics at the pixel it was coloured from for at least 97% of them (label boundaries)."""
    from clsplat.data.scene import DrivingSequence, Frame
    from clsplat.data.synthetic import LIDAR_MOUNT

    seq = generate_sequence(height=44, width=80, num_frames=2, seed=2, dt=0.2)
    scene = seq.metadata["scene"]
    labels = []
    for f in seq.frames:
        pw = f.lidar.to_world(f.ego_to_world).points.astype(np.float64)
        origin = f.ego_to_world[:3, :3] @ LIDAR_MOUNT + f.ego_to_world[:3, 3]
        dirs = (pw - origin)[None]
        s, pid = scene.trace(origin, dirs, f.timestamp)
        labels.append(scene.shade(origin, dirs, s, pid, f.timestamp)[1][0].astype(np.uint8))
    bare = [Frame(f.timestamp, f.ego_to_world, f.images, lidar=f.lidar, boxes=f.boxes) for f in seq.frames]
    lab_seq = DrivingSequence(seq.cameras, bare, "labelled-lidar", {"lidar_semantics": labels})
    init, _ = init_background(lab_seq, [0, 1], seq.camera_names, get_preset("autosplat", "tiny"), np.random.default_rng(0))
    lidar = init.source[:, 0] >= 0
    assert lidar.sum() > 300 and set(np.unique(init.labels[lidar])) >= {ROAD, OTHER}
    agree = 0
    for k in np.nonzero(lidar)[0]:
        i, ci, lin = init.source[k]
        pix = seq.frames[i].semantics[seq.cameras[ci].name].reshape(-1)[lin]
        agree += int(_SEM_TO_BG[pix] == init.labels[k])
    assert agree / lidar.sum() > 0.97, agree / lidar.sum()


def test_user_mask_folder_fills_semantics_and_names_bad_masks(tmp_path):
    """Masks written as class-index PNGs (<CAM>/<NN>.png) load back exactly; a missing, wrongly
    sized or out-of-range mask is a ValueError naming the file."""
    from clsplat.data.scene import SEMANTIC_CLASSES, DrivingSequence, Frame
    from clsplat.io.images import write_image
    from clsplat.models.autosplat.init import load_mask_folder

    seq = generate_sequence(height=16, width=24, num_frames=2, seed=0, dt=0.2)
    for k, f in enumerate(seq.frames):
        for c, m in f.semantics.items():
            (tmp_path / c).mkdir(exist_ok=True)
            write_image(tmp_path / c / f"{k + 3:02d}.png", m.astype(np.float32) / 255.0)
    bare = DrivingSequence(seq.cameras, [Frame(f.timestamp, f.ego_to_world, f.images, lidar=f.lidar)
                                         for f in seq.frames])
    load_mask_folder(bare, tmp_path, [3, 4])  # source frames 3 and 4 -> NN = 03, 04
    for f, g in zip(seq.frames, bare.frames):
        for c in seq.camera_names:
            assert np.array_equal(f.semantics[c], g.semantics[c])
    with pytest.raises(ValueError, match="05.png' missing"):
        load_mask_folder(bare, tmp_path, [4, 5])
    with pytest.raises(ValueError, match="does not exist"):
        load_mask_folder(bare, tmp_path / "nope", [3, 4])
    cam = seq.camera_names[0]
    write_image(tmp_path / cam / "03.png", np.zeros((8, 8), np.float32))
    with pytest.raises(ValueError, match="03.png' is"):
        load_mask_folder(bare, tmp_path, [3, 4])
    write_image(tmp_path / cam / "03.png", np.full((16, 24), len(SEMANTIC_CLASSES) / 255.0, np.float32))
    with pytest.raises(ValueError, match="holds class"):
        load_mask_folder(bare, tmp_path, [3, 4])


# ---------------------------------------------------------------- road continuation (issue 33)
def _strip(n: int = 4000, seed: int = 0):
    """Road Gaussians on the plane z = 0.3 + 0.02 x over x in [0, 40], y in [-3, 2] (a dark grey
    road), and poses along +x at y = 0: a road seen 2 m to the left and 3 m to the right."""
    rng = np.random.default_rng(seed)
    xy = np.stack([rng.uniform(0, 40, n), rng.uniform(-3, 2, n)], 1)
    means = np.concatenate([xy, (0.3 + 0.02 * xy[:, 0])[:, None]], 1)
    colors = np.full((n, 3), 0.25) + rng.normal(0, 0.01, (n, 3))
    normals = np.tile([-0.02, 0.0, 1.0], (n, 1)) / np.hypot(1, 0.02)
    poses = np.tile(np.eye(4), (8, 1, 1))
    poses[:, 0, 3] = np.linspace(5, 30, 8)
    poses[:, 2, 3] = 0.3 + 0.02 * poses[:, 0, 3] + 1.6
    return means, colors, normals, poses


def test_extend_road_adds_a_flat_road_beyond_the_observed_edges():
    from clsplat.models.autosplat.init import extend_road
    means, colors, normals, poses = _strip()
    em, ec, en = extend_road(means, colors, normals, poses, width=3.0, spacing=0.5)
    left, right = em[:, 1] > 2.0, em[:, 1] < -3.0
    assert (left | right).all()                                         # every added one lies beyond an edge
    assert left.sum() > 400 and right.sum() > 400                       # both sides, all along the road
    assert em[left, 1].max() <= 2.0 + 3.0 + 0.05 and em[right, 1].min() >= -3.0 - 3.0 - 0.05
    assert np.ptp(em[left, 0]) > 38 and np.ptp(em[right, 0]) > 38
    # on the road's own plane (its height continued across from the edge), coloured and oriented as the road
    assert np.abs(em[:, 2] - (0.3 + 0.02 * em[:, 0])).max() < 0.03
    assert np.abs(ec - 0.25).max() < 0.02
    assert np.all(en @ np.array([0.0, 0.0, 1.0]) > 0.999)
    # a grid of the given step: no two added Gaussians closer than it
    from clsplat.models.autosplat.init import knn_mean_distance
    import torch
    assert knn_mean_distance(torch.from_numpy(em), k=1).min() > 0.49
    # 0 adds nothing
    assert all(len(a) == 0 for a in extend_road(means, colors, normals, poses, width=0.0, spacing=0.5))


def test_extend_road_follows_the_road_not_the_heading():
    """A road along the diagonal with the ego's heading 10 degrees off it (a lane change): the
    continuation is parallel to the road's own principal axis."""
    from clsplat.models.autosplat.init import extend_road
    means, colors, normals, poses = _strip()
    c, s = np.cos(np.pi / 4), np.sin(np.pi / 4)
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    h = np.radians(10.0)
    tilt = np.array([[np.cos(h), -np.sin(h), 0], [np.sin(h), np.cos(h), 0], [0, 0, 1.0]])
    poses = poses.copy()
    poses[:, :3, :3] = R @ tilt
    poses[:, :3, 3] = poses[:, :3, 3] @ R.T
    em, *_ = extend_road(means @ R.T, colors, normals @ R.T, poses, width=3.0, spacing=0.5)
    back = em @ R               # into the road's frame
    assert len(em) > 800
    assert np.all((back[:, 1] > 2.0) | (back[:, 1] < -3.0))
    assert back[:, 1].max() <= 5.1 and back[:, 1].min() >= -6.1


def test_road_extend_m_adds_road_gaussians_in_init_and_zero_changes_nothing():
    seq = generate_sequence(height=44, width=80, num_frames=3, seed=2, dt=0.2)
    tiny = get_preset("autosplat", "tiny")
    base, _ = init_background(seq, [0, 1, 2], seq.camera_names, tiny, np.random.default_rng(0))
    zero, _ = init_background(seq, [0, 1, 2], seq.camera_names, tiny.replace(road_extend_m=0.0),
                              np.random.default_rng(0))
    for f in ("means", "colors", "scales", "labels", "normals", "source"):
        assert np.array_equal(getattr(base, f), getattr(zero, f)), f
    ext, _ = init_background(seq, [0, 1, 2], seq.camera_names, tiny.replace(road_extend_m=8.0),
                             np.random.default_rng(0))
    n = len(base) - tiny.dome_points
    assert np.array_equal(ext.means[:n], base.means[:n])          # the observed set is untouched
    assert np.array_equal(ext.means[-tiny.dome_points:], base.means[n:])
    added = np.zeros(len(ext), bool)
    added[n:len(ext) - tiny.dome_points] = True
    assert added.sum() > 50
    assert np.all(ext.labels[added] == ROAD) and np.all(ext.source[added] == -1)
    # beyond the observed road's lateral extent: the street runs along x, so per 2 m strip of x the
    # added Gaussians lie left of its leftmost road Gaussian or right of its rightmost one
    road = base.means[base.labels == ROAD].astype(np.float64)
    add = ext.means[added].astype(np.float64)
    strip = np.floor(road[:, 0] / 2.0)
    lo = {b: road[strip == b, 1].min() for b in np.unique(strip)}
    hi = {b: road[strip == b, 1].max() for b in np.unique(strip)}
    out = [y > hi[b] or y < lo[b] for (x, y), b in zip(add[:, :2], np.floor(add[:, 0] / 2.0)) if b in lo]
    assert len(out) > 0.9 * len(add) and np.mean(out) > 0.95
    assert (add[:, 1] > road[:, 1].max()).sum() > 10 and (add[:, 1] < road[:, 1].min()).sum() > 10
    assert add[:, 1].max() < road[:, 1].max() + 8.0 + 1e-3 and add[:, 1].min() > road[:, 1].min() - 8.0 - 1e-3
    # and on the road's plane: within 0.15 m of a plane fitted to the observed road
    A = np.c_[road[:, :2], np.ones(len(road))]
    coef = np.linalg.lstsq(A, road[:, 2], rcond=None)[0]
    assert np.abs(np.c_[add[:, :2], np.ones(len(add))] @ coef - add[:, 2]).max() < 0.15
    assert np.allclose(ext.scales[added], 4 * tiny.lidar_voxel)


@pytest.mark.parametrize("value", [-1.0, float("nan"), float("inf"), "3", True, 1e6])
def test_bad_road_extend_m_is_named(value):
    with pytest.raises(ValueError, match="road_extend_m") as e:
        get_preset("autosplat", "tiny").replace(road_extend_m=value)
    assert "\n" not in str(e.value)


def test_road_extend_m_is_off_in_every_preset():
    for name in ("tiny", "demo", "small", "paper"):
        assert get_preset("autosplat", name).road_extend_m == 0.0, name
