"""What ``packed=True`` costs against ``packed=False``, calls alternating in one process.

    python bench/experiments/packed_cost.py [--n 1000000] [--width 640] [--height 352] [--pairs 6]

Builds one scene (:func:`clsplat.bench.scenes.random_frustum_scene`, plain RGB, one camera)
and times ``--pairs`` rounds of (packed, unpacked) or (unpacked, packed), the order flipping
every round, each call a forward (``rasterization``) and a backward (``loss.backward()``) after
one warm-up call of each. Alternating calls in one process see the same load and the same
allocator state, which separate processes on a shared machine do not. Prints one JSON line per
call and a summary line with the medians, their packed / unpacked ratios, and the median over
rounds of each round's packed / unpacked ratio.
"""
from __future__ import annotations

import argparse
import json
import statistics
import time

import clsplat  # first: thread defaults before torch loads

__all__ = ["main"]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python bench/experiments/packed_cost.py", description=__doc__.split("\n")[0])
    p.add_argument("--n", type=int, default=1_000_000)
    p.add_argument("--width", type=int, default=640)
    p.add_argument("--height", type=int, default=352)
    p.add_argument("--pairs", type=int, default=6)
    a = p.parse_args(argv)
    import torch

    from clsplat.bench.percall import _leaves
    from clsplat.bench.scenes import random_frustum_scene

    torch.set_num_threads(1)
    args = _leaves(random_frustum_scene(a.n, a.width, a.height, sh_degree=None, seed=0))
    rows: dict[bool, list[tuple[float, float]]] = {True: [], False: []}

    def call(packed: bool, record: bool) -> None:
        t0 = time.perf_counter()
        img, alpha, _ = clsplat.rasterization(**args, packed=packed)
        t1 = time.perf_counter()
        (img.sum() + alpha.sum()).backward()
        t2 = time.perf_counter()
        for k in ("means", "quats", "scales", "opacities", "colors"):
            args[k].grad = None
        if record:
            rows[packed].append((t1 - t0, t2 - t1))
            print(json.dumps({"packed": packed, "fwd_s": t1 - t0, "bwd_s": t2 - t1}), flush=True)

    call(True, False)
    call(False, False)
    for i in range(a.pairs):
        for packed in ((True, False) if i % 2 == 0 else (False, True)):
            call(packed, True)
    med = {lay: {"fwd_s": statistics.median(r[0] for r in rows[lay]),
                 "bwd_s": statistics.median(r[1] for r in rows[lay]),
                 "total_s": statistics.median(r[0] + r[1] for r in rows[lay])} for lay in (True, False)}
    # each round's packed call over its unpacked neighbour: the load drifts less within a round
    paired = {k: statistics.median(pk[i] / up[i] for pk, up in zip(rows[True], rows[False]))
              for k, i in (("fwd_s", 0), ("bwd_s", 1))}
    paired["total_s"] = statistics.median((pk[0] + pk[1]) / (up[0] + up[1]) for pk, up in zip(rows[True], rows[False]))
    print(json.dumps({"summary": {"n": a.n, "size": f"{a.width}x{a.height}", "pairs": a.pairs,
                                  "packed": med[True], "unpacked": med[False],
                                  "ratio_of_medians": {k: med[True][k] / med[False][k] for k in med[True]},
                                  "median_of_round_ratios": paired}}), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
