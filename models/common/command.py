"""The one skeleton of ``clsplat train FAMILY`` and ``clsplat eval FAMILY``, and the one way a
model is rebuilt from its checkpoint.

A family supplies its parts by subclassing :class:`Family` (one instance per family, listed in
:mod:`clsplat.models.registry`); :func:`train_main` and :func:`eval_main` run the steps every
command shares, in this order::

    train: parse -> preset (--preset, --set, the family's flags) -> data -> threads -> LPIPS ->
           seed -> run folder (lock, stage) -> model -> [viewer] -> loop -> evaluate (rank 0)
           -> publish
    eval:  parse -> the family's checks -> threads -> checkpoint -> preset -> model (restore) ->
           LPIPS -> staged outputs -> evaluate

One error policy: a user's mistake anywhere in them is a ValueError naming the argument, printed
as one line (``clsplat train FAMILY: ...``) with exit status 2; nothing is published (the run
folder keeps the previous run, the partial one stays staged for ``--resume``).
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, ClassVar

from clsplat.argparser import ArgumentParser

from .cli import (add_common_args, add_eval_args, add_eval_scenes_arg, add_eval_split_arg, add_view_args,
                  lpips_from_args)
from .presets import Preset, apply_sets, check_preset_matches, get_preset, preset_from_saved

__all__ = ["Family", "TrainJob", "Restored", "train_main", "eval_main", "restore"]


@dataclass
class TrainJob:
    """One ``clsplat train FAMILY`` run, as the skeleton hands it to the family's parts.

    ``data`` is what :meth:`Family.load_data` returned; ``stage`` the run folder's staging
    folder (every output goes there, published as a group at the end); ``model`` what
    :meth:`Family.build` returned; ``on_step`` the viewer's hook (``--view``) or None; ``extra``
    whatever a family's parts pass each other."""

    args: argparse.Namespace
    preset: Preset
    data: Any
    lpips: Any = None
    stage: Path | None = None
    model: Any = None
    on_step: Callable[[int, dict], None] | None = None
    extra: dict = field(default_factory=dict)


@dataclass
class Restored:
    """A model rebuilt from a checkpoint: the model (whatever the family trains: a network, or
    AutoSplat's trainer with its scene), its preset with the run's ``--set`` changes, the raw
    checkpoint and its path."""

    model: Any
    preset: Preset
    checkpoint: dict
    path: Path


