"""AutoSplat end to end on a tiny street, on the shared training loop: CLI outputs, bitwise resume
(mid-stage, right after and across a densification), a skipped non-finite step, torchrun data
parallelism, skipped stages, bad input."""
import json
import math
import os
import subprocess
import sys

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
TINY_STEPS = sum(TINY.stage_steps().values())
CAMS = ["CAM_FRONT", "CAM_BACK_LEFT"]


@pytest.fixture(scope="module")
def street():
    return generate_sequence(height=32, width=56, num_frames=4, seed=1, dt=0.2)


@pytest.fixture(scope="module")
def full_run(street, tmp_path_factory):
    """The uninterrupted tiny run: its trainer and log."""
    out = tmp_path_factory.mktemp("full")
    full = Trainer(prepare_data(street, CAMS, holdout=4), TINY, Switches(), out, progress=False)
    full.fit()
    return full, [json.loads(x) for x in (out / "log.jsonl").read_text().splitlines()]


def _log(folder):
    return [json.loads(x) for x in (folder / "log.jsonl").read_text().splitlines()]


# TINY: 4 steps per stage, densification after steps 3, 7, 11, 15. Stopped after 5: mid-stage
# (background phase 2), the resumed run crosses the densification after step 7; stopped after 7:
# right after a densification changed the set sizes and Adam's state.
@pytest.mark.slow   # trains the tiny preset
@pytest.mark.parametrize("stop", [5, 7])
def test_resume_on_the_shared_loop_is_bitwise(street, full_run, tmp_path, stop):
    full, full_log = full_run
    densified = {r["step"] for r in full_log if any(k.startswith("densify_") for k in r)}
    assert 7 in densified and full_log[6]["gaussians"] != full_log[5]["gaussians"]  # it did change sizes
    data = prepare_data(street, CAMS, holdout=4)
    part = Trainer(data, TINY, Switches(), tmp_path, progress=False)
    part.fit(stop_at=stop)
    assert part.step == stop and torch.load(tmp_path / "checkpoint.pt", weights_only=True)["step"] == stop
    resumed = Trainer(data, TINY, Switches(), tmp_path, progress=False)
    resumed.fit(resume=True)
    assert resumed.step == full.step == full.total
    assert resumed.model.sizes() == full.model.sizes()
    a, b = full.model.state_dict(), resumed.model.state_dict()
    assert a.keys() == b.keys()
    for k in a:
        assert torch.equal(a[k], b[k]), k
    for (qa, sa), (qb, sb) in zip(full.opt.state.items(), resumed.opt.state.items()):  # Adam's moments too
        assert torch.equal(sa["exp_avg"], sb["exp_avg"]) and torch.equal(sa["exp_avg_sq"], sb["exp_avg_sq"])
    logs = _log(tmp_path)
    assert [r["step"] for r in logs] == list(range(1, full.total + 1))
    assert [r["loss"] for r in logs] == [r["loss"] for r in full_log]
    assert [r["grad_norm"] for r in logs] == [r["grad_norm"] for r in full_log]
    with pytest.raises(ValueError, match="switches"):
        Trainer(data, TINY, Switches(symmetry=False), tmp_path, progress=False).fit(resume=True)


def test_a_non_finite_step_is_skipped(street, tmp_path):
    """A NaN loss at step 6 (background phase 2) leaves every parameter as it was and the run goes on."""

    class Poisoned(Trainer):
        def sample_loss(self, model, step, index):
            terms = super().sample_loss(model, step, index)
            if step == 5:
                terms["loss"] = terms["loss"] * math.nan
            return terms

    seen = {}
    t = Poisoned(prepare_data(street, CAMS, holdout=4), TINY, Switches(), tmp_path, progress=False)
    t.fit(on_step=lambda step, rec: seen.__setitem__(step, {k: v.clone() for k, v in t.model.state_dict().items()})
          if step in (5, 6) else None)
    assert t.step == t.total
    logs = _log(tmp_path)
    assert logs[5]["skipped"] is True and "grad_norm" not in logs[5]
    assert all("skipped" not in r for i, r in enumerate(logs) if i != 5)
    for k, v in seen[5].items():
        assert torch.equal(v, seen[6][k]), k
    assert all(torch.isfinite(q).all() for q in t.model.parameters())


