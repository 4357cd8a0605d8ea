"""DrivingForward against its controls: a markdown table from the ``metrics.json`` of runs (issue 32).

For each run folder given (``NAME=DIR``; DIR holds ``metrics.json`` and ``val_curve.jsonl``) it
prints, per row, the model's depth (AbsRel, delta<1.25, scale ratio), the image-blind layout
baseline on the same pixels, the pose network's median translation error and the constant-motion
control's (the training split's mean motion), overall and per ego-speed bin; and the validation
learning curve's first and last points. Percentages of a standing ego's motion are undefined, so
the ``standing`` bin reports metres.

    .venv/bin/python bench/experiments/df_controls_table.py small=runs/df_s0 "pose dataset=runs/df_pd_s0" \
        --curves-png bench/figures/df_varied_val_curves.png

With ``--curves-png`` it also draws every run's validation curve (AbsRel, scale ratio, pose
translation error in metres) in one figure.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path


def _f(v, fmt: str = ".3f") -> str:
    return "–" if v is None else format(v, fmt)


def rows(name: str, folder: Path) -> list[str]:
    """Table rows of one run: ``all`` and each non-empty speed bin (none while it has no metrics.json)."""
    if not (folder / "metrics.json").is_file():
        return []
    m = json.loads((folder / "metrics.json").read_text())
    out = []
    blocks = [("all", m["all"])] + [(k, b) for k, b in m.get("speed_bins", {}).items() if b.get("windows")]
    for label, b in blocks:
        moving = label != "standing"
        pose = _f(b.get("pose_t_err_pct_median"), ".1f") + " %" if moving else _f(b.get("pose_t_err_m_median")) + " m"
        const = (_f(b.get("constant_motion_t_err_pct_median"), ".1f") + " %" if moving
                 else _f(b.get("constant_motion_t_err_m_median")) + " m")
        if b.get("pose_t_err_m") is None:
            pose = "given"
        out.append(f"| {name} | {m['protocol']['split']} | {label} | {b.get('windows', '')} | {_f(b.get('abs_rel'))} | "
                   f"{_f(b.get('layout_abs_rel'))} | {_f(b.get('delta1'))} | {_f(b.get('layout_delta1'))} | "
                   f"{_f(b.get('scale_ratio'))} | {pose} | {const} | {_f(b.get('psnr'), '.2f')} |")
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("runs", nargs="+", help="NAME=DIR of a finished run")
    p.add_argument("--curves-png", default=None, help="draw the runs' validation curves into this PNG")
    a = p.parse_args(argv)
    print("| run | split | ego speed (m/s) | windows | AbsRel | layout AbsRel | δ1 | layout δ1 | scale | "
          "pose t err (median) | constant motion | PSNR +1 |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    curves = []
    for spec in a.runs:
        name, _, folder = spec.partition("=")
        d = Path(folder)
        table = rows(name, d)
        if table:
            print("\n".join(table))
        vc = d / "val_curve.jsonl"
        if vc.is_file():
            pts = [json.loads(x) for x in vc.read_text().splitlines()]
            first, last = pts[0], pts[-1]
            curves.append(f"- {name}: validation curve, step {first['step']} -> {last['step']}: AbsRel "
                          f"{_f(first.get('abs_rel'))} -> {_f(last.get('abs_rel'))}, scale "
                          f"{_f(first.get('scale_ratio'))} -> {_f(last.get('scale_ratio'))}, pose t error "
                          f"{_f(first.get('pose_t_err_m'))} -> {_f(last.get('pose_t_err_m'))} m "
                          f"(predicted {_f(first.get('pose_t_pred_m'))} -> {_f(last.get('pose_t_pred_m'))} m, "
                          f"true {_f(last.get('pose_t_true_m'))} m)")
    if curves:
        print()
        print("\n".join(curves))
    if a.curves_png:
        plot_curves([spec.partition("=")[::2] for spec in a.runs], a.curves_png)
    return 0


def plot_curves(runs: list[tuple[str, str]], png: str) -> None:
    """Every run's ``val_curve.jsonl`` in three panels against step."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from clsplat.bench.figure import save_figure
    fig, axes = plt.subplots(1, 3, figsize=(12, 3.4), dpi=110)
    panels = (("abs_rel", "depth AbsRel"), ("scale_ratio", "scale ratio (median gt / median pred)"),
              ("pose_t_err_m", "pose translation error (m, mean)"))
    for k, (name, folder) in enumerate(runs):
        vc = Path(folder) / "val_curve.jsonl"
        if not vc.is_file():
            continue
        pts = [json.loads(x) for x in vc.read_text().splitlines()]
        for ax, (key, _) in zip(axes, panels):
            xy = [(r["step"], r[key]) for r in pts if isinstance(r.get(key), (int, float))]
            if xy:
                ax.plot(*zip(*xy), marker=".", label=name, color=f"C{k}")   # one colour per run in every panel
    for ax, (_, title) in zip(axes, panels):
        ax.set_title(title, fontsize=9)
        ax.set_xlabel("step")
        ax.grid(alpha=0.3)
    handles = [plt.Line2D([], [], color=f"C{k}", marker=".", label=name) for k, (name, _) in enumerate(runs)]
    axes[0].legend(handles=handles, fontsize=7)
    save_figure(fig, png)


if __name__ == "__main__":
    raise SystemExit(main())
