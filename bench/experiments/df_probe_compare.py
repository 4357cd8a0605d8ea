"""Two ``df_geometric_pose_probe.py --json`` files of the same windows side by side (issue 32): per
speed bin the median and largest translation error, the windows over 10 % and the rotation tail,
then the windows that cross 10 % (or 0.5 degrees) from one file to the other.

    .venv/bin/python bench/experiments/df_probe_compare.py A.json B.json
"""
from __future__ import annotations

import argparse
import json

from pathlib import Path

import numpy as np

from clsplat.data.synthetic import SPEED_BINS, speed_bin


def _crosses(x: dict, y: dict) -> bool:
    return (y["t_err_pct"] > 10) != (x["t_err_pct"] > 10) or (y["r_err_deg"] > 0.5) != (x["r_err_deg"] > 0.5)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("a", type=Path)
    p.add_argument("b", type=Path)
    args = p.parse_args(argv)
    try:
        a, b = (json.loads(f.read_text())["windows"] for f in (args.a, args.b))
    except (OSError, ValueError, KeyError, TypeError) as e:
        p.error(f"a / b: expected two df_geometric_pose_probe.py --json files ({e})")
    if [w["window"] for w in a] != [w["window"] for w in b]:
        p.error("the two files hold different windows")
    rows: dict[str, list] = {}
    for x, y in zip(a, b):
        rows.setdefault(speed_bin(x["speed"]), []).append((x, y))
    for k in SPEED_BINS:
        r = rows.get(k, [])
        if not r:
            continue
        if k == "standing":
            print(f"{k} n {len(r)}: mean error A {np.mean([x['t_err_m'] for x, _ in r]):.4f} m, "
                  f"B {np.mean([y['t_err_m'] for _, y in r]):.4f} m")
            continue
        e = [[w["t_err_pct"] for w in pair] for pair in r]
        rot = [[w["r_err_deg"] for w in pair] for pair in r]
        ea, eb = np.array(e).T
        ra, rb = np.array(rot).T
        print(f"{k} n {len(r)}: median A {np.median(ea):.2f} % B {np.median(eb):.2f} % | max A {ea.max():.1f} "
              f"B {eb.max():.1f} | > 10 %: A {(ea > 10).sum()} B {(eb > 10).sum()} | rotation max A {ra.max():.2f} "
              f"B {rb.max():.2f} deg (> 0.5: {(ra > 0.5).sum()} / {(rb > 0.5).sum()})")
    cross = [(x["window"], round(x["t_err_pct"], 1), round(y["t_err_pct"], 1)) for x, y in zip(a, b)
             if x["t_err_pct"] is not None and y["t_err_pct"] is not None and _crosses(x, y)]
    print("windows crossing 10 % or 0.5 deg (window, A %, B %):", cross)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
