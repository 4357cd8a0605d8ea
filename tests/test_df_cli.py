"""``clsplat train|eval drivingforward`` (models/drivingforward/cli.py): run files, bitwise resume,
two-process data parallel == one process, evaluation metrics and contact sheets (synthetic, and a
PandaSet-format folder scored against projected LiDAR), LPIPS off without weights, and refusing a
checkpoint of another preset."""
import contextlib
import json

import pytest
import torch

from clsplat.models.common.data import parse_data
from clsplat.models.common.metrics import LPIPS_OFF_MESSAGE
from clsplat.models.common.presets import get_preset
from clsplat.models.drivingforward.cli import evaluate, load_model, train
from clsplat.models.drivingforward.data import load_triplet

KEYS = {"psnr", "ssim", "abs_rel", "sq_rel", "rmse", "delta1", "scale_ratio"}
POSE_KEYS = {"pose_t_err_m", "pose_t_err_pct", "pose_r_err_deg", "pose_t_pred_m", "pose_t_true_m"}

pytestmark = pytest.mark.slow   # the tests train the tiny preset (the module's runs, torchrun) or evaluate it


def _train(out, steps, *extra):
    """A tiny run on one torch thread (conftest.DF_TINY_RUN's), so runs compare bit for bit."""
    return train(["--preset", "tiny", "--steps", str(steps), "--out", str(out), "--no-progress",
                  "--checkpoint-every", "1", "--threads", "1", *extra])


@pytest.fixture(scope="module")
def runs(tmp_path_factory, df_tiny_run):
    import shutil
    root = tmp_path_factory.mktemp("df")
    curve = ("--val-every", "1", "--val-scenes", "1")
    shutil.copytree(df_tiny_run, root / "straight")   # the session's run (conftest.DF_TINY_RUN)
    assert _train(root / "resumed", 1, "--eval-scenes", "0", *curve) == 0
    assert _train(root / "resumed", 2, "--eval-scenes", "0", "--resume", *curve) == 0
    assert _train(root / "dataset", 2, "--eval-scenes", "1", "--pose", "dataset",
                  "--set", "detach_render_pose=True") == 0
    return root


def test_train_writes_the_run_files(runs, capsys):
    d = runs / "straight"
    for f in ("checkpoint.pt", "log.jsonl", "loss.png", "metrics.json", "contact_sheet.png", "depth_sheet.png"):
        assert (d / f).is_file(), f
    log = [json.loads(line) for line in (d / "log.jsonl").read_text().splitlines()]
    assert [r["step"] for r in log] == [1, 2]
    assert {"loss", "reproj", "smooth", "spatial", "spatio_temporal", "render", "mse"} <= set(log[0])
    assert "lpips" not in log[0]
    m = json.loads((d / "metrics.json").read_text())
    assert KEYS <= set(m["all"]) and KEYS <= set(m["per_camera"]["CAM_FRONT"])
    ck = torch.load(d / "checkpoint.pt", weights_only=True)
    assert ck["preset"]["name"] == "tiny" and ck["step"] == 2


def test_eval_reports_the_pose_networks_motion_against_the_datas(runs):
    m = json.loads((runs / "straight" / "metrics.json").read_text())
    assert POSE_KEYS <= set(m["all"]) and not POSE_KEYS & set(m["per_camera"]["CAM_FRONT"])
    a = m["all"]
    s = load_triplet(parse_data("synthetic", default_world="varied"), 0, get_preset("drivingforward", "tiny"), "test")
    from clsplat.models.drivingforward.data import camera0_motion
    assert a["pose_t_true_m"] == pytest.approx(float(camera0_motion(s)[:3, 3].norm()), rel=1e-5)
    assert a["pose_t_err_m"] >= abs(a["pose_t_true_m"] - a["pose_t_pred_m"]) - 1e-9   # triangle inequality
    if a["pose_t_true_m"] >= 1e-3:
        assert a["pose_t_err_pct"] == pytest.approx(100 * a["pose_t_err_m"] / a["pose_t_true_m"], rel=1e-6)
    else:                                                 # a standing ego: no percentage of zero motion
        assert a["pose_t_err_pct"] is None and a["pose_t_err_pct_median"] is None
    assert m["protocol"]["pose_source"] == "network"