class Family:
    """What a model family gives the commands. Subclass it, set the class attributes, and
    override the parts; the defaults are those of a feed-forward family on ``--data`` specs."""

    #: registry and checkpoint name, ``clsplat train NAME``
    name: ClassVar[str]
    #: the paper's name, for messages
    title: ClassVar[str]
    #: ``--preset`` without the flag
    default_preset: ClassVar[str] = "small"
    #: the synthetic world of a plain ``--data synthetic``
    default_world: ClassVar[str] = "classic"
    #: a feed-forward family scores held-out scenes (``--eval-scenes``, ``--num-scenes``,
    #: ``--eval-split``); a per-scene family scores its own sequence's held-out frames
    feed_forward: ClassVar[bool] = True
    #: why ``--weights`` means nothing to the family (None: its encoders load them)
    no_weights: ClassVar[str | None] = None
    #: the ``--help`` text of ``train`` and ``eval``
    train_help: ClassVar[str] = ""
    eval_help: ClassVar[str] = ""

    # ----------------------------------------------------------------------------- train
    def add_train_args(self, p: argparse.ArgumentParser) -> None:
        """The family's own ``train`` flags."""

    def train_preset(self, args: argparse.Namespace, preset: Preset) -> Preset:
        """The preset after the family's flags (``--set`` is applied already)."""
        return preset

    def load_data(self, job: TrainJob) -> Any:
        """The training data named by ``--data`` (default: a :class:`~.data.DataSource`); may
        leave what later parts need in ``job.extra``."""
        from .data import parse_data
        a = job.args
        return parse_data(a.data, seed=a.seed, safe_pickle=not a.trust_pickle, default_world=self.default_world)

    def build(self, job: TrainJob) -> Any:
        """The model to train (``job.stage`` is open: ``--resume`` state is there)."""
        raise NotImplementedError

    def scene(self, job: TrainJob):
        """The :class:`~clsplat.viewer.scene.ViewScene` of the model now (``--view``)."""
        raise NotImplementedError

    def fit(self, job: TrainJob) -> bool:
        """Train ``job.model`` into ``job.stage``; False when the run stopped before its end."""
        raise NotImplementedError

    def evaluate_run(self, job: TrainJob) -> str:
        """Evaluate the trained model into ``job.stage`` (rank 0 only); the summary line(s)."""
        raise NotImplementedError

    # ------------------------------------------------------------------------------ eval
    def add_eval_args(self, p: argparse.ArgumentParser) -> None:
        """The family's own ``eval`` flags."""

    def check_eval_args(self, args: argparse.Namespace) -> None:
        """Refuse a bad ``eval`` flag before the checkpoint is read (ValueError naming it)."""

    def checkpoint_path(self, args: argparse.Namespace) -> Path:
        """The checkpoint ``clsplat eval`` reads (``--checkpoint``)."""
        return Path(args.checkpoint)

    def restore_model(self, ck: dict, preset: Preset, path: Path, device=None, **context) -> Any:
        """The model of checkpoint ``ck`` (read from ``path``) with ``preset``'s networks."""
        raise NotImplementedError

    def saved_preset(self, saved: dict | None, name: str | None = None) -> Preset:
        """The preset a checkpoint was written with (the run's ``--set`` changes applied)."""
        return preset_from_saved(self.name, saved, name)

    def evaluate_checkpoint(self, restored: Restored, args: argparse.Namespace, stage: Path, lpips) -> str:
        """``clsplat eval``: evaluate the restored model into ``stage``; the summary line(s)."""
        raise NotImplementedError

    def checkpoint_scene(self, restored: Restored, run: Path, data: str | None, sample: int = 0,
                         safe_pickle: bool = True):
        """The viewer's scene of a checkpoint (``clsplat view RUN``)."""
        raise NotImplementedError


def restore(family: Family, path: str | Path, device=None, preset_name: str | None = None,
            checkpoint: dict | None = None, **context) -> Restored:
    """The one checkpoint rebuild: read ``path`` (refusing another family's checkpoint), take the
    preset it was written with (``preset_name``: refuse a checkpoint of another preset), check
    that the registered preset's fields match its record, and let the family rebuild the model.
    ``checkpoint``: the file's contents when the caller has read them already (checked for the
    family all the same). ``context`` goes to :meth:`Family.restore_model` (``data``,
    ``safe_pickle``, ``scale``: what AutoSplat rebuilds its run's data from)."""
    from .train import load_checkpoint
    path = Path(path)
    ck = load_checkpoint(path, family.name) if checkpoint is None else checkpoint
    if ck.get("family") != family.name:
        raise ValueError(f"checkpoint {str(path)!r} was written by {ck.get('family')!r}, not {family.name!r}")
    preset = family.saved_preset(ck.get("preset"), preset_name)
    check_preset_matches(ck.get("preset") or {}, preset, str(path))
    return Restored(family.restore_model(ck, preset, path, device, **context), preset, ck, path)


