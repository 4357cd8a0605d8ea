"""One contract for the three model families (models/README.md): ``clsplat train|eval FAMILY``
take the same flags, print a user's mistake as one line naming the argument with exit status 2,
and write ``metrics.json`` in one schema (models/common/report.py) with the same keys for the
same quantities; every family has the ``tiny``, ``small`` and ``paper`` presets."""
import json

import pytest

from clsplat.cli import console
import clsplat.models.registry  # noqa: F401  (every family, with its presets)
from clsplat.models import FAMILIES
from clsplat.models.common.presets import preset_names
from clsplat.models.common.report import METRICS_SCHEMA, check_report

TRAIN_FLAGS = ("--data", "--preset", "--set", "--steps", "--out", "--resume", "--seed", "--device", "--threads",
               "--checkpoint-every", "--batch-size", "--weights", "--no-progress", "--trust-pickle", "--lpips-vgg",
               "--lpips-lin")
EVAL_FLAGS = ("--checkpoint", "--data", "--out", "--device", "--threads", "--seed", "--no-progress",
              "--trust-pickle", "--lpips-vgg", "--lpips-lin")
#: the smallest run that trains and evaluates (a few seconds)
TINY_RUN = {"pgt": ["--steps", "1", "--eval-scenes", "1"]}   # the others: the session's runs (conftest)
EVAL_RUN = {"drivingforward": ["--num-scenes", "1", "--no-oracle"], "pgt": ["--num-scenes", "1", "--budgets", "1"],
            "autosplat": []}


def _run(argv: list[str]) -> int:
    """The exit status of ``clsplat ARGV`` (argparse's mistakes exit; the commands return)."""
    try:
        return console(argv)
    except SystemExit as e:
        return e.code


def _help(capsys, *argv) -> str:
    with pytest.raises(SystemExit) as e:
        console([*argv, "--help"])
    assert e.value.code == 0
    return capsys.readouterr().out


@pytest.mark.parametrize("family", FAMILIES)
def test_the_same_flags(family, capsys):
    text = _help(capsys, "train", family)
    assert [f for f in TRAIN_FLAGS if f not in text] == []
    text = _help(capsys, "eval", family)
    assert [f for f in EVAL_FLAGS if f not in text] == []


@pytest.mark.parametrize("family", FAMILIES)
def test_every_family_has_the_same_preset_names(family):
    assert {"tiny", "small", "paper"} <= set(preset_names(family))


@pytest.mark.parametrize("family", FAMILIES)
@pytest.mark.parametrize("argv,named", [
    (["--preset", "huge"], "'huge'"),
    (["--set", "no_such_field=1"], "--set"),
    (["--set", "name"], "--set"),
    (["--steps", "0"], "--steps"),
    (["--data", "kitti:/x"], "kitti"),
    (["--threads", "many"], "--threads"),
])
def test_a_mistake_is_one_line_naming_the_argument(family, argv, named, tmp_path, capsys):
    rc = _run(["train", family, "--preset", "tiny", "--no-progress", "--out", str(tmp_path / "o"), *argv])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and err[0].startswith(f"clsplat train {family}") and named in err[0], err
    assert not (tmp_path / "o" / "checkpoint.pt").exists()