def test_eval_reports_speed_bins_and_the_constant_motion_control(runs):
    """Issue 32: every metrics.json has a ``speed_bins`` block keyed by the four ego-speed bins, the bin
    of each held-out window holding the keys of ``all``, and the constant-motion control (the training
    split's mean motion) beside the pose network's error."""
    from clsplat.data.synthetic import SPEED_BINS, speed_bin
    m = json.loads((runs / "straight" / "metrics.json").read_text())
    a, bins = m["all"], m["speed_bins"]
    assert list(bins) == list(SPEED_BINS) == ["standing", "0.5-5", "5-10", "10-15"]
    hit = speed_bin(a["speed_mps"])
    assert set(bins[hit]) == set(a) and bins[hit]["windows"] == a["windows"] == 1
    assert all(bins[k] == {"windows": 0} for k in bins if k != hit)
    assert {"constant_motion_t_err_m", "constant_motion_t_err_pct_median", "pose_t_err_pct_median"} <= set(a)
    assert "constant_motion" in m["protocol"] and m["protocol"]["split"] == "test"


def test_the_constant_motion_of_the_classic_street_is_its_exact_motion():
    """Why the classic street cannot show that a pose network learned anything: its training split's
    mean motion is every test street's motion to 1e-9 m (constant 8 m/s); the varied world's is not."""
    from clsplat.models.common.metrics import pose_errors
    from clsplat.models.drivingforward.data import camera0_motion
    from clsplat.models.drivingforward.evaluation import training_controls
    p = get_preset("drivingforward", "tiny")
    for world, exact in (("classic", True), ("varied", False)):
        src = parse_data(f"synthetic:{world}")
        _, motion = training_controls(src, p, 3, ["CAM_FRONT"], layout=False)
        errs = [pose_errors(motion, camera0_motion(load_triplet(src, i, p, "test", ["CAM_FRONT"])))["t_err_m"]
                for i in range(3)]
        assert (max(errs) < 1e-9) == exact, (world, errs)


def test_validation_curve_starts_before_training_and_resumes_as_one_run(runs):
    """``val_curve.jsonl``: depth and pose on validation windows at step 0 and every --val-every steps;
    a resumed run's curve equals the uninterrupted one's, point for point."""
    a, b = ([json.loads(x) for x in (runs / r / "val_curve.jsonl").read_text().splitlines()]
            for r in ("straight", "resumed"))
    assert [r["step"] for r in a] == [0, 1, 2] and a == b
    assert {"abs_rel", "delta1", "scale_ratio", "pose_t_err_m"} <= set(a[0])
    assert (runs / "straight" / "val_curve.png").is_file()


def test_eval_split_val_scores_the_validation_streets(runs, tmp_path):
    out = {}
    for split in ("val", "test"):
        assert evaluate(["--checkpoint", str(runs / "straight" / "checkpoint.pt"), "--out", str(tmp_path / split),
                         "--num-scenes", "1", "--no-progress", "--no-oracle", "--layout-windows", "0",
                         "--eval-split", split]) == 0
        out[split] = json.loads((tmp_path / split / "metrics.json").read_text())
    assert out["val"]["protocol"]["split"] == "val" and out["val"]["all"]["psnr"] != out["test"]["all"]["psnr"]


def test_eval_scores_the_image_blind_layout_baseline_beside_the_model(runs):
    """``layout_*``: the per-pixel median true depth of the first training windows, the same map for
    every held-out window, scored like the model (a model that does not beat it has not learned
    depth from its images)."""
    from clsplat.models.common.presets import get_preset
    from clsplat.models.drivingforward.evaluation import layout_depth

    p, src, cams = get_preset("drivingforward", "tiny"), parse_data("synthetic"), ["CAM_FRONT_LEFT"]
    lay = layout_depth(src, p, 3, cams)
    truth = torch.stack([load_triplet(src, i, p, "train", cams)["depths"][1] for i in range(3)]).double()
    assert torch.isinf(truth).any()                         # sky: counted as the far limit
    assert torch.equal(lay, truth.clamp(max=p.max_depth).median(0).values.float())
    test = torch.stack([load_triplet(src, i, p, "test", cams)["depths"][1] for i in range(3)]).double()
    assert not torch.equal(lay, test.clamp(max=p.max_depth).median(0).values.float())   # training windows only
    assert layout_depth(src, p, 0, cams) is None
    with pytest.raises(ValueError, match="--layout-windows"):
        layout_depth(src, p, -1, cams)
    m = json.loads((runs / "straight" / "metrics.json").read_text())
    assert {"layout_abs_rel", "layout_delta1", "layout_scale_ratio"} <= set(m["all"])
    assert 0 < m["all"]["layout_abs_rel"] < 1 and m["protocol"]["layout"].startswith("image-blind")


