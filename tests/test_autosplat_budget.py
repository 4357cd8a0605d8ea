"""AutoSplat's object budget (issue 36, deliverable 2): the foreground stage's iterations and each
track's initial points and Gaussian cap follow the number of tracks and their boxes' pixels over the
training views (:func:`clsplat.models.autosplat.objects.object_budget`), an empty street pays
nothing, the cap holds, the preset fields are checked, and with the fields off nothing changes."""
import json

import numpy as np
import pytest

from clsplat.data.scene import DrivingSequence, Frame
from clsplat.data.synthetic import generate_sequence
from clsplat.models.autosplat.background import foreground_mask
from clsplat.models.autosplat.data import prepare_data
from clsplat.models.autosplat.densify import Densifier
from clsplat.models.autosplat.model import Switches
from clsplat.models.autosplat.objects import (fixed_object_budget, object_budget, track_box_pixels)
from clsplat.models.autosplat.trainer import Trainer
from clsplat.models.common.presets import get_preset

TINY = get_preset("autosplat", "tiny")
CAMS = ["CAM_FRONT", "CAM_BACK_LEFT"]
SCALED = TINY.replace(fg_steps_per_track=10.0, fg_steps_per_area=4.0, fg_steps_max=1000)


@pytest.fixture(scope="module")
def street():
    return generate_sequence(height=32, width=56, num_frames=4, seed=1, dt=0.2)


def _without(seq: DrivingSequence, boxes: bool = True, instances: bool = True) -> DrivingSequence:
    """``seq`` with its boxes and/or instance masks taken away."""
    frames = [Frame(f.timestamp, f.ego_to_world, f.images, f.depths, f.semantics,
                    {} if instances else f.instances,
                    f.lidar, [] if boxes else f.boxes) for f in seq.frames]
    return DrivingSequence(seq.cameras, frames, seq.name, dict(seq.metadata))


def _pixels(counts: list[list[int]]) -> np.ndarray:
    """``[T, F, 1]`` box pixels from per-track lists over frames."""
    return np.asarray(counts, np.int64).reshape(len(counts), -1, 1)


def test_the_foreground_budget_grows_with_the_tracks_and_their_area():
    one = object_budget(SCALED, _pixels([[100, 0, 50]]), 1000)
    three = object_budget(SCALED, _pixels([[100, 0, 50], [10, 10, 10], [0, 0, 5]]), 1000)
    bigger = object_budget(SCALED, _pixels([[1000, 0, 500]]), 1000)
    # 4 + ceil(10 * 1 + 4 * 0.15) = 15; with three tracks 4 + ceil(30 + 4 * 0.185) = 35
    assert (one.fg_steps, three.fg_steps, bigger.fg_steps) == (15, 35, 20)
    assert one.visible_tracks == 1 and three.visible_tracks == 3
    assert one.object_area == pytest.approx(0.15) and bigger.object_area == pytest.approx(1.5)


def test_an_empty_street_gets_no_foreground_iteration_and_no_object():
    for b in (object_budget(SCALED, np.zeros((0, 3, 2), np.int64), 1000),   # no track
              object_budget(SCALED, np.zeros((2, 3, 2), np.int64), 1000),   # tracks whose boxes never show
              fixed_object_budget(TINY, 0)):
        assert b.fg_steps == 0
    assert object_budget(SCALED, np.zeros((0, 3, 2), np.int64), 1000).object_points == ()


def test_the_cap_holds_and_never_cuts_below_the_preset_steps():
    many = _pixels([[50, 50]] * 40)
    assert object_budget(SCALED.replace(fg_steps_max=120), many, 1000).fg_steps == 120
    assert object_budget(SCALED, many, 1000).fg_steps == 4 + 400 + 16
    # a cap below fg_steps: the preset's own iterations still run (the cap limits what is added)
    assert object_budget(SCALED.replace(fg_steps=50, fg_steps_max=10), many, 1000).fg_steps == 50


