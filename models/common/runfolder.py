"""A training run's folder: one run at a time (a lock), outputs replaced as a group (staging).

Every ``clsplat train FAMILY --out DIR`` goes through :class:`RunFolder`:

* **Lock.** ``DIR/.lock`` is held with ``flock`` for the whole run, so a second run started on
  the same ``DIR`` is refused (:class:`RunFolderBusy`, a ValueError naming the lock and the pid
  holding it) instead of interleaving its files with the first. The kernel releases the lock
  when the process ends in any way, SIGKILL included, so a killed run never leaves a stale lock.
* **Staging.** The run writes everything (checkpoint, log, plots, metrics, sheets) into
  ``DIR/.staging/``. The previous run's files in ``DIR`` stay as they were until
  :meth:`RunFolder.publish`, called once the new run is complete, replaces them as a group: the
  old run's files are removed (those its manifest ``DIR/.manifest.json`` lists, or for a folder
  written before manifests, the known run-file names) and the new ones moved in. A run that
  fails (full disk, error, kill) leaves ``DIR`` untouched and its partial files staged.
* **Crash-safe publication.** ``publish`` first writes ``.staging/.manifest.json`` (the commit
  record), then moves files. If the process dies in between, the next :class:`RunFolder` on
  ``DIR`` finds the commit record and finishes the publication before anything else.
* **Resume.** ``resume=True`` continues the staged, unfinished run when there is one (a run that
  was killed or stopped early), else the published run: its ``checkpoint.pt`` and ``log.jsonl``
  are copied into a fresh stage, and the continued run is published as a group like any other.

Under ``torchrun`` only rank 0 touches the folder; the other ranks wait for it at a barrier and
read the stage (the resume checkpoint) from the same path.
"""
from __future__ import annotations

import errno
import fnmatch
import json
import os
import shutil
from pathlib import Path

from clsplat.io.atomic import write_text_atomic

__all__ = ["RunFolder", "RunFolderBusy", "STAGING", "LOCK", "MANIFEST", "RESUME_FILES", "KNOWN_RUN_FILES"]

STAGING = ".staging"
LOCK = ".lock"
MANIFEST = ".manifest.json"
#: what a resumed run needs from the run it continues
RESUME_FILES = ("checkpoint.pt", "log.jsonl", "val_curve.jsonl")
#: output names of the model commands: in a folder written before manifests existed, these
#: are taken to be the previous run's files (and replaced as a group with it)
KNOWN_RUN_FILES = ("checkpoint.pt", "log.jsonl", "loss.png", "metrics.json", "budget.json", "scene.ply",
                   "val_curve.jsonl", "val_curve.png",
                   "contact_sheet.png", "far_side.png",
                   "depth_sheet.png", "lateral_shift_*m.png", "budget_*.png", "*_sheet.png")


class RunFolderBusy(ValueError):
    """Another process holds the run folder's lock."""


def _rank() -> tuple[int, int]:
    world = int(os.environ.get("WORLD_SIZE", "1"))
    return (int(os.environ.get("RANK", "0")), world) if world > 1 else (0, 1)


def _share_outcome(error: str | None) -> str | None:
    """Rank 0's outcome of preparing the folder ('' for success, else the error message), sent to
    every rank (a collective: it is also the barrier the other ranks wait at). Without a process
    group, ``error`` itself."""
    import torch.distributed as dist

    if not (dist.is_available() and dist.is_initialized()):
        return error
    box = [error]
    dist.broadcast_object_list(box, src=0)
    return box[0]


def _remove(p: Path) -> None:
    if p.is_dir() and not p.is_symlink():
        shutil.rmtree(p)
    elif p.exists() or p.is_symlink():
        p.unlink()


