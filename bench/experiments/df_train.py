"""DrivingForward training benchmark: train a preset on synthetic streets for a wall-clock budget.

Runs ``clsplat train drivingforward`` in chunks of ``--chunk`` steps, each chunk resuming from the
previous checkpoint (the bitwise resume path), until ``--minutes`` have passed; then evaluates the
last checkpoint on ``--eval-scenes`` held-out streets (``clsplat eval drivingforward``: novel-view
PSNR/SSIM at frame +1 beside the oracle-depth baseline, depth AbsRel, delta<1.25, scale ratio) and
draws the learning curves. The run directory then holds checkpoint.pt, log.jsonl, loss.png,
curves.png, eval/metrics.json and the contact sheets. Interrupted, it can be restarted with the
same command (it resumes).

    nice -n 10 .venv/bin/python bench/experiments/df_train.py --preset small --minutes 47 \\
        --out bench/out/df_small --figure bench/figures/df_small_curves.png
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path


def curves(log: Path, png: Path, title: str, window: int = 10) -> None:
    """Every loss term against the step (raw and a running mean of ``window`` steps)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from clsplat.bench.figure import save_figure

    recs = [json.loads(line) for line in log.read_text().splitlines() if line.strip()]
    keys = ["loss", "reproj", "spatial", "spatio_temporal", "smooth", "mse"]
    fig, axes = plt.subplots(2, 3, figsize=(13, 7))
    steps = np.array([r["step"] for r in recs])
    for ax, k in zip(axes.ravel(), keys):
        y = np.array([r.get(k, np.nan) for r in recs], dtype=float)
        ax.plot(steps, y, color="0.75", lw=0.8, label="per step")
        if len(y) >= window:
            ax.plot(steps[window - 1:], np.convolve(y, np.ones(window) / window, "valid"), color="C0",
                    label=f"mean of {window}")
        ax.set_title(k)
        ax.set_xlabel("step")
        ax.legend(fontsize=7)
    fig.suptitle(title)
    save_figure(fig, png, dpi=110)


def main(argv: list[str] | None = None) -> int:
    from clsplat.models.drivingforward.cli import evaluate, train

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--preset", default="small")
    p.add_argument("--minutes", type=float, default=47.0, help="training wall-clock budget")
    p.add_argument("--chunk", type=int, default=20, help="steps per resumed chunk (= checkpoint interval)")
    p.add_argument("--out", default="bench/out/df_small")
    p.add_argument("--eval-scenes", type=int, default=8)
    p.add_argument("--figure", default=None, help="copy of the learning curves (PNG)")
    p.add_argument("--data", default="synthetic")
    a = p.parse_args(argv)
    out = Path(a.out)
    t0 = time.time()
    ck = out / "checkpoint.pt"
    while time.time() - t0 < a.minutes * 60:
        done = 0
        if ck.exists():
            import torch
            done = int(torch.load(ck, map_location="cpu", weights_only=True)["step"])
        args = ["--data", a.data, "--preset", a.preset, "--steps", str(done + a.chunk), "--out", str(out),
                "--checkpoint-every", str(a.chunk), "--eval-scenes", "0", "--no-progress"]
        if done:
            args.append("--resume")
        rc = train(args)
        if rc:
            return rc
        print(f"[df_train] step {done + a.chunk} after {(time.time() - t0) / 60:.1f} min", flush=True)
    curves(out / "log.jsonl", out / "curves.png", f"DrivingForward {a.preset} on synthetic streets")
    if a.figure:
        curves(out / "log.jsonl", Path(a.figure), f"DrivingForward {a.preset} on synthetic streets")
    t1 = time.time()
    rc = evaluate(["--checkpoint", str(ck), "--data", a.data, "--num-scenes", str(a.eval_scenes),
                   "--out", str(out / "eval")])
    print(f"[df_train] evaluation took {time.time() - t1:.0f} s", flush=True)
    return rc


if __name__ == "__main__":
    raise SystemExit(main())
