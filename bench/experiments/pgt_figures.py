"""PGT benchmark figures and tables from a finished ``bench/experiments/pgt_run.sh`` run folder.

Reads RUN/base/log.jsonl, RUN/budget/log.jsonl, RUN/eval/{budget.json,metrics.json} and
RUN/speed/pgt_speed.json and RUN/matching/pgt_matching.json (whichever exist) and writes:

* ``FIG/pgt_curves.png``: training curves of both stages (running mean over ``--window`` steps):
  base loss, render and depth terms; budget-stage render and L_io terms with the sampled κ;
* ``FIG/pgt_budget.png``: a copy of the evaluation's budget curve (PSNR against count and render
  time, Pareto front);
* markdown tables on stdout (budget curve, depth, speed, matchers) for the PGT section of bench/notes/pgt_ecosplat.md.

Run: ``python bench/experiments/pgt_figures.py bench/out/pgt --figures bench/figures``.
"""
from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

import numpy as np


def running_mean(values: list[float], window: int) -> np.ndarray:
    """Mean over the last ``window`` values at each index (fewer at the start)."""
    v = np.asarray(values, dtype=np.float64)
    c = np.concatenate([[0.0], np.cumsum(v)])
    i = np.arange(1, len(v) + 1)
    lo = np.maximum(i - window, 0)
    return (c[i] - c[lo]) / (i - lo)


def plot_curves(run: Path, png: Path, window: int) -> Path | None:
    """Both stages' curves side by side; None when neither log exists."""
    from clsplat.models.common.train import read_log
    logs = {stage: read_log(run / stage / "log.jsonl") for stage in ("base", "budget")
            if (run / stage / "log.jsonl").is_file()}
    if not logs:
        return None
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from clsplat.bench.figure import save_figure
    fig, axes = plt.subplots(1, 2, figsize=(12, 4), dpi=110)
    panels = {"base": ("loss", "render", "depth", "chamfer"), "budget": ("loss", "render", "io")}
    for ax, stage in zip(axes, ("base", "budget")):
        recs = logs.get(stage, [])
        for key in panels[stage]:
            pts = [(r["step"], r[key]) for r in recs if isinstance(r.get(key), (int, float))]
            if pts:
                s, v = zip(*pts)
                ax.plot(s, running_mean(list(v), window), label=f"{key} (mean of {window})")
        ax.set_yscale("log")
        ax.set_xlabel("step")
        ax.set_title(f"{stage} stage" + ("" if recs else " (no log)"))
        ax.grid(alpha=0.3)
        if stage == "budget" and recs and "kappa" in recs[0]:
            k = ax.twinx()
            k.plot([r["step"] for r in recs], [r["kappa"] for r in recs], ".", ms=1.5, color="grey", alpha=0.5)
            k.set_ylabel("sampled κ")
            k.set_ylim(0, 1)
        ax.legend(fontsize=7, loc="upper right")
    fig.suptitle(f"PGT training curves ({run})")
    save_figure(fig, png)
    return png


def budget_table(rows: list[dict]) -> str:
    """Markdown: one line per κ, PSNR / SSIM / render ms / count of each method side by side."""
    methods = [m for m in ("finetuned", "opacity", "random") if any(r["method"] == m for r in rows)]
    head = "| κ | Gaussians | " + " | ".join(f"{m} PSNR / SSIM / ms" for m in methods) + " |"
    lines = [head, "|" + "---|" * (2 + len(methods))]
    by = {(r["method"], r["budget"]): r for r in rows}
    for k in sorted({r["budget"] for r in rows}, reverse=True):
        n = next(by[(m, k)]["n_gaussians"] for m in methods if (m, k) in by)
        cells = [f"{by[(m, k)]['psnr']:.2f} / {by[(m, k)]['ssim']:.3f} / {by[(m, k)]['render_ms']:.1f}"
                 if (m, k) in by else "-" for m in methods]
        lines.append(f"| {k:g} | {n:.0f} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("run", help="the OUT folder of bench/experiments/pgt_run.sh")
    p.add_argument("--figures", default="bench/figures")
    p.add_argument("--window", type=int, default=50, help="running-mean window (steps)")
    args = p.parse_args()
    run, fig = Path(args.run), Path(args.figures)
    png = plot_curves(run, fig / "pgt_curves.png", args.window)
    print(f"curves: {png}")
    ev = run / "eval"
    if (ev / "budget.png").is_file():
        shutil.copyfile(ev / "budget.png", fig / "pgt_budget.png")
        print(f"budget curve: {fig / 'pgt_budget.png'}")
    if (ev / "budget.json").is_file():
        print(budget_table(json.loads((ev / "budget.json").read_text())))
    if (ev / "metrics.json").is_file():
        m = json.loads((ev / "metrics.json").read_text())
        a = m["all"]
        print(f"\nfull set (step {m.get('step')}, {m['protocol']['scenes']} held-out samples): PSNR {a['psnr']:.2f}, "
              f"SSIM {a['ssim']:.3f}, render {m['render_ms']:.1f} ms, prediction {m['seconds_per_prediction']:.3f} s")
        print("| depth | AbsRel | SqRel | RMSE (m) | δ<1.25 |\n|---|---|---|---|---|")
        for name, key in (("coarse D₀ (no residual head)", "depth_without_residual"),
                          ("D₀ + 0.5·tanh(r) (residual head)", "depth_with_residual")):
            d = m["all"] if key == "depth_with_residual" else m[key]
            print(f"| {name} | {d['abs_rel']:.3f} | {d['sq_rel']:.3f} | {d['rmse']:.2f} | {d['delta1']:.3f} |")
    sp = run / "speed" / "pgt_speed.json"
    if sp.is_file():
        print("\n| preset | matching | H x W | parameters | s / step | s / prediction |\n|---|---|---|---|---|---|")
        for r in json.loads(sp.read_text()):
            print(f"| {r['preset']} | {r['matching']} | {r['height']} x {r['width']} | {r['parameters']:,} | "
                  f"{r['step_s']:.3f} | {r['prediction_s']:.3f} |")
    mt = run / "matching" / "pgt_matching.json"
    if mt.is_file():
        print("\n| matcher | steps | parameters | s / step | s / prediction | AbsRel D₀ | AbsRel D | δ<1.25 D₀ "
              "| PSNR | SSIM |\n|---|---|---|---|---|---|---|---|---|---|")
        for r in json.loads(mt.read_text()):
            print(f"| {r['matching']} | {r['steps']} | {r['parameters']:,} | {r['step_s']:.2f} | "
                  f"{r['prediction_s']:.3f} | {r['abs_rel_coarse']:.3f} | {r['abs_rel_refined']:.3f} | "
                  f"{r['delta1_coarse']:.3f} | {r['psnr']:.2f} | {r['ssim']:.3f} |")


if __name__ == "__main__":
    main()
