"""AutoSplat end to end on a tiny street: CLI outputs, bitwise resume, skipped stages, bad input."""
import json

import numpy as np
import pytest
import torch

from clsplat.data.scene import Box3D, DrivingSequence, Frame
from clsplat.data.synthetic import generate_sequence
from clsplat.models.autosplat.cli import train
from clsplat.models.autosplat.data import parse_frames
from clsplat.models.autosplat.model import Switches
from clsplat.models.common.presets import get_preset
from clsplat.models.autosplat.data import prepare_data
from clsplat.models.autosplat.evaluate import evaluate_run
from clsplat.models.autosplat.trainer import Trainer

TINY = get_preset("autosplat", "tiny")
CAMS = ["CAM_FRONT", "CAM_BACK_LEFT"]


@pytest.fixture(scope="module")
def street():
    return generate_sequence(height=32, width=56, num_frames=4, seed=1, dt=0.2)


def test_resume_is_bitwise(street, tmp_path):
    data = prepare_data(street, CAMS, holdout=4)
    full = Trainer(data, TINY, Switches(), tmp_path / "full", progress=False)
    full.fit()
    part = Trainer(data, TINY, Switches(), tmp_path / "part", progress=False)
    part.fit(stop_at=7)  # mid-foreground, after densification changed the set sizes
    assert part.step == 7
    resumed = Trainer(data, TINY, Switches(), tmp_path / "part", progress=False)
    resumed.fit(resume=True)
    assert resumed.step == full.step == full.total
    a, b = full.model.state_dict(), resumed.model.state_dict()
    assert a.keys() == b.keys()
    for k in a:
        assert torch.equal(a[k], b[k]), k
    assert full.model.sizes() != {"background": 0}
    logs = [json.loads(x) for x in (tmp_path / "part" / "log.jsonl").read_text().splitlines()]
    assert [r["step"] for r in logs] == list(range(1, full.total + 1))
    with pytest.raises(ValueError, match="switches"):
        Trainer(data, TINY, Switches(symmetry=False), tmp_path / "part", progress=False).fit(resume=True)


def test_sequence_without_tracks_skips_foreground_and_static_tracks_get_no_residual(street, tmp_path):
    frames = [Frame(f.timestamp, f.ego_to_world, f.images, f.depths, f.semantics,
                    {c: np.zeros_like(v) for c, v in f.instances.items()}, f.lidar, []) for f in street.frames]
    seq = DrivingSequence(street.cameras, frames, "no-tracks", dict(street.metadata))
    t = Trainer(prepare_data(seq, CAMS, 4), TINY, Switches(), tmp_path, progress=False)
    assert t.steps["foreground"] == 0 and not t.tracks
    t2 = Trainer(prepare_data(street, CAMS, 4), TINY, Switches(), tmp_path, progress=False)
    dyn = {str(k) for k, tr in enumerate(t2.tracks) if tr.dynamic}
    # only moving tracks are decomposed (issue 19), each with its residual SH
    assert dyn and set(t2.model.residuals.keys()) == dyn and len(dyn) == len(t2.tracks)


def test_cli_writes_the_run_folder(tmp_path):
    out = tmp_path / "run"
    rc = train(["--data", "synthetic", "--preset", "tiny", "--frames", "0:4", "--scale", "0.2",
                "--cameras", "CAM_FRONT", "CAM_BACK", "--no-progress", "--out", str(out)])
    assert rc == 0
    for name in ("metrics.json", "scene.ply", "checkpoint.pt", "loss.png", "log.jsonl", "contact_sheet.png",
                 "lateral_shift_1m.png", "lateral_shift_2m.png", "lateral_shift_3m.png"):
        assert (out / name).is_file(), name
    m = json.loads((out / "metrics.json").read_text())
    for block in (m["all"], m["train"]):
        assert np.isfinite(block["psnr"]) and np.isfinite(block["ssim"])
    assert set(m["per_camera"]) == {"CAM_FRONT", "CAM_BACK"} == set(m["train"]["per_camera"])
    assert set(m["lane_change"]) == {"1m", "2m", "3m"} and m["lane_change"]["2m"]["psnr"] > 5
    assert m["lane_change"]["2m"]["frames"] == m["protocol"]["test_frames"] and m["lane_change"]["2m"]["psnr_road"] > 5
    assert np.isfinite(m["lane_change"]["2m"]["road_depth_mae_m"]) and m["lane_change"]["2m"]["road_depth_abs_rel"] > 0
    assert np.isfinite(m["all"]["psnr_objects"]) and np.isfinite(m["train"]["psnr_objects"])
    assert m["gaussians"]["road"] > 0 and m["gaussians"]["sky"] > 0 and m["gaussians"]["objects"] > 0
    assert set(m["seconds_per_stage"]) >= {"load", "init", "bg_phase1", "bg_phase2", "foreground", "fusion"}


