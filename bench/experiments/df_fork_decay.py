"""Fork a constant-rate DrivingForward run at step A into its ``lr_decay_at=A`` arm (issue 32: the
paired decay study of bench/notes/drivingforward_varied_world.md, "A step decay of the rate").

The decay arm is, step for step, the constant arm until step A (``lr_factors`` multiplies by
``lr_decay_factor`` only from step A on; seed 0's from-scratch decay log equals the constant log bit
for bit through step 1500). So its state at step A is the constant arm's checkpoint at A with two
things rewritten:

* ``lr_decay_at`` in the checkpoint's preset record (``--resume`` checks the record against the
  preset asked for);
* the rate the optimiser holds. A run steps its ``LambdaLR`` at the end of each step, so the stored
  rate is the one the *saved* preset gave for step A (factor 1); the decay arm holds
  ``initial_lr * (1 * lr_decay_factor)`` there, the product ``LambdaLR`` forms. Without this the fork
  takes step A + 1 at the full rate.

Then ``clsplat train drivingforward ... --set lr_decay_at=A --resume --out DST``. Half the compute of
running both arms from step 0; the fork logs the decayed rate from step A + 1 as the from-scratch run
does (checked on ``tiny --set lr_warmup=2``, fork at 10, 14 steps: the log's steps, rates and
losses and the held-out AbsRel equal the from-scratch decay run's bit for bit). Only for presets whose rate factor is 1 at A (warm-up over, no pose half-life), checked.

    .venv/bin/python bench/experiments/df_fork_decay.py SRC DST --at 1500   # SRC published at step A
    .venv/bin/python bench/experiments/df_fork_decay.py --in-place DIR --at 1500   # DIR/.staging's checkpoint
"""
from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path

import torch


def fork(checkpoint: Path, at: int) -> list[float]:
    """Rewrite ``checkpoint`` (a constant-rate run at step ``at``) into the decay arm's; the new rates."""
    ck = torch.load(checkpoint, map_location="cpu", weights_only=True)
    preset = ck["preset"]
    if ck["step"] != at:
        raise SystemExit(f"--at: the checkpoint is at step {ck['step']}, not {at}")
    if preset.get("lr_decay_at") not in (None, at):
        raise SystemExit(f"SRC: its preset already decays at {preset['lr_decay_at']}")
    if preset.get("lr_warmup", 0) > at or preset.get("pose_lr_half_life") is not None:
        raise SystemExit("SRC: its rate factor at --at is not 1 (warm-up or pose half-life): not forkable")
    if ck.get("scheduler") is None:
        raise SystemExit("SRC: a run without a rate schedule (lr_warmup 0): the decay arm's schedule would "
                         "restart at step 0 on resume")
    factor = float(preset["lr_decay_factor"])
    preset["lr_decay_at"] = at
    for g in ck["optimizer"]["param_groups"]:
        g["lr"] = g["initial_lr"] * (1.0 * factor)
    ck["scheduler"]["_last_lr"] = [g["lr"] for g in ck["optimizer"]["param_groups"]]
    torch.save(ck, checkpoint)
    return [g["lr"] for g in ck["optimizer"]["param_groups"]]


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("src", nargs="?", type=Path, help="a constant-rate run folder, published at step --at")
    p.add_argument("dst", nargs="?", type=Path, help="the decay arm's run folder (must not exist)")
    p.add_argument("--in-place", type=Path, help="rewrite DIR/.staging/checkpoint.pt instead of copying")
    p.add_argument("--at", type=int, required=True, help="the step of the checkpoint and of the decay")
    a = p.parse_args(argv)
    if a.in_place is not None:
        ck = a.in_place / ".staging" / "checkpoint.pt"
    else:
        if a.src is None or a.dst is None:
            p.error("SRC and DST are needed without --in-place")
        if not a.src.is_dir():
            p.error(f"SRC: {a.src} is not a run folder")
        if a.dst.exists():
            p.error(f"DST: {a.dst} exists")
        shutil.copytree(a.src, a.dst)
        ck = a.dst / "checkpoint.pt"
    if not ck.is_file():
        sys.exit(f"no checkpoint at {ck}")
    print(f"{ck}: lr_decay_at={a.at}, rates {fork(ck, a.at)}")


if __name__ == "__main__":
    main()