@pytest.mark.slow   # torchrun: two processes
def test_torchrun_data_parallel_equals_one_process(tmp_path, two_process_run):
    """``torchrun --nproc_per_node 2 ... --batch-size 2``: each rank renders one of the iteration's two
    frames, gradients and densification statistics are summed over the ranks, and the run ends where
    one process with two frames per iteration does (float sums in another order: close, not bitwise)."""
    args = ["--data", "synthetic", "--preset", "tiny", "--frames", "0:4", "--scale", "0.2", "--cameras",
            "CAM_FRONT", "CAM_BACK", "--batch-size", "2", "--no-progress"]
    one, two = two_process_run(tmp_path, "autosplat", args)
    script = tmp_path / "autosplat_train.py"    # the entry point two_process_run wrote
    assert two["step"] == one["step"] == TINY_STEPS
    assert two["extra"]["sizes"] == one["extra"]["sizes"]
    for k, v in one["model"].items():
        assert torch.allclose(v, two["model"][k], rtol=1e-4, atol=1e-5), (k, float((v - two["model"][k]).abs().max()))
    la, lb = _log(tmp_path / "one"), _log(tmp_path / "two")
    assert [x["frames"] for x in la] == [x["frames"] for x in lb] and len(la[0]["frames"]) == 2
    assert [x["loss"] for x in la] == pytest.approx([x["loss"] for x in lb], rel=1e-4)
    assert (tmp_path / "two" / "metrics.json").is_file()
    # fewer frames per iteration than processes: one line that says why
    env = {**os.environ, "WORLD_SIZE": "2"}
    r = subprocess.run([sys.executable, str(script), "--batch-size", "1", "--out", str(tmp_path / "x"),
                        "--no-progress"], capture_output=True, text=True, timeout=120, env=env)
    assert r.returncode == 2 and r.stderr.strip().splitlines() == [
        "clsplat train autosplat: --batch-size: 1 frame(s) per iteration cannot be shared by 2 processes; "
        "give --batch-size 2 or more"]


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


@pytest.mark.slow   # trains the tiny preset
def test_cli_writes_the_run_folder(autosplat_tiny_run):
    """``clsplat train autosplat --preset tiny --frames 0:4 --scale 0.2 --cameras CAM_FRONT CAM_BACK``
    (the session's run, tests/conftest.py, shared with tests/test_autosplat_cli.py)."""
    out = autosplat_tiny_run
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


def test_bad_input_is_named(street, tmp_path, capsys):
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
    with pytest.raises(ValueError, match="--batch-size"):
        Trainer(prepare_data(street, CAMS, 4), TINY, Switches(), tmp_path, progress=False, batch_size=0)
    # the command: one line naming the argument, exit status 2 (the skeleton's error policy)
    for argv, named in ((["--data", "kitti:/x"], "--data"), (["--frames", "4:2"], "--frames"),
                        (["--scale", "0"], "--scale")):
        capsys.readouterr()
        assert train([*argv, "--out", str(tmp_path / "x"), "--no-progress"]) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith("clsplat train autosplat: ") and named in err and "\n" not in err


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


@pytest.mark.slow   # trains the tiny preset
def test_phase1_budget_share_keeps_room_for_phase2(street, full_run, tmp_path):
    """``phase1_budget_share``: phase 1 (road and sky) densifies the background up to that share
    of ``max_gaussians`` only, and phase 2 grows it beyond (the small preset's road otherwise
    filled the whole cap before any building was densified)."""
    data = prepare_data(street, CAMS, holdout=4)
    probe = Trainer(data, TINY, Switches(), tmp_path / "probe", progress=False)
    probe.initialise()
    n0 = len(probe.model.background)
    _, full_log = full_run   # TINY: densification after steps 3 (phase 1), 7 (phase 2), 11, 15
    grown1 = full_log[2]["densify_background"] - n0
    assert grown1 > 40, grown1          # phase 1 alone grows the background without the share
    preset = TINY.replace(max_gaussians=n0 + 4 * grown1, phase1_budget_share=(n0 + 10) / (n0 + 4 * grown1))
    tr = Trainer(data, preset, Switches(), tmp_path / "run", progress=False)
    tr.fit()
    log = _log(tmp_path / "run")
    assert log[2]["stage"] == "bg_phase1" and log[6]["stage"] == "bg_phase2"
    assert log[2]["densify_background"] <= n0 + 10
    assert log[6]["densify_background"] > n0 + 10    # phase 2 may use the rest
    with pytest.raises(ValueError, match=r"phase1_budget_share: expected a share in \(0, 1\]"):
        TINY.replace(phase1_budget_share=0.0)