def test_bad_input_is_named(street, tmp_path):
    with pytest.raises(ValueError, match="cameras: 'CAM_NOPE' is not in the data"):
        prepare_data(street, ["CAM_NOPE"], 4)
    with pytest.raises(ValueError, match="--frames"):
        parse_frames("3:3")
    with pytest.raises(ValueError, match="--frames"):
        parse_frames("a:b")
    with pytest.raises(ValueError, match="holdout"):
        prepare_data(street, CAMS, 1)
    # no LiDAR: a clear error (there is no image-only initialisation)
    nolidar = DrivingSequence(street.cameras, [Frame(f.timestamp, f.ego_to_world, f.images, f.depths, f.semantics,
                                                     f.instances, None, f.boxes) for f in street.frames])
    with pytest.raises(ValueError, match="no LiDAR"):
        Trainer(prepare_data(nolidar, CAMS, 4), TINY, Switches(), tmp_path, progress=False).fit()
    # boxes that are not tracks: two boxes with one id in a frame
    f0 = street.frames[0]
    b = f0.boxes[0]
    dup = Box3D(b.track_id, b.label, b.size, b.center + np.array([10.0, 0, 0]), b.quat)
    bad = DrivingSequence(street.cameras, [Frame(f0.timestamp, f0.ego_to_world, f0.images, lidar=f0.lidar,
                                                 boxes=[b, dup])] + street.frames[1:])
    with pytest.raises(ValueError, match="track id"):
        Trainer(prepare_data(bad, CAMS, 4), TINY, Switches(), tmp_path, progress=False)
    with pytest.raises(ValueError, match="--data"):
        train(["--data", "kitti:/x", "--out", str(tmp_path / "x"), "--no-progress"])
    with pytest.raises(ValueError, match="--frames"):
        train(["--frames", "4:2", "--out", str(tmp_path / "x"), "--no-progress"])
    with pytest.raises(ValueError, match="--batch-size"):
        train(["--batch-size", "2", "--out", str(tmp_path / "x"), "--no-progress"])
    with pytest.raises(ValueError, match="--scale"):
        train(["--scale", "0", "--out", str(tmp_path / "x"), "--no-progress"])


@pytest.mark.filterwarnings("ignore:All-NaN slice")
def test_unselected_camera_is_never_rendered_nor_read(street, tmp_path, monkeypatch):
    """Train and evaluate on two of six cameras: the other cameras' images are NaN (any read would
    poison the colours and the loss), and no render ever uses one of their poses."""
    from clsplat.models.common.gaussians import GaussianSet

    others = [c for c in street.camera_names if c not in CAMS]
    frames = [Frame(f.timestamp, f.ego_to_world, {c: (v if c in CAMS else np.full_like(v, np.nan))
                                                  for c, v in f.images.items()},
                    f.depths, f.semantics, f.instances, f.lidar, f.boxes) for f in street.frames]
    seq = DrivingSequence(street.cameras, frames, "subset", dict(street.metadata))
    seen = []
    render = GaussianSet.render

    def spy(self, viewmats, *args, **kwargs):
        seen.append(viewmats.detach().clone())
        return render(self, viewmats, *args, **kwargs)

    monkeypatch.setattr(GaussianSet, "render", spy)
    data = prepare_data(seq, CAMS, 4)
    assert data.images.shape[1] == len(CAMS) and torch.isfinite(data.images).all()
    t = Trainer(data, TINY, Switches(), tmp_path, progress=False)
    t.fit()
    m = evaluate_run(t)
    assert np.isfinite(m["all"]["psnr"]) and np.isfinite(m["train"]["psnr"]) and set(m["per_camera"]) == set(CAMS)
    assert all(torch.isfinite(p).all() for p in t.model.parameters())
    forbidden = torch.from_numpy(np.stack([seq.viewmats(i, others) for i in range(len(seq.frames))])
                                 .reshape(-1, 4, 4).astype(np.float32))
    assert len(seen) >= t.total
    for vm in seen:
        assert vm.shape[0] == len(CAMS)
        d = (vm[:, None] - forbidden[None]).abs().flatten(2).max(-1).values
        assert float(d.min()) > 1e-3


def test_road_pixels_from_labelled_lidar_match_the_generator():
    """Without image semantics (PandaSet), the road mask comes from the labelled LiDAR points
    projected into each camera: its pixels are road in the generator's own semantics."""
    from clsplat.data.synthetic import ROAD_HALF, SEMANTIC_CLASSES
    from clsplat.models.autosplat.init import ROAD
    from clsplat.models.autosplat.data import ROAD_SEMANTIC, _lidar_classes

    seq = generate_sequence(height=44, width=80, num_frames=1, seed=2)
    f = seq.frames[0]
    pts = f.lidar.to_world(f.ego_to_world).points.astype(np.float64)
    name = seq.camera_names[0]
    # each point labelled from the street's geometry alone (the ground plane z = 0 with
    # |y| <= ROAD_HALF is road, everything else "other"), independent of any projection code
    on_road = (np.abs(pts[:, 2]) < 0.03) & (np.abs(pts[:, 1]) <= ROAD_HALF)
    labels = np.where(on_road, ROAD_SEMANTIC, SEMANTIC_CLASSES.index("other")).astype(np.uint8)
    bare = [Frame(f.timestamp, f.ego_to_world, f.images, lidar=f.lidar, boxes=f.boxes)]
    lab_seq = DrivingSequence(seq.cameras, bare, "labelled-lidar", {"lidar_semantics": [labels]})
    road = _lidar_classes(lab_seq, 0, name) == ROAD
    truth = f.semantics[name] == ROAD_SEMANTIC
    assert road.sum() > 20
    assert (truth[road]).mean() > 0.8          # 3x3 dilation spills over the road's edges
