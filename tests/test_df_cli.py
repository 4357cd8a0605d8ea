"""``clsplat train|eval drivingforward`` (models/drivingforward/cli.py): run files, bitwise resume,
evaluation metrics and contact sheets, and refusing a checkpoint of another preset."""
import json

import pytest
import torch

from clsplat.models.drivingforward.cli import evaluate, load_model, train

KEYS = {"psnr", "ssim", "abs_rel", "sq_rel", "rmse", "delta1", "scale_ratio"}


def _train(out, steps, *extra):
    return train(["--preset", "tiny", "--steps", str(steps), "--out", str(out), "--no-progress",
                  "--checkpoint-every", "1", *extra])


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    root = tmp_path_factory.mktemp("df")
    assert _train(root / "straight", 2, "--eval-scenes", "1") == 0
    assert _train(root / "resumed", 1, "--eval-scenes", "0") == 0
    assert _train(root / "resumed", 2, "--eval-scenes", "0", "--resume") == 0
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
    assert KEYS <= set(m["all"]) and KEYS <= set(m["CAM_FRONT"])
    ck = torch.load(d / "checkpoint.pt", weights_only=True)
    assert ck["preset"]["name"] == "tiny" and ck["step"] == 2


def test_resume_is_bitwise(runs):
    a = torch.load(runs / "straight" / "checkpoint.pt", weights_only=True)
    b = torch.load(runs / "resumed" / "checkpoint.pt", weights_only=True)
    for k, v in a["model"].items():
        assert torch.equal(v, b["model"][k]), k
    la = [json.loads(x) for x in (runs / "straight" / "log.jsonl").read_text().splitlines()]
    lb = [json.loads(x) for x in (runs / "resumed" / "log.jsonl").read_text().splitlines()]
    strip = lambda r: {k: v for k, v in r.items() if k != "time_s"}  # noqa: E731
    assert [strip(r) for r in la] == [strip(r) for r in lb]


def test_eval_subset_of_cameras_and_frames(runs, tmp_path):
    ck = runs / "straight" / "checkpoint.pt"
    rc = evaluate(["--checkpoint", str(ck), "--num-scenes", "1", "--cameras", "CAM_FRONT", "CAM_BACK",
                   "--frames", "-1", "0", "--target", "1", "--no-oracle", "--out", str(tmp_path)])
    assert rc == 0
    m = json.loads((tmp_path / "metrics.json").read_text())
    assert set(m) >= {"CAM_FRONT", "CAM_BACK", "all"} and "CAM_FRONT_LEFT" not in m
    assert KEYS <= set(m["all"]) and m["settings"]["frames"] == [-1, 0]
    assert (tmp_path / "contact_sheet.png").is_file()


def test_errors_name_the_argument(runs, tmp_path, capsys):
    ck = runs / "straight" / "checkpoint.pt"
    with pytest.raises(ValueError, match="preset 'tiny', not 'small'"):
        load_model(str(ck), preset_name="small")
    assert evaluate(["--checkpoint", str(ck), "--preset", "small", "--out", str(tmp_path)]) == 2
    assert "not 'small'" in capsys.readouterr().err
    assert evaluate(["--checkpoint", str(ck), "--frames", "2", "--out", str(tmp_path)]) == 2
    assert "frames/target" in capsys.readouterr().err
    assert train(["--preset", "huge", "--steps", "1", "--out", str(tmp_path)]) == 2
    assert "unknown preset 'huge'" in capsys.readouterr().err
    assert evaluate(["--checkpoint", str(tmp_path / "none.pt"), "--out", str(tmp_path)]) == 2
    assert "does not exist" in capsys.readouterr().err
