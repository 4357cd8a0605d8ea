"""``clsplat train pgt`` / ``clsplat eval pgt`` (models/pgt/cli.py) end to end on the tiny preset:
base stage, budget stage from --init, bitwise resume, the budget curve files, and clear errors."""
from __future__ import annotations

import json

import pytest
import torch

from clsplat.models.pgt.cli import evaluate, parse_budgets, train

pytestmark = pytest.mark.slow   # every test trains the tiny preset (the module's runs) or evaluates it


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    # every run of this module on one torch thread: the tests compare their weights bit for bit, and
    # the default thread count follows the machine's load (a sum in another order)
    root = tmp_path_factory.mktemp("pgt")
    base, budget = root / "base", root / "budget"
    assert train(["--stage", "base", "--preset", "tiny", "--threads", "1", "--steps", "2", "--out", str(base)]) == 0
    assert train(["--stage", "budget", "--init", str(base / "checkpoint.pt"), "--preset", "tiny", "--threads", "1",
                  "--steps", "2", "--out", str(budget)]) == 0
    return root


def test_stages_write_runs_and_only_the_budget_heads_change(runs):
    base = torch.load(runs / "base" / "checkpoint.pt", weights_only=True)
    budget = torch.load(runs / "budget" / "checkpoint.pt", weights_only=True)
    assert base["step"] == 2 and budget["step"] == 2 and budget["extra"]["stage"] == "budget"
    for k, v in base["model"].items():
        assert torch.equal(v, budget["model"][k]), k  # everything but the copies is frozen
    copies = [k for k in budget["model"] if k.startswith("budget.")]
    assert "budget.rate.weight" in copies and budget["model"]["budget.rate.weight"].shape[-2:] == (7, 7)
    assert any(not torch.equal(budget["model"][k], base["model"][k.replace("budget.heads.", "heads.")])
               for k in copies if k.startswith("budget.heads."))
    logs = [json.loads(line) for line in (runs / "budget" / "log.jsonl").read_text().splitlines()]
    assert len(logs) == 2 and all({"io", "kappa", "render", "loss"} <= set(r) for r in logs)
    assert all(0.85 <= r["kappa"] <= 0.95 for r in logs)
    assert (runs / "base" / "loss.png").is_file()


def test_issue18_budget_stage_trains_on_many_views_from_a_base_with_other_budget_fields(runs, tmp_path):
    """The budget stage with issue 18's fields (multi-view samples, importance head, coverage
    input, density target, log-uniform κ) starts from the base checkpoint written with the
    defaults: only the base network has to match; its importance head trains."""
    out = tmp_path / "b18"
    sets = ["budget_views=4", "selection='stratified'", "importance_head=True", "coverage_input=True",
            "target='density'", "kappa_schedule='log_uniform'", "kappa_min=0.02", "fill_cap_px=8.0",
            "budget_colour=True"]
    assert train(["--stage", "budget", "--init", str(runs / "base" / "checkpoint.pt"), "--preset", "tiny", "--threads", "1",
                  "--steps", "2", "--eval-scenes", "0", "--out", str(out)] + [a for s in sets for a in ("--set", s)]) == 0
    ck = torch.load(out / "checkpoint.pt", weights_only=True)
    base = torch.load(runs / "base" / "checkpoint.pt", weights_only=True)["model"]
    assert not torch.equal(ck["model"]["budget.importance.2.weight"], base["heads.opacity.2.weight"])
    assert "budget.cover.weight" in ck["model"] and "budget.colour.2.weight" in ck["model"]
    logs = [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines()]
    assert all(0.02 <= r["kappa"] <= 0.95 for r in logs)
    # another base network is still refused by name
    assert train(["--stage", "budget", "--init", str(runs / "base" / "checkpoint.pt"), "--preset", "tiny", "--threads", "1",
                  "--set", "head_channels=8", "--steps", "1", "--out", str(tmp_path / "bad")]) == 2