def test_dataset_pose_run_keeps_the_pose_network_untrained_and_its_choice(runs, tmp_path, capsys):
    from clsplat.models.common.presets import get_preset
    from clsplat.models.common.train import seed_everything
    from clsplat.models.drivingforward.model import DrivingForward

    d = runs / "dataset"
    ck = torch.load(d / "checkpoint.pt", weights_only=True)
    assert ck["preset"]["pose_source"] == "dataset" and ck["preset"]["detach_render_pose"] is True
    seed_everything(0)
    init = DrivingForward(get_preset("drivingforward", "tiny")).state_dict()
    pose = [k for k in init if k.startswith("pose_net.") and "running" not in k and "num_batches" not in k]
    assert pose and all(torch.equal(init[k], ck["model"][k]) for k in pose)
    depth = [k for k in init if k.startswith("depth_net.") and k.endswith("weight")]
    assert any(not torch.equal(init[k], ck["model"][k]) for k in depth)       # the rest did train
    m = json.loads((d / "metrics.json").read_text())
    assert KEYS <= set(m["all"]) and not POSE_KEYS & set(m["all"]) and m["protocol"]["pose_source"] == "dataset"
    model, preset = load_model(str(d / "checkpoint.pt"))                      # eval runs the run's preset
    assert preset.pose_source == "dataset" and preset.detach_render_pose and preset.name == "tiny"
    # resuming without the run's choices is refused, naming the field
    assert _train(d, 3, "--eval-scenes", "0", "--resume") == 2
    assert "pose_source" in capsys.readouterr().err
    assert _train(d, 3, "--eval-scenes", "0", "--resume", "--pose", "dataset", "--set", "detach_render_pose=True") == 0


