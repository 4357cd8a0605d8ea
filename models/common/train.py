"""The training loop every model family uses, and its parts.

:func:`train` runs ``spec.steps`` optimiser steps. Each step's global batch is the sample indices
``step·B .. step·B + B − 1``; the family's ``sample_loss(model, step, index)`` computes one
sample's loss terms, deriving everything random from ``index`` (see :func:`sample_generator`).
That makes two things exact:

* **resume**: the checkpoint holds the model, optimiser, scheduler, step, every RNG state and
  the family's extra state, so ``resume=True`` continues bitwise as if never interrupted;
* **data parallel**: under ``torchrun`` (``WORLD_SIZE`` > 1; gloo on CPU, NCCL on CUDA) rank r
  takes every world-th sample of the batch, gradients are summed with one all-reduce, and the
  update equals one process accumulating the same B samples.

A family whose training is more than "one optimiser over fixed parameters" says so through a
:class:`LoopHooks` (AutoSplat: stages that train different parameter groups, densification that
replaces parameters and their Adam moments after the optimiser step, set sizes and statistics in
the checkpoint); DrivingForward and PGT pass none.

Data parallelism uses ``torch.distributed`` collectives directly rather than the
``DistributedDataParallel`` wrapper: DDP only synchronises gradients of computations that go
through the wrapper's ``forward``, and the models here call several methods per sample
(reconstruct, render, warp). One flat all-reduce per step does the same job.

Rank 0 writes ``out_dir/log.jsonl`` (one line per step: every loss term averaged over the batch,
the learning rate, seconds), ``out_dir/loss.png`` and ``out_dir/checkpoint.pt`` (atomically, with
:func:`clsplat.io.atomic.atomic_write`: written to a temporary file in the same folder, then
renamed, so an interrupted or failed write never destroys the previous checkpoint; a write
failure is an ``OSError`` naming the file and the cause). The commands run the loop inside a
:class:`~.runfolder.RunFolder`, whose staging folder is ``out_dir``. A step whose loss or gradients are not finite is
skipped (no update) and logged; :data:`MAX_CONSECUTIVE_SKIPS` in a row stop the run with an
error that names the terms.
"""
from __future__ import annotations

import io
import json
import math
import os
import random
import sys
import time
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Collection, Iterator

import numpy as np
import torch
import torch.distributed as dist

from clsplat.io.atomic import atomic_write

from .presets import Preset, check_preset_matches

__all__ = ["TrainSpec", "LoopHooks", "train", "seed_everything", "set_threads", "sample_generator", "capture_rng",
           "restore_rng", "save_checkpoint", "load_checkpoint", "JsonlLog", "plot_losses", "atomic_write",
           "distributed_info", "end_distributed", "MAX_CONSECUTIVE_SKIPS", "CHECKPOINT_FORMAT"]

#: consecutive non-finite steps after which training stops with an error.
MAX_CONSECUTIVE_SKIPS = 20
#: version of the checkpoint dictionary layout.
CHECKPOINT_FORMAT = 1
_CHECKPOINT_NAME = "checkpoint.pt"


# ---------------------------------------------------------------------------------------
# seeds, threads, RNG state
# ---------------------------------------------------------------------------------------
def seed_everything(seed: int) -> None:
    """Seed python's, numpy's and torch's global generators."""
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed: expected a non-negative int, got {seed!r}")
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)


def set_threads(n: int | None = None, device=None) -> int:
    """Set torch's intra-op threads once, at an entry point; returns the number set.

    With ``n`` None on a CPU OpenCL device: :func:`clsplat.threads.default_torch_threads`
    (the cores other processes leave idle, when idle OpenMP workers let go of the core soon;
    else 1, as PoCL's workers and spinning OpenMP workers fight over the cores); elsewhere
    torch's default.
    """
    if n is None:
        from clsplat.runtime import get_runtime
        from clsplat.threads import default_torch_threads
        import pyopencl as cl
        rt = get_runtime(device)
        n = default_torch_threads() if rt.device.type & cl.device_type.CPU else torch.get_num_threads()
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise ValueError(f"threads: expected a positive int, got {n!r}")
    torch.set_num_threads(n)
    return n


