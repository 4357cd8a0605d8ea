"""AutoSplat's work-precision picture (issue 19, item 6): held-out PSNR against training time and
against Gaussian count, one curve per run (e.g. the ``demo`` and ``small`` presets and plain 3DGS),
from checkpoints the runs left behind.

Each run folder ``RUN`` has its ``log.jsonl`` (per-step wall time and Gaussian count) and a
folder ``RUN.cks`` of checkpoints taken during training (``ck_<step>.pt``, e.g. hard links made
as the run wrote them). ``--eval`` scores every checkpoint not yet scored on the held-out frames
(``clsplat eval autosplat --checkpoint ck --views recorded --out RUN.cks/eval_<step>``); the final
point of a finished run is its own ``metrics.json``. Training time at a step is the sum of the
logged step times up to it (the loop's own seconds; load, initialisation and evaluation not
counted). Writes the figure and a JSON table of the points.

    .venv/bin/python bench/experiments/autosplat_work_precision.py --eval --data pandaset:DIR --scale 1 \\
        --run demo=bench/out/as_demo --run small=bench/out/as_small --run "plain 3DGS (demo)=bench/out/as_plain" \\
        --out bench/figures/autosplat_work_precision.png
"""
from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
from pathlib import Path


def _log(run: Path) -> list[dict]:
    for p in (run / "log.jsonl", run / ".staging" / "log.jsonl"):
        if p.is_file():
            return [json.loads(line) for line in p.read_text().splitlines() if line.strip()]
    raise FileNotFoundError(f"{run}: no log.jsonl")


def points(run: Path, evaluate: bool, data: str | None = None, scale: float | None = None) -> list[dict]:
    """One point per scored checkpoint of ``run``: step, train seconds, Gaussians, held-out PSNR/SSIM."""
    log = _log(run)
    cum, t = {}, 0.0
    count = {}
    for r in log:
        t += r["time_s"]
        cum[r["step"]] = t
        count[r["step"]] = r.get("gaussians")
    cks = run.with_name(run.name + ".cks")
    scored = []
    for ck in sorted(cks.glob("ck_*.pt"), key=lambda p: int(re.findall(r"\d+", p.name)[0])) if cks.is_dir() else []:
        out = cks / ("eval_" + ck.stem[3:])
        if not (out / "metrics.json").is_file() and evaluate:
            subprocess.run([str(Path(sys.executable).with_name("clsplat")), "eval", "autosplat", "--checkpoint",
                            str(ck), "--views", "recorded", "--out", str(out), *(["--data", data] if data else []),
                            *(["--scale", str(scale)] if scale else [])],
                           check=True,
                           env={**os.environ, "POCL_MAX_WORK_GROUP_SIZE": os.environ.get("POCL_MAX_WORK_GROUP_SIZE", "256")})
        if (out / "metrics.json").is_file():
            scored.append(json.loads((out / "metrics.json").read_text()))
    if (run / "metrics.json").is_file():
        scored.append(json.loads((run / "metrics.json").read_text()))
    pts = {}
    for m in scored:
        s = int(m["step"])
        last = max(k for k in cum if k < s) if any(k < s for k in cum) else None
        if last is None:
            continue
        pts[s] = {"step": s, "train_s": cum[last], "gaussians": m.get("gaussians", {}).get("total", count[last]),
                  "psnr": m["all"]["psnr"], "ssim": m["all"]["ssim"]}
    return [pts[k] for k in sorted(pts)]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--run", action="append", required=True, metavar="LABEL=RUN", help="a curve: label and run folder")
    p.add_argument("--eval", action="store_true", help="score the checkpoints not yet scored")
    p.add_argument("--scale", type=float, default=None, help="the runs' image scale (checkpoints taken "
                   "during training have no metrics.json recording it)")
    p.add_argument("--data", default=None, help="the runs' --data (a checkpoint outside its run folder needs it)")
    p.add_argument("--out", required=True, help="figure path (.png); the points go beside it as .json")
    a = p.parse_args()
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    curves = {}
    for spec in a.run:
        label, _, path = spec.partition("=")
        curves[label] = points(Path(path), a.eval, a.data, a.scale)
    fig, ax = plt.subplots(1, 2, figsize=(11, 4.2))
    for label, pts in curves.items():
        if not pts:
            continue
        x_t = [q["train_s"] / 60 for q in pts]
        x_g = [q["gaussians"] for q in pts]
        y = [q["psnr"] for q in pts]
        line, = ax[0].plot(x_t, y, "o-", label=label)
        ax[1].plot(x_g, y, "o-", color=line.get_color(), label=label)
        for q, xt in zip(pts, x_t):
            ax[0].annotate(f"{q['step']}", (xt, q["psnr"]), fontsize=7, textcoords="offset points", xytext=(3, -9))
    ax[0].set_xlabel("training time (min, this machine)")
    ax[1].set_xlabel("Gaussians")
    ax[1].set_xscale("log")
    for x in ax:
        x.set_ylabel("held-out PSNR (dB)")
        x.grid(alpha=0.3)
        x.legend(fontsize=8)
    ax[0].set_title("PSNR against training time (labels: iteration)")
    ax[1].set_title("PSNR against Gaussian count")
    fig.tight_layout()
    out = Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    out.with_suffix(".json").write_text(json.dumps(curves, indent=1))
    for label, pts in curves.items():
        for q in pts:
            print(f"{label:24s} step {q['step']:5d}  {q['train_s'] / 60:6.1f} min  {q['gaussians']:7d} G  "
                  f"PSNR {q['psnr']:.2f}  SSIM {q['ssim']:.3f}")


if __name__ == "__main__":
    main()
