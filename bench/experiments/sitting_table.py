"""Summarise a thread sitting (bench/experiments/thread_sitting.sh's JSON lines) as a markdown table.

    python bench/experiments/sitting_table.py FILE.jsonl [--skip-rounds r1] [--base t1]

One row per (family, setting): rounds, torch threads, load range, and the median over rounds of
each part of the step (seconds), plus the step's ratio to the ``--base`` setting's.
"""
from __future__ import annotations

import argparse
import json
import statistics
from collections import defaultdict

PARTS = ("step", "data", "nets_fwd", "nets_bwd", "render_fwd", "render_bwd", "optim")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("file")
    p.add_argument("--skip-rounds", default="", help="comma-separated round labels to leave out, e.g. r1")
    p.add_argument("--base", default="t1")
    a = p.parse_args()
    skip = {s for s in a.skip_rounds.split(",") if s}
    rows = defaultdict(list)
    for line in open(a.file):
        d = json.loads(line)
        rnd, *rest = d["label"].split()
        cfg = " ".join(rest)
        if rnd in skip or d.get("rc", 0) != 0:
            continue
        rows[(d["family"], cfg)].append(d)
    print("| family | setting | torch threads | rounds | load | " + " | ".join(PARTS) + f" | step / {a.base} |")
    print("|---" * (6 + len(PARTS)) + "|")
    for (fam, cfg), ds in rows.items():
        med = {k: statistics.median(d["median_s"][k] for d in ds) for k in PARTS}
        base = rows.get((fam, a.base + cfg[len(cfg.split()[0]):]))  # "t1 loaded" for "default loaded"
        ratio = med["step"] / statistics.median(d["median_s"]["step"] for d in base) if base else float("nan")
        loads = [d["load_start"] for d in ds]
        threads = sorted({d["torch_threads"] for d in ds})
        print(f"| {fam} | {cfg} | {','.join(map(str, threads))} | {len(ds)} | {min(loads):.2f}-{max(loads):.2f} | "
              + " | ".join(f"{med[k]:.3f}" for k in PARTS) + f" | {ratio:.2f} |")


if __name__ == "__main__":
    main()
