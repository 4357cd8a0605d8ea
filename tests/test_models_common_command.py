"""models/common/command.py: the one skeleton of ``clsplat train|eval FAMILY``, run on a toy
family (a two-layer network fitted to sin): parse -> preset -> data -> run folder -> loop ->
evaluate -> publish, one error policy (one line, exit 2, nothing published), and the one
checkpoint rebuild (:func:`restore`: the run's ``--set`` changes come back, another family's
checkpoint is refused)."""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import pytest
import torch

from clsplat.models.common import presets
from clsplat.models.common.command import Family, TrainJob, eval_main, restore, train_main


@dataclass(frozen=True)
class ToyPreset(presets.Preset):
    name: str = "small"
    width: int = 8
    steps: int = 4
    lr: float = 1e-2


presets.register("toycmd", ToyPreset())
presets.register("toycmd", ToyPreset(name="tiny", width=4))


class _Data:
    name = "sin"

    def __init__(self, seed: int) -> None:
        g = torch.Generator().manual_seed(seed)
        self.x = torch.randn(64, 4, generator=g)
        self.y = self.x.sin().sum(-1, keepdim=True)


class ToyFamily(Family):
    """Fits y = sum(sin(x)); ``--data bad`` is a user's mistake in the data step."""

    name = "toycmd"
    title = "Toy"
    no_weights = "a toy"

    def __init__(self) -> None:
        self.calls: list[str] = []

    def load_data(self, job: TrainJob):
        self.calls.append("data")
        if job.args.data == "bad":
            raise ValueError("--data: 'bad' is not a data set")
        return _Data(job.args.seed)

    def build(self, job: TrainJob):
        self.calls.append("build")
        return torch.nn.Sequential(torch.nn.Linear(4, job.preset.width), torch.nn.Tanh(),
                                   torch.nn.Linear(job.preset.width, 1))

    def fit(self, job: TrainJob) -> bool:
        from clsplat.models.common.train import TrainSpec, train
        self.calls.append("fit")
        d = job.data

        def sample_loss(model, step, index):
            return {"loss": ((model(d.x) - d.y) ** 2).mean()}

        spec = TrainSpec(out_dir=job.stage, steps=job.args.steps or job.preset.steps, batch_size=1,
                         checkpoint_every=2, seed=job.args.seed, resume=job.args.resume, progress=False)
        opt = torch.optim.Adam(job.model.parameters(), lr=job.preset.lr)
        train(job.model, opt, spec, job.preset, self.name, sample_loss)
        return True

    def evaluate_run(self, job: TrainJob) -> str:
        self.calls.append("evaluate")
        with torch.no_grad():
            mse = float(((job.model(job.data.x) - job.data.y) ** 2).mean())
        (job.stage / "metrics.json").write_text(json.dumps({"mse": mse}))
        return f"mse {mse:.4f}"

    def restore_model(self, ck, preset, path, device=None, **context):
        model = torch.nn.Sequential(torch.nn.Linear(4, preset.width), torch.nn.Tanh(), torch.nn.Linear(preset.width, 1))
        model.load_state_dict(ck["model"])
        return model

    def evaluate_checkpoint(self, restored, args, stage: Path, lpips) -> str:
        d = _Data(args.seed)
        mse = float(((restored.model(d.x) - d.y) ** 2).mean())
        (stage / "metrics.json").write_text(json.dumps({"mse": mse, "width": restored.preset.width}))
        return f"mse {mse:.4f}"


def test_train_runs_the_steps_in_order_and_publishes_the_run(tmp_path, capsys):
    fam = ToyFamily()
    out = tmp_path / "run"
    assert train_main(fam, ["--out", str(out), "--set", "width=6", "--no-progress"]) == 0
    assert fam.calls == ["data", "build", "fit", "evaluate"]
    assert {"checkpoint.pt", "log.jsonl", "metrics.json"} <= {p.name for p in out.iterdir()}
    assert "mse " in capsys.readouterr().out
    # the one rebuild: the run's --set change travels in the checkpoint
    r = restore(fam, out / "checkpoint.pt")
    assert r.preset.width == 6 and r.model[0].out_features == 6 and r.checkpoint["step"] == 4
    # eval through the same skeleton, into a staged group
    ev = tmp_path / "eval"
    assert eval_main(fam, ["--checkpoint", str(out / "checkpoint.pt"), "--out", str(ev)]) == 0
    assert json.loads((ev / "metrics.json").read_text())["width"] == 6