def test_road_init_ties_the_flat_start_to_the_flatness_switch(street, tmp_path):
    """``road_init``: "flat" starts road Gaussians as thin discs in the road's frame in every run;
    "with-flatness" (default) does so only with flatness on, else isotropic with identity
    rotations as 3DGS starts them (issue 19: plain 3DGS kept half of the flatness treatment). The
    sky dome's discs are the dome's geometry and stay in both."""
    from clsplat.models.autosplat.init import ROAD, SKY
    data = prepare_data(street, CAMS, holdout=4)

    def start(preset, switches):
        t = Trainer(data, preset, switches, tmp_path, progress=False)
        t.initialise()
        bg = t.model.background
        return bg.labels, bg.log_scales.detach().exp(), bg.quats.detach()

    assert TINY.road_init == "with-flatness"
    for preset, switches, flat in ((TINY.replace(road_init="flat"), Switches(flatness=False), True),
                                   (TINY, Switches(), True), (TINY, Switches(flatness=False), False)):
        labels, scales, quats = start(preset, switches)
        road, sky = labels == ROAD, labels == SKY
        assert road.sum() > 20 and sky.sum() > 20
        thin = scales[road].min(1).values < 0.5 * scales[road].max(1).values
        assert bool(thin.all()) == flat and bool(thin.any()) == flat
        identity = (quats[road] == torch.tensor([1.0, 0, 0, 0])).all(1)
        assert bool(identity.all()) != flat
        assert bool((scales[sky].min(1).values < 0.1 * scales[sky].max(1).values).all())   # the dome's discs
    with pytest.raises(ValueError, match=r"road_init: expected one of"):
        TINY.replace(road_init="round")


def test_road_classes_put_the_sidewalk_in_the_road_set(tmp_path):
    """``road_classes``: the semantic classes whose pixels and LiDAR points form the road set
    (phase 1, flatness, the flat start); ("road", "sidewalk") adds the sidewalk, the same ground.
    (At 32 x 56 the colouring's 5-pixel z-buffer window hides every sidewalk point behind the road.)"""
    from clsplat.data.scene import SEMANTIC_CLASSES
    from clsplat.models.autosplat.init import OTHER, ROAD
    street = generate_sequence(height=88, width=160, num_frames=4, seed=1, dt=0.2, cameras=tuple(CAMS))
    sem = np.stack([[street.frames[i].semantics[c] for c in CAMS] for i in range(len(street.frames))])
    side = sem == SEMANTIC_CLASSES.index("sidewalk")
    assert side.sum() > 20
    both = ("road", "sidewalk")
    plain, ground = prepare_data(street, CAMS, 4), prepare_data(street, CAMS, 4, road_classes=both)
    assert bool((plain.classes.numpy()[side] == OTHER).all()) and bool((ground.classes.numpy()[side] == ROAD).all())
    assert torch.equal(plain.classes[torch.from_numpy(~side)], ground.classes[torch.from_numpy(~side)])

    def road_count(preset, data):
        t = Trainer(data, preset, Switches(), tmp_path, progress=False)
        t.initialise()
        return int((t.model.background.labels == ROAD).sum())

    assert road_count(TINY.replace(road_classes=both), ground) > road_count(TINY, plain)
    with pytest.raises(ValueError, match=r"road_classes: expected ground classes"):
        TINY.replace(road_classes=("road", "sky"))


def test_a_checkpoint_from_before_road_init_and_road_classes_resumes_as_it_trained():
    from clsplat.models.common.presets import preset_from_saved
    saved = get_preset("autosplat", "demo").to_dict()
    for k in ("road_init", "road_classes"):
        del saved[k]                                 # a record written before issue 19 added them
    old = preset_from_saved("autosplat", saved)
    assert old.road_init == "flat" and old.road_classes == ("road",)
    now = preset_from_saved("autosplat", get_preset("autosplat", "demo").to_dict())
    assert now == get_preset("autosplat", "demo")    # a current record is its preset, unchanged


