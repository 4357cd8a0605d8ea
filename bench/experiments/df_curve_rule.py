"""A DrivingForward validation-curve rule, paired by seed (issue 32): arm B's runs against arm A's.

No figure: the table a rule written before its runs asks for. Each run folder holds
``val_curve.jsonl`` (:class:`~clsplat.models.drivingforward.training.ValCurve`: AbsRel, δ1 and the
scale ratio of the validation windows every few steps); per seed, the mean AbsRel over the points
at ``--steps LO HI`` (inclusive) of arm B minus that of arm A, then the mean over seeds, against the
rule's two bounds: adopt only if the mean falls by at least ``--min-gain`` and no seed rises by more
than ``--max-rise``.

    python bench/experiments/df_curve_rule.py --a A_s0 A_s1 A_s2 --b B_s0 B_s1 B_s2 --steps 500 600 \
        [--min-gain 0.02 --max-rise 0.01] [--json OUT]

Runs are paired in the order given (seed 0 with seed 0, ...).
"""
from __future__ import annotations

import argparse
import json
import statistics
from pathlib import Path


def curve_mean(run: Path, lo: int, hi: int, key: str) -> tuple[float, int]:
    """Mean of ``key`` over the curve's points with lo <= step <= hi (the last point per step)."""
    points = {}
    for line in (run / "val_curve.jsonl").read_text().splitlines():
        if line.strip():
            p = json.loads(line)
            points[int(p["step"])] = p
    vals = [p[key] for s, p in sorted(points.items()) if lo <= s <= hi]
    if not vals:
        raise SystemExit(f"{run}: no validation point between steps {lo} and {hi}")
    return statistics.fmean(vals), len(vals)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--a", nargs="+", type=Path, required=True, help="arm A's run folders, one per seed")
    ap.add_argument("--b", nargs="+", type=Path, required=True, help="arm B's, in the same seed order")
    ap.add_argument("--steps", nargs=2, type=int, default=(500, 600), metavar=("LO", "HI"))
    ap.add_argument("--min-gain", type=float, default=0.02)
    ap.add_argument("--max-rise", type=float, default=0.01)
    ap.add_argument("--json", type=Path)
    a = ap.parse_args()
    if len(a.a) != len(a.b):
        raise SystemExit("--a, --b: one run per seed in each arm (as many in both)")
    rows = []
    print("| seed | A AbsRel | B AbsRel | B − A | A δ1 | B δ1 | A scale | B scale | points |")
    print("|---|---|---|---|---|---|---|---|---|")
    for i, (ra, rb) in enumerate(zip(a.a, a.b)):
        (am, n), (bm, _) = curve_mean(ra, *a.steps, "abs_rel"), curve_mean(rb, *a.steps, "abs_rel")
        ad, bd = curve_mean(ra, *a.steps, "delta1")[0], curve_mean(rb, *a.steps, "delta1")[0]
        asc, bsc = curve_mean(ra, *a.steps, "scale_ratio")[0], curve_mean(rb, *a.steps, "scale_ratio")[0]
        rows.append({"a": str(ra), "b": str(rb), "a_abs_rel": am, "b_abs_rel": bm, "diff": bm - am,
                     "a_delta1": ad, "b_delta1": bd, "a_scale": asc, "b_scale": bsc, "points": n})
        print(f"| {i} | {am:.4f} | {bm:.4f} | {bm - am:+.4f} | {ad:.3f} | {bd:.3f} | {asc:.3f} | {bsc:.3f} | {n} |")
    mean = statistics.fmean(r["diff"] for r in rows)
    worst = max(r["diff"] for r in rows)
    adopt = mean <= -a.min_gain and worst <= a.max_rise
    print(f"\nmean B − A {mean:+.4f} (adopt needs <= {-a.min_gain:+.4f}), largest seed rise {worst:+.4f} "
          f"(<= {a.max_rise:+.4f}): **{'adopt' if adopt else 'not adopted'}**")
    if a.json:
        a.json.write_text(json.dumps({"steps": list(a.steps), "rows": rows, "mean_diff": mean,
                                      "largest_rise": worst, "adopt": adopt}, indent=1) + "\n")


if __name__ == "__main__":
    main()
