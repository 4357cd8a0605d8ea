"""models/common/runfolder.py with the shared training loop, under faults, in real child processes:
a run killed (SIGKILL) while it writes a checkpoint, or stopped by a file-size limit, leaves the
previous checkpoint loadable and ``--resume`` continues bitwise; a second run on the same folder
is refused naming the lock; a run's outputs replace the previous run's as a group."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest
import torch

from clsplat.models.common.runfolder import MANIFEST, STAGING, RunFolder, RunFolderBusy
from clsplat.models.common.train import load_checkpoint

# A tiny family driven through RunFolder + the shared loop, exactly as the train commands do.
# argv: OUT STEPS [--resume] [--hang-at K] [--fsize-at K]
#   --hang-at K   the K-th checkpoint write stops half-way (after writing half the bytes of the
#                 temporary file), touches OUT.ready and sleeps: the parent kills it there
#   --fsize-at K  before the K-th checkpoint write, RLIMIT_FSIZE drops below the checkpoint size
CHILD = textwrap.dedent('''
    import argparse, os, resource, sys, time
    from dataclasses import dataclass
    from pathlib import Path
    import torch
    from clsplat.models.common import train as T
    from clsplat.models.common.presets import Preset
    from clsplat.models.common.runfolder import RunFolder

    @dataclass(frozen=True)
    class ToyPreset(Preset):
        name: str = "toy"

    ap = argparse.ArgumentParser()
    ap.add_argument("out"); ap.add_argument("steps", type=int); ap.add_argument("--resume", action="store_true")
    ap.add_argument("--hang-at", type=int, default=0); ap.add_argument("--fsize-at", type=int, default=0)
    a = ap.parse_args()
    calls = [0]
    real = T._write_bytes

    def write(path, data):
        calls[0] += 1
        if calls[0] == a.hang_at:
            with open(path, "wb") as fh:
                fh.write(bytes(data)[: len(data) // 2])
                fh.flush()
            Path(a.out + ".ready").touch()
            time.sleep(600)
        if calls[0] == a.fsize_at:
            resource.setrlimit(resource.RLIMIT_FSIZE, (len(data) // 2, resource.RLIM_INFINITY))
        return real(path, data)
    T._write_bytes = write

    def sample_loss(model, step, index):
        g = T.sample_generator(3, index)
        x = torch.randn(8, 4, generator=g, dtype=torch.float64)
        loss = ((model(x) - x.sum(-1, keepdim=True).sin()) ** 2).mean() + 1e-3 * torch.rand(()).double()
        return {"loss": loss}

    torch.manual_seed(0)
    model = torch.nn.Sequential(torch.nn.Linear(4, 16), torch.nn.Tanh(), torch.nn.Linear(16, 1)).double()
    opt = torch.optim.Adam(model.parameters(), lr=1e-2)
    try:
        with RunFolder(a.out, resume=a.resume) as rf:
            spec = T.TrainSpec(out_dir=rf.stage, steps=a.steps, batch_size=2, checkpoint_every=1,
                               resume=a.resume, progress=False)
            T.train(model, opt, spec, ToyPreset(), "toy", sample_loss)
            T.atomic_write(rf.stage / "metrics.json", lambda p: p.write_text('{"steps": %d}' % a.steps))
            rf.publish()
    except (OSError, ValueError) as e:  # what clsplat.cli.main does
        print(f"toy: {e}", file=sys.stderr)
        sys.exit(1 if isinstance(e, OSError) else 2)
''')


@pytest.fixture(scope="module")
def child(tmp_path_factory) -> Path:
    p = tmp_path_factory.mktemp("child") / "toy_run.py"
    p.write_text(CHILD)
    return p


def run(child: Path, out: Path, steps: int, *extra: str, **kw) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(child), str(out), str(steps), *extra], capture_output=True,
                          text=True, timeout=120, **kw)


def ck_state(path: Path) -> dict:
    ck = torch.load(path, weights_only=True)
    return {"step": ck["step"], **{f"model.{k}": v for k, v in ck["model"].items()}}


def assert_same_run(a: Path, b: Path) -> None:
    sa, sb = ck_state(a / "checkpoint.pt"), ck_state(b / "checkpoint.pt")
    assert sa.keys() == sb.keys()
    for k in sa:
        assert torch.equal(torch.as_tensor(sa[k]), torch.as_tensor(sb[k])), k  # bitwise
    strip = lambda d: [{k: v for k, v in json.loads(x).items() if k not in ("time_s", "backward_s")}  # noqa: E731
                       for x in (d / "log.jsonl").read_text().splitlines()]
    assert strip(a) == strip(b)


@pytest.fixture(scope="module")
def straight(child, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("straight") / "run"
    r = run(child, out, 6)
    assert r.returncode == 0, r.stderr
    return out


@pytest.mark.slow   # kill-and-resume children
def test_sigkill_during_a_checkpoint_write_then_resume_is_bitwise(child, straight, tmp_path):
    out = tmp_path / "run"
    assert run(child, out, 2).returncode == 0  # an earlier, finished run in the same folder
    before = {p.name: p.read_bytes() for p in out.iterdir() if p.is_file() and p.name != ".lock"}
    proc = subprocess.Popen([sys.executable, str(child), str(out), "6", "--hang-at", "4"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    ready = Path(str(out) + ".ready")
    t0 = time.monotonic()
    while not ready.exists():
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() - t0 < 60
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)  # half of the step-4 checkpoint is on disk
    proc.wait()
    stage = out / STAGING
    assert any(p.name.startswith(".checkpoint.tmp") for p in stage.iterdir())  # the torn write
    assert load_checkpoint(stage / "checkpoint.pt")["step"] == 3  # the previous checkpoint is whole
    # the earlier finished run is untouched, file by file
    assert {p.name: p.read_bytes() for p in out.iterdir() if p.is_file() and p.name != ".lock"} == before
    r = run(child, out, 6, "--resume")  # the kernel released the dead run's lock
    assert r.returncode == 0, r.stderr
    assert "resuming the unfinished run staged" in r.stdout
    assert_same_run(out, straight)
    assert not stage.exists() and json.loads((out / "metrics.json").read_text()) == {"steps": 6}
    assert sorted(json.loads((out / MANIFEST).read_text())["files"]) == ["checkpoint.pt", "log.jsonl", "loss.png",
                                                                        "metrics.json"]


@pytest.mark.slow   # kill-and-resume children
def test_a_file_size_limit_stops_the_run_with_one_line_and_resume_is_bitwise(child, straight, tmp_path):
    out = tmp_path / "run"
    r = run(child, out, 6, "--fsize-at", "4")
    assert r.returncode == 1
    line = r.stderr.strip()
    assert "\n" not in line and "Traceback" not in r.stderr
    assert "checkpoint.pt" in line and "File too large" in line and "previous checkpoint.pt is unchanged" in line
    assert load_checkpoint(out / STAGING / "checkpoint.pt")["step"] == 3
    assert not (out / "checkpoint.pt").exists()  # nothing half-done was published
    r = run(child, out, 6, "--resume")
    assert r.returncode == 0, r.stderr
    assert_same_run(out, straight)


@pytest.mark.slow   # kill-and-resume children
def test_resume_of_a_finished_run_extends_it_bitwise_and_publishes_as_a_group(child, straight, tmp_path):
    out = tmp_path / "run"
    assert run(child, out, 3).returncode == 0
    r = run(child, out, 6, "--resume")
    assert r.returncode == 0, r.stderr
    assert_same_run(out, straight)


@pytest.mark.slow   # kill-and-resume children
def test_a_second_run_on_the_same_folder_is_refused_naming_the_lock(child, tmp_path):
    out = tmp_path / "run"
    first = subprocess.Popen([sys.executable, str(child), str(out), "6", "--hang-at", "2"],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        t0 = time.monotonic()
        while not Path(str(out) + ".ready").exists():
            assert first.poll() is None and time.monotonic() - t0 < 60
            time.sleep(0.05)
        r = run(child, out, 6)
        assert r.returncode == 2
        assert f"is in use by another run (process {first.pid} holds the lock '{out / '.lock'}')" in r.stderr
        with pytest.raises(RunFolderBusy, match=r"--out: .* in use by another run .*\.lock"):
            RunFolder(out).__enter__()
        assert load_checkpoint(out / STAGING / "checkpoint.pt")["step"] == 1  # the first run's files, intact
    finally:
        first.kill()
        first.wait()
    with RunFolder(out, resume=True) as rf:  # free again once the holder is gone
        assert rf.stage.is_dir()


def test_a_new_run_replaces_the_previous_runs_files_as_a_group(tmp_path):
    out = tmp_path / "run"
    out.mkdir()
    for name in ("checkpoint.pt", "log.jsonl", "metrics.json", "contact_sheet.png"):  # a run from before manifests
        (out / name).write_text("old " + name)
    (out / "notes.txt").write_text("the user's own file")
    with RunFolder(out) as rf:
        (rf.stage / "checkpoint.pt").write_text("new")
        (rf.stage / "log.jsonl").write_text("new")
        (rf.stage / ".checkpoint.tmp99.pt").write_text("torn")
        assert (out / "metrics.json").read_text() == "old metrics.json"  # untouched until publication
        rf.publish()
    names = sorted(p.name for p in out.iterdir())
    assert names == [".lock", MANIFEST, "checkpoint.pt", "log.jsonl", "notes.txt"]
    assert (out / "checkpoint.pt").read_text() == "new"
    with RunFolder(out) as rf:  # the next run removes exactly what the manifest lists
        (rf.stage / "metrics.json").write_text("newer")
        rf.publish()
    assert sorted(p.name for p in out.iterdir()) == [".lock", MANIFEST, "metrics.json", "notes.txt"]


def test_a_publication_cut_short_is_finished_by_the_next_run(tmp_path):
    out = tmp_path / "run"
    with RunFolder(out) as rf:
        (rf.stage / "metrics.json").write_text("A")
        rf.publish()
    stage = out / STAGING
    stage.mkdir()
    (stage / "checkpoint.pt").write_text("B")
    (stage / "metrics.json").write_text("B")
    (stage / MANIFEST).write_text(json.dumps({"files": ["checkpoint.pt", "metrics.json"]}))  # committed,
    os.replace(stage / "checkpoint.pt", out / "checkpoint.pt")  # then killed after moving one file
    with RunFolder(out, resume=True) as rf:  # finishes the publication, then resumes the run it published
        assert (rf.stage / "checkpoint.pt").read_text() == "B"
    assert (out / "metrics.json").read_text() == "B" and (out / "checkpoint.pt").read_text() == "B"


def test_resume_without_a_checkpoint_and_a_file_as_out(tmp_path):
    with pytest.raises(ValueError, match=r"^--resume: no checkpoint to resume in"):
        RunFolder(tmp_path / "none", resume=True).__enter__()
    assert not (tmp_path / "none").exists()  # a failed resume creates nothing
    (tmp_path / "f").write_text("x")
    with pytest.raises(ValueError, match=r"^--out: '.*/f' exists and is not a folder"):
        RunFolder(tmp_path / "f").__enter__()
