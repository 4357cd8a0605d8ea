"""The markdown rows of DrivingForward runs' ``metrics.json`` with their controls beside them (issue
32): pose translation error (median, %; standing windows in metres) against the constant-motion
control, depth AbsRel / δ1 / scale ratio against the layout (image-blind) baseline, overall and per
ego-speed bin; and, with ``--stream``, the training stream of each run (the pose network's
prediction on each step's training window before its update, ``diag_translation`` in
``log.jsonl``) against the true motion in 50-step blocks.

    .venv/bin/python bench/experiments/df_val_table.py RUN_DIR [RUN_DIR ...] [--stream --data SPEC]

A run folder's ``metrics.json`` (written at the end of ``clsplat train drivingforward``) and its
``log.jsonl`` are read; ``--stream`` loads the training windows' true motion from ``--data``
(default the varied world; the cache used for the runs gives the same windows) at the run's seed.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

BINS = ("all", "standing", "0.5-5", "5-10", "10-15")


def _row(name: str, block: dict, bin_name: str) -> str:
    def f(k: str, fmt: str = "{:.3f}") -> str:
        v = block.get(k)
        return fmt.format(v) if isinstance(v, (int, float)) else "–"
    if bin_name == "standing":
        pose, const = f("pose_t_err_m_median", "{:.3f} m"), f("constant_motion_t_err_m_median", "{:.3f} m")
    else:
        pose, const = f("pose_t_err_pct_median", "{:.1f} %"), f("constant_motion_t_err_pct_median", "{:.1f} %")
    n = len(block.get("windows", [])) if isinstance(block.get("windows"), list) else block.get("windows", "–")
    return (f"| {name} | {bin_name} | {n} | {pose} | {const} | {f('abs_rel')} | {f('layout_abs_rel')} | "
            f"{f('delta1')} | {f('layout_delta1')} | {f('scale_ratio')} |")


def table(runs: list[Path], bins: bool) -> str:
    out = ["| run | bin | windows | pose t err (median) | constant motion | AbsRel | layout AbsRel | δ1 | layout δ1 | scale |",
           "|---|---|---|---|---|---|---|---|---|---|"]
    for d in runs:
        m = json.loads((d / "metrics.json").read_text())
        out.append(_row(f"{d.name} @{m.get('step')}", m["all"], "all"))
        if bins:
            for b in BINS[1:]:
                blk = m.get("speed_bins", {}).get(b, {})
                if blk.get("windows"):                          # a bin without windows: no row
                    out.append(_row(f"{d.name} @{m.get('step')}", blk, b))
    return "\n".join(out)


def stream(run: Path, data: str, seed: int, block: int = 50) -> list[str]:
    """Per ``block`` steps: corr(pred, true) of the camera-0 translation norm, mean predicted / true,
    the median relative error on moving windows (true > 0.05 m), the mean prediction on standing ones."""
    import numpy as np
    import torch

    from clsplat.models.common.data import parse_data
    from clsplat.models.common.presets import get_preset
    from clsplat.models.drivingforward.data import gt_ego_motion, load_triplet

    preset = get_preset("drivingforward", "small")
    src = parse_data(data, seed=seed, default_world="varied")
    logs = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines() if line.strip()]
    out = []
    for a in range(0, len(logs), block):
        seg = [r for r in logs[a:a + block] if "diag_translation" in r]
        if len(seg) < 5:
            continue
        true = []
        for r in seg:       # step s (from 1) trains on window s - 1 of the train split (batch 1)
            s = load_triplet(src, r["step"] - 1, preset, "train")
            E0 = s["cam_to_ego"][0].double()
            T0 = torch.linalg.inv(E0) @ gt_ego_motion(s)[2].double() @ E0
            true.append(float(T0[:3, 3].norm()))
        p, t = np.array([r["diag_translation"] for r in seg]), np.array(true)
        mv = t > 0.05
        out.append(f"steps {seg[0]['step']}-{seg[-1]['step']}: corr {np.corrcoef(p, t)[0, 1]:+.2f}, pred/true mean "
                   f"{p.mean():.2f}/{t.mean():.2f} m, moving err median {np.median(np.abs(p[mv] - t[mv]) / t[mv]) * 100:.0f} %, "
                   f"standing pred {p[~mv].mean() if (~mv).any() else float('nan'):.2f} m, depth median "
                   f"{np.mean([r['diag_depth_median'] for r in seg]):.1f} m")
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("runs", nargs="+", type=Path, help="run folders (each with metrics.json)")
    p.add_argument("--bins", action="store_true", help="a row per ego-speed bin as well")
    p.add_argument("--stream", action="store_true", help="the training stream against the true motion")
    p.add_argument("--data", default="synthetic-cache:/work/cache/df")
    p.add_argument("--seed", type=int, nargs="*", default=None, help="each run's --seed (default 0 for all)")
    a = p.parse_args(argv)
    for d in a.runs:
        if not (d / "metrics.json").is_file():
            raise SystemExit(f"df_val_table: {d}: no metrics.json")
    print(table(a.runs, a.bins))
    if a.stream:
        seeds = a.seed or [0] * len(a.runs)
        for d, s in zip(a.runs, seeds):
            print(f"\n{d.name} (seed {s}):")
            for line in stream(d, a.data, s):
                print("  " + line)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
