"""Where a training step goes, for any model family, measured inside the real training command.

    python bench/experiments/step_profile.py [--skip 2] [--json FILE] [--label TEXT] -- \\
        train drivingforward --preset small --steps 6 --out DIR [--threads N] ...

runs ``clsplat <args after -->`` in this process with timing hooks installed and prints one JSON
line: the medians, over the steps after the first ``--skip``, of

* ``step``: the whole optimisation step (DrivingForward / PGT: from one optimiser step to the
  next, so logging is included; AutoSplat, on the same loop: from the end of one
  ``Trainer.after_step`` to the next, so densification is included);
* ``data``: the family's sample function (DrivingForward ``load_triplet``, PGT ``make_sample``;
  AutoSplat preloads its data, so 0), renders inside it not counted as the renderer's;
* ``render_fwd``: inside :func:`clsplat.rasterization` (validation, projection, binning, sort,
  compositing, read-backs);
* ``render_bwd``: inside the ``backward`` of clsplat's autograd functions;
* ``nets_bwd``: ``Tensor.backward`` minus ``render_bwd`` (the networks' and losses' backward);
* ``optim``: inside the optimiser's ``step`` (global step hooks);
* ``nets_fwd``: the rest (networks' forward, losses, bookkeeping);

(AutoSplat: also per stage of its schedule, ``median_s_by_stage``)

with ``torch_threads`` (what the command chose), the thread environment and the 1-minute load
average at the start and the end. ``clsplat`` is imported first, as every clsplat command does,
so the package's thread defaults apply unless ``CLSPLAT_THREAD_DEFAULTS=0`` is set.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time

import clsplat  # first: the thread defaults go in before torch loads

__all__ = ["main"]

PARTS = ("data", "render_fwd", "render_bwd", "backward", "optim")


class _Clock:
    """Per-step accumulators; a step closes at :meth:`close`."""

    def __init__(self) -> None:
        self.acc = dict.fromkeys(PARTS, 0.0)
        self.steps: list[dict] = []
        self.start = time.perf_counter()
        self.in_data = 0

    def add(self, key: str, seconds: float) -> None:
        self.acc[key] += seconds

    def close(self, end: float | None = None, stage: str | None = None) -> None:
        end = time.perf_counter() if end is None else end
        rec = dict(self.acc, step=end - self.start)
        if stage is not None:
            rec["stage"] = stage
        rec["nets_bwd"] = rec["backward"] - rec["render_bwd"]
        rec["nets_fwd"] = rec["step"] - rec["data"] - rec["render_fwd"] - rec["backward"] - rec["optim"]
        self.steps.append(rec)
        self.acc = dict.fromkeys(PARTS, 0.0)
        self.start = end


def _install(clock: _Clock, family: str) -> None:
    import functools

    import torch

    import clsplat.autograd as ag

    def timed(fn, key, skip_in_data=False, data=False):
        @functools.wraps(fn)
        def wrapper(*a, **k):
            if skip_in_data and clock.in_data:
                return fn(*a, **k)
            clock.in_data += data
            t0 = time.perf_counter()
            try:
                return fn(*a, **k)
            finally:
                clock.add(key, time.perf_counter() - t0)
                clock.in_data -= data
        return wrapper

    clsplat.rasterization = timed(clsplat.rasterization, "render_fwd", skip_in_data=True)
    for fn_cls in (ag.ProjectFn, ag.ShFn, ag.RasterizeFn):
        fn_cls.backward = staticmethod(timed(fn_cls.backward, "render_bwd", skip_in_data=True))
    torch.Tensor.backward = timed(torch.Tensor.backward, "backward")

    t_opt = [0.0]

    def pre(opt, args, kwargs):
        t_opt[0] = time.perf_counter()

    def post(opt, args, kwargs):
        t = time.perf_counter()
        clock.add("optim", t - t_opt[0])
        if family != "autosplat":
            clock.close(t)

    from torch.optim.optimizer import register_optimizer_step_post_hook, register_optimizer_step_pre_hook
    register_optimizer_step_pre_hook(pre)
    register_optimizer_step_post_hook(post)

    if family == "drivingforward":
        import clsplat.models.drivingforward.data as dfd
        dfd.load_triplet = timed(dfd.load_triplet, "data", data=True)
    elif family == "pgt":
        import clsplat.models.pgt.training as pt
        pt.make_sample = timed(pt.make_sample, "data", data=True)
    elif family == "autosplat":
        from clsplat.models.autosplat.trainer import Trainer
        after = Trainer.after_step

        @functools.wraps(after)
        def after_step(self, i, applied):
            out = after(self, i, applied)
            clock.close(stage=self.stage_of(i)[0])
            return out
        Trainer.after_step = after_step
    else:
        raise ValueError(f"family: expected drivingforward, pgt or autosplat, got {family!r}")


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if "--" not in argv:
        print("step_profile: give the clsplat command after --", file=sys.stderr)
        return 2
    cut = argv.index("--")
    p = argparse.ArgumentParser(prog="python bench/experiments/step_profile.py")
    p.add_argument("--skip", type=int, default=2, help="steps left out of the medians (warm-up)")
    p.add_argument("--json", default=None, help="append the JSON line to this file")
    p.add_argument("--label", default="")
    p.add_argument("--cpu-backward", choices=("pixel", "gaussian"), default=None,
                   help="the compositing backward PoCL's CPU device runs by default (clsplat.stages."
                        "BACKWARD_IMPL_CPU), to time a step with either (issue 35)")
    a = p.parse_args(argv[:cut])
    if a.cpu_backward is not None:
        import clsplat.stages
        clsplat.stages.BACKWARD_IMPL_CPU = a.cpu_backward
    cmd = argv[cut + 1:]
    if len(cmd) < 2 or cmd[0] != "train":
        print("step_profile: expected `-- train FAMILY ...`", file=sys.stderr)
        return 2
    import torch

    from clsplat.cli import main as cli_main

    clock = _Clock()
    _install(clock, cmd[1])
    load0 = os.getloadavg()[0]
    t0 = time.perf_counter()
    rc = cli_main(cmd)
    wall = time.perf_counter() - t0
    kept = clock.steps[a.skip:]
    if not kept:
        print(f"step_profile: {len(clock.steps)} steps ran, none left after --skip {a.skip}", file=sys.stderr)
        return 1
    def medians(rows: list[dict]) -> dict:
        return {k: round(statistics.median(s[k] for s in rows), 4) for k in rows[0] if k != "stage"}

    by_stage: dict[str, list[dict]] = {}
    for s in kept:
        if "stage" in s:
            by_stage.setdefault(s["stage"], []).append(s)
    out = {"label": a.label, "family": cmd[1], "cmd": " ".join(cmd), "rc": rc, "steps": len(kept),
           "torch_threads": torch.get_num_threads(),
           "env": {k: os.environ.get(k) for k in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT", "KMP_BLOCKTIME",
                                                       "CLSPLAT_THREAD_DEFAULTS")},
           "load_start": load0, "load_end": os.getloadavg()[0], "wall_s": wall,
           "median_s": medians(kept),
           **({"median_s_by_stage": {k: dict(medians(v), steps=len(v)) for k, v in by_stage.items()}}
              if by_stage else {}),
           "per_step_s": [round(s["step"], 4) for s in kept]}
    line = json.dumps(out)
    print(line, flush=True)
    if a.json:
        with open(a.json, "a") as f:
            f.write(line + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
