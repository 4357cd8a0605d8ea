"""DrivingForward issue-17 ablation: a table of held-out metrics and one figure of learning curves
over several run folders written by ``clsplat train drivingforward`` (``bench/notes/drivingforward_training.md``,
"DrivingForward learns from random initialisation (issue 17)").

Each run folder holds ``log.jsonl`` and ``metrics.json`` (the training command's ``--eval-scenes``
evaluation). The table has, per run: steps, the training median depth over the last 20 logged
steps and its minimum/maximum after step 20 (a collapse shows as a median at the far limit, 122 m
on the synthetic rig), the pose network's t -> t+1 translation (0.8 m true), and the held-out
scale ratio, AbsRel, delta<1.25, pose errors, PSNR at frame +1 and the oracle-depth PSNR. The figure
plots, per run, the median depth, the translation, the total loss and the spatial loss against
the step (running mean of 10).

    .venv/bin/python bench/experiments/df_ablation.py bench/out/i17/r1_tinit bench/out/i17/r2_tinit_ss3 \\
        --figure bench/figures/df_issue17_curves.png
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path


def _log(run: Path) -> list[dict]:
    return [json.loads(x) for x in (run / "log.jsonl").read_text().splitlines() if x.strip()]


def row(run: Path) -> dict:
    """Summary of one run folder (see the module docstring)."""
    log = _log(run)
    med = [r["diag_depth_median"] for r in log]
    tr = [r["diag_translation"] for r in log]
    late = med[20:] or med
    out = {"run": run.name, "steps": log[-1]["step"] if log else 0,
           "depth_median_last20": sorted(med[-20:])[len(med[-20:]) // 2] if med else float("nan"),
           "depth_median_min": min(late) if late else float("nan"),
           "depth_median_max": max(late) if late else float("nan"),
           "translation_last20": sum(tr[-20:]) / max(1, len(tr[-20:]))}
    m = run / "metrics.json"
    if m.is_file():
        a = json.loads(m.read_text())["all"]
        for k in ("scale_ratio", "abs_rel", "delta1", "pose_t_err_m", "pose_t_err_pct", "pose_r_err_deg",
                  "psnr", "oracle_psnr"):
            out[k] = a.get(k)
    return out


def table(rows: list[dict]) -> str:
    cols = ["run", "steps", "depth_median_last20", "depth_median_min", "depth_median_max", "translation_last20",
            "scale_ratio", "abs_rel", "delta1", "pose_t_err_m", "pose_t_err_pct", "pose_r_err_deg", "psnr",
            "oracle_psnr"]
    fmt = lambda v: "-" if v is None else (f"{v:.3g}" if isinstance(v, float) else str(v))  # noqa: E731
    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    lines += ["| " + " | ".join(fmt(r.get(c)) for c in cols) + " |" for r in rows]
    return "\n".join(lines)


def figure(runs: list[Path], png: Path, window: int = 10) -> None:
    """Median depth, translation, loss and spatial loss against the step, one line per run."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from clsplat.bench.figure import save_figure

    keys = [("diag_depth_median", "training median depth (m)"), ("diag_translation", "pose t->t+1 translation (m)"),
            ("loss", "total loss"), ("spatial", "spatial loss")]
    fig, axes = plt.subplots(2, 2, figsize=(12, 7))
    for run in runs:
        log = _log(run)
        steps = np.array([r["step"] for r in log])
        for ax, (k, title) in zip(axes.ravel(), keys):
            y = np.array([r.get(k, np.nan) for r in log], dtype=float)
            if len(y) >= window:
                ax.plot(steps[window - 1:], np.convolve(y, np.ones(window) / window, "valid"), label=run.name)
            else:
                ax.plot(steps, y, label=run.name)
            ax.set_title(title)
            ax.set_xlabel("step")
    axes[0, 0].set_yscale("log")
    axes[0, 0].legend(fontsize=7)
    fig.suptitle(f"DrivingForward small, random initialisation (running mean of {window})")
    save_figure(fig, png, dpi=100)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("runs", nargs="+", help="run folders (log.jsonl, metrics.json)")
    p.add_argument("--figure", default=None, help="learning-curve PNG")
    a = p.parse_args(argv)
    runs = [Path(r) for r in a.runs]
    missing = [str(r) for r in runs if not (r / "log.jsonl").is_file()]
    if missing:
        p.error(f"runs: no log.jsonl in {missing}")
    print(table([row(r) for r in runs]))
    if a.figure:
        figure(runs, Path(a.figure))
        print(f"wrote {a.figure}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