class RunFolder:
    """Context manager holding ``out``'s lock and a staging folder for one run (module docstring).

    Args:
        out: the run folder (``--out``); created if missing.
        resume: continue the staged or the published run instead of starting a new one.
        arg: the argument name used in error messages.

    Use::

        with RunFolder(args.out, resume=args.resume) as rf:
            train(..., out_dir=rf.stage)
            evaluate(..., out_dir=rf.stage)
            rf.publish()
    """

    def __init__(self, out: str | Path, resume: bool = False, arg: str = "--out") -> None:
        if not isinstance(out, (str, Path)) or not str(out):
            raise ValueError(f"{arg}: expected a folder path, got {out!r}")
        self.out = Path(out)
        self.stage = self.out / STAGING
        self.resume, self.arg = bool(resume), arg
        self.rank, self.world = _rank()
        self._fd: int | None = None
        self.published = False

    # ------------------------------------------------------------------ lock
    def _lock(self) -> None:
        import fcntl

        path = self.out / LOCK
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as e:
            try:
                holder = os.pread(fd, 64, 0).decode(errors="replace").strip() or "?"
            finally:
                os.close(fd)
            if e.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                raise RunFolderBusy(f"{self.arg}: {str(self.out)!r} is in use by another run (process {holder} "
                                    f"holds the lock {str(path)!r}); wait for it to finish or choose another "
                                    f"{self.arg}") from None
            raise
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        self._fd = fd

    def _unlock(self) -> None:
        if self._fd is not None:
            os.close(self._fd)  # releases the flock
            self._fd = None

    # ------------------------------------------------------------------ enter / exit
    def __enter__(self) -> "RunFolder":
        if self.rank != 0:
            error = _share_outcome(None)  # rank 0 prepares the stage
            if error:
                raise ValueError(error)
            return self
        try:
            self._enter_rank0()
        except BaseException as e:
            _share_outcome(str(e) or type(e).__name__)
            raise
        _share_outcome("")
        return self

    def _enter_rank0(self) -> None:
        if self.out.exists() and not self.out.is_dir():
            raise ValueError(f"{self.arg}: {str(self.out)!r} exists and is not a folder")
        if self.resume and not self.out.is_dir():
            raise ValueError(f"--resume: no checkpoint to resume in {str(self.out)!r} (the folder does not exist)")
        self.out.mkdir(parents=True, exist_ok=True)
        self._lock()
        try:
            if (self.stage / MANIFEST).is_file():
                self._finish_publication()
            self._prepare_stage()
        except BaseException:
            self._unlock()
            raise

    def __exit__(self, *exc) -> None:
        self._unlock()

    def _prepare_stage(self) -> None:
        if not self.resume:
            _remove(self.stage)
            self.stage.mkdir()
            return
        if (self.stage / "checkpoint.pt").is_file():
            print(f"resuming the unfinished run staged in {self.stage}", flush=True)
            return
        if not (self.out / "checkpoint.pt").is_file():
            raise ValueError(f"--resume: no checkpoint to resume in {str(self.out)!r} (neither a finished run's "
                             f"checkpoint.pt nor an unfinished one in {STAGING}/)")
        _remove(self.stage)
        self.stage.mkdir()
        for name in RESUME_FILES:
            if (self.out / name).is_file():
                shutil.copy2(self.out / name, self.stage / name)

    # ------------------------------------------------------------------ publication
    def _previous_files(self) -> list[str]:
        man = self.out / MANIFEST
        if man.is_file():
            try:
                names = json.loads(man.read_text())["files"]
                return [n for n in names if isinstance(n, str) and n and "/" not in n and not n.startswith(".")]
            except (ValueError, KeyError, TypeError):
                pass
        return [p.name for p in self.out.iterdir() if not p.name.startswith(".")
                and any(fnmatch.fnmatch(p.name, pat) for pat in KNOWN_RUN_FILES)]

    def publish(self) -> list[Path]:
        """Replace the previous run's files in ``out`` by the staged ones, as a group; returns the
        published paths. Only rank 0 publishes (other ranks return [])."""
        if self.rank != 0:
            return []
        if self._fd is None:
            raise RuntimeError("RunFolder.publish: the folder is not held (use it as a context manager)")
        for p in self.stage.iterdir():  # temporary files of interrupted atomic writes
            if p.name.startswith(".") and p.name != MANIFEST:
                _remove(p)
        names = sorted(p.name for p in self.stage.iterdir() if not p.name.startswith("."))
        write_text_atomic(self.stage / MANIFEST, json.dumps({"files": names}, indent=1))  # the commit record
        self._finish_publication()
        self.published = True
        return [self.out / n for n in names]

    def _finish_publication(self) -> None:
        """Move the committed stage into ``out`` (idempotent: a crash in here is finished by the next run)."""
        try:
            new = json.loads((self.stage / MANIFEST).read_text())["files"]
        except (OSError, ValueError, KeyError, TypeError):
            _remove(self.stage / MANIFEST)  # a torn commit record: the stage was never committed
            return
        for name in self._previous_files():
            if name not in new:
                _remove(self.out / name)
        for name in new:
            src = self.stage / name
            if src.exists():
                if (self.out / name).is_dir():
                    _remove(self.out / name)
                os.replace(src, self.out / name)
        os.replace(self.stage / MANIFEST, self.out / MANIFEST)
        _remove(self.stage)
