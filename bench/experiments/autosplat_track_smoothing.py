"""Issue 36 (tracker noise): how much of the tracker's frame-to-frame box error can a temporal
smoother of each track remove, before any training? A bound at the box level, the cheapest test of
"smooth the tracker's cuboids over time" (the lead the foreground-stage pose correction left).

For each moving track of generated streets with tracker-noise boxes (``--data``, validation seeds by
default) the box centres' x and y are smoothed over time, each frame by a polynomial of degree
``--degree`` fitted to the frames within ``--half-width`` seconds (a local polynomial, Savitzky-Golay
style, on the frames' timestamps; a window with too few frames keeps the box). What is printed is
the frame-to-frame centre error against the generator's exact boxes (each track's mean error
removed: a constant offset is a gauge an object set absorbs), before and after, averaged over
tracks. Beside it, what the same smoother does to a track it should leave alone: a car turning on a
15 m radius at 8 m/s while braking at 4 m/s^2 (no noise), sampled at 10 and 5 Hz: the largest shift
it makes there (its bias on real motion, which the generator's constant-velocity movers never show).

    .venv/bin/python bench/experiments/autosplat_track_smoothing.py --data synthetic:busy-noisy \
        synthetic:overtake-noisy --seed 0 1 2
"""
from __future__ import annotations

import argparse

import numpy as np


def local_poly(t: np.ndarray, x: np.ndarray, half_width: float, degree: int) -> np.ndarray:
    """``[n]`` each sample of ``x [n]`` (at times ``t [n]``) replaced by the value at its own time of a
    degree-``degree`` polynomial fitted to the samples within ``half_width`` seconds of it."""
    out = x.astype(np.float64).copy()
    for k in range(len(t)):
        m = np.abs(t - t[k]) <= half_width + 1e-9
        if m.sum() >= degree + 2:
            out[k] = np.polyfit(t[m] - t[k], x[m], degree)[-1]
    return out


def turning_bias(half_width: float, degree: int, dt: float) -> float:
    """Largest shift (m) the smoother makes on a noiseless turning, braking car sampled every ``dt`` s."""
    t = np.arange(0.0, 4.0, dt)
    th = 8.0 * t / 15.0
    x, y, s = 15 * np.sin(th), 15 * (1 - np.cos(th)), 8 * t - 2 * t ** 2
    xy = np.hypot(local_poly(t, x, half_width, degree) - x, local_poly(t, y, half_width, degree) - y)
    return float(max(xy.max(), np.abs(local_poly(t, s, half_width, degree) - s).max()))


def tracks(spec: str, seed: int) -> list[np.ndarray]:
    """Per moving track, ``[n, 5]`` rows (timestamp, noisy x, noisy y, exact x, exact y)."""
    from clsplat.models.autosplat.data import load_sequence
    seq = load_sequence(spec, None, None, 0.25, seed=seed)   # boxes do not depend on the resolution
    exact = seq.metadata["exact_boxes"]
    rows: dict[int, list] = {}
    for i, f in enumerate(seq.frames):
        for b in f.boxes:
            e = exact[i][b.track_id]
            rows.setdefault(b.track_id, []).append((f.timestamp, b.center[0], b.center[1], e.center[0], e.center[1]))
    return [np.asarray(v) for v in rows.values() if len(v) >= 4]


def frame_to_frame(a: np.ndarray, half_width: float | None, degree: int) -> float:
    """Mean frame-to-frame centre error (m) of one track's boxes, smoothed or not (``None``)."""
    t = a[:, 0]
    xy = a[:, 1:3] if half_width is None else \
        np.stack([local_poly(t, a[:, 1 + j], half_width, degree) for j in range(2)], 1)
    d = xy - a[:, 3:5]
    return float(np.linalg.norm(d - d.mean(0), axis=1).mean())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", nargs="+", default=["synthetic:busy-noisy", "synthetic:overtake-noisy"])
    ap.add_argument("--seed", nargs="+", type=int, default=[0, 1, 2])
    ap.add_argument("--degree", nargs="+", type=int, default=[1, 2])
    ap.add_argument("--half-width", nargs="+", type=float, default=[0.4, 0.6, 0.8, 1.0, 1.5, 100.0])
    args = ap.parse_args()
    data = {spec: [a for s in args.seed for a in tracks(spec, s)] for spec in args.data}
    print("frame-to-frame centre error (m), mean over tracks; bias on a turning, braking car (m)")
    print("smoother | " + " | ".join(f"{spec} ({len(v)} tracks)" for spec, v in data.items()) + " | bias 10 Hz | bias 5 Hz")
    print("none | " + " | ".join(f"{np.mean([frame_to_frame(a, None, 0) for a in v]):.3f}" for v in data.values())
          + " | 0 | 0")
    for deg in args.degree:
        for h in args.half_width:
            errs = [np.mean([frame_to_frame(a, h, deg) for a in v]) for v in data.values()]
            print(f"degree {deg}, +-{h:g} s | " + " | ".join(f"{e:.3f}" for e in errs)
                  + f" | {turning_bias(h, deg, 0.1):.3f} | {turning_bias(h, deg, 0.2):.3f}")


if __name__ == "__main__":
    main()