def sample_generator(seed: int, index: int) -> torch.Generator:
    """A torch generator for sample ``index`` of a run seeded with ``seed`` (for augmentation,
    point subsets, ...): the same sample gets the same randomness however it is reached."""
    return torch.Generator().manual_seed((int(seed) * 1_000_003 + int(index)) % (2**63 - 1))


def capture_rng() -> dict:
    """Python, numpy and torch global RNG states, in a form ``torch.load(weights_only=True)``
    accepts."""
    npst = np.random.get_state(legacy=False)
    return {"python": random.getstate(),
            "numpy": {"key": torch.from_numpy(npst["state"]["key"].astype(np.int64)), "pos": int(npst["state"]["pos"]),
                      "has_gauss": int(npst["has_gauss"]), "gauss": float(npst["gauss"])},
            "torch": torch.get_rng_state()}


def restore_rng(state: dict) -> None:
    """Inverse of :func:`capture_rng`."""
    try:
        py = state["python"]
        random.setstate((py[0], tuple(py[1]), py[2]))
        n = state["numpy"]
        np.random.set_state({"bit_generator": "MT19937",
                             "state": {"key": n["key"].numpy().astype(np.uint32), "pos": n["pos"]},
                             "has_gauss": n["has_gauss"], "gauss": n["gauss"]})
        torch.set_rng_state(state["torch"])
    except (KeyError, TypeError, ValueError, IndexError, RuntimeError) as e:
        raise ValueError(f"rng: checkpoint RNG state is malformed ({type(e).__name__}: {e})") from None


# ---------------------------------------------------------------------------------------
# files: atomic writes, checkpoints, the JSONL log, the loss plot
# ---------------------------------------------------------------------------------------
def _write_bytes(path: Path, data) -> None:
    """Write ``data`` to ``path`` with Python's file I/O and flush it to disk, so that a full disk
    or a file-size limit is an ``OSError`` (ENOSPC, EFBIG) here, not an error inside a library."""
    with open(path, "wb") as fh:
        fh.write(data)
        fh.flush()
        os.fsync(fh.fileno())


def save_checkpoint(path: str | Path, state: dict, family: str, preset: Preset) -> Path:
    """Write ``state`` plus the family, preset and format atomically to ``path``."""
    full = {**state, "format": CHECKPOINT_FORMAT, "family": family, "preset": preset.to_dict(),
            "preset_class": type(preset).__name__}
    # Serialised in memory first: torch's own file writer reports a full disk as "RuntimeError:
    # [enforce fail at inline_container.cc] unexpected pos" and aborts the process under
    # RLIMIT_FSIZE; Python's write names the cause, and atomic_write names the file.
    buf = io.BytesIO()
    torch.save(full, buf)
    return atomic_write(path, lambda p: _write_bytes(p, buf.getbuffer()))


def load_checkpoint(path: str | Path, family: str | None = None, preset: Preset | None = None) -> dict:
    """Read a checkpoint written by :func:`save_checkpoint` (tensors on the CPU).

    Raises ValueError naming the file when it is missing, unreadable or truncated, not a clsplat
    checkpoint, from another model family, or (with ``preset``) from another preset.
    """
    p = Path(path)
    if not p.is_file():
        raise ValueError(f"checkpoint: {str(p)!r} does not exist")
    try:
        ck = torch.load(p, map_location="cpu", weights_only=True)
    except Exception as e:  # torch raises RuntimeError, UnpicklingError, EOFError, ... on bad files
        raise ValueError(f"checkpoint: {str(p)!r} cannot be read: it is corrupt, truncated or not a "
                         f"clsplat checkpoint ({type(e).__name__}: {str(e).splitlines()[0][:200] if str(e) else ''})") from None
    if not isinstance(ck, dict) or ck.get("format") != CHECKPOINT_FORMAT or "family" not in ck:
        raise ValueError(f"checkpoint: {str(p)!r} is not a clsplat model checkpoint (format {CHECKPOINT_FORMAT})")
    if family is not None and ck["family"] != family:
        raise ValueError(f"checkpoint: {str(p)!r} is a {ck['family']!r} checkpoint, not {family!r}")
    if preset is not None:
        check_preset_matches(ck.get("preset"), preset, str(p))
    return ck