@pytest.mark.parametrize("args, msg", [
    (["--set", "nofield=1"], "unknown preset fields ['nofield']"), (["--set", "lr"], "FIELD=VALUE"),
    (["--set", "lr=abc"], "not a Python literal"), (["--set", "detach_render_pose=3"], "expected a bool"),
    (["--set", "name='x'"], "name cannot be changed"), (["--set", "supersample=0"], "supersample"),
    (["--set", "pose_translation_init=(0, 0, -9)"], "pose_translation_init"), (["--pose", "gps"], "invalid choice"),
])
def test_preset_overrides_reject_bad_input_with_one_line(tmp_path, capsys, args, msg):
    with pytest.raises(SystemExit) if args[0] == "--pose" else contextlib.nullcontext():
        assert _train(tmp_path, 1, *args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert msg in err[-1]
    assert not (tmp_path / "checkpoint.pt").exists()


def test_resume_is_bitwise(runs):
    a = torch.load(runs / "straight" / "checkpoint.pt", weights_only=True)
    b = torch.load(runs / "resumed" / "checkpoint.pt", weights_only=True)
    for k, v in a["model"].items():
        assert torch.equal(v, b["model"][k]), k
    la = [json.loads(x) for x in (runs / "straight" / "log.jsonl").read_text().splitlines()]
    lb = [json.loads(x) for x in (runs / "resumed" / "log.jsonl").read_text().splitlines()]
    strip = lambda r: {k: v for k, v in r.items() if k not in ("time_s", "backward_s")}  # noqa: E731 (timings)
    assert [strip(r) for r in la] == [strip(r) for r in lb]


def test_eval_subset_of_cameras_and_frames(runs, tmp_path, capsys):
    ck = runs / "straight" / "checkpoint.pt"
    rc = evaluate(["--checkpoint", str(ck), "--num-scenes", "1", "--cameras", "CAM_FRONT", "CAM_BACK",
                   "--offsets", "-1", "0", "--target", "1", "--no-oracle", "--out", str(tmp_path)])
    assert rc == 0
    assert LPIPS_OFF_MESSAGE in capsys.readouterr().out    # no weights: says so, never reports LPIPS
    m = json.loads((tmp_path / "metrics.json").read_text())
    assert set(m["per_camera"]) == {"CAM_FRONT", "CAM_BACK"}
    assert KEYS <= set(m["all"]) and KEYS <= set(m["per_camera"]["CAM_BACK"]) and m["protocol"]["frames"] == [-1, 0]
    assert "lpips" not in m["all"] and m["protocol"]["lpips"].startswith("off")
    assert (tmp_path / "contact_sheet.png").is_file()


def test_eval_supersample_scores_a_model_on_other_images_of_the_same_streets(runs, tmp_path, capsys):
    """``--supersample S`` renders the held-out images with S x S rays per pixel whatever the model
    trained on (issue 17's lead 3 compares models on the same images); the default is the preset's."""
    ck = runs / "straight" / "checkpoint.pt"
    trained = json.loads((runs / "straight" / "metrics.json").read_text())
    assert trained["protocol"]["supersample"] == 1
    # --threads 1 as the training run had: the bitwise comparison below needs one summation order
    for s in ("1", "2"):
        assert evaluate(["--checkpoint", str(ck), "--num-scenes", "1", "--supersample", s, "--threads", "1",
                         "--out", str(tmp_path / f"s{s}")]) == 0
    m1, m2 = (json.loads((tmp_path / d / "metrics.json").read_text()) for d in ("s1", "s2"))
    assert m1["all"] == trained["all"]                     # the preset's own images: the training evaluation
    assert m2["protocol"]["supersample"] == 2 and m2["all"]["n_pixels"] == m1["all"]["n_pixels"]
    assert m2["all"]["psnr"] != m1["all"]["psnr"] and m2["all"]["oracle_psnr"] != m1["all"]["oracle_psnr"]
    with pytest.raises(SystemExit) as e:                   # argparse: one line naming the argument
        evaluate(["--checkpoint", str(ck), "--supersample", "0", "--out", str(tmp_path / "bad")])
    assert e.value.code == 2 and "--supersample" in capsys.readouterr().err


def test_errors_name_the_argument(runs, tmp_path, capsys):
    ck = runs / "straight" / "checkpoint.pt"
    with pytest.raises(ValueError, match="preset 'tiny', not 'small'"):
        load_model(str(ck), preset_name="small")
    assert evaluate(["--checkpoint", str(ck), "--preset", "small", "--out", str(tmp_path)]) == 2
    assert "not 'small'" in capsys.readouterr().err
    assert evaluate(["--checkpoint", str(ck), "--offsets", "2", "--out", str(tmp_path)]) == 2
    assert "--offsets/--target" in capsys.readouterr().err
    assert train(["--preset", "huge", "--steps", "1", "--out", str(tmp_path)]) == 2
    assert "unknown preset 'huge'" in capsys.readouterr().err
    assert evaluate(["--checkpoint", str(tmp_path / "none.pt"), "--out", str(tmp_path)]) == 2
    assert "does not exist" in capsys.readouterr().err


def test_two_process_data_parallel_equals_one_process(tmp_path, two_process_run):
    """``torchrun --nproc_per_node 2`` with global batch 2 makes the same update as one process
    with batch 2 (gradients all-reduced). BatchNorm running statistics are not part of the update:
    as with torch DDP's buffer broadcast, the checkpoint carries rank 0's."""
    # --threads 1 in both runs: each sample's forward and backward then do the same float32
    # arithmetic in one process and in two (torch's default thread count follows the machine's
    # load, and another count changes the convolutions' summation order), so what differs is only
    # the reduction this test is about.
    args = ["--preset", "tiny", "--steps", "1", "--batch-size", "2", "--eval-scenes", "0", "--no-progress",
            "--threads", "1"]
    one, two = two_process_run(tmp_path, "drivingforward", args, timeout=300)
    assert two["step"] == one["step"] == 1
    # One process accumulates (loss_a / 2).backward() and (loss_b / 2).backward() in float32; two
    # processes compute the same per-sample gradients and all-reduce them. Halving the loss halves
    # every gradient exactly (a power of two), and the sum of two float32 terms is correctly rounded
    # either way, so the moments (Adam's exp_avg = 0.1 g after one step) agree bit for bit, and so do
    # the weights, Adam being elementwise. A wrong reduction (a missing all-reduce, a sum for a mean,
    # a per-rank normalisation) moves the gradients by O(1) of their size.
    from clsplat.models.common.presets import get_preset
    from clsplat.models.drivingforward.cli import make_optimizer
    from clsplat.models.drivingforward.model import DrivingForward

    model = DrivingForward(get_preset("drivingforward", "tiny"))
    names = {id(q): k for k, q in model.named_parameters()}
    params = [names[id(q)] for g in make_optimizer(model, model.preset).param_groups for q in g["params"]]
    assert len(one["optimizer"]["state"]) == len(two["optimizer"]["state"]) == len(params)
    for i, k in enumerate(params):
        for moment in ("exp_avg", "exp_avg_sq"):
            assert torch.equal(one["optimizer"]["state"][i][moment], two["optimizer"]["state"][i][moment]), (k, moment)
        assert torch.equal(one["model"][k], two["model"][k]), k
    assert len(params) > 100
    la = json.loads((tmp_path / "one" / "log.jsonl").read_text().splitlines()[0])
    lb = json.loads((tmp_path / "two" / "log.jsonl").read_text().splitlines()[0])
    assert la["loss"] == pytest.approx(lb["loss"], rel=1e-5) and "skipped" not in la and "skipped" not in lb


def test_eval_on_a_pandaset_sequence_scores_depth_against_projected_lidar(runs, tmp_path, capsys):
    """A PandaSet-format folder (clsplat's writer, from a synthetic street with simulated LiDAR) has
    no depth maps: depth is scored against the LiDAR sweep projected into each camera, and that
    projection agrees with the generator's depth maps."""
    from clsplat.data import write_pandaset
    from clsplat.models.common.data import to_torch_frame
    from clsplat.models.common.presets import get_preset

    cams = ["CAM_FRONT", "CAM_FRONT_LEFT"]
    seq = parse_data("synthetic").sequence(0, num_frames=15, height=32, width=56, lidar=True, dt=0.1, cameras=cams)
    write_pandaset(seq, tmp_path / "001")
    src = parse_data(f"pandaset:{tmp_path / '001'}")
    s = load_triplet(src, 0, get_preset("drivingforward", "tiny"), "test")
    assert "depths" not in s and s["lidar_depth"].shape == (2, 32, 56)
    ld, gt = s["lidar_depth"], to_torch_frame(seq, 13)["depths"]          # test window 0 = frames 12..14
    ok = torch.isfinite(ld) & torch.isfinite(gt)
    assert ok.float().mean() > 0.3 and float(((ld[ok] - gt[ok]).abs() / gt[ok]).median()) < 0.03
    rc = evaluate(["--checkpoint", str(runs / "straight" / "checkpoint.pt"), "--data", f"pandaset:{tmp_path / '001'}",
                   "--num-scenes", "1", "--out", str(tmp_path / "eval")])
    assert rc == 0
    m = json.loads((tmp_path / "eval" / "metrics.json").read_text())
    assert KEYS <= set(m["all"]) and m["all"]["n_pixels"] > 0 and "oracle_psnr" not in m["all"]
    assert m["protocol"]["depth_gt"].startswith("projected LiDAR") and m["protocol"]["data"].startswith("pandaset")
    assert (tmp_path / "eval" / "depth_sheet.png").is_file()
    # the layout over sparse LiDAR: the median of the windows that have a return at a pixel (a
    # missing return is unknown, not far), so it lies within the returns' range where any exists
    from clsplat.models.drivingforward.evaluation import evaluate_model, layout_depth
    tiny = get_preset("drivingforward", "tiny")
    lay = layout_depth(src, tiny, 3, cams)
    sweeps = torch.stack([load_triplet(src, i, tiny, "train", cameras=cams)["lidar_depth"] for i in range(3)])
    hit = torch.isfinite(sweeps).any(0)
    assert hit.float().mean() > 0.3 and (lay[~hit] == tiny.max_depth).all()
    lo, hi = sweeps.nan_to_num(posinf=1e9).amin(0), sweeps.nan_to_num(posinf=-1.0).amax(0)
    assert ((lay[hit] >= lo[hit]) & (lay[hit] <= hi[hit].clamp(max=tiny.max_depth))).all()
    assert 0 < m["all"]["layout_abs_rel"] < 1
    with pytest.raises(ValueError, match="--layout-windows"):     # checked before any depth is looked for
        evaluate_model(torch.nn.Module(), src, layout=-1)
    # the path of a user with one recorded sequence: self-supervised training on it with the same
    # command, then held-out frames scored against projected LiDAR, with the pose against its ego poses
    seq6 = parse_data("synthetic").sequence(1, num_frames=15, height=32, width=56, lidar=True, dt=0.1)
    write_pandaset(seq6, tmp_path / "002")
    assert _train(tmp_path / "train", 1, "--data", f"pandaset:{tmp_path / '002'}", "--eval-scenes", "1") == 0
    # its 15 frames leave 2 for validation, fewer than a window: the run says so and goes on
    assert "no validation curve: num_frames: the val split" in capsys.readouterr().out
    assert not (tmp_path / "train" / "val_curve.jsonl").exists()
    m = json.loads((tmp_path / "train" / "metrics.json").read_text())
    assert KEYS <= set(m["all"]) and POSE_KEYS <= set(m["all"]) and 0.7 < m["all"]["pose_t_true_m"] < 0.9
    assert m["protocol"]["depth_gt"].startswith("projected LiDAR")


def test_eval_on_a_full_disk_is_one_line_and_keeps_the_earlier_evaluation(runs, tmp_path, full_disk_on, capsys):
    """The contact sheet (written after metrics.json) hits a full disk: one line naming the file,
    and the earlier evaluation's files stay as they were (not a new metrics.json beside old sheets)."""
    import re

    from clsplat.cli import console

    out = tmp_path / "eval"
    args = ["eval", "drivingforward", "--checkpoint", str(runs / "straight" / "checkpoint.pt"), "--num-scenes", "1",
            "--no-oracle", "--out", str(out)]
    assert console(args) == 0
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    assert {"metrics.json", "contact_sheet.png"} <= set(before)
    full_disk_on("contact_sheet")
    capsys.readouterr()
    assert console(args + ["--seed", "1"]) == 1
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert re.fullmatch(rf"clsplat eval drivingforward: writing '{re.escape(str(out))}/\.staging-[^/]+/"
                        r"contact_sheet\.png' failed \(No space left on device\); no partial file is left", err), err
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before


def test_view_serves_the_run_and_leaves_it_unchanged(runs, tmp_path, capsys):
    """``--view`` (no browser connected): the viewer starts at the first step, showing the model run
    on a held-out sample, and the run's weights are bitwise those of the same run unwatched; a
    port in use is a one-line error naming --view-port before the run starts."""
    pytest.importorskip("viser", reason="the view extra is not installed")
    import socket
    assert _train(tmp_path / "viewed", 2, "--eval-scenes", "0", "--view", "--view-port", "0") == 0
    assert "clsplat train --view: watch the run at http://127.0.0.1:" in capsys.readouterr().out
    a = torch.load(runs / "straight" / "checkpoint.pt", weights_only=True)["model"]
    b = torch.load(tmp_path / "viewed" / "checkpoint.pt", weights_only=True)["model"]
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen(1)
        port = s.getsockname()[1]
        assert _train(tmp_path / "taken", 1, "--view", "--view-port", str(port)) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"--view-port {port}: cannot listen" in err[0]
    assert not (tmp_path / "taken" / "checkpoint.pt").exists()


def test_lr_warmup_ramps_the_rate_and_resumes_bitwise(tmp_path):
    """``lr_warmup=N``: step s (from 1) runs at s/N of the preset's rate until the ramp is done; the
    ramp is checkpointed with the optimiser, so a resumed run equals a straight one bit for bit,
    with every departure of ``small``'s recipe on (the ground prior and the zero-started output layer,
    the pose's initial motion, the second-order smoothness, no spatio-temporal term)."""
    from clsplat.models.drivingforward.presets import SMALL, TINY
    warm = ("--eval-scenes", "0", "--set", "lr_warmup=4", "--set", f"ground_prior_cap={SMALL.ground_prior_cap}",
            "--set", f"pose_translation_init={SMALL.pose_translation_init}",
            "--set", f"depth_zero_init={SMALL.depth_zero_init}", "--set", f"smooth_order={SMALL.smooth_order}",
            "--set", f"w_smooth={SMALL.w_smooth}", "--set", f"w_spatio_temporal={SMALL.w_spatio_temporal}")
    assert _train(tmp_path / "straight", 3, *warm) == 0
    assert _train(tmp_path / "resumed", 2, *warm) == 0
    assert _train(tmp_path / "resumed", 3, *warm, "--resume") == 0
    logs = [[json.loads(x) for x in (tmp_path / r / "log.jsonl").read_text().splitlines()]
            for r in ("straight", "resumed")]
    assert [r["lr"] for r in logs[0]] == pytest.approx([TINY.lr * s / 4 for s in (1, 2, 3)])
    assert [r["loss"] for r in logs[0]] == [r["loss"] for r in logs[1]]
    a, b = (torch.load(tmp_path / r / "checkpoint.pt", weights_only=True) for r in ("straight", "resumed"))
    assert a["preset"]["ground_prior_cap"] == b["preset"]["ground_prior_cap"] == SMALL.ground_prior_cap
    assert "spatio_temporal" not in logs[0][0] and a["preset"]["w_spatio_temporal"] == 0.0
    for k, v in a["model"].items():
        assert torch.equal(v, b["model"][k]), k
