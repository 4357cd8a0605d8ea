"""What the pose sign test decided in a DrivingForward run (issue 32, ``pose_sign_test``): for each
window of ``--window`` steps of ``log.jsonl``, the summed ``diag_sign_delta`` (the pose network's
own objective with its translations as predicted minus with them negated; > 0: the negated branch
was lower), how many steps favoured each branch, and the translation's sign after the window
(``diag_translation_sign`` of the next logged step), with the flips marked.

    .venv/bin/python bench/experiments/df_sign_test_log.py RUN_DIR [RUN_DIR ...] [--window 10]
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path


def windows(log: list[dict], w: int) -> list[str]:
    """One line per window of ``w`` steps that logged a ``diag_sign_delta``."""
    by_step = {r["step"]: r for r in log}
    out, sign = [], 1.0
    last = max(by_step) if by_step else 0
    for start in range(1, last + 1, w):
        rs = [by_step[s] for s in range(start, start + w) if s in by_step and "diag_sign_delta" in by_step[s]]
        if not rs:
            break
        d = [r["diag_sign_delta"] for r in rs]
        nxt = by_step.get(start + w, {}).get("diag_translation_sign", sign)
        flag = "  FLIP" if nxt != sign else ""
        out.append(f"steps {start:3d}-{start + w - 1:3d}: sum {sum(d):+.5f}, negated lower on {sum(x > 0 for x in d)}"
                   f"/{len(d)}, sign after {nxt:+.0f}{flag}")
        sign = nxt
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("runs", nargs="+", type=Path)
    p.add_argument("--window", type=int, default=10, help="the run's pose_sign_test_window")
    a = p.parse_args(argv)
    if a.window < 1:
        raise SystemExit("df_sign_test_log: --window must be >= 1")
    for d in a.runs:
        f = d / "log.jsonl" if (d / "log.jsonl").is_file() else d / ".staging" / "log.jsonl"
        if not f.is_file():
            raise SystemExit(f"df_sign_test_log: no log.jsonl in {d}")
        log = [json.loads(line) for line in f.read_text().splitlines() if line.strip()]
        print(f"{d}:")
        for line in windows(log, a.window):
            print("  " + line)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
