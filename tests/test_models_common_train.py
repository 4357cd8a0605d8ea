"""models/common/train.py: bitwise resume, two-process data parallel == one process, skipped
non-finite steps, divergence error, checkpoint checks, atomic writes, log and plot."""
from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import textwrap
from dataclasses import dataclass
from pathlib import Path

import pytest
import torch

from clsplat.models.common import presets
from clsplat.models.common.train import (JsonlLog, TrainSpec, atomic_write, clip_and_measure, gradient_norm, load_checkpoint,
                                         sample_generator, train)

# The toy family lives in a module the DDP subprocess can import too.
TOY = textwrap.dedent('''
    import math
    from dataclasses import dataclass
    import torch
    from clsplat.models.common.presets import Preset
    from clsplat.models.common.train import TrainSpec, sample_generator, train

    @dataclass(frozen=True)
    class ToyPreset(Preset):
        name: str = "toy"
        width: int = 8

    class Toy(torch.nn.Module):
        def __init__(self, width):
            super().__init__()
            self.net = torch.nn.Sequential(torch.nn.Linear(4, width), torch.nn.Tanh(), torch.nn.Linear(width, 1))
            self.unused = torch.nn.Linear(2, 2)  # never gets a gradient: must stay untouched

        def forward(self, x):
            return self.net(x)

    def sample_loss(model, step, index, nan_at=()):
        g = sample_generator(7, index)
        x = torch.randn(16, 4, generator=g, dtype=torch.float64)
        y = x.sin().sum(-1, keepdim=True)
        mse = ((model(x) - y) ** 2).mean()
        if index in nan_at:
            mse = mse * math.nan
        # dropout-like use of the global RNG, so resume must restore it
        noise = 1e-3 * torch.rand(()).double()
        return {"loss": mse + noise, "mse": mse}

    def run(out, steps, resume=False, batch=2, nan_at=(), every=3):
        torch.manual_seed(0)
        model = Toy(8).double()
        opt = torch.optim.Adam(model.parameters(), lr=1e-2)
        sched = torch.optim.lr_scheduler.StepLR(opt, 2, 0.5)
        spec = TrainSpec(out_dir=out, steps=steps, batch_size=batch, checkpoint_every=every, resume=resume,
                         progress=False)
        res = train(model, opt, spec, ToyPreset(), "toy", lambda m, s, i: sample_loss(m, s, i, nan_at), sched)
        return model, res
''')


@pytest.fixture(scope="module")
def toy(tmp_path_factory):
    d = tmp_path_factory.mktemp("toy")
    (d / "toy_family.py").write_text(TOY)
    sys.path.insert(0, str(d))
    import toy_family
    yield toy_family, d
    sys.path.remove(str(d))


def params(model):
    return {k: v.clone() for k, v in model.state_dict().items()}


def test_resume_is_bitwise(toy, tmp_path):
    t, _ = toy
    full, _ = t.run(tmp_path / "a", 7)
    t.run(tmp_path / "b", 4, every=2)  # "interrupted" after step 4 (checkpoint at 4)
    # the interrupted run wrote log lines past its checkpoint? simulate a torn extra line
    with open(tmp_path / "b" / "log.jsonl", "a") as fh:
        fh.write('{"step": 5, "loss": 1.0}\n{"st')
    resumed, res = t.run(tmp_path / "b", 7, resume=True)
    assert res["resumed_from"] == 4
    for k, v in params(full).items():
        assert torch.equal(v, resumed.state_dict()[k]), k
    la = [json.loads(x) for x in (tmp_path / "a" / "log.jsonl").read_text().splitlines()]
    lb = [json.loads(x) for x in (tmp_path / "b" / "log.jsonl").read_text().splitlines()]
    assert [r["step"] for r in lb] == list(range(1, 8))
    assert [r["loss"] for r in la] == [r["loss"] for r in lb]
    assert (tmp_path / "b" / "loss.png").stat().st_size > 1000