@pytest.mark.slow   # trains the tiny preset (4 x 6 steps)
def test_road_opacity_floor_holds_with_flatness_and_zero_or_plain_changes_nothing(street, tmp_path):
    """``road_opacity_floor`` (issue 33, H2): with flatness on, every road-labelled background
    Gaussian keeps opacity >= the floor through training (densification at step 3 included) while
    other Gaussians are free; a floor of 0, or flatness off, trains bit for bit as a trainer whose
    floor hook does nothing."""
    from clsplat.models.autosplat.init import ROAD
    data = prepare_data(street, CAMS, holdout=4)

    class NoHook(Trainer):
        def hold_road_opacity(self) -> None:
            pass

    def run(cls, preset, switches, name):
        t = cls(data, preset, switches, tmp_path / name, progress=False)
        t.fit(stop_at=6)
        return t

    held = run(Trainer, TINY.replace(road_opacity_floor=0.9), Switches(), "floor")
    bg = held.model.background
    opac = torch.sigmoid(bg.opacity_logits.detach())
    road = bg.labels == ROAD
    assert road.sum() > 20 and float(opac[road].min()) >= 0.9 - 1e-6
    assert float(opac[~road].min()) < 0.9                       # the floor is the road's alone
    assert any(k.startswith("densify_") for k in _log(tmp_path / "floor")[2])   # a densification was crossed
    for preset, switches in ((TINY.replace(road_opacity_floor=0.0), Switches()),
                             (TINY.replace(road_opacity_floor=0.9), Switches(flatness=False))):
        tag = f"{preset.road_opacity_floor}_{switches.flatness}"
        a = run(Trainer, preset, switches, "a" + tag).model.state_dict()
        b = run(NoHook, preset, switches, "b" + tag).model.state_dict()
        assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a), tag


@pytest.mark.parametrize("value", [-0.1, 1.0, 1.5, math.nan, True, "0.5"])
def test_bad_road_opacity_floor_is_named(value):
    with pytest.raises(ValueError, match=r"road_opacity_floor: expected an opacity in \[0, 1\)"):
        TINY.replace(road_opacity_floor=value)


def test_road_opacity_floor_is_off_in_every_preset():
    for name in ("tiny", "demo", "small", "paper"):
        assert get_preset("autosplat", name).road_opacity_floor == 0.0, name


# issue 36 (tracker noise): the pose corrections trained in the foreground stage too
def _fg_end() -> int:
    s = TINY.stage_steps()
    return s["bg_phase1"] + s["bg_phase2"] + s["foreground"]


@pytest.mark.slow   # trains the tiny preset three times to the end of the foreground stage
def test_fg_pose_correction_trains_the_corrections_in_the_foreground_stage_only_when_on(street, tmp_path):
    data = prepare_data(street, CAMS, holdout=4)
    on_preset = TINY.replace(fg_pose_correction=True)
    off = Trainer(data, TINY, Switches(), tmp_path / "off", progress=False)
    on = Trainer(data, on_preset, Switches(), tmp_path / "on", progress=False)
    off.fit(stop_at=_fg_end())
    on.fit(stop_at=_fg_end())
    fg = [s for s in range(off.total) if off.stage_of(s)[0] == "foreground"]
    fusion = [s for s in range(off.total) if off.stage_of(s)[0] == "fusion"]
    pose = off.group_owner.index("pose")
    assert fg and all(pose not in off.trainable_groups(s) for s in fg)
    assert all(pose in on.trainable_groups(s) for s in fg)
    assert all(pose in t.trainable_groups(s) for t in (on, off) for s in fusion)
    # the switch off wins: no correction anywhere
    noswitch = Trainer(data, on_preset, Switches(pose_correction=False), tmp_path / "ns", progress=False)
    noswitch._build_optimizer()
    assert all(pose not in noswitch.trainable_groups(s) for s in range(noswitch.total))
    assert torch.count_nonzero(off.model.pose.delta) == 0   # off: untouched until fusion
    d = on.model.pose.delta.detach()
    trained = on.model.pose.trained
    assert torch.count_nonzero(d[:, trained]) > 0            # on: moved in the foreground stage
    assert torch.count_nonzero(d[:, ~trained]) == 0          # held-out frames are interpolated, never trained
    # the foreground renders use them: the same object set placed differently
    k, f = next((k, f) for k in range(len(on.tracks)) for f in np.flatnonzero(trained.numpy())
                if bool(on.model.present[k, f]) and torch.count_nonzero(d[k, f]))
    placed = on.model.object_set(k, int(f)).means
    unplaced = on.model.object_set(k, int(f), pose_correction=False).means
    assert not torch.allclose(placed, unplaced)
    # a run stopped mid-foreground resumes bitwise, corrections and their Adam moments included
    part = Trainer(data, on_preset, Switches(), tmp_path / "part", progress=False)
    part.fit(stop_at=fg[1])
    resumed = Trainer(data, on_preset, Switches(), tmp_path / "part", progress=False)
    resumed.fit(resume=True, stop_at=_fg_end())
    assert torch.equal(resumed.model.pose.delta, on.model.pose.delta)
    a, b = on.opt.state[on.model.pose.delta], resumed.opt.state[resumed.model.pose.delta]
    assert torch.equal(a["exp_avg"], b["exp_avg"]) and torch.equal(a["exp_avg_sq"], b["exp_avg_sq"])


