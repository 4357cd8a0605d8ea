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