@pytest.mark.slow   # torchrun: two processes
def test_two_process_data_parallel_equals_one_process(toy, tmp_path):
    t, d = toy
    one, _ = t.run(tmp_path / "one", 4, batch=4)
    script = tmp_path / "ddp.py"
    script.write_text(textwrap.dedent(f'''
        import sys, torch
        sys.path.insert(0, {str(d)!r})
        torch.set_num_threads(1)
        import toy_family
        model, _ = toy_family.run({str(tmp_path / "two")!r}, 4, batch=4)
        import torch.distributed as dist
        if dist.get_rank() == 0:
            torch.save(model.state_dict(), {str(tmp_path / "two.pt")!r})
        dist.destroy_process_group()
    '''))
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    with socket.socket() as s:  # a free port for the rendezvous
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    r = subprocess.run([sys.executable, "-m", "torch.distributed.run", "--nproc_per_node", "2", "--master_port", str(port),
                        str(script)], capture_output=True, text=True, timeout=300, env=env)
    assert r.returncode == 0, r.stderr[-3000:]
    two = torch.load(tmp_path / "two.pt")
    for k, v in one.state_dict().items():
        assert torch.allclose(v, two[k], rtol=1e-12, atol=1e-14), k
    assert torch.equal(one.state_dict()["unused.weight"], two["unused.weight"])


def test_non_finite_steps_are_skipped_and_divergence_is_an_error(toy, tmp_path):
    t, _ = toy
    model, res = t.run(tmp_path / "nan", 3, batch=1, nan_at=(1,))
    assert res["skipped"] == 1
    recs = [json.loads(x) for x in (tmp_path / "nan" / "log.jsonl").read_text().splitlines()]
    assert recs[1].get("skipped") is True and "skipped" not in recs[0]
    assert all(torch.isfinite(v).all() for v in model.state_dict().values())
    with pytest.raises(RuntimeError, match=r"diverged: 20 consecutive.*\['loss', 'mse'\]"):
        t.run(tmp_path / "div", 30, batch=1, nan_at=tuple(range(30)))


def test_checkpoint_errors_name_the_file(toy, tmp_path):
    t, _ = toy
    t.run(tmp_path / "c", 2)
    ck = tmp_path / "c" / "checkpoint.pt"
    with pytest.raises(ValueError, match="is a 'toy' checkpoint, not 'pgt'"):
        load_checkpoint(ck, family="pgt")
    with pytest.raises(ValueError, match="preset 'toy'.*width: 8 != 16"):
        load_checkpoint(ck, family="toy", preset=t.ToyPreset(width=16))
    bad = tmp_path / "bad.pt"
    bad.write_bytes(ck.read_bytes()[:200])
    with pytest.raises(ValueError, match="bad.pt.*corrupt, truncated"):
        load_checkpoint(bad)
    with pytest.raises(ValueError, match="does not exist"):
        load_checkpoint(tmp_path / "none.pt")
    torch.save({"weights": torch.zeros(1)}, tmp_path / "other.pt")
    with pytest.raises(ValueError, match="not a clsplat model checkpoint"):
        load_checkpoint(tmp_path / "other.pt")
    with pytest.raises(ValueError, match="steps: the checkpoint is at step 2"):
        t.run(tmp_path / "c", 1, resume=True)
    model = t.Toy(8).double()
    two_groups = torch.optim.Adam([{"params": model.net.parameters()}, {"params": model.unused.parameters()}])
    spec = TrainSpec(out_dir=tmp_path / "c", steps=3, resume=True, progress=False)
    with pytest.raises(ValueError, match="resume: .*checkpoint.pt does not fit this model or optimiser"):
        train(model, two_groups, spec, t.ToyPreset(), "toy", lambda m, s, i: t.sample_loss(m, s, i))