def test_budget_stage_with_kappa_in_the_decoder_trains_and_evaluates(runs, tmp_path):
    """``kappa_decoder``: the budget stage trains copies of the decoder's last stages (and their κ
    FiLM) while the base decoder stays frozen; the evaluation rebuilds the copies from the
    checkpoint's preset and keeps exact counts, with κ = 1 the base model for the naive rows and
    the finetuned parameters unpruned for the others."""
    out = tmp_path / "kd"
    assert train(["--stage", "budget", "--init", str(runs / "base" / "checkpoint.pt"), "--preset", "tiny", "--threads", "1",
                  "--steps", "2", "--eval-scenes", "0", "--set", "kappa_decoder=2", "--set", "budget_views=4",
                  "--set", "selection='stratified'", "--set", "importance_head=True", "--out", str(out)]) == 0
    ck = torch.load(out / "checkpoint.pt", weights_only=True)["model"]
    base = torch.load(runs / "base" / "checkpoint.pt", weights_only=True)["model"]
    for k, v in base.items():
        assert torch.equal(v, ck[k]), k
    assert any(not torch.equal(ck[k], base[k.replace("budget.decoder.stages.0.", "decoder.up2.")])
               for k in ck if k.startswith("budget.decoder.stages.0."))
    assert "budget.decoder.film.1.net.2.weight" in ck and "budget.decoder.stages.1.0.weight" in ck
    assert evaluate(["--checkpoint", str(out / "checkpoint.pt"), "--budgets", "1,0.1", "--num-scenes", "1",
                     "--repeats", "1", "--views", "4", "--out", str(tmp_path / "ev")]) == 0
    rows = json.loads((tmp_path / "ev" / "budget.json").read_text())
    assert all(r["n_gaussians"] == round(r["budget"] * 4 * 32 * 48) for r in rows)
    for params in ("base", "finetuned"):  # κ = 1: the base model, or the finetuned parameters unpruned
        assert len({r["psnr"] for r in rows if r["budget"] == 1.0 and r["parameters"] == params}) == 1


def test_base_stage_resumes_bitwise(runs, tmp_path, monkeypatch):
    """A run interrupted after its step-1 checkpoint and resumed ends where the uninterrupted one did."""
    from clsplat.models.pgt import training
    real = training.make_sample_loss

    def interrupted(*args, **kwargs):
        fn = real(*args, **kwargs)

        def sample_loss(model, step, index):
            if step == 1:
                raise KeyboardInterrupt("simulated interruption")
            return fn(model, step, index)
        return sample_loss

    out = tmp_path / "resumed"
    monkeypatch.setattr(training, "make_sample_loss", interrupted)
    with pytest.raises(KeyboardInterrupt):
        train(["--preset", "tiny", "--threads", "1", "--steps", "2", "--checkpoint-every", "1", "--out", str(out)])
    monkeypatch.setattr(training, "make_sample_loss", real)
    # the unfinished run stays staged; the folder gets its outputs only when a run completes
    assert torch.load(out / ".staging" / "checkpoint.pt", weights_only=True)["step"] == 1
    assert not (out / "checkpoint.pt").exists()
    assert train(["--preset", "tiny", "--threads", "1", "--steps", "2", "--out", str(out), "--resume"]) == 0
    a = torch.load(out / "checkpoint.pt", weights_only=True)["model"]
    b = torch.load(runs / "base" / "checkpoint.pt", weights_only=True)["model"]
    assert all(torch.equal(a[k], b[k]) for k in b)


NAIVE = ("random", "opacity", "grid", "dedup")
ON_FINETUNED = tuple(f"{m}@finetuned" for m in NAIVE)