class JsonlLog:
    """Append-only JSON-lines log, one record per step.

    Args:
        path: the log file.
        resume_step: None for a new run (the file is truncated); else the step a resumed run
            continues from: lines with ``step`` > resume_step (written after the checkpoint, by
            the interrupted run) are dropped, so the log reads as one uninterrupted run.
    """

    def __init__(self, path: str | Path, resume_step: int | None = None) -> None:
        self.path = Path(path)
        keep: list[str] = []
        if resume_step is not None and self.path.is_file():
            for line in self.path.read_text().splitlines():
                try:
                    if json.loads(line).get("step", math.inf) <= resume_step:
                        keep.append(line)
                except json.JSONDecodeError:
                    break  # a torn last line from the interruption
        atomic_write(self.path, lambda p: p.write_text("".join(k + "\n" for k in keep)))

    def write(self, record: dict) -> None:
        """Append one line; a failed write (full disk) is an OSError naming the log file."""
        try:
            with open(self.path, "a") as fh:
                fh.write(json.dumps(record, allow_nan=True) + "\n")
        except OSError as e:
            raise OSError(e.errno, f"writing {str(self.path)!r} failed ({e.strerror or e}); the lines "
                                   "before this step are kept") from e


def read_log(path: str | Path) -> list[dict]:
    """The records of a JSONL log (a torn last line is ignored)."""
    out = []
    for line in Path(path).read_text().splitlines():
        try:
            out.append(json.loads(line))
        except json.JSONDecodeError:
            break
    return out


def plot_losses(log_jsonl: str | Path, png: str | Path, keys: list[str] | None = None,
                title: str = "training loss", exclude: tuple[str, ...] | set[str] = ()) -> Path | None:
    """Plot loss terms against step (log scale) from a JSONL log; None if the log is empty.
    Without ``keys``: every numeric field of any record but the loop's bookkeeping and ``exclude``."""
    recs = read_log(log_jsonl)
    if not recs:
        return None
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    skip = {"step", "time_s", "lr", "skipped", "n_samples", "grad_norm", "backward_s", *exclude}
    if not keys:  # every numeric term any record has (a staged family's terms change between stages)
        keys = list(dict.fromkeys(k for r in recs for k, v in r.items() if k not in skip and not k.startswith("diag_")
                                  and isinstance(v, (int, float)) and not isinstance(v, bool)))
    fig, ax = plt.subplots(figsize=(7, 4), dpi=110)
    for k in keys:
        pts = [(r["step"], r[k]) for r in recs if isinstance(r.get(k), (int, float)) and math.isfinite(r[k]) and r[k] > 0]
        if pts:
            s, v = zip(*pts)
            ax.plot(s, v, label=k, lw=1.5 if k == "loss" else 0.8)
    ax.set_yscale("log")
    ax.set_xlabel("step")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    out = atomic_write(png, lambda p: fig.savefig(p, format="png"))
    plt.close(fig)
    return out


# ---------------------------------------------------------------------------------------
# distributed
# ---------------------------------------------------------------------------------------
def distributed_info() -> tuple[int, int]:
    """(rank, world size); initialises the default process group under torchrun
    (gloo on CPU, NCCL when CUDA is available)."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world <= 1:
        return 0, 1
    if not dist.is_initialized():
        dist.init_process_group(backend="nccl" if torch.cuda.is_available() else "gloo")
    return dist.get_rank(), dist.get_world_size()


def end_distributed() -> None:
    """Under torchrun, wait for every rank (rank 0 may still be evaluating or publishing the run
    folder) and take the process group down before the interpreter exits. A rank that exits with
    the group still up can abort in gloo's teardown ("terminate called without an active
    exception", seen once in CI under load). No-op in one process."""
    if dist.is_available() and dist.is_initialized():
        dist.barrier()
        dist.destroy_process_group()


def _params(model: torch.nn.Module) -> list[torch.nn.Parameter]:
    return [p for p in model.parameters() if p.requires_grad]


def _broadcast_parameters(model: torch.nn.Module) -> None:
    for t in list(model.parameters()) + list(model.buffers()):
        dist.broadcast(t.data, 0)