def test_atomic_write_keeps_the_old_file_when_writing_fails(tmp_path):
    p = tmp_path / "metrics.json"
    p.write_text("old")

    def full_disk(tmp: Path):
        tmp.write_text("partial")
        raise OSError(28, "No space left on device")

    with pytest.raises(OSError, match="metrics.json.* failed .No space left on device.; the previous metrics.json is unchanged"):
        atomic_write(p, full_disk)
    assert p.read_text() == "old" and sorted(x.name for x in tmp_path.iterdir()) == ["metrics.json"]


def test_presets_registry_and_description():
    @dataclass(frozen=True)
    class P(presets.Preset):
        name: str
        size: int = 3

    p = P("x")
    assert "size = 3" in p.describe() and p.to_dict() == {"name": "x", "size": 3}
    with pytest.raises(ValueError, match="unknown fields"):
        p.replace(colour=1)
    with pytest.raises(ValueError, match="family: unknown model family 'toy2'"):
        presets.get_preset("toy2", "x")


def test_checkpoint_from_before_a_new_preset_field_loads_while_the_field_keeps_its_default():
    @dataclass(frozen=True)
    class P(presets.Preset):
        name: str
        size: int = 3
        added_later: float | None = None

    old = {"name": "x", "size": 3}
    presets.check_preset_matches(old, P("x"), "old.pt")
    with pytest.raises(ValueError, match="old.pt.*added_later: None != 0.5"):
        presets.check_preset_matches(old, P("x", added_later=0.5), "old.pt")
    with pytest.raises(ValueError, match="preset 'x' differs from the one asked for .*size: 3 != 4"):
        presets.check_preset_matches(old, P("x", size=4), "old.pt")


def test_sample_generator_depends_only_on_seed_and_index():
    a = torch.rand(3, generator=sample_generator(1, 5))
    torch.rand(10)
    assert torch.equal(a, torch.rand(3, generator=sample_generator(1, 5)))
    assert not torch.equal(a, torch.rand(3, generator=sample_generator(1, 6)))


def test_log_keeps_lines_up_to_the_resumed_step(tmp_path):
    p = tmp_path / "log.jsonl"
    p.write_text("".join(json.dumps({"step": s}) + "\n" for s in range(1, 6)))
    log = JsonlLog(p, resume_step=3)
    log.write({"step": 4, "loss": 0.5})
    assert [json.loads(x)["step"] for x in p.read_text().splitlines()] == [1, 2, 3, 4]


def test_gradient_norm_is_measured_without_touching_unclipped_gradients():
    """Finite gradients whose norm overflows float32: logged as inf, left as they are without a
    clip (a clip to inf would have made them NaN), scaled to zero with one."""
    p = torch.nn.Parameter(torch.zeros(3))
    p.grad = torch.tensor([1e20, 1e20, 1.0])
    assert clip_and_measure([p], None) == float("inf")
    assert torch.equal(p.grad, torch.tensor([1e20, 1e20, 1.0]))
    q = torch.nn.Parameter(torch.zeros(2))
    q.grad = torch.tensor([3.0, 4.0])
    assert clip_and_measure([q], 1.0) == 5.0 and torch.allclose(q.grad.norm(), torch.tensor(1.0))
    assert clip_and_measure([torch.nn.Parameter(torch.zeros(1))], None) == 0.0