@pytest.mark.parametrize("views", [8, 2])
def test_eval_writes_the_budget_curve(runs, views):
    """Every method at every κ, with issue 33's controls: each naive selection also on the
    finetuned parameters (finite PSNR, exact counts); at κ = 1 the naive rows are the base model
    and the finetuned model's own κ = 1 (its parameters unpruned) equals every naive selection
    on those parameters, which keeps every pixel there."""
    out = runs / f"eval{views}"
    assert evaluate(["--checkpoint", str(runs / "budget" / "checkpoint.pt"), "--budgets", "1,0.2,0.05",
                     "--num-scenes", "1", "--repeats", "1", "--views", str(views), "--out", str(out)]) == 0
    rows = json.loads((out / "budget.json").read_text())
    assert {(r["method"], r["budget"]) for r in rows} == {
        (m, k) for m in ("finetuned",) + NAIVE + ON_FINETUNED for k in (1.0, 0.2, 0.05)}
    P = views * 32 * 48
    for r in rows:
        assert set(r) == {"method", "selection", "parameters", "budget", "views", "n_gaussians", "psnr",
                          "psnr_covered", "ssim", "render_ms", "psnr_per_sample"}
        assert r["psnr_per_sample"] == [r["psnr"]]   # one sample: its own PSNR is the mean
        assert r["views"] == views
        assert r["n_gaussians"] == round(r["budget"] * P)  # exact: every method, every sample
        assert r["render_ms"] > 0 and 0 < r["psnr"] < 60 and -1 <= r["ssim"] <= 1 and 0 < r["psnr_covered"] < 60
        assert r["parameters"] == ("finetuned" if r["method"] == "finetuned" or "@" in r["method"] else "base")
        assert r["selection"] == ("learned" if r["method"] == "finetuned" else r["method"].split("@")[0])
    row = {(r["method"], r["budget"]): r for r in rows}
    base_full = {(r["psnr"], r["n_gaussians"]) for r in rows if r["budget"] == 1.0 and r["parameters"] == "base"}
    assert len(base_full) == 1  # κ = 1 is the base model for the naive rows
    for m in ON_FINETUNED:      # the selections at κ = 1 on the finetuned parameters: the finetuned model
        assert row[(m, 1.0)]["psnr"] == row[("finetuned", 1.0)]["psnr"]
        assert row[(m, 1.0)]["ssim"] == row[("finetuned", 1.0)]["ssim"]
    # the budget stage trained: its unpruned parameters are not the base model's
    assert row[("finetuned", 1.0)]["psnr"] != row[("random", 1.0)]["psnr"]
    # opacity@finetuned ranks by the finetuned opacity: here (no importance head) the learned selection
    for k in (0.2, 0.05):
        assert row[("opacity@finetuned", k)]["psnr"] == row[("finetuned", k)]["psnr"]
    m = json.loads((out / "metrics.json").read_text())
    assert m["protocol"]["split"] == "test"
    assert {"abs_rel", "delta1"} <= set(m["all"]) and {"abs_rel", "delta1"} <= set(m["depth_without_residual"])
    assert m["seconds_per_prediction"] > 0 and m["family"] == "pgt" and m["step"] >= 1
    assert (out / "budget.png").stat().st_size > 1000 and (out / "contact_sheet.png").is_file()


def test_eval_on_the_validation_streets(runs):
    """``--eval-split val``: other streets than the test split's (disjoint seeds), recorded in
    the protocol; the same rows."""
    out = runs / "eval-val"
    assert evaluate(["--checkpoint", str(runs / "budget" / "checkpoint.pt"), "--budgets", "1,0.2", "--views", "4",
                     "--num-scenes", "1", "--repeats", "1", "--eval-split", "val", "--out", str(out)]) == 0
    test = runs / "eval-test4"
    assert evaluate(["--checkpoint", str(runs / "budget" / "checkpoint.pt"), "--budgets", "1,0.2", "--views", "4",
                     "--num-scenes", "1", "--repeats", "1", "--out", str(test)]) == 0
    v, t = (json.loads((d / "metrics.json").read_text()) for d in (out, test))
    assert v["protocol"]["split"] == "val" and t["protocol"]["split"] == "test"
    assert v["all"]["psnr"] != t["all"]["psnr"]
    rows = json.loads((out / "budget.json").read_text())
    assert {r["method"] for r in rows} == {"finetuned", *NAIVE, *ON_FINETUNED}
    assert all(0 < r["psnr"] < 60 for r in rows)


