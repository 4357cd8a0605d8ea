"""Markdown tables from `percall_ab.sh` and `clsplat bench percall --json` lines.

    python bench/experiments/percall_table.py ab FILE.jsonl [FILE.jsonl ...]   # tree A vs tree B
    python bench/experiments/percall_table.py layout FILE.jsonl                # packed vs unpacked

Medians over rounds of the per-process medians (fwd, bwd, fwd+bwd, calling-thread CPU, kernels).
"""
from __future__ import annotations

import json
import statistics
import sys
from collections import defaultdict

KEYS = ("fwd_ms", "bwd_ms", "total_ms", "cpu_ms", "kernel_ms")


def _rows(files: list[str]) -> list[dict]:
    return [json.loads(line) for f in files for line in open(f) if line.startswith("{")]


def _line(label: str, rs: list[dict]) -> str:
    med = {k: statistics.median(r[k] for r in rs) for k in KEYS}
    loads = [float(r["load"]) for r in rs if "load" in r]
    load = f"{min(loads):.1f}-{max(loads):.1f}" if loads else "-"
    return f"| {label} | {len(rs)} | {load} | " + " | ".join(f"{med[k]:.2f}" for k in KEYS) + " |"


def main() -> None:
    mode, files = sys.argv[1], sys.argv[2:]
    groups = defaultdict(list)
    for r in _rows(files):
        key = (r["scene"], r["N"], r["size"], "packed" if r["packed"] else "unpacked",
               r.get("tree", "") if mode == "ab" else "")
        groups[key].append(r)
    print("| scene | rounds | load | fwd ms | bwd ms | fwd+bwd ms | calling-thread CPU ms | kernels ms |")
    print("|---|---|---|---|---|---|---|---|")
    for (scene, n, size, layout, tree), rs in groups.items():
        print(_line(f"{scene} ({n}, {size}) {layout} {tree}".strip(), rs))


if __name__ == "__main__":
    main()