def test_gradient_norm_tells_non_finite_gradients_from_an_overflowing_norm_and_clips_as_torch_does():
    """One pass measures the norm and, when it is finite, vouches for every gradient; a NaN or an
    inf gradient is found, while finite gradients whose norm overflows still count as finite. The
    clip with the measured norm is ``clip_grad_norm_``'s, bit for bit."""
    def params(*grads):
        out = []
        for g in grads:
            q = torch.nn.Parameter(torch.zeros_like(g))
            q.grad = g.clone()
            out.append(q)
        return out
    gen = torch.Generator().manual_seed(0)
    ps = params(torch.randn(1000, generator=gen), torch.randn(7, 3, generator=gen))
    total, ok = gradient_norm(ps)
    assert ok and float(total) == float(torch.nn.utils.get_total_norm([q.grad for q in ps]))
    twins = params(*[q.grad for q in ps])
    assert clip_and_measure(ps, 0.5, total) == float(torch.nn.utils.clip_grad_norm_(twins, 0.5))
    assert all(torch.equal(a.grad, b.grad) for a, b in zip(ps, twins))
    for bad in (float("nan"), float("inf")):
        g = torch.ones(5)
        g[2] = bad
        assert gradient_norm(params(torch.ones(3), g))[1] is False
    total, ok = gradient_norm(params(torch.tensor([1e20, 1e20, 1.0])))
    assert ok and float(total) == float("inf")
    total, ok = gradient_norm([torch.nn.Parameter(torch.zeros(2))])     # no gradient at all
    assert ok and float(total) == 0.0


def test_a_log_line_that_cannot_be_written_names_the_log(tmp_path, monkeypatch):
    import builtins
    import errno

    log = JsonlLog(tmp_path / "log.jsonl")
    log.write({"step": 1})
    real_open = builtins.open

    class Full:
        def __init__(self, *a, **k):
            self.fh = real_open(*a, **k)

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self.fh.close()

        def write(self, text):
            raise OSError(errno.ENOSPC, "No space left on device")
    monkeypatch.setattr(builtins, "open", Full)
    with pytest.raises(OSError, match=r"writing '.*log\.jsonl' failed \(No space left on device\)"):
        log.write({"step": 2})
    monkeypatch.undo()
    assert [json.loads(x) for x in (tmp_path / "log.jsonl").read_text().splitlines()] == [{"step": 1}]


class _RunsCode:
    """Unpickling this runs ``os.system``."""

    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return os.system, (f"touch {self.marker}",)


def test_checkpoints_and_weight_files_never_run_code(tmp_path):
    """Checkpoints (--resume, --init, eval --checkpoint), backbone weights (--weights) and LPIPS
    weights are read with torch.load(weights_only=True): a file carrying a pickle payload is
    refused, naming the file, and the payload does not run."""
    from clsplat.models.common.backbones import ResNet18, load_backbone_weights
    from clsplat.models.common.metrics import LPIPS

    marker = tmp_path / "ran"
    bad = tmp_path / "bad.pt"
    torch.save({"format": 1, "family": "toy", "model": {"w": torch.zeros(1)}, "x": _RunsCode(marker)}, bad)
    with pytest.raises(ValueError, match=r"checkpoint: '.*bad\.pt' cannot be read"):
        load_checkpoint(bad)
    with pytest.raises(ValueError, match=r"bad\.pt"):
        load_backbone_weights(ResNet18(), str(bad))
    with pytest.raises(ValueError, match=r"bad\.pt"):
        LPIPS(str(bad), str(bad))
    assert not marker.exists()


def test_on_step_sees_every_step_and_its_logged_record(toy, tmp_path):
    """The hook ``clsplat train FAMILY --view`` hangs on: called once per step, in order, with the
    record the log gets."""
    t, _ = toy
    seen = []
    torch.manual_seed(0)
    model = t.Toy(8).double()
    opt = torch.optim.Adam(model.parameters(), lr=1e-2)
    spec = TrainSpec(out_dir=tmp_path, steps=4, batch_size=2, checkpoint_every=2, progress=False)
    train(model, opt, spec, t.ToyPreset(), "toy", t.sample_loss, on_step=lambda s, r: seen.append((s, dict(r))))
    logged = [json.loads(x) for x in (tmp_path / "log.jsonl").read_text().splitlines()]
    assert [s for s, _ in seen] == [1, 2, 3, 4]
    assert [r["loss"] for _, r in seen] == [r["loss"] for r in logged]


