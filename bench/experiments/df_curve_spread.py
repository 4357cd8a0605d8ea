"""How much a DrivingForward run's validation figures move between consecutive snapshots (issue 32):
per run, over the curve points of the last ``--span`` steps (``val_curve.jsonl``), the mean, standard
deviation, least and largest AbsRel and the scale ratio's range. A run reported by its last snapshot
alone carries that spread.

    .venv/bin/python bench/experiments/df_curve_spread.py RUN [RUN ...] [--span 100]
"""
from __future__ import annotations

import argparse
import json
import statistics
from pathlib import Path


def spread(run: Path, span: int) -> dict:
    """Mean, sd, min and max AbsRel and the scale's range over the points within ``span`` steps of the last."""
    points = {}
    for line in (run / "val_curve.jsonl").read_text().splitlines():
        if line.strip():
            p = json.loads(line)
            points[int(p["step"])] = p
    if not points:
        raise ValueError("no curve points")
    last = max(points)
    window = [points[s] for s in sorted(points) if s >= last - span]
    a = [p["abs_rel"] for p in window]
    s = [p["scale_ratio"] for p in window]
    return {"last": last, "n": len(a), "mean": statistics.mean(a), "sd": statistics.stdev(a) if len(a) > 1 else 0.0,
            "min": min(a), "max": max(a), "scale_min": min(s), "scale_max": max(s)}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("runs", nargs="+", type=Path)
    p.add_argument("--span", type=int, default=100, help="steps before the last point (default 100)")
    a = p.parse_args(argv)
    if a.span < 0:
        p.error(f"--span: expected steps >= 0, got {a.span}")
    print("| run | last step | points | AbsRel mean | sd | min | max | scale |")
    print("|---|---|---|---|---|---|---|---|")
    for run in a.runs:
        try:
            r = spread(run, a.span)
        except (OSError, ValueError, KeyError) as e:
            p.error(f"runs: {run} has no readable val_curve.jsonl with points ({e})")
        print(f"| {run.name} | {r['last']} | {r['n']} | {r['mean']:.3f} | {r['sd']:.3f} | {r['min']:.3f} | "
              f"{r['max']:.3f} | {r['scale_min']:.2f}-{r['scale_max']:.2f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