def _parser(command: str, family: Family) -> argparse.ArgumentParser:
    """``clsplat COMMAND FAMILY``'s flags: the shared ones, the feed-forward families' held-out
    scenes and split, the family's own, and (``train``) the viewer's."""
    p = ArgumentParser(prog=f"clsplat {command} {family.name}",
                       description=(family.train_help if command == "train" else family.eval_help) or None,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    if command == "train":
        add_common_args(p, default_preset=family.default_preset)
        if family.feed_forward:
            add_eval_scenes_arg(p)
    else:
        add_eval_args(p, scenes=family.feed_forward)
    if family.feed_forward:
        add_eval_split_arg(p)
    (family.add_train_args if command == "train" else family.add_eval_args)(p)
    if command == "train":
        add_view_args(p)
    return p


def _main(command: str, family: Family, body: Callable[[Family, argparse.Namespace], int], argv: list[str]) -> int:
    """Parse ``argv`` and run ``body``; a ValueError is the one-line error policy's (exit 2)."""
    args = _parser(command, family).parse_args(argv)
    try:
        return body(family, args)
    except ValueError as e:
        print(f"clsplat {command} {family.name}: {e}", file=sys.stderr)
        return 2


def train_main(family: Family, argv: list[str]) -> int:
    """``clsplat train FAMILY ARGV``; returns the exit status (a worker rank under torchrun
    ends the process with it instead: :func:`_end_worker_rank`)."""
    rc = _main("train", family, _train, argv)
    _end_worker_rank(rc)
    return rc


def _end_worker_rank(rc: int) -> None:
    """Under torchrun, a rank other than 0 ends here with its exit status, its output flushed,
    without the interpreter's teardown. Its work is done (the run ended at a barrier and the
    process group is down), and a worker exiting normally aborted in a library's static
    destructors under load ("terminate called without an active exception", SIGABRT, seen twice
    in fresh-clone test runs), which made torchrun report a finished run as failed."""
    if int(os.environ.get("WORLD_SIZE", "1")) > 1 and int(os.environ.get("RANK", "0")) != 0:
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(rc)


def eval_main(family: Family, argv: list[str]) -> int:
    """``clsplat eval FAMILY ARGV``; returns the exit status."""
    return _main("eval", family, _eval, argv)


def _train(family: Family, args: argparse.Namespace) -> int:
    from .runfolder import RunFolder
    from .train import distributed_info, end_distributed, seed_everything, set_threads
    from .view import train_watcher

    if family.no_weights is not None and args.weights is not None:
        raise ValueError(f"--weights: {family.title} has no pretrained backbone to load ({family.no_weights})")
    preset = family.train_preset(args, apply_sets(get_preset(family.name, args.preset), args.set))
    if args.view:   # a taken port is a one-line error now, not after the data loaded
        from clsplat.viewer.server import check_port_free
        check_port_free(args.view_host, args.view_port, ("--view-host", "--view-port"))
    job = TrainJob(args, preset, None)
    t0 = time.perf_counter()
    job.data = family.load_data(job)
    job.extra["load_seconds"] = time.perf_counter() - t0
    threads = set_threads(args.threads, args.device)
    job.lpips = lpips_from_args(args)   # before the seed: building LPIPS' networks draws random numbers
    seed_everything(args.seed)
    distributed_info()  # under torchrun: the process group the run folder's ranks meet in
    rank0 = distributed_info()[0] == 0
    from clsplat.runtime import get_runtime
    print(f"{family.title}: data {getattr(job.data, 'name', args.data)}, torch threads {threads}, "
          f"renderer {get_runtime(args.device).name}", flush=True)
    summary = None
    with RunFolder(args.out, resume=args.resume) as rf:  # the lock; outputs staged, then published as a group
        job.stage = rf.stage
        job.model = family.build(job)
        watcher = train_watcher(args, lambda: family.scene(job), args.device)
        job.on_step = None if watcher is None else watcher.on_step
        try:
            finished = family.fit(job)
        finally:
            if watcher is not None:
                watcher.close()
        if not finished:
            end_distributed()
            return 0
        if rank0:
            summary = family.evaluate_run(job)
        rf.publish()
    if summary:
        print(summary, flush=True)
    end_distributed()
    return 0


def _eval(family: Family, args: argparse.Namespace) -> int:
    from clsplat.io.atomic import staged_group

    from .train import set_threads
    family.check_eval_args(args)
    set_threads(args.threads, args.device)
    restored = restore(family, family.checkpoint_path(args), args.device, getattr(args, "preset", None),
                       data=args.data, safe_pickle=not args.trust_pickle, scale=getattr(args, "scale", None))
    lpips = lpips_from_args(args)
    with staged_group(args.out) as stage:  # the outputs replace an earlier evaluation's together
        summary = family.evaluate_checkpoint(restored, args, stage, lpips)
    print(summary, flush=True)
    return 0