def _allreduce_gradients(params: list[torch.nn.Parameter], extra: torch.Tensor) -> torch.Tensor:
    """Sum gradients and ``extra`` over ranks in one flat all-reduce. A parameter without a
    gradient on every rank keeps ``grad = None`` (so Adam leaves it alone, as in one process)."""
    has = torch.tensor([p.grad is not None for p in params], dtype=torch.float64)
    flat = [p.grad.reshape(-1).double() if p.grad is not None else torch.zeros(p.numel(), dtype=torch.float64)
            for p in params]
    buf = torch.cat(flat + [has, extra.double().reshape(-1)])
    dist.all_reduce(buf)
    off = 0
    for p, h in zip(params, buf[sum(map(len, flat)):sum(map(len, flat)) + len(params)]):
        g = buf[off:off + p.numel()]
        off += p.numel()
        p.grad = g.reshape(p.shape).to(p.dtype) if h > 0 else None
    return buf[-extra.numel():]


# ---------------------------------------------------------------------------------------
# the loop
# ---------------------------------------------------------------------------------------
def gradient_norm(params: list[torch.nn.Parameter]) -> tuple[torch.Tensor, bool]:
    """``(total norm, every gradient finite)`` of ``params``' gradients, in one pass where they are:
    a finite total norm means every gradient is finite, and only a non-finite one (a NaN or inf,
    or finite gradients whose norm overflows) is checked element by element. The norm is
    ``clip_grad_norm_``'s own (``get_total_norm``), so :func:`clip_and_measure` given it clips as
    that does, bit for bit. A separate ``isfinite`` scan of every gradient took ~3 % of an
    AutoSplat step (py-spy, bench/notes/shared_nets_losses_metrics.md)."""
    grads = [q.grad for q in params if q.grad is not None]
    if not grads:
        return torch.tensor(0.0), True
    total = torch.nn.utils.get_total_norm(grads)
    return total, bool(torch.isfinite(total)) or all(bool(torch.isfinite(g).all()) for g in grads)


def clip_and_measure(params: list[torch.nn.Parameter], clip: float | None,
                     total: torch.Tensor | None = None) -> float:
    """Total gradient norm of ``params`` (logged every step), clipping to ``clip`` when given;
    ``total``: that norm when already measured (:func:`gradient_norm`).

    Without a clip the gradients are only measured, never rescaled: ``clip_grad_norm_`` with an
    infinite bound would multiply them by inf/inf = NaN when finite gradients overflow the norm.
    """
    if total is None:
        total = gradient_norm(params)[0]
    if clip is not None:
        torch.nn.utils.clip_grads_with_norm_(params, clip, total)
    return float(total)


@dataclass
class TrainSpec:
    """How to run: steps, global batch, checkpoints, seed, clipping, resume."""

    out_dir: str | Path
    steps: int
    batch_size: int = 1
    checkpoint_every: int = 100
    log_every: int = 1
    seed: int = 0
    grad_clip: float | None = None
    resume: bool = False
    progress: bool = True

    def validate(self) -> None:
        for name in ("steps", "batch_size", "checkpoint_every", "log_every"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"{name}: expected a positive int, got {v!r}")
        if self.grad_clip is not None and not (math.isfinite(self.grad_clip) and self.grad_clip > 0):
            raise ValueError(f"grad_clip: expected a positive number or None, got {self.grad_clip!r}")


class LoopHooks:
    """What a family adds to :func:`train`; every method is optional (this base does nothing).

    The order inside one step: ``trainable_groups`` -> the samples' forward and backward ->
    gradients of the other groups dropped -> all-reduce -> optimiser and scheduler step (when the
    step is finite) -> ``after_step`` -> the log record -> the checkpoint (``state``).
    """

    def trainable_groups(self, step: int) -> Collection[int] | None:
        """Indices into ``optimizer.param_groups`` that ``step`` updates (a stage of a schedule of
        parameter groups). The other groups' gradients are dropped before the all-reduce, so Adam
        leaves those parameters and their moments exactly as they are. None: every group."""
        return None

    def after_step(self, step: int, applied: bool) -> dict:
        """Runs on every rank after the optimiser step (``applied`` False when the step was skipped
        as non-finite), e.g. densification, which may replace parameters in the model and in the
        optimiser (:func:`clsplat.strategy.swap_parameter`; the loop re-reads the model's
        parameters every step). Collectives are allowed: every rank calls it with the same
        arguments. Returns fields for the step's log record (diagnostics: never plotted)."""
        return {}

    def state(self) -> dict:
        """Extra checkpoint state (tensors and plain values), saved under ``extra`` with
        ``extra_state`` at every checkpoint."""
        return {}

    def load_state(self, extra: dict, path: Path) -> None:
        """Restore :meth:`state` from checkpoint ``path``'s ``extra`` on resume, *before* the model's
        and optimiser's state are loaded (a family whose parameter shapes change resizes them here,
        in place, so the optimiser's parameter groups still hold them). ValueError naming ``path``
        when the checkpoint was made by another kind of run."""