@pytest.mark.parametrize("family", FAMILIES)
def test_weights_are_loaded_or_refused_by_name(family, tmp_path, capsys):
    missing = tmp_path / "resnet18.pth"
    rc = _run(["train", family, "--preset", "tiny", "--no-progress", "--weights", str(missing),
               "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1
    # a family with a backbone names the file it cannot read; the others say they have none
    assert (str(missing) in err[0]) if family == "drivingforward" else ("--weights" in err[0]), err


@pytest.fixture(scope="module")
def runs(tmp_path_factory, autosplat_tiny_run, df_tiny_run):
    """Every family's tiny run and its evaluation; AutoSplat's and DrivingForward's are the
    session's shared runs (tests/conftest.py), trained once for every file that reads them."""
    import shutil
    root = tmp_path_factory.mktemp("contract")
    shared = {"autosplat": autosplat_tiny_run, "drivingforward": df_tiny_run}
    for family in FAMILIES:
        out = root / family
        if family in shared:
            shutil.copytree(shared[family], out)
        else:
            assert console(["train", family, "--preset", "tiny", "--no-progress", "--out", str(out),
                            *TINY_RUN[family]]) == 0
        assert console(["eval", family, "--checkpoint", str(out / "checkpoint.pt"), "--no-progress",
                        "--out", str(root / f"{family}-eval"), *EVAL_RUN[family]]) == 0
    return root


@pytest.mark.slow   # trains and evaluates every family's tiny preset
@pytest.mark.parametrize("family", FAMILIES)
@pytest.mark.parametrize("folder", ["{}", "{}-eval"])
def test_metrics_json_has_one_schema(runs, family, folder):
    m = json.loads((runs / folder.format(family) / "metrics.json").read_text())
    check_report(m)
    assert m["schema"] == METRICS_SCHEMA and m["family"] == family and m["preset"] == "tiny" and m["step"] >= 1
    assert m["protocol"]["psnr"].startswith("mean over images") and "valid" in m["protocol"]["ssim"]
    assert m["protocol"]["lpips"].startswith("off")           # no weights given: no LPIPS key anywhere
    for block in (m["all"], *m["per_camera"].values()):
        assert 0 < block["psnr"] < 100 and -1 <= block["ssim"] <= 1 and "lpips" not in block
    assert m["per_camera"] and set(m["per_camera"]) <= {"CAM_FRONT", "CAM_FRONT_LEFT", "CAM_FRONT_RIGHT",
                                                        "CAM_BACK_LEFT", "CAM_BACK_RIGHT", "CAM_BACK"}
    leftovers = {"test_psnr", "test_ssim", "psnr_mean", "settings", "iterations"} & set(m)
    assert not leftovers, f"keys outside the schema: {leftovers}"


@pytest.mark.slow   # trains and evaluates every family's tiny preset
def test_eval_autosplat_reproduces_the_training_evaluation(runs):
    """AutoSplat's held-out frames scored by ``train`` and again by ``eval`` on its checkpoint
    (the model rebuilt on the run's recorded data) give the same numbers."""
    a = json.loads((runs / "autosplat" / "metrics.json").read_text())
    b = json.loads((runs / "autosplat-eval" / "metrics.json").read_text())
    assert b["step"] == a["step"] and b["protocol"]["test_frames"] == a["protocol"]["test_frames"]
    assert b["all"]["psnr"] == pytest.approx(a["all"]["psnr"], abs=1e-4)
    assert b["all"]["ssim"] == pytest.approx(a["all"]["ssim"], abs=1e-5)


def test_one_name_for_one_meaning_across_the_presets():
    """Fields that mean the same thing have the same name in every family (the depth range of the
    predicted depth, the scale cap in metres, ...); names retired by a rename are gone and a
    checkpoint's preset record that still uses them reads as the new names."""
    import dataclasses

    from clsplat.models.common.presets import check_preset_matches, get_preset, preset_from_saved

    fields = {f: {x.name for x in dataclasses.fields(get_preset(f, "tiny"))} for f in FAMILIES}
    shared = {"min_depth", "max_depth", "scale_cap", "sh_degree", "lr", "steps", "batch_size", "grad_clip", "w_lpips"}
    assert shared <= fields["drivingforward"] and shared <= fields["pgt"]
    assert "sh_degree" in fields["autosplat"]
    retired = {"near", "far", "scale_cap_m"}
    assert not any(retired & names for names in fields.values())
    pgt = get_preset("pgt", "tiny")
    old = {{"min_depth": "near", "max_depth": "far", "scale_cap": "scale_cap_m"}.get(k, k): v
           for k, v in pgt.to_dict().items()}
    check_preset_matches(old, pgt, "old.pt")                 # no error: the same preset under old names
    assert preset_from_saved("pgt", old) == pgt


@pytest.mark.slow   # trains PGT's tiny preset for one step
def test_a_run_names_the_opencl_device_it_renders_on(tmp_path, capsys):
    """The first line of a run names the renderer (platform and device), so that a log says where
    its times and bits came from (bench/experiments/gpu_models.sh reads it)."""
    import clsplat
    assert console(["train", "pgt", "--preset", "tiny", "--no-progress", "--out", str(tmp_path / "run"),
                    *TINY_RUN["pgt"]]) == 0
    head = [line for line in capsys.readouterr().out.splitlines() if "torch threads" in line][0]
    assert head.endswith(f", renderer {clsplat.get_runtime().name}"), head
