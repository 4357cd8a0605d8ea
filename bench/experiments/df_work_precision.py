"""DrivingForward's work-precision figure: held-out depth error against the training budget.

    .venv/bin/python bench/experiments/df_work_precision.py \\
        --run "given motion, seed 0=bench/figures/df_varied/i32d_cap10ws001_s0_300" ... \\
        --step-seconds 2.24 --out bench/figures/df_work_precision.png

Each ``--run LABEL=DIR`` is one finished training run (its ``metrics.json``: the evaluation
after the run's last step); runs with the same label form one line, ordered by their step count
(a longer run of the same recipe, resumed from the shorter one's folder, is the next point).
The y axis is depth AbsRel divided by the image-blind layout baseline's AbsRel **on the same
pixels** (``all.layout_abs_rel``: the per-pixel median training depth), so 1.0 is a model that
learned nothing from the image and the issue 32 target is 0.7. The x axis is training steps; the
top axis converts them to CPU hours at ``--step-seconds`` (a measured CPU time per step, given
on the command line with where it was measured, not computed here). A JSON table of every point
is written beside the figure.
"""
from __future__ import annotations

import argparse
import json
from collections import defaultdict
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

#: the issue 32 target, AbsRel at most this share of the layout baseline's
TARGET_RATIO = 0.7


def read_point(run: Path) -> dict:
    """One run's point: steps, split, pose source, AbsRel, layout AbsRel, ratio, delta1, scale."""
    m = json.loads((run / "metrics.json").read_text())
    a, p = m["all"], m["protocol"]
    return {"run": str(run), "steps": int(m["step"]), "split": p.get("split"),
            "pose_source": p.get("pose_source"), "abs_rel": a["abs_rel"],
            "layout_abs_rel": a["layout_abs_rel"], "ratio": a["abs_rel"] / a["layout_abs_rel"],
            "delta1": a["delta1"], "scale_ratio": a["scale_ratio"]}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--run", action="append", required=True, metavar="LABEL=DIR",
                    help="a finished run folder and its line's label (repeat)")
    ap.add_argument("--step-seconds", type=float, required=True,
                    help="measured CPU seconds per training step, for the top axis")
    ap.add_argument("--ymax", type=float, default=2.0, help="clip the y axis (a collapsed run goes off it)")
    ap.add_argument("--out", type=Path, required=True, help="the PNG; the table goes to OUT.json")
    a = ap.parse_args(argv)
    if a.step_seconds <= 0:
        ap.error("--step-seconds: must be > 0")
    lines: dict[str, list[dict]] = defaultdict(list)
    for spec in a.run:
        label, sep, folder = spec.rpartition("=")
        if not sep or not label:
            ap.error(f"--run: expected LABEL=DIR, got {spec!r}")
        if not (Path(folder) / "metrics.json").is_file():
            ap.error(f"--run: {folder} has no metrics.json")
        lines[label].append(read_point(Path(folder)))
    fig, ax = plt.subplots(figsize=(7.5, 4.2))
    for label, pts in lines.items():
        pts.sort(key=lambda q: q["steps"])
        ys = [min(q["ratio"], a.ymax) for q in pts]
        ax.plot([q["steps"] for q in pts], ys, marker="o", label=label)
        for q, y in zip(pts, ys):
            if q["ratio"] > a.ymax:
                ax.annotate(f"{q['ratio']:.0f}x", (q["steps"], y), textcoords="offset points",
                            xytext=(4, -10), fontsize=7)
    ax.axhline(1.0, color="k", lw=0.8, ls="--")
    ax.text(ax.get_xlim()[0], 1.01, " layout baseline (image-blind)", fontsize=7, va="bottom")
    ax.axhline(TARGET_RATIO, color="tab:red", lw=0.8, ls=":")
    ax.text(ax.get_xlim()[0], TARGET_RATIO + 0.01, " target 0.7", fontsize=7, va="bottom", color="tab:red")
    ax.set_xlabel("training steps")
    ax.set_ylabel("depth AbsRel / layout's AbsRel (same pixels)")
    ax.set_ylim(0.5, a.ymax * 1.02)
    top = ax.secondary_xaxis("top", functions=(lambda s: s * a.step_seconds / 3600,
                                               lambda h: h * 3600 / a.step_seconds))
    top.set_xlabel(f"CPU hours at {a.step_seconds:g} s a step")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="upper right")
    fig.tight_layout()
    a.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(a.out, dpi=130)
    table = {label: pts for label, pts in lines.items()}
    a.out.with_suffix(".json").write_text(json.dumps({"step_seconds": a.step_seconds, "lines": table},
                                                     indent=1) + "\n")
    for label, pts in lines.items():
        print(label + ": " + ", ".join(f"{q['steps']} steps {q['ratio']:.3f}x (AbsRel {q['abs_rel']:.3f})"
                                       for q in pts))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
