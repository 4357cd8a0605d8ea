"""AutoSplat runs scored against the anti-aliased truth (issue 36, the rasteriser's dilation
``eps2d``; bench/notes/autosplat_moving_objects.md, "The 2D dilation and the outline band").

The generator renders one ray a pixel, so its edges are aliased, and a run is scored against
them. A change that lifts a run's held-out PSNR there may fit the aliasing itself (a sharper
renderer reproduces the staircase) rather than the scene. This script scores each run's held-out
renders against the same views generated with ``s x s`` rays a pixel (``--supersample``; the
regenerated one-ray frames are checked equal to the run's), pooled over the whole image, the
moving cars and pedestrians and the parked cars, each also split into the 1-pixel outline band
and the interior (the generator's instance masks, as ``autosplat_small_objects.py``). Runs of one
street and seed share one supersampled street.

    PYTHONPATH=<tree> .venv/bin/python bench/experiments/autosplat_aa_scored.py RUN [RUN ...] [--out DIR]

Prints one markdown row per run (PSNR in dB against the anti-aliased truth) and writes
``aa_scored.json`` into ``--out`` (default: print only).
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from autosplat_small_objects import _Acc, _kinds, _near, _supersampled  # noqa: E402

PARTS = ("image", "car", "car/band", "car/interior", "pedestrian", "pedestrian/band", "pedestrian/interior",
         "parked", "parked/band", "parked/interior")


def analyse(runs: list[Path], supersample: int, band: int) -> list[dict]:
    """``[{"run", "acc": {part: {psnr, pixels}}}]`` for ``runs`` (module docstring)."""
    from clsplat.models.autosplat.evaluate import trainer_from_checkpoint
    from clsplat.models.autosplat.init import moving_track_ids
    from clsplat.models.common.train import load_checkpoint

    cache: dict[tuple, dict[int, np.ndarray]] = {}
    out = []
    for run in runs:
        ck = load_checkpoint(run / "checkpoint.pt", "autosplat")
        tr = trainer_from_checkpoint(ck, run / "checkpoint.pt", run, None, out_dir=Path("/tmp"))
        d = tr.data
        m = json.loads((run / "metrics.json").read_text())
        key = (m.get("protocol", m).get("data", "synthetic"), tr.preset.seed, tuple(d.test_frames))
        if key not in cache:
            cache[key] = _supersampled(tr, run, d.test_frames, supersample)
        truths = cache[key]
        kinds = _kinds(d.seq, set(moving_track_ids(d.seq, tr.preset.dynamic_threshold)))
        acc = _Acc()
        for i in d.test_frames:
            with torch.no_grad():
                r = tr.render_frame(i).numpy().astype(np.float64)
            err = ((np.clip(r, 0, 1) - np.clip(truths[i], 0, 1)) ** 2).sum(-1)
            acc.add("image", err, np.ones(err.shape, bool))
            inst = np.stack([d.seq.frames[i].instances[c] for c in d.cameras])
            for t in np.unique(inst[inst > 0]):
                kind = kinds.get(int(t))
                if kind not in ("car", "pedestrian", "parked"):
                    continue
                mk = inst == t
                b = _near(mk, band)
                acc.add(kind, err, mk)
                acc.add(f"{kind}/band", err, b)
                acc.add(f"{kind}/interior", err, mk & ~b)
        out.append({"run": run.name, "acc": acc.table()})
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("runs", nargs="+", type=Path)
    p.add_argument("--band", type=int, default=1, help="outline band width in pixels (default 1)")
    p.add_argument("--supersample", type=int, default=4, help="rays per pixel side of the truth (default 4)")
    p.add_argument("--out", type=Path, default=None, help="write aa_scored.json here")
    a = p.parse_args()
    if a.supersample < 2:
        p.error("--supersample: expected at least 2 rays a pixel side")
    res = analyse(a.runs, a.supersample, a.band)
    print("| run | " + " | ".join(PARTS) + " |   (PSNR against the anti-aliased truth)")
    print("|---" * (len(PARTS) + 1) + "|")
    for o in res:
        cells = [o["acc"].get(k, {}).get("psnr") for k in PARTS]
        print(f"| {o['run']} | " + " | ".join("–" if c is None else f"{c:.2f}" for c in cells) + " |")
    if a.out is not None:
        a.out.mkdir(parents=True, exist_ok=True)
        (a.out / "aa_scored.json").write_text(json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