def test_eval_of_a_base_checkpoint_has_only_the_baselines(runs):
    out = runs / "eval-base"
    assert evaluate(["--checkpoint", str(runs / "base" / "checkpoint.pt"), "--budgets", "0.5",
                     "--num-scenes", "1", "--repeats", "1", "--out", str(out)]) == 0
    assert {r["method"] for r in json.loads((out / "budget.json").read_text())} == {"random", "opacity", "grid",
                                                                                   "dedup"}


def test_bad_arguments_are_clear_errors(runs, tmp_path, capsys):
    for text in ("0", "1.5", "0.5,-1", "a,b", ""):
        with pytest.raises(ValueError, match="--budgets"):
            parse_budgets(text)
    assert evaluate(["--checkpoint", str(runs / "base" / "checkpoint.pt"), "--budgets", "2",
                     "--out", str(tmp_path / "e")]) == 2
    assert "--budgets" in capsys.readouterr().err
    for views in ("1", "25"):
        assert evaluate(["--checkpoint", str(runs / "base" / "checkpoint.pt"), "--views", views,
                         "--out", str(tmp_path / "e")]) == 2
        assert "--views" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        evaluate(["--checkpoint", str(runs / "base" / "checkpoint.pt"), "--eval-split", "train",
                  "--out", str(tmp_path / "e")])
    assert "--eval-split" in capsys.readouterr().err
    assert train(["--stage", "budget", "--preset", "tiny", "--steps", "1", "--out", str(tmp_path / "b")]) == 2
    assert "--init" in capsys.readouterr().err
    assert train(["--stage", "budget", "--init", str(tmp_path / "missing.pt"), "--preset", "tiny", "--steps", "1",
                  "--out", str(tmp_path / "b")]) == 2
    assert "does not exist" in capsys.readouterr().err
    assert train(["--preset", "huge", "--steps", "1", "--out", str(tmp_path / "c")]) == 2
    assert "unknown preset 'huge'" in capsys.readouterr().err
    assert evaluate(["--checkpoint", str(tmp_path / "missing.pt"), "--out", str(tmp_path / "e")]) == 2


def test_eval_on_a_full_disk_is_one_line_and_keeps_the_earlier_evaluation(runs, tmp_path, full_disk_on, capsys):
    """The budget plot (the group's last file) hits a full disk: one line naming the file, and the
    earlier evaluation's four files stay as they were (not a new metrics.json beside old plots)."""
    import re

    from clsplat.cli import console

    out = tmp_path / "eval"
    args = ["eval", "pgt", "--checkpoint", str(runs / "base" / "checkpoint.pt"), "--budgets", "0.5",
            "--num-scenes", "1", "--repeats", "1", "--out", str(out)]
    assert console(args) == 0
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    assert set(before) == {"budget.json", "budget.png", "contact_sheet.png", "metrics.json"}
    full_disk_on("budget")
    capsys.readouterr()
    assert console(args + ["--seed", "1"]) == 1
    err = capsys.readouterr().err.strip()
    assert re.fullmatch(rf"clsplat eval pgt: writing '{re.escape(str(out))}/\.staging-[^/]+/budget\.png' failed "
                        r"\(No space left on device\); no partial file is left", err), err
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before


def test_view_serves_the_run_and_leaves_it_unchanged(runs, tmp_path, capsys):
    """``--view`` (no browser connected): the viewer starts at the first step, showing the model run
    on a held-out sample, and the run's weights are bitwise those of the same run unwatched."""
    pytest.importorskip("viser", reason="the view extra is not installed")
    out = tmp_path / "viewed"
    assert train(["--stage", "base", "--preset", "tiny", "--threads", "1", "--steps", "2", "--out", str(out), "--view",
                  "--view-port", "0"]) == 0
    assert "clsplat train --view: watch the run at http://127.0.0.1:" in capsys.readouterr().out
    a = torch.load(out / "checkpoint.pt", weights_only=True)["model"]
    b = torch.load(runs / "base" / "checkpoint.pt", weights_only=True)["model"]
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in b)