@dataclass(frozen=True)
class _StagedPreset(presets.Preset):
    name: str = "staged"


class _Grower(torch.nn.Module):
    """Two parameter groups: ``a`` (a fixed vector) and ``rows`` (grows by its first rows after step 3)."""

    def __init__(self, n: int) -> None:
        super().__init__()
        self.a = torch.nn.Parameter(torch.linspace(-1, 1, 4, dtype=torch.float64))
        self.rows = torch.nn.Parameter(torch.linspace(0, 1, 2 * n, dtype=torch.float64).reshape(n, 2))


def _staged_run(out, steps, resume=False, every=10):
    """A staged family on the shared loop: odd steps train only group 1 (``rows``), even steps both;
    after step 3 ``rows`` grows by copies of its first 2 rows (fresh Adam moments) through
    :func:`clsplat.strategy.rebuild`; the size travels in the checkpoint."""
    from clsplat.models.common.train import LoopHooks
    from clsplat.strategy import rebuild

    torch.manual_seed(0)  # the loss draws from the global RNG (a resumed run restores it)
    model = _Grower(0 if resume else 3)
    opt = torch.optim.Adam([{"params": [model.a], "lr": 0.05}, {"params": [model.rows], "lr": 0.1}])

    class Hooks(LoopHooks):
        def trainable_groups(self, step):
            return [1] if step % 2 else [0, 1]

        def after_step(self, step, applied):
            if step == 2:
                params = {"rows": model.rows}
                rebuild(params, {"rows": opt}, lambda n, p: torch.cat([p, p[:2]]),
                        lambda k, v: torch.cat([v, v.new_zeros((2,) + v.shape[1:])]))
                model.rows = params["rows"]
            return {"n_rows": len(model.rows)}

        def state(self):
            return {"n_rows": len(model.rows)}

        def load_state(self, extra, path):
            model.rows.data = model.rows.data.new_zeros(extra["n_rows"], 2)

    def sample_loss(m, step, index):
        g = sample_generator(3, index)
        t = torch.randn(len(m.rows), 2, generator=g, dtype=torch.float64)
        return {"loss": ((m.rows - t) ** 2).mean() + (m.a ** 2).sum() * torch.rand(()).double()}

    spec = TrainSpec(out_dir=out, steps=steps, checkpoint_every=every, resume=resume, progress=False)
    train(model, opt, spec, _StagedPreset(), "staged", sample_loss, hooks=Hooks())
    return model, opt


@pytest.mark.parametrize("stop", [2, 3])
def test_staged_hooks_freeze_groups_and_resume_bitwise_across_parameter_surgery(tmp_path, stop):
    """``trainable_groups`` leaves the other groups exactly alone (no Adam step, no moment decay);
    ``after_step`` replaces a parameter and its moments; a run stopped before (2) or right after (3)
    that surgery resumes bitwise; the hooks' log fields are written."""
    full, full_opt = _staged_run(tmp_path / "full", 6)
    recs = [json.loads(x) for x in (tmp_path / "full" / "log.jsonl").read_text().splitlines()]
    assert [r["n_rows"] for r in recs] == [3, 3, 5, 5, 5, 5] and len(full.rows) == 5
    assert full_opt.state[full.a]["step"] == 3  # a trained at steps 0, 2, 4 only
    assert full_opt.state[full.rows]["step"] == 6  # the grown leaf kept the old one's step count
    _staged_run(tmp_path / "part", stop, every=stop)
    resumed, resumed_opt = _staged_run(tmp_path / "part", 6, resume=True)
    assert torch.equal(full.a, resumed.a) and torch.equal(full.rows, resumed.rows)
    for p, q in ((full.a, resumed.a), (full.rows, resumed.rows)):
        for k in ("exp_avg", "exp_avg_sq"):
            assert torch.equal(full_opt.state[p][k], resumed_opt.state[q][k])
