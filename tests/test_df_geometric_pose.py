"""models/drivingforward/geometric_pose.py: the pose source "geometric" measures a window's rig
motion from its own images (moving, crawling and standing windows of the varied world, both directions),
drives the warps without training the pose network, travels through ``--pose geometric`` into the
checkpoint and ``metrics.json`` (the loader reading the frames again at the fit's size; its pose
scored against the data's), and refuses bad fields."""
import dataclasses
import json

import pytest
import torch

from clsplat.models.common.data import parse_data
from clsplat.models.common.presets import get_preset
from clsplat.models.drivingforward.data import gt_ego_motion, load_triplet
from clsplat.models.drivingforward.geometric_pose import GROUND_CAP_DEFAULT, geometric_size, window_motions
from clsplat.models.drivingforward.ground_motion import fit_ground_motion_direct
from clsplat.models.drivingforward.model import DrivingForward

# (128, 224): the road's texture resolves the motion (at tiny's 32x56 it does not), in ~3 CPU s a fit
SIZE = (128, 224)


@pytest.fixture(scope="module")
def preset():
    return get_preset("drivingforward", "tiny").replace(pose_source="geometric", geometric_size=SIZE)


@pytest.fixture(scope="module")
def varied():
    return parse_data("synthetic", default_world="varied")


@pytest.fixture(scope="module")
def sample():
    return load_triplet(parse_data("synthetic"), 1, get_preset("drivingforward", "tiny"))


def _window(source, index, preset):
    return load_triplet(source, index, dataclasses.replace(preset, height=SIZE[0], width=SIZE[1]), "train")


@pytest.mark.slow
def test_the_fit_measures_a_moving_window_both_ways(preset, varied):
    s = _window(varied, 4, preset)                       # a training street at 5.5 m/s
    M = window_motions(s, preset)
    gt = gt_ego_motion(s)
    for got, true in ((M[0], gt[0]), (M[1], gt[2])):
        t, t_true = got[:3, 3].double(), true[:3, 3].double()
        assert float(t_true.norm()) > 0.4
        assert float((t - t_true).norm()) < 0.05 * float(t_true.norm())
        assert float(torch.dot(t, t_true)) > 0           # the direction, not only the size


@pytest.mark.slow
def test_a_standing_window_reads_as_standing(preset, varied):
    s = _window(varied, 0, preset)                       # a training street standing at t
    assert float(gt_ego_motion(s)[2][:3, 3].norm()) < 1e-6
    assert all(float(m[:3, 3].norm()) < 0.01 for m in window_motions(s, preset))


@pytest.mark.slow
def test_geometric_keep_reads_a_crawling_window_that_the_plain_fit_reads_as_standing(preset, varied):
    """A crawl (0.11 m a frame): with every ground pixel's residual in the search's mean, the pixels
    the plane wrongly claims cost more at the true motion than the road gains, and zero wins; with
    ``geometric_keep`` 0.75 they drop out and the crawl is measured (issue 32)."""
    s = _window(varied, 12, preset)                      # a training street crawling at 1.08 m/s
    gt = gt_ego_motion(s)
    bound = preset.geometric_max_speed * float(s["timestamps"][2] - s["timestamps"][1])
    plain = fit_ground_motion_direct(s["images"][1], s["images"][2], s["Ks"], s["cam_to_ego"].double(),
                                     GROUND_CAP_DEFAULT, search=(-bound, bound, preset.geometric_search))
    trimmed = window_motions(s, preset.replace(geometric_keep=0.75))      # the field, both directions
    for got, true in ((trimmed[0], gt[0]), (trimmed[1], gt[2])):
        t, t_true = got[:3, 3].double(), true[:3, 3].double()
        assert 0.05 < float(t_true.norm()) < 0.15
        assert float((t - t_true).norm()) < 0.1 * float(t_true.norm())
    assert float(plain[:3, 3].norm()) < 0.2 * float(gt[2][:3, 3].norm())   # the failure: read as standing


@pytest.mark.slow
def test_the_yaw_search_reads_a_turn_that_the_fit_without_it_reads_as_driving_straight(preset, varied):
    """A training street turning 1.1 degrees a frame at 2.9 m/s: Gauss-Newton from zero yaw, with the
    trimmed cost, leaves nearly the whole turn out (about 1 degree of rotation error both ways);
    ``geometric_max_yaw_rate`` 30 deg/s searches the yaw first and reads it (issue 32)."""
    from clsplat.models.common.metrics import pose_errors
    p = preset.replace(geometric_keep=0.75)
    s = _window(varied, 16, p)
    gt = gt_ego_motion(s)
    true = (gt[0].double(), gt[2].double())
    plain = [pose_errors(m.double(), t)["r_err_deg"] for m, t in zip(window_motions(s, p), true)]
    turned = [pose_errors(m.double(), t)["r_err_deg"]
              for m, t in zip(window_motions(s, p.replace(geometric_max_yaw_rate=30.0)), true)]
    assert min(plain) > 0.8, plain
    assert max(turned) < 0.25, turned
    with pytest.raises(ValueError, match="true_depth"):   # the probe's bound needs depth maps
        window_motions({k: v for k, v in s.items() if k != "depths"}, p, true_depth=True)