@pytest.mark.parametrize("value", [1, 0, "True", None])
def test_bad_fg_pose_correction_is_named(value):
    with pytest.raises(ValueError, match=r"fg_pose_correction: expected True or False"):
        TINY.replace(fg_pose_correction=value)


def test_fg_pose_correction_is_off_in_every_preset():
    for name in ("tiny", "demo", "small", "paper"):
        assert get_preset("autosplat", name).fg_pose_correction is False, name


@pytest.mark.slow   # trains the tiny preset to the end of the foreground stage
def test_pose_translation_only_learns_the_translation_and_holds_the_rotation(street, tmp_path):
    data = prepare_data(street, CAMS, holdout=4)
    t = Trainer(data, TINY.replace(fg_pose_correction=True, pose_translation_only=True), Switches(), tmp_path,
                progress=False)
    t.fit(stop_at=_fg_end())
    d = t.model.pose.delta.detach()
    assert torch.count_nonzero(d[..., :3]) == 0 and torch.count_nonzero(d[..., 3:]) > 0
    k, f = next((k, f) for k in range(len(t.tracks)) for f in range(d.shape[1]) if torch.count_nonzero(d[k, f]))
    assert torch.equal(t.model.pose(k, f)[3:], d[k, f, 3:]) and torch.count_nonzero(t.model.pose(k, f)[:3]) == 0
    assert TINY.pose_translation_only is False
    with pytest.raises(ValueError, match=r"pose_translation_only: expected True or False"):
        TINY.replace(pose_translation_only=1)


def _step_rows(t: Trainer, step: int) -> set[tuple[int, int]]:
    """The (track, frame) rows of the pose table that ``step``'s samples render."""
    frames = {t.frame_of(step * t.batch_size + j) for j in range(t.batch_size)}
    return {(k, f) for f in frames for k in range(len(t.tracks)) if bool(t.model.present[k, f])}


@pytest.mark.slow   # trains the tiny preset through fusion four times, twice one step at a time
def test_pose_selective_adam_moves_only_the_rows_a_step_renders(street, tmp_path):
    data = prepare_data(street, CAMS, holdout=4)
    fusion = [s for s in range(TINY_STEPS) if Trainer(data, TINY, Switches(), tmp_path / "x",
                                                      progress=False).stage_of(s)[0] == "fusion"]
    outside = {}
    for name, preset in (("plain", TINY), ("selective", TINY.replace(pose_selective_adam=True))):
        t = Trainer(data, preset, Switches(), tmp_path / name, progress=False)
        t.fit(stop_at=fusion[0] + 1)
        moved_outside = 0
        for s in fusion[1:]:
            before = t.model.pose.delta.detach().clone()
            t = Trainer(data, preset, Switches(), tmp_path / name, progress=False)
            t.fit(resume=True, stop_at=s + 1)
            changed = (t.model.pose.delta.detach() != before).any(-1)
            rows = {(int(k), int(f)) for k, f in torch.nonzero(changed)}
            assert rows, f"{name}: step {s} moved no pose row"
            moved_outside += len(rows - _step_rows(t, s))
        outside[name] = moved_outside
        # resumed at every fusion step, bitwise the run that was never stopped (table and moments)
        whole = Trainer(data, preset, Switches(), tmp_path / f"{name}_whole", progress=False)
        whole.fit(stop_at=fusion[-1] + 1)
        assert torch.equal(whole.model.pose.delta, t.model.pose.delta)
        a, b = whole.opt.state[whole.model.pose.delta], t.opt.state[t.model.pose.delta]
        assert torch.equal(a["exp_avg"], b["exp_avg"]) and torch.equal(a["exp_avg_sq"], b["exp_avg_sq"])
    assert outside["plain"] > 0                  # Adam's momentum moves rows the step never rendered
    assert outside["selective"] == 0


def test_pose_selective_adam_is_named_and_off_where_not_chosen():
    with pytest.raises(ValueError, match=r"pose_selective_adam: expected True or False"):
        TINY.replace(pose_selective_adam=1)
    assert TINY.pose_selective_adam is False
    from clsplat.models.common.presets import preset_from_saved
    saved = TINY.replace(pose_selective_adam=True).to_dict()
    del saved["pose_selective_adam"]                 # a record written before the field existed
    assert preset_from_saved("autosplat", saved).pose_selective_adam is False