def test_steps_rescale_the_scene_terms_with_the_schedule():
    """``--steps N`` (with_total_steps) scales the scene's added foreground iterations by the same
    factor as the four stages: a short run on a busy street stays short."""
    from clsplat.models.autosplat.presets import with_total_steps
    demo = get_preset("autosplat", "demo")
    total = sum(demo.stage_steps().values())
    many = _pixels([[400, 400]] * 30)                       # a busy street: the cap binds
    full = object_budget(demo, many, 1000).fg_steps
    assert full == demo.fg_steps_max
    short = with_total_steps(demo, total // 10)
    assert sum(short.stage_steps().values()) == total // 10
    assert (short.fg_steps_per_track, short.fg_steps_per_area) == pytest.approx(
        (demo.fg_steps_per_track * (total // 10) / total, demo.fg_steps_per_area * (total // 10) / total))
    assert object_budget(short, many, 1000).fg_steps <= full // 10 + 2
    assert with_total_steps(demo, total) == demo                # the preset's own length: unchanged


def test_object_points_and_caps_follow_the_box_pixels():
    p = TINY.replace(object_points_per_pixel=0.5, object_points_min=20)   # object_points 200
    b = object_budget(p, _pixels([[10, 30], [0, 300], [1000, 2000], [0, 0]]), 10_000)
    # the most pixels in one view x 0.5, clipped to 20..200
    assert b.object_points == (20, 150, 200, 20)
    assert b.object_caps == tuple(4 * n for n in b.object_points)
    assert b.fg_steps == TINY.fg_steps   # no iteration term on: the preset's fg_steps
    off = object_budget(TINY.replace(fg_steps_per_track=1.0), _pixels([[10, 30]]), 10_000)
    assert off.object_points == (200,) and off.object_caps == (800,)
    dens = Densifier(p, {"background": 5, "object0": 20, "object1": 150}, sky=0,
                     object_caps={"object0": 80, "object1": 600})
    assert (dens.cap("object0", "foreground", 20), dens.cap("object1", "fusion", 700),
            dens.cap("object2", "fusion", 3)) == (80, 700, 800)


@pytest.mark.parametrize("field,value", [
    ("fg_steps_per_track", -1.0), ("fg_steps_per_track", float("nan")), ("fg_steps_per_area", float("inf")),
    ("fg_steps_per_area", "2"), ("fg_steps_max", -1), ("fg_steps_max", 2.5), ("object_points_per_pixel", -0.1),
    ("object_points_min", 0), ("object_points_min", True)])
def test_bad_budget_fields_are_named(field, value):
    with pytest.raises(ValueError) as e:
        TINY.replace(**{field: value})
    msg = str(e.value)
    assert "\n" not in msg and f".{field}:" in msg


def test_box_pixels_count_the_boxes_not_the_instance_masks(street):
    d = prepare_data(street, CAMS, 4)
    tracks = sorted({b.track_id for f in street.frames for b in f.boxes})
    px = track_box_pixels(street, tracks, d.train_frames, CAMS)
    assert px.shape == (len(tracks), len(d.train_frames), len(CAMS)) and px.sum() > 0
    # the same counts with the instance masks gone: boxes only
    assert np.array_equal(px, track_box_pixels(_without(street, boxes=False), tracks, d.train_frames, CAMS))
    # each track's count is its box's pixels as foreground_mask gives them without instance masks
    bare = _without(street, boxes=False)
    for k, t in enumerate(tracks):
        for j, i in enumerate(d.train_frames):
            assert list(px[k, j]) == [int(m.sum()) for m in foreground_mask(bare, i, CAMS, {t})]


def test_fields_off_count_nothing_and_keep_the_fixed_budget(street, tmp_path, monkeypatch):
    import clsplat.models.autosplat.trainer as tr
    monkeypatch.setattr(tr, "track_box_pixels", lambda *a, **k: pytest.fail("counted with the fields off"))
    t = Trainer(prepare_data(street, CAMS, 4), TINY, Switches(), tmp_path, progress=False)
    assert t.tracks and t.steps["foreground"] == TINY.fg_steps
    assert t.budget == fixed_object_budget(TINY, len(t.tracks))


def test_the_trainer_uses_the_scaled_budget(street, tmp_path):
    p = SCALED.replace(object_points_per_pixel=0.05, object_points_min=8, fg_steps_max=30)
    d = prepare_data(street, CAMS, 4)
    t = Trainer(d, p, Switches(), tmp_path, progress=False)
    px = track_box_pixels(street, [x.track_id for x in t.tracks], d.train_frames, CAMS)
    want = object_budget(p, px, d.width * d.height)
    assert (t.budget.fg_steps, t.budget.object_points) == (want.fg_steps, want.object_points)
    assert t.steps["foreground"] == want.fg_steps > TINY.fg_steps
    t.initialise()
    # each object starts from its template points plus at most as many LiDAR points
    for k, n in enumerate(want.object_points):
        assert n <= len(t.model.objects[k]) <= 2 * n
    assert t.densifier.object_caps == {f"object{k}": 4 * n for k, n in enumerate(want.object_points)}


@pytest.mark.slow   # trains the tiny preset
def test_an_empty_street_skips_the_foreground_stage(street, tmp_path):
    d = prepare_data(_without(street), CAMS, 4)
    t = Trainer(d, SCALED, Switches(), tmp_path, progress=False)
    assert t.steps["foreground"] == 0 and not t.tracks and t.budget.object_points == ()
    t.fit()
    stages = [json.loads(x)["stage"] for x in (tmp_path / "log.jsonl").read_text().splitlines()]
    assert "foreground" not in stages and len(stages) == t.total == sum(t.steps.values())
    assert t.stage_seconds["foreground"] == 0 and list(t.model.sizes()) == ["background"]


def test_a_checkpoint_with_another_foreground_budget_is_refused(street, tmp_path):
    t = Trainer(prepare_data(street, CAMS, 4), SCALED, Switches(), tmp_path, progress=False)
    saved = t.state()
    assert saved["object_budget"]["fg_steps"] == t.steps["foreground"]
    saved["object_budget"] = {**saved["object_budget"], "fg_steps": t.steps["foreground"] + 1}
    with pytest.raises(ValueError, match="foreground iterations") as e:
        t.load_state(saved, tmp_path / "checkpoint.pt")
    assert "\n" not in str(e.value)
    del saved["object_budget"]   # a checkpoint from before issue 36: the budget is derived again
    t.load_state(saved, tmp_path / "checkpoint.pt")


@pytest.mark.slow   # trains the tiny preset twice
def test_a_scaled_budget_trains_as_the_fixed_one_of_the_same_length(street, tmp_path):
    """The budget changes the foreground stage's length and nothing else: a run whose tracks give it
    8 foreground iterations ends bitwise where ``fg_steps=8`` ends."""
    import torch
    d = prepare_data(street, CAMS, 4)
    runs = []
    for k, p in enumerate((TINY.replace(fg_steps_per_track=100.0, fg_steps_max=8), TINY.replace(fg_steps=8))):
        t = Trainer(d, p, Switches(), tmp_path / str(k), progress=False)
        assert t.steps["foreground"] == 8
        t.fit()
        runs.append(t.model.state_dict())
    assert runs[0].keys() == runs[1].keys()
    assert all(torch.equal(runs[0][k], runs[1][k]) for k in runs[0])


# --- the box-pixel count inside each box's rectangle (issue 36 (b)) -----------------------------------

def _rect_as_before(box, w2c, K, width, height):
    """``_box_pixel_rect`` before the rectangle count (main at 9bb1ff4), verbatim: the whole image
    for a box with a corner at or behind the camera plane."""
    half = box.size / 2
    corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * half
    world = corners @ box.box_to_world[:3, :3].T + box.box_to_world[:3, 3]
    pc = world @ w2c[:3, :3].T + w2c[:3, 3]
    z = pc[:, 2]
    if (z <= 0).all():
        return None
    if (z <= 1e-6).any():
        return 0, height, 0, width
    u = K[0, 0] * pc[:, 0] / z + K[0, 2]
    v = K[1, 1] * pc[:, 1] / z + K[1, 2]
    x0, x1 = max(0, int(np.floor(u.min() - 0.5)) - 1), min(width, int(np.ceil(u.max() - 0.5)) + 2)
    y0, y1 = max(0, int(np.floor(v.min() - 0.5)) - 1), min(height, int(np.ceil(v.max() - 0.5)) + 2)
    if x0 >= x1 or y0 >= y1:
        return None
    return y0, y1, x0, x1


def _masks_as_before(cam, T, boxes, width, height):
    """``box_hit_masks`` before the rectangle count (main at 9bb1ff4), verbatim: rays for the whole
    image, a full-image mask per box."""
    import warnings
    u, v = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    d = np.stack([(u - cam.K[0, 2]) / cam.K[0, 0], (v - cam.K[1, 2]) / cam.K[1, 1], np.ones_like(u)], -1)
    d = d @ T[:3, :3].T
    o = T[:3, 3]
    w2c = np.linalg.inv(T)
    for b in boxes:
        r = _rect_as_before(b, w2c, cam.K, width, height)
        if r is None:
            continue
        y0, y1, x0, x1 = r
        B = np.linalg.inv(b.box_to_world)
        ol = B[:3, :3] @ o + B[:3, 3]
        dl = np.ascontiguousarray(d[y0:y1, x0:x1]) @ B[:3, :3].T
        half = b.size / 2
        with np.errstate(divide="ignore", invalid="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)   # all-NaN slices, as before
            t1 = (-half - ol) / dl
            t2 = (half - ol) / dl
            tn = np.nanmax(np.minimum(t1, t2), -1)
            tf = np.nanmin(np.maximum(t1, t2), -1)
        m = np.zeros((height, width), bool)
        m[y0:y1, x0:x1] = (tn <= tf) & (tf > 0)
        yield b, m


def count_as_before(seq: DrivingSequence, track_ids, frame_ids, cameras) -> np.ndarray:
    """``[T, F, C]``: ``track_box_pixels`` before the rectangle count (main at 9bb1ff4): each full-image
    mask's pixels summed (also the reference of ``autosplat_object_budget.py count``)."""
    row = {int(t): k for k, t in enumerate(track_ids)}
    out = np.zeros((len(track_ids), len(frame_ids), len(cameras)), np.int64)
    for j, i in enumerate(frame_ids):
        boxes = [b for b in seq.frames[i].boxes if b.track_id in row]
        for c, name in enumerate(cameras):
            cam = seq.camera(name)
            for b, hit in _masks_as_before(cam, seq.cam_to_world(i, name), boxes, cam.width, cam.height):
                out[row[b.track_id], j, c] = int(hit.sum())
    return out


# busy-noisy repeats busy's case on one more generated street: the slow tier (make test) runs it
@pytest.mark.parametrize("spec", ["synthetic:busy", pytest.param("synthetic:busy-noisy", marks=pytest.mark.slow),
                                  "synthetic:overtake"])
def test_the_rectangle_count_equals_the_full_image_masks(spec):
    """The count inside each box's projected rectangle (boxes reaching behind the camera cut just in
    front of it, rays made for the rectangle only) is the old full-image masks' sum, and the masks
    are the old ones pixel for pixel: a busy street (41 boxes, exact and tracker-noise) and a car
    overtaking beside the ego (boxes reaching behind the side cameras), six frames, six cameras."""
    from clsplat.models.autosplat.background import box_hit_counts, box_hit_masks
    from clsplat.models.autosplat.data import load_sequence
    seq = load_sequence(spec, None, (0, 6), 0.25, seed=3)
    cams = [c.name for c in seq.cameras]
    tracks = sorted({b.track_id for f in seq.frames for b in f.boxes})
    frames = list(range(len(seq.frames)))
    new = track_box_pixels(seq, tracks, frames, cams)
    assert new.sum() > 0 and (new > 0).sum() >= 2 * len(cams)
    assert np.array_equal(new, count_as_before(seq, tracks, frames, cams))
    near = 0
    for i in frames:
        for name in cams:
            cam, T = seq.camera(name), seq.cam_to_world(i, name)
            boxes = seq.frames[i].boxes
            w2c = np.linalg.inv(T)
            near += sum(_rect_as_before(b, w2c, cam.K, cam.width, cam.height) == (0, cam.height, 0, cam.width)
                        for b in boxes)
            old = {b.track_id: m for b, m in _masks_as_before(cam, T, boxes, cam.width, cam.height) if m.any()}
            got = list(box_hit_masks(cam, T, boxes, cam.width, cam.height))
            assert {b.track_id for b, m in got if m.any()} == set(old)
            assert all(np.array_equal(m, old[b.track_id]) for b, m in got if m.any())
            # box_hit_counts is the sum of box_hit_masks' mask for the same boxes
            assert [(b.track_id, n) for b, n in box_hit_counts(cam, T, boxes, cam.width, cam.height)] == \
                [(b.track_id, int(m.sum())) for b, m in got]
    assert near > 0   # the case the new rectangle changes: a box reaching behind the camera plane


def test_a_box_beside_and_behind_the_camera_keeps_every_pixel():
    """Boxes that straddle the camera plane, close to the camera, at many poses: the cut rectangle
    holds every pixel the whole-image test finds (and the camera inside a box sees the whole image)."""
    from clsplat.data.scene import Box3D
    from clsplat.models.autosplat.background import box_hit_masks
    cam = generate_sequence(height=40, width=72, num_frames=1, seed=0).cameras[0]
    rng = np.random.default_rng(0)
    T = np.eye(4)
    checked = 0
    for _ in range(200):
        c = rng.normal(size=3) * [2.0, 1.0, 1.5]
        q = rng.normal(size=4)
        b = Box3D(center=c, size=rng.uniform(0.3, 4.0, 3), quat=q / np.linalg.norm(q), track_id=1, label="car")
        old = [m for _, m in _masks_as_before(cam, T, [b], cam.width, cam.height)]
        new = [m for _, m in box_hit_masks(cam, T, [b], cam.width, cam.height)]
        want = old[0] if old else np.zeros((cam.height, cam.width), bool)
        have = new[0] if new else np.zeros((cam.height, cam.width), bool)
        assert np.array_equal(want, have)
        checked += int(want.any())
    assert checked > 20
