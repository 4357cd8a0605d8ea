"""What one budget-stage step costs with κ conditioning in the decoder (``kappa_decoder``) against
κ at the heads only, measured side by side on the same samples.

Both models start from one base checkpoint (``--init``) with the ``small`` preset's budget stage,
``kappa_decoder`` set to 0 and to each value of ``--stages``; every round runs one training
sample (forward, render, loss, backward; no optimiser step, which is small and the same work)
through each model in turn, so load on a shared machine hits both alike. Prints the median
seconds per step of each and the ratio of medians.

Run: ``python bench/experiments/pgt_budget_step_cost.py --init /work/runs/pgt_base/checkpoint.pt
--rounds 12 --stages 2``.
"""
from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from clsplat.models.common.data import parse_data
from clsplat.models.common.train import load_checkpoint, set_threads
from clsplat.models.pgt.model import PGT
from clsplat.models.pgt.presets import SMALL
from clsplat.models.pgt.training import make_sample_loss


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--init", required=True, help="base checkpoint")
    ap.add_argument("--rounds", type=int, default=12)
    ap.add_argument("--warmup", type=int, default=2)
    ap.add_argument("--stages", default="2", help="comma-separated kappa_decoder values to compare with 0")
    args = ap.parse_args()
    set_threads(1, None)
    source = parse_data("synthetic", seed=0)
    state = {k: v for k, v in load_checkpoint(args.init, "pgt")["model"].items() if not k.startswith("budget.")}
    variants = {}
    for kd in [0] + [int(x) for x in args.stages.split(",")]:
        preset = SMALL.replace(kappa_decoder=kd)
        model = PGT(preset)
        model.load_state_dict(state)
        model.enable_budget()
        variants[kd] = (model, make_sample_loss(source, preset, "budget", 0))
    times: dict[int, list[float]] = {kd: [] for kd in variants}
    for r in range(args.warmup + args.rounds):
        for kd, (model, loss_fn) in variants.items():
            model.zero_grad(set_to_none=True)
            t0 = time.perf_counter()
            loss_fn(model, r, r)["loss"].backward()
            dt = time.perf_counter() - t0
            if r >= args.warmup:
                times[kd].append(dt)
    base = float(np.median(times[0]))
    for kd, ts in times.items():
        med = float(np.median(ts))
        print(f"kappa_decoder={kd}: median {med:.3f} s/step over {len(ts)} steps "
              f"(min {min(ts):.3f}, max {max(ts):.3f}); ratio to 0: {med / base:.2f}x")


if __name__ == "__main__":
    main()
