"""AutoSplat decomposes only the tracks that move (issue 19): the selection by displacement, the
background keeping the static tracks' LiDAR points, the foreground masks covering moving tracks."""
import numpy as np
import pytest

from clsplat.data.scene import Box3D, DrivingSequence, Frame
from clsplat.data.synthetic import generate_sequence
from clsplat.models.autosplat.background import foreground_mask
from clsplat.models.autosplat.data import prepare_data
from clsplat.models.autosplat.init import accumulate_lidar, moving_track_ids
from clsplat.models.autosplat.model import collect_tracks

CAMS = ["CAM_FRONT", "CAM_FRONT_LEFT"]


@pytest.fixture(scope="module")
def street():
    # 2 moving vehicles (track ids 1, 2; ~8 m/s) and 6 parked ones (3..8), 0.6 s of driving
    return generate_sequence(height=24, width=40, num_frames=4, seed=2, dt=0.2, cameras=tuple(CAMS))


def _shifted(seq: DrivingSequence, track: int, dx_per_frame: float) -> DrivingSequence:
    """``seq`` with track ``track``'s box moved ``dx_per_frame`` metres along x per frame."""
    frames = []
    for k, f in enumerate(seq.frames):
        boxes = [Box3D(b.track_id, b.label, b.size, b.center + np.r_[k * dx_per_frame * (b.track_id == track), 0, 0],
                       b.quat, b.uuid) for b in f.boxes]
        frames.append(Frame(f.timestamp, f.ego_to_world, f.images, f.depths, f.semantics, f.instances, f.lidar, boxes))
    return DrivingSequence(seq.cameras, frames, seq.name, seq.metadata)


def test_only_tracks_that_move_are_decomposed(street):
    assert moving_track_ids(street, 0.5) == {1, 2}
    tracks = collect_tracks(street, [0, 1, 3], 0.5)
    assert [t.track_id for t in tracks] == [1, 2] and all(t.dynamic for t in tracks)
    every = collect_tracks(street, [0, 1, 3], 0.5, moving_only=False)
    assert [t.track_id for t in every] == list(range(1, 9))
    assert [t.dynamic for t in every] == [True, True] + [False] * 6
    # the threshold is in metres of displacement over the sequence: a parked car nudged 0.1 m per
    # frame (0.3 m in all) stays static at 0.5 m and is decomposed at 0.2 m
    nudged = _shifted(street, 3, 0.1)
    assert moving_track_ids(nudged, 0.5) == {1, 2}
    assert moving_track_ids(nudged, 0.2) == {1, 2, 3}
    # above every track's displacement, nothing is decomposed
    assert collect_tracks(street, [0, 1, 3], 1e3) == []


def test_static_tracks_keep_their_lidar_points_in_the_background(street):
    moving = moving_track_ids(street, 0.5)
    kept = accumulate_lidar(street, [0], 0.15, moving)[0][1]
    boxes = {b.track_id: b for b in street.frames[0].boxes}
    inside = {t: int(b.contains(kept).sum()) for t, b in boxes.items()}
    assert inside[1] == inside[2] == 0                  # moving: removed (they become object sets)
    assert sum(inside[t] for t in range(3, 9)) > 0      # parked: stay, as plain 3DGS has them
    every = accumulate_lidar(street, [0], 0.15)[0][1]   # remove=None: every tracked box, as before
    assert sum(int(b.contains(every).sum()) for b in boxes.values()) == 0


def test_foreground_masks_cover_the_moving_tracks_only(street):
    data = prepare_data(street, CAMS, 4, dynamic_threshold=0.5)
    inst = np.stack([np.stack([f.instances[c] for c in CAMS]) for f in street.frames])
    assert np.array_equal(data.foreground.numpy(), np.isin(inst, [1, 2]))
    assert (inst >= 3).any()                            # parked cars are in view, and not foreground
    all_tracks = foreground_mask(street, 0, CAMS)
    assert np.array_equal(all_tracks, inst[0] > 0)