@contextmanager
def _progress(enabled: bool, total: int, initial: int) -> Iterator:
    if not enabled:
        yield None
        return
    from tqdm import tqdm
    bar = tqdm(total=total, initial=initial, dynamic_ncols=True, file=sys.stderr)
    try:
        yield bar
    finally:
        bar.close()


def train(model: torch.nn.Module, optimizer: torch.optim.Optimizer, spec: TrainSpec, preset: Preset,
          family: str, sample_loss: Callable[[torch.nn.Module, int, int], dict[str, torch.Tensor]],
          scheduler=None, extra_state: dict | None = None,
          on_checkpoint: Callable[[int], None] | None = None,
          on_step: Callable[[int, dict], None] | None = None, hooks: LoopHooks | None = None) -> dict:
    """Train ``model`` for ``spec.steps`` steps (see the module docstring).

    Args:
        model: the network; its parameters are what ``optimizer`` updates.
        optimizer: built over ``model``'s parameters.
        spec: run settings; ``spec.out_dir`` must exist or be creatable.
        preset: the family's preset (printed, saved in the checkpoint, checked on resume).
        family: model family name (saved in the checkpoint, checked on resume).
        sample_loss: ``(model, step, sample_index) -> {"loss": scalar, term: scalar, ...}`` for one
            sample; a term a sample lacks counts as 0 in the batch mean (under torchrun the keys
            are gathered from every rank).
        scheduler: optional LR scheduler, stepped after every applied optimiser step.
        extra_state: a dict of tensors/plain values the family wants checkpointed (updated in
            place on resume).
        on_checkpoint: called with the step after each checkpoint is written (rank 0).
        on_step: called with (step, log record) after each step (rank 0; e.g. ``--view``).
        hooks: the family's :class:`LoopHooks` (stages, densification, extra checkpoint state).
    Returns:
        {"step": final step, "skipped": skipped steps, "last": last logged record,
         "resumed_from": step or None}.
    """
    spec.validate()
    rank, world = distributed_info()
    out = Path(spec.out_dir)
    if rank == 0:
        out.mkdir(parents=True, exist_ok=True)
    ckpt_path = out / _CHECKPOINT_NAME
    start, resumed_from = 0, None
    if spec.resume:
        ck = load_checkpoint(ckpt_path, family, preset)
        if hooks is not None:
            hooks.load_state(ck.get("extra", {}), ckpt_path)
        try:
            model.load_state_dict(ck["model"])
            optimizer.load_state_dict(ck["optimizer"])
            if scheduler is not None and ck.get("scheduler") is not None:
                scheduler.load_state_dict(ck["scheduler"])
        except (RuntimeError, ValueError, KeyError) as e:
            raise ValueError(f"resume: {ckpt_path} does not fit this model or optimiser (written by another "
                             f"version of clsplat?): {str(e).splitlines()[0]}") from e
        if extra_state is not None:
            extra_state.update(ck.get("extra", {}))
        restore_rng(ck["rng"])
        start = resumed_from = int(ck["step"])
        if start > spec.steps:
            raise ValueError(f"steps: the checkpoint is at step {start}, beyond the requested {spec.steps}")
    if world > 1:
        _broadcast_parameters(model)
    log = JsonlLog(out / "log.jsonl", resume_step=start if spec.resume else None) if rank == 0 else None
    if rank == 0:
        print(preset.describe(), flush=True)
        print(f"training {family}: steps {start}..{spec.steps}, global batch {spec.batch_size}, "
              f"{world} process(es), torch threads {torch.get_num_threads()}, out {out}", flush=True)

    def checkpoint(step: int) -> None:
        if rank == 0:
            save_checkpoint(ckpt_path, {
                "model": model.state_dict(), "optimizer": optimizer.state_dict(),
                "scheduler": scheduler.state_dict() if scheduler is not None else None,
                "step": step, "rng": capture_rng(),
                "extra": {**(extra_state or {}), **(hooks.state() if hooks is not None else {})}}, family, preset)
            if on_checkpoint is not None:
                on_checkpoint(step)

    B = spec.batch_size
    skipped = consecutive = 0
    last: dict = {}
    bad_terms: set[str] = set()
    diagnostics: set[str] = set()  # the hooks' log fields, left out of the loss plot
    with _progress(spec.progress and rank == 0, spec.steps, start) as bar:
        for step in range(start, spec.steps):
            t0 = time.perf_counter()
            params = _params(model)  # after_step may have replaced some (densification)
            optimizer.zero_grad(set_to_none=True)
            indices = list(range(step * B, (step + 1) * B))[rank::world]
            sums: dict[str, float] = {}
            local_ok = True
            backward_s = 0.0
            for idx in indices:
                terms = sample_loss(model, step, idx)
                if "loss" not in terms:
                    raise ValueError("sample_loss: the returned dict must have a 'loss' entry")
                loss = terms["loss"]
                if not torch.isfinite(loss.detach()).all():
                    local_ok = False
                    bad_terms.update(k for k, v in terms.items() if not torch.isfinite(torch.as_tensor(v)).all())
                else:
                    tb = time.perf_counter()
                    (loss / B).backward()
                    backward_s += time.perf_counter() - tb
                for k, v in terms.items():
                    sums[k] = sums.get(k, 0.0) + float(torch.as_tensor(v).detach())
            groups = hooks.trainable_groups(step) if hooks is not None else None
            lr = optimizer.param_groups[0]["lr"]  # the rate this step uses (the scheduler moves it after)
            if groups is not None:  # a stage: the other groups get no update (their gradients are dropped)
                frozen = set(range(len(optimizer.param_groups))) - set(groups)
                for i in frozen:
                    for q in optimizer.param_groups[i]["params"]:
                        q.grad = None
            keys = sorted(sums)
            if world > 1:  # the union of every rank's terms (a term one rank's samples lack is 0 there)
                gathered: list = [None] * world
                dist.all_gather_object(gathered, keys)
                keys = sorted(set().union(*gathered))
            stats = torch.tensor([sums.get(k, 0.0) for k in keys] + [float(not local_ok)], dtype=torch.float64)
            if world > 1:
                stats = _allreduce_gradients(params, stats)
            total_norm, grads_ok = gradient_norm(params)
            ok = bool(stats[-1] == 0) and grads_ok
            if ok:
                grad_norm = clip_and_measure(params, spec.grad_clip, total_norm)
                optimizer.step()
                if scheduler is not None:
                    scheduler.step()
                consecutive = 0
            else:
                skipped += 1
                consecutive += 1
                if not grads_ok:
                    bad_terms.add("gradients")
                if consecutive >= MAX_CONSECUTIVE_SKIPS:
                    raise RuntimeError(f"training diverged: {consecutive} consecutive steps up to step {step + 1} "
                                       f"had non-finite values in {sorted(bad_terms)}; lower the learning rate "
                                       f"or resume from the last checkpoint ({ckpt_path})")
            fields = hooks.after_step(step, ok) if hooks is not None else {}
            diagnostics.update(fields)
            rec = {"step": step + 1, **{k: float(v) / B for k, v in zip(keys, stats[:-1].tolist())},
                   "lr": lr, "time_s": time.perf_counter() - t0,
                   "backward_s": backward_s, **fields}
            if ok:
                rec["grad_norm"] = grad_norm
            else:
                rec["skipped"] = True
            last = rec
            if log is not None and ((step + 1) % spec.log_every == 0 or step + 1 == spec.steps):
                log.write(rec)
            if on_step is not None and rank == 0:
                on_step(step + 1, rec)
            if bar is not None:
                bar.update(1)
                bar.set_postfix(loss=f"{rec.get('loss', float('nan')):.4g}")
            if (step + 1) % spec.checkpoint_every == 0 or step + 1 == spec.steps:
                checkpoint(step + 1)
    if rank == 0:
        plot_losses(out / "log.jsonl", out / "loss.png", title=f"{family} ({preset.name}) training loss",  # type: ignore[attr-defined]
                    exclude=diagnostics)
    return {"step": spec.steps, "skipped": skipped, "last": last, "resumed_from": resumed_from}