@pytest.mark.parametrize("argv,named", [
    (["--data", "bad"], "--data: 'bad'"),
    (["--preset", "huge"], "unknown preset 'huge'"),
    (["--set", "width=x"], "--set"),
    (["--weights", "w.pth"], "--weights: Toy has no pretrained backbone"),
])
def test_a_users_mistake_is_one_line_and_nothing_is_published(tmp_path, capsys, argv, named):
    fam = ToyFamily()
    out = tmp_path / "run"
    assert train_main(fam, ["--out", str(out), "--no-progress", *argv]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("clsplat train toycmd: ") and named in err and "\n" not in err
    assert "build" not in fam.calls and not (out / "checkpoint.pt").exists()


def test_restore_refuses_another_familys_checkpoint_and_another_preset(tmp_path, capsys):
    fam = ToyFamily()
    out = tmp_path / "run"
    assert train_main(fam, ["--out", str(out), "--preset", "tiny", "--no-progress"]) == 0
    ck = torch.load(out / "checkpoint.pt", weights_only=False)
    ck["family"] = "pgt"
    torch.save(ck, tmp_path / "other.pt")
    with pytest.raises(ValueError, match="not 'toycmd'"):
        restore(fam, tmp_path / "other.pt")
    with pytest.raises(ValueError, match="small"):
        restore(fam, out / "checkpoint.pt", preset_name="small")
    assert eval_main(fam, ["--checkpoint", str(tmp_path / "other.pt"), "--out", str(tmp_path / "e")]) == 2
    assert capsys.readouterr().err.startswith("clsplat eval toycmd: ")


def test_registry_lists_every_family_and_models_common_imports_none():
    """The families are reached through the registry's explicit imports, not through module
    names built from strings (``importlib``) anywhere in the models."""
    import ast

    from clsplat.models import FAMILIES
    from clsplat.models.registry import REGISTRY, family

    assert tuple(REGISTRY) == FAMILIES and all(isinstance(f, Family) and f.name == n for n, f in REGISTRY.items())
    with pytest.raises(ValueError, match="family: unknown model family 'nerf'"):
        family("nerf")
    root = Path(__file__).resolve().parents[1] / "models"
    named = [str(p.relative_to(root)) for p in root.rglob("*.py")
             if any(isinstance(n, (ast.Import, ast.ImportFrom)) and "importlib" in
                    ([a.name for a in n.names] if isinstance(n, ast.Import) else [n.module or ""])
                    for n in ast.walk(ast.parse(p.read_text())))]
    assert named == []


def test_a_worker_rank_ends_with_its_exit_status_and_rank0_returns(monkeypatch):
    """Under torchrun a rank other than 0 ends the process with ``os._exit(status)`` once the
    command is done (no interpreter teardown: a worker's normal exit aborted in a library's
    static destructors under load); rank 0 and a single process return to the caller."""
    from clsplat.models.common import command

    ended = []

    class Ended(Exception):
        pass

    def fake_exit(code):
        ended.append(code)
        raise Ended

    monkeypatch.setattr(command.os, "_exit", fake_exit)
    for world, rank in (("1", "0"), ("2", "0")):
        monkeypatch.setenv("WORLD_SIZE", world)
        monkeypatch.setenv("RANK", rank)
        command._end_worker_rank(0)
    assert ended == []
    monkeypatch.setenv("WORLD_SIZE", "2")
    monkeypatch.setenv("RANK", "1")
    with pytest.raises(Ended):
        command._end_worker_rank(2)
    assert ended == [2]