def test_a_street_caches_fits_are_kept_reused_bitwise_and_refitted_when_a_field_changes(tmp_path, monkeypatch):
    """``synthetic-cache:DIR``: a window's fitted motions are kept beside its street and read back bit
    for bit instead of fitted again; another fit field, a damaged file, or another source kind fits."""
    from clsplat.models.drivingforward import geometric_pose as G
    p = get_preset("drivingforward", "tiny").replace(pose_source="geometric", geometric_size=(32, 56))
    src = parse_data(f"synthetic-cache:{tmp_path}", default_world="varied")
    fits = []
    real = G.window_motions
    monkeypatch.setattr(G, "window_motions", lambda *a, **k: (fits.append(1), real(*a, **k))[1])
    first = G.load_window_motions(src, 4, p)
    kept = sorted((tmp_path / "geometric").glob("*.pt"))
    assert len(fits) == 1 and len(kept) == 1
    again = G.load_window_motions(src, 4, p)
    assert len(fits) == 1 and all(torch.equal(a, b) for a, b in zip(first, again))
    G.load_window_motions(src, 4, p.replace(geometric_keep=0.75))              # another field: fitted
    assert len(fits) == 2 and len(list((tmp_path / "geometric").glob("*.pt"))) == 2
    kept[0].write_bytes(b"not a tensor file")                                  # damaged: fitted, rewritten
    assert all(torch.equal(a, b) for a, b in zip(G.load_window_motions(src, 4, p), first)) and len(fits) == 3
    assert len(G.load_window_motions(src, 4, p)) == 2 and len(fits) == 3
    G.load_window_motions(parse_data("synthetic", default_world="varied"), 4, p)   # no cache: always fitted
    assert len(fits) == 4


def test_geometric_motions_drive_the_warps_and_leave_the_pose_network_untrained(sample):
    torch.manual_seed(0)
    m = DrivingForward(get_preset("drivingforward", "tiny").replace(pose_source="geometric"))
    M = gt_ego_motion(sample)
    terms = m.training_losses(sample["images"], sample["images"], sample["Ks"], sample["cam_to_ego"],
                              ego_motion_gt=[M[0], M[2]])
    m.zero_grad()
    terms["loss"].backward()
    assert all(q.grad is None for q in m.pose_net.parameters())
    assert any(q.grad is not None for q in m.depth_net.parameters())
    with pytest.raises(ValueError, match="ego_motion_gt: preset pose_source 'geometric'"):
        m.training_losses(sample["images"], sample["images"], sample["Ks"], sample["cam_to_ego"])
    still = dict(sample, timestamps=torch.zeros(3, dtype=torch.float64))   # frames at one instant
    with pytest.raises(ValueError, match="timestamps"):
        window_motions(still, get_preset("drivingforward", "tiny"))


def test_the_fits_size_defaults_to_the_presets_and_bad_fields_are_refused():
    tiny = get_preset("drivingforward", "tiny")
    assert geometric_size(tiny) == (tiny.height, tiny.width)
    assert tiny.pose_source == "network" and get_preset("drivingforward", "small").pose_source == "network"
    assert tiny.geometric_keep == 1.0 and get_preset("drivingforward", "small").geometric_keep == 1.0   # off
    assert tiny.geometric_max_yaw_rate == 0.0 == get_preset("drivingforward", "small").geometric_max_yaw_rate
    assert tiny.replace(geometric_size=[176, 320]).geometric_size == (176, 320)   # a checkpoint's list
    for field, value in (("geometric_size", (176,)), ("geometric_size", (4, 320)), ("geometric_size", (176.0, 320)),
                         ("geometric_size", (100, 176)),
                         ("geometric_search", 1), ("geometric_search", True), ("geometric_max_speed", 0.0),
                         ("geometric_max_speed", float("inf")), ("geometric_keep", 0.0), ("geometric_keep", 1.5),
                         ("geometric_keep", True), ("geometric_max_yaw_rate", -1.0),
                         ("geometric_max_yaw_rate", float("nan")), ("geometric_max_yaw_rate", True),
                         ("pose_source", "lidar")):
        with pytest.raises(ValueError, match=field):
            tiny.replace(**{field: value})


@pytest.mark.slow
def test_pose_geometric_trains_resumes_bitwise_and_reports_the_images_motion(tmp_path):
    from clsplat.models.drivingforward.cli import train

    def run(out, steps, *extra):
        return train(["--preset", "tiny", "--steps", str(steps), "--out", str(out), "--no-progress", "--threads", "1",
                      "--checkpoint-every", "1", "--val-every", "0", "--pose", "geometric",
                      "--set", f"geometric_size={SIZE}", *extra])

    out = tmp_path / "geo"
    assert run(out, 2, "--eval-scenes", "1") == 0
    # the fit draws no random numbers: a run stopped after step 1 and resumed ends bit for bit the same
    assert run(tmp_path / "resumed", 1, "--eval-scenes", "0") == 0
    assert run(tmp_path / "resumed", 2, "--eval-scenes", "0", "--resume") == 0
    a = torch.load(out / "checkpoint.pt", weights_only=True)
    b = torch.load(tmp_path / "resumed" / "checkpoint.pt", weights_only=True)
    assert a["step"] == b["step"] == 2
    for k, v in a["model"].items():
        assert torch.equal(v, b["model"][k]), k
    ck = torch.load(out / "checkpoint.pt", weights_only=True)
    assert ck["preset"]["pose_source"] == "geometric" and list(ck["preset"]["geometric_size"]) == list(SIZE)
    m = json.loads((out / "metrics.json").read_text())
    assert m["protocol"]["pose_source"] == "geometric" and "ground-plane fit at 128x224" in m["protocol"]["pose"]
    a = m["all"]
    assert {"pose_t_err_m", "pose_t_err_pct", "pose_t_pred_m", "pose_t_true_m"} <= set(a)
    assert abs(a["pose_t_pred_m"] - a["pose_t_true_m"]) <= a["pose_t_err_m"] + 1e-9
